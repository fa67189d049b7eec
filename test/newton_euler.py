"""Independent joint-torque regressor from An, Atkeson and Hollerbach (1986), for the tests.

A second formulation of ``RobotModel.regressor``: numpy only, kinematics read from the URDF with
xml.etree (no pinocchio). Per link i, in its joint frame (= URDF link frame, origin on joint i):

- forward recursion for w_i, wd_i and the joint origin acceleration pdd_i (gravity g_i carried in
  the same frame and entering as pdd_i - g_i);
- A_i (6x10), eq. 1 / appendix eq. 14 and 17:
  f = m (pdd - g) + ([wd x] + [w x][w x]) mc,  n = [(g - pdd) x] mc + [. wd] I + [w x][. w] I;
- wrench transmission T (eq. 3-5) towards the base, summed over the distal links (eq. 2, 6);
- projection on the joint axis (eq. 7): the moment for a revolute joint, the force for a
  prismatic one.

Joints not identified are locked (treated as fixed) at ``locked`` (default 0); fixed and locked
joints merge their child links into the nearest identified joint's link.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

GRAVITY = np.array([0.0, 0.0, -9.81])
ONE_DOF = ('revolute', 'continuous', 'prismatic')


@dataclass
class UrdfJoint:
    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray  # 4x4 pose of the joint frame (at q = 0) in the parent link frame
    axis: np.ndarray  # unit vector in the joint frame


@dataclass
class UrdfLink:
    name: str
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))  # in the link frame
    rot: np.ndarray = field(default_factory=lambda: np.eye(3))  # inertial frame in link frame
    inertia: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # about com, inertial


def _floats(text: str | None, default: str) -> np.ndarray:
    return np.array([float(v) for v in (text or default).split()])


def rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _pose(elem: ET.Element | None) -> np.ndarray:
    T = np.eye(4)
    if elem is not None:
        T[:3, :3] = rpy_matrix(_floats(elem.get('rpy'), '0 0 0'))
        T[:3, 3] = _floats(elem.get('xyz'), '0 0 0')
    return T


def parse_urdf(xml: str) -> tuple[dict[str, UrdfJoint], dict[str, UrdfLink]]:
    """Joints and links of a URDF document, by name."""
    root = ET.fromstring(xml)
    links = {}
    for el in root.findall('link'):
        link = UrdfLink(el.get('name'))
        inertial = el.find('inertial')
        if inertial is not None:
            T = _pose(inertial.find('origin'))
            link.com, link.rot = T[:3, 3], T[:3, :3]
            link.mass = float(inertial.find('mass').get('value'))
            i = {k: float(v) for k, v in inertial.find('inertia').attrib.items()}
            link.inertia = np.array([[i['ixx'], i['ixy'], i['ixz']],
                                     [i['ixy'], i['iyy'], i['iyz']],
                                     [i['ixz'], i['iyz'], i['izz']]])
        links[link.name] = link
    joints = {}
    for el in root.findall('joint'):
        axis_el = el.find('axis')
        axis = _floats(axis_el.get('xyz') if axis_el is not None else None, '1 0 0')
        joints[el.get('name')] = UrdfJoint(
            el.get('name'), el.get('type'), el.find('parent').get('link'),
            el.find('child').get('link'), _pose(el.find('origin')), axis / np.linalg.norm(axis))
    return joints, links


def _skew(v: np.ndarray) -> np.ndarray:
    """[v x] for v of shape (..., 3) -> (..., 3, 3)."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def _dot_matrix(w: np.ndarray) -> np.ndarray:
    """[. w] (..., 3, 6): I w = [. w] [Ixx, Ixy, Ixz, Iyy, Iyz, Izz]."""
    M = np.zeros(w.shape[:-1] + (3, 6))
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    M[..., 0, 0], M[..., 0, 1], M[..., 0, 2] = x, y, z
    M[..., 1, 1], M[..., 1, 3], M[..., 1, 4] = x, y, z
    M[..., 2, 2], M[..., 2, 4], M[..., 2, 5] = x, y, z
    return M


def _axis_rotation(axis: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rodrigues: rotations (N, 3, 3) by angles q (N,) about a unit axis."""
    K = _skew(axis)
    s, c = np.sin(q)[:, None, None], np.cos(q)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _motion(joint: UrdfJoint, value: float) -> np.ndarray:
    """4x4 joint motion for a locked joint (multi-DOF joints: their zero pose)."""
    T = np.eye(4)
    if joint.type in ('revolute', 'continuous'):
        T[:3, :3] = _axis_rotation(joint.axis, np.array([value]))[0]
    elif joint.type == 'prismatic':
        T[:3, 3] = joint.axis * value
    return T


class Chain:
    """The identified joints of a URDF as a tree of rigid bodies (locked joints made fixed)."""

    def __init__(self, xml: str, joints: Sequence[str],
                 locked: Mapping[str, float] | None = None):
        self.joints_by_name, self.links = parse_urdf(xml)
        self.names = list(joints)
        for j in self.names:
            if self.joints_by_name[j].type not in ONE_DOF:
                raise ValueError(f'joint {j} is not a 1-DOF joint')
        self.locked = dict(locked or {})
        self._parent_joint = {j.child: j for j in self.joints_by_name.values()}
        self._memo: dict[str, tuple[str | None, np.ndarray]] = {}
        # Per identified joint: parent body (an identified joint or None = base) and the
        # joint frame's pose at q = 0 in that body's frame.
        self.parent: dict[str, str | None] = {}
        self.placement: dict[str, np.ndarray] = {}
        for j in self.names:
            joint = self.joints_by_name[j]
            body, T = self.body_of(joint.parent)
            self.parent[j], self.placement[j] = body, T @ joint.origin
        self.order = sorted(self.names, key=self._depth)

    def _depth(self, j: str) -> int:
        d, p = 0, self.parent[j]
        while p is not None:
            d, p = d + 1, self.parent[p]
        return d

    def body_of(self, link: str) -> tuple[str | None, np.ndarray]:
        """(identified joint moving ``link`` or None for the base, pose of the link frame in
        that joint's frame)."""
        if link not in self._memo:
            joint = self._parent_joint.get(link)
            if joint is None:
                self._memo[link] = (None, np.eye(4))
            elif joint.name in self.names:
                self._memo[link] = (joint.name, np.eye(4))
            else:
                body, T = self.body_of(joint.parent)
                value = float(self.locked.get(joint.name, 0.0))
                self._memo[link] = (body, T @ joint.origin @ _motion(joint, value))
        return self._memo[link]

    def standard_parameters(self) -> np.ndarray:
        """phi (10 n,): per identified joint's link (with the links merged into it) [m, mx, my,
        mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz] about the joint frame origin, in the joint frame."""
        phi = np.zeros(10 * len(self.names))
        for name, link in self.links.items():
            body, T = self.body_of(name)
            if body is None or link.mass == 0.0:
                continue
            R = T[:3, :3] @ link.rot
            c = T[:3, :3] @ link.com + T[:3, 3]
            Io = R @ link.inertia @ R.T + link.mass * (c @ c * np.eye(3) - np.outer(c, c))
            k = 10 * self.names.index(body)
            phi[k:k + 10] += np.concatenate([[link.mass], link.mass * c, Io[np.triu_indices(3)]])
        return phi

    def regressor(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                  gravity: np.ndarray = GRAVITY) -> np.ndarray:
        """K (N, n, 10 n) with tau = K phi, joints and parameter blocks in ``names`` order."""
        q, qd, qdd = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (q, qd, qdd))
        N, n = q.shape[0], len(self.names)
        zeros = np.zeros((N, 3))
        base = dict(w=zeros, wd=zeros, pdd=zeros, g=np.tile(gravity, (N, 1)))
        state, transmit, W = {}, {}, {}
        for j in self.order:  # forward recursion, base to tip
            i = self.names.index(j)
            joint, X0 = self.joints_by_name[j], self.placement[j]
            a = joint.axis
            p = state[self.parent[j]] if self.parent[j] is not None else base
            if joint.type == 'prismatic':
                R = np.tile(X0[:3, :3], (N, 1, 1))
                s = X0[:3, 3] + q[:, i, None] * (X0[:3, :3] @ a)
            else:
                R = X0[:3, :3] @ _axis_rotation(a, q[:, i])
                s = np.tile(X0[:3, 3], (N, 1))
            Rt = np.swapaxes(R, 1, 2)
            w = np.einsum('nij,nj->ni', Rt, p['w'])
            wd = np.einsum('nij,nj->ni', Rt, p['wd'])
            acc = p['pdd'] + np.cross(p['wd'], s) + np.cross(p['w'], np.cross(p['w'], s))
            pdd = np.einsum('nij,nj->ni', Rt, acc)
            if joint.type == 'prismatic':
                pdd = pdd + 2 * np.cross(w, qd[:, i, None] * a) + qdd[:, i, None] * a
            else:
                wd = wd + np.cross(w, qd[:, i, None] * a) + qdd[:, i, None] * a
                w = w + qd[:, i, None] * a
            g = np.einsum('nij,nj->ni', Rt, p['g'])
            state[j] = dict(w=w, wd=wd, pdd=pdd, g=g)
            # A_j (eq. 1, appendix eq. 14 and 17)
            A = np.zeros((N, 6, 10))
            A[:, :3, 0] = pdd - g
            A[:, :3, 1:4] = _skew(wd) + _skew(w) @ _skew(w)
            A[:, 3:, 1:4] = _skew(g - pdd)
            A[:, 3:, 4:] = _dot_matrix(wd) + _skew(w) @ _dot_matrix(w)
            W[j] = np.zeros((N, 6, 10 * n))
            W[j][:, :, 10 * i:10 * i + 10] = A
            # T (eq. 3): wrench in frame j -> wrench at the parent body's origin, in its frame
            T = np.zeros((N, 6, 6))
            T[:, :3, :3] = R
            T[:, 3:, 3:] = R
            T[:, 3:, :3] = _skew(s) @ R
            transmit[j] = T
        for j in reversed(self.order):  # eq. 2, 5, 6: sum the distal wrenches
            if self.parent[j] is not None:
                W[self.parent[j]] += transmit[j] @ W[j]
        K = np.zeros((N, n, 10 * n))
        for i, j in enumerate(self.names):  # eq. 7: project on the joint axis
            joint = self.joints_by_name[j]
            select = np.zeros(6)
            if joint.type == 'prismatic':
                select[:3] = joint.axis
            else:
                select[3:] = joint.axis
            K[:, i, :] = np.einsum('k,nkp->np', select, W[j])
        return K
