"""The robot model: URDF loading, pinocchio regressor, base parameters, motor torque, plausible
signal ranges, the paper tables, the simulated arm."""
