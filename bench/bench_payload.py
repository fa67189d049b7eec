"""Payload change detection: delay versus payload mass, and false alarms.

    .venv/bin/python bench/bench_payload.py [--minutes 30] [--seeds 3]

1. Delay: the 7-DOF Panda-like arm (test/fixtures/panda_like.urdf) at 1 kHz, torque noise
   0.05 N m and a 20-bit encoder, under computed-torque control of a Fourier trajectory,
   picks a payload (mass m, centre of mass at a random offset up to 0.1 m) at 3 s and places
   it at 6 s; the node's pipeline and PayloadMonitor (shipped defaults) stream the samples.
   Per mass: detections of the pick and the place, and their delays (detection stamp minus
   the true change time; the smoother's 10 ms included).
2. False alarms: the same arm without any change for --minutes of simulated time (perfect
   tracking of the trajectory, same noise), and the bundled bags; changes declared.
3. Cost: the monitor's time per sample against the pipeline's, in the same run.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from identification_node.excitation.trajectories import load_trajectory  # noqa: E402
from identification_node.model.robot import load_robot  # noqa: E402
from identification_node.model.simulation import (ArmSimulator, SensorNoise,  # noqa: E402
                                                  simulate_kinematic)
from identification_node.offline.identification import identify_bag  # noqa: E402
from identification_node.payload.fit import PayloadChange, attachment  # noqa: E402
from identification_node.payload.fit import true_parameter_changes  # noqa: E402
from identification_node.payload.monitor import PayloadMonitor  # noqa: E402
from identification_node.payload.monitor import monitor_from_settings  # noqa: E402
from identification_node.pipeline import IdentificationPipeline  # noqa: E402
from identification_node.settings import Settings, read_parameter_file  # noqa: E402
from identification_node.wire.records import JointStateRecord  # noqa: E402

URDF = str(ROOT / 'test/fixtures/panda_like.urdf')
NOISE = SensorNoise(torque_std=0.05, encoder_counts=2 ** 20)
MASSES = (0.1, 0.15, 0.2, 0.25, 0.5, 1.0, 2.0, 3.0)
PICK, PLACE = 3.0, 6.0
BAGS = (('mit_paper_moves', 'identification.yaml'), ('mit_exciting', 'identification.yaml'),
        ('mit_paper_moves_sqlite3', 'identification.yaml'),
        ('crs_a465_fourier', 'crs_a465.yaml'))


class Runner:
    """The pipeline and monitor over samples, timing each."""

    def __init__(self, robot):
        self.robot = robot
        self.pipe = IdentificationPipeline(robot)
        self.mon = PayloadMonitor(robot, attachment(robot), robot.phi_model)
        self.events: list = []
        self.pipe_time = self.mon_time = 0.0
        self.samples = 0

    def feed(self, t: np.ndarray, q: np.ndarray, tau: np.ndarray) -> None:
        ns = np.round(t * 1e9).astype(np.int64)
        names = tuple(self.robot.joint_names)
        for a in range(0, len(ns), 1000):
            s = slice(a, a + 1000)
            t0 = time.perf_counter()
            self.pipe.add_joint_states(JointStateRecord(ns[s], names, q[s],
                                                        np.zeros((len(ns[s]), 0)), tau[s]))
            out = self.pipe.process()
            t1 = time.perf_counter()
            self.events += self.mon.add(out.stamps_ns, out.q, out.qd, out.qdd, out.measured)
            self.mon_time += time.perf_counter() - t1
            self.pipe_time += t1 - t0
            self.samples += len(out.stamps_ns)

    def changes(self) -> list:
        return [e for e in self.events if e.kind == 'change']


def delays(robot, seeds: int) -> None:
    print('1. detection delay (pick at 3 s, place at 6 s; shipped defaults)')
    print(f"{'mass kg':>8} {'picks':>6} {'places':>7} {'pick delay ms (median, max)':>29} "
          f"{'place delay ms':>15} {'others':>7}")
    traj = load_trajectory('fourier', robot)
    phi = robot.phi_model
    for mass in MASSES:
        found, d_pick, d_place, others = [0, 0], [], [], 0
        for seed in range(seeds):
            rng = np.random.default_rng(100 + seed)
            com = rng.uniform(-0.1, 0.1, 3) * [0.5, 0.5, 1.0]
            events = [PayloadChange(PICK, None, mass, tuple(com)),
                      PayloadChange(PLACE, None, 0.0)]
            sim = ArmSimulator(robot, phi).run(traj, 8.0, NOISE, seed,
                                               changes=true_parameter_changes(robot, phi, events))
            run = Runner(robot)
            run.feed(sim.t, sim.q_meas, sim.tau_meas)
            seen = [False, False]
            for e in run.changes():
                k = 0 if PICK <= e.detected < PLACE else 1 if e.detected >= PLACE else None
                if k is None or seen[k]:
                    others += 1
                    continue
                seen[k] = True
                found[k] += 1
                (d_pick if k == 0 else d_place).append(e.detected - (PICK, PLACE)[k])
        print(f'{mass:8.2f} {found[0]:>3}/{seeds:<2} {found[1]:>4}/{seeds:<2} '
              f'{_ms(d_pick):>29} {_ms(d_place):>15} {others:>7}')


def _ms(values: list) -> str:
    if not values:
        return '-'
    v = 1e3 * np.array(values)
    return f'{np.median(v):.0f}, {v.max():.0f}'


def false_alarms(robot, minutes: float) -> None:
    print(f'\n2. false alarms: {minutes:g} min of simulated motion without a change, '
          'and the bundled bags')
    traj = load_trajectory('fourier', robot)
    run = Runner(robot)
    chunk = 10.0
    start = time.perf_counter()
    for k in range(int(np.ceil(minutes * 60 / chunk))):
        t = k * chunk + np.arange(int(chunk * 1000)) / 1000.0
        sim = simulate_kinematic(robot, None, traj, t, NOISE, seed=k)
        run.feed(sim.t, sim.q_meas, sim.tau_meas)
    hours = run.samples / 1000.0 / 3600.0
    print(f'   simulated run: {len(run.changes())} changes declared over {run.samples} samples '
          f'({hours * 60:.1f} min; {time.perf_counter() - start:.0f} s to run)')
    if run.changes():
        print('   at ' + ', '.join(f'{e.detected:.3f} s' for e in run.changes()))
    print(f'   cost per sample: pipeline {1e6 * run.pipe_time / run.samples:.1f} us, payload '
          f'monitor {1e6 * run.mon_time / run.samples:.1f} us '
          f'(ratio {run.mon_time / run.pipe_time:.2f})')
    for bag, config in BAGS:
        settings = Settings.from_dict(read_parameter_file(ROOT / 'config' / config))
        bot = settings.load_robot()
        mon = monitor_from_settings(settings, bot)
        events = []
        identify_bag(ROOT / 'bags' / bag, settings, bot, on_output=lambda out: events.extend(
            mon.add(out.stamps_ns, out.q, out.qd, out.qdd, out.measured)))
        n = sum(e.kind == 'change' for e in events)
        print(f'   bag {bag}: {n} changes declared')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--minutes', type=float, default=30.0)
    parser.add_argument('--seeds', type=int, default=3)
    args = parser.parse_args()
    robot = load_robot(URDF)
    delays(robot, args.seeds)
    false_alarms(robot, args.minutes)
    return 0


if __name__ == '__main__':
    sys.exit(main())
