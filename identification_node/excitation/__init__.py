"""Excitation trajectories: Fourier design, framing, limits and collisions."""
