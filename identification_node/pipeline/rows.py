"""Stage 5, rows: the fixed-lag smoother, pinocchio's regressor and the base rows.

Positions (and measured velocities) and the torque go through the same smoother
(signals.FixedLagSmoother: local cubic fit over 2L+1 samples), giving q, qd, qdd and tau at the
window centre, L samples behind the newest; then Y(q, qd, qdd) (RobotModel.regressor) and the
base rows [Yb | tau] (BaseParameters' columns). Everything per batch, no loop over samples but
pinocchio's.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.pipeline.samples import Samples
from identification_node.pipeline.signals import FixedLagSmoother


class Rows(NamedTuple):
    """Smoothed samples at the window centres t (M,) s: q, qd, qdd, tau (M, n), and the rows
    [Yb | tau] (M, n, b + 1) of the base regressor and the torque."""
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    rows: np.ndarray


class RowBuilder:
    """Smoother, regressor and base rows of ``robot`` for validated samples with torque."""

    def __init__(self, robot: RobotModel, base: BaseParameters, half_window: int, order: int,
                 max_gap: float):
        self.robot, self.base = robot, base
        self.half_window, self.order, self.max_gap = int(half_window), int(order), max_gap
        # columns of [Y | tau] that make the rows [Yb | tau]
        self._columns = np.append(base.base_index, robot.num_params)
        self._work: dict[str, np.ndarray] = {}
        self.reset_counts()
        self.reset()

    def reset(self) -> None:
        """Forget the smoother's window (a new stream): it is made on first use, when the
        channels (with or without measured velocity) are known. What it held and never output
        is counted in ``smoother_edge``."""
        self._count_edges(restart=True)
        self._smoother: FixedLagSmoother | None = None

    def reset_counts(self) -> None:
        self._in = self._out = 0    # samples into / out of the smoother
        # valid samples the smoother never outputs: half a window at the stream's start, at
        # either side of a stamp gap, and what a restart drops (not rejections: apart)
        self.smoother_edge = 0

    def _count_edges(self, restart: bool = False) -> None:
        """All that went in and did not come out, but the newest half window (the delay);
        on a restart all of it."""
        waiting = self._in - self._out
        lost = waiting if restart else max(waiting - self.half_window, 0)
        self.smoother_edge += lost
        self._out += lost

    def __call__(self, s: Samples, measured_velocity: bool, reuse_at: int | None = None
                 ) -> Rows:
        """The rows of the windows the samples ``s`` complete. ``reuse_at``: when at least
        this many come out, the rows live in a work array the next call reuses (the caller is
        done with them by then)."""
        n = self.robot.dof
        x = np.hstack([s.q, s.qd, s.tau] if measured_velocity else [s.q, s.tau])
        if self._smoother is None:
            self._smoother = FixedLagSmoother(x.shape[1], half_window=self.half_window,
                                              order=self.order, max_gap=self.max_gap)
        # stamps increasing and values finite: checked by the stages before
        t, x, xd, xdd = self._smoother.push_checked(s.stamps, x)
        self._in += len(s.stamps)
        self._out += len(t)
        self._count_edges()
        q = x[:, :n]
        qd, qdd = (x[:, n:2 * n], xd[:, n:2 * n]) if measured_velocity else (xd[:, :n],
                                                                             xdd[:, :n])
        tau = x[:, -n:]
        # [Y | tau] (N, n, p + 1): the regressor and the torque, for the base rows at once
        p, b = self.robot.num_params, self.base.num_base
        Yt = self._buffer('regressor', (len(t), n, p + 1))
        self.robot.regressor(q, qd, qdd, out=Yt[:, :, :p], checked=True)
        Yt[:, :, p] = tau
        shape = (len(t), n, b + 1)
        reuse = reuse_at is not None and len(t) >= reuse_at
        rows = self._buffer('rows', shape) if reuse else np.empty(shape)
        np.take(Yt, self._columns, axis=2, out=rows, mode='clip')
        return Rows(t, q, qd, qdd, tau, rows)

    def _buffer(self, name: str, shape: tuple) -> np.ndarray:
        """A work array of ``shape``, reused across batches (grown when needed): allocating
        megabytes afresh every batch costs more in page faults than the arithmetic on them."""
        size = math.prod(shape)
        buf = self._work.get(name)
        if buf is None or buf.size < size:
            self._work[name] = buf = np.empty(size)
        return buf[:size].reshape(shape)
