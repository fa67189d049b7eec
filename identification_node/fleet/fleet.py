"""Fleet identification: many bags of many robots, reduced to estimates per robot and period.

Map: each bag, or each time segment of a long bag, streams through the node's pipeline
(replay.identify_bag) and leaves its sufficient statistics (BagStatistics): the per-joint
normal equations of its rows (NormalEquations), the residual sums over samples and over blocks
(ResidualStatistics, for the honest stddev) and the counters. A segment's pipeline (its
stage pipeline.SegmentWindow) is fed ``half_window * max_gap + hold_time + align_tolerance``
seconds of the bag on either side and keeps only the rows centred inside the segment, so its
rows are the whole bag's (the smoother never fits across a gap larger than max_gap).

Reduce: statistics add exactly (sums), in a fixed order (bag, segment), whatever order the
tasks finish in. Bags are separate recordings: residual blocks restart at each bag, as the
pipeline's do at a stream restart. They also restart wherever the stamps cross a multiple of
estimate.RESIDUAL_GRID (10 s), and segments are cut only there (plan_tasks), so a segment's
blocks are the whole bag's: the merged statistics, estimate and stddev equal the unsplit
run's. (A cut elsewhere, bag_statistics' own start_ns/stop_ns, keeps rows and estimate but
shifts the blocks.) Whole bags are the default unit.

Solve: ``solve_unconstrained(NormalEquations) -> theta`` (the streaming estimator's own least
squares on the merged normal equations) is the seam of the unconstrained solve (``solve=``);
the pipeline then derives noise, covariance and convergence from the statistics at that theta
as it does for streamed data (IdentificationPipeline.restore), so a group of bags gives what
``identify`` gives for one bag holding them one after another (each its own stream). Then,
as ``identify`` does, results.identification.make_consistent solves the same information physically
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

from identification_node.bags.feed import JOINT_STATES, MOTOR_CURRENTS
from identification_node.errors import IdentificationError
from identification_node.model.robot import RobotModel
from identification_node.replay.segments import (BagStatistics, Solve, bag_smoother, bag_span,
                                                 bag_statistics, consistent_solver, grid_segments,
                                                 identification, model_key, pinned,
                                                 solve_unconstrained)
from identification_node.replay.stream import bag_robot
from identification_node.settings import Settings

__all__ = ['DEFAULT_SIGMA', 'MANIFEST_COLUMNS', 'OPTIONAL_COLUMNS', 'FleetEntry',
           'read_manifest', 'scan_directory', 'entry_settings', 'entry_robot', 'MapTask',
           'task_settings', 'choose_smoother', 'MapFailure', 'run_task', 'plan_tasks',
           'reduce_statistics', 'connect', 'FleetResult', 'run_fleet', 'content_hash',
           'drop_duplicates', 'print_progress', 'drift_flags', 'outlier_flags',
           'fleet_document']

DEFAULT_SIGMA = 5.0          # k: flag changes larger than k standard deviations
MANIFEST_COLUMNS = ('bag', 'robot', 'period')
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
            reader = csv.DictReader(f)
            rows = list(reader)
            header = [c.strip() for c in reader.fieldnames or ()]
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
    entries: list[FleetEntry] = []
    seen: dict[str, int] = {}     # bag: its line
    for line, raw in enumerate(rows, start=2):
        if None in raw:   # DictReader keys the fields beyond the header's by None
            raise IdentificationError(f'manifest {path} line {line}: more fields than the '
                                      'header names')
        row = {k.strip(): (v or '').strip() for k, v in raw.items() if k is not None}
        if not all(row.get(c) for c in MANIFEST_COLUMNS):
            raise IdentificationError(f'manifest {path} line {line}: bag, robot and period '
                                      'must all be given')

        def local(name: str) -> str | None:
            return str(path.parent / row[name]) if row.get(name) else None

        bag = str(path.parent / row['bag'])
        if bag in seen:
            raise IdentificationError(f"manifest {path} line {line}: bag {row['bag']} is "
                                      f"listed twice (first on line {seen[bag]})")
        seen[bag] = line
        entries.append(FleetEntry(bag, row['robot'], row['period'], local('urdf'),
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
    """One task per bag, or per ``segment_seconds`` of its stamps (bag_span), rounded to a
    multiple of the residual grid (estimate.RESIDUAL_GRID, 10 s) and cut at multiples of it,
    where the residual blocks restart, so the segments' statistics merge to the whole bag's exactly
    (the first and last segment open-ended, so every row belongs to exactly one);
    ``smoothers``: per robot the smoother parameters of its tasks (choose_smoother)."""
    from identification_node.bags.reader import open_bag

    tasks = []
    for e in entries:
        base = MapTask(e, joint_states=joint_states, motor_currents=motor_currents,
                       smoother=(smoothers or {}).get(e.robot, ()))
        if not segment_seconds:
            tasks.append(base)
            continue
        try:
            with open_bag(e.bag) as reader:
                start, end = bag_span(reader, joint_states)
        except Exception:           # the map task reports it
            tasks.append(base)
            continue
        tasks += [replace(base, index=i, start_ns=g.start_ns, stop_ns=g.stop_ns)
                  for i, g in enumerate(grid_segments(start, end, segment_seconds))]
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
    keyed: list[tuple[tuple[str, str] | str, BagStatistics]] = [
        *groups.items(), *totals.items()]
    for key, stats in keyed:
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
    from identification_node.results.documents import result_document

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
