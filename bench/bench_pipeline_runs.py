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
        [--warmup 400] [--profile 30]

``--warmup R``: runs before the measured ones (the smoother's window filled, caches warm). The
default 400 (4 s at 10 ms) measures while the automatic smoother is chosen (the first 5 s) and
the time offset checked (the first 10 s); 2000 measures the steady state after both.

``--profile N`` then runs the pipeline's paced runs once more under cProfile and prints the N
functions with the most time of their own (cProfile's overhead inflates Python-level calls;
the figures above are the unprofiled ones).
"""
from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import sys
import time
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # as the node's entry point, before numpy

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_node import PANDA  # noqa: E402


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
    args = parser.parse_args()

    from identification_node.excitation.trajectories import FourierTrajectory
    from identification_node.settings import Settings
    from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
    from identification_node.wire.cdr import encode_joint_states

    # the node's defaults (friction and offset columns, the automatic smoother, ...)
    settings = Settings.from_dict({'robot': str(PANDA), 'torque_source': ['measured']})
    robot = settings.load_robot()
    warm = args.warmup
    per = 1000 * args.period     # messages per run, on average
    N = int(per * (args.runs + warm)) + 3
    sim = simulate_kinematic(robot, None, FourierTrajectory.random(robot, seed=1),
                             np.arange(N) * 1e-3, SensorNoise(torque_std=0.2))
    jitter = np.random.default_rng(2).uniform(0, 1e3 * args.jitter, N).astype(np.int64)
    messages = encode_joint_states(10**18 + np.arange(N) * 10**6 + jitter, robot.joint_names,
                                   sim.q_meas, sim.qd_meas, sim.tau_meas)
    starts = np.round(per * np.arange(args.runs + warm + 1)).astype(int)

    def pipeline_work():
        pipeline = settings.build(robot)

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


if __name__ == '__main__':
    main()
