"""Settings of the node and of offline replay, from one flat parameter dictionary.

The keys are the node's ROS parameter names (see config/identification.yaml); a YAML file in
the ROS parameter-file layout (``node: {ros__parameters: {...}}``) or a plain mapping works,
nested keys being joined with dots. Values are validated here, once, for the node and the CLI
alike: a bad value raises IdentificationError naming the parameter.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import ConsistencyOptions
from identification_node.estimation.robust import RobustSettings
from identification_node.model.plausibility import PlausibilitySettings
from identification_node.model.robot import RobotModel, load_robot
from identification_node.model.torque import JointTorqueConfig
from identification_node.safe_yaml import read_yaml

if TYPE_CHECKING:   # the pipeline's defaults come from PARAMETERS below: imported when used
    from identification_node.pipeline import IdentificationPipeline, PipelineConfig

# name: (default, description). Per-joint lists hold one value for every joint, or one per
# identified joint in the order of `joints`.
PARAMETERS: dict[str, tuple[Any, str]] = {
    'robot': ('mit_dd_arm', 'bundled robot name or URDF/MJCF file path'),
    'robot_description': ('', 'URDF XML; when set it is used instead of `robot`'),
    'joints': ([], 'identified joints in this order (empty: all movable joints but URDF '
               '<mimic> ones and those they follow; identify: those the bag carries, the others '
               'locked)'),
    'extras': (['fv', 'fc', 'fo'], 'per-joint extra columns among fv (viscous), fc (Coulomb), '
               'fo (offset), Ia (rotor inertia); [] for none'),
    'coulomb_velocity': (0.0, 'rad/s; > 0 smooths the Coulomb sign as tanh(qd / value)'),
    'torque_source': (['measured'], 'per joint: measured, current or three_phase'),
    'kt': ([1.0], 'per joint motor torque constant, N m/A'),
    'gear_ratio': ([1.0], 'per joint gear ratio (joint torque = ratio * motor torque)'),
    'pole_pairs': ([1], 'per joint motor pole pairs'),
    'angle_offset': ([0.0], 'per joint electrical angle offset, rad'),
    'phase_order': (['abc'], 'per joint phase order: abc or acb'),
    'forgetting_factor': (1.0, 'RLS forgetting factor per sample in [0.9, 1]; 1 = none'),
    'smoother.half_window': (0, 'fixed-lag smoother half window, samples (the delay); 0: '
                             'from smoother.cutoff and the sampling rate; > 0 wins over it'),
    'smoother.cutoff': (0.0, 'Hz, -3 dB cut-off of the smoother; 0: chosen from the first '
                        'smoother.auto_seconds of motion (reported)'),
    'smoother.auto_seconds': (5.0, 's of motion the automatic cut-off is chosen from (held '
                              'back until then)'),
    'smoother.order': (3, 'polynomial order of the smoother'),
    'smoother.max_gap': (0.05, 's; a larger stamp gap restarts the smoother'),
    'velocity_source': ('auto', 'auto, measured or differentiate'),
    'align_tolerance': (0.002, 's; currents are matched to joint states within this'),
    'hold_time': (0.1, 's to wait for currents before a joint state is given up'),
    'restart_jump': (1.0, 's; a larger backward stamp jump is a restarted stream'),
    'time_offset.warn': (0.02, 's; the offset between the torque (currents or effort) and the '
                         'motion is estimated (pipeline/time_offset.py); one beyond this is '
                         'warned of (identify, /diagnostics); 0: not checked'),
    'time_offset.refuse': (0.1, 's; an offset beyond this makes identify refuse the bag and the '
                           'node report an error in /diagnostics'),
    'time_offset.seconds': (10.0, 's of motion (the first of a stream) the offset is estimated '
                            'from'),
    'time_offset.search': (1.0, 's; offsets are searched within +- this'),
    'update_batch': (50, 'samples gathered per RLS update (predictions use the estimate so far)'),
    'joint_noise_std': ([], 'per joint torque noise std for weighting, N m (empty: equal)'),
    'coulomb_exclusion_speed': (0.1, 'rad/s (m/s); > 0 with fc identified: a joint equation '
                                'is left out while |qd| < this (the Coulomb column is what the '
                                'smoother makes of sign(qd); with coulomb_velocity > 0: while '
                                '|qd| < this + |qdd| * smoother half window; batch: within the '
                                'filter\'s reach of |qd| < this); 0: none'),
    'converged_ratio': (0.1, 'converged when parameter uncertainty < ratio * residual RMS'),
    'max_condition': (1e8, 'largest information condition number counted as excited'),
    'min_samples': (1000, 'samples needed before convergence is declared'),
    'process_period': (0.01, 's (wall clock) between batch processing runs (latency vs CPU)'),
    'publish.effort_rate': (0.0, 'Hz for predicted/measured effort; 0 = every sample'),
    'publish.estimate_rate': (1.0, 'Hz for base_parameters, estimate.* and robot_description'),
    'publish.diagnostics_rate': (1.0, 'Hz for /diagnostics'),
    'output_directory': ('identification_output', 'directory the save service writes into'),
    # robustness (plausibility.py, robust.py)
    'plausibility.margin': (2.0, 'URDF limits are widened by this factor (>= 1) into the '
                            'bounds beyond which samples are rejected as implausible'),
    'plausibility.position': (1e6, 'rad (prismatic: / 10 m); |q| bound of joints without range'),
    'plausibility.velocity': (100.0, 'rad/s (prismatic: / 10 m/s) without a URDF velocity limit'),
    'plausibility.acceleration': (1000.0, 'rad/s^2 (prismatic: / 10 m/s^2) |qdd| bound'),
    'plausibility.effort': (1e4, 'N m (or N) without a URDF effort limit'),
    'plausibility.current_limit': ([], 'per joint motor current bound, A (empty or 0: the '
                                   'current giving the torque bound through kt and gear_ratio)'),
    'robust.enabled': (True, 'innovation gating of outliers once the estimate converged'),
    'robust.k': (5.0, 'a sample beyond k residual standard deviations is an outlier'),
    'robust.window': (1000, 'samples over which the fraction of outliers is watched'),
    'robust.shift_fraction': (0.5, 'this fraction of outliers in the window is a residual '
                              'shift: reported, and gating stops until it falls below half'),
    'max_names': (256, 'names per input message; messages with more are rejected'),
    'layout_cache_bytes': (4 << 20, 'bytes of message layouts (name lists) kept decoded'),
    'watchdog_timeout': (10.0, 's without the executor or processing making progress after '
                         'which the node logs it and exits (status 3) for a supervisor; 0: off'),
    'input_queue_bytes': (64 << 20, 'bytes of input messages held per topic until processed; '
                          'beyond, the oldest are dropped (diagnostics dropped_messages.*)'),
    'lost_messages.middleware_event': (False, "count lost messages also by the middleware's "
                                       'message-lost event (several publishers); off: it can '
                                       'deadlock rmw_fastrtps under bursts'),
    'payload.enabled': (False, 'identify a payload and detect its changes (pick, place)'),
    'drive_gains.back_emf': (False, 'identify the drive gains (N m/A at the joint) from '
                             'motor_voltages by the back-EMF (current-driven joints)'),
    'drive_gains.known_payload': (False, 'identify the drive gains from segments with a known '
                                  'payload (service ~/drive_gains/known_payload)'),
    'payload.link': ('', 'link or fixed frame carrying the payload (empty: the last '
                     'identified link)'),
    'payload.arm': ('', "the arm's parameters the payload is fitted against: an estimate.yaml "
                    "(~/save) of the arm without payload; 'estimate': the running estimate, "
                    "taken at each ~/payload/reset; empty: the model's own"),
    'payload.fit_time': (1.0, 's of samples after a change before the payload is fitted'),
    'payload.settle': (0.1, 's after a detection before samples are used'),
    'payload.refresh': (5.0, 's between refits while the payload stays'),
    'payload.window': (0.25, 's, moving window of the change detector'),
    'payload.threshold': (50.0, 'change detector chi-square threshold (4 dof)'),
    'payload.min_change': (0.2, 'kg; the smallest mass change declared (detection threshold)'),
    'payload.min_z': (8.0, 'a mass change is declared at this many of its standard deviations'),
    'payload.confirm': (0.1, 's the change conditions must hold before a change is declared'),
    'payload.cutoff': (20.0, "Hz, -3 dB cut-off of the payload monitor's own smoother (its "
                       'delay ~ 0.7 / cutoff s at any rate; the estimator keeps its own)'),
    'payload.tolerance.mass': (0.02, 'kg; mass stddev above this: not excited'),
    'payload.tolerance.com': (0.005, 'm; centre of mass stddev above this: not excited'),
    'payload.tolerance.inertia': (0.002, 'kg m^2; inertia stddev above this: not excited'),
    'physical_consistency': (True, 'publish and save the physically consistent estimate '
                             '(constrained least squares); false: the unconstrained one only'),
    'consistency.weight': (1e-3, 'weight of the log-det prior toward the description\'s '
                           'inertials where no consistent body lies in the confidence region, '
                           'in chi-square units of the data term'),
    'consistency.confidence': (0.99, 'chi-square level of the data\'s confidence region inside '
                               'which the prior (closest to the description) chooses; 0: '
                               'none, the data\'s best consistent fit'),
    'consistency.mass_ratio': (3.0, 'each link\'s mass within [1/r, r] times the description\'s '
                               '(0: no bound); a bound in use is reported'),
    'consistency.total_mass': ([], 'kg, [lo, hi] of the identified links\' total mass (empty: '
                               'none)'),
    'save_inconsistent': (False, '~/save writes identified.urdf even when the estimate is not '
                          'physically consistent'),
    'consistency.margin': (1e-6, 'pseudo-inertia margin: J - margin * 1 >= 0 (kg, kg m^2)'),
    'consistency.solver': ('CLARABEL', 'cvxpy solver: CLARABEL or SCS'),
    'consistency.time_limit': (5.0, 's per constrained solve; on time-out the unconstrained '
                               'estimate is kept and the failure reported'),
    'consistency.geometry_box': (True, 'bound each centre of mass by the bounding box of its '
                                 'link\'s URDF collision/visual primitives, where it has some'),
    'consistency.mass_min': ([], 'per identified link lower mass bound, kg (empty: none)'),
    'consistency.mass_max': ([], 'per identified link upper mass bound, kg (empty: none)'),
    'consistency.com_box': ([], '6 values per identified link: centre of mass box lo x y z, '
                            'hi x y z in the link frame, m (empty: geometry_box)'),
}
# List parameters of floats whose default is empty (their element type cannot be read off).
FLOAT_LISTS = ('joint_noise_std', 'plausibility.current_limit', 'consistency.mass_min',
               'consistency.mass_max', 'consistency.com_box', 'consistency.total_mass')
# List parameters with a default for which [] is a value too (ROS types [] as bytes).
EMPTY_LISTS = ('extras',)

# Inclusive ranges of numeric parameters: the node's typed parameter descriptors carry them and
# Settings checks them, for the node and the offline configuration alike (bounds that exclude
# their end, such as > 0, are checked where the value is used).
RANGES: dict[str, tuple[float, float]] = {
    'coulomb_velocity': (0.0, math.inf),
    'forgetting_factor': (0.9, 1.0),
    'smoother.half_window': (0, 10_000),
    'smoother.cutoff': (0.0, 1e6),
    'smoother.auto_seconds': (0.1, 3600.0),
    'smoother.order': (2, 4),
    'update_batch': (1, 10**9),
    'time_offset.warn': (0.0, 10.0),
    'time_offset.refuse': (0.0, 10.0),
    'time_offset.seconds': (1.0, 3600.0),
    'time_offset.search': (0.01, 60.0),
    'coulomb_exclusion_speed': (0.0, math.inf),
    'min_samples': (0, 10**12),
    'publish.effort_rate': (0.0, math.inf),
    'input_queue_bytes': (1, 1 << 62),
}
PER_JOINT = ('torque_source', 'kt', 'gear_ratio', 'pole_pairs', 'angle_offset', 'phase_order')
# PipelineConfig fields whose parameter has another name.
CONFIG_FIELD_PARAMETERS = {
    'forgetting': 'forgetting_factor', 'half_window': 'smoother.half_window',
    'smoother_order': 'smoother.order', 'max_gap': 'smoother.max_gap',
    'cutoff': 'smoother.cutoff', 'auto_seconds': 'smoother.auto_seconds',
    'velocity': 'velocity_source', 'offset_warn': 'time_offset.warn',
    'offset_refuse': 'time_offset.refuse',
    'offset_seconds': 'time_offset.seconds', 'offset_search': 'time_offset.search'}


def flatten(tree: Mapping, prefix: str = '') -> dict[str, Any]:
    """Nested mapping to dotted keys."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            out.update(flatten(value, name + '.'))
        else:
            out[name] = value
    return out


def read_parameter_file(path: str | Path) -> dict[str, Any]:
    """The parameters of a ROS parameter YAML file (first node's ros__parameters) or of a
    plain YAML mapping, flattened."""
    data = read_yaml(path, f'parameter file {path}')
    if not isinstance(data, Mapping):
        raise IdentificationError(f'parameter file {path} does not hold a mapping')
    for node, value in data.items():
        if isinstance(value, Mapping) and 'ros__parameters' in value:
            if not isinstance(value['ros__parameters'], Mapping):
                raise IdentificationError(f'parameter file {path}: {node}.ros__parameters '
                                          'is not a mapping of parameter names to values')
            return flatten(value['ros__parameters'])
    return flatten(data)


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
        given = flatten(given)
        unknown = sorted(set(given) - set(PARAMETERS))
        if unknown:
            raise IdentificationError(f'unknown parameter(s) {unknown}; known: '
                                      f'{sorted(PARAMETERS)}')
        values = {k: default for k, (default, _) in PARAMETERS.items()}
        values.update(given)
        for name, (default, _) in PARAMETERS.items():
            values[name] = coerce(name, values[name], default)
        if values['watchdog_timeout'] < 0:
            raise IdentificationError('parameter watchdog_timeout must be >= 0')
        for name, (lo, hi) in RANGES.items():
            if not lo <= values[name] <= hi:
                raise IdentificationError(
                    f'parameter {name} = {values[name]} must be in [{lo}, {hi}]')
        for name in ('process_period', 'publish.estimate_rate', 'publish.diagnostics_rate'):
            if not values[name] > 0:
                raise IdentificationError(f'parameter {name} = {values[name]} must be > 0')
        if values['publish.effort_rate'] < 0:
            raise IdentificationError('parameter publish.effort_rate must be >= 0')
        if not str(values['output_directory']).strip():
            raise IdentificationError('parameter output_directory must not be empty')
        settings = cls(values, frozenset(given))
        settings.consistency_options()
        return settings

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
        v = self.values
        options = ConsistencyOptions(
            weight=v['consistency.weight'], margin=v['consistency.margin'],
            solver=v['consistency.solver'].upper(), time_limit=v['consistency.time_limit'],
            geometry_box=v['consistency.geometry_box'], mass_min=tuple(v['consistency.mass_min']),
            mass_max=tuple(v['consistency.mass_max']), com_box=tuple(v['consistency.com_box']),
            confidence=v['consistency.confidence'], mass_ratio=v['consistency.mass_ratio'],
            total_mass=tuple(v['consistency.total_mass']))
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
        from identification_node.pipeline import PipelineConfig
        v = self.values
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
            plausibility=PlausibilitySettings(
                margin=v['plausibility.margin'], position=v['plausibility.position'],
                velocity=v['plausibility.velocity'],
                acceleration=v['plausibility.acceleration'], effort=v['plausibility.effort'],
                current_limit=v['plausibility.current_limit']),
            robust=RobustSettings(enabled=v['robust.enabled'], k=v['robust.k'],
                                  window=v['robust.window'],
                                  shift_fraction=v['robust.shift_fraction']),
            max_names=v['max_names'], layout_cache_bytes=v['layout_cache_bytes'])

    def build(self, robot: RobotModel | None = None) -> IdentificationPipeline:
        """The pipeline these settings describe (loading the robot unless given)."""
        from identification_node.pipeline import IdentificationPipeline
        robot = robot or self.load_robot()
        try:
            return IdentificationPipeline(robot, self.pipeline_config(robot.joint_names))
        except IdentificationError as exc:   # name the parameter, not the PipelineConfig field
            text = str(exc)
            for field, name in CONFIG_FIELD_PARAMETERS.items():
                if text.startswith(f'parameter {field} '):
                    text = f'parameter {name} ' + text[len(f'parameter {field} '):]
            raise IdentificationError(text) from None


def element_type(name: str, default: list) -> type:
    """The type of the elements of list parameter ``name`` (its default's, or for an empty
    default float for the per-joint numbers and str otherwise)."""
    return type(default[0]) if default else (float if name in FLOAT_LISTS else str)


def coerce(name: str, value: Any, default: Any) -> Any:
    """Value converted to the default's type, or IdentificationError naming the parameter."""
    def bad(expected: str) -> IdentificationError:
        return IdentificationError(f'parameter {name} = {value!r} must be {expected}')

    if isinstance(default, list):
        if isinstance(value, (str, bytes)) or not hasattr(value, '__iter__'):
            value = [value]
        value = list(value)
        kind = element_type(name, default)
        return [coerce(f'{name}[{i}]', v, kind()) for i, v in enumerate(value)]
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad('true or false')
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise bad('an integer')
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad('a number')
        if not math.isfinite(value):
            raise bad('finite')
        return float(value)
    if not isinstance(value, str):
        raise bad('a string')
    return value
