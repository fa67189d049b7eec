"""Identified parameters as URDF <inertial> blocks, their physical consistency, and the parts of
a URDF the consistent solve reads (bodies merged into an identified link, geometry primitives).

The <inertial> of identified link i is written from its standard parameters [m, mx, my, mz, Ixx,
...] (about the joint origin, link frame) minus those of the bodies of locked joints merged into
it (which keep their own <inertial>, so the model stays right when they move), as the centre of
mass c = (mx, my, mz) / m and the inertia about it, I_c = I_o - m (|c|^2 1 - c c^T), rpy 0.
Links attached by fixed joints only lose their <inertial>: the identified values contain them.
Every link of the description is kept. Each identified joint's viscous and Coulomb friction
(fv, fc, when identified) go into its <dynamics damping= friction=>; a torque offset fo and a
rotor inertia Ia have no place in a URDF (estimate.yaml holds them; a comment names them).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

from identification_node.model.pseudo_inertia import link_inertia, locked_scale, pseudo_inertia
from identification_node.model.robot import PIN_ORDER, RobotModel


def inertia_problems(Ic: np.ndarray, rtol: float = 1e-9) -> list[str]:
    """Why the inertia ``Ic`` (3, 3) about a body's centre of mass is not physically
    consistent (empty when it is): finite, positive definite, principal moments obeying the
    triangle inequality."""
    try:
        ev = np.linalg.eigvalsh(Ic)
    except (np.linalg.LinAlgError, ValueError):   # overflow on absurd values
        return ['inertia about the centre of mass is not finite']
    if not np.isfinite(ev).all():
        return ['inertia about the centre of mass is not finite']
    tol = rtol * max(1.0, float(np.abs(ev).max()))
    moments = ', '.join(f'{v:.4g}' for v in ev)   # plain text: diagnostics values carry it
    if ev[0] <= tol:
        return ['inertia about the centre of mass is not positive definite '
                f'(principal moments {moments} kg m^2)']
    if 2 * ev.max() > ev.sum() + tol:
        return [f'principal moments {moments} kg m^2 violate the triangle inequality']
    return []


def link_problem(link: str, phi10: np.ndarray, rtol: float = 1e-9) -> str:
    """Why one link block [m, mx, my, mz, Ixx, ...] is not physically consistent (mass > 0,
    inertia about the centre of mass positive definite and obeying the triangle inequality);
    '' when it is."""
    if not np.isfinite(phi10).all():
        return f'{link}: parameters not finite (' + ' '.join(f'{v:.4g}' for v in phi10) + ')'
    with np.errstate(over='ignore', invalid='ignore'):
        m, _, Ic = link_inertia(phi10)
    if not m > 0:
        return f'{link}: mass {m:.6g} kg is not positive'
    problems = inertia_problems(Ic, rtol)
    return f'{link}: {problems[0]}' if problems else ''


def consistency_problems(robot: RobotModel, phi: np.ndarray, rtol: float = 1e-9) -> list[str]:
    """Why ``phi`` is not physically consistent (empty when it is): every link's block
    (link_problem); rotor inertia and friction coefficients >= 0."""
    problems = [link_problem(link, phi[10 * i:10 * i + 10], rtol)
                for i, link in enumerate(robot.link_names)]
    problems = [p for p in problems if p]
    for name, value in zip(robot.param_names[robot.n_inertial:], phi[robot.n_inertial:]):
        if not np.isfinite(value):
            problems.append(f'{name} = {value} is not finite')
        elif name.rsplit('.', 1)[1] in ('fv', 'fc', 'Ia') and value < 0:
            problems.append(f'{name} = {value:.6g} is negative')
    return problems


def _merged_links(robot: RobotModel, joint_id: int, main: str) -> list[str]:
    return [f.name for f in robot.model.frames
            if f.parentJoint == joint_id and f.type == pin.FrameType.BODY and f.name != main]


def _origin(el: ET.Element | None) -> pin.SE3:
    """An URDF <origin> (xyz, rpy; absent: identity) as an SE3."""
    if el is None:
        return pin.SE3.Identity()
    xyz = np.array([float(v) for v in el.get('xyz', '0 0 0').split()])
    rpy = [float(v) for v in el.get('rpy', '0 0 0').split()]
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def _xml_inertia(link: ET.Element) -> pin.Inertia:
    """A link's <inertial> in its link frame (zero when it has none)."""
    el = link.find('inertial')
    mass = None if el is None else el.find('mass')
    if el is None or mass is None:
        return pin.Inertia.Zero()
    m = float(mass.get('value', 0.0))
    about_com = np.zeros((3, 3))
    inertia = el.find('inertia')
    if inertia is not None:
        for k, (a, b) in {'ixx': (0, 0), 'ixy': (0, 1), 'ixz': (0, 2), 'iyy': (1, 1),
                          'iyz': (1, 2), 'izz': (2, 2)}.items():
            about_com[a, b] = about_com[b, a] = float(inertia.get(k, 0.0))
    M = _origin(el.find('origin'))
    return pin.Inertia(m, M.translation, M.rotation @ about_com @ M.rotation.T)


def _shape_corners(geometry: ET.Element) -> np.ndarray | None:
    """Corners (8, 3) of the bounding box of a primitive shape in its own frame; None for
    meshes and unknown shapes."""
    half = None
    for shape in geometry:
        if shape.tag == 'box':
            half = 0.5 * np.array([float(v) for v in shape.attrib['size'].split()])
        elif shape.tag in ('cylinder', 'capsule'):
            r, length = float(shape.attrib['radius']), float(shape.attrib['length'])
            half = np.array([r, r, 0.5 * length + (r if shape.tag == 'capsule' else 0.0)])
        elif shape.tag == 'sphere':
            half = np.full(3, float(shape.attrib['radius']))
    if half is None:
        return None
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    return signs * half


def _locked_links(root: ET.Element, main: str, merged: list[str]) -> set[str]:
    """Those of ``merged`` below a movable (locked) joint on their way up to ``main``."""
    parent: dict[str | None, tuple[str | None, str | None]] = {}
    for j in root.findall('joint'):
        child, up = j.find('child'), j.find('parent')
        if child is not None and up is not None:
            parent[child.get('link')] = (up.get('link'), j.get('type'))
    out = set()
    for name in merged:
        link: str | None = name
        while link != main and link in parent:
            link, kind = parent[link]
            if kind != 'fixed':
                out.add(name)
                break
    return out


def merged_bodies(robot: RobotModel, i: int) -> tuple[np.ndarray, np.ndarray | None]:
    """For identified link i: the standard parameters (10,) of the links of locked joints merged
    into it (in its joint frame, at the locked configuration; zero if none), and the corners
    (k, 3) of the bounding boxes of the collision and visual primitives of all of its links
    (joint frame, m; None when it has none). URDF descriptions only (zeros, None otherwise)."""
    if robot.kind != 'urdf':
        return np.zeros(10), None
    root = ET.fromstring(robot.description)
    links = {el.get('name'): el for el in root.findall('link')}
    jid, main = robot.joint_ids[i], robot.link_names[i]
    frames = {f.name: f.placement for f in robot.model.frames
              if f.parentJoint == jid and f.type == pin.FrameType.BODY and f.name in links}
    locked = _locked_links(root, main, [n for n in frames if n != main])
    fixed = pin.Inertia.Zero()
    corners = []
    for name, placement in frames.items():
        if name in locked:
            fixed += placement.act(_xml_inertia(links[name]))
        for el in links[name].findall('collision') + links[name].findall('visual'):
            geometry = el.find('geometry')
            c = None if geometry is None else _shape_corners(geometry)
            if c is not None:
                M = placement * _origin(el.find('origin'))
                corners.append(c @ M.rotation.T + M.translation)
    return (fixed.toDynamicParameters()[PIN_ORDER],
            np.concatenate(corners) if corners else None)


def identified_urdf(robot: RobotModel, phi: np.ndarray, note: str = '') -> str:
    """The robot's URDF with each identified link's <inertial> replaced by ``phi``'s values:
    the links merged into it on fixed joints lose theirs, those of locked joints keep theirs,
    scaled by their share (pseudo_inertia.locked_scale; 1 when they fit as described)."""
    if robot.kind != 'urdf':
        raise ValueError('identified URDF output needs a URDF robot description')
    root = ET.fromstring(robot.description)
    links = {el.get('name'): el for el in root.findall('link')}
    scaled = []
    for i, (jid, name) in enumerate(zip(robot.joint_ids, robot.link_names)):
        merged = _merged_links(robot, jid, name)
        locked = _locked_links(root, name, merged)
        for other in set(merged) - locked:
            old = links.get(other)
            merged_inertial = None if old is None else old.find('inertial')
            if old is not None and merged_inertial is not None:
                old.remove(merged_inertial)
        block, fixed = phi[10 * i:10 * i + 10], merged_bodies(robot, i)[0]
        share = locked_scale(block, fixed, pseudo_inertia(robot.phi_model[10 * i:10 * i + 10]
                                                          - fixed))
        if share != 1.0:
            for other in sorted(locked):
                _scale_inertial(links[other], share)
            if abs(share - 1.0) > 1e-3:
                scaled.append(f'{name} {share:.4g}')
        link = links[name]
        old = link.find('inertial')
        if old is not None:
            link.remove(old)
        m, c, Ic = link_inertia(block - share * fixed)
        inertial = ET.Element('inertial')
        ET.SubElement(inertial, 'origin', xyz=' '.join(f'{v:.9g}' for v in c), rpy='0 0 0')
        ET.SubElement(inertial, 'mass', value=f'{m:.9g}')
        ET.SubElement(inertial, 'inertia', {
            k: f'{Ic[a, b]:.9g}' for k, (a, b) in {
                'ixx': (0, 0), 'ixy': (0, 1), 'ixz': (0, 2),
                'iyy': (1, 1), 'iyz': (1, 2), 'izz': (2, 2)}.items()})
        link.insert(0, inertial)
    _write_friction(robot, root, phi)
    if scaled:
        note = (note + '; ' if note else '') + (
            'inertials of locked links scaled with the link they are merged into: '
            + ', '.join(scaled))
    kept = [e for e in ('fo', 'Ia') if e in robot.extras]
    if kept:
        note = (note + '; ' if note else '') + ', '.join(
            {'fo': 'torque offsets fo', 'Ia': 'rotor inertias Ia'}[e] for e in kept) + (
                ' are not URDF quantities: see the estimate (estimate.yaml)')
    if note:
        root.insert(0, ET.Comment(f' {note} '))
    ET.indent(root, space='  ')
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding='unicode') + '\n'


def _scale_inertial(link: ET.Element, factor: float) -> None:
    """A link's <mass> and <inertia> multiplied by ``factor`` (its centre of mass kept)."""
    el = link.find('inertial')
    for tag, keys in (('mass', ('value',)),
                      ('inertia', ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz'))):
        item = None if el is None else el.find(tag)
        for key in keys:
            value = None if item is None else item.get(key)
            if item is not None and value is not None:
                item.set(key, f'{factor * float(value):.9g}')


def _write_friction(robot: RobotModel, root: ET.Element, phi: np.ndarray) -> None:
    """Each identified joint's fv and fc (those identified) into its <dynamics damping friction>
    (N m s/rad and N m; N s/m and N for prismatic joints), its other attributes kept."""
    fields = {'fv': 'damping', 'fc': 'friction'}
    if not set(fields) & set(robot.extras):
        return
    joints = {el.get('name'): el for el in root.findall('joint')}
    extras = np.reshape(phi[robot.n_inertial:], (robot.dof, len(robot.extras)))
    for name, values in zip(robot.joint_names, extras):
        joint = joints.get(name)
        if joint is None:
            continue
        dynamics = joint.find('dynamics')
        if dynamics is None:
            dynamics = ET.SubElement(joint, 'dynamics')
        for extra, value in zip(robot.extras, values):
            if extra in fields:
                dynamics.set(fields[extra], f'{value:.9g}')
