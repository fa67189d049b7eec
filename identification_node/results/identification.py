"""An identification's outcome (Identification), whichever the method, with its history
(Checkpoint) and a bounded torque series (TorqueSeries, SeriesSampler). Units SI;
stamps int64 ns."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from identification_node.estimation.consistency import (ConsistencyOptions, ConsistentEstimate,
                                                        ConsistentSolver, pipeline_equations)
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.estimation.prior import safe_prior
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.model.identifiability import BaseParameters, unexcited_directions
from identification_node.model.robot import RobotModel
from identification_node.model.urdf_export import consistency_problems
from identification_node.pipeline import IdentificationPipeline
from identification_node.pipeline.time_offset import TimeOffset

__all__ = ['Checkpoint', 'ReplayResult', 'SERIES_POINTS', 'TorqueSeries', 'SeriesSampler',
           'Identification', 'from_replay', 'exclusion_warnings', 'make_consistent']


@dataclass
class Checkpoint:
    """The running estimate after ``num_samples`` samples (for convergence plots)."""
    num_samples: int
    stamp: float
    values: np.ndarray
    stddev: np.ndarray


@dataclass
class ReplayResult:
    """The pipeline after the whole bag, and the estimate's history."""
    bag: str
    pipeline: IdentificationPipeline
    messages: int
    history: list[Checkpoint] = field(default_factory=list)


SERIES_POINTS = 4000      # samples kept for the torque plots


# -- series for plots ---------------------------------------------------------------------------
@dataclass
class TorqueSeries:
    """An evenly strided subsample of processed rows: stamps (N,) int64 ns, measured torque
    (N, n) and base regressor rows (N, n, b), so that predicted = regressor @ theta;
    ``origin_ns``: the bag's first sample (time zero of plots); ``q`` (N, n): the rows'
    positions (rad, m) when kept."""
    stamps_ns: np.ndarray
    measured: np.ndarray
    regressor: np.ndarray
    origin_ns: int | None = None
    q: np.ndarray | None = None

    def predicted(self, theta: np.ndarray) -> np.ndarray:
        return self.regressor @ np.asarray(theta, dtype=float)


class SeriesSampler:
    """Keeps every ``stride``-th row added, doubling the stride (and dropping every other kept
    row) when more than ``capacity`` are kept: bounded memory, evenly spread rows."""

    def __init__(self, capacity: int = SERIES_POINTS):
        self.capacity = max(2, int(capacity))
        self.stride = 1
        self.count = 0
        self._index = np.zeros(0, dtype=np.int64)
        self._arrays: dict[str, np.ndarray] = {}

    def add(self, **arrays: np.ndarray) -> None:
        m = len(next(iter(arrays.values())))
        idx = self.count + np.arange(m)
        keep = idx % self.stride == 0
        self.count += m
        if not keep.any():
            return
        self._index = np.concatenate([self._index, idx[keep]])
        for k, v in arrays.items():
            v = np.asarray(v)[keep]
            self._arrays[k] = v if k not in self._arrays else np.concatenate([self._arrays[k], v])
        while len(self._index) > self.capacity:
            self.stride *= 2
            sel = self._index % self.stride == 0
            self._index = self._index[sel]
            self._arrays = {k: v[sel] for k, v in self._arrays.items()}

    def arrays(self) -> dict[str, np.ndarray]:
        return dict(self._arrays)


# -- the outcome of an identification, whichever the method --------------------------------------
@dataclass
class Identification:
    """An identification's outcome: the base estimate theta with its covariance (SI units of the
    base parameters), the residual sums of the rows fitted (relative error for any theta), the
    per-joint torque noise variance (N m)^2, the estimate's history and a torque series."""
    bag: str
    method: str                      # 'rls' or 'batch'
    processing: str                  # 'smoothed', 'filtered' or 'periodic'
    robot: RobotModel
    base: BaseParameters
    theta: np.ndarray
    covariance: np.ndarray
    num_samples: int                 # samples used (before filtering or averaging)
    messages: int
    rejected: dict
    condition_number: float
    residuals: ResidualStatistics
    noise_variance: np.ndarray       # per joint, of the torque noise the fit averages (N m)^2
    converged: bool
    history: list[Checkpoint] = field(default_factory=list)
    series: TorqueSeries | None = None
    details: dict = field(default_factory=dict)
    pipeline: IdentificationPipeline | None = None
    # the information fitted and its per-joint weights (the WLS objective), for the
    # constrained solve; its outcome (make_consistent)
    fit_equations: NormalEquations | None = None
    fit_weights: np.ndarray | float = 1.0
    consistent: ConsistentEstimate | None = None
    # what the user should know: a missing model term (model_terms.py), locked joints
    warnings: list[str] = field(default_factory=list)
    # per joint, the N m of a unit residual of ``residuals``' rows (weighted rows: their
    # joint_noise_std)
    residual_scale: np.ndarray | float = 1.0
    # the torque's offset against the motion (pipeline/time_offset.py), None: not estimated
    time_offset: TimeOffset | None = None

    @property
    def estimate(self) -> np.ndarray:
        """The estimate published: the consistent one when solved, else theta (unconstrained)."""
        c = self.consistent
        # c.ok: c.phi and c.theta are set
        return c.theta if c is not None and c.ok and c.theta is not None else self.theta

    @property
    def stddev(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def rel_stddev(self) -> np.ndarray:
        """100 stddev / |theta| (percent; inf where theta is 0)."""
        with np.errstate(divide='ignore', invalid='ignore'):
            return np.where(self.theta == 0, np.inf, 100 * self.stddev / np.abs(self.theta))

    @property
    def unexcited(self) -> list[tuple[str, list[str]]]:
        """The base-parameter directions the data do not determine (identifiability.
        unexcited_directions of the rows fitted; empty when the motion excites them all)."""
        limit = self.pipeline.config.max_condition if self.pipeline is not None else 1e8
        return unexcited_directions(self.residuals.gram.sum(axis=0), self.base.names, limit)

    @property
    def theta_model(self) -> np.ndarray:
        """The base parameters of the robot description's own (URDF/CAD) parameters."""
        return self.base.to_base(self.robot.phi_model)

    def relative_error(self, theta: np.ndarray | None = None) -> np.ndarray:
        """Per-joint 100 ||tau - Yb theta|| / ||tau|| over the rows fitted (percent)."""
        return self.residuals.relative_error(self.theta if theta is None else theta)

    @property
    def residual_rms(self) -> np.ndarray:
        """Per-joint RMS of the fitted rows' torque residual (N m)."""
        return np.sqrt(self.residuals.variance(self.theta)) * self.residual_scale

    def standard_parameters(self) -> np.ndarray:
        """The consistent full parameter vector when solved, else the one closest to the
        model's that reproduces theta."""
        c = self.consistent
        if c is not None and c.phi is not None:    # c.ok
            return c.phi
        return self.base.closest_standard(self.theta, safe_prior(self.robot)[0])

    def consistency_problems(self) -> list[str]:
        return consistency_problems(self.robot, self.standard_parameters())


def from_replay(result: ReplayResult, series: TorqueSeries | None = None) -> Identification:
    """The Identification of a streamed replay (replay.ReplayResult)."""
    p = result.pipeline
    est = p.estimate()
    offset = p.time_offset.result   # the torque against the motion (time_offset.py)
    return Identification(
        result.bag, 'rls', 'smoothed', p.robot, p.base, est.values, p.covariance,
        est.num_samples, result.messages, {k: v for k, v in p.rejected.items() if v},
        est.condition_number, p.residuals, p.noise_std() ** 2, est.converged,
        list(result.history), series,
        {'processing': 'smoothed',
         'smoother_half_window': None if p.smoother is None else p.smoother.half_window,
         'smoother_order': int(p.config.smoother_order),
         'smoother': None if p.smoother is None else p.smoother.document(),
         'forgetting_factor': float(p.config.forgetting),
         'excluded_equations': p.excluded_rows,
         'excluded_per_joint': dict(zip(p.robot.joint_names,
                                        p.excluded_equations.tolist())),
         'time_offset': None if offset is None else offset.document()}, p,
        *pipeline_equations(p),
        warnings=([offset.describe()] if offset is not None and offset.level else [])
        + exclusion_warnings(p.robot, p.excluded_equations, p.used,
                             p.config.coulomb_exclusion_speed)
        + p.model_term_warnings(), residual_scale=p.estimator.joint_scale, time_offset=offset)


def exclusion_warnings(robot: RobotModel, excluded: np.ndarray, total: int, speed: float,
                       most: float = 0.5) -> list[str]:
    """Warnings for the joints of which more than ``most`` of the ``total`` equations were
    left out near velocity reversals (``excluded`` (n,)) by coulomb_exclusion_speed
    ``speed`` (rad/s; RobotModel.in_joint_units per joint)."""
    share = np.asarray(excluded, dtype=float) / max(int(total), 1)
    speeds = robot.in_joint_units(speed)
    return [f'{j}: {100 * f:.0f} % of its equations left out near velocity reversals '
            f'(|qd| < {s:g} {"m/s" if p else "rad/s"}, coulomb_exclusion_speed {speed:g}'
            f'{" / 10 for a prismatic joint" if p else ""}): a slow joint; lower '
            'coulomb_exclusion_speed or set it to 0'
            for j, f, s, p in zip(robot.joint_names, share, speeds, robot.prismatic) if f > most]


def make_consistent(ident: Identification, options: ConsistencyOptions | None,
                    solver: ConsistentSolver | None = None) -> Identification:
    """``ident`` with its constrained solve (consistency.py) on the information it fitted,
    with the same weights; unchanged when ``options`` is None (physical_consistency off).
    ``solver``: ConsistentSolver.for_robot of this robot, base and ``options``, made once for
    many solves (its problem is canonicalised once: a warm solve costs a tenth of a cold).
    """
    if options is not None and ident.fit_equations is not None:
        solver = solver or ConsistentSolver.for_robot(ident.robot, ident.base, options)
        ident.consistent = solver.solve(ident.fit_equations, ident.fit_weights)
    return ident
