"""Robot model and the inertial-parameter regressor tau = Y(q, qd, qdd) phi.

Conventions used everywhere in this package (README, "Conventions"):

- Units are SI: m, kg, s, rad, N, N m (prismatic joints: m and N).
- Joints: the identified joints in the order given by the user (default: the model's order of
  its movable joints). Every other movable joint is locked at a reference position. All per-joint
  arrays (q, qd, qdd, tau, currents) follow this order.
- Standard parameter vector phi, first the links: link i is the child link of joint i, 10 values
  each, ``[m, mx, my, mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz]``: mass, first moments m*c and the inertia
  tensor about the joint frame origin, all in the link (= joint) frame, as in An, Atkeson and
  Hollerbach (1986). Names ``<link>.m`` ... ``<link>.Izz``. Then the optional per-joint columns,
  joint by joint, each in the order ``fv`` (viscous friction, N m s/rad), ``fc`` (Coulomb friction,
  N m), ``fo`` (torque offset, N m), ``Ia`` (rotor/reflected inertia, kg m^2): ``<joint>.fv``...
- Regressor arrays have shape (N, n, p): N samples, n joints, p parameters.
"""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from itertools import repeat
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pinocchio as pin

from identification_node.errors import IdentificationError
from identification_node.model.coulomb import coulomb_column
from identification_node.model.pseudo_inertia import link_inertia

LINK_PARAMS = ('m', 'mx', 'my', 'mz', 'Ixx', 'Ixy', 'Ixz', 'Iyy', 'Iyz', 'Izz')
JOINT_EXTRAS = ('fv', 'fc', 'fo', 'Ia')
# ours[k] = pinocchio's dynamic parameters [m, mcx, mcy, mcz, Ixx, Ixy, Iyy, Ixz, Iyz, Izz][k]
PIN_ORDER = np.array([0, 1, 2, 3, 4, 5, 7, 6, 8, 9])
BUNDLED_DIR = Path(__file__).resolve().parent.parent / 'robots'
_REGRESSOR_CHUNK = 128   # samples per stacked pinocchio regressor (bounds the work memory)
PRISMATIC_SCALE = 0.1    # m per rad: a prismatic joint's share of a setting given in rad


def bundled_robots() -> list[str]:
    """Names of the robots shipped with the package."""
    return sorted(p.stem for p in BUNDLED_DIR.glob('*.urdf'))


def read_description(source: str | os.PathLike) -> tuple[str, str, str]:
    """Resolve a bundled name, a file path or an XML string to (xml text, 'urdf'|'mjcf', label)."""
    text = str(source).strip()
    if not text:
        raise IdentificationError('no robot given: name a bundled robot, a URDF file or XML')
    if text.startswith('<'):
        xml, label = text, 'robot_description'
    elif text in bundled_robots():
        path = BUNDLED_DIR / f'{text}.urdf'
        xml, label = path.read_text(), text
    elif Path(text).is_file():
        try:
            xml = Path(text).read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise IdentificationError(f'cannot read robot file {text}: {exc}') from None
        label = Path(text).stem
    else:
        raise IdentificationError(
            f"unknown robot '{text}': not a bundled robot ({', '.join(bundled_robots())}), "
            'an existing URDF/MJCF file, nor URDF XML')
    kind = 'mjcf' if '<mujoco' in xml[:2000] else 'urdf'
    return xml, kind, label


@contextlib.contextmanager
def _captured_stderr_fd(sink: list):
    """Capture what C++ code writes to file descriptor 2 (urdfdom prints parse errors there)."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile('w+') as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            sink.append(tmp.read())


def _build_pin_model(xml: str, kind: str, label: str) -> pin.Model:
    printed: list[str] = []
    try:
        with _captured_stderr_fd(printed):
            if kind == 'urdf':
                if '<robot' not in xml:
                    raise ValueError('no <robot> element')
                return pin.buildModelFromXML(xml)
            # pinocchio reads MJCF from files only.
            with tempfile.NamedTemporaryFile('w', suffix='.xml', delete=False) as f:
                f.write(xml)
            try:
                return pin.buildModelFromMJCF(f.name)
            finally:
                os.unlink(f.name)
    except Exception as exc:  # pinocchio raises plain ValueError/RuntimeError with C++ text
        detail = ' '.join(' '.join(printed).split())
        raise IdentificationError(f'robot {label}: {kind.upper()} does not parse: {exc}'
                                  + (f' ({detail})' if detail else '')) from None


def _reduced_model(full: pin.Model, lock: list[int], qref: np.ndarray) -> pin.Model:
    """pin.buildReducedModel of ``full`` with the joints ``lock`` fixed at ``qref``, also where
    a joint (movable or fixed) and a link share a name (URDF keeps them apart; the reduction
    looks frames up by name and refuses a name two frames carry): such joints are renamed for
    the reduction and named back after it."""
    body = pin.FrameType.BODY
    links = {f.name for f in full.frames if f.type == body}
    clash = {f.name for f in full.frames if f.type != body and f.name in links}
    if not clash:
        return pin.buildReducedModel(full, lock, qref)
    model = pin.Model(full)
    temporary = {name: f'{name}#joint' for name in clash}
    while links & set(temporary.values()):   # a link named like that, too
        temporary = {name: f'{new}#' for name, new in temporary.items()}
    for j in range(1, model.njoints):
        model.names[j] = temporary.get(model.names[j], model.names[j])
    for i, frame in enumerate(model.frames):
        if frame.type != body and frame.name in clash:
            frame.name = temporary[frame.name]
            model.frames[i] = frame
    reduced = pin.buildReducedModel(model, lock, qref)
    original = {new: name for name, new in temporary.items()}
    for j in range(1, reduced.njoints):
        reduced.names[j] = original.get(reduced.names[j], reduced.names[j])
    for i, frame in enumerate(reduced.frames):
        if frame.name in original:
            frame.name = original[frame.name]
            reduced.frames[i] = frame
    return reduced


def _check_joint_frames(model: pin.Model, label: str) -> None:
    """IdentificationError naming the joint whose axis is zero (URDF ``<axis xyz="0 0 0">``:
    its torque would be identically zero) or whose frame is degenerate (not finite, a
    rotation that is not one, a placement beyond any arm's size)."""
    for j in range(1, model.njoints):
        name = model.names[j]
        axis = getattr(model.joints[j].extract(), 'axis', None)
        if axis is not None and not np.linalg.norm(axis) > 0.5:   # pinocchio normalises it
            raise IdentificationError(f"robot {label}: joint '{name}' has a zero axis "
                                      f'{np.asarray(axis).tolist()}; give its direction '
                                      '(URDF <axis xyz="...">)')
    placements = [(model.names[j], model.jointPlacements[j]) for j in range(1, model.njoints)]
    for name, placement in placements + [(f.name, f.placement) for f in model.frames]:
        rotation, translation = placement.rotation, placement.translation
        if not (np.isfinite(placement.homogeneous).all()
                and np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6)
                and np.linalg.det(rotation) > 0 and np.abs(translation).max() <= 1e3):
            raise IdentificationError(f"robot {label}: the frame of '{name}' is "
                                      f'degenerate (origin {translation.tolist()} m, rotation '
                                      f'{rotation.tolist()}); check its URDF <origin>')


def _mimic_joints(xml: str) -> dict[str, tuple[str, float, float]]:
    """URDF joints with a <mimic>: name -> (the joint it follows, multiplier, offset), so that
    q = multiplier * q_leader + offset."""
    import xml.etree.ElementTree as ET
    try:
        root = ET.fromstring(xml)
    except ET.ParseError:
        return {}
    out: dict[str, tuple[str, float, float]] = {}
    for j in root.iter('joint'):
        m = j.find('mimic')
        if m is not None:
            try:
                gain, offset = float(m.get('multiplier', 1.0)), float(m.get('offset', 0.0))
            except ValueError:
                raise IdentificationError(f"joint '{j.get('name')}': <mimic> multiplier and "
                                          'offset must be numbers') from None
            out[j.get('name', '')] = (m.get('joint', '?'), gain, offset)
    return out


def _is_prismatic(joint: pin.JointModel) -> bool:
    return 'Prismatic' in joint.shortname() or joint.shortname().startswith('JointModelP')


def _pin_inertia(link_phi: np.ndarray, link: str) -> pin.Inertia:
    """pinocchio's Inertia of one link's standard parameters (10,). A massless link (between
    the joints of a ball joint written as three revolute ones, say) keeps its rotational
    inertia: Inertia.FromDynamicParameters divides the first moment by the mass (NaN)."""
    if link_phi[0] != 0.0:
        dyn = np.empty(10)
        dyn[PIN_ORDER] = link_phi
        return pin.Inertia.FromDynamicParameters(dyn)
    if np.any(link_phi[1:4] != 0.0):
        raise IdentificationError(f'link {link}: a first moment {link_phi[1:4].tolist()} kg m '
                                  'without mass is no rigid body')
    return pin.Inertia(*link_inertia(link_phi))


class RobotModel:
    """The identified joints of a rigid-body model and their regressor.

    ``description`` is a bundled robot name, a URDF (or MJCF) file path, or URDF XML;
    ``name`` is the description's own (URDF ``<robot name>``), else the file's stem.
    ``joints`` selects and orders the identified joints; other movable joints are locked at
    ``locked_positions`` (default 0, or the neutral configuration). ``extras`` adds per-joint
    columns from ``JOINT_EXTRAS``; ``coulomb_velocity`` > 0 (rad/s; prismatic joints: / 10
    m/s, in_joint_units) replaces sign(qd) by tanh(qd / coulomb_velocity) in the Coulomb
    column.
    """

    def __init__(self, description: str | os.PathLike, joints: Sequence[str] | None = None, *,
                 extras: Sequence[str] = (), coulomb_velocity: float = 0.0,
                 locked_positions: Mapping[str, float] | None = None):
        self.description, self.kind, self.name = read_description(description)
        full = _build_pin_model(self.description, self.kind, self.name)
        self.name = full.name or self.name    # the URDF's <robot name> (MJCF: model)
        _check_joint_frames(full, self.name)
        self.description_joints = list(full.names)[1:]   # every joint, movable or not
        movable = [full.names[j] for j in range(1, full.njoints) if full.joints[j].nv > 0]
        if not movable:
            where = '' if str(description).lstrip().startswith('<') or self.name == str(
                description) else f' ({description})'
            raise IdentificationError(f'robot {self.name}{where} has no movable joints: '
                                      'nothing to identify')
        mimics = _mimic_joints(self.description) if self.kind == 'urdf' else {}
        grouped = set(mimics) | {leader for leader, _, _ in mimics.values()}
        if joints is None or len(joints) == 0:
            joints = [j for j in movable if j not in grouped] or movable
        joints = [str(j).strip() for j in joints]
        mimicking = [j for j in joints if j in grouped]
        if mimicking:
            others = [j for j in joints if j not in grouped]
            raise IdentificationError(
                f'robot {self.name}: ' + ', '.join(
                    f"joint '{j}' mimics '{leader}'" for j, (leader, _, _) in mimics.items())
                + ' (URDF <mimic>): mimic joints are not modelled, so neither they nor the '
                f"joints they follow can be identified ({', '.join(mimicking)} asked for); "
                f"without them (joints: [{', '.join(others)}]) they are locked together at "
                'their reference position')
        self.mimic_locked = [j for j in movable if j in grouped]
        if len(set(joints)) != len(joints):
            raise IdentificationError(f'joints listed more than once: {joints}')
        for j in joints:
            if j not in movable:
                raise IdentificationError(
                    f"joint '{j}' is not a movable joint of robot {self.name} "
                    f"(movable joints: {', '.join(movable)})")
            if full.joints[full.getJointId(j)].nv != 1:
                raise IdentificationError(
                    f"joint '{j}' of robot {self.name} has {full.joints[full.getJointId(j)].nv} "
                    'degrees of freedom: only revolute, continuous and prismatic joints are '
                    'identified (lock the others)')
        unknown_extras = set(extras) - set(JOINT_EXTRAS)
        if unknown_extras:
            raise IdentificationError(
                f'unknown extra columns {sorted(unknown_extras)}; choose from {JOINT_EXTRAS}')
        if not np.isfinite(coulomb_velocity) or coulomb_velocity < 0:
            raise IdentificationError('coulomb_velocity must be finite and >= 0')
        self.extras = tuple(e for e in JOINT_EXTRAS if e in extras)
        self.coulomb_velocity = float(coulomb_velocity)
        self.model = self._lock(full, joints, movable, dict(locked_positions or {}), mimics)
        self.data = self.model.createData()
        self.joint_names = list(joints)
        self._setup_indices()

    # -- construction -------------------------------------------------------------------------
    def _lock(self, full: pin.Model, joints: list[str], movable: list[str],
              locked_positions: dict[str, float],
              mimics: dict[str, tuple[str, float, float]]) -> pin.Model:
        """The model with the movable joints not in ``joints`` locked: at ``locked_positions``
        (default the neutral one), a mimic joint at multiplier * its leader's + offset."""
        unknown = set(locked_positions) - set(movable)
        if unknown:
            raise IdentificationError(f'locked_positions name unknown joints {sorted(unknown)}')
        follow = sorted(set(locked_positions) & set(mimics))
        if follow:
            raise IdentificationError(f'locked_positions name mimic joints {follow}: they are '
                                      'locked with the joints they follow; give those')
        lock = [full.getJointId(j) for j in movable if j not in joints]
        if not lock:
            return full
        qref = pin.neutral(full)

        def put(name: str, value: float) -> None:
            jm = full.joints[full.getJointId(name)]
            if jm.nq == 1:
                qref[jm.idx_q] = float(value)
            elif jm.nq == 2 and jm.nv == 1:
                qref[jm.idx_q:jm.idx_q + 2] = np.cos(value), np.sin(value)
            else:
                raise IdentificationError(f'cannot lock multi-DOF joint {name} at a scalar')

        def position(name: str) -> float:
            jm = full.joints[full.getJointId(name)]
            return float(qref[jm.idx_q] if jm.nq == 1 else
                         np.arctan2(qref[jm.idx_q + 1], qref[jm.idx_q]))

        for name, value in locked_positions.items():
            put(name, value)
        for _ in range(len(mimics)):      # chains of mimics: leaders first
            for name, (leader, gain, offset) in mimics.items():
                if name in movable and leader in movable:
                    put(name, gain * position(leader) + offset)
        return _reduced_model(full, lock, qref)

    def in_joint_units(self, value: float) -> np.ndarray:
        """(n,) a setting given in rad (rad/s, rad/s^2) for each joint: as is for revolute
        joints, times PRISMATIC_SCALE (0.1 m/rad) for prismatic ones (m, m/s, m/s^2)."""
        return value * np.where(self.prismatic, PRISMATIC_SCALE, 1.0)

    def _setup_indices(self) -> None:
        m = self.model
        n = len(self.joint_names)
        self.joint_ids = [m.getJointId(j) for j in self.joint_names]
        jms = [m.joints[j] for j in self.joint_ids]
        self.idx_v = np.array([jm.idx_v for jm in jms])
        self.idx_q = np.array([jm.idx_q for jm in jms])
        self.continuous = np.array([jm.nq == 2 for jm in jms])
        self.prismatic = np.array([_is_prismatic(jm) for jm in jms])
        self.link_names = [self._child_link(j) for j in self.joint_ids]
        self.n_inertial = 10 * n
        self.param_names = [f'{link}.{p}' for link in self.link_names for p in LINK_PARAMS]
        self.param_names += [f'{j}.{e}' for j in self.joint_names for e in self.extras]
        self.num_params = len(self.param_names)
        # Regressor column block of pinocchio's joint id j starts at 10 * (j - 1).
        cols = np.concatenate([10 * (j - 1) + PIN_ORDER for j in self.joint_ids])
        width = 10 * (m.njoints - 1)
        # flat index of each of the package's regressor entries in pinocchio's (nv, width)
        self._flat = (self.idx_v[:, None] * width + cols[None, :]).reshape(-1)
        self._q_neutral = pin.neutral(m)
        self._identity_q = (m.nq == len(jms) and not self.continuous.any()
                            and np.array_equal(self.idx_q, np.arange(m.nq)))
        self._identity_v = m.nv == len(jms) and np.array_equal(self.idx_v, np.arange(m.nv))
        # each extra's column of each joint (its row): (extra, rows, columns)
        rows, ne = np.arange(n), len(self.extras)
        self._extra_columns = [(e, rows, self.n_inertial + rows * ne + k)
                               for k, e in enumerate(self.extras)]
        lower, upper = m.lowerPositionLimit[self.idx_q], m.upperPositionLimit[self.idx_q]
        lower = np.where(self.continuous, -np.inf, lower)
        upper = np.where(self.continuous, np.inf, upper)
        self.position_limits = np.stack([lower, upper], axis=1)
        self.velocity_limits = np.asarray(m.velocityLimit)[self.idx_v].copy()
        self.effort_limits = np.asarray(m.effortLimit)[self.idx_v].copy()

    def _child_link(self, joint_id: int) -> str:
        for f in self.model.frames:
            if f.parentJoint == joint_id and f.type == pin.FrameType.BODY:
                return f.name
        return self.model.names[joint_id] + '_link'

    # -- dimensions and parameters ------------------------------------------------------------
    @property
    def dof(self) -> int:
        return len(self.joint_names)

    def param_index(self, name: str) -> int:
        """Column of a standard parameter name, with a clear error for unknown names."""
        try:
            return self.param_names.index(name)
        except ValueError:
            raise IdentificationError(f'unknown parameter {name!r}') from None

    @property
    def phi_model(self) -> np.ndarray:
        """The model's own standard parameters (inertials of the description; URDF damping and
        friction as fv and fc; armature as Ia; offset 0)."""
        phi = np.zeros(self.num_params)
        for i, j in enumerate(self.joint_ids):
            phi[10 * i:10 * i + 10] = self.model.inertias[j].toDynamicParameters()[PIN_ORDER]
        per_joint = {'fv': self.model.damping, 'fc': self.model.friction,
                     'fo': np.zeros(self.model.nv), 'Ia': self.model.armature}
        for i in range(self.dof):
            for k, e in enumerate(self.extras):
                phi[self.n_inertial + i * len(self.extras) + k] = per_joint[e][self.idx_v[i]]
        return phi

    def pinocchio_model(self, phi: np.ndarray | None = None) -> pin.Model:
        """A copy of the (reduced) pinocchio model carrying the standard parameters ``phi``
        (inertials and, when present, Ia as armature, fv as damping, fc as friction)."""
        model = self.model.copy()
        if phi is None:
            return model
        phi = self._check_phi(phi)
        for i, j in enumerate(self.joint_ids):
            model.inertias[j] = _pin_inertia(phi[10 * i:10 * i + 10], self.link_names[i])
        fields = {'Ia': 'armature', 'fv': 'damping', 'fc': 'friction'}
        for k, e in enumerate(self.extras):
            if e in fields:
                arr = np.array(getattr(model, fields[e]))
                arr[self.idx_v] = phi[self.n_inertial + k::len(self.extras)]
                setattr(model, fields[e], arr)
        return model

    def _check_phi(self, phi: np.ndarray) -> np.ndarray:
        phi = np.asarray(phi, dtype=float)
        if phi.shape != (self.num_params,):
            raise IdentificationError(
                f'parameter vector has shape {phi.shape}, expected ({self.num_params},)')
        return phi

    # -- kinematic samples ----------------------------------------------------------------------
    def check_samples(self, *arrays: np.ndarray) -> list[np.ndarray]:
        """Validate joint-space arrays: (N, n) or (n,) floats, all finite, same N."""
        out = []
        for name, a in zip(('q', 'qd', 'qdd', 'tau'), arrays):
            try:
                a = np.asarray(a, dtype=float)
            except (TypeError, ValueError):
                raise IdentificationError(f'{name} is not an array of numbers') from None
            if a.ndim == 1:
                a = a[None, :]
            if a.ndim != 2 or a.shape[1] != self.dof:
                raise IdentificationError(
                    f'{name} has shape {a.shape}; expected (N, {self.dof}) for joints '
                    f'{self.joint_names}')
            if not np.isfinite(a).all():
                k = int(np.argwhere(~np.isfinite(a))[0][0])
                raise IdentificationError(f'{name} contains NaN or inf (first at sample {k})')
            out.append(a)
        if len({a.shape[0] for a in out}) > 1:
            raise IdentificationError(
                f'sample counts differ: {[a.shape[0] for a in out]} (q, qd, qdd, tau)')
        return out

    def configuration(self, q: np.ndarray) -> np.ndarray:
        """Pinocchio configurations (N, nq) for joint positions (N, n); continuous joints
        are stored as (cos, sin)."""
        q = np.atleast_2d(q)
        if self._identity_q:   # pinocchio's configuration is the joint vector itself
            return np.ascontiguousarray(q, dtype=float)
        Q = np.tile(self._q_neutral, (q.shape[0], 1))
        plain = ~self.continuous
        Q[:, self.idx_q[plain]] = q[:, plain]
        Q[:, self.idx_q[self.continuous]] = np.cos(q[:, self.continuous])
        Q[:, self.idx_q[self.continuous] + 1] = np.sin(q[:, self.continuous])
        return Q

    def _tangent(self, x: np.ndarray) -> np.ndarray:
        if self._identity_v:
            return np.ascontiguousarray(x, dtype=float)
        V = np.zeros((x.shape[0], self.model.nv))
        V[:, self.idx_v] = x
        return V

    # -- dynamics ---------------------------------------------------------------------------------
    def regressor(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                  out: np.ndarray | None = None, *, checked: bool = False,
                  coulomb: np.ndarray | None = None) -> np.ndarray:
        """Regressor Y (N, n, p) with tau = Y @ phi, for N samples of (q, qd, qdd): pinocchio's
        ``computeJointTorqueRegressor`` per sample, mapped to this package's parameter order,
        plus the friction and rotor columns. ``checked``: the samples are (N, n) finite float
        arrays already (the pipeline's), so they are not checked again. ``coulomb`` (N, n):
        the fc columns' values instead of coulomb_column(qd) (the smoothed sign)."""
        if not checked:
            q, qd, qdd = self.check_samples(q, qd, qdd)
        N = q.shape[0]
        shape = (N, self.dof, self.num_params)
        if out is None:
            out = np.empty(shape)
        elif out.shape != shape:
            raise IdentificationError(f'out has shape {out.shape}, expected {shape}')
        ni = self.n_inertial
        Q, V, A = self.configuration(q), self._tangent(qd), self._tangent(qdd)
        model, data, flat = self.model, self.data, self._flat
        for a in range(0, N, _REGRESSOR_CHUNK):
            b = min(N, a + _REGRESSOR_CHUNK)
            # the package's rows and columns of the whole chunk picked in one take
            Ypin = joint_torque_regressors(model, data, Q[a:b], V[a:b], A[a:b])
            out[a:b, :, :ni] = Ypin.reshape(b - a, -1).take(flat, axis=1).reshape(
                b - a, self.dof, ni)
        if self.extras:
            out[:, :, ni:] = 0.0
            for e, rows, columns in self._extra_columns:
                out[:, rows, columns] = (
                    qd if e == 'fv' else qdd if e == 'Ia' else 1.0 if e == 'fo'
                    else coulomb if coulomb is not None
                    else coulomb_column(qd, self.in_joint_units(self.coulomb_velocity)))
        return out

    def inverse_dynamics(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                         phi: np.ndarray | None = None) -> np.ndarray:
        """Joint torques (N, n) = Y phi, for ``phi`` (default: the model's own parameters)."""
        phi = self.phi_model if phi is None else self._check_phi(phi)
        return self.regressor(q, qd, qdd) @ phi

    def rnea(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
             phi: np.ndarray | None = None) -> np.ndarray:
        """Joint torques (N, n) from pinocchio's recursive Newton-Euler algorithm for ``phi``
        (default: the model's own), plus the friction and rotor terms. An independent check of
        the regressor."""
        q, qd, qdd = self.check_samples(q, qd, qdd)
        model = self.pinocchio_model(phi)
        data = model.createData()
        Q, V, A = self.configuration(q), self._tangent(qd), self._tangent(qdd)
        tau = np.array([pin.rnea(model, data, Q[k], V[k], A[k])[self.idx_v]
                        for k in range(q.shape[0])])
        if phi is None:
            phi = self.phi_model
        extra = dict(zip(self.extras, np.reshape(phi[self.n_inertial:], (self.dof, -1)).T))
        armature = np.asarray(model.armature)[self.idx_v]
        tau += qdd * (extra.get('Ia', 0.0) - armature)  # rnea may already include armature
        tau += qd * extra.get('fv', 0.0) + extra.get('fo', 0.0)
        if 'fc' in extra:
            tau += extra['fc'] * coulomb_column(qd, self.in_joint_units(self.coulomb_velocity))
        return tau


def joint_torque_regressors(model: pin.Model, data: pin.Data, Q: np.ndarray, V: np.ndarray,
                            A: np.ndarray) -> np.ndarray:
    """pinocchio's ``computeJointTorqueRegressor`` of samples (Q (N, nq), V and A (N, nv)):
    (N, nv, 10 (njoints - 1)), in pinocchio's joint and parameter order. The one call of
    pinocchio's regressor (RobotModel.regressor maps it); one binding call per sample, mapped
    (no Python statement per sample)."""
    return np.array(list(map(pin.computeJointTorqueRegressor, repeat(model), repeat(data),
                             Q, V, A)))


def load_robot(robot: str | os.PathLike, joints: Sequence[str] | None = None,
               **options) -> RobotModel:
    """Build a RobotModel from a bundled name, a file path or URDF XML (see RobotModel)."""
    return RobotModel(robot, joints, **options)
