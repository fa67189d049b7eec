"""Settings of the node and of offline replay, from one flat parameter dictionary.

The keys are the node's ROS parameter names (config.py, config/identification.yaml); a YAML
file in the ROS parameter-file layout (``node: {ros__parameters: {...}}``) or a plain mapping
works, nested keys being joined with dots. Values are validated once (config.validated), for
the node and the CLI alike: a bad value raises IdentificationError naming the parameter.
Settings turns them into the robot, the pipeline and the consistent solve's options.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping

from identification_node.config import PER_JOINT, Config, flatten, parameters_of, validated
from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import ConsistencyOptions
from identification_node.estimation.robust import RobustSettings
from identification_node.model.plausibility import PlausibilitySettings
from identification_node.model.robot import RobotModel, load_robot
from identification_node.model.torque import JointTorqueConfig
from identification_node.pipeline import IdentificationPipeline, PipelineConfig
from identification_node.pipeline.config import CONFIG_FIELD_PARAMETERS
from identification_node.safe_yaml import read_yaml

__all__ = ['Settings', 'read_parameter_file']


def read_parameter_file(path: str | Path) -> dict[str, Any]:
    """The parameters of a ROS parameter YAML file (first node's ros__parameters) or of a
    plain YAML mapping, flattened; scalars read as rcl reads them (safe_yaml.ros_scalar)."""
    return parameters_of(read_yaml(path, f'parameter file {path}', ros=True),
                         f'parameter file {path}')


@dataclass
class Settings:
    """Validated settings; ``build`` turns them into the robot and the pipeline."""
    values: dict[str, Any]
    given: frozenset = frozenset()

    @property
    def given_robot(self) -> bool:
        """Whether the robot was set explicitly (not the default)."""
        return bool({'robot', 'robot_description'} & self.given)

    @classmethod
    def from_dict(cls, given: Mapping[str, Any]) -> Settings:
        """Settings of ``given`` (nested or dotted parameter names; defaults for the rest),
        validated (config.validated, and the consistent solve's options)."""
        values = validated(given)
        settings = cls(values, frozenset(flatten(given)))
        settings.consistency_options()
        return settings

    @property
    def config(self) -> Config:
        """The settings as the typed tree of config.py."""
        return Config.from_values(self.values)

    def __getitem__(self, name: str) -> Any:
        return self.values[name]

    @property
    def output_directory(self) -> Path:
        return Path(self.values['output_directory']).expanduser().resolve()

    def consistency_options(self) -> ConsistencyOptions | None:
        """The constrained solve's options (validated), None when physical_consistency is
        false."""
        if not self.values['physical_consistency']:
            return None
        c = self.config.consistency
        given: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                                 for k, v in asdict(c).items()}
        options = ConsistencyOptions(**dict(given, solver=c.solver.upper()))
        options.validate()
        return options

    def load_robot(self) -> RobotModel:
        v = self.values
        source = v['robot_description'] if v['robot_description'].strip() else v['robot']
        return load_robot(source, v['joints'] or None, extras=v['extras'],
                          coulomb_velocity=v['coulomb_velocity'])

    def torque_configs(self, joints: list[str]) -> dict[str, JointTorqueConfig]:
        per_joint = {}
        for name in PER_JOINT:
            value = self.values[name]
            if len(value) not in (1, len(joints)):
                raise IdentificationError(
                    f'parameter {name} has {len(value)} values; give 1 or one per joint '
                    f'({len(joints)}: {joints})')
            per_joint[name] = value * len(joints) if len(value) == 1 else value
        out = {}
        for i, joint in enumerate(joints):
            try:
                out[joint] = JointTorqueConfig.from_dict({
                    'source': per_joint['torque_source'][i], 'kt': per_joint['kt'][i],
                    'gear_ratio': per_joint['gear_ratio'][i],
                    'pole_pairs': per_joint['pole_pairs'][i],
                    'angle_offset': per_joint['angle_offset'][i],
                    'phase_order': per_joint['phase_order'][i]})
            except IdentificationError as exc:   # '... joint '(unnamed)': <field> must be ...'
                detail = str(exc).split(': ', 1)[-1]
                field = detail.split(' ', 1)[0]
                name = 'torque_source' if field == 'source' else field
                raise IdentificationError(f'parameter {name} of joint {joint}: {detail}') \
                    from None
        return out

    def pipeline_config(self, joints: list[str]) -> PipelineConfig:
        """The pipeline's settings for the identified ``joints``."""
        v = self.values
        tree = self.config
        return PipelineConfig(
            torque=self.torque_configs(joints), forgetting=v['forgetting_factor'],
            half_window=v['smoother.half_window'], smoother_order=v['smoother.order'],
            cutoff=v['smoother.cutoff'], auto_seconds=v['smoother.auto_seconds'],
            max_gap=v['smoother.max_gap'], velocity=v['velocity_source'],
            align_tolerance=v['align_tolerance'], hold_time=v['hold_time'],
            restart_jump=v['restart_jump'], update_batch=v['update_batch'],
            offset_warn=v['time_offset.warn'], offset_refuse=v['time_offset.refuse'],
            offset_seconds=v['time_offset.seconds'], offset_search=v['time_offset.search'],
            joint_noise_std=v['joint_noise_std'],
            coulomb_exclusion_speed=v['coulomb_exclusion_speed'],
            converged_ratio=v['converged_ratio'], max_condition=v['max_condition'],
            min_samples=v['min_samples'],
            plausibility=PlausibilitySettings(**asdict(tree.plausibility)),
            robust=RobustSettings(**asdict(tree.robust)),
            max_names=v['max_names'], layout_cache_bytes=v['layout_cache_bytes'])

    def build(self, robot: RobotModel | None = None) -> IdentificationPipeline:
        """The pipeline these settings describe (loading the robot unless given)."""
        robot = robot or self.load_robot()
        try:
            return IdentificationPipeline(robot, self.pipeline_config(robot.joint_names))
        except IdentificationError as exc:   # name the parameter, not the PipelineConfig field
            text = str(exc)
            for field, name in CONFIG_FIELD_PARAMETERS.items():
                if text.startswith(f'parameter {field} '):
                    text = f'parameter {name} ' + text[len(f'parameter {field} '):]
            raise IdentificationError(text) from None
