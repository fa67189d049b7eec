"""The identification pipeline: stamped joint states and currents in, base-parameter estimate
out, one stage per module (see the package doc)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Mapping, NamedTuple

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.model_terms import ModelTermStatistics
from identification_node.estimation.model_terms import features as model_features
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.estimation.prior import safe_prior
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.pipeline.config import PipelineConfig
from identification_node.pipeline.estimate import EstimateReport, OnlineEstimate
from identification_node.pipeline.rows import RowBuilder, smooths_sign
from identification_node.pipeline.status import PipelineStatus
from identification_node.pipeline.time_offset import TimeOffset, TimeOffsetCheck
from identification_node.pipeline.torque_samples import TorqueSamples
from identification_node.pipeline.window import SegmentWindow
from identification_node.wire.records import JointStateRecord


class InputSamples(NamedTuple):
    """The validated samples one ``process`` call took in, before the smoother: header
    stamps (int64 ns), q, qd (NaN where not measured) and the joint torque (each (N, n))."""
    stamps_ns: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray


@dataclass
class PipelineOutput:
    """Samples processed by one ``process`` call, stamped with their own header stamps
    (``stamps_ns``, int64 ns): smoothed q, qd, qdd, the smoothed measured torque and the
    torque predicted by the estimate before the call's update (each (N, n)); ``inputs``: the
    samples the call took in (not delayed by the smoother, nor held for its choice)."""
    stamps_ns: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    measured: np.ndarray
    predicted: np.ndarray
    inputs: InputSamples | None = None

    @classmethod
    def empty(cls, dof: int) -> PipelineOutput:
        z = np.empty((0, dof))
        return cls(np.empty(0, dtype=np.int64), z, z, z, z, z)


class IdentificationPipeline:
    """Identification of ``robot``'s base parameters from streamed samples: the input stages
    (TorqueSamples), the rows (RowBuilder) and the estimate (OnlineEstimate)."""

    def __init__(self, robot: RobotModel, config: PipelineConfig | None = None,
                 base: BaseParameters | None = None):
        self.robot = robot
        self.config = config or PipelineConfig()
        self.config.validate(robot.dof)
        unknown = set(self.config.torque) - set(robot.joint_names)
        if unknown:
            raise IdentificationError(f'torque sources name unknown joints {sorted(unknown)}')
        self.base = base or BaseParameters.from_robot(robot)
        self.samples = TorqueSamples(robot, self.config)
        self.converter = self.samples.converter
        c = self.config
        weights = (np.asarray(c.joint_noise_std, dtype=float) ** -2 if len(c.joint_noise_std)
                   else None)
        self.row_builder = RowBuilder(robot, self.base, c.half_window, c.smoother_order,
                                      c.max_gap, c.cutoff, c.auto_seconds, weights,
                                      c.coulomb_exclusion_speed)
        self.estimator = OnlineEstimate(self.base.num_base, robot.dof, c,
                                        'fc' in robot.extras, self.samples.counters.reject,
                                        smooths_sign(robot),
                                        robot.in_joint_units(c.coulomb_exclusion_speed))
        self.gate = self.estimator.gate    # robust.InnovationGate: listeners, events, counts
        # time_offset.TimeOffsetCheck: is the torque late or early against the motion?
        self.time_offset = TimeOffsetCheck(c.offset_warn, c.offset_refuse, c.offset_seconds,
                                           c.offset_search)
        self.bounds = self.samples.bounds  # plausibility.PlausibilityBounds
        # the model's parameters, degenerate inertials replaced (prior.py); notes say which
        self.prior, self.prior_notes = safe_prior(robot)
        self.frozen = False
        # the estimator's batch update left to update() (the node: after publishing the run's
        # outputs, which do not need it: they are predicted before it)
        self.defer_updates = False
        self._window: SegmentWindow | None = None
        self.reset()

    @property
    def window(self) -> SegmentWindow | None:
        """window.SegmentWindow: one time segment of the stream only (None: all of it); set
        before the first message (parallel replay and fleet). Its messages' rejections are
        counted here, its margins' by its neighbours."""
        return self._window

    @window.setter
    def window(self, window: SegmentWindow | None) -> None:
        self._window = window
        self.samples.counters.inside = None if window is None else window.keep

    # -- input: called on the ROS side, so nothing but a copy ------------------------------------
    def add_joint_state(self, record: JointStateRecord) -> None:
        if self.window is None or self.window.feed(record.stamp_ns):
            self.samples.add_joint_state(record)

    def add_joint_states(self, block: JointStateRecord) -> None:
        """Joint states sharing names and layout, at once: stamp_ns (M,) int64, position,
        velocity and effort (M, k) ((M, 0) when absent). The same as adding the M records
        one by one (bag replay reads such blocks)."""
        if self.window is not None:
            fed = self.window.feed(block.stamp_ns)
            if not fed.all():
                if not fed.any():
                    return
                block = type(block)(np.asarray(block.stamp_ns)[fed], block.names,
                                    *(np.asarray(a)[fed] for a in block[2:]))
        self.samples.add_joint_states(block)

    def add_joint_state_cdr(self, messages: list[bytes]) -> None:
        """sensor_msgs/JointState messages as CDR bytes, in arrival order (as the node takes
        them); decoded when processed (one that cannot be decoded is counted 'malformed')."""
        self._unwindowed('joint states')
        self.samples.add_joint_state_cdr(messages)

    def add_currents(self, record: JointStateRecord) -> None:
        if self.window is None or self.window.feed(record.stamp_ns):
            self.samples.add_currents(record)

    def add_currents_cdr(self, messages: list[bytes]) -> None:
        """Motor current messages (sensor_msgs/JointState) as CDR bytes, in arrival order."""
        self._unwindowed('currents')
        self.samples.add_currents_cdr(messages)

    def _unwindowed(self, what: str) -> None:
        if self.window is not None:   # their stamps are known only once decoded
            raise IdentificationError(f'a segment window takes decoded {what}, not CDR bytes')

    def add_malformed(self, log_ns: int | None = None) -> None:
        """Count a message that could not even be decoded (received, and rejected; in a
        segment window, by its log time ``log_ns`` as its stamp)."""
        if self.window is not None and log_ns is not None:
            self.window.feed(log_ns)   # counted in the window's messages when inside
        self.samples.add_malformed(log_ns)

    @property
    def pending(self) -> int:
        return self.samples.pending

    # -- counters ---------------------------------------------------------------------------------
    received = property(lambda self: self.samples.counters.received,
                        doc='joint state messages received')
    rejected = property(lambda self: self.samples.counters.rejected,
                        doc='rejected messages per reason (validate.REJECT_REASONS)')
    restarts = property(lambda self: self.samples.counters.restarts, doc='stream restarts')
    excluded_rows = property(lambda self: self.estimator.excluded_rows,
                             doc='joint equations left out near velocity reversals')
    excluded_equations = property(lambda self: self.estimator.excluded.copy(),
                                  doc='(n,) per joint: equations left out near reversals')
    epoch_ns = property(lambda self: self.samples.counters.epoch_ns,
                        doc='the first stamp (ns): time zero of the float stamps')
    velocity_measured = property(lambda self: self.samples.velocity_measured)
    numerical_failures = property(lambda self: self.estimator.numerical_failures,
                                  doc='estimator updates rolled back to the last finite state')
    smoother_edge = property(lambda self: self.row_builder.smoother_edge,
                             doc='valid samples the smoother never output (rows.RowBuilder)')
    layout_cache_bytes = property(
        lambda self: sum(v.cache.bytes for v in (self.samples.validate,
                                                 self.samples.validate_currents)),
        doc='estimated bytes of the decoded message layouts kept')

    # -- state ----------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the estimate and all buffered data; counters restart too."""
        self.samples.reset()
        self.row_builder.reset()
        self.row_builder.reset_counts()
        self.estimator.reset()
        self.time_offset.reset()
        self.used = 0
        self._restarts_seen = 0
        self._last_output_stamp = math.nan

    @property
    def smoother(self):
        """The smoother in use (rows.SmootherChoice: half window, cut-off, rate, delay, how
        it was set); None while the first samples are held back to choose it."""
        return self.row_builder.choice

    @property
    def choosing(self) -> bool:
        """Whether the smoother's choice is under way: ``process`` advances it even without
        new samples."""
        return self.row_builder.searching

    @property
    def delay(self) -> float:
        """Smoother delay in samples (NaN while it is being chosen); ``smoother.delay`` in
        seconds."""
        choice = self.row_builder.choice
        return math.nan if choice is None else float(choice.half_window)

    def live_clock(self, clock) -> None:
        """A live stream: joint states wait for their currents ``hold_time`` of ``clock``
        (a monotonic time in s) as well as of stamps (align.py)."""
        self.samples.alignment.clock = clock

    # -- processing -----------------------------------------------------------------------------
    def process(self, flush: bool = False) -> PipelineOutput:
        """Work through everything queued (a batch ``update`` left due first). ``flush``
        decides joint states still waiting for currents (end of a bag) instead of holding
        them for ``hold_time``."""
        self.update()
        s = self.samples.process(flush)
        outputs = []
        if self.samples.counters.restarts != self._restarts_seen:
            self._restarts_seen = self.samples.counters.restarts
            held = self.row_builder.drain(self.samples.velocity_measured)
            if held is not None:     # the samples the smoother's choice waited for
                outputs.append(self._use(held))
            self.row_builder.reset()
            self.estimator.end_stream()
            self.time_offset.restart()
        if len(s) or flush or self.row_builder.searching:
            est = self.estimator
            outputs.append(self._use(self.row_builder(
                s, self.samples.velocity_measured,
                self.config.update_batch if est.batch_due and not outputs else None, flush)))
        if flush:
            self.time_offset.finish()
        outputs = [o for o in outputs if len(o.stamps_ns)]
        if not outputs:
            result = PipelineOutput.empty(self.robot.dof)
        elif len(outputs) == 1:
            result = outputs[0]
        else:
            stamps_ns, q, qd, qdd, measured, predicted = (np.concatenate(a) for a in zip(*(
                (o.stamps_ns, o.q, o.qd, o.qdd, o.measured, o.predicted) for o in outputs)))
            result = PipelineOutput(stamps_ns, q, qd, qdd, measured, predicted)
        if len(s):
            assert s.tau is not None   # the input stages give samples with their torques
            result.inputs = InputSamples(self.samples.counters.stamps_ns(s.stamps), s.q, s.qd,
                                         s.tau)
        return result

    def update(self) -> None:
        """The estimator's update of a full batch, if one is gathered (what ``process`` leaves
        with ``defer_updates``; the next ``process`` does it first)."""
        self.estimator.apply_due()

    def _use(self, r) -> PipelineOutput:
        """Rows (rows.Rows) checked, predicted and given to the estimator."""
        est = self.estimator
        half_window = self.row_builder.half_window   # None while the smoother is chosen
        if half_window is not None and est.half_window != half_window:
            est.set_smoother(half_window, self.config.smoother_order)
        if len(r.t) == 0:
            return PipelineOutput.empty(self.robot.dof)
        stamps_ns = self.samples.counters.stamps_ns(r.t)
        predicted = r.rows[:, :, :self.base.num_base] @ est.theta
        # the smoothed motion and torque within bounds too (accelerations are checked here
        # only; a spike that passed the raw gates spreads over the smoothing window)
        keep = self.bounds.ok(r.q, r.qd, r.qdd, r.tau) & np.isfinite(predicted).all(axis=1)
        implausible = ~keep
        if self.window is not None:   # a segment's rows only: the others are its neighbours'
            inside = self.window.keep(stamps_ns)
            keep &= inside
            implausible &= inside
        if implausible.any():
            self.samples.counters.reject('implausible', np.count_nonzero(implausible))
        if not keep.all():
            r = type(r)(*(a[keep] for a in r))
            predicted, stamps_ns = predicted[keep], stamps_ns[keep]
            if len(r.t) == 0:
                return PipelineOutput.empty(self.robot.dof)
        if self.time_offset.active:
            self.time_offset.add(r.t, r.rows[:, :, :self.base.num_base], r.tau,
                                 model_features(r.q, r.qd)[..., :3])
        if not self.frozen:
            est.add(r.rows, r.t, r.qd, r.qdd, stamps_ns, q=r.q, defer=self.defer_updates)
            self.used += len(r.t)
        self._last_output_stamp = float(stamps_ns[-1]) * 1e-9
        return PipelineOutput(stamps_ns, r.q, r.qd, r.qdd, r.tau, predicted)

    def restore(self, rls: RecursiveLeastSquares, residuals: ResidualStatistics,
                used: int, received: int = 0, rejected: Mapping[str, int] | None = None,
                excluded: np.ndarray | None = None, restarts: int = 0,
                last_stamp_ns: int | None = None, terms: ModelTermStatistics | None = None,
                time_offset: TimeOffset | None = None) -> None:
        """Take the sufficient statistics of processed data (e.g. merged over many bags,
        fleet.py): the estimate, covariance, noise and convergence then follow exactly as
        for data streamed in, and so do the warnings of equations left out per joint
        (``excluded`` (n,)), of missing model terms (``terms``) and of the torque's time offset
        (``time_offset``, the check's result). Nothing stays queued; the counters are the
        given ones."""
        if (rls.num_params, residuals.p, residuals.n) != (
                self.base.num_base, self.base.num_base, self.robot.dof):
            raise IdentificationError('statistics of another robot or parameter set')
        self.reset()
        self.estimator.restore(rls, residuals, excluded, terms)
        self.time_offset.result = time_offset
        counters = self.samples.counters
        counters.received, counters.restarts = int(received), int(restarts)
        counters.rejected.update(rejected or {})
        self.used, self._restarts_seen = int(used), int(restarts)
        if last_stamp_ns is not None:
            self._last_output_stamp = float(last_stamp_ns) * 1e-9

    # -- results --------------------------------------------------------------------------------
    @property
    def rls(self) -> RecursiveLeastSquares:
        """The recursive estimator, up to date with every processed sample."""
        return self.estimator.rls

    @property
    def residuals(self) -> ResidualStatistics:
        """Residual statistics, up to date with every processed sample."""
        return self.estimator.residuals

    def residual_rms(self) -> np.ndarray:
        """Per-joint RMS of the smoothed measured minus predicted torque over the samples
        used, for the current estimate (N m)."""
        return self.estimator.residual_rms()

    def relative_error(self, theta: np.ndarray | None = None) -> np.ndarray:
        """Per-joint 100 ||tau - Yb theta|| / ||tau|| (percent) over the samples used, for
        ``theta`` (default: the current estimate)."""
        return self.residuals.relative_error(self.rls.theta if theta is None else theta)

    def noise_variance(self) -> np.ndarray:
        """Per-joint noise level of the weighted rows' residual (OnlineEstimate.noise_variance):
        what the covariance is scaled by."""
        return self.estimator.noise_variance()

    def noise_std(self) -> np.ndarray:
        """Per-joint torque noise level the estimate averages (N m)."""
        return self.estimator.noise_std()

    def model_term_warnings(self) -> list[str]:
        """Joints whose residual correlates with sign(qd), qd or q (model_terms.py): the
        likely missing term named."""
        return self.estimator.model_term_warnings(self.robot.joint_names, self.robot.extras)

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of the base estimate (see OnlineEstimate.covariance)."""
        return self.estimator.covariance

    @property
    def stddev(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    def excitation(self) -> tuple[float, float]:
        """(condition number, smallest eigenvalue) of the information the data brought."""
        return self.estimator.excitation()

    def converged(self) -> bool:
        """Excited, enough samples, and the parameter uncertainty contributes less than
        ``converged_ratio`` of the torque noise on every joint."""
        return self.estimator.converged(self.excitation()[0], self.covariance)

    def estimate(self) -> EstimateReport:
        """A snapshot of the running estimate."""
        cond, min_eig = self.excitation()
        cov = self.covariance
        rls = self.rls
        return EstimateReport(
            names=list(self.base.names), values=rls.theta.copy(),
            stddev=np.sqrt(np.diag(cov)), num_samples=int(rls.num_samples),
            stamp=self._last_output_stamp, condition_number=cond, min_eigenvalue=min_eig,
            residual_rms=self.residual_rms(),
            converged=self.estimator.converged(cond, cov), frozen=self.frozen)

    def status(self) -> PipelineStatus:
        """A snapshot of the estimate, counters and stage states (pipeline/status.py)."""
        gate, counters = self.gate, self.samples.counters
        choice = self.smoother
        return PipelineStatus(
            estimate=self.estimate(), received=self.received, used=self.used,
            restarts=self.restarts, rejected=dict(self.rejected),
            gate_enabled=bool(gate.settings.enabled), gate_armed=bool(gate.armed),
            gate_suspended=bool(gate.suspended), residual_shifts=gate.shifts,
            numerical_failures=self.numerical_failures, smoother_edge=self.smoother_edge,
            layout_cache_bytes=self.layout_cache_bytes,
            excluded_equations=self.excluded_equations,
            model_term_warnings=self.model_term_warnings(),
            missing_joints=sorted(counters.missing_joints | counters.missing_current_joints),
            time_offset=self.time_offset.result,
            smoother=None if choice is None else replace(choice),
            holding=self.row_builder.holding)

    def standard_parameters(self) -> np.ndarray:
        """The full standard parameter vector closest to the model's own that reproduces the
        base estimate (for the identified URDF)."""
        return self.base.closest_standard(self.rls.theta, self.prior)
