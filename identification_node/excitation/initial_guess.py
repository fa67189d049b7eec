"""Initial guesses of an excitation: the Fourier basis, coefficient vectors, the paper's
least-squares guess and Table I, scaled into the limits.

Coefficient vectors x hold per joint [a_1..a_H, b_1..b_H, q0] (rad/s, rad), joints in order.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from identification_node.config import Excitation
from identification_node.errors import IdentificationError
from identification_node.excitation.limits import (LIMIT_KINDS, VERIFY_POINTS, ExcitationLimits,
                                                   position_ranges, static_ratios, worst_ratio,
                                                   limit_ratios)
from identification_node.excitation.trajectories import TABLE1_PERIOD, FourierTrajectory

__all__ = ['DEFAULT_HARMONICS', 'DEFAULT_PERIOD', 'INITIAL_MARGIN', 'LSQ_POINTS', 'REST_TORQUE',
           'TABLE1_OFFSET', 'VERIFY_RATIO', 'centre_fault', 'check_harmonics', 'fourier_basis',
           'from_x', 'initial_trajectory', 'least_squares_guess', 'nearest_rest_pose',
           'rest_pose', 'scale_motion', 'scale_to_limits', 'shrink_into_limits',
           'table1_trajectory', 'to_x']

DEFAULT_HARMONICS = Excitation.harmonics
DEFAULT_PERIOD = Excitation.period
LSQ_POINTS = 100            # random target velocities of the initial guess (paper: 100)
INITIAL_MARGIN = 0.95        # the initial guess reaches this fraction of its tightest limit
VERIFY_RATIO = 0.999        # a verified result stays below this fraction of every limit
REST_TORQUE = 0.7           # the rest pose's static torque stays within this fraction of a limit
REST_STARTS = 8             # random starts (besides the centre) of the search for a rest pose
# Table I's joint zeros -> ours (crs_a465.urdf: arm straight up at zero), q_ours = q_paper +
# offset. Table I moves joint 2 over [36, 148] deg and joint 3 over [-163, -10] deg: centred on
# +90 and -90 deg, where our symmetric +-90 / +-110 deg ranges are centred on 0. With the
# quarter-turn shifts every joint stays inside our limits; the senses of rotation are kept (the
# paper does not state them).
TABLE1_OFFSET = (0.0, -math.pi / 2, math.pi / 2, 0.0, 0.0, 0.0)


def fourier_basis(t: np.ndarray, harmonics: int, period: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matrices (N, 2H + 1) mapping one joint's coefficients [a_1..a_H, b_1..b_H, q0] to its
    position, velocity and acceleration at times t (s), as in FourierTrajectory.sample."""
    t = np.asarray(t, dtype=float)
    wl = 2.0 * math.pi / period * np.arange(1, harmonics + 1)
    S, C = np.sin(np.outer(t, wl)), np.cos(np.outer(t, wl))
    one, zero = np.ones((t.size, 1)), np.zeros((t.size, 1))
    return (np.hstack([S / wl, -C / wl, one]), np.hstack([C, S, zero]),
            np.hstack([-S * wl, C * wl, zero]))


def to_x(traj: FourierTrajectory) -> np.ndarray:
    """The coefficient vector of ``traj``."""
    return np.hstack([traj.a, traj.b, traj.q0[:, None]]).ravel()


def from_x(x: np.ndarray, n: int, period: float, names: Sequence[str]) -> FourierTrajectory:
    """The FourierTrajectory of coefficient vector ``x`` (n joints, period s)."""
    X = np.asarray(x, dtype=float).reshape(n, -1)
    H = (X.shape[1] - 1) // 2
    return FourierTrajectory(X[:, :H], X[:, H:2 * H], X[:, 2 * H], period, names)


def least_squares_guess(limits: ExcitationLimits, harmonics: int = DEFAULT_HARMONICS,
                        period: float = DEFAULT_PERIOD, seed: int | None = 0,
                        num_points: int = LSQ_POINTS) -> FourierTrajectory:
    """The paper's initial guess (III.A, eq. 7-8), before scaling into the limits: per joint,
    random target velocities, uniform within the velocity limit, at ``num_points`` equally
    spaced instants of one period; the coefficients (a_l, b_l) solve A delta = qd by least
    squares, A the velocity form of the series [cos(w l t), sin(w l t)].

    The paper's printed A (entries s/(w l), c/(w l) and a column of ones) is the position
    form, which cannot reproduce velocities and leaves q0 undetermined; we fit the velocity
    form, as its text says, and put q0 at the centre of the position range (0 when unlimited).
    """
    H = check_harmonics(harmonics)
    M = max(int(num_points), 2 * H)
    rng = np.random.default_rng(seed)
    t = np.arange(M) * (period / M)
    _, Bv, _ = fourier_basis(t, H, period)
    A = Bv[:, :2 * H]
    vmax = limits.velocity_limits
    target = rng.uniform(-1.0, 1.0, size=(M, limits.dof)) * vmax
    coef = np.linalg.lstsq(A, target, rcond=None)[0].T  # (n, 2H)
    return FourierTrajectory(coef[:, :H], coef[:, H:], position_ranges(limits)[1], period,
                             limits.joint_names)


def scale_to_limits(traj: FourierTrajectory, limits: ExcitationLimits,
                    margin: float = INITIAL_MARGIN, num_points: int = VERIFY_POINTS,
                    rest: np.ndarray | None = None) -> FourierTrajectory:
    """Per joint, scale the amplitudes (up or down) so the motion reaches ``margin`` of its
    tightest kinematic limit (position range, velocity, acceleration), with q0 centring the
    excursion in the position range (unchanged for joints without position limits), or on
    ``rest`` (rest_pose) where given."""
    unit = FourierTrajectory(traj.a, traj.b, np.zeros(traj.dof), traj.period)
    q, qd, qdd = unit.sample(np.linspace(0.0, traj.period, num_points))
    limited, centre, half = position_ranges(limits)
    if rest is not None:   # the room on the nearer side of the rest pose
        lo, hi = limits.position_limits.T
        half = np.minimum(hi - rest, rest - lo)
    span = 0.5 * (q.max(axis=0) - q.min(axis=0))
    with np.errstate(divide='ignore'):
        scale = margin * np.min([half / span, limits.velocity_limits / np.abs(qd).max(axis=0),
                                 limits.acceleration_limits / np.abs(qdd).max(axis=0)], axis=0)
    if not np.isfinite(scale).all():
        bad = [j for j, s in zip(limits.joint_names, scale) if not np.isfinite(s)]
        raise IdentificationError(f'the trajectory does not move joints {bad}')
    mid = 0.5 * (q.max(axis=0) + q.min(axis=0))
    q0 = np.where(limited, centre - scale * mid, traj.q0) if rest is None else rest - scale * mid
    return FourierTrajectory(traj.a * scale[:, None], traj.b * scale[:, None], q0,
                             traj.period, traj.joint_names)


Closest = Callable[[np.ndarray], 'tuple[float, tuple[str, str] | None]']


def centre_fault(robot, limits: ExcitationLimits, phis: Sequence[np.ndarray] | None = None,
                 level: float = REST_TORQUE, closest: Closest | None = None) -> str | None:
    """Why an excitation cannot be centred on the centre of the position ranges, or None: the
    static torque there (under each of ``phis``) beyond ``level`` of an effort limit ('holds
    <joint> at <ratio> x its torque limit (with the margin)'), or the clearance ``closest(q)``
    gives (m beyond the minimum distance, and its pair or None) below 0 ('is in collision
    (<a> - <b>)')."""
    centre = position_ranges(limits)[1]
    at = static_ratios(robot, limits, centre, phis)
    j = int(np.argmax(at))
    if at[j] > level:
        return f'holds {robot.joint_names[j]} at {at[j]:.2f} x its torque limit (with the margin)'
    if closest is not None:
        clearance, pair = closest(centre)
        if clearance < 0:
            return 'is in collision' + (f' ({pair[0]} - {pair[1]})' if pair else '')
    return None


def rest_pose(robot, limits: ExcitationLimits, phis: Sequence[np.ndarray] | None = None,
              level: float = REST_TORQUE, seed: int = 0,
              clearance: Callable[[np.ndarray], float] | None = None,
              pad: float = 0.0) -> np.ndarray | None:
    """The pose (n,) an excitation is centred on and scaled towards, where the centre of the
    position ranges will not do (centre_fault; ``clearance(q)``: m beyond the minimum
    distance): None where it does, else nearest_rest_pose."""
    closest = None if clearance is None else (lambda q: (clearance(q), None))
    if centre_fault(robot, limits, phis, level, closest) is None:
        return None
    return nearest_rest_pose(robot, limits, phis, level, seed, clearance, pad)


def nearest_rest_pose(robot, limits: ExcitationLimits, phis: Sequence[np.ndarray] | None = None,
                      level: float = REST_TORQUE, seed: int = 0,
                      clearance: Callable[[np.ndarray], float] | None = None,
                      pad: float = 0.0) -> np.ndarray:
    """The pose nearest the centre of the position ranges (in half widths of the ranges, pi
    where unlimited) within their middle three quarters whose static torque (under each of
    ``phis``) stays within ``level`` of every effort limit, ``pad`` beyond ``clearance(q)``'s
    0 where given (an arm held out against gravity at the centre hangs, one in collision there
    unfolds), or failing that the pose of least static torque found (a clear one where any
    is)."""
    from scipy.optimize import minimize

    limited, centre, half = position_ranges(limits)

    def ratios(q: np.ndarray) -> np.ndarray:
        return static_ratios(robot, limits, q, phis)

    width = np.where(limited, 0.75 * half, math.pi)
    box = list(zip(centre - width, centre + width))
    starts = [centre, *np.random.default_rng(seed).uniform(centre - width, centre + width,
                                                           (REST_STARTS, robot.dof))]
    lows = [minimize(lambda q: float((ratios(q) ** 2).sum()), s, method='L-BFGS-B',
                     bounds=box).x for s in starts]
    free = lows if clearance is None else [q for q in lows if clearance(q) >= pad] or lows
    low = min(free, key=lambda q: ratios(q).max())
    constraints = [{'type': 'ineq', 'fun': lambda q: level - ratios(q)}]
    if clearance is not None:
        constraints.append({'type': 'ineq', 'fun': lambda q: clearance(q) - pad})
    near = minimize(lambda q: float((((q - centre) / width) ** 2).sum()), low, method='SLSQP',
                    bounds=box, constraints=constraints)
    rest = np.clip(near.x, centre - width, centre + width)
    ok = ratios(rest).max() <= level * (1.0 + 1e-6) and (
        clearance is None or clearance(rest) >= pad)
    return rest if ok else low


def shrink_into_limits(traj: FourierTrajectory, robot, limits: ExcitationLimits,
                       target: float = VERIFY_RATIO, max_steps: int = 60,
                       phis: Sequence[np.ndarray] | None = None,
                       rest: np.ndarray | None = None) -> tuple[FourierTrajectory, float, dict]:
    """Scale the motion down until every limit ratio (limit_ratios) is at most ``target``:
    amplitudes times s, and each offset q0 drawn towards the centre of its position range by
    the same factor (kept where unlimited), so every kinematic ratio scales by s exactly; or
    towards ``rest`` (rest_pose) where given. Returns (trajectory, s, ratios);
    IdentificationError when even that pose at rest exceeds the effort limits. ``phis``: the
    torque models (see limit_ratios)."""
    ratios = limit_ratios(traj, robot, limits, phis=phis)
    kinematic = max(ratios[k] for k in LIMIT_KINDS[:3])
    scale = min(1.0, target / kinematic) if kinematic > 0 else 1.0
    for _ in range(max_steps):
        cur = scale_motion(traj, limits, scale, rest)
        if scale != 1.0:
            ratios = limit_ratios(cur, robot, limits, phis=phis)
        if worst_ratio(ratios) <= target:
            return cur, scale, ratios
        scale *= float(np.clip(target / worst_ratio(ratios), 0.5, 0.995))
    effort = ratios['per_joint']['effort']
    over = ', '.join(f'{name} {r:.3g} x' for name, r in zip(limits.joint_names, effort)
                     if r > target)
    pose = ('the centre of the position ranges' if rest is None
            else 'the pose of least static torque found')
    raise IdentificationError('infeasible limits: the trajectory cannot be scaled into the '
                              f'effort limits (with their margin): the static torque near {pose} '
                              f'exceeds them ({over} the limit); '
                              '--no-effort leaves torque limits out, or narrow the position '
                              'limits (--limits) to where gravity asks less')


def scale_motion(traj: FourierTrajectory, limits: ExcitationLimits, scale: float,
                 rest: np.ndarray | None = None) -> FourierTrajectory:
    """The motion of ``traj`` scaled by ``scale``: amplitudes, and offsets towards the centre
    of the position ranges (kept where unlimited), or towards ``rest`` (rest_pose)."""
    centre = position_ranges(limits, traj.q0)[1] if rest is None else rest
    return FourierTrajectory(traj.a * scale, traj.b * scale, centre + scale * (traj.q0 - centre),
                             traj.period, traj.joint_names)


def table1_trajectory(robot, harmonics: int = DEFAULT_HARMONICS,
                      period: float = TABLE1_PERIOD) -> FourierTrajectory:
    """Table I of Radkhah, Kulic and Croft for a 6-joint robot, with its offsets moved into
    our joint zeros (TABLE1_OFFSET) for the bundled crs_a465; zero-padded beyond its 5
    harmonics."""
    if robot.dof != 6:
        raise IdentificationError(f'Table I is for the 6 joints of the CRS A460/A465; the robot '
                                  f'identifies {robot.dof} ({robot.joint_names})')
    H = check_harmonics(harmonics)
    t1 = FourierTrajectory.crs_table1(period)
    if H < t1.harmonics:
        raise IdentificationError(f'Table I has {t1.harmonics} harmonics; ask for at least '
                                  f'{t1.harmonics}')
    pad = np.zeros((6, H - t1.harmonics))
    offset = np.array(TABLE1_OFFSET) if robot.name == 'crs_a465' else np.zeros(6)
    return FourierTrajectory(np.hstack([t1.a, pad]), np.hstack([t1.b, pad]), t1.q0 + offset,
                             period, robot.joint_names)


def check_harmonics(harmonics: int) -> int:
    if isinstance(harmonics, bool) or not isinstance(harmonics, (int, np.integer)) \
            or harmonics < 1:
        raise IdentificationError(f'harmonics must be an integer >= 1, got {harmonics!r}')
    return int(harmonics)


def initial_trajectory(robot, initial: str | FourierTrajectory | None,
                       limits: ExcitationLimits, harmonics: int, period: float,
                       seed: int | None, phis: Sequence[np.ndarray] | None = None,
                       rest: np.ndarray | None = None) -> FourierTrajectory:
    """The starting point: 'lsq' (None; least_squares_guess scaled into the limits), 'table1'
    (table1_trajectory) or a FourierTrajectory, shrunk into every limit; centred on and
    shrunk towards ``rest`` (rest_pose) where given."""
    if initial is None or (isinstance(initial, str) and initial == 'lsq'):
        guess = scale_to_limits(least_squares_guess(limits, harmonics, period, seed), limits,
                                rest=rest)
    elif isinstance(initial, str) and initial == 'table1':
        guess = table1_trajectory(robot, harmonics, period)
    elif isinstance(initial, FourierTrajectory):
        guess = initial
        if (guess.dof, guess.harmonics, guess.period) != (robot.dof, harmonics, period):
            raise IdentificationError(
                f'initial trajectory has {guess.dof} joints, {guess.harmonics} harmonics, '
                f'period {guess.period} s; need {robot.dof}, {harmonics}, {period} s')
        guess = FourierTrajectory(guess.a, guess.b, guess.q0, period, robot.joint_names)
    else:
        raise IdentificationError(f"unknown initial trajectory {initial!r}: use 'lsq', "
                                  "'table1' or a FourierTrajectory")
    return shrink_into_limits(guess, robot, limits, phis=phis, rest=rest)[0]
