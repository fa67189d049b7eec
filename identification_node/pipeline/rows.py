"""Stage 5, rows: the fixed-lag smoother, pinocchio's regressor and the base rows.

Positions (and measured velocities) and the torque go through the same smoother
(signals.FixedLagSmoother: local cubic fit over 2L+1 samples), giving q, qd, qdd and tau at the
window centre, L samples behind the newest; then Y(q, qd, qdd) (RobotModel.regressor) and the
base rows [Yb | tau] (BaseParameters' columns). Everything per batch, no loop over samples but
pinocchio's.

The half window L is given (``half_window`` > 0), or follows from a cut-off in Hz and the
sampling rate (``cutoff`` > 0), or is chosen from the data (both 0): the samples of the first
``auto_seconds`` of motion are held back, and :class:`WindowSearch` picks the window on them,
one candidate per AUTO_STEP s of new samples and call (so the node's processing runs stay
short; samples keep being held meanwhile); then they and all later samples go through that one
smoother. The choice: least squares of the base rows is fitted on those samples for half
windows on a geometric grid, and the chosen window is the one where the fit's predicted torque
changes least between its two neighbours on the grid. Too short a window leaves differentiation
noise in the regressor (errors in variables: a bias toward smaller inertia), too long a one
distorts the motion (the opposite bias); where neither acts the estimate stands still. The fits
leave out the equations the estimator leaves out (near_reversal, with Coulomb friction): a
window's smear of the friction's jump at a reversal would otherwise decide the choice.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.pipeline.samples import Samples
from identification_node.pipeline.signals import (MIN_HALF_WINDOW, FixedLagSmoother,
                                                  half_window_for_cutoff, smoothed_sign,
                                                  smoother_cutoff)

AUTO_GRID = 2.0 ** 0.25   # ratio of neighbouring half windows tried by choose_half_window
AUTO_ROWS = 500           # samples whose rows the choice fits (evenly spread)
AUTO_STEP = 0.05          # s of new samples per candidate window the search tries per call
AUTO_TAPS = 2001          # longer candidate windows are fitted on every s-th sample (cost)
MOTION = 1e-3             # rad (m): a joint this far from its first position is moving
AUTO_WAIT = 6.0           # times auto_seconds held at most without enough motion
FALLBACK_CUTOFF = 5.0     # Hz: the cut-off when the data are too short to choose from


@dataclass
class SmootherChoice:
    """The smoother in use: half window (samples), polynomial order, the sampling rate (Hz,
    median of the steps it was chosen on; NaN until samples came) and how it was set:
    'half_window' (given), 'cutoff' (given in Hz), 'automatic' (chosen from the data) or
    'fallback' (too few samples to choose from: FALLBACK_CUTOFF)."""
    half_window: int
    order: int
    rate: float = math.nan
    source: str = 'half_window'
    seconds: float = 0.0     # s of samples the automatic choice used

    @property
    def cutoff(self) -> float:
        """-3 dB frequency (Hz) of the smoothed values at ``rate``."""
        return (smoother_cutoff(self.half_window, self.order, self.rate)
                if self.rate > 0 else math.nan)

    @property
    def delay(self) -> float:
        """Output lag (s) behind the newest input at ``rate``: half_window / rate."""
        return self.half_window / self.rate if self.rate > 0 else math.nan

    def document(self) -> dict:
        return {'half_window': self.half_window, 'order': self.order,
                'cutoff_hz': self.cutoff, 'rate_hz': self.rate, 'delay_s': self.delay,
                'window_s': (2 * self.half_window) / self.rate if self.rate > 0 else math.nan,
                'source': self.source, 'auto_seconds_used': self.seconds}


def near_reversal(qd: np.ndarray, qdd: np.ndarray, speed: np.ndarray, reach: float
                  ) -> np.ndarray:
    """Mask (N, n) of the joint equations whose smoothing window may hold a velocity
    reversal: |qd| < speed + |qdd| reach, for smoothed qd (rad/s), qdd (rad/s^2), the speed
    per joint (n,) (RobotModel.in_joint_units of coulomb_exclusion_speed) and the half
    window ``reach`` (s). There a sign friction torque turns faster than the smoother
    resolves, so those equations are left out when Coulomb friction is identified; with
    the smoothed sign in the Coulomb column (smooths_sign) the reach is 0: only the slow
    motion (stiction, Stribeck) is left out."""
    return np.abs(qd) < speed + np.abs(qdd) * reach


def smooths_sign(robot: RobotModel) -> bool:
    """Whether the streaming rows' Coulomb column is the smoothed sign (smoothed_sign): fc
    identified with the sign model (coulomb_velocity 0)."""
    return 'fc' in robot.extras and robot.coulomb_velocity == 0


def coulomb_columns(robot: RobotModel) -> list[int]:
    """The standard-parameter index of each joint's fc, joints in order."""
    return [robot.param_index(f'{j}.fc') for j in robot.joint_names]


def smoothed_coulomb(qd: np.ndarray, qdd: np.ndarray, half_window: int, order: int,
                     period: float) -> np.ndarray | None:
    """The Coulomb column values (N, n) the smoother of ``half_window`` and ``order`` at
    ``period`` (s) makes of sign(qd) (signals.smoothed_sign), so that the Coulomb column
    matches the smoothed torque at reversals too (RobotModel.regressor's ``coulomb``); None
    without a period (the plain sign then)."""
    if not (period > 0 and math.isfinite(period)):
        return None
    return smoothed_sign(qd, qdd, half_window, order, period)


def _rate(stamps: np.ndarray) -> float:
    return 1.0 / float(np.median(np.diff(stamps))) if len(stamps) > 1 else math.nan


class WindowSearch:
    """The choice of the half window (samples) for samples t (N,) s, q, tau (N, n) and
    measured qd (N, n) (None: differentiated) by the criterion of the module doc, one
    candidate window per ``step`` (the node's processing stays responsive); ``result``:
    the half window once ``done``, None when the samples are too few for three candidates.
    ``weights`` (n,): per-joint weights of the fit; ``exclusion_speed`` > 0 (rad/s; prismatic
    joints: in_joint_units) with Coulomb friction identified: the equations near_reversal left
    out, as the estimator leaves them out."""

    def __init__(self, robot: RobotModel, base: BaseParameters, t: np.ndarray, q: np.ndarray,
                 qd: np.ndarray | None, tau: np.ndarray, order: int, max_gap: float,
                 weights: np.ndarray | None = None, exclusion_speed: float = 0.0):
        self.robot, self.base, self.order, self.t = robot, base, int(order), t
        self.exclusion = (robot.in_joint_units(float(exclusion_speed))
                          if 'fc' in robot.extras and exclusion_speed > 0 else None)
        self.period = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        self.measured = qd is not None
        self.x = np.hstack([q, tau] if qd is None else [q, qd, tau])
        N, n = len(t), robot.dof
        largest = (N // 3 - 1) // 2
        grid = sorted({int(round(MIN_HALF_WINDOW * AUTO_GRID ** k)) for k in range(200)
                       if MIN_HALF_WINDOW * AUTO_GRID ** k <= largest})
        self.grid = [L for L in grid if L >= max(MIN_HALF_WINDOW, order)]
        self.root = None if weights is None else np.sqrt(np.asarray(weights, dtype=float))
        self.fits: list[tuple[np.ndarray, np.ndarray]] = []
        self.result: int | None = None
        self.done = len(self.grid) < 3
        if self.done:
            return
        top = self.grid[-1]
        self.stride = {L: max(1, math.ceil((2 * L + 1) / AUTO_TAPS)) for L in self.grid}
        s_top = self.stride[top]
        segment = np.concatenate([[0], np.cumsum(np.diff(t) > max_gap)])
        centres = np.unique(np.linspace(top, N - 1 - top, AUTO_ROWS).round().astype(np.int64))
        centres = np.unique(np.clip(centres // s_top * s_top, top, N - 1 - top))
        self.centres = centres[segment[centres - top] == segment[centres + top]]
        self.done = len(self.centres) * n < 4 * base.num_base

    def step(self) -> None:
        """Fit the next candidate window; decide after the last."""
        if self.done:
            return
        n, b = self.robot.dof, self.base.num_base
        L = self.grid[len(self.fits)]
        k = self.stride[L]    # a long window fitted on every k-th of its samples (centres too)
        v, d, dd = FixedLagSmoother(self.x.shape[1], L // k, self.order).fit_at(
            self.t[::k], self.x[::k], self.centres // k)
        qd, qdd = (v[:, n:2 * n], d[:, n:2 * n]) if self.measured else (d[:, :n], dd[:, :n])
        smooth = smooths_sign(self.robot)
        Y = self.robot.regressor(v[:, :n], qd, qdd, coulomb=smoothed_coulomb(
            qd, qdd, L // k, self.order, k * self.period) if smooth else None)
        Yb = self.base.base_regressor(Y)
        y = v[:, -n:]
        if self.root is not None:
            Yb, y = Yb * self.root[None, :, None], y * self.root
        if self.exclusion is not None:
            used = ~near_reversal(qd, qdd, self.exclusion,
                                  0.0 if smooth else L * self.period)
            Yb, y = Yb * used[:, :, None], y * used
        A = Yb.reshape(-1, b)
        theta = np.linalg.lstsq(A.T @ A, A.T @ y.reshape(-1), rcond=1e-12)[0]
        self.fits.append((A, theta))
        if len(self.fits) == len(self.grid):
            f = self.fits
            change = [np.sqrt(np.mean((f[i][0] @ (f[i + 1][1] - f[i - 1][1])) ** 2))
                      for i in range(1, len(f) - 1)]
            self.result = self.grid[1 + int(np.argmin(change))]
            self.done, self.fits = True, []

    def run(self) -> int | None:
        while not self.done:
            self.step()
        return self.result


def choose_half_window(robot: RobotModel, base: BaseParameters, t: np.ndarray, q: np.ndarray,
                       qd: np.ndarray | None, tau: np.ndarray, order: int, max_gap: float,
                       weights: np.ndarray | None = None, exclusion_speed: float = 0.0
                       ) -> int | None:
    """WindowSearch's result, at once."""
    return WindowSearch(robot, base, t, q, qd, tau, order, max_gap, weights,
                        exclusion_speed).run()


class Rows(NamedTuple):
    """Smoothed samples at the window centres t (M,) s: q, qd, qdd, tau (M, n), and the rows
    [Yb | tau] (M, n, b + 1) of the base regressor and the torque."""
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    rows: np.ndarray


def choose_smoother(robot: RobotModel, base: BaseParameters, t: np.ndarray, q: np.ndarray,
                    qd: np.ndarray, tau: np.ndarray, order: int, max_gap: float,
                    cutoff: float = 0.0, auto_seconds: float = 5.0,
                    weights: np.ndarray | None = None, final: bool = False,
                    exclusion_speed: float = 0.0) -> SmootherChoice | None:
    """The smoother for a stream's first samples t (N,) s, q, qd (NaN: not measured), tau
    (N, n): of the given ``cutoff`` (Hz) at their rate, or chosen (WindowSearch) on the first
    ``auto_seconds`` of motion; None while more samples are needed (``final``: no more come,
    decide with these)."""
    plan = plan_smoother(robot, base, t, q, qd, tau, order, max_gap, cutoff, auto_seconds,
                         weights, final, exclusion_speed)
    return plan if plan is None or isinstance(plan, SmootherChoice) else plan.finish()


class _Search:
    """A WindowSearch under way, with what the SmootherChoice it ends in needs."""

    def __init__(self, search: WindowSearch, order: int, rate: float, seconds: float):
        self.search, self.order, self.rate, self.seconds = search, order, rate, seconds

    def finish(self) -> SmootherChoice:
        L = self.search.run()
        if L is None:
            return SmootherChoice(half_window_for_cutoff(FALLBACK_CUTOFF, self.rate, self.order),
                                  self.order, self.rate, 'fallback')
        return SmootherChoice(L, self.order, self.rate, 'automatic', self.seconds)


def _first_motion(q: np.ndarray, q0: np.ndarray) -> int:
    """Index of the first sample of q (N, n) with a joint more than MOTION from q0 (n,);
    N when none."""
    moved = np.abs(q - q0).max(axis=1) > MOTION
    return int(np.argmax(moved)) if moved.any() else len(q)


def _choice_due(span: float, waited: float, auto_seconds: float) -> bool:
    """Whether the automatic choice is made, after ``span`` s of motion in ``waited`` s of
    held samples."""
    return span >= auto_seconds or waited >= AUTO_WAIT * auto_seconds


def plan_smoother(robot: RobotModel, base: BaseParameters, t: np.ndarray, q: np.ndarray,
                  qd: np.ndarray, tau: np.ndarray, order: int, max_gap: float,
                  cutoff: float = 0.0, auto_seconds: float = 5.0,
                  weights: np.ndarray | None = None, final: bool = False,
                  exclusion_speed: float = 0.0) -> SmootherChoice | _Search | None:
    """choose_smoother's decision, or the search to run to it (step by step)."""
    if cutoff > 0:
        if len(t) < 16 and not final:
            return None
        rate = _rate(t) if len(t) > 1 else 1.0 / max(max_gap, 1e-9)
        return SmootherChoice(half_window_for_cutoff(cutoff, rate, order), order, rate,
                              'cutoff')
    first = _first_motion(q, q[0]) if len(t) else 0
    span = (t[-1] - t[first]) if first < len(t) else 0.0
    waited = (t[-1] - t[0]) if len(t) else 0.0
    if not final and not _choice_due(span, waited, auto_seconds):
        return None
    rate = _rate(t)
    if math.isnan(rate):
        return SmootherChoice(half_window_for_cutoff(FALLBACK_CUTOFF, 1.0, order), order, 1.0,
                              'fallback')
    part = (slice(first, first + int(np.searchsorted(t[first:], t[first] + auto_seconds
                                                     + 1e-9))) if span else slice(0, len(t)))
    measured = qd[part] if np.isfinite(qd[part]).all() else None
    search = WindowSearch(robot, base, t[part], q[part], measured, tau[part], order, max_gap,
                          weights, exclusion_speed)
    return _Search(search, order, rate, float(t[part][-1] - t[part][0]))


class RowBuilder:
    """Smoother, regressor and base rows of ``robot`` for validated samples with torque.
    ``half_window`` (samples) > 0 fixes the smoother; else ``cutoff`` (Hz) > 0 sets it at the
    data's sampling rate; else it is chosen from the first ``auto_seconds`` of motion
    (module doc; ``weights`` (n,): per-joint weights of that choice's fit,
    ``exclusion_speed``: its equations left out near_reversal)."""

    def __init__(self, robot: RobotModel, base: BaseParameters, half_window: int, order: int,
                 max_gap: float, cutoff: float = 0.0, auto_seconds: float = 5.0,
                 weights: np.ndarray | None = None, exclusion_speed: float = 0.0):
        self.robot, self.base = robot, base
        self.order, self.max_gap = int(order), max_gap
        self.cutoff, self.auto_seconds, self.weights = float(cutoff), float(auto_seconds), weights
        self.exclusion_speed = float(exclusion_speed)
        # the Coulomb column as the smoother makes of sign(qd) (smooths_sign); False: sign(qd)
        # itself (predictions of the raw torque)
        self.smooth_sign = True
        # True: the choice is all the caller wants (segments.chosen_smoother): the samples
        # held for it stay held, no rows are made of them
        self.choose_only = False
        self.choice: SmootherChoice | None = (
            SmootherChoice(int(half_window), self.order) if half_window else None)
        self._held: list[Samples] = []     # samples waiting for the choice
        # stamp of the held samples' first motion (nan: none yet), followed per call: the
        # choice's condition asked without joining them (quadratic in their count)
        self._moved_at = math.nan
        self._search: _Search | None = None   # the choice under way
        # columns of [Y | tau] that make the rows [Yb | tau]
        self._columns = np.append(base.base_index, robot.num_params)
        self._work: dict[str, np.ndarray] = {}
        self.reset_counts()
        self.reset()

    @property
    def half_window(self) -> int | None:
        """The smoother's half window (samples); None while it is still to be chosen."""
        return None if self.choice is None else self.choice.half_window

    @property
    def searching(self) -> bool:
        """Whether the choice of the window is under way (calls without samples advance it)."""
        return self._search is not None

    @property
    def holding(self) -> int:
        """Samples held back for the choice of the smoother."""
        return sum(len(s) for s in self._held)

    def reset(self) -> None:
        """Forget the smoother's window (a new stream): it is made on first use, when the
        channels (with or without measured velocity) are known. What it held and never output
        is counted in ``smoother_edge``. Call ``drain`` first for the held samples."""
        if self.choice is not None:
            self._count_edges(restart=True)
        self._smoother: FixedLagSmoother | None = None

    def reset_counts(self) -> None:
        """Counters to zero; samples held for the choice are dropped (a pipeline reset)."""
        self._held, self._search, self._moved_at = [], None, math.nan
        self._in = self._out = 0    # samples into / out of the smoother
        # valid samples the smoother never outputs: half a window at the stream's start, at
        # either side of a stamp gap, and what a restart drops (not rejections: apart)
        self.smoother_edge = 0

    def _count_edges(self, restart: bool = False) -> None:
        """All that went in and did not come out, but the newest half window (the delay);
        on a restart all of it."""
        assert self.choice is not None   # counted once the smoother is chosen
        waiting = self._in - self._out
        lost = waiting if restart else max(waiting - self.choice.half_window, 0)
        self.smoother_edge += lost
        self._out += lost

    def _choose(self, flush: bool, new: int = 0) -> bool:
        """Decide the smoother once the held samples allow it (``flush``: with what there
        is; ``new``: samples that came with this call); whether it is decided."""
        if self._search is None:
            if not (flush or self.cutoff > 0 or self._choice_may_be_due()):
                return False
            held = self._join_held()
            assert held.tau is not None   # the rows' samples carry their torques
            plan = plan_smoother(self.robot, self.base, held.stamps, held.q, held.qd,
                                 held.tau, self.order, self.max_gap, self.cutoff,
                                 self.auto_seconds, self.weights, flush,
                                 self.exclusion_speed)
            if plan is None:
                return False
            if isinstance(plan, SmootherChoice):
                self.choice = plan
                return True
            self._search = plan
        if flush:
            self.choice = self._search.finish()
        else:     # a candidate per AUTO_STEP s of new samples, at least one per call: the
            # choice spreads over the node's processing runs, in step with the input
            per = max(1, int(AUTO_STEP * self._search.rate))
            for _ in range(max(1, new // per)):
                self._search.search.step()
            if self._search.search.done:
                self.choice = self._search.finish()
        if self.choice is None:
            return False
        self._search = None
        self._join_held()
        return True

    def _join_held(self) -> Samples:
        """The held samples as one (kept so)."""
        held = self._held[0]
        for s in self._held[1:]:
            held = held.concat(s)
        self._held = [held]
        return held

    def _hold(self, s: Samples) -> None:
        """Hold ``s`` (stamps after those held) for the choice."""
        self._held.append(s)
        if math.isnan(self._moved_at) and (
                k := _first_motion(s.q, self._held[0].q[0])) < len(s):
            self._moved_at = float(s.stamps[k])

    def _choice_may_be_due(self) -> bool:
        """plan_smoother's condition on the held samples (without joining them)."""
        first, last = float(self._held[0].stamps[0]), float(self._held[-1].stamps[-1])
        moved = 0.0 if math.isnan(self._moved_at) else last - self._moved_at
        return _choice_due(moved, last - first, self.auto_seconds)

    def drain(self, measured_velocity: bool) -> Rows | None:
        """The rows of the samples held for the choice (deciding it with what is held), at
        the end of their stream; None when nothing is held."""
        if not self._held:
            return None
        return self(Samples.empty(self.robot.dof), measured_velocity, flush=True)

    def _empty(self) -> Rows:
        n = self.robot.dof
        z = np.zeros((0, n))
        return Rows(np.zeros(0), z, z, z, z, np.zeros((0, n, self.base.num_base + 1)))

    def __call__(self, s: Samples, measured_velocity: bool, reuse_at: int | None = None,
                 flush: bool = False) -> Rows:
        """The rows of the windows the samples ``s`` complete. ``reuse_at``: when at least
        this many come out, the rows live in a work array the next call reuses (the caller is
        done with them by then). ``flush``: the stream ends (a held choice is decided)."""
        if self.choice is None:
            if len(s):
                self._hold(s)
            if not self._held or not self._choose(flush, len(s)) or self.choose_only:
                return self._empty()
            s, self._held, self._moved_at = self._held[0], [], math.nan
        elif math.isnan(self.choice.rate) and len(s) > 1:
            self.choice.rate = _rate(s.stamps)
        if len(s) == 0:
            return self._empty()
        # chosen by now (or returned above); the rows' samples carry their torques
        assert self.choice is not None and s.tau is not None
        n = self.robot.dof
        x = np.concatenate([s.q, s.qd, s.tau] if measured_velocity else [s.q, s.tau], axis=1)
        if self._smoother is None:
            self._smoother = FixedLagSmoother(x.shape[1], half_window=self.choice.half_window,
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
        coulomb = (smoothed_coulomb(qd, qdd, self.choice.half_window, self.order,
                                    self.period(t))
                   if self.smooth_sign and smooths_sign(self.robot) else None)
        self.robot.regressor(q, qd, qdd, out=Yt[:, :, :p], checked=True, coulomb=coulomb)
        Yt[:, :, p] = tau
        shape = (len(t), n, b + 1)
        reuse = reuse_at is not None and len(t) >= reuse_at
        rows = self._buffer('rows', shape) if reuse else np.empty(shape)
        Yt.take(self._columns, axis=2, out=rows, mode='clip')
        return Rows(t, q, qd, qdd, tau, rows)

    def period(self, t: np.ndarray) -> float:
        """The sample period (s) the smoother's chosen window is at: the choice's rate, else
        that of the window centres ``t`` (s)."""
        assert self.choice is not None   # chosen: there are rows
        return 1.0 / (self.choice.rate if self.choice.rate > 0 else _rate(t))

    def _buffer(self, name: str, shape: tuple) -> np.ndarray:
        """A work array of ``shape``, reused across batches (grown when needed): allocating
        megabytes afresh every batch costs more in page faults than the arithmetic on them."""
        size = math.prod(shape)
        buf = self._work.get(name)
        if buf is None or buf.size < size:
            self._work[name] = buf = np.empty(size)
        return buf[:size].reshape(shape)
