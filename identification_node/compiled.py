"""The pipeline's per-run numerical step, compiled when the extension was built.

``_kernel.cpp`` (C++17, built by setup.py when pybind11 is there; no other dependency) does the
fixed-lag smoother, regressor, base rows and predicted torque of one processing run in one
call, and with measured torque also the decoding and validation of the run's JointState
messages before them (``push_cdr``). The live node runs the pipeline every few milliseconds
on a few samples, woken from sleep with cold caches, where the Python path's cost is the
amount of Python and numpy code it goes through, not the arithmetic; compiled, the run takes
a fraction of it (bench/bench_pipeline_runs.py). The Python path (bagio.JointStateDecoder,
the pipeline's validation, signals.FixedLagSmoother, RobotModel.regressor) stays the
reference: both give the same results to rounding (tested), and the pipeline falls back to
it when the extension is missing. bagio.encode_joint_states uses the extension's
``fill_joint_states`` the same way, and estimators.RecursiveLeastSquares its
``factor_information`` (the Cholesky update of the information and its solution).
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
    ``regress(q, qd, qdd)`` gives Y (N, n, p) as ``robot.regressor`` does.
    ``set_layout(names, columns)`` registers the message columns (n,) of the robot's joints in
    JointState messages with ``names``; ``push_cdr(messages, epoch_ns, last_stamp, theta,
    measured_velocity)`` pushes the samples of a list of JointState CDR messages (stamps in s
    since epoch_ns, torque = effort) and returns push's tuple and the newest stamp, or None,
    changing nothing, unless every message is clean: little-endian CDR of a registered layout,
    lengths right, values finite, stamps increasing after ``last_stamp``."""
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
