"""Conversions between ROS messages and the core's plain arrays: stamps, JointState output, and
JointState input taken from a subscription's queue in batches; the acknowledgement wait of
publishers about to go."""
from __future__ import annotations

import collections
import math
import threading
import time
from functools import partial
from typing import Any, Callable, Iterable, Sequence, cast

import numpy as np
from builtin_interfaces.msg import Time
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.duration import Duration
from rclpy.event_handler import (QoSMessageLostInfo, SubscriptionEventCallbacks,
                                 UnsupportedEventTypeError)
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription

from identification_node.wire.cdr import encode_joint_states


def time_msg(ns: int) -> Time:
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def wait_for_all_acked(publishers: Iterable[Publisher], timeout: float) -> bool:
    """Wait up to ``timeout`` s in all until the reliable subscribers of ``publishers`` have
    acknowledged everything published; False if some did not. Call before destroying them:
    a reliable writer's unacknowledged messages die with it."""
    deadline = time.monotonic() + timeout
    ok = True
    for pub in publishers:
        left = max(deadline - time.monotonic(), 0.0)
        ok &= bool(pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))))
    return ok


def publish_joint_states(publisher, stamps_ns: np.ndarray, names: Sequence[str], position=None,
                         velocity=None, effort=None) -> None:
    """Publish one JointState per row of the given (N, n) arrays, stamped with ``stamps_ns``.
    The messages are serialized together (wire.cdr.encode_joint_states) and published as CDR
    bytes, which rclpy hands to the middleware as they are."""
    for raw in encode_joint_states(stamps_ns, names, position, velocity, effort):
        publisher.publish(raw)


class PolledGroup(ReentrantCallbackGroup):
    """A callback group whose subscriptions rclpy's executors never wait for nor dispatch
    (they ask ``can_execute``), nor, unless ``events``, their event handlers: with
    rmw_fastrtps an event handler in the wait set wakes the executor on every message of its
    subscription (1.4 kHz wake-ups, about half a core at 1 kHz, measured). The EventsExecutor
    does not honour callback groups: spin nodes with polled inputs with rclpy's Executor
    classes (spin.make_executor(polled=True))."""

    def __init__(self, events: bool = False) -> None:
        super().__init__()
        self.events = events

    def can_execute(self, entity: Any) -> bool:
        return (self.events and not isinstance(entity, Subscription)
                and super().can_execute(entity))


class PolledSubscription:
    """A raw subscription of ``node`` that the executor never dispatches: ``poll`` takes every
    queued message from the middleware and hands them to ``handle`` as one list of CDR bytes,
    in arrival order.

    Receiving 1 kHz through an executor callback per message cost the process 81 us of CPU
    per message, taking the queue in batches 58 us (EventsExecutor, a no-op handler). The
    subscription is created by ``create_subscription`` (topic remapping, QoS and QoS
    overrides as usual) in a PolledGroup; ``poll`` takes its messages through the
    subscription's handle, as executors do.

    ``lost`` counts the messages that never reached ``handle``. While the topic has one
    publisher: the gaps in the publication sequence numbers of the messages taken, which
    include what this subscription's own KEEP_LAST queue dropped between two polls (no
    middleware event reports that). With ``message_lost_event``, also with several publishers
    (their numbers interleave) or a middleware without sequence numbers: the messages the
    middleware reports lost (the message_lost event: transport and writer-side losses). None
    if it can do neither.

    The event is off by default: rmw_fastrtps takes its sample-lost status under a lock that
    its shared-memory receive thread takes in the other order, and under bursts the two
    deadlock (the node hangs, signals included). The sequence-number gaps need no middleware
    call; the price is that losses while a topic has several publishers go uncounted. With
    the event on, its handlers wake the executor on every message (see PolledGroup).

    ``receive`` (any thread, e.g. one of its own while ``poll``'s thread is busy) moves the
    middleware's messages into this subscription's own queue, bounded by ``max_bytes``: the
    oldest beyond it are dropped, counted in ``dropped`` (the middleware's queue is bounded
    in count only: large messages sent faster than taken would fill memory).
    """

    def __init__(self, node: Node, msg_type: Any, topic: str,
                 handle: Callable[[list[bytes]], None], qos: Any,
                 message_lost_event: bool = False, max_bytes: float = math.inf,
                 **kwargs: Any) -> None:
        self.handle, self.node, self.topic = handle, node, topic
        self.max_bytes = max_bytes
        self.dropped = 0                # messages taken but dropped beyond max_bytes
        self.taken = 0                  # messages taken from the middleware so far
        self.peak_bytes = 0             # the most this queue held (bytes)
        self._queue: collections.deque[bytes] = collections.deque()
        self._queued_bytes = 0
        self._queue_lock = threading.Lock()
        self.sequence_numbers: bool | None = None    # known from the first message taken
        self._last_seq: int | None = None
        self._gaps = self._reported = 0     # written by poll's / the executor's thread
        create = partial(node.create_subscription, msg_type, topic,
                         lambda raw: handle([raw]),  # type: ignore[list-item]  # raw=True: bytes
                         qos, raw=True,
                         callback_group=PolledGroup(events=message_lost_event), **kwargs)
        self.events = False
        if message_lost_event:
            try:
                self.subscription: Subscription = create(
                    event_callbacks=SubscriptionEventCallbacks(
                        message_lost=self._on_message_lost))
                self.events = True
            except UnsupportedEventTypeError:
                pass
        if not self.events:
            self.subscription = create()   # the QoS override parameters are declared once

    @property
    def lost(self) -> int | None:
        """Messages lost so far (see the class doc); None if this middleware cannot tell."""
        if self.sequence_numbers is False and not self.events:
            return None
        return self._gaps + self._reported

    def reset_lost(self) -> None:
        self._gaps = self._reported = self.dropped = 0

    def receive(self) -> int:
        """Move every message the middleware holds into this subscription's queue (the oldest
        beyond ``max_bytes`` dropped); returns how many were taken."""
        sub, numbers = self.subscription, []
        dropped = 0
        with self._queue_lock, sub.handle:
            queue = self._queue     # under the lock: poll swaps it for a new one
            take = sub.handle.take_message
            while (taken := take(sub.msg_type, True)) is not None:
                queue.append(taken[0])
                numbers.append(taken[1]['publication_sequence_number'])
                self._queued_bytes += len(taken[0])
                while self._queued_bytes > self.max_bytes:
                    self._queued_bytes -= len(queue.popleft())
                    dropped += 1
                self.peak_bytes = max(self.peak_bytes, self._queued_bytes)
            if numbers:
                self._count_gaps(numbers)
            self.dropped += dropped
            self.taken += len(numbers)
        if dropped:
            self.node.get_logger().warning(
                f'{self.dropped} messages on {self.subscription.topic_name} dropped: more '
                f'than input_queue_bytes ({self.max_bytes:.0f}) waiting for processing',
                throttle_duration_sec=5.0)
        return len(numbers)

    def poll(self) -> int:
        """Hand every queued message to ``handle``; returns how many there were."""
        self.receive()
        with self._queue_lock:
            messages, self._queue = list(self._queue), collections.deque()
            self._queued_bytes = 0
        if messages:
            self.handle(messages)
        return len(messages)

    def _count_gaps(self, taken: list[int | None]) -> None:
        self.sequence_numbers = taken[0] is not None
        if not self.sequence_numbers:
            return
        numbers = cast('list[int]', taken)   # the middleware numbers every message or none
        if self._last_seq is not None:
            numbers = [self._last_seq] + numbers
        self._last_seq = numbers[-1]
        if numbers[-1] - numbers[0] == len(numbers) - 1:
            return      # consecutive (the usual case, without numpy)
        step = np.diff(np.array(numbers, dtype=np.int64))
        jumps = step[step > 1]   # a step back (another publisher, a restart) loses nothing
        if len(jumps) and self._one_publisher():
            self._gaps += int(jumps.sum()) - len(jumps)
            self._warn_lost()

    def _on_message_lost(self, info: QoSMessageLostInfo) -> None:
        if self.sequence_numbers is not False and self._one_publisher():
            return      # the gap in the sequence numbers counts them
        self._reported += int(info.total_count_change)
        self._warn_lost()

    def _one_publisher(self) -> bool:
        return self.node.count_publishers(self.subscription.topic_name) == 1

    def _warn_lost(self) -> None:
        self.node.get_logger().warning(
            f'{self.lost} messages on {self.subscription.topic_name} lost before the node '
            'took them (queue depth, processing stalls or network; see the qos_overrides.* '
            'parameters)', throttle_duration_sec=5.0)

    def destroy(self) -> None:
        """Destroy the subscription."""
        self.node.destroy_subscription(self.subscription)
