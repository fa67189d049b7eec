"""Record ROS 2 topics into a rosbag2 bag (in place of ``ros2 bag record``).

Subscriptions are raw (the wire CDR bytes are written as they arrive, no deserialization);
each topic's type comes from the ROS graph and its QoS from the publishers present when the
topic is first seen: best effort if any publisher is best effort (a reliable reader would not
match it), transient local if every publisher is (so latched data sent before the recorder
started is recorded, and the topic is marked latched in the bag). The log time of a message
is the node clock at reception [ns]. The bag is written through BagWriter, so it appears at
``out`` only when close() finishes it; abort() leaves nothing.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Iterable

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

from identification_node.bags.writer import BagWriter
from identification_node.errors import IdentificationError
from identification_node.ros.player import message_class

DEPTH = 1000  # reader queue: 1 s at 1 kHz while the callback is late
DISCOVERY_PERIOD = 0.25  # [s] between graph look-ups for topics not seen yet

__all__ = ['BagRecorder', 'subscription_qos']


def subscription_qos(publisher_qos: Iterable[QoSProfile]) -> tuple[QoSProfile, bool]:
    """(reader QoS, latched) matching every given publisher QoS (see the module doc)."""
    offers = list(publisher_qos)
    best_effort = any(q.reliability == ReliabilityPolicy.BEST_EFFORT for q in offers)
    latched = bool(offers) and all(
        q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offers)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=DEPTH,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    ), latched


class BagRecorder:
    """Record ``topics`` (resolved against the node namespace and remappings) to ``out``.

    discover() subscribes to the topics that have appeared in the graph with a publisher;
    spin() runs an executor until a duration passes or stop() is called, discovering late
    topics on the way; close() finishes the bag, abort() discards it. Attributes: types
    {topic: msgtype} of the topics subscribed, counts {topic: messages written}, latched.
    """

    def __init__(self, node: Node, out: str | Path, topics: Iterable[str],
                 storage: str = 'mcap', *, overwrite: bool = False) -> None:
        self.node = node
        self.requested: list[str] = []
        for topic in topics:
            try:
                name = node.resolve_topic_name(topic)
            except Exception as err:  # rclpy's InvalidTopicNameException and the like
                raise IdentificationError(f'invalid topic name {topic!r}: {err}') from None
            if name not in self.requested:
                self.requested.append(name)
        if not self.requested:
            raise IdentificationError('no topic to record')
        self.writer = BagWriter(out, storage, overwrite=overwrite)
        self.types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.latched: set[str] = set()
        self.skipped: dict[str, str] = {}  # topic -> why it is not recorded
        self._subs: dict[str, Any] = {}
        self._stopping = False
        self.started_ns = self.stopped_ns = 0

    @property
    def path(self) -> Path:
        return self.writer.path

    @property
    def missing(self) -> list[str]:
        """Requested topics neither recorded nor refused yet."""
        return [t for t in self.requested if t not in self.types and t not in self.skipped]

    def _warn(self, text: str) -> None:
        self.node.get_logger().warning(text)

    def discover(self) -> list[str]:
        """Subscribe to the missing topics that now have a publisher; return them."""
        missing = self.missing
        if not missing:
            return []
        graph = dict(self.node.get_topic_names_and_types())
        added = []
        for topic in missing:
            types = graph.get(topic)
            if not types:
                continue
            if len(types) > 1:
                self.skipped[topic] = f'several types on the topic: {", ".join(types)}'
                self._warn(f'not recording {topic}: {self.skipped[topic]}')
                continue
            infos = self.node.get_publishers_info_by_topic(topic)
            if not infos:  # only subscribers so far: the QoS to match is not known yet
                continue
            try:
                self._subscribe(topic, types[0], [i.qos_profile for i in infos])
            except IdentificationError as err:
                self.skipped[topic] = str(err)
                self._warn(f'not recording {topic}: {err}')
                continue
            added.append(topic)
        return added

    def _subscribe(self, topic: str, msgtype: str, offers: list[QoSProfile]) -> None:
        cls = message_class(msgtype)
        qos, latched = subscription_qos(offers)
        self.writer.add_topic(topic, msgtype, latched=latched)
        self.types[topic] = msgtype
        self.counts[topic] = 0
        if latched:
            self.latched.add(topic)
        self._subs[topic] = self.node.create_subscription(
            cls, topic, self._callback(topic), qos, raw=True)
        kind = ('best effort' if qos.reliability == ReliabilityPolicy.BEST_EFFORT
                else 'reliable') + (', transient local' if latched else '')
        self.node.get_logger().info(f'recording {topic} [{msgtype}] ({kind})')

    def _callback(self, topic: str) -> Callable[[bytes], None]:
        write, clock, counts = self.writer.write_raw, self.node.get_clock(), self.counts

        def on_message(raw: bytes) -> None:
            write(topic, clock.now().nanoseconds, raw)
            counts[topic] += 1
        return on_message

    def stop(self) -> None:
        """Make spin() return (thread and signal-handler safe)."""
        self._stopping = True

    def spin(self, executor: Any, duration: float | None = None,
             discovery_timeout: float = 10.0, drain: float = 0.1) -> None:
        """Record until ``duration`` s passed or stop(); the node must be in ``executor``.

        IdentificationError (nothing written yet, the caller aborts) if none of the topics
        appeared within ``discovery_timeout`` s. After stopping, messages already received
        are handled for ``drain`` s more.
        """
        start = time.monotonic()
        self.started_ns = time.time_ns()
        end = start + duration if duration is not None else float('inf')
        never = Future()
        next_discovery = start
        while not self._stopping:
            now = time.monotonic()
            if now >= end:
                break
            if self.missing and now >= next_discovery:
                self.discover()
                next_discovery = now + DISCOVERY_PERIOD
                if not self.types and now - start >= discovery_timeout:
                    raise IdentificationError(
                        f'none of the topics {", ".join(self.requested)} has a publisher '
                        f'after {discovery_timeout:g} s')
            executor.spin_until_future_complete(never, timeout_sec=min(0.1, end - now))
        executor.spin_until_future_complete(never, timeout_sec=drain)
        self.stopped_ns = time.time_ns()

    def _unsubscribe(self) -> None:
        for sub in self._subs.values():
            self.node.destroy_subscription(sub)
        self._subs = {}

    def close(self) -> None:
        """Stop listening and finish the bag (it appears at ``path``)."""
        self._unsubscribe()
        self.writer.close()

    def abort(self) -> None:
        """Stop listening and discard the bag."""
        self._unsubscribe()
        self.writer.abort()

    def summary(self) -> str:
        """Multi-line report: total, then one line per requested topic."""
        total = sum(self.counts.values())
        secs = max(self.stopped_ns - self.started_ns, 0) * 1e-9
        lines = [f'recorded {total} messages on {len(self.types)} topics in {secs:.3f} s '
                 f'to {self.path}']
        for topic in self.requested:
            if topic in self.types:
                lines.append(f'  {topic} [{self.types[topic]}]: {self.counts[topic]}'
                             + (' (latched)' if topic in self.latched else ''))
            else:
                lines.append(f'  {topic}: not recorded '
                             f'({self.skipped.get(topic, "no publisher seen")})')
        return '\n'.join(lines)

    def __enter__(self) -> BagRecorder:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
