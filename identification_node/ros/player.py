"""Live replay of a rosbag2 bag over ROS 2 (in place of ``ros2 bag play``).

Messages are published as the raw CDR bytes stored in the bag (``Publisher.publish(bytes)``
goes to ``rcl_publish_serialized_message``): no deserialization. Timing follows the bag's
log times divided by the rate, scheduled against ``time.monotonic``; messages due within
``BATCH`` of each other go out back to back. Publisher QoS follows the QoS the recorded
publishers offered (rosbag2's rule): transient local (latched, e.g. /robot_description) only
if every recorded offer was, best effort only if every offer was, else reliable volatile.
Optionally publishes /clock (rosgraph_msgs/Clock) carrying the bag's log time, so nodes with
``use_sim_time`` follow the bag.
"""
from __future__ import annotations

import importlib
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosDurability, QosReliability

from identification_node.bags.reader import BagReader, open_bag
from identification_node.errors import IdentificationError
from identification_node.ros.conversions import wait_for_all_acked
from identification_node.wire.cdr import CLOCK

DEFAULT_CLOCK_HZ = 40.0
BATCH = 2e-4  # [s] messages due this close to now are published without sleeping
VOLATILE_DEPTH = 1000  # deep enough for a batch of a fast topic on a slow reader
_MAX_SLEEP = 0.05  # [s] so stop() and signals act promptly

__all__ = ['BagPlayer', 'PlayStats', 'DEFAULT_CLOCK_HZ', 'message_class', 'offered_qos',
           'playback_qos', 'select_topics']


def message_class(msgtype: str) -> type:
    """The rclpy message class of ``pkg/msg/Type`` (IdentificationError if not importable)."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        parts.insert(1, 'msg')
    if len(parts) != 3 or not all(parts):
        raise IdentificationError(f'invalid message type name {msgtype!r}')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.{parts[1]}'), parts[2])
    except (ImportError, AttributeError):
        raise IdentificationError(
            f'message type {msgtype} is not available to rclpy here (package '
            f'{parts[0]} not installed?)') from None


def offered_qos(reader: BagReader) -> dict[str, list[Qos]]:
    """{topic: QoS profiles the recorded publishers offered} from the bag metadata."""
    # BagReader has no public accessor for the connections' rosbag2 extension.
    out: dict[str, list[Qos]] = {}
    for conn in getattr(reader, '_connections', ()):
        ext = getattr(conn, 'ext', None)
        out.setdefault(conn.topic, []).extend(getattr(ext, 'offered_qos_profiles', None) or [])
    return out


def playback_qos(offers: Iterable[Qos]) -> QoSProfile:
    """Publisher QoS for recorded offers: latched (transient local, depth = the deepest
    offer, at least 1) only if all were, best effort only if all were; default reliable."""
    offers = list(offers)
    latched = bool(offers) and all(
        q.durability == QosDurability.TRANSIENT_LOCAL for q in offers)
    best_effort = bool(offers) and all(
        q.reliability == QosReliability.BEST_EFFORT for q in offers)
    depth = max([1] + [int(q.depth) for q in offers]) if latched else VOLATILE_DEPTH
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _absolute(topic: str) -> str:
    return topic if topic.startswith('/') else '/' + topic


def select_topics(reader: BagReader, topics: Iterable[str] | None = None,
                  clock: bool = False, warn: Callable[[str], None] | None = None
                  ) -> list[str]:
    """Bag topics to play: the requested ones present in the bag (all if None), minus the
    bag's /clock when the player publishes its own. IdentificationError if none is left;
    requested topics absent from the bag are only warned about."""
    warn = warn or (lambda _text: None)
    if topics is None:
        chosen = sorted(reader.topics)
    else:
        wanted = list(dict.fromkeys(_absolute(t) for t in topics))
        missing = [t for t in wanted if t not in reader.topics]
        chosen = [t for t in wanted if t in reader.topics]
        if missing and chosen:
            warn(f'not in the bag, not played: {", ".join(missing)}')
        if not chosen:
            have = ', '.join(sorted(reader.topics)) or 'none'
            raise IdentificationError(
                f'bag {str(reader.path)!r} has none of the topics {", ".join(wanted)} '
                f'(it has: {have})')
    if clock:
        dropped = [t for t in chosen if t == '/clock' and reader.topics[t] == CLOCK]
        if dropped:
            warn("the bag's own /clock is not played (--clock publishes the bag time)")
            chosen = [t for t in chosen if t not in dropped]
    if not chosen:
        raise IdentificationError(f'bag {str(reader.path)!r} has no topic to play')
    return chosen


@dataclass
class PlayStats:
    """What one play() did; times in seconds (wall: first to last publish, bag: log time
    span of the published messages, summed over loops)."""

    published: int = 0
    per_topic: dict[str, int] = field(default_factory=dict)
    wall_time: float = 0.0
    bag_time: float = 0.0
    loops: int = 0
    clock_published: int = 0
    interrupted: bool = False

    @property
    def achieved_rate(self) -> float:
        """Bag time played per wall second (nan when undefined)."""
        return self.bag_time / self.wall_time if self.wall_time > 0 else math.nan

    @property
    def message_rate(self) -> float:
        """Messages per wall second (nan when undefined)."""
        return self.published / self.wall_time if self.wall_time > 0 else math.nan

    def summary(self) -> str:
        """One line for the end of a play."""
        n = len(self.per_topic)
        text = (f'published {self.published} messages on {n} topic{"s" * (n != 1)} in '
                f'{self.wall_time:.3f} s (bag {self.bag_time:.3f} s; achieved rate '
                f'{self.achieved_rate:.3f}x, {self.message_rate:.1f} msg/s')
        if self.loops > 1:
            text += f', {self.loops} loops'
        if self.clock_published:
            text += f', {self.clock_published} /clock'
        return text + (')' + (' [interrupted]' if self.interrupted else ''))


class BagPlayer:
    """Publish a bag's messages on ``node`` with their recorded timing divided by ``rate``.

    ``bag`` is a path or an open BagReader (then owned by the player); ``topics`` None plays
    all; ``clock`` False, True (DEFAULT_CLOCK_HZ) or a rate [Hz] for /clock. Publishers are
    created at construction and live until close(), so latched topics stay available to late
    subscribers after play() returns. stop() may be called from any thread or signal handler.
    """

    def __init__(self, node: Node, bag: str | Path | BagReader, rate: float = 1.0,
                 topics: Iterable[str] | None = None, loop: bool = False,
                 clock: bool | float = False) -> None:
        rate = float(rate)
        if not (math.isfinite(rate) and rate > 0):
            raise IdentificationError(f'rate must be a positive number, got {rate}')
        clock_hz = DEFAULT_CLOCK_HZ if clock is True else float(clock or 0.0)
        if not (math.isfinite(clock_hz) and clock_hz >= 0):
            raise IdentificationError(f'clock rate must be a positive number, got {clock}')
        self.node, self.rate, self.loop, self.clock_hz = node, rate, bool(loop), clock_hz
        self._stop = threading.Event()
        self.reader = bag if isinstance(bag, BagReader) else open_bag(bag)
        try:
            log = node.get_logger()
            self.topics = select_topics(self.reader, topics, clock_hz > 0, log.warning)
            self.qos: dict[str, QoSProfile] = {}
            self._pubs: dict[str, Any] = {}
            offers = offered_qos(self.reader)
            for topic in list(self.topics):
                msgtype = self.reader.topics[topic]
                try:
                    cls = message_class(msgtype)
                except IdentificationError as err:
                    log.warning(f'topic {topic} not played: {err}')
                    continue
                self.qos[topic] = playback_qos(offers.get(topic, ()))
                self._pubs[topic] = node.create_publisher(cls, topic, self.qos[topic])
            self.topics = [t for t in self.topics if t in self._pubs]
            if not self.topics:
                raise IdentificationError(
                    f'bag {str(self.reader.path)!r}: no topic with a message type known here')
            self._clock_pub = None
            if clock_hz > 0:
                self._clock_cls = message_class(CLOCK)
                self._clock_pub = node.create_publisher(
                    self._clock_cls, '/clock',
                    QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        except BaseException:
            self.close()
            raise

    @property
    def latched_topics(self) -> list[str]:
        """Topics published transient local."""
        return [t for t, q in self.qos.items() if q.durability == DurabilityPolicy.TRANSIENT_LOCAL]

    def wait_for_subscribers(self, timeout: float) -> list[str]:
        """Wait until every volatile topic (latched ones reach late subscribers anyway) has
        a matched subscriber, at most ``timeout`` s; return the topics still without one."""
        deadline = time.monotonic() + timeout
        volatile = [(t, p) for t, p in self._pubs.items() if t not in self.latched_topics]
        while True:
            lonely = [t for t, p in volatile if p.get_subscription_count() == 0]
            if not lonely or self._stop.is_set() or time.monotonic() >= deadline:
                return lonely
            time.sleep(0.01)

    def stop(self) -> None:
        """Ask play() to return after the message being published (thread/signal safe)."""
        self._stop.set()

    def _publish_clock(self, t_ns: int) -> None:
        msg = self._clock_cls()
        msg.clock.sec, msg.clock.nanosec = divmod(int(t_ns), 1_000_000_000)
        assert self._clock_pub is not None   # called only when publishing a clock
        self._clock_pub.publish(msg)

    def play(self) -> PlayStats:
        """Publish the selected topics (once, or until stop() with loop); blocks."""
        stats = PlayStats(per_topic=dict.fromkeys(self.topics, 0))
        start_ns, end_ns = self.reader.start_ns, self.reader.end_ns
        scale = 1e-9 / self.rate  # wall seconds per bag nanosecond
        clock_period = 1.0 / self.clock_hz if self._clock_pub is not None else math.inf
        pubs, monotonic, sleep = self._pubs, time.monotonic, time.sleep
        first = last = None
        while not self._stop.is_set():
            t0 = monotonic()
            next_clock = math.inf
            if self._clock_pub is not None:  # a loop starts and ends on the bag's own times
                self._publish_clock(start_ns)
                stats.clock_published += 1
                next_clock = t0 + clock_period
            lo = hi = None
            for topic, _, t_ns, raw in self.reader.raw_messages(self.topics):
                due = t0 + (t_ns - start_ns) * scale
                while True:
                    now = monotonic()
                    if now >= next_clock:
                        bag_now = start_ns + min((now - t0) / scale, end_ns - start_ns)
                        self._publish_clock(int(bag_now))
                        stats.clock_published += 1
                        next_clock += clock_period
                        if next_clock <= now:  # fell behind: skip, do not burst
                            next_clock = now + clock_period
                    if due - now <= BATCH or self._stop.is_set():
                        break
                    sleep(min(due - now, next_clock - now, _MAX_SLEEP))
                if self._stop.is_set():
                    break
                pubs[topic].publish(raw if type(raw) is bytes else bytes(raw))
                last = monotonic()
                first = first if first is not None else last
                lo = t_ns if lo is None else lo
                hi = t_ns
                stats.per_topic[topic] += 1
                stats.published += 1
            if lo is not None and hi is not None:   # set together
                stats.bag_time += (hi - lo) * 1e-9
            if self._clock_pub is not None and not self._stop.is_set():
                self._publish_clock(end_ns)
                stats.clock_published += 1
            stats.loops += 1
            if not self.loop:
                break
        stats.interrupted = self._stop.is_set()
        if first is not None and last is not None:   # set together
            stats.wall_time = last - first
        return stats

    def wait_for_acks(self, timeout: float = 5.0) -> bool:
        """Wait until reliable subscribers acknowledged everything published (before the
        process exits, so the tail of the bag is not lost)."""
        return wait_for_all_acked(self._pubs.values(), timeout)

    def close(self) -> None:
        """Destroy the publishers and close the bag (idempotent)."""
        for pub in list(getattr(self, '_pubs', {}).values()):
            self.node.destroy_publisher(pub)
        self._pubs = {}
        clock_pub, self._clock_pub = getattr(self, '_clock_pub', None), None
        if clock_pub is not None:
            self.node.destroy_publisher(clock_pub)
        self.reader.close()

    def __enter__(self) -> BagPlayer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
