"""Per identified link, ``~/links/<link>/inertia`` (geometry_msgs/InertiaStamped, transient
local), published at each estimate refresh once samples came in.

As the message's definition says: m (kg), com (m) the centre of mass in the link's frame, and
ixx ... izz (kg m^2) the inertia tensor about the centre of mass, axes of the link's frame;
header.frame_id = the link (the child link of its joint, whose frame is the joint's), stamp =
the newest sample in the estimate. The values are those of the whole body moving with the link
(links attached by fixed joints included), from the published estimate (physically consistent
unless physical_consistency is false). Only the base parameters are identified: what the motion
cannot tell apart among links comes from the description's prior. A link whose values are not
physically consistent is not published (diagnostics name it). Link names that are not valid
ROS name tokens have their other characters replaced by ``_``.
"""
from __future__ import annotations

import re

import numpy as np
from geometry_msgs.msg import InertiaStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from identification_node.model.urdf_export import link_inertia, link_problem
from identification_node.ros.conversions import time_msg

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def topic_token(link: str) -> str:
    """``link`` as a ROS name token (letters, digits, _; not starting with a digit)."""
    token = re.sub(r'[^A-Za-z0-9_]', '_', link)
    return f'_{token}' if not token or token[0].isdigit() else token


def inertia_stamped(link: str, phi10: np.ndarray, stamp_ns: int) -> InertiaStamped:
    """One link block [m, mx, my, mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz] (about the link frame's
    origin) as InertiaStamped about its centre of mass."""
    m, c, Ic = link_inertia(np.asarray(phi10, dtype=float))
    msg = InertiaStamped()
    msg.header.frame_id = link
    msg.header.stamp = time_msg(stamp_ns)
    msg.inertia.m = m
    msg.inertia.com.x, msg.inertia.com.y, msg.inertia.com.z = (float(v) for v in c)
    for key, (a, b) in {'ixx': (0, 0), 'ixy': (0, 1), 'ixz': (0, 2), 'iyy': (1, 1),
                        'iyz': (1, 2), 'izz': (2, 2)}.items():
        setattr(msg.inertia, key, float(Ic[a, b]))
    return msg


class LinkOutputs:
    """The publishers of every identified link of ``robot``."""

    def __init__(self, node: Node, robot):
        self.links = list(robot.link_names)
        self._pubs = [node.create_publisher(InertiaStamped, f'~/links/{topic_token(link)}/inertia',
                                            LATCHED) for link in self.links]
        self.withheld: list[str] = []   # links not published at the last refresh, and why

    def publish(self, phi: np.ndarray, stamp_ns: int) -> None:
        """Publish each link's block of the standard parameters ``phi`` (robot order)."""
        withheld = []
        for i, (link, pub) in enumerate(zip(self.links, self._pubs)):
            block = phi[10 * i:10 * i + 10]
            problem = link_problem(link, block)
            if problem:
                withheld.append(problem)
            else:
                pub.publish(inertia_stamped(link, block, stamp_ns))
        self.withheld = withheld
