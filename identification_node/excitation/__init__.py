"""Excitation trajectories: Fourier design (``design``), its criteria and limits, framing and
collisions."""
