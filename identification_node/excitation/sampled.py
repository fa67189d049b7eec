"""Trajectories through sampled positions (cubic spline), and motion samples as CSV."""
from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.interpolate import CubicSpline

from identification_node.errors import IdentificationError
from identification_node.excitation.trajectory_base import Trajectory, as_times, finite
from identification_node.fileio import atomic_write_text

__all__ = ['SampledTrajectory', 'write_motion_csv']


class SampledTrajectory(Trajectory):
    """A trajectory from samples ``t`` (N,), strictly increasing, shifted to start at 0, and
    ``q`` (N, n); derivatives from a cubic spline (not-a-knot ends). Outside the sampled span
    it holds the end positions with zero velocity and acceleration."""

    def __init__(self, t: np.ndarray, q: np.ndarray, joint_names: Sequence[str] | None = None):
        t = finite('t', np.asarray(t, dtype=float))
        q = finite('q', np.asarray(q, dtype=float))
        if q.ndim == 1:
            q = q[:, None]
        if t.ndim != 1 or q.ndim != 2 or q.shape[0] != t.shape[0] or q.shape[1] < 1:
            raise IdentificationError(f'sampled trajectory: t {t.shape} and q {q.shape} must be '
                                      '(N,) and (N, n)')
        if t.shape[0] < 2:
            raise IdentificationError('sampled trajectory needs at least 2 samples')
        if np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0))
            raise IdentificationError(f'sample times must increase strictly (row {k + 1})')
        if joint_names is not None and len(joint_names) != q.shape[1]:
            raise IdentificationError(f'{len(joint_names)} joint names for {q.shape[1]} columns')
        self.t, self.q = t - t[0], q
        self.dof = q.shape[1]
        self.duration = float(self.t[-1])
        self.joint_names = None if joint_names is None else [str(j) for j in joint_names]
        self._spline = CubicSpline(self.t, q, axis=0)
        self._d1, self._d2 = self._spline.derivative(1), self._spline.derivative(2)

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = as_times(t)
        inside = ((t >= 0) & (t <= self.duration))[:, None]
        tc = np.clip(t, 0.0, self.duration)
        return (self._spline(tc), np.where(inside, self._d1(tc), 0.0),
                np.where(inside, self._d2(tc), 0.0))

    def to_csv(self, path: str | os.PathLike) -> Path:
        """Write columns t, then one per joint (header: t and the joint names, or q1..qn),
        atomically."""
        names = self.joint_names or [f'q{i + 1}' for i in range(self.dof)]
        buf = io.StringIO()
        np.savetxt(buf, np.column_stack([self.t, self.q]), delimiter=',', fmt='%.17g',
                   header=','.join(['t'] + names), comments='')
        return atomic_write_text(path, buf.getvalue())

    @classmethod
    def from_csv(cls, path: str | os.PathLike) -> SampledTrajectory:
        """Read a CSV written by to_csv (first column time in s, header row with names)."""
        try:
            with open(path) as f:
                header = f.readline().strip()
                data = np.loadtxt(f, delimiter=',', ndmin=2)
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise IdentificationError(f'cannot read trajectory CSV {path}: {exc}') from None
        names = [h.strip() for h in header.split(',')]
        if len(names) < 2 or names[0].lower() not in ('t', 'time'):
            raise IdentificationError(
                f'trajectory CSV {path}: header must be t,<joint>,... got {header!r}')
        if data.shape[1] != len(names):
            raise IdentificationError(f'trajectory CSV {path}: {data.shape[1]} columns, header '
                                      f'names {len(names)}')
        position = [k for k, h in enumerate(names) if h.endswith('.position')]
        if position:   # write_motion_csv's layout: the positions, derivatives from the spline
            return cls(data[:, 0], data[:, position],
                       [names[k][:-len('.position')] for k in position])
        return cls(data[:, 0], data[:, 1:], names[1:])


def write_motion_csv(path: str | os.PathLike, t: np.ndarray, q: np.ndarray, qd: np.ndarray,
                     qdd: np.ndarray, joint_names: Sequence[str]) -> Path:
    """Write samples as CSV, header ``t,<joint>.position,...,<joint>.velocity,...,
    <joint>.acceleration,...`` (s, rad, rad/s, rad/s^2; m for prismatic joints), atomically."""
    names = [str(j) for j in joint_names]
    header = ['t'] + [f'{j}.{kind}' for kind in ('position', 'velocity', 'acceleration')
                      for j in names]
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack([t, q, qd, qdd]), delimiter=',', fmt='%.17g',
               header=','.join(header), comments='')
    return atomic_write_text(path, buf.getvalue())
