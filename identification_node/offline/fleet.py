"""Fleet identification: many bags of many robots, reduced to estimates per robot and period.

Map: each bag, or each time segment of a long bag, streams through the node's pipeline
(replay.identify_bag) and leaves its sufficient statistics (BagStatistics): the per-joint
normal equations of its rows (NormalEquations), the residual sums over samples and over blocks
(ResidualStatistics, for the honest stddev) and the counters. A segment's pipeline is fed
``half_window * max_gap + hold_time + align_tolerance`` seconds of the bag on either side and
keeps only the rows centred inside the segment, so its rows are the whole bag's (the smoother
never fits across a gap larger than max_gap).

Reduce: statistics add exactly (sums), in a fixed order (bag, segment), whatever order the
tasks finish in. Bags are separate recordings: residual blocks restart at each bag, as the
pipeline's do at a stream restart. They also restart wherever the stamps cross a multiple of
estimate.RESIDUAL_GRID (60 s), and segments are cut only there (plan_tasks), so a segment's
blocks are the whole bag's: the merged statistics, estimate and stddev equal the unsplit
run's. (A cut elsewhere, bag_statistics' own start_ns/stop_ns, keeps rows and estimate but
shifts the blocks.) Whole bags are the default unit.

Solve: ``solve_unconstrained(NormalEquations) -> theta`` (the streaming estimator's own least
squares on the merged normal equations) is the seam of the unconstrained solve (``solve=``);
the pipeline then derives noise, covariance and convergence from the statistics at that theta
as it does for streamed data (IdentificationPipeline.restore), so a group of bags gives what
``identify`` gives for one bag holding them one after another (each its own stream). Then,
as ``identify`` does, offline.make_consistent solves the same information physically
consistent (consistency.ConsistentSolver; ``physical_consistency=False``, the CLI's
``--no-physical-consistency``, or the robot's config ``physical_consistency: false`` skip it),
so each period's document has ``estimate`` (consistent), ``unconstrained_estimate``,
``links`` and ``consistency_solver`` as identify's.

Smoother: the statistics of a robot's bags merge exactly only when every bag went through
the same smoother. Unless the robot's settings fix ``smoother.half_window``, it is chosen once
per robot, as ``identify`` would on the robot's first bag in manifest order (choose_smoother),
and given to every map task of that robot (``MapTask.smoother``); the fleet document reports
it per robot.

Flags: a base parameter that moved by more than k combined standard deviations between
consecutive periods of a robot (drift), and robots whose estimate lies more than k robust
deviations from the rest of the fleet with the same model (at least 3 robots).
ROS-free; dask only in connect and run_fleet. Units SI, stamps int64 ns.
"""
from __future__ import annotations

import csv
import datetime
import hashlib
import math
import os
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import ConsistentSolver
from identification_node.estimation.residuals import ResidualStatistics
from identification_node.estimation.rls import RecursiveLeastSquares
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.model.robot import RobotModel
from identification_node.offline.replay import (JOINT_STATES, MOTOR_CURRENTS, Checkpoint,
                                                ReplayResult, bag_robot, identify_bag)
from identification_node.pipeline import IdentificationPipeline
from identification_node.settings import Settings

DEFAULT_SIGMA = 5.0          # k: flag changes larger than k standard deviations
MANIFEST_COLUMNS = ('bag', 'robot', 'period')
SMOOTHER = ('smoother.half_window', 'smoother.cutoff')   # BagStatistics.smoother
OPTIONAL_COLUMNS = ('urdf', 'config')


# -- input ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FleetEntry:
    """One bag of the fleet: its robot and period (day or tag), and optionally the URDF and
    node parameter file to identify it with (else the bag's /robot_description)."""
    bag: str
    robot: str
    period: str
    urdf: str | None = None
    config: str | None = None


def read_manifest(path: str | os.PathLike) -> list[FleetEntry]:
    """The manifest CSV (header bag,robot,period[,urdf][,config]; paths relative to its
    folder)."""
    path = Path(path)
    try:
        with open(path, newline='') as f:
            rows = list(csv.DictReader(f))
            header = [c.strip() for c in (rows and rows[0].keys() or [])]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise IdentificationError(f'cannot read the manifest {path}: {exc}') from None
    missing = [c for c in MANIFEST_COLUMNS if c not in header]
    if not rows or missing:
        raise IdentificationError(
            f'manifest {path} needs a header bag,robot,period (optional urdf, config) and '
            f'rows; ' + (f'missing {", ".join(missing)}' if rows else 'it has no rows'))
    unknown = sorted(set(header) - set(MANIFEST_COLUMNS) - set(OPTIONAL_COLUMNS))
    if unknown:
        raise IdentificationError(f'manifest {path}: unknown columns {", ".join(unknown)}')
    entries, seen = [], {}
    for line, row in enumerate(rows, start=2):
        row = {k.strip(): (v or '').strip() for k, v in row.items() if k is not None}
        if not all(row.get(c) for c in MANIFEST_COLUMNS):
            raise IdentificationError(f'manifest {path} line {line}: bag, robot and period '
                                      'must all be given')

        def local(name: str) -> str | None:
            return str(path.parent / row[name]) if row.get(name) else None

        if local('bag') in seen:
            raise IdentificationError(f"manifest {path} line {line}: bag {row['bag']} is "
                                      f"listed twice (first on line {seen[local('bag')]})")
        seen[local('bag')] = line
        entries.append(FleetEntry(local('bag'), row['robot'], row['period'], local('urdf'),
                                  local('config')))
    return entries


def scan_directory(path: str | os.PathLike, config: str | None = None
                   ) -> tuple[list[FleetEntry], list[dict]]:
    """The bags in a folder (its subfolders holding metadata.yaml), grouped by the robot
    description each carries: robot '<URDF name>-<8 hex of model_key>', period the UTC day of the
    bag's first message, ``config`` the parameter file of every entry (joints, extras, ...).
    Returns (entries, failures: the bags that cannot be read or carry no description)."""
    from identification_node.bags.reader import open_bag

    settings = entry_settings(FleetEntry('', '', '', config=config))
    entries, failed = [], []
    bags = sorted(p for p in Path(path).iterdir() if (p / 'metadata.yaml').is_file())
    if not bags:
        raise IdentificationError(f'{path} holds no rosbag2 bags (folders with metadata.yaml)')
    for bag in bags:
        try:
            robot = bag_robot(bag, settings)
            with open_bag(bag) as reader:
                day = datetime.datetime.fromtimestamp(reader.start_ns * 1e-9,
                                                      datetime.timezone.utc).date()
        except Exception as exc:      # a corrupt bag among many is reported, not fatal
            failed.append({'bag': str(bag), 'error': _why(exc)})
            continue
        name = robot.model.name or robot.name    # the URDF's robot name
        entries.append(FleetEntry(str(bag), f'{name}-{model_key(robot)[:8]}', day.isoformat(),
                                  config=config))
    return entries, failed


def model_key(robot: RobotModel) -> str:
    """Hash of what the statistics depend on: description, identified joints and extras."""
    text = '\n'.join([robot.description or robot.name, ','.join(robot.joint_names),
                      ','.join(robot.extras), repr(robot.coulomb_velocity)])
    return hashlib.sha256(text.encode()).hexdigest()


def entry_settings(entry: FleetEntry) -> Settings:
    """The settings of an entry: its parameter file, its URDF overriding the robot."""
    from identification_node.settings import read_parameter_file

    values = read_parameter_file(entry.config) if entry.config else {}
    if entry.urdf:
        values['robot'], values['robot_description'] = entry.urdf, ''
    return Settings.from_dict(values)


def entry_robot(entry: FleetEntry, settings: Settings) -> RobotModel:
    return (settings.load_robot() if entry.urdf or settings.given_robot
            else bag_robot(entry.bag, settings))


# -- map: one bag or segment to its statistics ----------------------------------------------------
@dataclass
class BagStatistics:
    """Sufficient statistics of the rows of some bags (or segments): per-joint normal
    equations of the weighted rows [Yb | tau] (as RecursiveLeastSquares.normal_equations),
    residual sums over samples and blocks, samples in the estimator, the pipeline's counters,
    the first and last row stamps (ns), and the model they belong to (model_key)."""
    bags: tuple
    model: str
    normal_equations: NormalEquations
    residuals: ResidualStatistics
    num_samples: int
    used: int
    messages: int
    received: int
    rejected: dict
    excluded_rows: int
    restarts: int
    first_ns: int | None
    last_ns: int | None
    smoother: tuple = ()     # (parameter, value) pairs of the smoother the rows went through

    def __add__(self, other: BagStatistics) -> BagStatistics:
        if self.model != other.model:
            raise IdentificationError(
                f'bags {self.bags[0]} and {other.bags[0]} are of different robot models '
                '(description, joints or extras): their statistics do not merge')
        if self.smoother != other.smoother:
            raise IdentificationError(
                f'bags {self.bags[0]} and {other.bags[0]} went through different smoothers '
                f'({dict(self.smoother)}, {dict(other.smoother)}): their statistics do not '
                'merge exactly')
        stamps = [s for s in (self.first_ns, other.first_ns) if s is not None]
        lasts = [s for s in (self.last_ns, other.last_ns) if s is not None]
        return BagStatistics(
            tuple(dict.fromkeys(self.bags + other.bags)), self.model,
            self.normal_equations + other.normal_equations, self.residuals + other.residuals,
            self.num_samples + other.num_samples, self.used + other.used,
            self.messages + other.messages, self.received + other.received,
            {k: self.rejected.get(k, 0) + other.rejected.get(k, 0)
             for k in {**self.rejected, **other.rejected}},
            self.excluded_rows + other.excluded_rows, self.restarts + other.restarts,
            min(stamps) if stamps else None, max(lasts) if lasts else None, self.smoother)


class _SegmentPipeline(IdentificationPipeline):
    """The pipeline fed only the samples within ``margin_ns`` of [start_ns, stop_ns) (None:
    open), keeping the rows centred inside it; ``messages`` counts those inside."""

    def __init__(self, robot, config, base, start_ns: int | None, stop_ns: int | None,
                 margin_ns: int):
        super().__init__(robot, config, base)
        lo = -2 ** 62 if start_ns is None else start_ns
        hi = 2 ** 62 if stop_ns is None else stop_ns
        self._window = (lo, hi)
        self._feed = (lo - margin_ns, hi + margin_ns)
        self.messages = 0
        self.row_builder = _WindowRows(self.row_builder, self.samples.counters, lo, hi)

    def _keep(self, stamps_ns) -> np.ndarray:
        self.messages += int(np.count_nonzero(_inside(stamps_ns, *self._window)))
        return _inside(stamps_ns, *self._feed)

    def add_joint_state(self, record) -> None:
        if self._keep(record.stamp_ns):
            super().add_joint_state(record)

    def add_currents(self, record) -> None:
        if self._keep(record.stamp_ns):
            super().add_currents(record)

    def add_joint_states(self, block) -> None:
        keep = self._keep(np.asarray(block.stamp_ns))
        if keep.all():
            super().add_joint_states(block)
        elif keep.any():
            super().add_joint_states(type(block)(np.asarray(block.stamp_ns)[keep], block.names,
                                                 *(np.asarray(a)[keep] for a in block[2:])))


class _WindowRows:
    """A RowBuilder keeping only the rows centred in [lo, hi) ns (stamps of ``counters``)."""

    def __init__(self, rows, counters, lo: int, hi: int):
        self._rows, self._counters, self._window = rows, counters, (lo, hi)

    def __getattr__(self, name: str):   # the smoother's choice, counters: the RowBuilder's
        return getattr(self._rows, name)

    def reset(self) -> None:
        self._rows.reset()

    def drain(self, measured_velocity: bool):
        r = self._rows.drain(measured_velocity)
        return None if r is None else self._inside(r)

    def __call__(self, *args, **kwargs):
        return self._inside(self._rows(*args, **kwargs))

    def _inside(self, r):
        if len(r.t):
            keep = _inside(self._counters.stamps_ns(r.t), *self._window)
            if not keep.all():
                r = type(r)(*(a[keep] for a in r))
        return r


def _inside(stamps_ns, lo: int, hi: int):
    return (stamps_ns >= lo) & (stamps_ns < hi)


def segment_margin_ns(settings: Settings) -> int:
    """Samples on either side a segment needs: the smoother's half window can span
    half_window * max_gap, currents wait hold_time, alignment reaches align_tolerance."""
    v = settings.values
    return int(math.ceil((v['smoother.half_window'] * v['smoother.max_gap'] + v['hold_time']
                          + v['align_tolerance']) * 1e9)) + 1


def pinned(settings: Settings, smoother: tuple) -> Settings:
    """``settings`` with smoother parameters ((name, value) pairs, bag_smoother) set."""
    if not smoother:
        return settings
    return Settings({**settings.values, **dict(smoother)},
                    settings.given | {k for k, _ in smoother})


def bag_smoother(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                 joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS
                 ) -> tuple:
    """The smoother parameters the pipeline of ``settings`` uses on ``bag`` (as identify):
    () when they fix the half window, else the half window and cut-off it chooses (the bag
    read until chosen)."""
    choice = chosen_smoother(bag, settings, robot, joint_states, motor_currents)
    return () if choice is None else (('smoother.half_window', int(choice.half_window)),
                                      ('smoother.cutoff', float(choice.cutoff)))


def chosen_smoother(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                    joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS):
    """The smoother (rows.SmootherChoice) the pipeline of ``settings`` chooses on ``bag``, the
    bag read until chosen; None when the settings fix the half window."""
    if settings['smoother.half_window']:
        return None
    pipeline = settings.build(robot)
    identify_bag(bag, settings, robot, joint_states, motor_currents, checkpoints=1,
                 pipeline=pipeline, until=lambda p: p.smoother is not None)
    return pipeline.smoother


def bag_statistics(bag: str | os.PathLike, settings: Settings, robot: RobotModel,
                   start_ns: int | None = None, stop_ns: int | None = None,
                   joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS
                   ) -> BagStatistics:
    """The sufficient statistics of a bag's rows through the node's pipeline, or of the rows
    with header stamps in [start_ns, stop_ns) (a segment; None: open). Needs forgetting 1
    (forgotten statistics do not merge). Settings that leave the smoother to be chosen get
    the one the whole bag chooses (bag_smoother); statistics of bags merge only with one
    smoother: pin theirs (``pinned``) to the first bag's, as run_fleet does."""
    if settings['forgetting_factor'] != 1.0:
        raise IdentificationError(
            f"fleet identification needs forgetting_factor 1 (got "
            f"{settings['forgetting_factor']}): forgotten statistics do not add up")
    smoother = bag_smoother(bag, settings, robot, joint_states, motor_currents)
    settings = pinned(settings, smoother)
    pipeline = settings.build(robot)
    segment = start_ns is not None or stop_ns is not None
    if segment:
        pipeline = _SegmentPipeline(robot, pipeline.config, pipeline.base, start_ns, stop_ns,
                                    segment_margin_ns(settings))
    span: list[int] = []     # first and last row stamps

    def stamps(out) -> None:
        if len(out.stamps_ns):
            span[:] = [span[0] if span else int(out.stamps_ns[0]), int(out.stamps_ns[-1])]

    try:
        result = identify_bag(bag, settings, robot, joint_states, motor_currents,
                              checkpoints=1, on_output=stamps, pipeline=pipeline)
        messages = result.messages
    except IdentificationError:
        if not segment or pipeline.used:   # a segment may hold no rows (a gap)
            raise
        messages = 0
    rls = pipeline.rls
    if segment:   # the margins' messages are counted by their own segments
        messages = pipeline.messages
    # an estimator without rows knows no joints yet: the zero sums of this robot's instead
    equations = (rls.normal_equations() if rls.num_samples else
                 NormalEquations.zeros(pipeline.base.num_base, robot.dof))
    return BagStatistics(
        (str(bag),), model_key(robot), equations, pipeline.residuals,
        int(rls.num_samples), int(pipeline.used), int(messages), int(pipeline.received),
        {k: v for k, v in pipeline.rejected.items() if v}, int(pipeline.excluded_rows),
        int(pipeline.restarts), *(span or (None, None)),
        smoother=smoother or tuple((k, settings[k]) for k in SMOOTHER))


# -- solve ----------------------------------------------------------------------------------------
Solve = Callable[[NormalEquations], np.ndarray]


def solve_unconstrained(equations: NormalEquations) -> np.ndarray:
    """The base parameters minimising sum_j ||tau_j - Y_j theta||^2 over merged normal
    equations, as the streaming estimator solves them. THE SEAM: a physically consistent
    solve with the same signature (normal equations in, base parameters out) replaces it
    (``solve=`` of identification and run_fleet); the covariance stays the information's.
    The physically consistent estimate is solved after it (identification), as identify's."""
    return RecursiveLeastSquares.from_normal_equations(equations, 0).theta


def identification(stats: BagStatistics, settings: Settings, robot: RobotModel,
                   label: str | None = None, solve: Solve = solve_unconstrained,
                   physical_consistency: bool = True, solver: ConsistentSolver | None = None):
    """The offline.Identification of merged statistics, as ``identify`` gives for their
    bags streamed one after another (one stream each): the physically consistent estimate
    too unless ``physical_consistency`` is False or ``settings`` turn it off (``solver``:
    consistent_solver's for this robot, re-used across its groups)."""
    from identification_node.offline.identification import from_replay, make_consistent

    if stats.model != model_key(robot):
        raise IdentificationError(f'statistics of {stats.bags[0]} are not of {robot.name}')
    settings = pinned(settings, stats.smoother)
    pipeline = settings.build(robot)
    ne = stats.normal_equations
    rls = RecursiveLeastSquares.from_normal_equations(ne, stats.num_samples, theta=solve(ne))
    pipeline.restore(rls, stats.residuals, stats.used, stats.received, stats.rejected,
                     stats.excluded_rows, stats.restarts, stats.last_ns)
    est = pipeline.estimate()
    history = [Checkpoint(est.num_samples, est.stamp, est.values, est.stddev)]
    ident = from_replay(ReplayResult(label or ', '.join(stats.bags), pipeline, stats.messages,
                                     history))
    return make_consistent(ident, settings.consistency_options() if physical_consistency
                           else None, solver)


def consistent_solver(settings: Settings, robot: RobotModel) -> ConsistentSolver | None:
    """The physically consistent solver of a robot's groups (None: switched off in
    ``settings``): made once, so its problem is canonicalised once, not per group."""
    options = settings.consistency_options()
    return (None if options is None else
            ConsistentSolver.for_robot(robot, settings.build(robot).base, options))


# -- the fleet run --------------------------------------------------------------------------------
@dataclass(frozen=True)
class MapTask:
    """One unit of map work: a bag, or segment ``index`` [start_ns, stop_ns) of it."""
    entry: FleetEntry
    index: int = 0
    start_ns: int | None = None
    stop_ns: int | None = None
    joint_states: str = JOINT_STATES
    motor_currents: str = MOTOR_CURRENTS
    smoother: tuple = ()      # (parameter, value) pairs fixing the robot's smoother


def task_settings(entry: FleetEntry, smoother: tuple = ()) -> Settings:
    """entry_settings with the robot's smoother parameters (choose_smoother) set."""
    return pinned(entry_settings(entry), smoother)


def choose_smoother(entry: FleetEntry, joint_states: str = JOINT_STATES,
                    motor_currents: str = MOTOR_CURRENTS) -> tuple:
    """bag_smoother of an entry: what all bags of its robot are to use. Pure, for a worker."""
    settings = entry_settings(entry)
    return bag_smoother(entry.bag, settings, entry_robot(entry, settings), joint_states,
                        motor_currents)


@dataclass
class MapFailure:
    bag: str
    error: str


def _why(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else '') if isinstance(exc, IdentificationError) else \
        f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(': ')


def run_task(task: MapTask) -> BagStatistics | MapFailure:
    """A map task on a worker: the bag's (segment's) statistics, or why it failed. Pure: the
    same task gives the same statistics, so Dask may rerun it when a worker dies."""
    try:
        settings = task_settings(task.entry, task.smoother)
        robot = entry_robot(task.entry, settings)
        return bag_statistics(task.entry.bag, settings, robot, task.start_ns, task.stop_ns,
                              task.joint_states, task.motor_currents)
    except Exception as exc:    # a corrupt or truncated bag is reported and skipped
        return MapFailure(task.entry.bag, _why(exc))


def plan_tasks(entries: Sequence[FleetEntry], segment_seconds: float | None = None,
               joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS,
               smoothers: dict[str, tuple] | None = None) -> list[MapTask]:
    """One task per bag, or per ``segment_seconds`` of its log time, rounded to a multiple of
    the residual grid (estimate.RESIDUAL_GRID, 60 s) and cut at multiples of it, where the
    residual blocks restart, so the segments' statistics merge to the whole bag's exactly
    (the first and last segment open-ended, so every row belongs to exactly one);
    ``smoothers``: per robot the smoother parameters of its tasks (choose_smoother)."""
    from identification_node.bags.reader import open_bag
    from identification_node.pipeline.estimate import RESIDUAL_GRID

    tasks = []
    for e in entries:
        base = MapTask(e, joint_states=joint_states, motor_currents=motor_currents,
                       smoother=(smoothers or {}).get(e.robot, ()))
        if not segment_seconds:
            tasks.append(base)
            continue
        try:
            with open_bag(e.bag) as reader:
                start, end = reader.start_ns, reader.end_ns
        except Exception:           # the map task reports it
            tasks.append(base)
            continue
        step = max(1, round(segment_seconds * 1e9 / RESIDUAL_GRID)) * RESIDUAL_GRID
        cuts = list(range((start // step + 1) * step, end, step))
        bounds = [None] + cuts + [None]
        tasks += [replace(base, index=i, start_ns=a, stop_ns=b)
                  for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:]))]
    return tasks


def reduce_statistics(pairs: Iterable[tuple[MapTask, BagStatistics]]
                      ) -> tuple[dict[tuple[str, str], BagStatistics], list[dict]]:
    """Merged statistics per (robot, period), summed in (bag, segment) order, and the
    failures ({bag, error}: a bag of another model than the rest of its robot's)."""
    groups: dict[tuple[str, str], BagStatistics] = {}
    failures = []
    for task, stats in sorted(pairs, key=lambda p: (p[0].entry.bag, p[0].index)):
        key = (task.entry.robot, task.entry.period)
        try:
            groups[key] = stats if key not in groups else groups[key] + stats
        except IdentificationError as exc:
            failures.append({'bag': task.entry.bag, 'error': str(exc)})
    return groups, failures


def connect(scheduler: str | None = None, workers: int | None = None, timeout: float = 5.0):
    """A dask.distributed Client: of the scheduler at ``scheduler`` (tcp://HOST:PORT), or of a
    LocalCluster with ``workers`` single-threaded worker processes (default: one per core).
    IdentificationError within ``timeout`` seconds when the scheduler cannot be reached."""
    import logging

    from distributed import Client, LocalCluster

    logging.getLogger('distributed').setLevel(logging.ERROR)
    if scheduler:
        try:
            client = Client(scheduler, timeout=f'{timeout}s')
        except (OSError, TimeoutError, ValueError) as exc:
            raise IdentificationError(f'cannot reach the dask scheduler at {scheduler}: '
                                      f'{str(exc).splitlines()[0] if str(exc) else exc!r}'
                                      ) from None
        try:
            client.wait_for_workers(1, timeout=timeout)
        except (OSError, TimeoutError):
            client.close()
            raise IdentificationError(f'the dask scheduler at {scheduler} has no workers '
                                      f'(none joined within {timeout:g} s)') from None
        return client
    n = (os.cpu_count() or 1) if workers is None else workers
    if n < 1:
        raise IdentificationError(f'--workers must be >= 1, got {n}')
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           host='127.0.0.1', dashboard_address='127.0.0.1:0')
    return Client(cluster)


@dataclass
class FleetResult:
    """Per (robot, period) and per robot: the merged statistics and the identification;
    the map failures ({bag, error})."""
    groups: dict
    totals: dict
    identifications: dict
    total_identifications: dict
    failed: list
    smoothers: dict = field(default_factory=dict)   # robot -> choose_smoother's parameters
    duplicates: list = field(default_factory=list)   # drop_duplicates': counted once


def run_fleet(entries: Sequence[FleetEntry], client, segment_seconds: float | None = None,
              joint_states: str = JOINT_STATES, motor_currents: str = MOTOR_CURRENTS,
              solve: Solve = solve_unconstrained, retries: int = 3,
              progress: Callable[[int, int], None] | None = None,
              physical_consistency: bool = True) -> FleetResult:
    """Map every bag (segment) on the cluster, reduce per robot and period, solve (physically
    consistent too unless ``physical_consistency`` is False)."""
    from distributed import as_completed

    entries, duplicates = drop_duplicates(entries, client)
    smoothers = _smoothers(entries, client, joint_states, motor_currents, retries)
    tasks = plan_tasks(entries, segment_seconds, joint_states, motor_currents, smoothers)
    futures = client.map(run_task, tasks, pure=True, retries=retries)
    index = {f.key: t for f, t in zip(futures, tasks)}
    done, results = 0, []
    for future in as_completed(futures):
        task = index[future.key]
        try:
            results.append((task, future.result()))
        except Exception as exc:   # e.g. KilledWorker: the bag crashed every worker it met
            results.append((task, MapFailure(task.entry.bag, f'map task lost: {_why(exc)}')))
        done += 1
        if progress is not None:
            progress(done, len(tasks))
    failed = sorted({(r.bag, r.error) for _, r in results if isinstance(r, MapFailure)})
    bad = {b for b, _ in failed}
    good = [(t, r) for t, r in results if isinstance(r, BagStatistics) and t.entry.bag not in bad]
    groups, failures = reduce_statistics(good)
    failures[:0] = [{'bag': b, 'error': e} for b, e in failed]
    totals: dict[str, BagStatistics] = {}
    for (robot, _), stats in sorted(groups.items(), key=lambda kv: kv[1].first_ns or 0):
        try:
            totals[robot] = stats if robot not in totals else totals[robot] + stats
        except IdentificationError as exc:     # one robot name, two models
            failures.append({'bag': ', '.join(stats.bags), 'error': str(exc)})
    entries_of = {(t.entry.robot, t.entry.period): t.entry for t, _ in good}
    models: dict[str, tuple] = {}     # robot: settings, model, consistent solver
    idents, total_idents = {}, {}
    for key, stats in [*groups.items(), *totals.items()]:
        robot = key[0] if isinstance(key, tuple) else key
        try:
            if robot not in models:
                entry = next(e for k, e in entries_of.items() if k[0] == robot)
                settings = task_settings(entry, smoothers.get(robot, ()))
                model = entry_robot(entry, settings)
                models[robot] = (settings, model,
                                 consistent_solver(settings, model) if physical_consistency
                                 else None)
            settings, model, solver = models[robot]
            label = f'{robot} {key[1]}' if isinstance(key, tuple) else robot
            ident = identification(stats, settings, model, label, solve, physical_consistency,
                                   solver)
            if isinstance(key, tuple):
                idents[key] = ident
            else:
                total_idents[robot] = ident
        except IdentificationError as exc:
            failures.append({'bag': ', '.join(stats.bags), 'error': str(exc)})
    return FleetResult(groups, totals, idents, total_idents, failures, smoothers, duplicates)


def _smoothers(entries: Sequence[FleetEntry], client, joint_states: str,
               motor_currents: str, retries: int) -> dict[str, tuple]:
    """choose_smoother per robot on the cluster: on its first bag in manifest order, or,
    when that one cannot be read, the next."""
    pending: dict[str, list[FleetEntry]] = {}
    for e in entries:
        pending.setdefault(e.robot, []).append(e)
    out: dict[str, tuple] = {}
    while pending:
        firsts = {robot: es.pop(0) for robot, es in pending.items()}
        futures = {robot: client.submit(choose_smoother, e, joint_states, motor_currents,
                                        pure=True, retries=retries)
                   for robot, e in firsts.items()}
        for robot, future in futures.items():
            try:
                out[robot] = future.result()
                pending.pop(robot)
            except Exception:   # noqa: BLE001 - that bag's own task reports why
                if not pending[robot]:
                    pending.pop(robot)
    return out


def content_hash(bag: str | os.PathLike) -> str | None:
    """A hash of the bag's messages (topic, log time, bytes, in log-time order): the same for
    a copy of a bag or the bag under another spelling of its path; None when the bag cannot
    be read (its map task says why)."""
    from identification_node.bags.reader import open_bag
    digest = hashlib.blake2b(digest_size=16)
    try:
        with open_bag(bag) as reader:
            for topic, _, t_ns, raw in reader.raw_messages():
                digest.update(b'%s\0%d\0%d\0' % (topic.encode(), t_ns, len(raw)))
                digest.update(raw)
    except Exception:   # noqa: BLE001 - reported by the bag's own task
        return None
    return digest.hexdigest()


def drop_duplicates(entries: Sequence[FleetEntry], client=None
                    ) -> tuple[list[FleetEntry], list[dict]]:
    """(entries without those whose bag holds the same messages as an earlier one's,
    [{bag, duplicate_of}]): the same data counted twice would shrink the stddev by sqrt(2).
    The hashes are computed on the cluster when ``client`` is given."""
    bags = [e.bag for e in entries]
    hashes = (client.gather(client.map(content_hash, bags, pure=True)) if client is not None
              else [content_hash(b) for b in bags])
    first: dict[str, str] = {}
    kept, duplicates = [], []
    for entry, key in zip(entries, hashes):
        if key is not None and key in first:
            duplicates.append({'bag': entry.bag, 'duplicate_of': first[key]})
            continue
        if key is not None:
            first[key] = entry.bag
        kept.append(entry)
    return kept, duplicates


def print_progress(done: int, total: int, unit: str = 'bags') -> None:
    """A plain count of map tasks done, on stderr."""
    print(f'fleet: {done}/{total} {unit} done', file=sys.stderr, flush=True)


# -- flags ----------------------------------------------------------------------------------------
def _params(doc: dict) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names, unconstrained base estimates and their stddev (nan, inf where not excited).
    The flags test these, not the consistent estimate: the unconstrained WLS estimate is
    unbiased with exactly the stddev of the information, so (b - a) / sqrt(sa^2 + sb^2) is a
    standard normal without change; the consistent one is pulled by the constraints and the
    regulariser (differently in each period, by amounts its stddev does not describe)."""
    ps = doc['base_parameters']
    sd = [p['stddev'] if p['stddev'] is not None else math.inf for p in ps]
    est = [p['unconstrained_estimate'] if p['unconstrained_estimate'] is not None else math.nan
           for p in ps]
    return [p['name'] for p in ps], np.array(est, dtype=float), np.array(sd, dtype=float)


def drift_flags(periods: dict[str, dict], robot: str, k: float = DEFAULT_SIGMA) -> list[dict]:
    """Parameters of ``robot`` that moved by more than k standard deviations of the change
    (sqrt(sd_a^2 + sd_b^2)) between consecutive periods; ``periods``: period -> identify
    document, in time order. A k-sigma test on the unconstrained base estimates and their
    stddev (see _params), also when the documents' ``estimate`` is the consistent one."""
    flags = []
    keys = list(periods)
    for before, after in zip(keys[:-1], keys[1:]):
        names, a, sa = _params(periods[before])
        _, b, sb = _params(periods[after])
        with np.errstate(invalid='ignore', divide='ignore'):
            z = np.abs(b - a) / np.sqrt(sa ** 2 + sb ** 2)
        for i in np.flatnonzero(z > k):
            flags.append({'robot': robot, 'period': after, 'parameter': names[i],
                          'change_sigma': float(z[i]), 'kind': 'drift', 'since': before,
                          'before': float(a[i]), 'after': float(b[i])})
    return flags


def outlier_flags(totals: dict[str, dict], models: dict[str, str], k: float = DEFAULT_SIGMA
                  ) -> list[dict]:
    """Robots whose estimate of a parameter lies more than k deviations from the median of
    the other robots of the same model: deviation sqrt(sd^2 + s^2), s the others' spread
    (1.4826 MAD, at least the median of their stddevs). Needs 3 robots of a model."""
    flags = []
    by_model: dict[str, list[str]] = {}
    for robot in totals:
        by_model.setdefault(models[robot], []).append(robot)
    for robots in by_model.values():
        if len(robots) < 3:
            continue
        data = {r: _params(totals[r]) for r in robots}
        for r in robots:
            names, x, sx = data[r]
            others = np.array([data[o][1] for o in robots if o != r])
            osd = np.array([data[o][2] for o in robots if o != r])
            med = np.median(others, axis=0)
            spread = np.maximum(1.4826 * np.median(np.abs(others - med), axis=0),
                                np.median(osd, axis=0))
            with np.errstate(invalid='ignore', divide='ignore'):
                z = np.abs(x - med) / np.sqrt(sx ** 2 + spread ** 2)
            for i in np.flatnonzero(z > k):
                flags.append({'robot': r, 'period': None, 'parameter': names[i],
                              'change_sigma': float(z[i]), 'kind': 'fleet_outlier',
                              'fleet_median': float(med[i]), 'estimate': float(x[i])})
    return flags


def fleet_document(result: FleetResult, k: float = DEFAULT_SIGMA) -> dict:
    """The ``fleet --json`` object: robots -> period -> the identify document, per-robot
    totals, flags and failed bags."""
    from identification_node.cli.identify import result_document

    robots: dict[str, dict] = {}
    order = sorted(result.identifications, key=lambda rp: (
        rp[0], result.groups[rp].first_ns or 0, rp[1]))
    for robot, period in order:
        doc = result_document(result.identifications[robot, period])
        doc['bags'] = list(result.groups[robot, period].bags)
        robots.setdefault(robot, {})[period] = doc
    totals = {}
    for robot, ident in result.total_identifications.items():
        totals[robot] = result_document(ident)
        totals[robot]['bags'] = list(result.totals[robot].bags)
    flags = [f for robot, periods in robots.items() for f in drift_flags(periods, robot, k)]
    flags += outlier_flags(totals, {r: result.totals[r].model for r in totals}, k)
    return {'robots': robots, 'totals': totals, 'flags': flags, 'failed': result.failed,
            'duplicates': result.duplicates, 'sigma': k,
            'smoothers': {r: dict(v) for r, v in sorted(result.smoothers.items())}}
