"""Payload detection with the shipped defaults: the matrix, the threshold in kg, false alarms.

    .venv/bin/python bench/bench_payload.py [--arms ur5 panda kinova fixture]
        [--rates 250 500 1000 2000] [--minutes 30] [--skip-matrix] [--skip-threshold]

Every run: the arm (example-robot-data's UR5, Panda with its 7 arm joints, Kinova, or the
project's 7-DOF fixture), with or without joint friction, is identified first by the node's
pipeline with default settings (30 s without payload; what --arm passes), then the default
payload monitor watches a different motion (test/payload_scenarios.py) at the given rate and
torque noise (18-bit encoders, measured velocities 0.01 rad/s).

1. Matrix: per arm, rate and noise/friction case, the four sequences (pick 1 kg; pick 3 kg
   and place; pick 1 kg, place, pick 0.25 kg; pick 2 kg, place, pick 0.5 kg; centres of mass
   up to 0.1 m off the flange): changes detected, the largest detection delay, the largest
   mass error (percent) and centre-of-mass error (mm) of the fitted segments, and changes
   declared that did not happen.
2. Threshold: per rate (UR5, friction, 0.1 N m) the smallest mass of [0.05, 0.3] kg whose
   pick is detected in every one of 3 seeds (payload.min_change, 0.2 kg, bounds it below).
3. False alarms: --minutes of motion without a change (UR5, friction, 0.2 N m, 1 kHz) and
   the bundled bags (their own robots, defaults); the monitor's cost per sample against the
   pipeline's, in the same run.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / 'test')]

import payload_scenarios as ps  # noqa: E402
from identification_node.replay.stream import identify_bag  # noqa: E402
from identification_node.payload.fit import PayloadChange  # noqa: E402
from identification_node.payload.monitor import monitor_from_settings  # noqa: E402
from identification_node.settings import Settings, read_parameter_file  # noqa: E402
from test_payload_matrix import SEQUENCES  # noqa: E402

CASES = ((0.05, True), (0.2, True), (0.1, False))   # torque noise N m, joint friction
BAGS = (('mit_paper_moves', 'identification.yaml'), ('mit_exciting', 'identification.yaml'),
        ('mit_paper_moves_sqlite3', 'identification.yaml'),
        ('crs_a465_fourier', 'crs_a465.yaml'))


def run_sequence(arm, phi_arm, rate, noise, changes, seed):
    """(detection delays or None per change, mass errors %, com errors mm, false alarms)."""
    mon = ps.monitor(arm, phi_arm)
    sim = ps.simulate(arm, rate, changes[-1].time + 5.0, noise, seed, changes)
    events = ps.watch(mon, sim)
    segments = mon.finish()
    detected = [ps.seconds(e.detected) for e in events if e.kind == 'change']
    delays, used = [], set()
    for c in changes:
        hit = [k for k, d in enumerate(detected) if c.time <= d <= c.time + 2.0
               and k not in used]
        delays.append(detected[hit[0]] - c.time if hit else None)
        used.update(hit[:1])
    mass, com = [], []
    if len(segments) == len(changes) + 1:
        for seg, c in zip(segments[1:], changes):
            p = seg.payload
            mass.append(100 * abs(p.mass - c.mass) / c.mass if c.mass else 0.0)
            if c.mass:
                com.append(1e3 * np.abs(p.com - c.com).max())
    return delays, mass, com, len(detected) - len(used)


def matrix(arms, rates) -> None:
    print('1. matrix (shipped defaults; arm identified first): per cell all four sequences')
    print(f"{'arm':>8} {'rate':>5} {'noise':>5} {'fric':>4} {'detected':>9} "
          f"{'max delay s':>11} {'mass err %':>10} {'com err mm':>10} {'false':>5}")
    for name in arms:
        for rate in rates:
            for noise, friction in CASES:
                arm = ps.make_arm(name, friction)
                phi_arm = ps.identify_arm(arm, rate, noise)
                n = found = false = 0
                delays, mass, com = [], [], []
                for k, changes in enumerate(SEQUENCES.values()):
                    d, m, c, f = run_sequence(arm, phi_arm, rate, noise, changes, 10 + k)
                    n += len(d)
                    found += sum(x is not None for x in d)
                    delays += [x for x in d if x is not None]
                    mass += m
                    com += c
                    false += f
                print(f'{name:>8} {rate:5.0f} {noise:5.2f} {"yes" if friction else "no":>4} '
                      f'{found:>4}/{n:<4} {max(delays, default=np.nan):11.3f} '
                      f'{max(mass, default=np.nan):10.2f} {max(com, default=np.nan):10.2f} '
                      f'{false:>5}', flush=True)


def threshold(rates) -> None:
    print('\n2. detection threshold (UR5, friction, 0.1 N m; smallest mass picked and '
          'detected in 3 of 3 seeds)')
    arm = ps.make_arm('ur5', True)
    for rate in rates:
        phi_arm = ps.identify_arm(arm, rate, 0.1)
        smallest = None
        for mass in (0.3, 0.25, 0.2, 0.15, 0.1, 0.05):
            ok = all(run_sequence(arm, phi_arm, rate, 0.1,
                                  [PayloadChange(4.0, None, mass, (0.02, 0.0, 0.05))],
                                  20 + s)[0][0] is not None for s in range(3))
            if not ok:
                break
            smallest = mass
        print(f'   {rate:6.0f} Hz: {smallest if smallest is not None else "> 0.3"} kg',
              flush=True)


def false_alarms(minutes: float) -> None:
    print(f'\n3. false alarms: {minutes:g} min of motion without a change (UR5, friction, '
          '0.2 N m, 1 kHz), and the bundled bags')
    arm = ps.make_arm('ur5', True)
    phi_arm = ps.identify_arm(arm, 1000.0, 0.2)
    mon = ps.monitor(arm, phi_arm)
    pipe = arm.settings.build(arm.robot)
    pipe_time = mon_time = 0.0
    declared, samples = 0, 0
    chunk = 60.0
    for k in range(int(np.ceil(minutes * 60 / chunk))):
        sim = ps.simulate(arm, 1000.0, chunk, 0.2, 100 + k)
        sim.t = sim.t + k * chunk
        t0 = time.perf_counter()
        ps.stream(pipe, sim)
        t1 = time.perf_counter()
        declared += sum(e.kind == 'change' for e in ps.watch(mon, sim))
        mon_time += time.perf_counter() - t1
        pipe_time += t1 - t0
        samples += len(sim.t)
    print(f'   simulated: {declared} changes declared over {samples / 60000:.1f} min; cost per '
          f'sample: pipeline {1e6 * pipe_time / samples:.1f} us, payload monitor '
          f'{1e6 * mon_time / samples:.1f} us (ratio {mon_time / pipe_time:.2f})')
    for bag, config in BAGS:
        settings = Settings.from_dict(read_parameter_file(ROOT / 'config' / config))
        robot = settings.load_robot()
        mon = monitor_from_settings(settings, robot)
        events = []
        identify_bag(ROOT / 'bags' / bag, settings, robot,
                     on_output=lambda out: events.extend(mon.add_output(out)))
        print(f"   bag {bag}: {sum(e.kind == 'change' for e in events)} changes declared")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--arms', nargs='+', default=['ur5', 'panda', 'kinova', 'fixture'])
    parser.add_argument('--rates', nargs='+', type=float, default=[250, 500, 1000, 2000])
    parser.add_argument('--minutes', type=float, default=30.0)
    parser.add_argument('--skip-matrix', action='store_true')
    parser.add_argument('--skip-threshold', action='store_true')
    args = parser.parse_args()
    if not args.skip_matrix:
        matrix(args.arms, args.rates)
    if not args.skip_threshold:
        threshold(args.rates)
    false_alarms(args.minutes)
    return 0


if __name__ == '__main__':
    sys.exit(main())
