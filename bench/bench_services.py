"""The node's services under concurrent calls while it identifies a 1 kHz stream (issue 31).

The node runs in its own process on a 7-DOF Panda-like arm (test/fixtures/panda_like.urdf) with
the shipped defaults (payload identification on), the simulated arm streams 1 kHz with torque
noise, and this process sends each burst at once from one client: 200 ``~/get_estimate``, 20
``~/save``, 100 ``~/freeze`` toggles, 30 (``~/save``, ``~/reset``) pairs and 50
``~/payload/reset``. Printed per burst: the calls answered (and of those refused), whether
each service answered in the order called, and the time until the last answer. The
baseline, measured in the same run: the same 200 ``get_estimate`` calls to a bare rclpy
Trigger server in a process of its own that answers a message of the node's size at once
(what the middleware alone costs).

    .venv/bin/python bench/bench_services.py [--repeat 3] [--timeout 60]
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PANDA = REPO / 'test' / 'fixtures' / 'panda_like.urdf'

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

os.environ.setdefault('ROS_DOMAIN_ID', str(30 + os.getpid() % 60))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
NAME = 'bench_services'
BARE = 'bare_services'


def serve_bare(size: int) -> None:
    """A Trigger server ``/bare_services/get_estimate`` answering ``size`` bytes at once."""
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_srvs.srv import Trigger

    rclpy.init()
    node = rclpy.create_node(BARE)
    text = 'x' * size

    def answer(request, response):
        response.success, response.message = True, text
        return response
    node.create_service(Trigger, f'/{BARE}/get_estimate', answer, qos_profile=QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass


class Caller:
    """A client node spun in a thread, with one client per service (kept: a new client's
    first replies can be lost to discovery)."""

    def __init__(self):
        import threading

        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        rclpy.init()
        self.node = rclpy.create_node('bench_services_caller')
        self.qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                              reliability=ReliabilityPolicy.RELIABLE)
        self.clients: dict = {}
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def client(self, srv_type, name: str):
        if name not in self.clients:
            self.clients[name] = self.node.create_client(srv_type, name, qos_profile=self.qos)
            if not self.clients[name].wait_for_service(timeout_sec=60):
                raise SystemExit(f'{name}: no service within 60 s')
            time.sleep(2.0)   # discovery of the reply reader: no API tells when it is done
        return self.clients[name]

    def burst(self, calls: list, timeout: float) -> dict:
        """Send ``calls`` ((srv_type, name, request), ...) at once; per service name the
        indices in the order their answers arrived, and the time until the last one."""
        clients = {name: self.client(t, name) for t, name, _ in calls}
        arrived: dict[str, list] = {name: [] for name in clients}
        done = []
        start = time.monotonic()
        for k, (_, name, request) in enumerate(calls):
            def note(f, name=name, k=k):
                arrived[name].append((k, f.result()))
                done.append(time.monotonic())
            clients[name].call_async(request).add_done_callback(note)
        end = start + timeout
        while len(done) < len(calls) and time.monotonic() < end:
            time.sleep(0.005)
        return {'answered': len(done), 'calls': len(calls),
                'refused': sum(not r.success for a in arrived.values() for _, r in a),
                'in_order': all([k for k, _ in a] == sorted(k for k, _ in a)
                                for a in arrived.values()),
                'seconds': (max(done) - start) if done else float('nan'),
                'responses': arrived}

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown()


def estimate(caller: Caller, timeout: float = 30.0) -> dict:
    import json

    from std_srvs.srv import Trigger

    res = caller.burst([(Trigger, f'/{NAME}/get_estimate', Trigger.Request())], timeout)
    answers = res['responses'][f'/{NAME}/get_estimate']
    return json.loads(answers[0][1].message) if answers and answers[0][1].success else {}


def wait_until(predicate, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.2)
    return False


def bursts() -> dict:
    from std_srvs.srv import SetBool, Trigger

    def n(srv, name, count, make=None):
        return [(srv, f'/{NAME}/{name}', make(k) if make else srv.Request())
                for k in range(count)]
    return {
        '200 get_estimate': n(Trigger, 'get_estimate', 200),
        '20 save': n(Trigger, 'save', 20),
        '100 freeze toggles': n(SetBool, 'freeze', 100,     # the last one resumes
                                lambda k: SetBool.Request(data=k % 2 == 0)),
        '30 save/reset pairs': [c for k in range(30) for c in (
            (Trigger, f'/{NAME}/save', Trigger.Request()),
            (Trigger, f'/{NAME}/reset', Trigger.Request()))],
        '50 payload/reset': n(Trigger, 'payload/reset', 50),
    }


def run(timeout: float) -> dict:
    """One run: the node and the simulated arm started, the bursts, then the bare server's
    baseline with messages of the node's size. Returns {burst: result}."""
    from std_srvs.srv import Trigger

    tmp = Path(tempfile.mkdtemp(prefix='bench_services_'))
    python = sys.executable
    node = subprocess.Popen(
        [python, '-m', 'identification_node', 'node', '--ros-args', '-r', f'__node:={NAME}',
         '-r', 'joint_states:=/bench_arm/joint_states', '-p', f'robot:={PANDA}',
         '-p', 'torque_source:=[measured]', '-p', 'payload.enabled:=true',
         '-p', f'output_directory:={tmp / "out"}'],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sim = subprocess.Popen(
        [python, '-m', 'identification_node', 'sim', '--ros-args', '-r', '__ns:=/bench_arm',
         '-p', f'robot:={PANDA}', '-p', 'trajectory:=fourier', '-p', 'rate:=1000.0',
         '-p', 'duration:=600.0', '-p', 'noise.torque_std:=0.05'],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    caller = Caller()
    bare = None
    try:
        if not wait_until(lambda: (e := estimate(caller)).get('consistency_status', 'starting')
                          != 'starting' and e['num_samples'] > 1000, 180):
            raise SystemExit('the node gave no consistent estimate within 180 s')
        results = {name: caller.burst(calls, timeout)
                   for name, calls in bursts().items()}
        size = len(next(iter(results['200 get_estimate']['responses'].values()))[0][1].message)
        bare = subprocess.Popen([python, __file__, '--serve-bare', str(size)], cwd=REPO)
        results['baseline: 200 to a bare server'] = caller.burst(
            [(Trigger, f'/{BARE}/get_estimate', Trigger.Request()) for _ in range(200)],
            timeout)
        return results
    finally:
        caller.close()
        shutil.rmtree(tmp, ignore_errors=True)
        for proc in (bare, sim, node):
            if proc is not None:
                proc.terminate()
                try:
                    proc.wait(20)
                except subprocess.TimeoutExpired:
                    proc.kill()


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == '--serve-bare':
        serve_bare(int(sys.argv[2]))
        return
    import numpy as np
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=int, default=1, help='runs (median shown)')
    parser.add_argument('--timeout', type=float, default=60.0, help='s per burst')
    args = parser.parse_args()
    print(f'7-DOF arm at 1 kHz, shipped defaults; {os.cpu_count()} cores, load '
          f'{os.getloadavg()[0]:.1f}')
    runs = []
    for r in range(args.repeat):
        runs.append(run(args.timeout))
        for name, res in runs[-1].items():
            print(f'  run {r + 1}  {name:32s} answered {res["answered"]:4d} of '
                  f'{res["calls"]:4d} ({res["refused"]} refused)  in order: '
                  f'{str(res["in_order"]):5s}  last answer '
                  f'after {res["seconds"]:7.3f} s', flush=True)
    names = list(runs[0])
    median = {name: float(np.median([run[name]['seconds'] for run in runs]))
              for name in names}
    base = median[names[-1]]
    print(f'median of {args.repeat}:')
    for name in names:
        lost = sum(run[name]['calls'] - run[name]['answered'] for run in runs)
        print(f'  {name:32s} {median[name]:7.3f} s  ({median[name] / base:5.2f}x the bare '
              f'server)  unanswered in all runs: {lost}')


if __name__ == '__main__':
    main()
