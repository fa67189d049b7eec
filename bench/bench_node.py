"""Node throughput: samples lost, CPU per message and latency, over real DDS between processes.

The identification node runs in its own process on a 7-DOF Panda-like arm
(test/fixtures/panda_like.urdf) with measured torque; a publisher process sends JointState at a
fixed rate, stamped with the wall clock at publication; this process subscribes to
~/predicted_effort and measures the latency from the sample's stamp to its arrival. CPU per
message is the node process's user + system time over the run divided by the messages it
received. Prints one line per run, the median over ``--repeat`` runs per rate, and the highest
rate with no sample lost in any run.

The node runs with the shipped defaults: the automatic smoother holds the first 5 s of motion
back for its choice, and the node then catches up (``--node-param smoother.half_window:=10``
pins a window instead). The p99 latency after the warm-up is compared with its budget, the
smoother's delay + 20 ms; "caught up" is the end of the last second of samples (from the
first output's stamp, over the whole run) whose median latency exceeded that budget.

``--listen-measured`` also subscribes to ~/measured_effort (the node publishes an effort
topic only while it has subscribers). ``--currents``: every joint's torque from 3-phase motor
currents instead (CURRENTS below): the publisher sends each sample's motor_currents message
(``<joint>/ia|ib|ic``, amperes; no electrical angle, the node derives it from the position)
with the joint state's stamp, right after it, so the node receives twice the messages.

    .venv/bin/python bench/bench_node.py [--rates 1000 5000 ...] [--seconds 6] [--warmup 15]
        [--repeat 3] [--node-param NAME:=VALUE]
"""
from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PANDA = REPO / 'test' / 'fixtures' / 'panda_like.urdf'

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

os.environ.setdefault('ROS_DOMAIN_ID', str(30 + os.getpid() % 60))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
# single-threaded BLAS, as the package's programs set it (programs.py), for the node that
# bench_node_split runs in its own process: idle OpenBLAS threads spin on the cores
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
# --currents: the node's torque source and motor constants (every joint alike)
CURRENTS = {'source': 'three_phase', 'kt': 0.5, 'gear_ratio': 50.0, 'pole_pairs': 7}


def publisher(rate: float, seconds: float, warmup: float, currents: bool) -> None:
    """Publish joint states (and with ``currents`` the motor currents of the same sample) at
    ``rate`` for ``warmup + seconds``; print the count of samples published after the
    warm-up."""
    import numpy as np
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from identification_node.model.robot import load_robot
    from identification_node.simulation.simulator import SensorNoise, simulate_kinematic
    from identification_node.model.torque import TorqueConverter
    from identification_node.excitation.trajectories import FourierTrajectory

    robot = load_robot(str(PANDA))
    n = int(rate * (seconds + warmup))
    period = min(n, int(rate * 10))    # one 10 s period, repeated
    sim = simulate_kinematic(robot, None, FourierTrajectory.random(robot, seed=1),
                             np.arange(period) / rate, SensorNoise(torque_std=0.2))
    rows = [(sim.q_meas[k].tolist(), sim.qd_meas[k].tolist(), sim.tau_meas[k].tolist())
            for k in range(period)]
    if currents:
        converter = TorqueConverter(robot.joint_names, [CURRENTS] * robot.dof)
        amps = converter.currents_from_torque(sim.tau_meas, sim.q_meas).reshape(period, -1)
        channels = converter.current_channel_names()   # joint-major ia, ib, ic: amps' order
    rclpy.init(args=[])   # not the script's own arguments (--node-param NAME:=V)
    node = rclpy.create_node('bench_publisher')
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
    pub = node.create_publisher(JointState, 'joint_states', qos)
    pub_cur = node.create_publisher(JointState, 'motor_currents', qos) if currents else None
    cur = JointState(name=channels) if currents else None
    deadline = time.monotonic() + 20
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    msg = JointState(name=list(robot.joint_names))
    start = time.monotonic()
    counted = 0
    for k in range(n):
        due = start + k / rate
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        q, qd, tau = rows[k % period]
        ns = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        msg.position, msg.velocity, msg.effort = q, qd, tau
        pub.publish(msg)
        if currents:
            cur.header.stamp = msg.header.stamp
            cur.effort = amps[k % period].tolist()
            pub_cur.publish(cur)
        counted += k >= rate * warmup
    print(counted, flush=True)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.shutdown()


STAMP = struct.Struct('<iI')   # header.stamp (sec, nanosec) after the 4-byte CDR header
NODE_ARGS: list[str] = []   # extra '-p name:=value' for the node (--node-param)


def budget_ms() -> float:
    """The latency budget of ~/predicted_effort beyond the smoother's delay (ms): the
    node's default latency_budget, issue 32's 20 ms."""
    from identification_node.config import default
    return 1e3 * default('latency_budget')


def cpu_seconds(pid: int) -> float:
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def run_rate(rate: float, seconds: float, warmup: float, listen_measured: bool,
             currents: bool) -> dict:
    import numpy as np
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.task import Future
    from sensor_msgs.msg import JointState

    from identification_node.ros.spin import make_executor

    torque = {'torque_source' if k == 'source' else k: f'[{v}]' for k, v in CURRENTS.items()
              } if currents else {'torque_source': '[measured]'}
    node_proc = subprocess.Popen(
        [sys.executable, '-m', 'identification_node', 'node', '--ros-args',
         '-p', f'robot:={PANDA}', *[a for k, v in torque.items() for a in ('-p', f'{k}:={v}')],
         '-p', 'publish.diagnostics_rate:=4.0', *NODE_ARGS],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    latencies: list[int] = []
    stamps: list[int] = []
    diag: dict[str, str] = {}
    rclpy.init(args=[])
    node = rclpy.create_node('bench_listener')

    def on_effort(raw: bytes) -> None:   # the header stamp straight from the CDR bytes
        sec, nanosec = STAMP.unpack_from(raw, 4)
        stamps.append(sec * 1_000_000_000 + nanosec)
        latencies.append(time.time_ns() - stamps[-1])

    def on_diag(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.endswith(': identification'):
                diag.update({kv.key: kv.value for kv in status.values})
    node.create_subscription(JointState, '/identification_node/predicted_effort', on_effort,
                             1000, raw=True)
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    if listen_measured:
        node.create_subscription(JointState, '/identification_node/measured_effort',
                                 lambda raw: None, 1000, raw=True)
    executor = make_executor()   # a listener that keeps up at 8 kHz: it measures latency
    executor.add_node(node)
    never = Future()

    def spin(seconds: float) -> None:
        executor.spin_until_future_complete(never, timeout_sec=seconds)

    end = time.monotonic() + 30
    while not diag and time.monotonic() < end:   # the node is up and publishing
        spin(0.1)
    pub = subprocess.Popen([sys.executable, __file__, '--publish', str(rate), str(seconds),
                            str(warmup), str(int(currents))], cwd=REPO,
                           stdout=subprocess.PIPE, text=True)
    cpu0 = None
    received0 = 0
    t_start = time.monotonic()
    while pub.poll() is None:
        spin(0.01)
        if cpu0 is None and time.monotonic() - t_start > warmup + 1.0:
            cpu0, received0, lat0 = cpu_seconds(node_proc.pid), int(
                diag.get('samples_received', 0)), len(latencies)
    published = int(pub.stdout.read().strip() or 0)
    cpu1 = cpu_seconds(node_proc.pid)
    period = float(diag.get('processing_period_s', 'nan'))   # at the stream's end
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        spin(0.05)
    received = int(diag.get('samples_received', 0))
    rejected = int(diag.get('samples_rejected', 0))
    node_proc.terminate()
    node_proc.communicate(timeout=20)
    node.destroy_node()
    rclpy.shutdown()
    lat = np.array(latencies[lat0:]) * 1e-6
    steady = received - received0
    delay = float(diag.get('smoother_delay_ms', 'nan'))
    # the end (s after the first output's stamp) of the last second of samples whose median
    # latency exceeded the budget: the start-up's catch-up (not the latency's tail)
    second = (np.array(stamps) - stamps[0]) // 1_000_000_000 if stamps else np.zeros(0)
    every = np.array(latencies) * 1e-6
    limit = delay + budget_ms()
    late = [k for k in np.unique(second) if np.median(every[second == k]) > limit]
    caught_up = float(late[-1] + 1) if late else 0.0
    return {
        'rate': rate, 'published': published, 'received': received,
        'lost': max(0, int(rate * (seconds + warmup)) - received - rejected),
        'cpu_us_per_msg': 1e6 * (cpu1 - cpu0) / max(steady, 1),
        'cpu_percent': 100 * (cpu1 - cpu0) / (steady / rate) if steady else float('nan'),
        'latency_ms_median': float(np.median(lat)) if len(lat) else float('nan'),
        'latency_ms_p99': float(np.percentile(lat, 99)) if len(lat) else float('nan'),
        'delay_ms': delay, 'caught_up_s': caught_up, 'period_ms': 1e3 * period,
    }


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == '--publish':
        publisher(*map(float, sys.argv[2:5]), currents=sys.argv[5:6] == ['1'])
        return
    import numpy as np
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rates', type=float, nargs='+', default=[1000, 2000, 5000, 8000])
    parser.add_argument('--seconds', type=float, default=6.0)
    parser.add_argument('--warmup', type=float, default=15.0,
                        help='s before the measured ones (the automatic smoother is chosen '
                        'on the first 5 s of motion, the time offset checked on 10 s)')
    parser.add_argument('--node-param', action='append', default=[], metavar='NAME:=VALUE',
                        help='node parameter override, e.g. process_period:=0.005')
    parser.add_argument('--repeat', type=int, default=1, help='runs per rate (median shown)')
    parser.add_argument('--listen-measured', action='store_true',
                        help='also subscribe to ~/measured_effort')
    parser.add_argument('--currents', action='store_true',
                        help='torque from 3-phase motor currents (a second input stream)')
    args = parser.parse_args()
    for p in args.node_param:
        NODE_ARGS.extend(['-p', p])
    print(f'7-DOF arm, {args.seconds:.0f} s per run after {args.warmup:.0f} s warm-up; '
          f'{os.cpu_count()} cores{"".join(" " + p for p in NODE_ARGS)}'
          f'{"; ~/measured_effort subscribed too" if args.listen_measured else ""}'
          f'{"; torque from 3-phase motor currents" if args.currents else ""}')
    best = 0.0
    for rate in args.rates:
        runs = []
        for _ in range(args.repeat):
            runs.append(run_rate(rate, args.seconds, args.warmup, args.listen_measured,
                                 args.currents))
            print(line(rate, runs[-1], args), flush=True)
        if args.repeat > 1:
            med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
            med['lost'] = max(r['lost'] for r in runs)
            print(line(rate, med, args, f'median of {args.repeat}'), flush=True)
        best = rate if all(r['lost'] == 0 for r in runs) and rate > best else best
    print(f'highest rate with no sample lost: {best:.0f} Hz')


def line(rate: float, r: dict, args: argparse.Namespace, label: str = '') -> str:
    budget = budget_ms()
    return (f"{rate:6.0f} Hz: lost {int(r['lost']):5d} of "
            f"{int(rate * (args.seconds + args.warmup))}  node CPU {r['cpu_us_per_msg']:6.1f} "
            f"us/msg ({r['cpu_percent']:5.1f} % of a core)  latency median "
            f"{r['latency_ms_median']:6.2f} ms  p99 {r['latency_ms_p99']:6.2f} ms  (smoother "
            f"delay {r['delay_ms']:.1f} ms; p99 "
            f"{'within' if r['latency_ms_p99'] <= r['delay_ms'] + budget else 'beyond'} "
            f"delay + {budget:g} ms; caught up {r['caught_up_s']:.0f} s after the first "
            f"output's stamp; processing period {r['period_ms']:.1f} ms)"
            f"{'  ' + label if label else ''}")


if __name__ == '__main__':
    main()
