"""The pipeline's settings; their defaults are the node parameters' (config.py)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from identification_node.config import default
from identification_node.errors import IdentificationError
from identification_node.estimation.robust import RobustSettings
from identification_node.model.plausibility import PlausibilitySettings
from identification_node.model.torque import JointTorqueConfig

# PipelineConfig fields whose parameter has another name.
CONFIG_FIELD_PARAMETERS = {
    'forgetting': 'forgetting_factor', 'half_window': 'smoother.half_window',
    'smoother_order': 'smoother.order', 'max_gap': 'smoother.max_gap',
    'cutoff': 'smoother.cutoff', 'auto_seconds': 'smoother.auto_seconds',
    'velocity': 'velocity_source', 'offset_warn': 'time_offset.warn',
    'offset_refuse': 'time_offset.refuse',
    'offset_seconds': 'time_offset.seconds', 'offset_search': 'time_offset.search'}


def _default(name: str) -> Any:
    """The default of the node parameter behind PipelineConfig field ``name``."""
    value = default(CONFIG_FIELD_PARAMETERS.get(name, name))
    return tuple(value) if isinstance(value, list) else value


@dataclass
class PipelineConfig:
    """Settings of the pipeline (the node's ROS parameters map onto these fields, see
    CONFIG_FIELD_PARAMETERS for those named otherwise)."""
    torque: Mapping[str, JointTorqueConfig] = field(default_factory=dict)
    forgetting: float = _default('forgetting')
    half_window: int = _default('half_window')
    smoother_order: int = _default('smoother_order')
    cutoff: float = _default('cutoff')            # Hz; 0: chosen from the data
    auto_seconds: float = _default('auto_seconds')
    max_gap: float = _default('max_gap')
    velocity: str = _default('velocity')
    align_tolerance: float = _default('align_tolerance')
    hold_time: float = _default('hold_time')
    restart_jump: float = _default('restart_jump')
    update_batch: int = _default('update_batch')
    offset_warn: float = _default('offset_warn')   # s; 0: no time offset check
    offset_refuse: float = _default('offset_refuse')
    offset_seconds: float = _default('offset_seconds')
    offset_search: float = _default('offset_search')
    joint_noise_std: Sequence[float] = _default('joint_noise_std')
    coulomb_exclusion_speed: float = _default('coulomb_exclusion_speed')
    converged_ratio: float = _default('converged_ratio')
    max_condition: float = _default('max_condition')
    min_samples: int = _default('min_samples')
    plausibility: PlausibilitySettings = field(default_factory=PlausibilitySettings)
    robust: RobustSettings = field(default_factory=RobustSettings)
    max_names: int = _default('max_names')     # more names in a message: rejected
    layout_cache_bytes: int = _default('layout_cache_bytes')   # bound of the layout caches

    def validate(self, dof: int) -> None:
        """Raise IdentificationError naming the first bad field."""
        checks = [
            ('forgetting', 0.9 <= self.forgetting <= 1.0, 'in [0.9, 1.0]'),
            ('half_window', int(self.half_window) >= 0, '>= 0 (0: from the cut-off)'),
            ('smoother_order', 2 <= int(self.smoother_order)
             <= min(4, 2 * self.half_window or 4), 'in [2, min(4, 2 * half_window)]'),
            ('cutoff', self.cutoff >= 0, '>= 0 Hz (0: chosen from the data)'),
            ('auto_seconds', self.auto_seconds > 0, '> 0 s'),
            ('max_gap', self.max_gap > 0, '> 0'),
            ('velocity', self.velocity in ('auto', 'measured', 'differentiate'),
             "'auto', 'measured' or 'differentiate'"),
            ('align_tolerance', self.align_tolerance > 0, '> 0'),
            ('hold_time', self.hold_time > 0, '> 0'),
            ('restart_jump', self.restart_jump > 0, '> 0'),
            ('update_batch', int(self.update_batch) >= 1, '>= 1'),
            ('offset_warn', self.offset_warn >= 0, '>= 0 s (0: no check)'),
            ('offset_refuse', self.offset_refuse >= self.offset_warn, '>= time_offset.warn'),
            ('offset_seconds', self.offset_seconds > 0, '> 0 s'),
            ('offset_search', self.offset_search > 0, '> 0 s'),
            ('joint_noise_std', len(self.joint_noise_std) in (0, dof)
             and all(s > 0 for s in self.joint_noise_std), f'empty or {dof} values > 0'),
            ('coulomb_exclusion_speed', self.coulomb_exclusion_speed >= 0, '>= 0'),
            ('converged_ratio', self.converged_ratio > 0, '> 0'),
            ('max_condition', self.max_condition > 1, '> 1'),
            ('min_samples', int(self.min_samples) >= 0, '>= 0'),
            ('max_names', int(self.max_names) >= 1, '>= 1'),
            ('layout_cache_bytes', int(self.layout_cache_bytes) >= 0, '>= 0'),
        ]
        for name, ok, expected in checks:
            value = getattr(self, name)
            if not ok or (isinstance(value, float) and not math.isfinite(value)):
                raise IdentificationError(f'parameter {name} = {value!r} must be {expected}')
        self.plausibility.validate(dof)
        self.robust.validate()
