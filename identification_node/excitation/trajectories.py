"""Fourier and framed excitation trajectories; matching and loading trajectories by name or file.

The trajectory interface (``sample(t) -> (q, qd, qdd)``) is in ``excitation.trajectory_base``;
quintic moves in ``excitation.quintic_moves``, sampled trajectories in ``excitation.sampled``.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.excitation.quintic_moves import QuinticMoves
from identification_node.excitation.sampled import SampledTrajectory
from identification_node.excitation.trajectory_base import (DEFAULT_HALF_RANGE, DEFAULT_VELOCITY,
                                                            JointLimits, Joints, RobotJoints,
                                                            Trajectory, as_times, centre_half,
                                                            check_keys, finite, limits_of,
                                                            quintic_shape)
from identification_node.safe_yaml import read_yaml

__all__ = ['TABLE1_PERIOD', 'FourierTrajectory', 'FramedTrajectory', 'load_trajectory',
           'match_joints']

# Table I of Radkhah, Kulic and Croft: rows are harmonics l = 1..5, columns joints 1..6.
_TABLE1_A = [[0.156, 0.064, 0.634, -0.197, 0.499, 0.435],
             [-0.478, -0.335, -0.421, -0.282, -0.135, 0.111],
             [0.078, 0.451, 0.216, 0.173, -0.112, -0.245],
             [-0.388, 0.292, -0.310, 0.154, -0.263, -0.162],
             [-0.070, 1.046, -0.357, -0.095, -0.086, -0.442]]
_TABLE1_B = [[0.088, -0.125, -0.359, 0.408, 0.552, -0.017],
             [0.253, 0.292, 0.112, -0.714, 0.085, -0.178],
             [-0.207, -0.369, -0.128, 0.267, -0.184, 0.340],
             [0.549, 0.557, -0.069, 0.291, -0.065, -0.552],
             [0.150, 0.964, 0.183, 0.751, 0.116, -0.089]]
_TABLE1_Q0 = [0.0, 1.813, -1.184, 0.087, -0.415, 0.124]
# The paper does not state the fundamental frequency. With a 10 s period (0.1 Hz) q(0) equals the
# paper's start points (section IV.C) for joints 2-6 within 0.1 deg (joint 3 up to the sign the
# OCR dropped); peak speeds are then 1.05-2.08 rad/s, inside the A465's limits (velocity does not
# depend on the period; position range grows and acceleration shrinks with it).
TABLE1_PERIOD = 10.0


class FourierTrajectory(Trajectory):
    """Finite Fourier series of Radkhah, Kulic and Croft (section II.C), per joint i:
    q_i(t) = sum_l a_il/(w l) sin(w l t) - b_il/(w l) cos(w l t) + q0_i, w = 2 pi / period.

    ``a``, ``b``: (n, H) velocity amplitudes (rad/s), ``q0``: (n,) offsets (rad), period in s.
    """

    period: float

    def __init__(self, a: np.ndarray, b: np.ndarray, q0: np.ndarray, period: float,
                 joint_names: Sequence[str] | None = None):
        a, b, q0 = finite('a', np.atleast_2d(a)), finite('b', np.atleast_2d(b)), \
            finite('q0', np.atleast_1d(q0))
        if a.ndim != 2 or a.shape != b.shape or q0.shape != (a.shape[0],):
            raise IdentificationError(
                f'Fourier coefficients: a {a.shape} and b {b.shape} must both be (n, H) and '
                f'q0 {q0.shape} must be (n,)')
        if a.shape[1] < 1:
            raise IdentificationError('Fourier trajectory needs at least one harmonic')
        try:
            period = float(period)
        except (TypeError, ValueError):
            raise IdentificationError(f'Fourier period must be a number, got {period!r}') \
                from None
        if not (math.isfinite(period) and period > 0):
            raise IdentificationError(f'Fourier period must be finite and > 0, got {period}')
        if joint_names is not None and len(joint_names) != a.shape[0]:
            raise IdentificationError(
                f'{len(joint_names)} joint names for {a.shape[0]} joints of Fourier coefficients')
        self.a, self.b, self.q0, self.period = a, b, q0, period
        self.dof = a.shape[0]
        self.harmonics = a.shape[1]
        self.duration = math.inf
        self.joint_names = None if joint_names is None else [str(j) for j in joint_names]

    @property
    def omega(self) -> float:
        """Fundamental pulsation w = 2 pi / period (rad/s)."""
        return 2.0 * math.pi / self.period

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = as_times(t)
        wl = self.omega * np.arange(1, self.harmonics + 1)
        s, c = np.sin(np.outer(t, wl)), np.cos(np.outer(t, wl))
        q = s @ (self.a / wl).T - c @ (self.b / wl).T + self.q0
        qd = c @ self.a.T + s @ self.b.T
        qdd = -s @ (self.a * wl).T + c @ (self.b * wl).T
        return q, qd, qdd

    def to_dict(self) -> dict:
        """Plain data for YAML: period, q0, a, b (lists of floats) and joints when known."""
        d = {'type': 'fourier', 'period': self.period, 'q0': self.q0.tolist(),
             'a': self.a.tolist(), 'b': self.b.tolist()}
        if self.joint_names is not None:
            d['joints'] = list(self.joint_names)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> FourierTrajectory:
        """Inverse of to_dict; keys period, q0, a, b, optional joints (and type: fourier)."""
        check_keys(d, ('period', 'q0', 'a', 'b'), 'Fourier trajectory')
        if d.get('type', 'fourier') != 'fourier':
            raise IdentificationError(f"trajectory type {d['type']!r} is not 'fourier'")
        try:
            a, b, q0 = (np.array(d[k], dtype=float) for k in ('a', 'b', 'q0'))
        except (TypeError, ValueError) as exc:
            raise IdentificationError(f'Fourier trajectory: non-numeric coefficients ({exc})') \
                from None
        return cls(a, b, q0, d['period'], d.get('joints'))

    @classmethod
    def crs_table1(cls, period: float = TABLE1_PERIOD,
                   joint_names: Sequence[str] | None = None) -> FourierTrajectory:
        """Table I of Radkhah, Kulic and Croft (CRS A460/A465, 6 joints, 5 harmonics)."""
        return cls(np.array(_TABLE1_A).T, np.array(_TABLE1_B).T, np.array(_TABLE1_Q0),
                   period, joint_names)

    @classmethod
    def random(cls, limits: JointLimits | Mapping, harmonics: int = 5, period: float = 10.0,
               seed: int = 0, margin: float = 0.8) -> FourierTrajectory:
        """A seeded random excitation inside ``margin`` times the position and velocity limits
        of a RobotModel or limits mapping (see check_limits), centred in the position range.
        Amplitudes fall as 1/l with the harmonic l."""
        pos, vel, _, names = limits_of(limits)
        n = pos.shape[0]
        if harmonics < 1 or not 0 < margin <= 1:
            raise IdentificationError('need harmonics >= 1 and 0 < margin <= 1')
        rng = np.random.default_rng(seed)
        decay = 1.0 / np.arange(1, harmonics + 1)
        a = rng.standard_normal((n, harmonics)) * decay
        b = rng.standard_normal((n, harmonics)) * decay
        centre, half = centre_half(pos)
        half = np.where(np.isfinite(half), half, DEFAULT_HALF_RANGE)
        vmax = np.where(np.isfinite(vel) & (vel > 0), vel, DEFAULT_VELOCITY)
        unit = cls(a, b, np.zeros(n), period)
        q, qd, _ = unit.sample(np.linspace(0.0, period, 4001))
        # q0 centres the excursion in the range, so the half span is what must fit.
        span = 0.5 * (q.max(axis=0) - q.min(axis=0))
        scale = margin * np.minimum(half / span, vmax / np.abs(qd).max(axis=0))
        q0 = centre - scale * 0.5 * (q.max(axis=0) + q.min(axis=0))
        return cls(a * scale[:, None], b * scale[:, None], q0, period, names)


class FramedTrajectory(Trajectory):
    """A periodic trajectory run for ``periods`` whole periods between smooth ramps from and
    back to the configuration ``start`` at rest.

    With p the periodic trajectory, u(t) = p(t - ramp_in) - start and w the quintic
    smoothstep (0 -> 1 with zero first and second derivatives at both ends):

    - ramp in, 0 <= t < ramp_in: q = start + w(t / ramp_in) u(t);
    - periodic part, ramp_in <= t <= ramp_in + periods * period: q = p(t - ramp_in), from the
      periodic trajectory's phase 0;
    - ramp out, over ramp_out s: q = start + (1 - w(s)) u(t), s the fraction of the ramp.

    q, qd and qdd are continuous; the motion starts and ends at ``start`` with zero velocity
    and acceleration, and a ramp's positions lie between ``start`` and p(t) (inside any
    position range holding both). Before 0 and after the end it holds ``start``.
    """

    def __init__(self, periodic: Trajectory, start: np.ndarray | None = None,
                 ramp_in: float = 1.0, ramp_out: float | None = None, periods: int = 1):
        if periodic.period is None:
            raise IdentificationError('framing needs a periodic trajectory')
        if isinstance(periods, bool) or not isinstance(periods, (int, np.integer)) \
                or periods < 1:
            raise IdentificationError(f'periods must be an integer >= 1, got {periods!r}')
        ramp_out = ramp_in if ramp_out is None else ramp_out
        for name, v in (('ramp_in', ramp_in), ('ramp_out', ramp_out)):
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating)) \
                    or not (math.isfinite(v) and v > 0):
                raise IdentificationError(f'{name} must be a duration > 0 s, got {v!r}')
        if start is None:
            start = getattr(periodic, 'q0', None)
            if start is None:
                raise IdentificationError('give the start configuration of the framing')
        start = finite('start', np.atleast_1d(np.asarray(start, dtype=float)))
        if start.shape != (periodic.dof,):
            raise IdentificationError(f'start configuration has {start.size} values for '
                                      f'{periodic.dof} joints')
        self.periodic, self.start = periodic, start
        self.ramp_in, self.ramp_out = float(ramp_in), float(ramp_out)
        self.periods = int(periods)
        self.dof = periodic.dof
        self.joint_names = periodic.joint_names
        self.harmonics = getattr(periodic, 'harmonics', None)
        self.period = None
        self.duration = self.ramp_in + self.periods * float(periodic.period) + self.ramp_out

    @property
    def periodic_window(self) -> tuple[float, float]:
        """(start, end) of the periodic part, s from the start of the trajectory."""
        assert self.periodic.period is not None   # checked by __init__
        return self.ramp_in, self.ramp_in + self.periods * float(self.periodic.period)

    def parts(self) -> dict:
        """Durations (s) of the ramp in, the periodic part and the ramp out, and the total."""
        t0, t1 = self.periodic_window
        return {'ramp_in': self.ramp_in, 'periodic': t1 - t0, 'ramp_out': self.ramp_out,
                'total': self.duration}

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = as_times(t)
        t0, t1 = self.periodic_window
        tc = np.clip(t, 0.0, self.duration)
        p, pd, pdd = self.periodic.sample(tc - t0)
        s_in = np.clip(tc / self.ramp_in, 0.0, 1.0)
        s_out = np.clip((tc - t1) / self.ramp_out, 0.0, 1.0)
        h_in, hd_in, hdd_in = quintic_shape(s_in)
        h_out, hd_out, hdd_out = quintic_shape(s_out)
        after = tc > t1
        w = np.where(after, 1.0 - h_out, h_in)[:, None]
        wd = np.where(after, -hd_out / self.ramp_out, hd_in / self.ramp_in)[:, None]
        wdd = np.where(after, -hdd_out / self.ramp_out ** 2,
                       hdd_in / self.ramp_in ** 2)[:, None]
        u = p - self.start
        return (self.start + w * u, w * pd + wd * u, w * pdd + 2.0 * wd * pd + wdd * u)

    def to_dict(self) -> dict:
        """The periodic trajectory's to_dict plus 'framing': start, ramp_in, ramp_out,
        periods (and the parts' durations)."""
        if not hasattr(self.periodic, 'to_dict'):
            raise IdentificationError('the periodic trajectory cannot be written as YAML')
        return {**self.periodic.to_dict(),
                'framing': {'start': self.start.tolist(), 'ramp_in': self.ramp_in,
                            'ramp_out': self.ramp_out, 'periods': self.periods,
                            'durations': self.parts()}}

    @classmethod
    def from_dict(cls, d: Mapping) -> FramedTrajectory:
        """Inverse of to_dict (a Fourier trajectory with a 'framing' mapping)."""
        f: Any = d.get('framing') if isinstance(d, Mapping) else None   # YAML data
        check_keys(f, ('start', 'ramp_in', 'ramp_out', 'periods'), 'framing')
        periodic = FourierTrajectory.from_dict(d)
        try:
            start = np.array(f['start'], dtype=float)
        except (TypeError, ValueError):
            raise IdentificationError(f"framing start must be numbers, got {f['start']!r}") \
                from None
        return cls(periodic, start, f['ramp_in'], f['ramp_out'], f['periods'])


def match_joints(traj: Trajectory, robot: Joints, source: str = 'trajectory') -> Trajectory:
    """``traj`` with its columns in the robot's joint order (by joint names when it has them);
    IdentificationError when the joints do not match."""
    joints = list(robot.joint_names)
    names = traj.joint_names
    if names is None:
        if traj.dof != len(joints):
            raise IdentificationError(f'{source} has {traj.dof} joints, robot has '
                                      f'{len(joints)} ({joints})')
        return traj
    if sorted(names) != sorted(joints):
        raise IdentificationError(f'{source} names joints {names}; the robot '
                                  f'identifies {joints}')
    order = [names.index(j) for j in joints]
    if isinstance(traj, FourierTrajectory):
        return FourierTrajectory(traj.a[order], traj.b[order], traj.q0[order], traj.period,
                                 joints)
    if isinstance(traj, SampledTrajectory):
        return SampledTrajectory(traj.t, traj.q[:, order], joints)
    if isinstance(traj, FramedTrajectory):
        return FramedTrajectory(match_joints(traj.periodic, robot, source), traj.start[order],
                                traj.ramp_in, traj.ramp_out, traj.periods)
    return traj


def load_trajectory(spec: str, robot: RobotJoints, seed: int = 0) -> Trajectory:
    """A trajectory for ``robot`` (a RobotModel) from a name or a file.

    'paper_moves': the MIT arm's quintic moves (3 joints); 'table1': the CRS A460/A465 Table I
    Fourier series (6 joints); 'fourier': a 5-harmonic Fourier series of random coefficients
    (``seed``) inside 80 % of the robot's position and velocity limits; a .yaml/.yml file of
    Fourier coefficients (keys period, q0, a, b, optional joints; with a 'framing' mapping, the
    FramedTrajectory that ramps in and out of it, as ``excite`` writes) or a .csv file (t, one
    column per joint, header with names; or write_motion_csv's layout, whose positions are
    used).
    """
    spec = str(spec).strip()
    n = robot.dof
    if spec in ('paper_moves', 'table1'):
        need = 3 if spec == 'paper_moves' else 6
        if n != need:
            raise IdentificationError(f"trajectory '{spec}' is for {need} joints; the robot "
                                      f'identifies {n} ({robot.joint_names})')
        if spec == 'paper_moves':
            return QuinticMoves.mit_paper(joint_names=robot.joint_names)
        return FourierTrajectory.crs_table1(joint_names=robot.joint_names)
    if spec == 'fourier':
        return FourierTrajectory.random(robot, seed=seed)
    path = Path(spec)
    suffix = path.suffix.lower()
    if suffix not in ('.yaml', '.yml', '.csv'):
        raise IdentificationError(
            f"unknown trajectory {spec!r}: use 'paper_moves', 'table1', 'fourier', or a "
            '.yaml/.yml (Fourier coefficients) or .csv (samples) file')
    if not path.is_file():
        raise IdentificationError(f'trajectory file {spec} does not exist')
    if suffix == '.csv':
        return match_joints(SampledTrajectory.from_csv(path), robot, f'trajectory {spec}')
    data = read_yaml(path, f'trajectory YAML {spec}')
    if isinstance(data, Mapping) and 'framing' in data:
        return match_joints(FramedTrajectory.from_dict(data), robot, f'trajectory {spec}')
    return match_joints(FourierTrajectory.from_dict(data), robot, f'trajectory {spec}')
