"""The node's parameters: its settings, its outputs, and the settings that may change while it
runs.

- Settings (config.PARAMETERS): declared typed and ranged (``parameter_descriptor``),
  read-only unless RUNTIME has them.
- Outputs (OutputParameters): ``base_parameter_names`` and per base parameter
  ``estimate.<name>``, ``estimate_stddev.<name>``, ``estimate_unconstrained.<name>`` (and
  what else is declared through it, e.g. ``drive_gain.<joint>``): written by the node only.
- Run-time settings (RUNTIME, RuntimeParameters): validated as at start-up, applied to the
  running pipeline and payload monitor:

  - ``forgetting_factor``: the RLS's from its next update on (what it has seen keeps its
    weight);
  - ``payload.threshold``, ``payload.min_change``, ``payload.min_z``: the change detector's,
    from its next samples on;
  - ``plausibility.margin``: the bounds every stage checks samples against, recomputed from
    the robot's limits.

``validated`` and ``apply`` are ROS-free.
"""
from __future__ import annotations

import threading
from typing import Any, Mapping, Sequence

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from identification_node.config import descriptor
from identification_node.errors import IdentificationError
from identification_node.model.plausibility import PlausibilityBounds
from identification_node.settings import Settings

__all__ = ['ESTIMATE_PREFIX', 'RUNTIME', 'STDDEV_PREFIX', 'UNCONSTRAINED_PREFIX',
           'OutputParameters', 'RuntimeParameters', 'apply', 'declare_settings',
           'parameter_descriptor', 'validated']

RUNTIME = ('forgetting_factor', 'payload.threshold', 'payload.min_change', 'payload.min_z',
           'plausibility.margin')
ESTIMATE_PREFIX, STDDEV_PREFIX = 'estimate.', 'estimate_stddev.'
UNCONSTRAINED_PREFIX = 'estimate_unconstrained.'
_DETECTOR = {'payload.threshold': 'threshold', 'payload.min_change': 'min_change',
             'payload.min_z': 'min_z'}
_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}
_ARRAY_TYPES = {bool: Parameter.Type.BOOL_ARRAY, int: Parameter.Type.INTEGER_ARRAY,
                float: Parameter.Type.DOUBLE_ARRAY, str: Parameter.Type.STRING_ARRAY}


def parameter_descriptor(name: str, default: Any, text: str) -> ParameterDescriptor:
    """The rclpy descriptor of a settings table entry: config.descriptor's type and range,
    read-only unless RUNTIME has it."""
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


def validated(settings: Settings, changes: Mapping[str, Any], robot) -> Settings:
    """The settings with ``changes`` (RUNTIME names only), checked as at start-up (types,
    ranges, the pipeline's and the payload monitor's own checks); IdentificationError naming
    the parameter otherwise."""
    refused = sorted(set(changes) - set(RUNTIME))
    if refused:
        raise IdentificationError(f'parameter {refused[0]} is read-only while the node runs '
                                  f'(settable: {", ".join(RUNTIME)})')
    values = dict(settings.values)
    values.update(changes)
    new = Settings.from_dict(values)
    new.pipeline_config(robot.joint_names).validate(robot.dof)
    from identification_node.payload.monitor import MonitorConfig
    MonitorConfig(**{k: new[f'payload.{k}'] for k in _DETECTOR.values()}).validate()
    return Settings(new.values, settings.given | frozenset(changes))


def apply(pipeline, monitor, changes: Mapping[str, Any]) -> None:
    """Put validated ``changes`` into the running ``pipeline`` (IdentificationPipeline) and
    payload ``monitor`` (PayloadMonitor or None). Call under the lock that guards them."""
    for name, value in changes.items():
        if name == 'forgetting_factor':
            pipeline.config.forgetting = float(value)   # also for a reset's new RLS
            pipeline.rls.forgetting = float(value)
        elif name in _DETECTOR and monitor is not None:
            setattr(monitor.config, _DETECTOR[name], float(value))
            setattr(monitor.detector, _DETECTOR[name], float(value))
        elif name == 'plausibility.margin':
            pipeline.config.plausibility.margin = float(value)
            stages = pipeline.samples
            configs = stages.converter.configs
            stages.bounds.update(PlausibilityBounds.from_robot(
                pipeline.robot, pipeline.config.plausibility,
                [c.gear_ratio for c in configs], [c.kt for c in configs]))


class OutputParameters:
    """Parameters ``node`` publishes its results in (see the module doc), refused to anyone
    else; ``set`` writes them."""

    def __init__(self, node: Node, names: Sequence[str]):
        self.node = node
        self.names = {'base_parameter_names'}
        self._internal_update = False
        node.declare_parameter('base_parameter_names', list(names), ParameterDescriptor(
            description='base parameter names, in the order of ~/base_parameters'))
        for name in names:
            for prefix, text in ((ESTIMATE_PREFIX, 'estimate'), (STDDEV_PREFIX, 'stddev'),
                                 (UNCONSTRAINED_PREFIX, 'unconstrained estimate')):
                self.declare(prefix + name, 0.0, f'{text} of base parameter {name} (SI units)')
        node.add_on_set_parameters_callback(self._refuse_external_writes)

    def declare(self, name: str, value: Any, description: str) -> None:
        """Declare output parameter ``name`` with its initial ``value``."""
        self.node.declare_parameter(name, value, ParameterDescriptor(description=description))
        self.names.add(name)

    def set(self, params: list[Parameter]) -> None:
        """Write ``params`` at once (one parameter event); call from one thread at a time."""
        self._internal_update = True
        try:
            self.node.set_parameters_atomically(params)
        finally:
            self._internal_update = False

    def _refuse_external_writes(self, params: list[Parameter]) -> SetParametersResult:
        if not self._internal_update:
            for p in params:
                if p.name in self.names:
                    return SetParametersResult(
                        successful=False,
                        reason=f'{p.name} is an output of the node; it cannot be set')
        return SetParametersResult(successful=True)


class RuntimeParameters:
    """The node's settings: ``settings`` as declared (config.PARAMETERS), then as changed
    at run time once ``watch`` is called (RUNTIME names, see the module doc)."""

    def __init__(self, node: Node, table: dict[str, tuple[Any, str]]):
        self.node = node
        self.settings = Settings.from_dict(declare_settings(node, table))

    def watch(self, pipeline, monitor, lock: threading.Lock) -> None:
        """Validate changes of RUNTIME settings as at start-up, and apply them to
        ``pipeline`` and the payload ``monitor`` (or None) under ``lock``."""
        self._pipeline, self._monitor, self._lock = pipeline, monitor, lock
        self.node.add_on_set_parameters_callback(self._validate)
        self.node.add_post_set_parameters_callback(self._apply)

    def _validate(self, params: list[Parameter]) -> SetParametersResult:
        changes = {p.name: p.value for p in params if p.name in RUNTIME}
        if changes:
            try:
                validated(self.settings, changes, self._pipeline.robot)
            except IdentificationError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply(self, params: list[Parameter]) -> None:
        changes = {p.name: p.value for p in params if p.name in RUNTIME}
        if changes:
            with self._lock:
                self.settings = validated(self.settings, changes, self._pipeline.robot)
                apply(self._pipeline, self._monitor, changes)
            text = ', '.join(f'{k} = {v}' for k, v in changes.items())
            self.node.get_logger().info(f'set {text}')
