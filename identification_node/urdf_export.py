"""Identified parameters as URDF <inertial> blocks, and their physical consistency.

The <inertial> of link i is written from the standard parameters [m, mx, my, mz, Ixx, ...] (about
the joint origin, link frame) as the centre of mass c = (mx, my, mz) / m and the inertia about
it, I_c = I_o - m (|c|^2 1 - c c^T), with rpy 0. Bodies that pinocchio merged into an identified
link (fixed children, locked subtrees) lose their own <inertial>, since the identified values
already contain them.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

from .robot import RobotModel


def link_inertia(phi10: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, centre of mass (3,), inertia about the centre of mass (3, 3)) of one link block."""
    m = float(phi10[0])
    Ixx, Ixy, Ixz, Iyy, Iyz, Izz = phi10[4:]
    Io = np.array([[Ixx, Ixy, Ixz], [Ixy, Iyy, Iyz], [Ixz, Iyz, Izz]])
    c = phi10[1:4] / m if m != 0 else np.zeros(3)
    return m, c, Io - m * (c @ c * np.eye(3) - np.outer(c, c))


def consistency_problems(robot: RobotModel, phi: np.ndarray, rtol: float = 1e-9) -> list[str]:
    """Why ``phi`` is not physically consistent (empty when it is): per link mass > 0, inertia
    about the centre of mass positive definite and obeying the triangle inequality; rotor
    inertia and friction coefficients >= 0."""
    problems = []
    for i, link in enumerate(robot.link_names):
        block = phi[10 * i:10 * i + 10]
        if not np.isfinite(block).all():
            problems.append(f'{link}: parameters not finite ('
                            + ' '.join(f'{v:.4g}' for v in block) + ')')
            continue
        with np.errstate(over='ignore', invalid='ignore'):
            m, _, Ic = link_inertia(block)
        if not m > 0:
            problems.append(f'{link}: mass {m:.6g} kg is not positive')
            continue
        try:
            ev = np.linalg.eigvalsh(Ic)
        except (np.linalg.LinAlgError, ValueError):   # overflow on absurd values
            problems.append(f'{link}: inertia about the centre of mass is not finite')
            continue
        tol = rtol * max(1.0, float(np.abs(ev).max()))
        if ev[0] <= tol:
            problems.append(f'{link}: inertia about the centre of mass is not positive definite '
                            f'(principal moments {np.array2string(ev, precision=4)})')
        elif 2 * ev.max() > ev.sum() + tol:
            problems.append(f'{link}: principal moments {np.array2string(ev, precision=4)} '
                            'violate the triangle inequality')
    for name, value in zip(robot.param_names[robot.n_inertial:], phi[robot.n_inertial:]):
        if not np.isfinite(value):
            problems.append(f'{name} = {value} is not finite')
        elif name.rsplit('.', 1)[1] in ('fv', 'fc', 'Ia') and value < 0:
            problems.append(f'{name} = {value:.6g} is negative')
    return problems


def _merged_links(robot: RobotModel, joint_id: int, main: str) -> list[str]:
    return [f.name for f in robot.model.frames
            if f.parentJoint == joint_id and f.type == pin.FrameType.BODY and f.name != main]


def identified_urdf(robot: RobotModel, phi: np.ndarray, note: str = '') -> str:
    """The robot's URDF with each identified link's <inertial> replaced by ``phi``'s values."""
    if robot.kind != 'urdf':
        raise ValueError('identified URDF output needs a URDF robot description')
    root = ET.fromstring(robot.description)
    links = {el.get('name'): el for el in root.findall('link')}
    for i, (jid, name) in enumerate(zip(robot.joint_ids, robot.link_names)):
        for merged in _merged_links(robot, jid, name):
            old = links.get(merged)
            if old is not None and old.find('inertial') is not None:
                old.remove(old.find('inertial'))
        link = links[name]
        old = link.find('inertial')
        if old is not None:
            link.remove(old)
        m, c, Ic = link_inertia(phi[10 * i:10 * i + 10])
        inertial = ET.Element('inertial')
        ET.SubElement(inertial, 'origin', xyz=' '.join(f'{v:.9g}' for v in c), rpy='0 0 0')
        ET.SubElement(inertial, 'mass', value=f'{m:.9g}')
        ET.SubElement(inertial, 'inertia', **{
            k: f'{Ic[a, b]:.9g}' for k, (a, b) in {
                'ixx': (0, 0), 'ixy': (0, 1), 'ixz': (0, 2),
                'iyy': (1, 1), 'iyz': (1, 2), 'izz': (2, 2)}.items()})
        link.insert(0, inertial)
    if note:
        root.insert(0, ET.Comment(f' {note} '))
    ET.indent(root, space='  ')
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding='unicode') + '\n'
