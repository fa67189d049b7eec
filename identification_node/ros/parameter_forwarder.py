"""Push identified quantities into another node's parameters (rcl_interfaces/SetParameters):
``ros2 run identification_node parameter_forwarder --ros-args -p preset:=admittance``.

Parameters (read-only):

- ``target``: the node whose parameters are set (``<target>/set_parameters``);
- ``mapping``: ``['remote.parameter=quantity', ...]`` (parameter_mapping.py: payload.mass,
  payload.weight, payload.com, payload.com.x|y|z, <joint>.fv|fc|fo|Ia, <link>.m, ...);
- ``source``: the identification node (default ``/identification_node``): its ``~/payload``
  and ``~/payload/stddev`` topics and its ``estimate.*`` / ``estimate_stddev.*`` parameters
  (their parameter events, one per estimate refresh);
- ``frame_parameter``: a parameter of the target naming the frame the payload's values must
  be in (the payload's frame_id, ``payload.link``); a payload in another frame is refused;
- ``threshold`` (3.0): a value is sent first when it passes its physical check, then only when
  it moved by more than this many standard deviations from the value last sent;
- ``preset``: ``admittance`` (ros2_controllers' admittance_controller: target
  /admittance_controller, gravity_compensation.CoG.pos = payload.com and
  gravity_compensation.CoG.force = payload.weight, frame from gravity_compensation.frame.id).
  Explicit parameters override the preset's.

Never sent: a value that fails its physical check (payload mass <= 0; a friction coefficient or
rotor inertia < 0; a link mass <= 0), one not excited or not determined, or a quantity the
identified model does not determine on its own (a regrouped base parameter): each reason is
logged once. The changed values of one refresh go in one SetParameters call; a value the
target refuses is logged and tried again at the next change.
"""
from __future__ import annotations

import sys
from typing import Any

import numpy as np
from geometry_msgs.msg import InertiaStamped
from rcl_interfaces.msg import ParameterDescriptor, ParameterEvent
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from identification_node.errors import IdentificationError
from identification_node.parameter_mapping import (PRESETS, ChangeGate, Quantity,
                                                   check_estimate_quantity, estimate_quantity,
                                                   parse_mapping, payload_quantity)
from identification_node.ros.spin import run_node

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
EVENTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                    reliability=ReliabilityPolicy.RELIABLE)
# name: (default, description); all read-only. A preset's values apply where not given.
PARAMETERS: dict[str, tuple[Any, str]] = {
    'preset': ('', 'admittance: ros2_controllers admittance_controller gravity compensation'),
    'target': ('', 'node whose parameters are set (preset admittance: /admittance_controller)'),
    'mapping': ([], "['remote.parameter=quantity', ...]: payload.mass, payload.weight, "
                'payload.com, payload.com.x|y|z, <joint>.fv|fc|fo|Ia, <link>.m'),
    'source': ('identification_node', 'the identification node (its ~/payload, '
               '~/payload/stddev and estimate.* parameters)'),
    'frame_parameter': ('', "target parameter naming the frame of the payload's values "
                        '(admittance: gravity_compensation.frame.id)'),
    'threshold': (3.0, 'a change is sent when it exceeds this many standard deviations'),
}


def _absolute(name: str) -> str:
    """A node name as its fully qualified name (as parameter events carry it)."""
    name = name.strip().rstrip('/')
    return name if not name or name.startswith('/') else '/' + name


class ParameterForwarder(Node):
    """See the module docstring."""

    def __init__(self, node_name: str = 'parameter_forwarder', **kwargs: Any):
        super().__init__(node_name, **kwargs)
        text = ParameterDescriptor(read_only=True, dynamic_typing=True)
        given = {k: self.declare_parameter(k, None, text).value for k in PARAMETERS}
        preset = str(given['preset'] or '')
        if preset and preset not in PRESETS:
            raise IdentificationError(f'parameter preset: {preset!r}; choose from '
                                      f'{", ".join(PRESETS)}')
        base = PRESETS.get(preset, {})
        self.target = _absolute(str(given['target'] or base.get('target', '')))
        if not self.target:
            raise IdentificationError('parameter target: name the node to set parameters of '
                                      '(or a preset)')
        try:
            self.mapping = parse_mapping(list(given['mapping']) if given['mapping']
                                         else base.get('mapping', {}))
        except IdentificationError as exc:
            raise IdentificationError(f'parameter mapping: {exc}') from None
        self.source = _absolute(str(given['source'] or 'identification_node'))
        self.frame_parameter = str(base.get('frame_parameter', '') if given['frame_parameter']
                                   is None else given['frame_parameter'])
        threshold = 3.0 if given['threshold'] is None else given['threshold']
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) \
                or not threshold >= 0:
            raise IdentificationError(f'parameter threshold = {threshold!r} must be a number '
                                      '>= 0 (standard deviations)')
        self.gate = ChangeGate(float(threshold))
        self.sent = self.refused = 0   # values set; payloads refused for their frame
        self._refused_stamp = None
        self.problems: set[str] = set()
        self.payload: tuple[InertiaStamped, InertiaStamped] | None = None
        self._payload_sd: InertiaStamped | None = None
        self._payload_value: InertiaStamped | None = None
        self._estimate: dict[str, float] = {}
        self._stddev: dict[str, float] = {}
        self._base_names: list[str] | None = None
        self._frame: str | None = None if self.frame_parameter else ''
        self._in_flight = False
        self._asking: set[str] = set()
        self._set = self.create_client(SetParameters, f'{self.target}/set_parameters')
        self._get_target = self.create_client(GetParameters, f'{self.target}/get_parameters')
        self._get_source = self.create_client(GetParameters, f'{self.source}/get_parameters')
        quantities = set(self.mapping.values())
        if any(q.startswith('payload.') for q in quantities):
            self.create_subscription(InertiaStamped, f'{self.source}/payload',
                                     self._on_payload, LATCHED)
            self.create_subscription(InertiaStamped, f'{self.source}/payload/stddev',
                                     self._on_payload_sd, LATCHED)
        if any(not q.startswith('payload.') for q in quantities):
            self.create_subscription(ParameterEvent, '/parameter_events', self._on_event,
                                     EVENTS)
        else:
            self._base_names = []
        self.create_timer(0.1, self._send)
        self.get_logger().info(f'forwarding {self.mapping} to {self.target} (changes beyond '
                               f'{self.gate.threshold:g} stddev)')

    # -- inputs -----------------------------------------------------------------------------------
    def _on_payload_sd(self, msg: InertiaStamped) -> None:
        self._payload_sd = msg
        self._pair()

    def _on_payload(self, msg: InertiaStamped) -> None:
        self._payload_value = msg
        self._pair()

    def _pair(self) -> None:
        """A payload with its standard deviations (the same stamp; either may come first)."""
        value, sd = self._payload_value, self._payload_sd
        if value is not None and sd is not None and value.header.stamp == sd.header.stamp:
            self.payload = (value, sd)
            self._send()

    def _on_event(self, event: ParameterEvent) -> None:
        if event.node != self.source:
            return
        for p in list(event.new_parameters) + list(event.changed_parameters):
            value = parameter_value_to_python(p.value)
            if p.name.startswith('estimate.'):
                self._estimate[p.name[len('estimate.'):]] = value
            elif p.name.startswith('estimate_stddev.'):
                self._stddev[p.name[len('estimate_stddev.'):]] = value
        self._send()

    def _problem(self, text: str) -> None:
        if text not in self.problems:
            self.problems.add(text)
            self.get_logger().error(text)

    # -- look-ups -----------------------------------------------------------------------------
    def _ask(self, key: str, client, names: list[str], done) -> None:
        """GetParameters ``names`` once the service is there; ``done(values)``."""
        if key in self._asking or not client.service_is_ready():
            return
        self._asking.add(key)

        def finished(future) -> None:
            self._asking.discard(key)
            result = future.result()
            if result is not None:
                done([parameter_value_to_python(v) for v in result.values])
        client.call_async(GetParameters.Request(names=names)).add_done_callback(finished)

    def _set_base_names(self, values: list) -> None:
        names = list(values[0] or [])
        for remote, quantity in list(self.mapping.items()):
            why = check_estimate_quantity(quantity, names)
            if why:
                self._problem(f'{remote}: {why}; not forwarded')
                del self.mapping[remote]
        self._base_names = names

    def _set_frame(self, values: list) -> None:
        if values[0] is None:
            self._problem(f'{self.target} has no parameter {self.frame_parameter}')
        self._frame = str(values[0] or '')

    # -- output -------------------------------------------------------------------------------
    def _quantity(self, name: str) -> Quantity | None:
        if name.startswith('payload.'):
            if self.payload is None:
                return None
            msg, sd = self.payload
            if self._frame and msg.header.frame_id != self._frame:
                if self._refused_stamp != msg.header.stamp:
                    self._refused_stamp = msg.header.stamp
                    self.refused += 1
                return Quantity(np.zeros(1), np.zeros(1), problem=(
                    f'payload in frame {msg.header.frame_id!r}, {self.target} expects '
                    f'{self._frame!r} ({self.frame_parameter}): set payload.link to it'))
            i, s = msg.inertia, sd.inertia
            return payload_quantity(name, i.m, (i.com.x, i.com.y, i.com.z), s.m,
                                    (s.com.x, s.com.y, s.com.z))
        if name not in self._estimate or name not in self._stddev:
            return None
        return estimate_quantity(name, self._estimate[name], self._stddev[name])

    def _send(self) -> None:
        if self._base_names is None:
            self._ask('names', self._get_source, ['base_parameter_names'], self._set_base_names)
        if self._frame is None:
            self._ask('frame', self._get_target, [self.frame_parameter], self._set_frame)
        if (self._in_flight or self._base_names is None or self._frame is None
                or not self._set.service_is_ready()):
            return
        due = {}
        for remote, name in self.mapping.items():
            q = self._quantity(name)
            if q is None:
                continue
            if q.problem:
                self._problem(f'{remote} = {name}: {q.problem}; not forwarded')
            elif self.gate.due(remote, q):
                due[remote] = q
        if not due:
            return
        request = SetParameters.Request(parameters=[
            Parameter(k, value=q.as_parameter()).to_parameter_msg() for k, q in due.items()])
        self._in_flight = True
        self._set.call_async(request).add_done_callback(lambda f: self._done(f, due))

    def _done(self, future, due: dict[str, Quantity]) -> None:
        self._in_flight = False
        response = future.result()
        results = list(response.results) if response is not None else []
        for (remote, q), result in zip(due.items(), results):
            if result.successful:
                self.gate.mark_sent(remote, q)
                self.sent += 1
                self.get_logger().info(f'{self.target}: {remote} = {q.as_parameter()}')
            else:
                self.get_logger().error(f'{self.target} refused {remote} = '
                                        f'{q.as_parameter()}: {result.reason}')


def main(args: list[str] | None = None) -> int:
    return run_node(ParameterForwarder, 'parameter_forwarder', args)


if __name__ == '__main__':
    sys.exit(main())
