"""Stage 6, estimate: recursive least squares on the base rows, with honest uncertainty.

Rows are weighted (joint noise weights; a joint's equation left out near a velocity reversal
when Coulomb friction is identified), gathered, and fed to the RLS and the residual statistics
every ``update_batch`` samples in one batch (what sample-by-sample updates give). The torque is
smoothed, so residuals are correlated over the window: the covariance's noise level is the
larger of the white raw noise that explains the smoothed residual
(signals.smoothing_noise_gain) and, once there are enough blocks, the residual's long-run
variance (ResidualStatistics' block sums); see ``noise_variance``. The blocks restart at every
RESIDUAL_GRID of the stamps, so a bag cut there into segments has its blocks
(replay/segments.py).

Before an update, samples whose rows would overflow are dropped ('regressor_overflow') and,
once the estimate has converged and predicts new samples, the robust gate (robust.py) holds
outliers back ('outlier'); an update that fails or turns non-finite is rolled back to the last
finite state ('numerical_failure', ``numerical_failures``).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.lsq import row_information
from identification_node.estimation.model_terms import (ModelTermStatistics, features,
                                                        missing_term_warnings)
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.estimation.robust import InnovationGate
from identification_node.pipeline.config import PipelineConfig
from identification_node.pipeline.rows import near_reversal
from identification_node.pipeline.signals import smoothing_noise_gain

_T = TypeVar('_T')

# What the numerical update may raise on absurd data: caught, the estimator rolled back.
PROVISIONAL_HALF_WINDOW = 10   # samples: residual blocks before the smoother is chosen
NUMERICAL_ERRORS = (ArithmeticError, ValueError, np.linalg.LinAlgError, IdentificationError)
# The residual blocks restart where the stamps (ns since 1970) cross a multiple of this, 10 s:
# which block a sample falls in then depends on its stamp and the samples since the last
# multiple only, not on where its stream began, so a bag cut at multiples merges exactly, and
# parallel replay can split a bag of a minute or two evenly. The unfinished block is left out
# of the block sums there, as at a stream restart: half a block per 10 s on average, 0.8 % of
# the samples with blocks of 168 (half window 10 at 1 kHz), about 9 % with the automatic
# smoother's windows of about 0.2 s (blocks of 1.7 s). Only the long-run variance's precision
# pays (about 5 %); the sample sums keep every row.
RESIDUAL_GRID = 10 * 10**9


@dataclass
class EstimateReport:
    """The running estimate: base parameters with standard deviations, and health figures."""
    names: list
    values: np.ndarray
    stddev: np.ndarray
    num_samples: int
    stamp: float
    condition_number: float
    min_eigenvalue: float
    residual_rms: np.ndarray
    converged: bool
    frozen: bool


def converged(covariance: np.ndarray, gram: np.ndarray, count: float,
              noise_variance: np.ndarray, num_samples: int, condition: float,
              config: PipelineConfig) -> bool:
    """Excited (``condition`` <= max_condition), ``num_samples`` >= min_samples, and the
    parameter uncertainty adds less than ``converged_ratio`` of the torque noise
    (``noise_variance`` (n,)) to every joint's predicted torque: the mean of trace(P G_j) /
    count over the rows whose per-joint Gram matrices are ``gram`` (n, b, b)."""
    if num_samples < config.min_samples or not condition <= config.max_condition:
        return False
    var = np.einsum('pq,nqp->n', covariance, gram) / max(count, 1)
    return bool(np.all(np.sqrt(np.maximum(var, 0))
                       <= config.converged_ratio * np.sqrt(noise_variance)))


class _Pending(NamedTuple):
    """Rows queued by OnlineEstimate.add, with what weighting them needs."""
    rows: np.ndarray
    t: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    stamps_ns: np.ndarray | None
    q: np.ndarray | None


def _finite_samples(rows: np.ndarray) -> np.ndarray:
    """Mask (N,) of the samples whose rows (N, n, k) have a finite sum of squares (the
    information and residual sums take them without overflow)."""
    with np.errstate(over='ignore', invalid='ignore'):
        return np.isfinite(np.einsum('njk,njk->n', rows, rows))


def _joined(arrays) -> np.ndarray:
    """The arrays of the queued parts, one after the other (the one itself when alone)."""
    return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)


class OnlineEstimate:
    """RLS and residual statistics of ``num_base`` parameters over ``dof`` joints' rows."""

    def __init__(self, num_base: int, dof: int, config: PipelineConfig, coulomb: bool,
                 reject=lambda reason, count: None, smoothed_sign: bool = False,
                 exclusion_speed: np.ndarray | None = None):
        self.num_base, self.dof, self.config, self.coulomb = num_base, dof, config, coulomb
        # (n,) coulomb_exclusion_speed per joint (RobotModel.in_joint_units); None: as given
        self.exclusion_speed = (np.full(dof, float(config.coulomb_exclusion_speed))
                                if exclusion_speed is None
                                else np.asarray(exclusion_speed, dtype=float))
        # the rows' Coulomb column is the smoothed sign (rows.smooths_sign): reversals in the
        # smoothing window need no exclusion, only slow motion does
        self.smoothed_sign = bool(smoothed_sign)
        self._reject = reject    # reject(reason, count): where dropped samples are counted
        self.gate = InnovationGate(config.robust)
        self.half_window: int | None = None
        # until the smoother is chosen (rows.RowBuilder), a stand-in for the block length
        self._set_smoother(int(config.half_window) or PROVISIONAL_HALF_WINDOW,
                           int(config.smoother_order))
        self.half_window = int(config.half_window) or None
        # Inverse-variance weights per joint (RLS weights multiply squared residuals).
        self._weights = (np.asarray(config.joint_noise_std, dtype=float) ** -2
                         if len(config.joint_noise_std) else None)
        self.reset()

    def _set_smoother(self, half_window: int, order: int) -> None:
        self._block = 8 * (2 * int(half_window) + 1)   # residual blocks: 8 windows
        self._white_scale = 1.0 / smoothing_noise_gain(int(half_window), int(order))
        self.half_window = int(half_window)

    def set_smoother(self, half_window: int, order: int) -> None:
        """The smoother's half window (samples) and order, once chosen: residual blocks of
        8 windows, the white-noise scale, the reach of the Coulomb exclusion. Before any row
        (the estimator is reset: its residual sums start with the new blocks)."""
        self._set_smoother(half_window, order)
        if self._residuals.count == 0 and not self._updates:
            self.reset()

    def reset(self) -> None:
        self._rls = RecursiveLeastSquares(self.num_base, forgetting=self.config.forgetting)
        self._residuals = ResidualStatistics(self.num_base, self.dof, self._block)
        self._updates: list[_Pending] = []
        self._pending_samples = 0
        self._excluded = np.zeros(self.dof, dtype=np.int64)   # per joint, near reversals
        self.terms = ModelTermStatistics(self.dof, self.num_base + 1)
        self._numerical_failures = 0
        self._rows_used = np.zeros(self.dof)   # per joint: rows of weight > 0 in the sums
        self._next_arm = 0                       # samples at which arming is asked next
        self._last_t = math.nan
        self._cell: int | None = None            # RESIDUAL_GRID cell of the last row added
        self.gate.reset()

    @property
    def theta(self) -> np.ndarray:
        """The estimate the predictions use: as of the last update."""
        return self._rls.theta

    @property
    def batch_due(self) -> bool:
        """Whether rows added now are applied within the call (so may live in a work array)."""
        return not self._updates

    def add(self, rows: np.ndarray, t: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
            stamps_ns: np.ndarray | None = None, q: np.ndarray | None = None,
            defer: bool = False) -> None:
        """Rows [Yb | tau] (N, n, b + 1) of samples at t (N,) with smoothed qd, qdd (N, n),
        queued as they are and applied once ``update_batch`` samples are gathered (or a result
        is read): weighting them and every other step then runs once per batch, not once per
        call. ``stamps_ns`` (N,) int64, the samples' stamps: the residual blocks restart where
        they cross a multiple of RESIDUAL_GRID. With the smoothed q (N, n), the residual's
        model-term sums (model_terms.py) too. The rows are weighted in place when applied.
        ``defer``: a full batch waits for ``apply_due`` (the rows must stay untouched until
        then)."""
        if len(rows) == 0:
            return
        self._last_t = float(t[-1])
        self._updates.append(_Pending(rows, t, qd, qdd, stamps_ns, q))
        self._pending_samples += len(rows)
        if not defer:
            self.apply_due()

    def apply_due(self) -> None:
        """Apply the rows gathered once ``update_batch`` samples are."""
        if self._pending_samples >= self.config.update_batch:
            self.apply()

    def apply(self) -> None:
        """Weight the rows gathered since the last update and feed them to the RLS and the
        residual statistics in one batch per RESIDUAL_GRID cell (the rows before a cell's
        start applied, its open residual block closed); each batch's per-joint information
        is formed once for both (without forgetting)."""
        if not self._updates:
            return
        parts, self._updates, self._pending_samples = self._updates, [], 0
        rows, t, qd, qdd = (_joined(p) for p in zip(*((u.rows, u.t, u.qd, u.qdd)
                                                      for u in parts)))
        w = self._row_weights(t, qd, qdd)
        used = None
        if w is not None:
            root = np.sqrt(np.broadcast_to(w, rows.shape[:2]))
            rows *= root[:, :, None]
            used = root > 0
        finite = _finite_samples(rows)
        if all(u.q is not None for u in parts):   # rows that overflow are left out here too
            f = features(_joined([u.q for u in parts]), qd)
            if used is not None:
                f *= used[:, :, None]
            self.terms.add(f[finite], rows[finite])
        cuts: list[int] = []
        if all(u.stamps_ns is not None for u in parts):
            cell = _joined([np.asarray(u.stamps_ns, dtype=np.int64) for u in parts]
                           ) // RESIDUAL_GRID
            before = cell[0] if self._cell is None else self._cell
            cuts = np.flatnonzero(np.diff(cell, prepend=before)).tolist()
            self._cell = int(cell[-1])
        for a, b in zip([0] + cuts, cuts + [len(rows)]):
            if a in cuts:     # a new cell: its open residual block closed
                self._residuals.close_block()
            if b > a:
                self._update(rows[a:b], None if used is None else used[a:b], finite[a:b])

    def _update(self, rows: np.ndarray, used: np.ndarray | None, finite: np.ndarray) -> None:
        """One batch of weighted rows into the RLS and the residual statistics (rolled back
        and counted when it fails); ``finite``: their samples' _finite_samples."""
        rows, used = self._screened(rows, used, finite)
        if len(rows) == 0:
            return
        saved = _state(self._rls), _state(self._residuals)
        try:
            with np.errstate(over='ignore', invalid='ignore'):
                information = row_information(rows)
            self._rls.update_rows(rows, used, information)
            self._residuals.add_rows(rows, information)
            ok = np.isfinite(self._rls.theta).all() and np.isfinite(self._rls.information).all()
        except NUMERICAL_ERRORS:
            ok = False
        if not ok:   # back to the last finite state; the batch is counted and dropped
            self._rls, self._residuals = saved
            self._numerical_failures += 1
            self._reject('numerical_failure', len(rows))
            return
        self._rows_used += len(rows) if used is None else used.sum(axis=0)

    def _screened(self, rows: np.ndarray, used: np.ndarray | None, finite: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray | None]:
        """The rows of a batch the estimator may take: samples whose sums would overflow
        (not ``finite``) dropped, and, once the estimate has converged, the robust gate's
        decision."""
        if not finite.all():
            self._reject('regressor_overflow', np.count_nonzero(~finite))
            rows, used = rows[finite], None if used is None else used[finite]
        gate, b = self.gate, self.num_base
        # armed once converged and predicting this batch: asked every gate window of samples
        # (the convergence test is not cheap), on a whole update batch (a read of the estimate
        # applies a few rows, too few to tell whether it predicts)
        due = (gate.settings.enabled and not gate.armed
               and len(rows) >= self.config.update_batch
               and self._rls.num_samples >= max(self.config.min_samples, self._next_arm))
        if not (gate.armed or due) or len(rows) == 0:
            return rows, used
        theta = self._rls.theta
        residuals = rows[:, :, b] - rows[:, :, :b] @ theta
        sigma = self._innovation_std(rows[:, :, :b], residuals, theta)
        if due:
            self._next_arm = self._rls.num_samples + int(gate.settings.window)
            if not (self.converged(self.excitation()[0], self.covariance)
                    and gate.arm(residuals, sigma)):
                return rows, used
        before = gate.outliers
        keep, back = gate.screen(
            residuals, sigma,
            lambda gated: (rows[gated], None if used is None else used[gated]), self._last_t)
        self._reject('outlier', gate.outliers - before)   # negative: given back on a shift
        if keep.all() and not back:
            return rows, used
        parts = [(rows[keep], None if used is None else used[keep])] + back
        if any(u is not None for _, u in parts):
            used = np.concatenate([np.ones(r.shape[:2], dtype=bool) if u is None else u
                                   for r, u in parts])
        return np.concatenate([r for r, _ in parts]), used

    def _innovation_std(self, Y: np.ndarray, residuals: np.ndarray, theta: np.ndarray
                        ) -> np.ndarray:
        """Standard deviation (N, n) of the innovations ``residuals`` of rows ``Y`` (N, n, b):
        the residual's per used row (rows left out, weight 0, hold no residual) and the
        estimate's own, y P y', which motion the estimate has not seen yet makes large. The
        latter only widens the gate: it is formed for the samples the former would gate."""
        noise = self._residuals.rss(theta) / np.maximum(self._rows_used, 1)
        sigma = np.broadcast_to(np.sqrt(noise), residuals.shape).copy()
        near = self.gate.beyond(residuals, sigma)
        if near.any():
            Yn = Y[near]
            with np.errstate(over='ignore', invalid='ignore'):
                sigma[near] = np.sqrt(noise + np.einsum('Njp,Njp->Nj', Yn @ self.covariance, Yn))
        return sigma

    def end_stream(self) -> None:
        """The stream ended (a restart): its rows applied, its unfinished residual block left
        out, so no block spans two streams (their residuals are not correlated)."""
        self.apply()
        self._residuals.close_block()
        self._cell = None

    def restore(self, rls: RecursiveLeastSquares, residuals: ResidualStatistics,
                excluded: np.ndarray | None = None,
                terms: ModelTermStatistics | None = None) -> None:
        """Take the estimator, residual and model-term sums and the equations left out per
        joint (n,) of processed data (e.g. merged over many bags, fleet.py); nothing gathered
        stays pending."""
        self.reset()
        self._rls, self._residuals = rls, residuals
        if excluded is not None:
            self._excluded = np.asarray(excluded, dtype=np.int64).copy()
        if terms is not None:
            self.terms = terms

    def _row_weights(self, t: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray | None:
        """Per (sample, joint) weights: the joint weights, and zero for a joint's equation
        near_reversal (rows.py) when Coulomb friction is identified and
        coulomb_exclusion_speed > 0."""
        if not self.coulomb or self.config.coulomb_exclusion_speed <= 0:
            return self._weights
        period = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        reach = 0.0 if self.smoothed_sign else period * float(self.half_window or 0)
        slow = near_reversal(qd, qdd, self.exclusion_speed, reach)
        self._excluded += np.count_nonzero(slow, axis=0)
        w = np.ones(qd.shape) if self._weights is None else np.tile(self._weights, (len(qd), 1))
        w[slow] = 0.0
        return w

    @property
    def excluded(self) -> np.ndarray:
        """(n,) per joint: equations left out near velocity reversals (rows gathered
        applied first)."""
        self.apply()
        return self._excluded

    @property
    def excluded_rows(self) -> int:
        """Joint equations left out near velocity reversals, all joints."""
        return int(self.excluded.sum())

    @property
    def numerical_failures(self) -> int:
        """Batches rolled back to the last finite state (rows gathered applied first)."""
        self.apply()
        return self._numerical_failures

    def model_term_warnings(self, joint_names: list[str], extras: tuple) -> list[str]:
        """model_terms.missing_term_warnings of the running estimate."""
        theta = self.rls.theta
        return missing_term_warnings(self.terms, theta, self.residuals.rss(theta),
                                     joint_names, extras)

    # -- results: every gathered row applied first ----------------------------------------------
    @property
    def rls(self) -> RecursiveLeastSquares:
        self.apply()
        return self._rls

    @property
    def residuals(self) -> ResidualStatistics:
        self.apply()
        return self._residuals

    @property
    def joint_scale(self) -> np.ndarray:
        """Per joint, the N m of a unit residual of the weighted rows: joint_noise_std when
        given, else 1 (n,)."""
        return np.ones(self.dof) if self._weights is None else self._weights ** -0.5

    def residual_rms(self) -> np.ndarray:
        """Per-joint RMS of the smoothed measured minus predicted torque (N m)."""
        return np.sqrt(self.residuals.variance(self.rls.theta)) * self.joint_scale

    def noise_variance(self) -> np.ndarray:
        """Per-joint variance of the weighted rows' residual the estimate averages
        (ResidualStatistics.noise_variance; (N m)^2 / joint_noise_std^2 when that is given):
        the covariance's and the convergence test's noise level."""
        return self.residuals.noise_variance(self.rls.theta, self._white_scale)

    def noise_std(self) -> np.ndarray:
        """Per-joint torque noise level the estimate averages (N m)."""
        return np.sqrt(self.noise_variance()) * self.joint_scale

    @property
    def covariance(self) -> np.ndarray:
        """The RLS covariance, whose noise level comes from the smoothed residuals, rescaled
        to their long-run variance."""
        var = self.residuals.variance(self.rls.theta)
        scale = (float(self.noise_variance().sum() / var.sum()) if np.nansum(var) > 0
                 else self._white_scale)
        return self.rls.covariance * scale

    def excitation(self) -> tuple[float, float]:
        """(condition number, smallest eigenvalue) of the information the data brought, without
        the forgetting regulariser."""
        information = self.rls.data_information
        if not np.isfinite(information).all():
            return math.inf, 0.0
        ev = np.linalg.eigvalsh(information)
        if ev[-1] <= 0:
            return math.inf, 0.0
        return (float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf), float(max(ev[0], 0.0))

    def converged(self, condition: float, covariance: np.ndarray) -> bool:
        r = self.residuals
        return converged(covariance, r.gram, r.count, self.noise_variance(),
                         self.rls.num_samples, condition, self.config)


def _state(obj: _T) -> _T:
    """A copy of ``obj`` to roll back to: its attributes, arrays copied (the estimators
    update some in place)."""
    saved = copy.copy(obj)
    for name, value in vars(obj).items():
        if isinstance(value, np.ndarray):
            setattr(saved, name, value.copy())
    return saved
