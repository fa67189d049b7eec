"""Incompatible QoS between a node's endpoints and the others on their topics, logged with
both profiles and counted.

A subscription whose publisher offers an incompatible QoS (e.g. best effort to a reliable
subscription) receives nothing, and nothing says so unless someone looks. rclpy's
incompatible-QoS event would tell, but an event handler of a subscription in the executor's
wait set wakes it on every message with rmw_fastrtps (conversions.PolledGroup: the node's
inputs are polled for that reason). So the node asks the ROS graph instead, every ``check``:
each other endpoint on the topic of a watched publisher or subscription is checked with
rclpy's ``qos_check_compatible``; a new incompatible one is logged once, naming the node and
both profiles, and counted in ``incompatible``.
"""
from __future__ import annotations

from typing import Any

from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSCompatibility, QoSProfile, qos_check_compatible
from rclpy.subscription import Subscription


def profile_text(qos: QoSProfile) -> str:
    """The policies that decide compatibility, in words (the history where known: the graph
    does not carry it)."""
    text = f'{qos.reliability.name.lower()}, {qos.durability.name.lower()}'
    if qos.history in (HistoryPolicy.KEEP_LAST, HistoryPolicy.KEEP_ALL):
        text += f', {qos.history.name.lower()}' + (
            f' {qos.depth}' if qos.history == HistoryPolicy.KEEP_LAST else '')
    if 0 < qos.deadline.nanoseconds < 1 << 62:     # beyond: infinite
        text += f', deadline {qos.deadline.nanoseconds * 1e-9:g} s'
    return text + f', liveliness {qos.liveliness.name.lower()}'


class QosWatch:
    """Watches the QoS compatibility of some of ``node``'s endpoints (see the module doc)."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.incompatible = 0
        self._ours: list[tuple[str, Any]] = []     # ('publisher' | 'subscription', endpoint)
        self._reported: set[tuple] = set()

    def watch(self, *endpoints: Any) -> None:
        """Watch rclpy Publishers and Subscriptions of the node."""
        for e in endpoints:
            self._ours.append(('subscription' if isinstance(e, Subscription) else 'publisher',
                               e))

    def check(self) -> int:
        """Look for new incompatible endpoints; returns how many were found."""
        node, found = self.node, 0
        me = (node.get_name(), node.get_namespace())
        for kind, ours in self._ours:
            topic = ours.topic_name
            others = (node.get_publishers_info_by_topic(topic) if kind == 'subscription'
                      else node.get_subscriptions_info_by_topic(topic))
            # our profile as the graph has it: the endpoint's own holds unset durations
            # (deadline, lease 0) where the graph holds infinite ones, which
            # qos_check_compatible takes for a deadline the publisher lacks
            mine = (node.get_subscriptions_info_by_topic(topic) if kind == 'subscription'
                    else node.get_publishers_info_by_topic(topic))
            own = next((i.qos_profile for i in mine if (i.node_name, i.node_namespace) == me),
                       ours.qos_profile)
            for info in others:
                if (info.node_name, info.node_namespace) == me:
                    continue
                offered, requested = ((info.qos_profile, own)
                                      if kind == 'subscription'
                                      else (own, info.qos_profile))
                compatibility, reason = qos_check_compatible(offered, requested)
                key = (kind, topic, bytes(info.endpoint_gid))
                if compatibility != QoSCompatibility.ERROR or key in self._reported:
                    continue
                self._reported.add(key)
                found += 1
                other = f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                node.get_logger().warning(
                    f'{topic}: incompatible QoS between this node\'s {kind} and the '
                    f"{'publisher' if kind == 'subscription' else 'subscription'} of {other}, "
                    f'no messages pass ({reason.removeprefix("ERROR: ").rstrip(";")}): '
                    f'offered {profile_text(offered)}; requested {profile_text(requested)}')
        self.incompatible += found
        return found
