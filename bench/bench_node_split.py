"""Where the node's CPU goes at 1 kHz, and what a Python node costs with no identification.

Runs the identification node in a child process on the 7-DOF arm of bench_node.py (same
publisher, ~/predicted_effort subscribed by a listener process so it is published), and
measures the thread CPU time of the three parts of each processing run: taking and decoding
the queued messages (``poll``), the pipeline (``pipeline``), and serializing and publishing
the efforts (``publish``), plus the whole process's CPU. ``node`` runs identify as the node
does with its defaults (``--node-param`` overrides them); ``passthrough`` runs replace the
pipeline by one that hands the received samples straight back as output: the
same messages in and out at the same schedule, none of the identification, i.e. the floor of
the ROS side. ``relay`` is the textbook rclpy node instead of ours: a raw subscription
callback that republishes each message's bytes on ~/predicted_effort (EventsExecutor; no
parameters, services or timers): what any rclpy node costs that passes these messages on.
Runs of the kinds alternate (this machine's CPU readings drift between runs); the medians are
printed last, then each mode's CPU over the relay's (medians, and per alternating pair).

    .venv/bin/python bench/bench_node_split.py [--rate 1000] [--seconds 6] [--repeat 3]
        [--modes node passthrough relay] [--node-param process_period:=0.01] [--no-listener]
        [--switch-interval S]

The interpreter's switch interval is the node's (node.main sets it) in every mode;
``--switch-interval S`` sets another. ``--no-listener``: no listener process, so nothing
subscribes to the outputs (the node then processes every ``idle_process_period``; the relay
still publishes, to nobody).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_node import PANDA, REPO  # noqa: E402  (also sets a private ROS domain)

PARTS = ('poll', 'pipeline', 'publish')
LISTENER_ENV = 'BENCH_SPLIT_LISTENER'   # '0': no listener process (set by --no-listener)
SWITCH_ENV = 'BENCH_SPLIT_SWITCH'       # the interpreter's switch interval, s (--switch-interval)
MODES = ('node', 'passthrough', 'relay')


def listen(seconds: float) -> None:
    """Subscribe to ~/predicted_effort for ``seconds`` (raw, nothing done with it)."""
    import rclpy
    from sensor_msgs.msg import JointState
    rclpy.init()
    node = rclpy.create_node('bench_split_listener')
    node.create_subscription(JointState, '/identification_node/predicted_effort',
                             lambda raw: None, 1000, raw=True)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    rclpy.shutdown()


def run_node(mode: str, rate: float, seconds: float, warmup: float,
             overrides: list[str]) -> dict:
    """The node in this process with timed parts; returns per-part CPU (s), runs, messages.
    ``overrides``: node parameters as NAME:=VALUE (VALUE in YAML)."""
    import numpy as np
    import rclpy
    import yaml
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from identification_node.pipeline import IdentificationPipeline, PipelineOutput
    from identification_node.pipeline.samples import stack_records
    from identification_node.ros import conversions, effort_outputs, node as node_module

    spent = dict.fromkeys(PARTS, 0.0)
    calls = dict.fromkeys(PARTS, 0)

    def timed(part: str, func, counted: bool = True):
        def wrapper(*args, **kwargs):
            start = time.thread_time()
            try:
                return func(*args, **kwargs)
            finally:
                spent[part] += time.thread_time() - start
                calls[part] += counted
        return wrapper

    def passthrough(self: IdentificationPipeline, flush: bool = False) -> PipelineOutput:
        blocks = list(stack_records(self.samples.joint_states.take()))
        if not blocks:
            return PipelineOutput.empty(self.robot.dof)
        stamps = np.concatenate([b.stamp_ns for b in blocks])
        q = np.vstack([b.position for b in blocks])
        self.samples.counters.received += len(stamps)
        return PipelineOutput(stamps, q, q, q, q, q)

    process = passthrough if mode == 'passthrough' else IdentificationPipeline.process
    IdentificationPipeline.process = timed('pipeline', process)
    # the estimator's update, after the run's publishing: the pipeline's part of the same run
    IdentificationPipeline.update = timed('pipeline', IdentificationPipeline.update, False)
    conversions.PolledSubscription.poll = timed('poll', conversions.PolledSubscription.poll)
    outputs = effort_outputs.EffortOutputs
    outputs.publish = timed('publish', outputs.publish)
    node_class = node_module.IdentificationNode

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    sys.setswitchinterval(float(os.environ.get(SWITCH_ENV) or node_module.SWITCH_INTERVAL))
    if mode == 'relay':
        return run_relay(rate, seconds, warmup)
    node_params = [Parameter(name, value=yaml.safe_load(value))
                   for name, value in (o.split(':=', 1) for o in overrides)]
    node = node_class(parameter_overrides=[Parameter('robot', value=str(PANDA)),
                                           Parameter('torque_source', value=['measured']),
                                           *node_params])

    def reset() -> None:
        spent.update(dict.fromkeys(PARTS, 0.0))
        calls.update(dict.fromkeys(PARTS, 0))
    result = drive(node, lambda: node.pipeline.received, rate, seconds, warmup, reset)
    print(json.dumps({**result, 'runs': calls['pipeline'], **spent}), flush=True)
    os._exit(0)   # no teardown to wait for


def run_relay(rate: float, seconds: float, warmup: float) -> None:
    """The ``relay`` mode of run_node (rclpy initialised)."""
    import rclpy
    from sensor_msgs.msg import JointState

    from identification_node.ros.effort_outputs import OUTPUT_QOS
    from identification_node.ros.node import INPUT_QOS

    node = rclpy.create_node('identification_node')
    pub = node.create_publisher(JointState, '~/predicted_effort', OUTPUT_QOS)
    received = [0]

    def relay(raw: bytes) -> None:
        received[0] += 1
        pub.publish(raw)
    node.create_subscription(JointState, 'joint_states', relay, INPUT_QOS, raw=True)
    result = drive(node, lambda: received[0], rate, seconds, warmup, polled=False)
    print(json.dumps({**result, 'runs': 0, **dict.fromkeys(PARTS, 0.0)}), flush=True)
    os._exit(0)


def drive(node, received, rate: float, seconds: float, warmup: float,
          reset=lambda: None, polled: bool = True) -> dict:
    """Spin ``node`` with the listener and the publisher (other processes) running; after
    ``warmup`` s of messages, ``reset()`` and measure: the process CPU (s), the wall time and
    the messages ``received()`` over ``seconds`` - 1 s."""
    from rclpy.task import Future

    from identification_node.ros.spin import make_executor

    executor = make_executor(polled)
    executor.add_node(node)
    never = Future()
    total = seconds + warmup
    helpers = []
    if os.environ.get(LISTENER_ENV, '1') == '1':
        helpers.append(subprocess.Popen([sys.executable, __file__, '--listen', str(total + 4)],
                                        cwd=REPO))
        time.sleep(1.0)
    helpers.append(subprocess.Popen(
        [sys.executable, str(REPO / 'bench' / 'bench_node.py'), '--publish', str(rate),
         str(seconds), str(warmup)], cwd=REPO, stdout=subprocess.DEVNULL))
    end = time.monotonic() + 30
    while received() < rate * warmup and time.monotonic() < end:
        executor.spin_until_future_complete(never, timeout_sec=0.05)
    if not received():
        sys.exit('bench_node_split: the node received nothing from the publisher')
    reset()
    received0 = received()
    cpu0, t0 = time.process_time(), time.monotonic()
    while time.monotonic() - t0 < seconds - 1.0:
        executor.spin_until_future_complete(never, timeout_sec=0.05)
    result = {'cpu': time.process_time() - cpu0, 'wall': time.monotonic() - t0,
              'messages': received() - received0}
    for helper in helpers:
        helper.kill()
    return result


def measure(mode: str, args: argparse.Namespace) -> dict:
    out = subprocess.run([sys.executable, __file__, '--run', mode, str(args.rate),
                          str(args.seconds), str(args.warmup), *args.node_param], cwd=REPO,
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, check=True,
                         env={**os.environ, LISTENER_ENV: '0' if args.no_listener else '1',
                              SWITCH_ENV: str(args.switch_interval or '')})
    return json.loads(out.stdout.strip().splitlines()[-1])


def cpu_share(r: dict) -> float:
    """The process's CPU over the measured wall time (cores)."""
    return r['cpu'] / r['wall']


def line(mode: str, r: dict, label: str = '') -> str:
    runs, wall = max(r['runs'], 1), r['wall']
    label = '  ' + label if label else ''
    node = (f'{mode:11s}: node {100 * cpu_share(r):5.1f} % of a core '
            f'({1e6 * r["cpu"] / max(r["messages"], 1):5.1f} us/msg)')
    if not r['runs']:   # relay: a callback per message, no processing runs
        return node + label
    parts = '  '.join(f'{p} {1e6 * r[p] / runs:4.0f} us' for p in PARTS)
    return (f'{node}; per processing run ({r["messages"] / runs:.1f} msgs): {parts}; parts '
            f'{100 * sum(r[p] for p in PARTS) / wall:4.1f} % of a core{label}')


def main() -> None:
    if sys.argv[1:2] == ['--listen']:
        listen(float(sys.argv[2]))
        return
    if sys.argv[1:2] == ['--run']:
        run_node(sys.argv[2], *map(float, sys.argv[3:6]), sys.argv[6:])
        return
    import numpy as np
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rate', type=float, default=1000.0)
    parser.add_argument('--seconds', type=float, default=6.0)
    parser.add_argument('--warmup', type=float, default=2.0)
    parser.add_argument('--repeat', type=int, default=3, help='runs of each kind, alternating')
    parser.add_argument('--modes', nargs='+', default=list(MODES), choices=MODES)
    parser.add_argument('--no-listener', action='store_true',
                        help='nothing subscribes to ~/predicted_effort (the node then runs at '
                        'its idle_process_period)')
    parser.add_argument('--switch-interval', type=float, metavar='S',
                        help="the interpreter's switch interval (default: the node's, "
                        'node.SWITCH_INTERVAL; node and relay alike)')
    parser.add_argument('--node-param', action='append', default=[], metavar='NAME:=VALUE',
                        help='node parameter override (node and passthrough modes)')
    args = parser.parse_args()
    print(f'7-DOF arm at {args.rate:.0f} Hz, {args.seconds:.0f} s per run; {os.cpu_count()} '
          f'cores; thread CPU per processing run{"".join(" " + p for p in args.node_param)}'
          + ('; no listener' if args.no_listener else ''))
    results: dict[str, list] = {mode: [] for mode in args.modes}
    for _ in range(args.repeat):
        for mode, runs in results.items():
            runs.append(measure(mode, args))
            print(line(mode, runs[-1]), flush=True)
    for mode, runs in results.items():
        med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        print(line(mode, med, f'median of {args.repeat}'))
    if 'relay' in results:
        base = [cpu_share(r) for r in results['relay']]
        for mode, runs in results.items():
            if mode != 'relay':
                ratio = np.median([cpu_share(r) for r in runs]) / np.median(base)
                pairs = ', '.join(f'{cpu_share(r) / b:.2f}' for r, b in zip(runs, base))
                print(f'{mode} / relay CPU: {ratio:.2f}x (medians; alternating pairs {pairs})')


if __name__ == '__main__':
    main()
