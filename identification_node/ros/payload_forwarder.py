"""Forward the identified payload to a controller's service: ``python -m identification_node
forward_payload --ros-args -p preset:=ur -r payload:=/identification_node/payload``.

Subscribes ``payload`` (geometry_msgs/InertiaStamped, transient local: the identification
node's ``~/payload``) and, for each message whose frame_id is ``frame`` (empty: any), calls
``service`` (type ``service_type``, ``pkg/srv/Type``) with the request fields ``fields``
(``field.path=quantity``, payload_delivery.py) filled from it. ``preset`` (ur, franka) sets
the service, its type, the fields and the frame of those drivers; explicit parameters
override it. ``transition_time`` (s, default 0): into the request's field of that name, where
the service has one (UR's newer SetPayload). The response's ``success`` and
``error``/``message`` fields are logged. The call is asynchronous; a payload arriving while
one is in flight replaces the waiting one.
"""
from __future__ import annotations

import importlib
import sys
from typing import Any

from geometry_msgs.msg import InertiaStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from identification_node.errors import IdentificationError
from identification_node.payload.delivery import PRESETS, has_field, fill_request, parse_fields
from identification_node.ros.spin import run_node

PAYLOAD_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


def service_class(name: str):
    """The service type ``pkg/srv/Type``, imported."""
    pkg, sep, rest = name.partition('/srv/')
    if not sep or not pkg or not rest:
        raise IdentificationError(f'parameter service_type: {name!r} is not pkg/srv/Type')
    try:
        return getattr(importlib.import_module(f'{pkg}.srv'), rest)
    except (ImportError, AttributeError):
        raise IdentificationError(f'parameter service_type: {name} is not installed') from None


class PayloadForwarder(Node):
    """See the module docstring."""

    def __init__(self, node_name: str = 'payload_forwarder', **kwargs: Any):
        super().__init__(node_name, **kwargs)
        text = ParameterDescriptor(read_only=True, dynamic_typing=True)
        preset = str(self.declare_parameter('preset', '', text).value or '')
        if preset and preset not in PRESETS:
            raise IdentificationError(f'parameter preset: {preset!r}; choose from '
                                      f'{", ".join(PRESETS)}')
        base = PRESETS.get(preset, {'service': '', 'service_type': '', 'frame': '',
                                    'fields': {}})
        self.transition_time = float(self.declare_parameter('transition_time', 0.0).value)
        value = {k: self.declare_parameter(k, None, text).value
                 for k in ('service', 'service_type', 'frame', 'fields')}
        self.service_name = value['service'] or base['service']
        if not self.service_name:
            raise IdentificationError('parameter service: name the controller service '
                                      '(or a preset)')
        self.srv_type = service_class(value['service_type'] or base['service_type'])
        self.frame = base['frame'] if value['frame'] is None else str(value['frame'])
        try:
            self.fields = parse_fields(list(value['fields']) if value['fields'] else
                                       base['fields'])
            self.optional = not value['fields'] and bool(base.get('optional'))
            request = fill_request(self.srv_type.Request(), self.fields,
                                   InertiaStamped().inertia, self.optional, self.transition_time)
            if self.optional:
                self.fields = {p: q for p, q in self.fields.items() if has_field(request, p)}
        except IdentificationError as exc:
            raise IdentificationError(f'parameter fields: {exc}') from None
        self.client = self.create_client(self.srv_type, self.service_name)
        self.create_subscription(InertiaStamped, 'payload', self._on_payload, PAYLOAD_QOS)
        self.sent = self.refused = 0
        self._waiting: InertiaStamped | None = None
        self._in_flight = False
        self.create_timer(0.1, self._send)
        self.get_logger().info(f'forwarding payloads to {self.service_name} '
                               f'({self.srv_type.__name__}: {self.fields})')

    def _on_payload(self, msg: InertiaStamped) -> None:
        if self.frame and msg.header.frame_id != self.frame:
            self.refused += 1
            self.get_logger().error(
                f'payload in frame {msg.header.frame_id!r}, the controller expects '
                f'{self.frame!r}: not forwarded (set payload.link to {self.frame})')
            return
        self._waiting = msg
        self._send()

    def _send(self) -> None:
        if self._waiting is None or self._in_flight or not self.client.service_is_ready():
            return
        msg, self._waiting = self._waiting, None
        request = fill_request(self.srv_type.Request(), self.fields, msg.inertia,
                               transition_time=self.transition_time)
        self._in_flight = True
        self.client.call_async(request).add_done_callback(self._done)

    def _done(self, future) -> None:
        self._in_flight = False
        response = future.result()
        ok = getattr(response, 'success', True)
        self.sent += 1
        detail = getattr(response, 'error', '') or getattr(response, 'message', '')
        log = self.get_logger().info if ok else self.get_logger().error
        log(f'{self.service_name}: {"accepted" if ok else "refused"} {detail}'.rstrip())
        self._send()


def main(args: list[str] | None = None) -> int:
    return run_node(PayloadForwarder, 'payload_forwarder', args)


if __name__ == '__main__':
    sys.exit(main())
