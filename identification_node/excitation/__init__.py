"""Excitation trajectories and their design.

Trajectories: ``trajectory_base`` (the interface, limit ratios), ``trajectories`` (Fourier and
framed trajectories, loading by name or file), ``quintic_moves``, ``sampled``. Design:
``criteria``, ``limits``, ``collision``, ``initial_guess``, ``problem`` (criterion and
constraints), ``design`` (the SLSQP run), ``framing`` (ramps, dense collision check),
``result``, ``export`` (samples, JointTrajectory, plot) and ``run`` (the ``excite`` use case)."""
