"""Replay benchmark: our offline identification against a naive pipeline, same bag, same process.

The bag: a simulated CRS A465 (6 joints) under the seeded 5-harmonic Fourier excitation at
1 kHz, /joint_states with position (262144-count encoders), velocity and effort (0.2 N m noise,
viscous and Coulomb friction of bags/crs_a465_friction.yaml), and /robot_description; made
once per sample count and cached in bench/.cache/ (gitignored).

(a) ours: ``identify_bag`` with config/crs_a465.yaml (measured torque, fv and fc identified;
    its smoother pinned at a half window of 10 samples for the bundled bags), the estimate
    read at the end; ``ours auto``: the same with the shipped smoother (chosen automatically
    from the first 5 s of motion), what a user replaying another bag gets.
(a') ours on every core (``--workers N``, default the machine's cores; 1: not run): the same
    settings through replay/parallel.py, the bag cut into N about equal segments (at
    multiples of the 10 s residual grid) in N processes (fork),
    their statistics merged (``identify BAG --workers N``).
(b) naive, as a user would write it: rosbags AnyReader deserializing every message, joints
    reordered by name, qdd = np.gradient(qd, t) over the whole arrays, pinocchio
    computeJointTorqueRegressor per sample into a stacked (6 N, 60) matrix, numpy lstsq.

Throughput is samples / wall time, best of --repeat interleaved runs with tracing off (CPU
time of the same run beside it). Peak memory, two ways: the tracemalloc peak of a run in this
process (Python and numpy allocations), and the peak resident set size of a fresh process
running only that pipeline, above its RSS after imports (VmHWM of /proc/self/status; it also
counts C++ and allocator memory). Ours is measured on a bag of half the length too: its peak
should not grow with the bag. BLAS runs single-threaded (OPENBLAS_NUM_THREADS=1, as in the
tests; set it to override): on 2 shared cores, BLAS threads spin against each other and make
both pipelines several times slower and erratic.

Last, pinocchio's regressor alone as ours calls it (RobotModel.regressor, us per sample);
bench_compiled_regressor.py measures a compiled loop over samples in its place.

    .venv/bin/python bench/bench_replay.py [--samples 100000] [--repeat 3] [--workers N]
"""
from __future__ import annotations

import argparse
import gc
import os
import re
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

from checkout import ROOT  # noqa: E402  (this checkout's package, here and in subprocesses)

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # before numpy loads OpenBLAS

import numpy as np  # noqa: E402

CACHE = ROOT / 'bench' / '.cache'
CONFIG = ROOT / 'config' / 'crs_a465.yaml'
FRICTION = ROOT / 'bags' / 'crs_a465_friction.yaml'
RATE = 1000.0
BAG_VERSION = 1  # bump when the bag recipe changes (cache key)


def make_bag(samples: int) -> Path:
    """The cached benchmark bag of ``samples`` joint states (made on first use)."""
    from identification_node.bags.writer import BagWriter
    from identification_node.simulation.bag import read_true_parameters
    from identification_node.excitation.trajectories import load_trajectory
    from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
    from identification_node.settings import Settings, read_parameter_file
    from identification_node.wire.cdr import JOINT_STATE

    path = CACHE / f'crs_a465_v{BAG_VERSION}_{samples}'
    if (path / 'metadata.yaml').is_file():
        return path
    robot = Settings.from_dict(read_parameter_file(CONFIG)).load_robot()
    phi = read_true_parameters(str(FRICTION), robot, 'true parameters')
    t = np.arange(samples) / RATE
    sim = simulate_kinematic(robot, phi, load_trajectory('fourier', robot), t,
                             SensorNoise(torque_std=0.2, encoder_counts=262144), seed=3)
    stamps = np.round(t * 1e9).astype(np.int64).tolist()
    names = list(robot.joint_names)
    with BagWriter(path, 'mcap', overwrite=True) as bag:
        bag.add_topic('/joint_states', JOINT_STATE)
        bag.write_string('/robot_description', 0, robot.description)
        for k, ns in enumerate(stamps):
            bag.write_joint_state('/joint_states', ns, ns * 1e-9, names, sim.q_meas[k],
                                  sim.qd_meas[k], sim.tau_meas[k])
    return path


def _settings(automatic: bool = False):
    """The benchmark's settings: config/crs_a465.yaml, with the shipped automatic smoother
    instead of its pinned half window when ``automatic``."""
    from identification_node.settings import Settings, read_parameter_file

    params = read_parameter_file(CONFIG)
    if automatic:
        params['smoother.half_window'] = 0
    return Settings.from_dict(params)


def run_ours(bag: Path, automatic: bool = False) -> tuple[int, np.ndarray]:
    """Offline identification through the live pipeline; (samples used, base estimate)."""
    from identification_node.replay.stream import identify_bag

    settings = _settings(automatic)
    robot = settings.load_robot()
    result = identify_bag(bag, settings, robot)
    estimate = result.pipeline.estimate()
    return result.messages, estimate.values


def run_parallel(bag: Path, workers: int, automatic: bool = False
                 ) -> tuple[int, np.ndarray]:
    """ours through identify --workers N's path; (messages, base estimate)."""
    from identification_node.replay.parallel import parallel_identify

    settings = _settings(automatic)
    robot = settings.load_robot()
    ident = parallel_identify(bag, settings, robot, workers)
    if ident is None:
        raise SystemExit(f'{bag} is too short to cut into segments (two residual-grid '
                         'cells needed)')
    return ident.messages, ident.theta


def run_naive(bag: Path) -> tuple[int, np.ndarray]:
    """What a user would write with rosbags, numpy and pinocchio; (samples, phi (60,))."""
    import pinocchio as pin
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    joints = ['joint1', 'joint2', 'joint3', 'joint4', 'joint5', 'joint6']
    stamps, q, qd, tau = [], [], [], []
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        urdf = None
        for conn, _, raw in reader.messages(
                [c for c in reader.connections if c.topic == '/robot_description']):
            urdf = reader.deserialize(raw, conn.msgtype).data
        for conn, _, raw in reader.messages(
                [c for c in reader.connections if c.topic == '/joint_states']):
            msg = reader.deserialize(raw, conn.msgtype)
            order = [list(msg.name).index(j) for j in joints]
            stamps.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
            q.append(msg.position[order])
            qd.append(msg.velocity[order])
            tau.append(msg.effort[order])
    t, q, qd, tau = np.array(stamps), np.array(q), np.array(qd), np.array(tau)
    qdd = np.gradient(qd, t, axis=0)
    model = pin.buildModelFromXML(urdf)
    data = model.createData()
    N = len(t)
    Y = np.empty((6 * N, 10 * model.nv))
    for k in range(N):
        Y[6 * k:6 * k + 6] = pin.computeJointTorqueRegressor(model, data, q[k], qd[k], qdd[k])
    phi = np.linalg.lstsq(Y, tau.reshape(-1), rcond=None)[0]
    return N, phi


def _status_kib(field: str) -> int:
    text = Path('/proc/self/status').read_text()
    return int(re.search(rf'^{field}:\s+(\d+)', text, re.M).group(1))


def run_ours_auto(bag: Path) -> tuple[int, np.ndarray]:
    """ours with the shipped (automatic) smoother."""
    return run_ours(bag, automatic=True)


PIPELINES = {'ours': run_ours, 'ours auto': run_ours_auto, 'naive': run_naive}


def throughput(bags: dict, repeat: int) -> dict:
    """{name: (samples, best wall s, CPU s of that run)}, runs interleaved."""
    best = {}
    for _ in range(repeat):
        for name, (fn, bag) in bags.items():
            gc.collect()
            t0, c0 = time.perf_counter(), time.process_time()
            n, _ = fn(bag)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if name not in best or wall < best[name][1]:
                best[name] = (n, wall, cpu)
    return best


def traced_peak(fn, bag: Path) -> float:
    """tracemalloc peak (MiB) of one run."""
    gc.collect()
    tracemalloc.start()
    tracemalloc.reset_peak()
    fn(bag)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def rss_peak(name: str, bag: Path) -> float:
    """Peak RSS (MiB) of a fresh process running pipeline ``name`` once, above its RSS after
    imports and a warm-up run on a tiny bag."""
    out = subprocess.run([sys.executable, __file__, '--rss', name, str(bag)], check=True,
                         capture_output=True, text=True).stdout
    return float(out.split()[-1])


def _rss_child(name: str, bag: Path) -> None:
    fn = PIPELINES[name]
    fn(make_bag(2000))
    gc.collect()
    Path('/proc/self/clear_refs').write_text('5')  # VmHWM := current RSS
    base = _status_kib('VmRSS')
    fn(bag)
    print((_status_kib('VmHWM') - base) / 1024)


def regressor_cost(samples: int = 20_000) -> float:
    """us per sample of RobotModel.regressor on the bench's arm, best of 3."""
    from identification_node.settings import Settings, read_parameter_file

    robot = Settings.from_dict(read_parameter_file(CONFIG)).load_robot()
    rng = np.random.default_rng(0)
    q, qd, qdd = (rng.uniform(-1, 1, (samples, robot.dof)) for _ in range(3))
    best = np.inf
    for _ in range(3):
        start = time.perf_counter()
        robot.regressor(q, qd, qdd, checked=True)
        best = min(best, time.perf_counter() - start)
    return best / samples * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--samples', type=int, default=100_000)
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--workers', type=int, default=None,
                        help="processes of ours on every core (default: the machine's cores)")
    parser.add_argument('--rss', nargs=2, metavar=('PIPELINE', 'BAG'), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.rss:
        return _rss_child(args.rss[0], Path(args.rss[1]))
    bag, half = make_bag(args.samples), make_bag(args.samples // 2)
    run_ours(make_bag(2000))  # imports and caches outside the measurements
    from identification_node.replay.parallel import default_workers
    workers = default_workers() if args.workers is None else args.workers
    runs = {name: (fn, bag) for name, fn in PIPELINES.items()}
    if workers > 1:
        runs['ours xN'] = (lambda b: run_parallel(b, workers), bag)
        runs['ours auto xN'] = (lambda b: run_parallel(b, workers, True), bag)
    speed = throughput(runs, args.repeat)
    rows = {name: (*speed[name], traced_peak(fn, bag), rss_peak(name, bag))
            for name, fn in PIPELINES.items()}
    half_n = run_ours(half)[0]
    half_mem = {name: (traced_peak(PIPELINES[name], half), rss_peak(name, half))
                for name in ('ours', 'ours auto')}
    print(f'bag: {bag.relative_to(ROOT)} ({args.samples} joint states, CRS A465, 6 joints), '
          f'best of {args.repeat}, OPENBLAS_NUM_THREADS={os.environ["OPENBLAS_NUM_THREADS"]}')
    print(f'{"":10s}{"samples":>8s}{"wall s":>8s}{"CPU s":>7s}{"samples/s":>11s}'
          f'{"tracemalloc peak":>18s}{"peak RSS":>12s}')
    for name, (n, wall, cpu, traced, rss) in rows.items():
        print(f'{name:10s}{n:8d}{wall:8.2f}{cpu:7.2f}{n / wall:11.0f}{traced:14.1f} MiB'
              f'{rss:8.1f} MiB')
    ours, naive = rows['ours'], rows['naive']
    for name in ('ours', 'ours auto'):
        if f'{name} xN' not in speed:
            continue
        n, wall, cpu = speed[f'{name} xN']
        one = rows[name]
        print(f'{name} on {workers} workers (identify --workers {workers}): {n} samples, '
              f'{wall:.2f} s wall, {n / wall:.0f} samples/s (parent CPU {cpu:.2f} s): '
              f'{(n / wall) / (naive[0] / naive[1]):.2f}x naive, '
              f'{(n / wall) / (one[0] / one[1]):.2f}x {name} on one core')
    for name in ('ours', 'ours auto'):
        r = rows[name]
        print(f'{name}/naive: throughput {(r[0] / r[1]) / (naive[0] / naive[1]):.2f}x '
              f'(CPU time {(naive[2] / naive[0]) / (r[2] / r[0]):.2f}x); peak memory '
              f'{r[3] / naive[3]:.3f}x (tracemalloc), {r[4] / naive[4]:.3f}x (RSS)')
    for name, (traced, rss) in half_mem.items():
        r = rows[name]
        print(f'{name} on {half_n} samples: tracemalloc peak {traced:.1f} MiB, peak RSS '
              f'{rss:.1f} MiB (on {r[0]}: {r[3]:.1f} MiB, {r[4]:.1f} MiB)')
    total = ours[1] / ours[0] * 1e6
    print(f'pinocchio\'s regressor in ours: {regressor_cost():.2f} us per sample of ours\' '
          f'{total:.2f} us (a compiled loop in its place: bench_compiled_regressor.py)')


if __name__ == '__main__':
    main()
