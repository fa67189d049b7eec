"""The identification node: ``ros2 run identification_node identification_node``.

Subscribes to ``joint_states`` and, when a joint's torque comes from motor currents, to
``motor_currents`` (sensor_msgs/JointState; channels ``<joint>/ia|ib|ic`` or ``<joint>/i``,
amperes in effort, optional electrical angle in position). A processing thread of its own
takes the queued input messages every ``process_period`` (wall clock), copies them into the
pipeline and runs it on them in one batch. This module wires the parts, each documented in its
own module under ros/:

- effort_outputs.py: ``~/predicted_effort``, ``~/measured_effort`` (while they have
  subscribers);
- estimate_outputs.py: ``~/base_parameters``, ``~/robot_description``, ``~/links/*`` and the
  ``estimate.*`` parameters, refreshed at ``publish.estimate_rate`` and after every command
  from a snapshot of the pipeline taken on the processing thread; the constrained solve
  (consistency.py) in a child process (solver_worker.py);
- estimate_services.py: ``~/reset``, ``~/freeze``, ``~/save``, ``~/get_estimate``, served by a
  thread of their own (service_requests.py): commands are applied in order by the processing
  thread and answered once the estimate after them is published;
- diagnostics.py: ``/diagnostics``; parameters.py: settings, outputs, run-time changes;
- payload_outputs.py (``payload.enabled``), drive_gains.py (``drive_gains.*``).
"""
from __future__ import annotations

import copy
import sys
import threading
import time
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import JointState

from identification_node.estimation.consistency import pipeline_equations
from identification_node.pipeline import EstimateReport
from identification_node.ros.conversions import PolledSubscription
from identification_node.ros.diagnostics import (NodeStatus, identification_status,
                                                 smoother_plan, smoother_text)
from identification_node.ros.drive_gains import COMMAND as DRIVE_GAIN_COMMAND
from identification_node.ros.drive_gains import DriveGainOutputs
from identification_node.ros.effort_outputs import EffortOutputs
from identification_node.ros.estimate_outputs import EstimateOutputs
from identification_node.ros.estimate_services import EstimateServices
from identification_node.ros.node_health import CallbackErrors, SimClockCheck
from identification_node.ros.parameters import OutputParameters, RuntimeParameters
from identification_node.ros.payload_outputs import PayloadOutputs
from identification_node.ros.qos_watch import QosWatch
from identification_node.ros.service_requests import (Commands, Outcome, RequestQueue,
                                                      ServiceThread, Snapshot)
from identification_node.ros.solver_worker import ConsistencyWorker
from identification_node.ros.spin import BudgetPeriod, PeriodicThread, run_node
from identification_node.config import PARAMETERS
from identification_node.settings import Settings

__all__ = ['INPUT_QOS', 'IdentificationNode', 'main']

# Deep enough for a 1 s burst at 1 kHz; best effort like other sensor streams.
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                       reliability=ReliabilityPolicy.BEST_EFFORT)
SHUTDOWN_WAIT = 0.3   # s a shutdown waits for a processing run in progress


class IdentificationNode(Node):
    """Wires the ROS interfaces to an IdentificationPipeline; no numerics of its own."""

    def __init__(self, node_name: str = 'identification_node', **kwargs: Any):
        super().__init__(node_name, **kwargs)
        self.runtime = RuntimeParameters(self, PARAMETERS)
        s = self.settings
        self.pipeline = s.build()
        self.pipeline.live_clock(time.monotonic)   # topics are not delivered in step
        self.robot = self.pipeline.robot
        self.outputs = OutputParameters(self, self.pipeline.base.names)
        self.errors = CallbackErrors(self.get_logger())
        self.callback_errors = self.errors.counts   # per callback name
        self._closing = False
        # The pipeline is shared by the processing thread, the services' snapshots and the
        # executor's callbacks.
        self.lock = threading.Lock()
        # Services on a thread of their own, answered from snapshots (service_requests.py).
        self._requests = RequestQueue()
        self._service_thread = ServiceThread(self, self.errors.service)
        # before the inputs: its start-up (cvxpy) takes seconds
        self.payload = (PayloadOutputs(self, s, self.pipeline, self._service_thread,
                                       self._requests) if s['payload.enabled'] else None)
        self.runtime.watch(self.pipeline, self.payload.monitor if self.payload else None,
                           self.lock)

        self.watchdog_timeout = s['watchdog_timeout']
        self.pipeline.gate.listeners.append(self._on_residual_shift)
        handlers = (self.pipeline.add_joint_state_cdr, self.pipeline.add_currents_cdr)
        self.drive_gains = None
        if s['drive_gains.back_emf'] or s['drive_gains.known_payload']:
            self.drive_gains = DriveGainOutputs(s, self.pipeline, self._service_thread,
                                                self._requests, self.outputs, self.subscribe)
            handlers = self.drive_gains.tee(*handlers)
        self.inputs = [self.subscribe('joint_states', handlers[0])]
        if self.pipeline.converter.needs_currents:
            self.inputs.append(self.subscribe('motor_currents', handlers[1]))
        if self.drive_gains is not None and self.drive_gains.voltages is not None:
            self.inputs.append(self.drive_gains.voltages)
        self.efforts = EffortOutputs(self, self.robot.joint_names, s['publish.effort_rate'])
        self.estimates = EstimateOutputs(self, self.pipeline, self.lock, self.outputs,
                                         self.payload, self.drive_gains,
                                         s.output_directory, s['save_inconsistent'])
        self.links = self.estimates.links
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._qos_watch = QosWatch(self)   # checked with the clock, every second
        self._qos_watch.watch(*(i.subscription for i in self.inputs), self.efforts.predicted,
                              self.efforts.measured, self.estimates.params,
                              self.estimates.urdf)
        EstimateServices(self._service_thread, self._requests)

        # The constrained solve and the publishing of each snapshot: on a worker thread, the
        # solver spawned here, on the main thread, so that Ctrl-C spares it.
        self.consistency = ConsistencyWorker(
            self.robot, self.pipeline.base, s.consistency_options(),
            lambda job: self.estimates.publish_snapshot(job, self.consistency.solve),
            self._requests.answer, lambda text: Outcome(error=text), self.callback_errors,
            self.get_logger())
        self._received_at_last_diag = 0
        self._last_diag_time = self.get_clock().now()
        self.create_timer(1.0 / s['publish.estimate_rate'],
                          self.errors.guarded(self.refresh_estimate))
        self.create_timer(1.0 / s['publish.diagnostics_rate'],
                          self.errors.guarded(self._publish_diagnostics))
        self._period = s['process_period']
        self._idle_period = max(self._period, s['idle_process_period'])
        self._current_period = self._period
        self._budget = BudgetPeriod(s['latency_budget'], self._period, self._idle_period)
        self.pipeline.defer_updates = True     # update() after the outputs are published
        self._processing = PeriodicThread(self._processing_period, self._process,
                                          'identification_processing',
                                          self._on_processing_error, alive=self.context.ok)
        self._requests.on_request = self._processing.wake
        # The middleware's queues emptied even while a processing run takes long (their
        # bound is a count; the node's own is in bytes: input_queue_bytes).
        self._fill_time = 0.0   # s until the busiest middleware queue is a quarter full
        self._received_mark = time.monotonic(), [source.taken for source in self.inputs]
        self._receiving = PeriodicThread(self._receiving_period, self._receive,
                                         'identification_receive', self._on_processing_error,
                                         alive=self.context.ok)
        # Wall clock: with use_sim_time and no /clock the node's timers stand still.
        self._sim_clock = SimClockCheck(self)
        self._clock_check = PeriodicThread(1.0, self._periodic_checks, 'identification_clock',
                                           self._on_processing_error, alive=self.context.ok)
        self._service_thread.start()
        for note in self.pipeline.prior_notes:
            self.get_logger().warning(note)
        self.get_logger().info(
            f'identifying {self.pipeline.base.num_base} base parameters of {self.robot.name} '
            f'(joints {", ".join(self.robot.joint_names)}); smoother: ' + smoother_plan(
                self.pipeline.smoother, s['smoother.cutoff'], s['smoother.auto_seconds']))

    @property
    def settings(self) -> Settings:
        """The node's settings, with their run-time changes (ros/parameters.py)."""
        return self.runtime.settings

    def subscribe(self, topic: str, handle: Callable[[list[bytes]], None]
                  ) -> PolledSubscription:
        """An input ``topic`` (JointState), polled by the processing thread into ``handle``."""
        # A copy each: the QoS override parameters are applied to the profile in place.
        overrides = QoSOverridingOptions.with_default_policies()
        return PolledSubscription(
            self, JointState, topic, handle, copy.copy(INPUT_QOS),
            message_lost_event=self.settings['lost_messages.middleware_event'],
            max_bytes=self.settings['input_queue_bytes'],
            qos_overriding_options=overrides)

    # -- robustness -------------------------------------------------------------------------------
    def _on_processing_error(self, exc: BaseException) -> None:
        if not self._closing:
            self.errors.processing(exc)

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
        self._sim_clock.check()

    # -- processing and output --------------------------------------------------------------------
    # The processing thread takes the queued input messages (PolledSubscription) as CDR bytes
    # and hands them to the pipeline as they are (it decodes them in blocks):
    # rclpy never turns them into Python message objects.
    def _process(self) -> None:
        commands = self._requests.take()
        with self.lock:
            jobs = self._apply(commands) if commands is not None else []
            for source in self.inputs:
                source.poll()
            idle = not self.pipeline.pending and not self.pipeline.choosing
            if not idle:
                chosen = self.pipeline.smoother is not None
                out = self.pipeline.process()
                events = self.payload.add(out) if self.payload is not None else ()
                if self.drive_gains is not None:
                    self.drive_gains.process(out)
        self.consistency.submit(jobs)
        if idle:
            return
        if not chosen and self.pipeline.smoother is not None:
            self.get_logger().info(f'smoother: {smoother_text(self.pipeline.smoother)}')
        try:
            self.efforts.publish(out)
            if events and self.payload is not None:
                self.payload.publish(events)
        finally:
            run = self._processing
            self._budget.add(run.late, time.monotonic() - run.started, run.interval)
            with self.lock:   # the estimator's update, once the outputs are out
                self.pipeline.update()

    def _processing_period(self) -> float:
        """While an output's latency counts (an effort output has subscribers, or the payload
        monitor runs) the longest period that keeps the outputs within ``latency_budget``
        (spin.BudgetPeriod; at least ``process_period``), else ``idle_process_period``:
        nothing waits for the samples' outputs (service commands wake the thread at once)."""
        busy = self.payload is not None or self.efforts.listened
        self._current_period = self._budget.period if busy else self._idle_period
        return self._current_period

    def _receiving_period(self) -> float:
        """The processing period, but at most the time the busiest middleware queue takes to
        fill a quarter of its depth at the rate it was last taken at (their depth is a count:
        beyond it they drop); ``process_period`` while nothing comes in (a burst may start)."""
        return max(self._period, min(self._current_period, self._fill_time))

    def _receive(self) -> None:
        for source in self.inputs:
            source.receive()
        now, taken = time.monotonic(), [source.taken for source in self.inputs]
        then, before = self._received_mark
        self._received_mark = now, taken
        if now > then:
            self._fill_time = min((
                0.25 * source.subscription.qos_profile.depth * (now - then) / (k - k0)
                for source, k, k0 in zip(self.inputs, taken, before) if k > k0), default=0.0)

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
                self._requests.applied(seq)
            except Exception as exc:   # noqa: BLE001 - answered with the reason, counted
                self.callback_errors['estimate'] += 1
                text = f'estimate failed: {type(exc).__name__}: {exc}'
                self.get_logger().error(text, throttle_duration_sec=5.0)
                jobs.append(Snapshot(seq, save, error=text))
        return jobs

    def _apply_command(self, kind: str, argument: Any) -> None:
        if kind == 'reset':
            self.pipeline.reset()
            for source in self.inputs:
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
                        pipeline_equations(p) if self.consistency.options else None)
        if save:
            snap.covariance, snap.rejected = p.covariance, dict(p.rejected)
            snap.payload = self.payload.current if self.payload else None
        return snap

    def estimate(self) -> EstimateReport:
        """The pipeline's estimate (safe from any thread: processing runs on its own)."""
        with self.lock:
            return self.pipeline.estimate()

    def refresh_estimate(self) -> None:
        """Ask for base_parameters, the estimate parameters and the identified URDF to be
        published: the processing thread takes the snapshot at its next run, the worker
        solves and publishes it."""
        self._requests.want_snapshot()

    def _publish_diagnostics(self) -> None:
        with self.lock:
            status = self.pipeline.status()
            extra = self.payload.diagnostics() if self.payload is not None else {}
            if self.drive_gains is not None:
                extra.update(self.drive_gains.diagnostics())
        now = self.get_clock().now()
        dt = (now - self._last_diag_time).nanoseconds * 1e-9
        rate = (status.received - self._received_at_last_diag) / dt if dt > 0 else 0.0
        self._received_at_last_diag, self._last_diag_time = status.received, now
        node = NodeStatus(
            input_rate_hz=rate, callback_errors=sum(self.callback_errors.values()),
            consistency_enabled=self.consistency.options is not None,
            consistent=self.consistency.consistent,
            consistency_problems=self.estimates.problems,
            lost={s.topic: s.lost for s in self.inputs},
            dropped={s.topic: s.dropped for s in self.inputs},
            qos_incompatible=self._qos_watch.incompatible, extra=extra,
            processing_period=self._current_period)
        msg = DiagnosticArray(status=[identification_status(
            f'{self.get_name()}: identification', self.robot.name, self.robot.joint_names,
            status, node)])
        msg.header.stamp = now.to_msg()
        self._pub_diag.publish(msg)

    def destroy_node(self) -> None:
        self._service_thread.stop()
        # A processing run over a large burst can take seconds on a busy machine: a shutdown
        # does not wait for it (its thread is a daemon; what it then fails at is not logged).
        self._closing = True
        self._clock_check.stop()
        self._receiving.stop(SHUTDOWN_WAIT)
        self._processing.stop(SHUTDOWN_WAIT)
        self.consistency.stop()
        for source in self.inputs:
            source.destroy()
        super().destroy_node()


# While the executor thread runs Python (the 1 Hz refresh takes a few ms), the processing thread
# gets the GIL after this interval (s) instead of the default 5 ms: the latency tail.
SWITCH_INTERVAL = 0.0005


def main(args: list[str] | None = None) -> int:
    sys.setswitchinterval(SWITCH_INTERVAL)
    return run_node(IdentificationNode, 'identification_node', args, polled=True)


if __name__ == '__main__':
    sys.exit(main())
