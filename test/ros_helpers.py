"""Helpers for tests over real DDS: a private ROS context, nodes spun in a thread, the simulated
arm as a subprocess, message collectors, service and parameter calls.

Every test module takes a ROS_DOMAIN_ID of its own, claimed by a file naming its pid for as
long as it runs, so that other modules and a second suite on the same machine do not hear it;
subprocesses get it through the environment.
"""
from __future__ import annotations

import atexit
import os
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import zlib
from pathlib import Path
from typing import Any, Callable, Mapping

import rclpy
import yaml
from rclpy.exceptions import InvalidHandle
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

ROOT = Path(__file__).resolve().parents[1]
PYTHON = str(ROOT / '.venv' / 'bin' / 'python') if (ROOT / '.venv').is_dir() else sys.executable
RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5000,
                      reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


DOMAIN_LOCKS = Path(tempfile.gettempdir()) / 'identification_node_test_domains'
_CLAIMED: set[int] = set()


def _claim(path: Path) -> bool:
    """Create ``path`` holding this process's pid; a file of a process that ended is taken
    over. A file, not a lock held on a descriptor: a run of the suite found its flock
    released while the descriptor stayed open (some library unlocked a reused fd number)."""
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
        except FileExistsError:
            try:
                owner = int(path.read_text() or 0)
                os.kill(owner, 0)          # raises if that process ended
                return False
            except (ProcessLookupError, ValueError, FileNotFoundError):
                path.unlink(missing_ok=True)    # its owner ended: take it over
                continue
            except PermissionError:             # alive, another user's
                return False
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        return True
    return False


def domain_id(module: str, first: int | None = None) -> int:
    """A ROS domain (1..100, FastDDS' safe range) for one test module, claimed for this
    process until ``release_domain`` (or its exit) by a file naming its pid, so that suites
    run side by side never share one. The search starts at ``first`` (default: a hash of the
    pid and ``module``)."""
    DOMAIN_LOCKS.mkdir(mode=0o777, exist_ok=True)
    start = (first - 1 if first is not None
             else os.getpid() * 7 + zlib.crc32(module.encode()))
    for k in range(100):
        domain = 1 + (start + k) % 100
        if domain not in _CLAIMED and _claim(DOMAIN_LOCKS / f'{domain}.pid'):
            _CLAIMED.add(domain)
            return domain
    raise RuntimeError(f'no free ROS domain: all of 1..100 are claimed in {DOMAIN_LOCKS}')


def release_domain(domain: int) -> None:
    """Give back a domain claimed by ``domain_id`` (nothing if it was not)."""
    if domain in _CLAIMED:
        _CLAIMED.discard(domain)
        (DOMAIN_LOCKS / f'{domain}.pid').unlink(missing_ok=True)


@atexit.register
def _release_all() -> None:
    for domain in list(_CLAIMED):
        release_domain(domain)


def wait_for(predicate: Callable[[], Any], timeout: float, period: float = 0.02) -> Any:
    """Poll until ``predicate()`` is truthy (returned) or ``timeout`` s pass (None)."""
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() > end:
            return value
        time.sleep(period)


class RosHarness:
    """A private rclpy context in ``domain``; every node added gets its own
    SingleThreadedExecutor spinning in a thread (as the node's main spins it)."""

    def __init__(self, domain: int):
        self.domain = domain
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self._spinners: dict = {}
        self._clients: dict = {}
        self.errors: list[str] = []
        self.procs: list[subprocess.Popen] = []
        self.client = self.add(Node('test_client', context=self.context))

    def add(self, node: Node) -> Node:
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(node)
        stop = threading.Event()
        thread = threading.Thread(target=self._spin, args=(executor, node.get_name(), stop),
                                  daemon=True)
        thread.start()
        self._spinners[node] = (executor, thread, stop)
        return node

    def _spin(self, executor, name: str, stop: threading.Event) -> None:
        """Spin until ``stop``. A callback's exception is kept for ``check`` (rclpy's spin()
        would end the thread, and every later call to the node would go unanswered), and an
        entity destroyed from the test thread while the executor had it selected is not one:
        rclpy raises InvalidHandle for that race (ros2/rclpy#1355) and the next wait no
        longer has the entity."""
        never = Future()    # slices of many events: about half the cost of spin_once each
        while not stop.is_set() and self.context.ok():
            try:
                executor.spin_until_future_complete(never, timeout_sec=0.1)
            except InvalidHandle:
                continue
            except Exception as exc:
                if stop.is_set() or not self.context.ok():
                    return      # shut down while spinning
                if len(self.errors) < 20:
                    self.errors.append(f'{name}: {type(exc).__name__}: {exc}')

    def check(self) -> None:
        """Fail naming the exceptions raised in the spinning nodes' callbacks, if any."""
        assert not self.errors, 'exceptions in callbacks: ' + '; '.join(self.errors)

    def spinner_state(self, node: Node) -> str:
        """Whether ``node``'s spinning thread lives, and where it is (for a failure message)."""
        thread = self._spinners[node][1]
        frame = sys._current_frames().get(thread.ident)
        if frame is None:
            return f'the thread spinning {node.get_name()} ended'
        where = ' <- '.join(f'{Path(f.filename).name}:{f.lineno} {f.name}'
                            for f in reversed(traceback.extract_stack(frame)[-6:]))
        return f'the thread spinning {node.get_name()} is at {where}'

    def remove(self, node: Node) -> None:
        executor, thread, stop = self._spinners.pop(node)
        stop.set()
        executor.shutdown()
        thread.join(5)
        node.destroy_node()

    def env(self) -> dict:
        return dict(os.environ, ROS_DOMAIN_ID=str(self.domain), PYTHONUNBUFFERED='1')

    def start(self, verb: str, params: Mapping[str, Any], tmp: Path, name: str,
              extra: tuple = ()) -> subprocess.Popen:
        """``python -m identification_node VERB --ros-args --params-file F`` with ``params``
        written to F for node ``name``; stdout and stderr are piped."""
        path = Path(tmp) / f'{name}_params.yaml'
        path.write_text(yaml.safe_dump({'/**': {'ros__parameters': dict(params)}}))
        proc = subprocess.Popen(
            [PYTHON, '-m', 'identification_node', verb, '--ros-args', '--params-file',
             str(path), *extra], cwd=ROOT, env=self.env(), stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True)
        self.procs.append(proc)
        return proc

    def shutdown(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        for node in list(self._spinners):
            self.remove(node)
        rclpy.try_shutdown(context=self.context)
        release_domain(self.domain)

    # -- calls ------------------------------------------------------------------------------------
    def call(self, srv_type, name: str, request, timeout: float = 10.0):
        """Call service ``name`` from the client node; the response, or AssertionError. Clients
        are kept: a new client's first request can go before the server matched its reply
        reader, and the reply is lost."""
        client = self._clients.get(name)
        if client is None:
            client = self._clients[name] = self.client.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=timeout), f'no service {name}'
        future = client.call_async(request)
        done = wait_for(future.done, timeout)
        self.check()
        assert done, f'service {name} did not answer; {self.spinner_state(self.client)}'
        return future.result()

    def get_parameters(self, target: str, names: list[str]) -> dict:
        from rcl_interfaces.srv import GetParameters
        res = self.call(GetParameters, f'{target}/get_parameters', GetParameters.Request(
            names=names))
        return {n: parameter_value_to_python(v) for n, v in zip(names, res.values)}

    def set_parameters(self, target: str, params: list) -> list:
        """SetParameters with rclpy Parameters; the SetParametersResult list."""
        from rcl_interfaces.srv import SetParameters
        res = self.call(SetParameters, f'{target}/set_parameters', SetParameters.Request(
            parameters=[p.to_parameter_msg() for p in params]))
        return list(res.results)


class Collector:
    """Messages of one topic, thread-safe."""

    def __init__(self, harness: RosHarness, msg_type, topic: str, qos: QoSProfile = RELIABLE,
                 node: Node | None = None):
        self.messages: list = []
        self._lock = threading.Lock()
        self.node = node or harness.client
        self.sub = self.node.create_subscription(msg_type, topic, self._cb, qos)

    def _cb(self, msg) -> None:
        with self._lock:
            self.messages.append(msg)

    def __len__(self) -> int:
        return len(self.messages)

    def snapshot(self) -> list:
        with self._lock:
            return list(self.messages)

    def close(self) -> None:
        self.node.destroy_subscription(self.sub)


def diagnostic_values(status) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def joint_state_msgs(stamps_ns, names, position=None, velocity=None, effort=None) -> list:
    """One new JointState per row of the given (N, n) arrays, stamped with ``stamps_ns``."""
    from sensor_msgs.msg import JointState
    out = []
    for k, ns in enumerate(list(stamps_ns)):
        msg = JointState(name=list(names))
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(ns), 10 ** 9)
        for field, a in (('position', position), ('velocity', velocity), ('effort', effort)):
            if a is not None:
                setattr(msg, field, [float(v) for v in a[k]])
        out.append(msg)
    return out
