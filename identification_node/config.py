"""Every setting of the node and of offline identification, once: a typed dataclass tree.

Each field holds its default and, in its metadata, its description, unit and validation
(``range``: inclusive bounds; ``check``: 'positive', 'nonnegative' or 'nonempty';
``element``: the element type of a list whose default is empty; ``empty_ok``: a list with a
default for which [] is a value too; ``per_joint``: one value for every joint or one per
identified joint). Sections are the dotted prefixes of the ROS parameter names
(``smoother.cutoff`` is ``Config().smoother.cutoff``).

Generated from the tree: the ROS parameter table PARAMETERS (name: (default, description)),
the ranges the node's parameter descriptors carry (RANGES), the reader of parameter
mappings (``flatten``, ``parameters_of``, ``validated``) and the defaults the subsystems'
own option dataclasses take (``default``). Imports nothing of the package but ``errors``.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from identification_node.errors import IdentificationError

__all__ = ['Config', 'Smoother', 'TimeOffset', 'Publish', 'Plausibility', 'Robust',
           'LostMessages', 'PayloadTolerance', 'Payload', 'DriveGains', 'Consistency',
           'BatchConfig', 'Excitation', 'PARAMETERS', 'RANGES', 'FLOAT_LISTS', 'EMPTY_LISTS',
           'PER_JOINT', 'FIELDS', 'Descriptor', 'default', 'descriptor', 'metadata', 'flatten',
           'parameters_of', 'element_type', 'coerce', 'validated']


def setting(default: Any, description: str, *, unit: str = '',
            range: tuple[float, float] | None = None, check: str | None = None,
            element: type | None = None, empty_ok: bool = False,
            per_joint: bool = False) -> Any:
    """A dataclass field of the tree: ``default`` (a list is copied for every instance) and
    its metadata (see the module doc)."""
    meta = {'description': description, 'unit': unit, 'range': range, 'check': check,
            'element': element, 'empty_ok': empty_ok, 'per_joint': per_joint}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


def section(kind: type) -> Any:
    """A dataclass field holding a section (a nested dataclass) of the tree."""
    return field(default_factory=kind)


# Per-joint lists hold one value for every joint, or one per identified joint in the order of
# `joints`.
@dataclass
class Smoother:
    """``smoother.*``: the fixed-lag polynomial smoother of the joint states."""
    half_window: int = setting(
        0, 'fixed-lag smoother half window, samples (the delay); 0: from smoother.cutoff and '
        'the sampling rate; > 0 wins over it', unit='samples', range=(0, 10_000))
    cutoff: float = setting(
        0.0, 'Hz, -3 dB cut-off of the smoother; 0: chosen from the first '
        'smoother.auto_seconds of motion (reported)', unit='Hz', range=(0.0, 1e6))
    auto_seconds: float = setting(
        5.0, 's of motion the automatic cut-off is chosen from (held back until then)',
        unit='s', range=(0.1, 3600.0))
    order: int = setting(3, 'polynomial order of the smoother', range=(2, 4))
    max_gap: float = setting(0.05, 's; a larger stamp gap restarts the smoother', unit='s')


@dataclass
class TimeOffset:
    """``time_offset.*``: the check of the offset between the torque and the motion."""
    warn: float = setting(
        0.02, 's; the offset between the torque (currents or effort) and the motion is '
        'estimated (pipeline/time_offset.py); one beyond this is warned of (identify, '
        '/diagnostics); 0: not checked', unit='s', range=(0.0, 10.0))
    refuse: float = setting(
        0.1, 's; an offset beyond this makes identify refuse the bag and the node report an '
        'error in /diagnostics', unit='s', range=(0.0, 10.0))
    seconds: float = setting(
        10.0, 's of motion (the first of a stream) the offset is estimated from', unit='s',
        range=(1.0, 3600.0))
    search: float = setting(1.0, 's; offsets are searched within +- this', unit='s',
                            range=(0.01, 60.0))


@dataclass
class Publish:
    """``publish.*``: output rates of the node."""
    effort_rate: float = setting(0.0, 'Hz for predicted/measured effort; 0 = every sample',
                                 unit='Hz', range=(0.0, math.inf))
    estimate_rate: float = setting(1.0, 'Hz for base_parameters, estimate.* and '
                                   'robot_description', unit='Hz', check='positive')
    diagnostics_rate: float = setting(1.0, 'Hz for /diagnostics', unit='Hz', check='positive')


@dataclass
class Plausibility:
    """``plausibility.*``: physical bounds on the samples (model/plausibility.py)."""
    margin: float = setting(
        2.0, 'URDF limits are widened by this factor (>= 1) into the bounds beyond which '
        'samples are rejected as implausible')
    position: float = setting(1e6, 'rad (prismatic: / 10 m); |q| bound of joints without '
                              'range', unit='rad')
    velocity: float = setting(100.0, 'rad/s (prismatic: / 10 m/s) without a URDF velocity '
                              'limit', unit='rad/s')
    acceleration: float = setting(1000.0, 'rad/s^2 (prismatic: / 10 m/s^2) |qdd| bound',
                                  unit='rad/s^2')
    effort: float = setting(1e4, 'N m (or N) without a URDF effort limit', unit='N m')
    current_limit: list[float] = setting(
        [], 'per joint motor current bound, A (empty or 0: the current giving the torque '
        'bound through kt and gear_ratio)', unit='A', element=float)


@dataclass
class Robust:
    """``robust.*``: innovation gating of outliers (estimation/robust.py)."""
    enabled: bool = setting(True, 'innovation gating of outliers once the estimate converged')
    k: float = setting(5.0, "a sample beyond k standard deviations of its innovation (the "
                       "residual's and the estimate's own, y P y') is an outlier")
    window: int = setting(1000, 'samples over which the fraction of outliers is watched',
                          unit='samples')
    shift_fraction: float = setting(
        0.5, 'this fraction of outliers in the window is a residual shift: reported, and '
        'gating stops until it falls below half')


@dataclass
class LostMessages:
    """``lost_messages.*``: how lost input messages are counted."""
    middleware_event: bool = setting(
        False, "count lost messages also by the middleware's message-lost event (several "
        'publishers); off: it can deadlock rmw_fastrtps under bursts')


@dataclass
class PayloadTolerance:
    """``payload.tolerance.*``: the payload fit's excitation thresholds."""
    mass: float = setting(0.02, 'kg; mass stddev above this: not excited', unit='kg')
    com: float = setting(0.005, 'm; centre of mass stddev above this: not excited', unit='m')
    inertia: float = setting(0.002, 'kg m^2; inertia stddev above this: not excited',
                             unit='kg m^2')


@dataclass
class Payload:
    """``payload.*``: payload identification and change detection (payload/monitor.py)."""
    enabled: bool = setting(False, 'identify a payload and detect its changes (pick, place)')
    link: str = setting('', 'link or fixed frame carrying the payload (empty: the last '
                        'identified link)')
    arm: str = setting(
        '', "the arm's parameters the payload is fitted against: an estimate.yaml (~/save) of "
        "the arm without payload; 'estimate': the running estimate, taken at each "
        "~/payload/reset (both with their covariance: the arm is corrected within it); "
        "empty: the model's own, taken as exact")
    fit_time: float = setting(1.0, 's of samples after a change before the payload is fitted',
                              unit='s')
    settle: float = setting(0.1, 's after a detection before samples are used', unit='s')
    refresh: float = setting(5.0, 's between refits while the payload stays', unit='s')
    window: float = setting(0.25, 's, moving window of the change detector', unit='s')
    threshold: float = setting(50.0, 'change detector chi-square threshold (4 dof)')
    min_change: float = setting(0.2, 'kg; the smallest mass change declared (detection '
                                'threshold)', unit='kg')
    min_z: float = setting(8.0, 'a mass change is declared at this many of its standard '
                           'deviations')
    confirm: float = setting(0.1, 's the change conditions must hold before a change is '
                             'declared', unit='s')
    cutoff: float = setting(
        20.0, "Hz, -3 dB cut-off of the payload monitor's own smoother (its delay ~ 0.7 / "
        'cutoff s at any rate; the estimator keeps its own)', unit='Hz')
    tolerance: PayloadTolerance = section(PayloadTolerance)


@dataclass
class DriveGains:
    """``drive_gains.*``: identification of the drive gains in situ."""
    back_emf: bool = setting(False, 'identify the drive gains (N m/A at the joint) from '
                             'motor_voltages by the back-EMF (current-driven joints)')
    known_payload: bool = setting(False, 'identify the drive gains from segments with a known '
                                  'payload (service ~/drive_gains/known_payload)')


@dataclass
class Consistency:
    """``consistency.*``: the physically consistent solve (estimation/consistency.py)."""
    weight: float = setting(
        1e-3, "weight of the prior toward the description's inertials in the search for "
        'the best consistent fit, in chi-square units of the data term')
    confidence: float = setting(
        0.1, "chi-square level of the region about the data's best consistent fit inside "
        "which the prior (closest to the description) chooses; 0: none, that fit itself")
    mass_ratio: float = setting(3.0, "each link's mass within [1/r, r] times the "
                                "description's (0: no bound); a bound in use is reported")
    mass_weight: float = setting(
        30.0, "weight w of sum_i |m_i / m0_i - 1| beside the log-det prior: where the data "
        "leave link masses open, as few as possible move from the description's (0: none)")
    total_mass: list[float] = setting([], "kg, [lo, hi] of the identified links' total mass "
                                      '(empty: none)', unit='kg', element=float)
    margin: float = setting(1e-6, 'pseudo-inertia margin: J - margin * 1 >= 0 (kg, kg m^2)',
                            unit='kg, kg m^2')
    solver: str = setting('CLARABEL', 'cvxpy solver: CLARABEL or SCS')
    time_limit: float = setting(
        5.0, 's per constrained solve; on time-out the unconstrained estimate is kept and the '
        'failure reported', unit='s')
    geometry_box: bool = setting(True, "bound each centre of mass by the bounding box of its "
                                 "link's URDF collision/visual primitives, where it has some")
    mass_min: list[float] = setting([], 'per identified link lower mass bound, kg (empty: '
                                    'none)', unit='kg', element=float)
    mass_max: list[float] = setting([], 'per identified link upper mass bound, kg (empty: '
                                    'none)', unit='kg', element=float)
    com_box: list[float] = setting(
        [], '6 values per identified link: centre of mass box lo x y z, hi x y z in the link '
        'frame, m (empty: geometry_box)', unit='m', element=float)


@dataclass
class Config:
    """Every ROS parameter of the node (config/identification.yaml), which offline
    identification reads from the same files."""
    robot: str = setting('mit_dd_arm', 'bundled robot name or URDF/MJCF file path')
    robot_description: str = setting('', 'URDF XML; when set it is used instead of `robot`')
    joints: list[str] = setting(
        [], 'identified joints in this order (empty: all movable joints but URDF <mimic> ones '
        'and those they follow; identify: those the bag carries, the others locked)',
        element=str)
    extras: list[str] = setting(['fv', 'fc', 'fo'], 'per-joint extra columns among fv '
                                '(viscous), fc (Coulomb), fo (offset), Ia (rotor inertia); [] '
                                'for none', empty_ok=True)
    coulomb_velocity: float = setting(0.0, 'rad/s (prismatic joints: / 10 m/s); > 0 smooths '
                                      'the Coulomb sign as tanh(qd / value)', unit='rad/s',
                                      range=(0.0, math.inf))
    torque_source: list[str] = setting(['measured'], 'per joint: measured, current or '
                                       'three_phase', per_joint=True)
    kt: list[float] = setting([1.0], 'per joint motor torque constant, N m/A', unit='N m/A',
                              per_joint=True)
    gear_ratio: list[float] = setting([1.0], 'per joint gear ratio (joint torque = ratio * '
                                      'motor torque)', per_joint=True)
    pole_pairs: list[int] = setting([1], 'per joint motor pole pairs', per_joint=True)
    angle_offset: list[float] = setting([0.0], 'per joint electrical angle offset, rad',
                                        unit='rad', per_joint=True)
    phase_order: list[str] = setting(['abc'], 'per joint phase order: abc or acb',
                                     per_joint=True)
    forgetting_factor: float = setting(1.0, 'RLS forgetting factor per sample in [0.9, 1]; 1 '
                                       '= none', range=(0.9, 1.0))
    smoother: Smoother = section(Smoother)
    velocity_source: str = setting('auto', 'auto, measured or differentiate')
    align_tolerance: float = setting(0.002, 's; currents are matched to joint states within '
                                     'this', unit='s')
    hold_time: float = setting(0.1, 's to wait for currents before a joint state is given up',
                               unit='s')
    restart_jump: float = setting(1.0, 's; a larger backward stamp jump is a restarted stream',
                                  unit='s')
    time_offset: TimeOffset = section(TimeOffset)
    update_batch: int = setting(200, 'samples gathered per RLS update (predictions use the '
                                'estimate so far)', unit='samples', range=(1, 10**9))
    joint_noise_std: list[float] = setting(
        [], 'per joint torque noise std for weighting, N m (empty: equal)', unit='N m',
        element=float)
    coulomb_exclusion_speed: float = setting(
        0.1, 'rad/s (prismatic joints: / 10 m/s); > 0 with fc identified: a joint equation is '
        'left out while |qd| < this (the Coulomb column is what the smoother makes of '
        'sign(qd); with coulomb_velocity > 0: while |qd| < this + |qdd| * smoother half '
        "window; batch: within the filter's reach of |qd| < this); 0: none", unit='rad/s',
        range=(0.0, math.inf))
    converged_ratio: float = setting(0.1, 'converged when parameter uncertainty < ratio * '
                                     'residual RMS')
    max_condition: float = setting(1e8, 'largest information condition number counted as '
                                   'excited')
    min_samples: int = setting(1000, 'samples needed before convergence is declared',
                               unit='samples', range=(0, 10**12))
    process_period: float = setting(
        0.01, 's (wall clock) between batch processing runs: the shortest period while an '
        'output waits (latency vs CPU), the period itself with latency_budget 0', unit='s',
        check='positive')
    latency_budget: float = setting(
        0.02, 's within which ~/predicted_effort and ~/measured_effort publish a sample once '
        "its output can be computed (the smoother's delay after it): the processing period "
        'is what the budget leaves of the recent runs and 2 ms, within process_period and '
        'idle_process_period; 0: every process_period', unit='s', range=(0.0, 1.0))
    idle_process_period: float = setting(
        0.1, 's (wall clock) between processing runs while no output waits for them: nothing '
        'subscribes to ~/predicted_effort or ~/measured_effort and payload.enabled is false '
        '(service requests are served at once); at least process_period', unit='s',
        range=(0.001, 1.0))
    publish: Publish = section(Publish)
    output_directory: str = setting('identification_output', 'directory the save service '
                                    'writes into', check='nonempty')
    plausibility: Plausibility = section(Plausibility)
    robust: Robust = section(Robust)
    max_names: int = setting(256, 'names per input message; messages with more are rejected')
    layout_cache_bytes: int = setting(4 << 20, 'bytes of message layouts (name lists) kept '
                                      'decoded', unit='bytes')
    watchdog_timeout: float = setting(
        10.0, 's without the executor or processing making progress after which the node logs '
        'it and exits (status 3) for a supervisor; 0: off', unit='s', check='nonnegative')
    input_queue_bytes: int = setting(
        64 << 20, 'bytes of input messages held per topic until processed; beyond, the oldest '
        'are dropped (diagnostics dropped_messages.*)', unit='bytes', range=(1, 1 << 62))
    lost_messages: LostMessages = section(LostMessages)
    payload: Payload = section(Payload)
    drive_gains: DriveGains = section(DriveGains)
    physical_consistency: bool = setting(
        True, 'publish and save the physically consistent estimate (constrained least '
        'squares); false: the unconstrained one only')
    save_inconsistent: bool = setting(False, '~/save writes identified.urdf even when the '
                                      'estimate is not physically consistent')
    consistency: Consistency = section(Consistency)

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> Config:
        """The tree of a flat mapping of every parameter (``validated``'s result)."""
        def build(kind: type, prefix: str) -> Any:
            kwargs = {}
            for f in dataclasses.fields(kind):
                sub = _SECTIONS[kind].get(f.name)
                kwargs[f.name] = (build(sub, f'{prefix}{f.name}.') if sub is not None
                                  else copy.deepcopy(values[prefix + f.name]))
            return kind(**kwargs)
        return build(cls, '')


@dataclass
class BatchConfig:
    """Defaults of offline batch identification (identify --method batch; not ROS
    parameters): periodic averaging and the zero-phase filtered path."""
    min_harmonics: int = setting(1, 'fewest harmonics of the Fourier fit to the averaged '
                                 'positions')
    cutoff: float = setting(20.0, 'Hz: zero-phase low-pass of the filtered path when neither '
                            'given nor chosen from the data; the Fourier band (periodic)',
                            unit='Hz')
    order: int = setting(4, 'Butterworth order of the zero-phase filter (run twice: squared '
                         'gain, no phase)')


@dataclass
class Excitation:
    """Defaults of excitation design (the ``excite`` verb; not ROS parameters)."""
    harmonics: int = setting(5, 'harmonics per joint of the Fourier series')
    period: float = setting(10.0, 'period of the series', unit='s')
    periods: int = setting(5, 'periods of the periodic part between the ramps')
    margin: float = setting(0.1, 'fraction of every limit kept free (position: of the half '
                            'range)')
    min_distance: float = setting(0.01, 'minimum distance between checked collision pairs',
                                  unit='m')
    maxiter: int = setting(200, 'SLSQP iterations')
    samples: int = setting(100, 'criterion samples over one period')
    rate: float = setting(100.0, 'sample rate of the CSV, the plot and the bag', unit='Hz')


def _section_kinds() -> dict[type, dict[str, type]]:
    """Of each section class, its fields that are sections, with their classes (the
    annotations are strings under ``from __future__ import annotations``)."""
    names = {kind.__name__: kind for kind in (Smoother, TimeOffset, Publish, Plausibility,
                                              Robust, LostMessages, PayloadTolerance, Payload,
                                              DriveGains, Consistency)}
    out: dict[type, dict[str, type]] = {}
    for kind in (Config,) + tuple(names.values()):
        out[kind] = {f.name: names[str(f.type)] for f in dataclasses.fields(kind)
                     if str(f.type) in names}
    return out


_SECTIONS = _section_kinds()


def _leaves(kind: type = Config, prefix: str = '') -> dict[str, dataclasses.Field]:
    """The fields of the tree by dotted parameter name, in declaration order."""
    out: dict[str, dataclasses.Field] = {}
    for f in dataclasses.fields(kind):
        if f.name in _SECTIONS[kind]:
            out.update(_leaves(_SECTIONS[kind][f.name], f'{prefix}{f.name}.'))
        else:
            out[prefix + f.name] = f
    return out


def _default_of(f: dataclasses.Field) -> Any:
    if callable(f.default_factory):
        return f.default_factory()
    return f.default


FIELDS: dict[str, dataclasses.Field] = _leaves()
# name: (default, description), the node's ROS parameter table.
PARAMETERS: dict[str, tuple[Any, str]] = {
    name: (_default_of(f), f.metadata['description']) for name, f in FIELDS.items()}
# Inclusive ranges of numeric parameters: the node's typed parameter descriptors carry them and
# ``validated`` checks them, for the node and the offline configuration alike (bounds that
# exclude their end, such as > 0, are checked where the value is used).
RANGES: dict[str, tuple[float, float]] = {
    name: f.metadata['range'] for name, f in FIELDS.items() if f.metadata['range']}
# List parameters of floats whose default is empty (their element type cannot be read off).
FLOAT_LISTS = tuple(name for name, f in FIELDS.items()
                    if f.metadata['element'] is float and not PARAMETERS[name][0])
# List parameters with a default for which [] is a value too (ROS types [] as bytes).
EMPTY_LISTS = tuple(name for name, f in FIELDS.items() if f.metadata['empty_ok'])
# Per-joint parameters (one value for every joint, or one per identified joint).
PER_JOINT = tuple(name for name, f in FIELDS.items() if f.metadata['per_joint'])


def default(name: str) -> Any:
    """The default of parameter ``name`` (dotted; a list is a new copy)."""
    value = PARAMETERS[name][0]
    return list(value) if isinstance(value, list) else value


def metadata(name: str) -> Mapping[str, Any]:
    """The metadata of parameter ``name``: description, unit, range, check, element,
    empty_ok, per_joint."""
    return FIELDS[name].metadata


@dataclass(frozen=True)
class Descriptor:
    """What the ROS parameter descriptor of a parameter says, ROS-free (ros/node.py makes the
    rclpy ParameterDescriptor of it): ``type`` of the value (bool, int, float or str), of its
    elements when ``array``; None: dynamically typed. ``range``: inclusive bounds, ints for
    an int parameter (rclpy's integer_range), floats otherwise (floating_point_range)."""
    description: str
    type: type | None
    array: bool = False
    range: tuple[float, float] | None = None


def descriptor(name: str, default: Any, description: str) -> Descriptor:
    """The descriptor of a parameter table entry (PARAMETERS' or another node's table of the
    same layout), its range from RANGES. Lists with an empty default, or which may be empty
    (EMPTY_LISTS), stay dynamically typed (``validated`` checks them): rclpy declares a typed
    parameter without a value uninitialized, which its parameter services then fail to
    report, and types an empty list as bytes."""
    if isinstance(default, list):
        if default and name not in EMPTY_LISTS:
            return Descriptor(description, element_type(name, default), array=True)
        return Descriptor(description, None)
    kind = type(default)
    bounds = RANGES.get(name)
    if bounds is not None:
        convert = int if kind is int else float
        bounds = (convert(bounds[0]), convert(bounds[1]))
    return Descriptor(description, kind, range=bounds)


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


def parameters_of(data: Any, source: str) -> dict[str, Any]:
    """The parameters of a read YAML document: the first node's ``ros__parameters`` of the
    ROS parameter-file layout, or a plain mapping, flattened. ``source`` names the file in
    errors."""
    if not isinstance(data, Mapping):
        raise IdentificationError(f'{source} does not hold a mapping')
    for node, value in data.items():
        if isinstance(value, Mapping) and 'ros__parameters' in value:
            if not isinstance(value['ros__parameters'], Mapping):
                raise IdentificationError(f'{source}: {node}.ros__parameters is not a '
                                          'mapping of parameter names to values')
            return flatten(value['ros__parameters'])
    return flatten(data)


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


def validated(given: Mapping[str, Any]) -> dict[str, Any]:
    """Every parameter's value: the defaults with ``given`` (nested or dotted names) over
    them, converted to the defaults' types and checked against the metadata;
    IdentificationError naming the first bad parameter."""
    given = flatten(given)
    unknown = sorted(set(given) - set(PARAMETERS))
    if unknown:
        raise IdentificationError(f'unknown parameter(s) {unknown}; known: '
                                  f'{sorted(PARAMETERS)}')
    values = {name: default(name) for name in PARAMETERS}
    values.update(given)
    for name, (value, _) in PARAMETERS.items():
        values[name] = coerce(name, values[name], value)
    for name, f in FIELDS.items():
        if f.metadata['check'] == 'nonnegative' and values[name] < 0:
            raise IdentificationError(f'parameter {name} must be >= 0')
    for name, (lo, hi) in RANGES.items():
        if not lo <= values[name] <= hi:
            raise IdentificationError(f'parameter {name} = {values[name]} must be in '
                                      f'[{lo}, {hi}]')
    for name, f in FIELDS.items():
        if f.metadata['check'] == 'positive' and not values[name] > 0:
            raise IdentificationError(f'parameter {name} = {values[name]} must be > 0')
    for name, f in FIELDS.items():
        if f.metadata['check'] == 'nonempty' and not str(values[name]).strip():
            raise IdentificationError(f'parameter {name} must not be empty')
    return values
