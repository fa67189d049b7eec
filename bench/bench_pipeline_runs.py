"""What one processing run of the pipeline costs, back to back and at the node's schedule.

No ROS: the 7-DOF arm of bench_node.py at 1 kHz, its JointState messages encoded as CDR, and
runs of ``--period`` times 1000 messages (as the node at 1 kHz with that ``process_period``)
added as the node adds them (``add_joint_state_cdr``) and processed by an
IdentificationPipeline. Each run's thread CPU time
is measured two ways: runs back to back (hot caches), and runs ``--period`` apart with the
thread asleep in between, as the node's processing thread runs them (what the node pays). A
fixed reference workload (a Python loop and a few small numpy operations) and ``time.sleep``
itself are measured the same two ways, so the machine's own wake-up penalty shows beside the
pipeline's. Kinds alternate.

    .venv/bin/python bench/bench_pipeline_runs.py [--runs 4000] [--period 0.0025] [--repeat 3]
        [--warmup 400] [--profile 30] [--startup 12] [--against REV]

``--warmup R``: runs before the measured ones (the smoother's window filled, caches warm). The
default 400 (4 s at 10 ms) measures while the automatic smoother is chosen (the first 5 s) and
the time offset checked (the first 10 s); 2000 measures the steady state after both.

``--profile N`` then runs the pipeline's paced runs once more under cProfile and prints the N
functions with the most time of their own (cProfile's overhead inflates Python-level calls;
the figures above are the unprofiled ones).

``--against REV`` then alternates paced runs, run by run in this process, of this checkout's
pipeline and of the one at git revision REV (its package copied under another name): on a
machine whose speed drifts by 20 % between invocations, the ratio of a change is measured
within it.

``--startup S`` then runs a new stream's first S s back to back and prints the pipeline's CPU
per second of data and its longest runs, the smoother's choice (at 5 s) and the time offset
check (10 s) among them: what a live stream's first seconds cost, and the longest wait a run
puts on the outputs.
"""
from __future__ import annotations

import argparse
import atexit
import cProfile
import importlib
import io
import os
import pstats
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # as the node's entry point, before numpy

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_node import PANDA  # noqa: E402

PARAMETERS = {'robot': str(PANDA), 'torque_source': ['measured']}   # else the node's defaults


def reference_work() -> float:
    """A fixed small workload: a Python loop and numpy operations on a short array."""
    s = 0.0
    for i in range(300):
        s += i
    a = np.arange(50.0)
    for _ in range(20):
        a = a * 1.0001 + 1.0
    return s + float(a[0])


def per_run(work, runs: int, period: float) -> float:
    """Mean thread CPU (us) of ``work(k)`` for k < runs, ``period`` s of sleep before each."""
    cpu = 0.0
    for k in range(runs):
        if period:
            time.sleep(period)
        start = time.thread_time()
        work(k)
        cpu += time.thread_time() - start
    return 1e6 * cpu / runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--runs', type=int, default=4000)
    parser.add_argument('--period', type=float, default=0.01, help='s between paced runs')
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--warmup', type=int, default=400, metavar='R',
                        help='runs before the measured ones')
    parser.add_argument('--jitter', type=float, default=0.0, metavar='US',
                        help='header stamps off their 1 ms grid by up to US microseconds '
                        '(uniform; a driver stamping on receipt, as bench_node\'s publisher)')
    parser.add_argument('--profile', type=int, default=0, metavar='N',
                        help='then profile the paced pipeline runs, print the top N functions')
    parser.add_argument('--startup', type=float, default=0.0, metavar='S',
                        help='then time a new stream\'s first S s, run by run')
    parser.add_argument('--against', metavar='REV',
                        help='then alternate paced runs in this process with the pipeline of '
                        'git revision REV')
    args = parser.parse_args()

    from identification_node.excitation.trajectories import FourierTrajectory
    from identification_node.settings import Settings
    from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
    from identification_node.wire.cdr import encode_joint_states

    # the node's defaults (friction and offset columns, the automatic smoother, ...)
    settings = Settings.from_dict(PARAMETERS)
    robot = settings.load_robot()
    warm = args.warmup
    per = 1000 * args.period     # messages per run, on average
    N = int(max(per * (args.runs + warm), 1000 * args.startup)) + 3
    sim = simulate_kinematic(robot, None, FourierTrajectory.random(robot, seed=1),
                             np.arange(N) * 1e-3, SensorNoise(torque_std=0.2))
    jitter = np.random.default_rng(2).uniform(0, 1e3 * args.jitter, N).astype(np.int64)
    messages = encode_joint_states(10**18 + np.arange(N) * 10**6 + jitter, robot.joint_names,
                                   sim.q_meas, sim.qd_meas, sim.tau_meas)
    starts = np.round(per * np.arange((N - 3) / per + 1)).astype(int)

    def pipeline_work(package: str | None = None):
        """A run of a new pipeline: this checkout's, or that of ``package`` (package_at)."""
        s, r = settings, robot
        if package is not None:
            s = importlib.import_module(package + '.settings').Settings.from_dict(PARAMETERS)
            r = s.load_robot()
        pipeline = s.build(r)

        def work(k: int) -> None:
            pipeline.add_joint_state_cdr(messages[starts[k]:starts[k + 1]])
            pipeline.process()
        work.pipeline = pipeline
        return work

    kinds = {'pipeline': pipeline_work,
             'reference workload': lambda: lambda k: reference_work(),
             'sleep alone': None}
    print(f'7-DOF arm, 1 kHz, runs of {per:g} messages; thread CPU per run (us), back to back and '
          f'{1e3 * args.period:g} ms apart; {args.runs} runs, median of {args.repeat}; stamps '
          + (f'jittered by up to {args.jitter:g} us' if args.jitter else 'on a 1 ms grid'))
    results: dict[str, list] = {kind: [] for kind in kinds}
    for _ in range(args.repeat):
        for kind, make in kinds.items():
            if make is None:   # the sleep's own CPU, nothing measured between
                start = time.thread_time()
                for _ in range(args.runs):
                    time.sleep(args.period)
                results[kind].append((0.0, 1e6 * (time.thread_time() - start) / args.runs))
                continue
            figures = []
            for period in (0.0, args.period):
                work = make()
                per_run(work, warm, 0.0)    # the smoother's window filled, caches warm
                figures.append(per_run(lambda k: work(k + warm), args.runs, period))
            results[kind].append(tuple(figures))
    for kind, runs in results.items():
        hot, paced = np.median(np.array(runs), axis=0)
        ratio = f'{paced / hot:4.1f}x' if hot else '     '
        print(f'{kind:19s}: back to back {hot:6.1f} us, paced {paced:6.1f} us  {ratio}')
    if args.profile:
        work = pipeline_work()
        per_run(work, warm, 0.0)
        profile = cProfile.Profile()

        def profiled(k: int) -> None:   # the runs only, not the sleeps between them
            profile.enable()
            work(k + warm)
            profile.disable()
        per_run(profiled, args.runs, args.period)
        pstats.Stats(profile).sort_stats('tottime').print_stats(args.profile)
    if args.startup:
        startup(pipeline_work(), int(1000 * args.startup / per), per)
    if args.against:
        against(args.against, pipeline_work(), pipeline_work(package_at(args.against)), warm,
                args.runs, args.period)


def against(rev: str, now, before, warm: int, runs: int, period: float) -> None:
    """Paced runs of this checkout's pipeline (``now``) and of ``rev``'s (``before``, from
    package_at) alternated run by run, in alternating order, each after ``period`` s of sleep:
    median thread CPU per run."""
    works = {'now': now, rev: before}
    for work in works.values():
        per_run(work, warm, 0.0)
    cpu: dict[str, list[float]] = {label: [] for label in works}
    both = list(works.items())
    for k in range(warm, warm + runs):
        for label, work in both if k % 2 else both[::-1]:
            cpu[label].append(per_run(lambda _, w=work, k=k: w(k), 1, period))
    us_now, us_before = (float(np.median(cpu[label])) for label in ('now', rev))
    print(f'paced runs alternating with {rev} in this process: median {us_before:.1f} us at '
          f'{rev}, {us_now:.1f} us now: {us_now / us_before:.3f}x')


def package_at(rev: str) -> str:
    """This checkout's package at git revision ``rev``, copied into a temporary directory under
    another name (its own imports renamed) and put on sys.path: that name, importable beside
    this checkout's package."""
    name = '_identification_node_' + re.sub(r'\W', '_', rev)
    root = Path(tempfile.mkdtemp(prefix='bench_against_'))
    atexit.register(shutil.rmtree, root, True)
    archive = subprocess.run(['git', '-C', str(checkout.ROOT), 'archive', rev,
                              'identification_node'], check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(root, filter='data')
    (root / 'identification_node').rename(root / name)
    for path in (root / name).rglob('*.py'):
        path.write_text(path.read_text().replace('identification_node', name))
    sys.path.insert(0, str(root))
    return name


def startup(work, runs: int, per: float) -> None:
    """A new stream's first ``runs`` runs back to back: CPU per second of data, longest runs."""
    cpu = np.array([per_run(lambda k: work(i), 1, 0.0) for i in range(runs)])   # us
    second = (np.arange(runs) * per / 1000).astype(int)
    totals = np.bincount(second, weights=cpu) / 1e3
    print(f'a new stream, runs of {per:g} messages back to back: pipeline CPU per second of '
          'data (ms):', ' '.join(f'{x:.0f}' for x in totals))
    for label, after in (('any', 0.0), ('after 6 s (the smoother chosen)', 6.0)):
        k = int(np.argmax(np.where(np.arange(runs) * per / 1000 >= after, cpu, -1.0)))
        print(f'longest run, {label}: {cpu[k] / 1e3:.1f} ms at {k * per / 1000:.2f} s')


if __name__ == '__main__':
    main()
