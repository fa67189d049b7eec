"""The pipeline's per-run numerical step, compiled when the extension was built.

``_kernel.cpp`` (C++17, built by setup.py when pybind11 is there; no other dependency) does the
fixed-lag smoother, regressor, base rows and predicted torque of one processing run in one
call. The live node runs the pipeline every few milliseconds on a few samples, where
the Python path's cost is the number of Python and numpy calls, not the arithmetic; compiled,
the step takes a fraction of it. The Python path (signals.FixedLagSmoother,
RobotModel.regressor) stays the reference: both give the same results to rounding (tested),
and the pipeline falls back to it when the extension is missing.
"""
from __future__ import annotations

import numpy as np

from .regressor_batch import _joint_kind
from .robot import JOINT_EXTRAS, RobotModel

try:
    from . import _kernel
except ImportError:   # not built: the Python path
    _kernel = None

AVAILABLE = _kernel is not None


def make_step(robot: RobotModel, base_columns: np.ndarray, half_window: int, order: int,
              max_gap: float):
    """A compiled step for ``robot`` (``_kernel.Step``), or None when the extension is not
    built or the robot has joints other than revolute, continuous and prismatic ones.

    ``push(t (N,), x (N, c), theta (b,), measured_velocity)`` with x = [q | tau] (c = 2n) or
    [q | qd | tau] (3n) returns (t_c, q, qd, qdd, tau, rows [Yb | tau] (M, n, b + 1),
    predicted = Yb theta) for the M windows completed; ``reset()`` forgets the buffer;
    ``regress(q, qd, qdd)`` gives Y (N, n, p) as ``robot.regressor`` does."""
    if _kernel is None:
        return None
    m = robot.model
    data = m.createData()
    kinds = [_joint_kind(m, data, j) for j in range(1, m.njoints)]
    if any(k is None for k in kinds) or m.njoints - 1 != robot.dof:
        return None
    ids = range(1, m.njoints)
    return _kernel.Step(
        np.array([m.parents[j] - 1 for j in ids], dtype=np.int64),
        np.array([robot.joint_ids.index(j) for j in ids], dtype=np.int64),
        np.array([m.jointPlacements[j].homogeneous for j in ids]),
        np.array([0 if kind == 'R' else 1 for kind, _ in kinds], dtype=np.int64),
        np.array([axis for _, axis in kinds]), np.asarray(m.gravity.linear, dtype=float),
        np.array([JOINT_EXTRAS.index(e) for e in robot.extras], dtype=np.int64),
        robot.coulomb_velocity, np.asarray(base_columns, dtype=np.int64), int(half_window),
        int(order), float(max_gap))
