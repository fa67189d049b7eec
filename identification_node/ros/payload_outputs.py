"""The node's payload interfaces (``payload.enabled``), wiring a PayloadMonitor.

- ``~/payload`` (geometry_msgs/InertiaStamped, transient local): published at every fit
  (after a change, and each refresh); header stamp = since when the payload holds, frame_id =
  the payload link; m (kg), com (m) and the inertia about the com (kg m^2), in that link's
  frame. A quantity the motion did not excite is published as 0 (a point mass / a centre of
  mass on the axis), and named in diagnostics (``payload.not_excited``).
- ``~/payload/stddev`` (InertiaStamped, transient local): the standard deviations of those
  quantities in the same fields and header (inf where not excited; 0 for a payload set by
  ``~/payload/set``), published just before each ``~/payload``.
- ``~/payload_changed`` (std_msgs/Header): a detected change, stamp = its estimated onset,
  frame_id = the payload link (the new payload follows on ``~/payload``).
- ``~/payload/reset`` (std_srvs/Trigger): forget the payload (e.g. after a tool change);
  it is identified afresh from the next samples (with ``payload.arm: estimate``, against
  the arm's running estimate taken now).
- ``~/payload/set`` (rcl_interfaces/SetParameters): a known payload, as parameters ``mass``
  (double), ``com`` (double array, 3) and ``inertia`` (double array ixx ixy ixz iyy iyz izz);
  watched from then on, not refitted until a change is detected. Refused with the reason
  unless it could be a URDF <inertial> (payload/validation.py: mass positive, finite, at most
  ``plausibility.margin`` times the arm's own mass; inertia positive definite, triangle
  inequality, or all 0: a point mass).
"""
from __future__ import annotations

import math
from typing import Callable

from geometry_msgs.msg import InertiaStamped
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from identification_node.errors import IdentificationError
from identification_node.payload.fit import ArmPrior, PayloadEstimate, prepare_consistency
from identification_node.payload.monitor import ARM_ESTIMATE, PayloadEvent, monitor_from_settings
from identification_node.payload.validation import checked_payload, max_payload_mass
from identification_node.ros.diagnostics import NOT_EXCITED, vector
from identification_node.ros.service_requests import (Outcome, RequestQueue, ServiceThread,
                                                      failed)

ARM_HINT = 'set payload.arm to its estimate.yaml'
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
EVENTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                    reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)


def inertia_message(est: PayloadEstimate, stamp: float) -> InertiaStamped:
    """``est`` as InertiaStamped (unexcited quantities 0; see the module docstring)."""
    msg = InertiaStamped()
    msg.header.frame_id = est.link
    msg.header.stamp.sec, msg.header.stamp.nanosec = _split(stamp)
    known = set(est.excited)
    msg.inertia.m = float(est.mass) if 'mass' in known else 0.0
    for axis, value in zip('xyz', est.com):
        setattr(msg.inertia.com, axis, float(value) if f'com.{axis}' in known else 0.0)
    for key, value in zip(('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz'), est.inertia):
        setattr(msg.inertia, key, float(value) if f'inertia.{key}' in known else 0.0)
    return msg


def stddev_message(est: PayloadEstimate, stamp: float) -> InertiaStamped:
    """The standard deviations of ``est``'s quantities in InertiaStamped's layout (inf where
    not excited), header as ``inertia_message``'s."""
    msg = InertiaStamped()
    msg.header.frame_id = est.link
    msg.header.stamp.sec, msg.header.stamp.nanosec = _split(stamp)
    sd = {q: float(v) for q, v in est.stddev.items()}
    msg.inertia.m = sd.get('mass', math.inf)
    for axis in 'xyz':
        setattr(msg.inertia.com, axis, sd.get(f'com.{axis}', math.inf))
    for key in ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz'):
        setattr(msg.inertia, key, sd.get(f'inertia.{key}', math.inf))
    return msg


def change_text(e: PayloadEvent) -> str:
    """'mass 2.001 +- 0.004 kg (change +2.001 +- 0.005 kg)' of a fit event."""
    p = e.payload
    assert p is not None   # a fit event's
    sd = p.stddev['mass']
    text = (f'mass {p.mass:.4g} +- {sd:.2g} kg' if 'mass' in p.excited
            else 'mass not excited')
    if math.isfinite(e.mass_change):
        text += f' (change {e.mass_change:+.4g} +- {e.mass_change_std:.2g} kg)'
    return text


def _split(stamp: float) -> tuple[int, int]:
    ns = int(round(stamp * 1e9)) if math.isfinite(stamp) else 0
    return ns // 1_000_000_000, ns % 1_000_000_000


class PayloadOutputs:
    """Publishers, services and diagnostics of the payload monitor; ``add`` runs on the
    node's processing thread (under the node's lock), ``publish`` after it."""

    def __init__(self, node: Node, settings, pipeline, services: ServiceThread,
                 requests: RequestQueue):
        self.node, self.requests = node, requests
        self.monitor = monitor_from_settings(settings, pipeline.robot, pipeline.base)
        prepare_consistency()   # cvxpy's import: seconds, not in a run
        self.pipeline = pipeline
        self._arm_from_estimate = settings['payload.arm'] == ARM_ESTIMATE
        self.max_mass = max_payload_mass(pipeline.robot, settings['plausibility.margin'])
        self.link = self.monitor.attach.link
        self.version = 0
        self.last_change: PayloadEvent | None = None
        self._pub = node.create_publisher(InertiaStamped, '~/payload', LATCHED)
        self._pub_sd = node.create_publisher(InertiaStamped, '~/payload/stddev', LATCHED)
        self._pub_changed = node.create_publisher(Header, '~/payload_changed', EVENTS)
        services.add(Trigger, '~/payload/reset', self._srv_reset)
        services.add(SetParameters, '~/payload/set', self._srv_set)
        node.get_logger().info(f'payload identification on {self.link}; changes of more '
                               f'than {self.monitor.config.min_change:g} kg are detected')

    @property
    def current(self) -> PayloadEstimate | None:
        return self.monitor.current

    def add(self, out) -> list[PayloadEvent]:
        events = self.monitor.add_output(out)
        if events:
            self.version += 1
            changes = [e for e in events if e.kind == 'change']
            if changes:
                self.last_change = changes[-1]
        return events

    def publish(self, events: list[PayloadEvent]) -> None:
        for e in events:
            if e.kind == 'change':
                msg = Header(frame_id=self.link)
                msg.stamp.sec, msg.stamp.nanosec = _split(e.stamp)
                self._pub_changed.publish(msg)
                self.node.get_logger().info(
                    f'payload change at {e.stamp:.3f} s (detected {e.detected:.3f} s); '
                    'fitting the new payload')
            elif e.payload is not None:
                self._publish_payload(e.payload, e.stamp)
                if e.kind == 'estimate':
                    self.node.get_logger().info(f'payload since {e.stamp:.3f} s: '
                                                + change_text(e))
        for warning in self.monitor.warnings(ARM_HINT):
            self.node.get_logger().warning(warning, throttle_duration_sec=60.0)

    def _publish_payload(self, est: PayloadEstimate, stamp: float) -> None:
        self._pub_sd.publish(stddev_message(est, stamp))   # first: ~/payload completes a pair
        self._pub.publish(inertia_message(est, stamp))

    def diagnostics(self) -> dict:
        m = self.monitor
        est = m.current
        values = {'payload.link': self.link, 'payload.changes': m.changes,
                  'payload.detector_statistic': m.detector.statistic,
                  'payload.stream_gaps': m.detector.gaps,
                  'payload.state': m.state,
                  'payload.detector_delay': m.detector_delay,
                  'payload.arm_residual_ratio': m.arm_residual_ratio,
                  **vector('payload.torque_noise', self.pipeline.robot.joint_names,
                           m.torque_noise())}
        warnings = m.warnings(ARM_HINT)
        if warnings:
            values['payload.warning'] = '; '.join(warnings)
        if self.last_change is not None:
            values['payload.last_change'] = f'{self.last_change.stamp:.6f}'
            values['payload.last_change_detected'] = f'{self.last_change.detected:.6f}'
        if est is not None:   # unexcited quantities: 'not excited' (diagnostics.py)
            doc = est.document()
            values['payload.mass'] = NOT_EXCITED if doc['mass'] is None else doc['mass']
            values.update(vector('payload.com', 'xyz', doc['com'],
                                 [v is not None for v in doc['com']]))
            values['payload.excited'] = ' '.join(doc['excited'])
            values['payload.not_excited'] = ' '.join(doc['not_excited'])
        return values

    # services: validated here, applied by the node's processing thread in order
    def _srv_reset(self, _req: Trigger.Request, reply: Callable) -> None:
        text = 'payload forgotten; identified afresh from now' + (
            ' against the running estimate of the arm' if self._arm_from_estimate else '')

        def answer(outcome: Outcome) -> None:
            res = Trigger.Response()
            if outcome.error:
                reply(failed(res, outcome.error))
            else:
                res.success, res.message = True, text
                reply(res)
        self.requests.command('payload_reset', None, answer)

    def _srv_set(self, req: SetParameters.Request, reply: Callable) -> None:
        res = SetParameters.Response()
        given = {p.name: Parameter.from_parameter_msg(p).value for p in req.parameters}
        try:
            unknown = set(given) - {'mass', 'com', 'inertia'}
            if unknown or 'mass' not in given:
                raise IdentificationError(f'give mass (and com, inertia) only; got '
                                          f'{sorted(given)}')
            phi = checked_payload(given['mass'], given.get('com', [0.0] * 3),
                                  given.get('inertia', [0.0] * 6), self.max_mass)
        except (IdentificationError, TypeError, ValueError) as exc:
            reply(failed(res, str(exc)))
            return

        def answer(outcome: Outcome) -> None:
            if outcome.error:
                reply(failed(res, outcome.error))
            else:
                res.results = [SetParametersResult(successful=True, reason='payload set')]
                reply(res)
        self.requests.command('payload_set', phi, answer)

    def apply(self, kind: str, argument) -> None:
        """Command ``payload_reset`` or ``payload_set`` (10 parameters), under the node's
        processing lock."""
        if kind == 'payload_reset':
            if self._arm_from_estimate:
                self.monitor.set_arm(self.pipeline.standard_parameters(),
                                     ArmPrior.from_covariance(self.pipeline.base,
                                                              self.pipeline.covariance))
            else:
                self.monitor.reset()
            self.version += 1
        elif kind == 'payload_set':
            est = self.monitor.set_payload(argument)
            self.version += 1
            self._publish_payload(est, self.node.get_clock().now().nanoseconds * 1e-9)
