"""The identification node: ``ros2 run identification_node identification_node``.

Subscribes to ``joint_states`` and, when a joint's torque comes from motor currents, to
``motor_currents`` (sensor_msgs/JointState; channels ``<joint>/ia|ib|ic`` or ``<joint>/i``,
amperes in effort, optional electrical angle in position). A processing thread of its own
takes the queued input messages every ``process_period`` (wall clock), copies them into the
pipeline, runs it on them in one batch and publishes (the effort topics only while they have
subscribers):

- ``~/predicted_effort``, ``~/measured_effort`` (JointState, stamped with the sample's stamp),
- ``~/base_parameters`` (Float64MultiArray: row 0 values, row 1 standard deviations, row 2
  the unconstrained values; row 0 is the physically consistent estimate unless
  ``physical_consistency`` is false, then rows 0 and 2 agree),
- ``~/robot_description`` (String, transient local: URDF with the consistent inertials),
- ``/diagnostics`` (counters, with ``lost_messages.<topic>``: input messages lost before the
  node took them, e.g. its queue overflowing while processing stalled, or dropped packets);

exposes ``estimate.<name>`` / ``estimate_stddev.<name>`` / ``estimate_unconstrained.<name>``
parameters (read-only from outside) and the services ``~/reset``, ``~/freeze``, ``~/save``,
``~/get_estimate``, served by a thread of their own (service_requests.py): commands are applied
in order by the processing thread and answered once the estimate after them is published;
``~/get_estimate`` answers from the newest published estimate (refreshed at
``publish.estimate_rate`` and after every command). The constrained solve (consistency.py)
runs at every estimate refresh in a child process (SolverProcess), on a snapshot of the
pipeline's information taken on the processing thread. With
``payload.enabled`` (ros/payload_outputs.py): ``~/payload`` (InertiaStamped, transient
local), ``~/payload_changed`` (Header: the change's stamp, frame_id the payload link), the
services ``~/payload/reset`` and ``~/payload/set``, and the payload in diagnostics, in
``~/robot_description`` and in what ``~/save`` writes.
"""
from __future__ import annotations

import collections
import copy
import functools
import json
import math
import sys
import threading
import time
import traceback
from typing import Any, Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String
from std_srvs.srv import SetBool, Trigger

from identification_node.config import PARAMETERS, descriptor
from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import (ConsistentEstimate, SolverProcess,
                                                        pipeline_equations)
from identification_node.model.urdf_export import consistency_problems, identified_urdf
from identification_node.results.documents import plain, snapshot_document, write_results
from identification_node.payload.fit import urdf_with_payload
from identification_node.pipeline import EstimateReport, PipelineOutput
from identification_node.ros.conversions import PolledSubscription, publish_joint_states
from identification_node.ros.diagnostics import SMOOTHER_SOURCES, key_values, vector
from identification_node.ros.drive_gains import COMMAND as DRIVE_GAIN_COMMAND
from identification_node.ros.drive_gains import DriveGainOutputs
from identification_node.ros.link_outputs import LinkOutputs
from identification_node.ros import runtime_parameters
from identification_node.ros.payload_outputs import PayloadOutputs
from identification_node.ros.runtime_parameters import RUNTIME
from identification_node.ros.qos_watch import QosWatch
from identification_node.ros.service_requests import (Commands, Outcome, RequestQueue,
                                                      ServiceThread, Snapshot, failed)
from identification_node.ros.spin import PeriodicThread, run_node
from identification_node.settings import Settings

# Deep enough for a 1 s burst at 1 kHz; best effort like other sensor streams.
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                       reliability=ReliabilityPolicy.BEST_EFFORT)
OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                        reliability=ReliabilityPolicy.RELIABLE)
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
ESTIMATE_PREFIX, STDDEV_PREFIX = 'estimate.', 'estimate_stddev.'
UNCONSTRAINED_PREFIX = 'estimate_unconstrained.'
# Whether the effort topics have subscribers is asked this often (s), not every run (it is a
# middleware query): a new subscriber may miss the efforts of its first ~0.1 s.
LISTENER_CHECK_PERIOD = 0.1
SHUTDOWN_WAIT = 0.3   # s a shutdown waits for a processing run in progress


_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}
_ARRAY_TYPES = {bool: Parameter.Type.BOOL_ARRAY, int: Parameter.Type.INTEGER_ARRAY,
                float: Parameter.Type.DOUBLE_ARRAY, str: Parameter.Type.STRING_ARRAY}


def parameter_descriptor(name: str, default: Any, text: str) -> ParameterDescriptor:
    """The rclpy descriptor of a settings table entry: config.descriptor's type and range,
    read-only unless runtime_parameters.RUNTIME has it."""
    spec = descriptor(name, default, text)
    d = ParameterDescriptor(description=spec.description, read_only=name not in RUNTIME)
    if spec.type is None:
        d.dynamic_typing = True
    elif spec.array:
        d.type = _ARRAY_TYPES[spec.type].value
    else:
        d.type = _TYPES[spec.type]
    if spec.range is not None and spec.type is int:
        d.integer_range = [IntegerRange(from_value=int(spec.range[0]),
                                        to_value=int(spec.range[1]), step=0)]
    elif spec.range is not None:
        d.floating_point_range = [FloatingPointRange(from_value=spec.range[0],
                                                     to_value=spec.range[1], step=0.0)]
    return d


def declare_settings(node: Node, table: dict[str, tuple[Any, str]]) -> dict[str, Any]:
    """Declare every parameter of ``table`` (name: (default, description)) read-only, typed
    and ranged (parameter_descriptor; Settings validates the rest), and return those given;
    lists with an empty default stay unset unless given; a list given as [] is []. A value
    rclpy refuses (type, range) raises IdentificationError naming the parameter."""
    values = {}
    for name, (default, text) in table.items():
        descriptor = parameter_descriptor(name, default, text)
        initial = None if isinstance(default, list) and not default else default
        try:
            value = node.declare_parameter(name, initial, descriptor).value
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            raise IdentificationError(f'parameter {name}: {exc}') from None
        if value is not None:
            values[name] = list(value) if isinstance(value, (list, tuple)) or hasattr(
                value, 'typecode') else value
        elif initial is not None and isinstance(default, list):
            values[name] = []   # given as [] (rcl leaves an empty list's type unset)
    return values


def smoother_text(choice) -> str:
    """The smoother in use (rows.SmootherChoice) in words: cut-off, window, delay."""
    rate = f'{choice.rate:.6g} Hz' if choice.rate > 0 else 'a rate not known yet'
    delay = f'{1e3 * choice.delay:.1f} ms' if choice.rate > 0 else f'{choice.half_window} samples'
    cutoff = f'cut-off {choice.cutoff:.3g} Hz' if choice.rate > 0 else 'cut-off not known yet'
    source = SMOOTHER_SOURCES.get(choice.source, choice.source)
    return (f'{cutoff} ({source}), half window {choice.half_window} samples at {rate}, '
            f'delay of ~/predicted_effort {delay}')


def smoother_values(choice, holding: int) -> dict[str, Any]:
    """The diagnostics of the smoother (rows.SmootherChoice, None while being chosen)."""
    if choice is None:
        return {'smoother': f'being chosen ({holding} samples held back)',
                'smoother_delay_samples': None}
    return {'smoother': SMOOTHER_SOURCES.get(choice.source, choice.source),
            'smoother_delay_samples': choice.half_window, 'smoother_delay_ms': 1e3 * choice.delay,
            'smoother_cutoff_hz': choice.cutoff, 'smoother_order': choice.order}


class IdentificationNode(Node):
    """Wires the ROS interfaces to an IdentificationPipeline; no numerics of its own."""

    def __init__(self, node_name: str = 'identification_node', **kwargs: Any):
        super().__init__(node_name, **kwargs)
        self.settings = Settings.from_dict(declare_settings(self, PARAMETERS))
        self.pipeline = self.settings.build()
        self.pipeline.live_clock(time.monotonic)   # topics are not delivered in step
        self.robot = self.pipeline.robot
        base = self.pipeline.base
        self._internal_update = False
        self._declare_estimate_parameters(base.names)
        self.add_on_set_parameters_callback(self._refuse_external_estimate_writes)
        self.add_on_set_parameters_callback(self._validate_runtime_parameters)
        self.add_post_set_parameters_callback(self._apply_runtime_parameters)
        self.callback_errors: collections.Counter = collections.Counter()
        self._closing = False
        # Services on a thread of their own, answered from snapshots (service_requests.py).
        self._requests = RequestQueue()
        self._service_thread = ServiceThread(self, self._on_service_error)
        # before the inputs: its start-up (cvxpy) takes seconds
        self.payload = (PayloadOutputs(self, self.settings, self.pipeline, self._service_thread,
                                       self._requests)
                        if self.settings['payload.enabled'] else None)

        self.watchdog_timeout = self.settings['watchdog_timeout']
        self.pipeline.gate.listeners.append(self._on_residual_shift)
        handlers = (self.pipeline.add_joint_state_cdr, self.pipeline.add_currents_cdr)
        self.drive_gains = None
        if self.settings['drive_gains.back_emf'] or self.settings['drive_gains.known_payload']:
            self.drive_gains = DriveGainOutputs(self, self.settings, self.pipeline,
                                                self._service_thread, self._requests)
            handlers = self.drive_gains.tee(*handlers)
        self._inputs = [self._subscribe('joint_states', handlers[0])]
        if self.pipeline.converter.needs_currents:
            self._inputs.append(self._subscribe('motor_currents', handlers[1]))
        if self.drive_gains is not None and self.drive_gains.voltages is not None:
            self._inputs.append(self.drive_gains.voltages)
        self._pub_predicted = self.create_publisher(JointState, '~/predicted_effort', OUTPUT_QOS)
        self._pub_measured = self.create_publisher(JointState, '~/measured_effort', OUTPUT_QOS)
        self._pub_params = self.create_publisher(Float64MultiArray, '~/base_parameters', 10)
        self._pub_urdf = self.create_publisher(String, '~/robot_description', LATCHED_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.links = LinkOutputs(self, self.robot)
        self._qos_watch = QosWatch(self)   # checked with the clock, every second
        self._qos_watch.watch(*(i.subscription for i in self._inputs), self._pub_predicted,
                              self._pub_measured, self._pub_params, self._pub_urdf)
        self._service_thread.add(Trigger, '~/reset', self._srv_reset)
        self._service_thread.add(SetBool, '~/freeze', self._srv_freeze)
        self._service_thread.add(Trigger, '~/save', self._srv_save)
        self._service_thread.add(Trigger, '~/get_estimate', self._srv_get_estimate)

        s = self.settings
        self._effort_rate = s['publish.effort_rate']
        self._last_effort_slot = -1
        self._effort_listened = (False, False)   # (predicted, measured), checked at most
        self._listeners_checked = -math.inf      # every LISTENER_CHECK_PERIOD s
        self._consistency: list[str] = []
        self._urdf_samples = 0
        # The constrained solve: built on first use, run by the worker (or a service) under
        # its own lock, never under the processing lock.
        self._consistency_options = s.consistency_options()
        self._solver: SolverProcess | None = None
        self._solver_lock = threading.Lock()
        self._publish_lock = threading.Lock()
        self._consistent: ConsistentEstimate | None = None
        self._solver_failure: str = ''
        self._jobs: list[Snapshot] = []     # taken by the worker in order
        self._job_ready = threading.Condition()
        self._worker_running = True
        if self._consistency_options is not None:
            try:   # spawned here, on the main thread, so that Ctrl-C spares it (SolverProcess)
                self._solver_instance()
            except Exception as exc:  # noqa: BLE001 - reported by the first solve again
                self.get_logger().error(f'physical consistency solver: {exc}')
        self._worker = threading.Thread(target=self._consistency_worker,
                                        name='identification_consistency', daemon=True)
        self._worker.start()
        self._received_at_last_diag = 0
        self._last_diag_time = self.get_clock().now()
        self.create_timer(1.0 / s['publish.estimate_rate'], self._guarded(self.refresh_estimate))
        self.create_timer(1.0 / s['publish.diagnostics_rate'],
                          self._guarded(self._publish_diagnostics))
        # The pipeline is shared by the processing thread and the executor's callbacks.
        self._lock = threading.Lock()
        self._processing = PeriodicThread(s['process_period'], self._process,
                                          'identification_processing',
                                          self._on_processing_error, alive=self.context.ok)
        # The middleware's queues emptied even while a processing run takes long (their
        # bound is a count; the node's own is in bytes: input_queue_bytes).
        self._receiving = PeriodicThread(s['process_period'], self._receive,
                                         'identification_receive', self._on_processing_error,
                                         alive=self.context.ok)
        # Wall clock: with use_sim_time and no /clock the node's timers stand still.
        self._ros_now = (-1, 0)     # (last ROS time seen, checks it stood still)
        self._clock_check = PeriodicThread(1.0, self._periodic_checks, 'identification_clock',
                                           self._on_processing_error, alive=self.context.ok)
        self._service_thread.start()
        for note in self.pipeline.prior_notes:
            self.get_logger().warning(note)
        self.get_logger().info(
            f'identifying {base.num_base} base parameters of {self.robot.name} '
            f'(joints {", ".join(self.robot.joint_names)}); smoother: '
            + (smoother_text(self.pipeline.smoother) if self.pipeline.smoother is not None
               else 'cut-off ' + (f"{s['smoother.cutoff']:g} Hz" if s['smoother.cutoff'] > 0
                                  else f"to be chosen from the first "
                                  f"{s['smoother.auto_seconds']:g} s of motion")))

    def _subscribe(self, topic: str, handle: Callable[[list[bytes]], None]) -> PolledSubscription:
        # A copy each: the QoS override parameters are applied to the profile in place.
        overrides = QoSOverridingOptions.with_default_policies()
        return PolledSubscription(
            self, JointState, topic, handle, copy.copy(INPUT_QOS),
            message_lost_event=self.settings['lost_messages.middleware_event'],
            max_bytes=self.settings['input_queue_bytes'],
            qos_overriding_options=overrides)

    # -- robustness -------------------------------------------------------------------------------
    def _guarded(self, callback: Callable) -> Callable:
        """``callback`` (a timer's) that never raises: a failure is counted (diagnostics
        ``callback_errors``) and logged in one line."""
        name = callback.__name__.lstrip('_')

        @functools.wraps(callback)
        def guarded(*args: Any) -> Any:
            try:
                return callback(*args)
            except Exception as exc:   # noqa: BLE001 - counted and logged, never raised
                self.callback_errors[name] += 1
                text = f'{name} failed: {type(exc).__name__}: {exc}'
                self.get_logger().error(text, throttle_duration_sec=5.0)
                return None
        return guarded

    def _on_service_error(self, name: str, exc: BaseException) -> None:
        key = 'srv_' + name.lstrip('~/').replace('/', '_')
        self.callback_errors[key] += 1
        self.get_logger().error(f'{key} failed: {type(exc).__name__}: {exc}',
                                throttle_duration_sec=5.0)

    def heartbeats(self) -> dict[str, Callable[[], float]]:
        """What the watchdog watches besides the executor (spin.Watchdog)."""
        return {'the processing thread': lambda: self._processing.beat}

    def _on_residual_shift(self, event: Any) -> None:
        self.get_logger().warning(
            f'residual shift: {100 * event.fraction:.0f} % of the last {event.window} samples '
            'beyond the robust gate of the estimate (a payload change?); gating stopped, the '
            'estimate follows the new data')

    def _periodic_checks(self) -> None:
        self._qos_watch.check()
        self._check_clock()

    def _check_clock(self) -> None:
        """Warn when use_sim_time is on but ROS time stands still (no /clock): the estimate
        and diagnostics timers then stop."""
        if not self.get_parameter('use_sim_time').value:
            self._ros_now = (-1, 0)
            return
        now = self.get_clock().now().nanoseconds
        still = self._ros_now[1] + 1 if now == self._ros_now[0] else 0
        self._ros_now = (now, still)
        if still == 3:
            self.get_logger().warning(
                'use_sim_time is true but ROS time has not advanced for 3 s (nothing on '
                '/clock?): the estimate, robot_description and diagnostics timers are stopped '
                'until it does; processing goes on')

    # -- parameters -------------------------------------------------------------------------------
    def _declare_estimate_parameters(self, names: list[str]) -> None:
        self._estimate_names = {'base_parameter_names'}
        self.declare_parameter('base_parameter_names', list(names), ParameterDescriptor(
            description='base parameter names, in the order of ~/base_parameters'))
        for name in names:
            for prefix, text in ((ESTIMATE_PREFIX, 'estimate'), (STDDEV_PREFIX, 'stddev'),
                                 (UNCONSTRAINED_PREFIX, 'unconstrained estimate')):
                self.declare_parameter(prefix + name, 0.0, ParameterDescriptor(
                    description=f'{text} of base parameter {name} (SI units)'))
                self._estimate_names.add(prefix + name)

    def _refuse_external_estimate_writes(self, params: list[Parameter]) -> SetParametersResult:
        if not self._internal_update:
            for p in params:
                if p.name in self._estimate_names:
                    return SetParametersResult(
                        successful=False,
                        reason=f'{p.name} is an output of the node; it cannot be set')
        return SetParametersResult(successful=True)

    def _validate_runtime_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """A run-time change of a RUNTIME setting, validated as at start-up."""
        changes = {p.name: p.value for p in params if p.name in RUNTIME}
        if changes:
            try:
                runtime_parameters.validated(self.settings, changes, self.robot)
            except IdentificationError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_runtime_parameters(self, params: list[Parameter]) -> None:
        changes = {p.name: p.value for p in params if p.name in RUNTIME}
        if changes:
            with self._lock:
                self.settings = runtime_parameters.validated(self.settings, changes, self.robot)
                runtime_parameters.apply(self.pipeline, self.payload.monitor if self.payload
                                         else None, changes)
            text = ', '.join(f'{k} = {v}' for k, v in changes.items())
            self.get_logger().info(f'set {text}')

    # -- processing and output --------------------------------------------------------------------
    # The processing thread takes the queued input messages (PolledSubscription) as CDR bytes
    # and hands them to the pipeline as they are (it decodes them in blocks):
    # rclpy never turns them into Python message objects.
    def _process(self) -> None:
        commands = self._requests.take()
        with self._lock:
            jobs = self._apply(commands) if commands is not None else []
            for source in self._inputs:
                source.poll()
            idle = not self.pipeline.pending and not self.pipeline.choosing
            if not idle:
                chosen = self.pipeline.smoother is not None
                out = self.pipeline.process()
                events = self.payload.add(out) if self.payload is not None else ()
                if self.drive_gains is not None:
                    self.drive_gains.process(out)
        self._submit(jobs)
        if idle:
            return
        if not chosen and self.pipeline.smoother is not None:
            self.get_logger().info(f'smoother: {smoother_text(self.pipeline.smoother)}')
        self._publish_efforts(out)
        if events:
            self.payload.publish(events)

    # -- commands and snapshots (service_requests.py) ------------------------------------------
    def _apply(self, commands: Commands) -> list[Snapshot]:
        """Apply the services' commands in order, with a snapshot wherever one is due (under
        the processing lock, on the processing thread)."""
        jobs = []
        for items, seq, save in commands.snapshots():
            try:
                for kind, argument in items:
                    self._apply_command(kind, argument)
                jobs.append(self._take_snapshot(seq, save))
            except Exception as exc:   # noqa: BLE001 - answered with the reason, counted
                self.callback_errors['estimate'] += 1
                text = f'estimate failed: {type(exc).__name__}: {exc}'
                self.get_logger().error(text, throttle_duration_sec=5.0)
                jobs.append(Snapshot(seq, save, error=text))
        return jobs

    def _apply_command(self, kind: str, argument: Any) -> None:
        if kind == 'reset':
            self.pipeline.reset()
            for source in self._inputs:
                source.reset_lost()
        elif kind == 'freeze':
            self.pipeline.frozen = bool(argument)
        elif kind == DRIVE_GAIN_COMMAND and self.drive_gains is not None:
            self.drive_gains.apply(argument)
        elif self.payload is not None:
            self.payload.apply(kind, argument)

    def _take_snapshot(self, seq: int, save: bool) -> Snapshot:
        p = self.pipeline
        snap = Snapshot(seq, save, p.estimate(),
                        pipeline_equations(p) if self._consistency_options else None)
        if save:
            snap.covariance, snap.rejected = p.covariance, dict(p.rejected)
            snap.payload = self.payload.current if self.payload else None
        return snap

    def _submit(self, jobs: list[Snapshot]) -> None:
        """Hand snapshots to the worker, in order; a newer one replaces one not yet taken
        unless that one is to be saved."""
        if not jobs:
            return
        with self._job_ready:
            for job in jobs:
                if self._jobs and not self._jobs[-1].save:
                    self._jobs[-1] = job
                else:
                    self._jobs.append(job)
            self._job_ready.notify()

    def _receive(self) -> None:
        for source in self._inputs:
            source.receive()

    def _on_processing_error(self, exc: BaseException) -> None:
        if self._closing:
            return
        self.callback_errors['processing'] += 1
        where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        at = f' (at {where.filename}:{where.lineno})' if where else ''
        self.get_logger().error(f'processing failed: {type(exc).__name__}: {exc}{at}',
                                throttle_duration_sec=5.0)

    def _publish_efforts(self, out: PipelineOutput) -> None:
        if len(out.stamps_ns) == 0:
            return
        now = time.monotonic()
        if now - self._listeners_checked >= LISTENER_CHECK_PERIOD:
            self._listeners_checked = now
            self._effort_listened = (self._pub_predicted.get_subscription_count() > 0,
                                     self._pub_measured.get_subscription_count() > 0)
        outputs = [(pub, effort) for pub, effort, listened in zip(
            (self._pub_predicted, self._pub_measured), (out.predicted, out.measured),
            self._effort_listened) if listened]   # none serialized for nobody
        if not outputs:
            return
        keep = slice(None)
        if self._effort_rate > 0:
            slots = (out.stamps_ns * self._effort_rate // 1e9).astype(np.int64)
            prev = np.concatenate([[self._last_effort_slot], slots[:-1]])
            keep = slots != prev
            self._last_effort_slot = int(slots[-1])
        names = self.robot.joint_names
        stamps = out.stamps_ns[keep]
        for pub, effort in outputs:
            publish_joint_states(pub, stamps, names, position=out.q[keep], effort=effort[keep])

    def estimate(self) -> EstimateReport:
        """The pipeline's estimate (safe from any thread: processing runs on its own)."""
        with self._lock:
            return self.pipeline.estimate()

    def refresh_estimate(self) -> None:
        """Ask for base_parameters, the estimate parameters and the identified URDF to be
        published: the processing thread takes the snapshot at its next run, the worker
        solves and publishes it."""
        self._requests.want_snapshot()

    def _consistency_worker(self) -> None:
        while True:
            with self._job_ready:
                while not self._jobs and self._worker_running:
                    self._job_ready.wait()
                if not self._worker_running:
                    return
                job = self._jobs.pop(0)
            try:
                outcome = self._publish_snapshot(job)
            except Exception as exc:  # noqa: BLE001 - the worker must survive and report
                self.callback_errors['estimate'] += 1
                self.get_logger().error('publishing the estimate failed: ' + ''.join(
                    traceback.format_exception(exc)), throttle_duration_sec=5.0)
                outcome = Outcome(error=f'estimate failed: {type(exc).__name__}: {exc}')
            self._requests.answer(job.seq, outcome)

    def _publish_snapshot(self, job: Snapshot) -> Outcome:
        """Solve (physical consistency), publish and, if asked, save ``job``: the answer to
        the requests it covers."""
        if job.error:
            return Outcome(error=job.error)
        est = job.estimate
        consistent = None if job.equations is None else self._solve(job.equations, job.save)
        self._publish_estimate(est, consistent)
        ok = consistent is not None and consistent.ok
        outcome = Outcome(estimate=json.dumps(plain({
            'names': est.names, 'values': (consistent.theta if ok else est.values).tolist(),
            'stddev': est.stddev.tolist(), 'unconstrained_values': est.values.tolist(),
            'consistency_status': 'disabled' if consistent is None else consistent.status,
            'num_samples': est.num_samples, 'time': est.stamp, 'converged': est.converged,
            'condition_number': est.condition_number})))
        if job.save:
            doc = snapshot_document(self.robot, self.pipeline.base, est, job.covariance,
                                    job.rejected, consistent)
            if job.payload is not None:
                doc['payload'] = plain(job.payload.document())
            try:
                paths = write_results(self.settings.output_directory, doc, self.robot,
                                      job.payload, self.settings['save_inconsistent'])
                outcome.saved = [str(p) for p in paths]
            except OSError as exc:
                outcome.save_error = f'cannot save: {exc}'
            except IdentificationError as exc:   # an inconsistent estimate, not asked for
                self.get_logger().error(str(exc))
                outcome.save_error = str(exc)
        return outcome

    def _solver_instance(self) -> SolverProcess:
        with self._solver_lock:
            if self._solver is None:
                self._solver = SolverProcess.for_robot(self.robot, self.pipeline.base,
                                                       self._consistency_options)
                self._solver.start()
            return self._solver

    def _solve(self, equations: tuple, wait: bool = True) -> ConsistentEstimate:
        """The constrained solve; unless ``wait``, status 'starting' (the unconstrained
        estimate goes out) while the solver process still builds its problem."""
        solver = self._solver_instance()
        with self._solver_lock:
            if not wait and not solver.ready():
                return ConsistentEstimate('starting', None, None,
                                          np.full(self.pipeline.base.num_base, np.inf), 0.0)
            result = solver.solve(*equations)
        self._consistent = result
        if not result.ok and result.status != self._solver_failure and self._worker_running:
            self.get_logger().warning(
                f'physically consistent solve: {result.status}; publishing the '
                'unconstrained estimate')
        self._solver_failure = '' if result.ok else result.status
        return result

    def _publish_estimate(self, est: EstimateReport, consistent: ConsistentEstimate | None
                          ) -> None:
        ok = consistent is not None and consistent.ok
        values = consistent.theta if ok else est.values
        b = len(est.names)
        msg = Float64MultiArray()
        msg.layout.dim = [MultiArrayDimension(label='value_stddev_unconstrained', size=3,
                                              stride=3 * b),
                          MultiArrayDimension(label='base_parameter', size=b, stride=b)]
        stddev = np.where(np.isfinite(est.stddev), est.stddev, -1.0)   # -1: not determined yet
        msg.data = np.concatenate([values, stddev, est.values]).tolist()
        params = [Parameter(ESTIMATE_PREFIX + n, value=float(v))
                  for n, v in zip(est.names, values)]
        params += [Parameter(STDDEV_PREFIX + n, value=float(s))
                   for n, s in zip(est.names, stddev)]
        params += [Parameter(UNCONSTRAINED_PREFIX + n, value=float(v))
                   for n, v in zip(est.names, est.values)]
        if self.drive_gains is not None:
            with self._lock:
                params += self.drive_gains.parameters()
        with self._publish_lock:
            self._pub_params.publish(msg)
            self._internal_update = True
            try:
                self.set_parameters_atomically(params)   # one parameter event, one snapshot
            finally:
                self._internal_update = False
            # The URDF topic is latched: rebuild it only when new samples or the solve changed
            # the estimate.
            version = (est.num_samples, self.payload.version if self.payload else 0, ok)
            if est.num_samples and version != self._urdf_samples and self.robot.kind == 'urdf':
                self._urdf_samples = version
                with self._lock:
                    phi = consistent.phi if ok else self.pipeline.standard_parameters()
                    payload = self.payload.current if self.payload else None
                self._consistency = consistency_problems(self.robot, phi)
                urdf = identified_urdf(self.robot, phi)
                if payload is not None:
                    urdf = urdf_with_payload(urdf, payload)
                self._pub_urdf.publish(String(data=urdf))
            if est.num_samples and math.isfinite(est.stamp):
                with self._lock:
                    phi = consistent.phi if ok else self.pipeline.standard_parameters()
                self.links.publish(phi, int(round(est.stamp * 1e9)))

    def _publish_diagnostics(self) -> None:
        p = self.pipeline
        with self._lock:
            est = p.estimate()
            received, used, restarts, rejected = p.received, p.used, p.restarts, dict(p.rejected)
            gate, failures, edges = p.gate, p.numerical_failures, p.smoother_edge
            robust = ('residual shift: not gating' if gate.suspended else
                      'gating' if gate.armed else 'waiting for convergence'
                      ) if gate.settings.enabled else 'off'
            shifts, cache = gate.shifts, p.layout_cache_bytes
            excluded, terms = p.excluded_equations, p.model_term_warnings()
            counters, offset = p.samples.counters, p.time_offset.result
            missing = sorted(counters.missing_joints | counters.missing_current_joints)
        now = self.get_clock().now()
        dt = (now - self._last_diag_time).nanoseconds * 1e-9
        rate = (received - self._received_at_last_diag) / dt if dt > 0 else 0.0
        self._received_at_last_diag, self._last_diag_time = received, now
        status = DiagnosticStatus(name=f'{self.get_name()}: identification',
                                  hardware_id=self.robot.name)
        if est.converged:
            status.level, status.message = DiagnosticStatus.OK, 'converged'
        else:
            status.level, status.message = DiagnosticStatus.WARN, 'not converged'
        if p.gate.suspended:
            status.level = DiagnosticStatus.WARN
            status.message += '; residual shift (payload change?)'
        if self._consistency:
            status.level = DiagnosticStatus.WARN
            status.message += '; identified parameters not physically consistent'
        if missing:
            status.level = DiagnosticStatus.WARN
            status.message += f"; messages lack joint(s) {', '.join(missing)}"
        if terms:
            status.level = DiagnosticStatus.WARN
            status.message += '; missing model term?'
        values = {
            'input_rate_hz': rate, 'samples_received': received,
            'samples_used': used, 'samples_rejected': sum(rejected.values()),
            'condition_number': est.condition_number,
            'min_information_eigenvalue': est.min_eigenvalue,
            'converged': est.converged, 'frozen': est.frozen, 'stream_restarts': restarts,
            **smoother_values(p.smoother, p.row_builder.holding),
            'physically_consistent': not self._consistency,
            'robust_gate': robust, 'residual_shifts': shifts, 'numerical_failures': failures,
            'smoother_edge_samples': edges, 'layout_cache_bytes': cache,
            'callback_errors': sum(self.callback_errors.values()),
            'time_offset_s': None if offset is None else offset.offset,
        }
        result = self._consistent
        values['consistency_status'] = ('disabled' if self._consistency_options is None else
                                        'not solved yet' if result is None else result.status)
        if result is not None:
            values['consistency_solve_time_ms'] = 1e3 * result.solve_time
            values['consistency_method'] = result.method or 'none'
            if not result.ok:
                status.level = DiagnosticStatus.ERROR
                status.message += ('; consistent solve failed: unconstrained estimate '
                                   'published, NOT physically consistent')
            if result.notes:
                values['consistency_notes'] = '; '.join(result.notes)
        values.update({f'lost_messages.{s.topic}': s.lost for s in self._inputs})
        values.update({f'dropped_messages.{s.topic}': s.dropped for s in self._inputs})
        values['qos_incompatible'] = self._qos_watch.incompatible
        values.update({f'rejected.{k}': v for k, v in rejected.items()})
        values.update(vector('residual_rms', self.robot.joint_names, est.residual_rms))
        values.update({f'excluded_equations.{j}': int(k)
                       for j, k in zip(self.robot.joint_names, excluded)})
        if missing:
            values['missing_joints'] = ', '.join(missing)
        if terms:
            values['model_term_warnings'] = '; '.join(terms)
        if self._consistency:
            values['consistency_problems'] = '; '.join(self._consistency)
        if self.payload is not None:
            with self._lock:
                values.update(self.payload.diagnostics())
        if offset is not None and offset.level:   # time_offset.py: torque late or early
            status.level = max(status.level, (DiagnosticStatus.WARN, DiagnosticStatus.ERROR)[
                offset.level - 1])
            status.message += f'; torque {offset.offset:+.3f} s off the motion'
        if self.drive_gains is not None:
            with self._lock:
                values.update(self.drive_gains.diagnostics())
        status.values = key_values(values)
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = now.to_msg()
        self._pub_diag.publish(msg)

    # -- services (answered on their own thread, service_requests.py) ------------------------
    @staticmethod
    def _answer(reply: Callable, response: Any, text: str) -> Callable[[Outcome], None]:
        def answer(outcome: Outcome) -> None:
            if outcome.error:
                reply(failed(response, outcome.error))
            else:
                response.success, response.message = True, text
                reply(response)
        return answer

    def _srv_reset(self, _req: Trigger.Request, reply: Callable) -> None:
        self._requests.command('reset', None, self._answer(reply, Trigger.Response(),
                                                           'estimate reset'))

    def _srv_freeze(self, req: SetBool.Request, reply: Callable) -> None:
        text = 'updates frozen' if req.data else 'updates resumed'
        self._requests.command('freeze', bool(req.data),
                               self._answer(reply, SetBool.Response(), text))

    def _srv_save(self, _req: Trigger.Request, reply: Callable) -> None:
        def answer(outcome: Outcome) -> None:
            res = Trigger.Response()
            if outcome.error or outcome.saved is None:
                reply(failed(res, outcome.error or outcome.save_error))
            else:
                res.success, res.message = True, ' '.join(outcome.saved)
                reply(res)
        self._requests.command('save', None, answer)

    def _srv_get_estimate(self, _req: Trigger.Request, reply: Callable) -> None:
        def answer(outcome: Outcome) -> None:
            self._answer(reply, Trigger.Response(), outcome.estimate)(outcome)
        self._requests.read(answer)

    def destroy_node(self) -> None:
        self._service_thread.stop()
        # A processing run over a large burst can take seconds on a busy machine: a shutdown
        # does not wait for it (its thread is a daemon; what it then fails at is not logged).
        self._closing = True
        self._clock_check.stop()
        self._receiving.stop(SHUTDOWN_WAIT)
        self._processing.stop(SHUTDOWN_WAIT)
        with self._job_ready:
            self._worker_running = False
            self._job_ready.notify()
        if self._solver is not None:
            self._solver.close()   # not under the solver lock: a solve may be in flight
        self._worker.join(timeout=1.0)
        for source in self._inputs:
            source.destroy()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    # While the executor thread runs Python (the 1 Hz refresh takes a few ms), the processing
    # thread gets the GIL after this interval instead of the default 5 ms: the latency tail.
    sys.setswitchinterval(0.0005)
    return run_node(IdentificationNode, 'identification_node', args, polled=True)


if __name__ == '__main__':
    sys.exit(main())
