"""The node's settings that may change while it runs (RUNTIME), validated as at start-up and
applied to the running pipeline and payload monitor; every other setting is read-only.

- ``forgetting_factor``: the RLS's from its next update on (what it has seen keeps its weight);
- ``payload.threshold``, ``payload.min_change``, ``payload.min_z``: the change detector's,
  from its next samples on;
- ``plausibility.margin``: the bounds every stage checks samples against, recomputed from the
  robot's limits.

ROS-free: the node (ros/node.py) calls ``validated`` from its parameter callback and ``apply``
under its processing lock.
"""
from __future__ import annotations

from typing import Any, Mapping

from identification_node.errors import IdentificationError
from identification_node.model.plausibility import PlausibilityBounds
from identification_node.settings import Settings

RUNTIME = ('forgetting_factor', 'payload.threshold', 'payload.min_change', 'payload.min_z',
           'plausibility.margin')
_DETECTOR = {'payload.threshold': 'threshold', 'payload.min_change': 'min_change',
             'payload.min_z': 'min_z'}


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
