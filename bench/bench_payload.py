"""Payload detection with the shipped defaults: the matrix, the threshold in kg, false alarms.

    .venv/bin/python bench/bench_payload.py [--arms ur5 panda kinova fixture]
        [--rates 250 500 1000 2000] [--cases 0.05:yes 0.2:yes 0.1:no] [--seed 10] [--minutes 30]
        [--skip-matrix] [--skip-threshold] [--skip-bags] [--skip-floor] [--recording]

Each part runs only the cells asked for (--arms, --rates, --cases: torque noise N m and
joint friction yes/no); --minutes 0 skips the simulated false-alarm run; --seed 20 runs the
matrix on other draws (seeds 20-23: the sequences' motions and noise).

Every run: the arm (example-robot-data's UR5, Panda with its 7 arm joints, Kinova, or the
project's 7-DOF fixture), with or without joint friction, is identified first by the node's
pipeline with default settings (30 s without payload; what --arm passes), then the default
payload monitor watches a different motion (test/payload_scenarios.py) at the given rate and
torque noise (18-bit encoders, measured velocities 0.01 rad/s).

1. Matrix: per arm, rate and noise/friction case, the four sequences (pick 1 kg; pick 3 kg
   and place; pick 1 kg, place, pick 0.25 kg; pick 2 kg, place, pick 0.5 kg; centres of mass
   up to 0.1 m off the flange): changes detected, the largest detection delay, the largest
   mass error (percent) and centre-of-mass error (mm) of the fitted segments, the largest
   of those errors in the fit's own reported stddev (z: mass, and per CoM axis), changes
   declared that did not happen, and the largest CoM stddev the fits reported (what the
   data can tell: above 2.5 mm a 5 mm error is no surprise); then the largest CoM error of
   the axes the fits report (stddev within payload.tolerance.com, 5 mm: what a user gets as
   a value) and how many CoM axes they withhold as "not excited"; last, the largest mass and
   CoM errors of the payloads of 1 kg and more (1, 2 and 3 kg: the issue's reference mass),
   and the largest delay of the changes of 1 kg and more (picks and places).
2. Threshold: per rate (UR5, friction, 0.1 N m) the smallest mass of the grid 0.3, 0.25,
   ..., 0.05 kg whose pick is detected within 2 s in every one of 3 seeds, as are all the
   grid's masses above it (payload.min_change, 0.2 kg, bounds it below; above 0.3 kg the
   grid goes on in 0.1 kg steps).
3. False alarms: --minutes of motion without a change (UR5, friction, 0.2 N m, 1 kHz; one
   10 s-period motion, fresh noise each minute) and
   the bundled bags (their own robots and configs, default payload settings, the arm
   identified first from the bag itself by the config's pipeline and passed as the arm);
   the monitor's cost per sample against the pipeline's, in the same run.
4. Information floor: per arm, rate and torque noise of the matrix, for each payload of its
   sequences the Cramer-Rao bound of the fit over the payload's hold (from its change to the
   next, or 5 s): the smallest stddev of mass (percent) and centre of mass (mm, largest axis)
   that any unbiased fit of its 10 parameters can reach with white torque noise, the motion
   known exactly and the arm exact. Where it nears 5 mm or 2 %, no detector meets the
   targets in every draw.
5. --recording: the real Kinova Gen3 runs of ../shared/data (bench/recordings.py) with the
   URDF as the arm (`identify BAG --payload`, defaults): the payload fitted over each run,
   with its stddev, and the gravity torque it explains: per joint the least-squares scale of
   g_URDF+payload(q) on g_URDF(q), against that of the measured torque on g_URDF(q).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from checkout import ROOT  # noqa: E402  (this checkout's package, here and in subprocesses)

import numpy as np

sys.path.insert(0, str(ROOT / 'test'))

import payload_scenarios as ps  # noqa: E402
from identification_node.replay.stream import identify_bag  # noqa: E402
from identification_node.payload.fit import (ArmPrior, PayloadChange, attachment,  # noqa
                                             payload_regressor)
from identification_node.payload.monitor import PayloadMonitor, monitor_from_settings  # noqa
from identification_node.settings import Settings, read_parameter_file  # noqa: E402
from test_payload_matrix import SEQUENCES  # noqa: E402

REFERENCE_MASS = 1.0   # kg: the reference payload (detected within 0.5 s)
CASES = ((0.05, True), (0.2, True), (0.1, False))   # torque noise N m, joint friction
MATRIX_SEED = 10   # the sequences' motions and noise: seeds 10-13 (--seed: other draws)
BAGS = (('mit_paper_moves', 'identification.yaml'), ('mit_exciting', 'identification.yaml'),
        ('mit_paper_moves_sqlite3', 'identification.yaml'),
        ('crs_a465_fourier', 'crs_a465.yaml'))


def run_sequence(arm, model, rate, noise, changes, seed):
    """``model``: the arm identified (payload_scenarios.identify_arm) or parameters taken as
    exact. (detection delays or None per change, mass errors %, com errors mm, their z-scores
    (error over the segment's reported stddev: mass, largest CoM axis), false alarms, the
    largest CoM stddev (mm) of each payload segment, the com errors (mm) of the axes the fit
    reports (excited: stddev within payload.tolerance.com), the CoM axes it withholds, the
    mass errors % and CoM errors mm of the payloads of REFERENCE_MASS and more, and the
    detection delays of the changes of REFERENCE_MASS and more)."""
    _, events, segments = ps.run(arm, model, rate, noise, seed, changes)
    detected = [ps.seconds(e.detected) for e in events if e.kind == 'change']
    delays, used, heavy_delay, before = [], set(), [], 0.0
    for c in changes:
        hit = [k for k, d in enumerate(detected) if c.time <= d <= c.time + 2.0
               and k not in used]
        delays.append(detected[hit[0]] - c.time if hit else None)
        used.update(hit[:1])
        if hit and abs(c.mass - before) >= REFERENCE_MASS:
            heavy_delay.append(delays[-1])
        before = c.mass
    mass, com, z, com_sd, reported, withheld = [], [], [], [], [], 0
    heavy_mass, heavy_com = [], []
    if len(segments) == len(changes) + 1:
        for seg, c in zip(segments[1:], changes):
            p = seg.payload
            mass.append(100 * abs(p.mass - c.mass) / c.mass if c.mass else 0.0)
            z.append(abs(p.mass - c.mass) / p.stddev['mass'])
            if c.mass:
                com.append(1e3 * np.abs(p.com - c.com).max())
                if c.mass >= REFERENCE_MASS:
                    heavy_mass.append(mass[-1])
                    heavy_com.append(com[-1])
                sd = np.array([p.stddev[f'com.{a}'] for a in 'xyz'])
                z.append(float(np.max(np.abs(p.com - c.com) / sd)))
                com_sd.append(1e3 * float(sd.max()))
                shown = np.array([f'com.{a}' in p.excited for a in 'xyz'])
                withheld += int(np.count_nonzero(~shown))
                reported += [1e3 * float(e) for e in np.abs(p.com - c.com)[shown]]
    return (delays, mass, com, z, len(detected) - len(used), com_sd, reported, withheld,
            heavy_mass, heavy_com, heavy_delay)


def parse_case(text: str) -> tuple[float, bool]:
    """'0.2:yes' as (torque noise N m, joint friction)."""
    noise, _, friction = text.partition(':')
    if friction not in ('yes', 'no'):
        raise argparse.ArgumentTypeError(f'{text!r}: NOISE:yes or NOISE:no')
    return float(noise), friction == 'yes'


def matrix(arms, rates, cases=CASES, seed: int = MATRIX_SEED) -> None:
    print('1. matrix (shipped defaults; arm identified first): per cell all four sequences'
          f'{"" if seed == MATRIX_SEED else f" (seeds {seed}-{seed + 3})"}')
    print(f"{'arm':>8} {'rate':>5} {'noise':>5} {'fric':>4} {'detected':>9} "
          f"{'max delay s':>11} {'mass err %':>10} {'com err mm':>10} {'max z':>6} "
          f"{'false':>5} {'com sd mm':>9} {'reported com err mm':>19} {'withheld':>8} "
          f"{'1 kg+ mass %':>12} {'1 kg+ com mm':>12} {'1 kg+ delay s':>13}")
    for name in arms:
        for rate in rates:
            for noise, friction in cases:
                arm = ps.make_arm(name, friction)
                model = ps.identify_arm(arm, rate, noise)
                n = found = false = 0
                delays, mass, com, zs, sds, shown, held = [], [], [], [], [], [], 0
                heavy_mass, heavy_com, heavy_delay = [], [], []
                for k, changes in enumerate(SEQUENCES.values()):
                    d, m, c, z, f, sd, r, w, hm, hc, hd = run_sequence(
                        arm, model, rate, noise, changes, seed + k)
                    heavy_mass += hm
                    heavy_delay += hd
                    heavy_com += hc
                    n += len(d)
                    found += sum(x is not None for x in d)
                    delays += [x for x in d if x is not None]
                    mass += m
                    com += c
                    zs += z
                    false += f
                    sds += sd
                    shown += r
                    held += w
                print(f'{name:>8} {rate:5.0f} {noise:5.2f} {"yes" if friction else "no":>4} '
                      f'{found:>4}/{n:<4} {max(delays, default=np.nan):11.3f} '
                      f'{max(mass, default=np.nan):10.2f} {max(com, default=np.nan):10.2f} '
                      f'{max(zs, default=np.nan):6.2f} {false:>5} '
                      f'{max(sds, default=np.nan):9.2f} {max(shown, default=np.nan):19.2f} '
                      f'{held:>8} {max(heavy_mass, default=np.nan):12.2f} '
                      f'{max(heavy_com, default=np.nan):12.2f} '
                      f'{max(heavy_delay, default=np.nan):13.3f}', flush=True)


def information_floor(arms, rates, cases=CASES, seed: int = MATRIX_SEED) -> None:
    """Part 4: per arm, rate and noise, each payload's Cramer-Rao stddev of mass (percent)
    and CoM (mm, largest axis) over its hold, on the matrix's motions (the same seeds)."""
    noises = sorted({noise for noise, _ in cases})
    print('\n4. information floor (Cramer-Rao; white torque noise, the motion and the arm '
          'exact): per payload of the sequences in order, stddev of mass % / CoM mm (largest '
          'axis) over its hold')
    for name in arms:
        arm = ps.make_arm(name, False)
        attach = attachment(arm.robot)
        for rate in rates:
            floors = []   # (mass kg, mass stddev % at unit noise, CoM stddev mm at unit noise)
            for k, changes in enumerate(SEQUENCES.values()):
                end = changes[-1].time + 5.0
                sim = ps.simulate(arm, rate, end, 0.0, seed + k, changes)
                Y = payload_regressor(attach, arm.robot.regressor(sim.q, sim.qd, sim.qdd))
                for c, until in zip(changes, [x.time for x in changes[1:]] + [end]):
                    if c.mass <= 0:
                        continue
                    A = Y[(sim.t >= c.time) & (sim.t < until)].reshape(-1, 10)
                    cov = np.linalg.inv(A.T @ A)
                    grad = np.zeros((3, 10))   # of the CoM h / m over (m, h)
                    grad[:, 0] = -np.asarray(c.com) / c.mass
                    grad[:, 1:4] = np.eye(3) / c.mass
                    com = np.sqrt(np.diag(grad @ cov @ grad.T)).max()
                    floors.append((c.mass, 100 * np.sqrt(cov[0, 0]) / c.mass, 1e3 * com))
            for noise in noises:
                print(f'{name:>8} {rate:5.0f} {noise:5.2f}  ' + '  '.join(
                    f'{m:g} kg {noise * sm:.2f}/{noise * sc:.2f}' for m, sm, sc in floors),
                    flush=True)


def threshold(rates) -> None:
    print('\n2. detection threshold (UR5, friction, 0.1 N m; pick at 4 s, CoM (0.02, 0, 0.05) m;'
          ' smallest mass of the grid detected within 2 s in 3 of 3 seeds, as are all above)')
    arm = ps.make_arm('ur5', True)
    grid = (0.3, 0.25, 0.2, 0.15, 0.1, 0.05)
    for rate in rates:
        model = ps.identify_arm(arm, rate, 0.1)
        smallest, delay, tried = None, np.nan, []

        def detected(mass: float) -> tuple[int, float]:
            delays = [run_sequence(arm, model, rate, 0.1,
                                   [PayloadChange(4.0, None, mass, (0.02, 0.0, 0.05))],
                                   20 + s)[0][0] for s in range(3)]
            hits = [d for d in delays if d is not None]
            tried.append(f'{mass:g} kg {len(hits)}/3')
            return len(hits), max(hits, default=np.nan)

        for mass in grid:
            hits, worst = detected(mass)
            if hits < 3:
                break
            smallest, delay = mass, worst
        mass = grid[0]
        while smallest is None and mass < 1.0:      # not even the grid's largest: go up
            mass = round(mass + 0.1, 3)
            hits, worst = detected(mass)
            if hits == 3:
                smallest, delay = mass, worst
        print(f'   {rate:6.0f} Hz: {smallest if smallest is not None else "> 1"} kg '
              f'(max delay {delay:.3f} s; {", ".join(tried)})', flush=True)


def simulated_false_alarms(minutes: float) -> None:
    print(f'\n3a. false alarms: {minutes:g} min of motion without a change (UR5, friction, '
          '0.2 N m, 1 kHz)')
    arm = ps.make_arm('ur5', True)
    mon = ps.monitor(arm, ps.identify_arm(arm, 1000.0, 0.2))
    pipe = arm.settings.build(arm.robot)
    pipe_time = mon_time = 0.0
    declared, samples = 0, 0
    chunk = 60.0
    for k in range(int(np.ceil(minutes * 60 / chunk))):
        # one motion throughout (its 10 s period divides the chunk), fresh noise per chunk:
        # chunks of different motions had joined with jumps of q
        sim = ps.simulate(arm, 1000.0, chunk, 0.2, 100 + k, motion_seed=100)
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


def bag_false_alarms() -> None:
    print('\n3b. false alarms over the bundled bags (their configs, default payload settings; '
          'arm: the URDF, then the arm identified from the bag itself)')
    print(f"   {'bag':<24} {'arm':<10} {'changes':>7} {'segment 0 mass kg':>18} warnings")
    for bag, config in BAGS:
        settings = Settings.from_dict(read_parameter_file(ROOT / 'config' / config))
        robot = settings.load_robot()
        identified = identify_bag(ROOT / 'bags' / bag, settings, robot).pipeline
        for label in ('urdf', 'identified'):
            mon = monitor_from_settings(settings, robot)
            if label == 'identified':   # as --arm with its estimate.yaml: with its covariance
                mon = PayloadMonitor(robot, mon.attach, identified.standard_parameters(),
                                     mon.config, arm_prior=ArmPrior.from_covariance(
                                         identified.base, identified.covariance))
            events = []
            identify_bag(ROOT / 'bags' / bag, settings, robot,
                         on_output=lambda out: events.extend(mon.add_output(out)))
            segments = mon.finish()
            p = segments[0].payload if segments else None
            first = ('-' if p is None else
                     f"{p.mass:+.3f} +- {p.stddev['mass']:.3f}")
            print(f"   {bag:<24} {label:<10} {sum(e.kind == 'change' for e in events):>7} "
                  f"{first:>18} {'; '.join(mon.warnings()) or '-'}", flush=True)


def recording() -> None:
    import json
    import tempfile

    sys.path.insert(0, str(ROOT / 'bench'))
    from corpus import run_identify
    from recordings import data_dir, kinova_bags, kinova_columns
    from identification_node.payload.fit import attachment, with_payload

    print('\n5. Kinova Gen3 recordings (../shared/data/kinova_gen3), the URDF as the arm: '
          'identify BAG --payload')
    root = data_dir() / 'kinova_gen3'
    with tempfile.TemporaryDirectory() as out:
        for bag, csv in zip(kinova_bags(Path(out)), ('opti_traj_testing1', 'opti_traj_testing2')):
            code, doc = run_identify([str(bag), '--payload'])
            note = ''
            if code:    # refused (the time-offset check): again without it
                config = Path(out) / 'no_offset_check.yaml'
                config.write_text('identification_node:\n  ros__parameters:\n'
                                  '    time_offset:\n      warn: 0.0\n')
                code, doc = run_identify([str(bag), '--payload', '--config', str(config)])
                note = ' (refused with the defaults; time_offset.warn 0)'
            [segment] = doc['payload_changes']
            f = segment['payload']['fitted']
            print(f'   {csv}{note}: exit {code}; mass {f["mass"]:.3f} +- '
                  f'{f["stddev"]["mass"]:.3f} kg,'
                  f' CoM ' + ', '.join(f'{c:+.3f} +- {sd:.3f}' for c, sd in zip(
                      f['com'], f['stddev']['com'])) + ' m; excited: '
                  f"{segment['payload']['excited'] or 'none'}; warnings: "
                  f"{json.dumps(doc['payload_warnings'])}")
            settings = Settings.from_dict({'robot': str(root / 'gen3_7dof.urdf')})
            robot = settings.load_robot()
            _, q, _, tau = kinova_columns(root / f'{csv}.csv')
            phi_payload = np.zeros(10)
            phi_payload[0] = f['mass']
            phi_payload[1:4] = f['mass'] * np.asarray(f['com'])
            # the point mass at the fitted CoM (the inertia about it is not determined)
            phi = with_payload(robot, attachment(robot, segment['payload']['link']),
                               robot.phi_model, phi_payload)
            zero = np.zeros_like(q)
            g0 = robot.inverse_dynamics(q, zero, zero, robot.phi_model)
            g1 = robot.inverse_dynamics(q, zero, zero, phi)

            def scale(a, b):
                return (a * b).sum(0) / (b * b).sum(0)
            print('      joint:                    ' + ' '.join(f'{j:>6}' for j in range(2, 7)))
            for label, ratio in (('measured / g_URDF', scale(tau, g0)),
                                 ('g_URDF+payload / g_URDF', scale(g1, g0)),
                                 ('measured / g_URDF+payload', scale(tau, g1))):
                print(f'      {label:<26}' + ' '.join(f'{r:6.2f}' for r in ratio[1:6]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--arms', nargs='+', default=['ur5', 'panda', 'kinova', 'fixture'])
    parser.add_argument('--rates', nargs='+', type=float, default=[250, 500, 1000, 2000])
    parser.add_argument('--cases', nargs='+', type=parse_case, default=list(CASES),
                        metavar='NOISE:FRICTION', help='e.g. 0.2:yes 0.1:no')
    parser.add_argument('--seed', type=int, default=MATRIX_SEED,
                        help="the matrix's first seed (one per sequence: motion and noise)")
    parser.add_argument('--minutes', type=float, default=30.0, help='0: skip the simulated run')
    parser.add_argument('--skip-matrix', action='store_true')
    parser.add_argument('--skip-threshold', action='store_true')
    parser.add_argument('--skip-bags', action='store_true')
    parser.add_argument('--skip-floor', action='store_true')
    parser.add_argument('--recording', action='store_true',
                        help='5.: the Kinova Gen3 recordings of ../shared/data')
    args = parser.parse_args()
    if not args.skip_matrix:
        matrix(args.arms, args.rates, args.cases, args.seed)
    if not args.skip_threshold:
        threshold(args.rates)
    if args.minutes > 0:
        simulated_false_alarms(args.minutes)
    if not args.skip_bags:
        bag_false_alarms()
    if not args.skip_floor:
        information_floor(args.arms, args.rates, args.cases, args.seed)
    if args.recording:
        recording()
    return 0


if __name__ == '__main__':
    sys.exit(main())
