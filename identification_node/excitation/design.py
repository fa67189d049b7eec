"""Excitation trajectories: finite Fourier series optimised for parameter identification.

Radkhah, Kulic and Croft, sections II.C-D and III.A-B. Each joint follows the Fourier series of
:class:`~identification_node.excitation.trajectories.FourierTrajectory` (velocity
amplitudes a, b in rad/s, offset q0 in rad, common period); the design picks the 2H + 1
coefficients per joint that minimise a criterion of the base regressor stacked over N samples of
one period, subject to the joint limits.

The criteria (``cond``, ``dopt``) are in ``excitation.criteria``, the limits and the limit
ratios in ``excitation.limits``. Each (joint, kind) of limit is one smooth constraint on the
Kreisselmeier-Steinhauser maximum of its ratios to the limit (see DesignProblem); with a
collision.CollisionChecker, one more per checked geometry pair on its distances. Every result is
verified on a fine grid after the optimisation (torques on EFFORT_POINTS samples) and, where
needed, its motion is scaled down towards the centre of the position ranges until every ratio
is below VERIFY_RATIO (towards a pose of lower static torque, clear, where the centre holds
the arm out against gravity or collides: initial_guess.centre_fault, nearest_rest_pose); then
framed by ramps from and back to rest (frame_excitation, trajectories.FramedTrajectory) and its
collisions verified densely (framed_clearance).

Initial guess: the paper's least squares on random target velocities (III.A,
least_squares_guess), or Table I (table1_trajectory, offsets moved to our joint zeros).

Here: the SLSQP run and the choice of the verified result (optimize_excitation). The initial
guesses are in ``excitation.initial_guess``, the problem's criterion and constraints in
``excitation.problem`` (DesignProblem), the ramps and the dense collision check in
``excitation.framing``, the result in ``excitation.result`` and its outputs (samples,
JointTrajectory, plot) in ``excitation.export``.
"""
from __future__ import annotations

import math
import time
from types import SimpleNamespace
from typing import Callable, Mapping, Sequence

import numpy as np

from identification_node.config import Excitation
from identification_node.errors import IdentificationError
from identification_node.excitation.criteria import (DEFAULT_SAMPLES, base_of, check_criterion,
                                                     report_value)
from identification_node.excitation.framing import (DEFAULT_PERIODS, check_start,
                                                    frame_excitation, framed_clearance)
from identification_node.excitation.initial_guess import (DEFAULT_HARMONICS, DEFAULT_PERIOD,
                                                          centre_fault, check_harmonics, from_x,
                                                          initial_trajectory, nearest_rest_pose,
                                                          scale_motion, shrink_into_limits, to_x)
from identification_node.excitation.limits import ExcitationLimits, as_limits, limit_ratios
from identification_node.excitation.problem import COLLISION_PAD, DesignProblem
from identification_node.excitation.result import DEFAULT_LIMIT_MARGIN, ExcitationResult
from identification_node.excitation.trajectories import FourierTrajectory

__all__ = ['BLENDS', 'CANDIDATES', 'DEFAULT_MAXITER', 'MARGIN', 'NEAR_FEASIBLE',
           'PROGRESS_INTERVAL', 'optimize_excitation']

DEFAULT_MAXITER = Excitation.maxiter   # SLSQP iterations
MARGIN = 1.0                # the optimiser's constraints: smooth max of the ratios <= MARGIN
CANDIDATES = 8              # iterates (best first) verified as final candidates, at most
NEAR_FEASIBLE = 0.1         # KS constraint violation of the iterates still tried as candidates
BLENDS = (0.9, 0.75, 0.5, 0.3, 0.15)  # fractions of the way from the initial guess tried last
PROGRESS_INTERVAL = 10.0    # s between progress lines, at most
TOUCH_SCREEN = 20           # configurations screened for pairs that touch by design, first


class _TimeUp(Exception):
    """The optimisation's time limit passed (raised from inside SLSQP's callbacks)."""


class _Progress:
    """Progress lines (iteration, criterion, worst constraint, elapsed) to ``report`` at most
    ``interval`` s apart, checked at every evaluation; and the optimiser's time limit (s after
    ``start``, None: none), which raises _TimeUp from the next evaluation."""

    def __init__(self, report: Callable[[str], None] | None, time_limit: float | None,
                 start: float, criterion: str):
        self.report, self.start, self.interval = report, start, PROGRESS_INTERVAL
        self.deadline = None if time_limit is None else start + time_limit
        self.criterion = criterion
        self.iteration, self.value, self.worst = 0, math.nan, math.nan
        self.best = math.inf     # criterion of the best iterate meeting the constraints
        self.last = start
        self.optimising = False
        self.verifying = False

    def iterate(self, value: float, worst: float) -> None:
        self.iteration += 1
        self.value, self.worst = value, worst
        if worst >= 0:
            self.best = min(self.best, value)
        self.tick()

    def tick(self) -> None:
        now = time.perf_counter()
        if self.optimising and self.deadline is not None and now >= self.deadline:
            self.optimising = False
            raise _TimeUp
        if self.report is not None and now - self.last >= self.interval:
            self.say(now)

    def say(self, now: float | None = None, what: str = '') -> None:
        now = time.perf_counter() if now is None else now
        self.last = now
        if self.report is None:
            return
        best = f', best feasible {self.best:.6g}' if math.isfinite(self.best) else ''
        if what:
            self.report(what)
        elif self.verifying:
            self.report(f'verifying: {now - self.start:.0f} s')
        elif not self.iteration:
            self.report(f'{"optimising" if self.optimising else "preparing"}: no iteration '
                        f'finished yet, {now - self.start:.0f} s')
        else:
            self.report(f'iteration {self.iteration}: criterion {self.criterion} '
                        f'{self.value:.6g}{best}, worst constraint {self.worst:+.3g} '
                        f'(< 0: violated), {now - self.start:.0f} s')


def _srdf_fix(checker) -> str:
    return ('disable them in the SRDF' if checker.srdf is not None else
            "the robot's SRDF (--srdf) leaves such pairs out")


def _touching_by_design(checker, limits, screen: int | None = None) -> str:
    """'' or what says which of the robot's own pairs are within the minimum distance in every
    configuration sampled within ``limits`` (CollisionChecker.always_close: in contact by
    design, so no motion meets them). ``screen``: that many samples first, the full check
    only for a pair close in all of them."""
    lo, hi = np.asarray(limits.position_limits, dtype=float).T
    lo, hi = np.where(np.isfinite(lo), lo, -math.pi), np.where(np.isfinite(hi), hi, math.pi)
    if screen is not None and not checker.always_close(lo, hi, samples=screen):
        return ''
    stuck = [p for p in checker.always_close(lo, hi) if checker.self_pair(p)]
    if not stuck:
        return ''
    return (', '.join(f'{a} - {b}' for a, b in stuck[:3])
            + (f' and {len(stuck) - 3} more' if len(stuck) > 3 else '')
            + ' are within the minimum distance in every configuration sampled '
            f'(they touch by design: {_srdf_fix(checker)})')


def optimize_excitation(robot, harmonics: int = DEFAULT_HARMONICS,
                        period: float = DEFAULT_PERIOD, criterion: str = 'cond',
                        limits: ExcitationLimits | Mapping | str | None = None,
                        seed: int | None = 0, maxiter: int = DEFAULT_MAXITER,
                        num_samples: int = DEFAULT_SAMPLES,
                        initial: str | FourierTrajectory | None = None, base=None,
                        noise_std: Sequence[float] | None = None,
                        margin: float = DEFAULT_LIMIT_MARGIN,
                        start: Sequence[float] | None = None, periods: int = DEFAULT_PERIODS,
                        phis: Sequence[np.ndarray] | None = None,
                        checker=None, progress: Callable[[str], None] | None = None,
                        time_limit: float | None = None) -> ExcitationResult:
    """Optimise a Fourier excitation of ``robot`` (a RobotModel) with SLSQP (the paper used
    Matlab's fmincon, also SQP), and frame it with ramps from and back to rest.

    Minimises ``criterion`` ('cond' or 'dopt', see the module docstring; ``noise_std`` (n,)
    N m weights the rows of each joint) on ``num_samples`` samples of one period (s), from
    ``initial`` (see initial_trajectory), under ``limits`` (ExcitationLimits, a mapping of
    per-joint overrides or a YAML path; default the robot's) with ``margin`` of each kept free
    (ExcitationLimits.with_margin), torques under every parameter vector of ``phis`` (default
    the robot's own; e.g. the model's and an estimate's), and with a CollisionChecker
    ``checker`` at least its min_distance between the checked pairs, as smooth constraints
    (see DesignProblem). Feasible iterates are verified on fine grids and scaled into the limits
    (shrink_into_limits), framed by ramps from ``start`` (default: the offset q0) into
    ``periods`` periods and back (frame_excitation), and the framed trajectory's collisions
    checked densely (framed_clearance); the best verified one is kept. Stopping at the
    iteration limit (``maxiter``) or the time limit (``time_limit`` s of optimisation; the
    verification follows) is said in ``message``; stopping on infeasibility is a warning
    (``warnings``); IdentificationError when no feasible point was found. ``base``:
    BaseParameters of the robot (default: computed). ``progress`` receives a line at least
    every PROGRESS_INTERVAL s: iteration, criterion, worst constraint, elapsed time.
    """
    from scipy.optimize import minimize

    start_time = time.perf_counter()
    check_criterion(criterion)
    H = check_harmonics(harmonics)
    try:
        period = float(period)
    except (TypeError, ValueError):
        raise IdentificationError(f'period must be a number, got {period!r}') from None
    if not (math.isfinite(period) and period > 0):
        raise IdentificationError(f'period must be finite and > 0, got {period}')
    for name, v, low in (('maxiter', maxiter, 0), ('num_samples', num_samples, 2),
                         ('periods', periods, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
            raise IdentificationError(f'{name} must be an integer >= {low}, got {v!r}')
    if time_limit is not None and not (isinstance(time_limit, (int, float)) and time_limit > 0
                                       and not isinstance(time_limit, bool)):
        raise IdentificationError(f'time limit must be a number of seconds > 0, got '
                                  f'{time_limit!r}')
    limits = as_limits(robot, limits)
    work = limits.with_margin(margin)
    start_q = None if start is None else check_start(start, work)
    checker = checker if checker is not None and checker.num_pairs else None
    if checker is not None:   # no motion meets a pair that always touches: say so at once
        stuck = _touching_by_design(checker, work, TOUCH_SCREEN)
        if stuck:
            raise IdentificationError(f'no feasible excitation: {stuck}')
    if checker is not None and start_q is not None:
        c = checker.clearance(start_q[None])
        if c['distance'] < checker.min_distance:
            raise IdentificationError(f'the start configuration is in collision: {c["pair"][0]}'
                                      f' - {c["pair"][1]} at {c["distance"]:.4g} m (minimum '
                                      f'{checker.min_distance:g} m)')
    base = base_of(robot, base)
    if num_samples * robot.dof < base.num_base:
        raise IdentificationError(f'{num_samples} samples x {robot.dof} joints cannot '
                                  f'determine {base.num_base} base parameters')
    design = DesignProblem(robot, base, work, H, period, int(num_samples), criterion,
                           noise_std, MARGIN, phis, checker, start_q)
    watch = _Progress(progress, time_limit, start_time, criterion)
    design.tick = watch.tick
    hulls, rest = design.checker, None   # clearances on the hulls

    def closest(q: np.ndarray) -> tuple[float, tuple[str, str] | None]:
        assert hulls is not None
        distance, pair = hulls.closest_pair(q)
        return distance - hulls.min_distance, pair
    why = centre_fault(robot, work, phis, closest=None if hulls is None else closest)
    if why is not None:
        rest = nearest_rest_pose(robot, work, phis, clearance=None if hulls is None else (
            lambda q: closest(q)[0]), pad=COLLISION_PAD)
        watch.say(what=f'the centre of the position ranges {why}: the motion is centred on '
                  f'[{", ".join(f"{v:.4g}" for v in rest)}] rad instead')
    init = initial_trajectory(robot, initial, work, H, period, seed, phis, rest)
    if checker is not None:
        init = _out_of_collision(init, design, work, rest)
    x0 = to_x(init)
    f0 = design.value(x0)[0]
    if not np.isfinite(f0):
        raise IdentificationError('the initial trajectory does not excite every base '
                                  'parameter: try another seed or more harmonics')
    held = design.hold_collisions_at(x0)
    if held.size:
        pairs = ', '.join(' - '.join(checker.pairs[i]) for i in held[:3])
        more = f' and {held.size - 3} more' if held.size > 3 else ''
        watch.say(what=f'{pairs}{more}: closer at the start than the optimiser asks for, held '
                  f'no closer (the final check keeps {checker.min_distance:g} m)')
    # init is inside the limits (shrunk on the fine grid); collisions at the design's samples
    initial_feasible = design.checker is None or bool(   # None iff checker is
        design.collision_distances(x0).min() >= checker.min_distance)
    # SLSQP's first step follows the gradient with a unit Hessian: scale the function so that
    # its gradient has unit norm at the start, or the first steps leave the limits far behind.
    g0 = float(np.linalg.norm(design.jac(x0)))
    fscale = 1.0 / g0 if g0 > 0 else 1.0
    # Keep every iterate that satisfies the constraints (SLSQP's own tolerance); the last
    # iterate may violate them slightly, shrink_into_limits then scales it in.
    # (function, worst constraint, x) of the iterates; SLSQP's approach the constraints from
    # outside, and shrink_into_limits scales small kinematic violations away
    iterates = [(f0, 0.0, x0)] if initial_feasible else []

    def track(x: np.ndarray) -> None:
        f = design.value(x)[0]
        if np.isfinite(f):
            worst = float(design.constraint(x).min())
            iterates.append((f, worst, x.copy()))
            watch.iterate(report_value(f, criterion), worst)

    res = None
    if maxiter > 0:
        watch.say(what=f'optimising: {x0.size} coefficients, {design.constraint(x0).size} '
                  f'constraints, at most {maxiter} iterations'
                  + ('' if time_limit is None else f' or {time_limit:g} s'))
        watch.optimising = True
        try:
            res = minimize(lambda x: design.fun(x) * fscale, x0,
                           jac=lambda x: design.jac(x) * fscale, method='SLSQP',
                           bounds=design.bounds(),
                           constraints=[{'type': 'ineq', 'fun': design.constraint,
                                         'jac': design.constraint_jac}],
                           callback=track, options={'maxiter': int(maxiter), 'ftol': 1e-9})
        except _TimeUp:
            last = iterates[-1][2] if iterates else x0
            res = SimpleNamespace(x=last, nit=watch.iteration, success=False, status=-1,
                                  message=f'time limit of {time_limit:g} s reached')
        watch.optimising, watch.verifying = False, True
        watch.say(what=f'{watch.iteration} iterations in {time.perf_counter() - start_time:.0f}'
                  ' s; verifying the best iterates on dense grids')
    names = list(robot.joint_names)
    reasons: list[tuple[str, bool]] = []   # why a candidate failed; a self-collision?

    def verified(x: np.ndarray) -> tuple | None:
        """(criterion, periodic, framed, scale, clearance) of x brought inside every limit,
        framed and checked for collisions; None (the reason noted) when it cannot be."""
        try:
            cand, s, _ = shrink_into_limits(from_x(x, robot.dof, period, names), robot, work,
                                            phis=phis, rest=rest)
            framed = frame_excitation(cand, robot, work, start_q, periods, phis)
        except IdentificationError as exc:   # cannot be brought inside the limits
            reasons.append((str(exc), False))
            return None
        clearance = None
        if checker is not None:
            for check in (lambda: checker.clearance(design.collision_configs(to_x(cand))),
                          lambda: framed_clearance(framed, robot, checker, tick=watch.tick)):
                clearance = check()   # the design's samples first: cheap
                if clearance['distance'] < checker.min_distance:
                    reasons.append((f'collision between {clearance["pair"][0]} and '
                                    f'{clearance["pair"][1]} ({clearance["distance"]:.4g} m)',
                                    checker.self_pair(clearance['pair'])))
                    return None
        return (report_value(design.value(to_x(cand))[0], criterion), cand, framed, s,
                clearance)

    f_init = report_value(f0, criterion)
    # the feasible iterates and those within NEAR_FEASIBLE of the constraints: the best of each
    # of CANDIDATES stretches of the iterations (consecutive iterates are alike and tend to
    # fail the dense checks alike), best first

    def rank(it: tuple) -> tuple:
        return it[0], it[1] < -1e-6
    close = [it for it in iterates if it[1] >= -NEAR_FEASIBLE]
    near = sorted((min((close[i] for i in part), key=rank)
                   for part in np.array_split(np.arange(len(close)), CANDIDATES) if part.size),
                  key=rank)
    candidates = [x for _, _, x in near]
    if res is not None and np.all(np.isfinite(res.x)):
        candidates.insert(0, res.x)
    if not initial_feasible:
        candidates.append(x0)   # the shrinking may still bring it inside
    best, initial_kept = None, False
    tried = candidates[:CANDIDATES]
    # each candidate's criterion as it stands: shrinking into the limits does not better it
    raw = [report_value(design.value(x)[0], criterion) for x in tried] + [math.inf]
    for i, x in enumerate(tried):
        found = verified(x)
        if found is not None and (best is None or found[0] < best[0]):
            best, initial_kept = found, x is x0
        if best is not None and x is not candidates[0] and best[0] <= min(raw[i + 1:]):
            break   # the iterates come best first; a later one is tried only if it may beat
            # what the shrinking left of this (a torque limit that slower motion breaks)
    if (best is None or best[0] >= f_init) and res is not None and initial_feasible:
        # blend the best near-feasible iterate (else the last) with the feasible initial
        # guess, x0 + alpha (x - x0), and keep the first verified blend improving on it
        x_end = near[0][2] if near and near[0][2] is not x0 else (
            iterates[-1][2] if iterates else res.x)
        for alpha in BLENDS:
            found = verified(x0 + alpha * (x_end - x0))
            if found is not None and found[0] < f_init:
                best, initial_kept = found, False
                break
    if best is None:
        why, self_collision = reasons[-1] if reasons else ('no iterate met the constraints',
                                                           False)
        hint = ''   # (pairs that touch by design were named before optimising)
        if checker is not None and self_collision and checker.srdf is None:
            hint = ('; without an SRDF every pair of links not on adjacent joints is '
                    f"checked: {_srdf_fix(checker)}")
        raise IdentificationError(
            f'no feasible excitation found ({why}): loosen the limits or their margin, lower '
            'the minimum distance, or try another start configuration, seed or fewer '
            'harmonics' + hint)
    value, traj, framed, scale, clearance = best
    is_initial = initial_kept
    warnings = []
    message = str(res.message) if res is not None else 'no iterations'
    if res is not None and res.status == 9:   # the iteration limit: said, not a warning
        message = (f'stopped at the limit of {res.nit} iterations (--maxiter); kept the best '
                   'feasible point found')
    elif res is not None and res.status == -1:
        message = f'stopped at the {message}; kept the best feasible point found'
    elif res is not None and not res.success:
        warnings.append(f'SLSQP stopped without converging after {res.nit} iterations '
                        f'({res.message}); kept the best feasible point found (the '
                        'constraints may be too tight: loosen the limits or the margin)')
    if is_initial or value >= f_init:
        warnings.append('no feasible point improved on the initial guess; kept '
                        + ('it' if initial_feasible else 'it, scaled into the constraints'))
    return ExcitationResult(
        trajectory=traj, initial=init, criterion=criterion, value=value,
        initial_value=f_init, ratios=limit_ratios(framed, robot, limits, phis=phis),
        iterations=int(res.nit) if res is not None else 0, evaluations=design.evaluations,
        success=bool(res.success) if res is not None else False,
        message=message,
        scale=scale, runtime=time.perf_counter() - start_time, num_samples=int(num_samples),
        limits=limits,
        noise_std=None if noise_std is None else [float(s) for s in noise_std],
        framed=framed, margin=float(margin),
        status=int(res.status) if res is not None else 0, warnings=warnings,
        clearance=clearance, collision=None if checker is None else checker.summary(),
        initial_feasible=initial_feasible)


def _out_of_collision(traj: FourierTrajectory, design: DesignProblem, limits: ExcitationLimits,
                      rest: np.ndarray | None = None, steps: int = 20) -> FourierTrajectory:
    """``traj``, or its motion scaled towards the centre of the position ranges or ``rest``
    (nearest_rest_pose; by 0.8 per step) until it meets the collision constraints (at the design's
    collision samples); failing that, the least scaled that keeps the minimum distance there
    (the pairs it brings closer than the constraints ask for are then held:
    DesignProblem.hold_collisions_at); ``traj`` unchanged when none does (the optimiser then
    starts infeasible)."""
    assert design.checker is not None   # called only with collision constraints
    cur, scale, clear = traj, 1.0, None
    for _ in range(steps):
        x = to_x(cur)
        if design.collision_ks(x, False)[0].max() <= design.margin:
            return cur
        if clear is None and design.collision_distances(x).min() >= design.checker.min_distance:
            clear = cur
        scale *= 0.8
        cur = scale_motion(traj, limits, scale, rest)
    return traj if clear is None else clear
