"""A payload rigidly attached to one link (or fixed frame) of the arm: its regressor and fit.

The payload's 10 standard parameters ``[m, mx, my, mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz]`` are
given in the frame F of the attachment (a link, or a fixed frame such as a tool flange), about
F's origin, as the links' (README, Conventions). They add to the inertial parameters of the
link whose joint carries F, so the payload's regressor is that link's 10 regressor columns
times the (linear) map of F's parameters into the joint frame. The payload is fitted to the
torque residual tau - Y phi_arm of an arm model, from NormalEquations. Where the arm's model
comes with its uncertainty (ArmPrior: an identified arm's base-parameter covariance), the
fit takes the arm's base regressor as further columns and solves for the payload and a
correction of the arm's base parameters together, the correction held by that prior: the
arm's error no longer leaks into the payload, and the payload's covariance includes the
arm's uncertainty. Outputs: mass (kg), centre of mass (m, in F), inertia about the centre of mass
(kg m^2, in F), with standard deviations; the quantities the motion did not excite are named
and given no value.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import pinocchio as pin

from identification_node.config import PayloadTolerance
from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import (SOLVERS, Body, ConsistencyOptions,
                                                        ConsistentSolver)
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.model.identifiability import BaseParameters
from identification_node.model.pseudo_inertia import pseudo_inertia
from identification_node.model.robot import RobotModel
from identification_node.model.urdf_export import link_inertia
from identification_node.safe_yaml import load_yaml, read_yaml

INERTIA_KEYS = ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz')
COM_KEYS = ('x', 'y', 'z')
#: the reported quantities, in the order of PayloadEstimate.values()
QUANTITIES = ('mass',) + tuple(f'com.{k}' for k in COM_KEYS) + tuple(
    f'inertia.{k}' for k in INERTIA_KEYS)
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
# Quantities with a standard deviation above these are reported "not excited" (no value).
DEFAULT_TOLERANCE = {'mass': PayloadTolerance.mass, 'com': PayloadTolerance.com,   # kg, m,
                     'inertia': PayloadTolerance.inertia}                  # kg m^2
PSEUDO_INERTIA_EPS = 1e-9   # J(phi) - eps 1 >= 0 (at most; kg m^2): consistent but free to be tiny
PAYLOAD_CONFIDENCE = 0.99   # the chi-square region in which its prior (the fit itself) chooses
# s per conic solver: a payload (10 parameters) solves in ~20 ms, on the node's processing
# thread; a failing solver must not hold it for consistency.time_limit (5 s)
PAYLOAD_TIME_LIMIT = 0.5


@dataclass(frozen=True)
class Attachment:
    """Where a payload is attached: ``link`` (a link or fixed frame of the model), the index
    of the identified joint that carries it (``joint_index``, into robot.joint_names) and the
    map ``transform`` (10, 10) from parameters in the link's frame to those in that joint's
    frame."""
    link: str
    joint_index: int
    transform: np.ndarray
    placement: pin.SE3

    @property
    def columns(self) -> np.ndarray:
        """The 10 regressor columns (standard parameter order) of the carrying link."""
        return 10 * self.joint_index + np.arange(10)


def frame_transform(placement: pin.SE3) -> np.ndarray:
    """T (10, 10) with phi_joint = T phi_frame for a body's standard parameters given in a
    frame at ``placement`` (rotation R, origin p, in the joint frame):
    m' = m, h' = R h + m p, I' = R I R' + 2 (p . R h) 1 - (R h p' + p (R h)') + m (|p|^2 1 - p p')
    (inertias about the respective origins)."""
    R, p = np.asarray(placement.rotation), np.asarray(placement.translation)
    T = np.zeros((10, 10))
    T[0, 0] = 1.0
    T[1:4, 0], T[1:4, 1:4] = p, R
    cols = np.zeros((10, 6))   # how each parameter moves the inertia's 6 entries
    cols[0] = [(p @ p) * (a == b) - p[a] * p[b] for a, b in _SYM]
    for k in range(3):
        Rh = R[:, k]
        M = 2.0 * (p @ Rh) * np.eye(3) - np.outer(Rh, p) - np.outer(p, Rh)
        cols[1 + k] = [M[a, b] for a, b in _SYM]
    for k, (c, d) in enumerate(_SYM):
        E = np.zeros((3, 3))
        E[c, d] = E[d, c] = 1.0
        M = R @ E @ R.T
        cols[4 + k] = [M[a, b] for a, b in _SYM]
    T[4:, :] = cols.T
    return T


def attachment(robot: RobotModel, link: str | None = None) -> Attachment:
    """The attachment of a payload to ``link`` (default: the last identified link); a fixed
    frame (e.g. a flange) moves with its parent joint at its placement. Unknown names, and
    frames that no identified joint moves, raise IdentificationError naming payload.link."""
    link = robot.link_names[-1] if not link else str(link).strip()
    frames = [f for f in robot.model.frames if f.name == link and f.type == pin.FrameType.BODY]
    if not frames:
        raise IdentificationError(
            f"parameter payload.link: '{link}' is not a link or fixed frame of robot "
            f"{robot.name} (links: {', '.join(robot.link_names)})")
    frame = frames[0]
    if frame.parentJoint not in robot.joint_ids:
        raise IdentificationError(
            f"parameter payload.link: '{link}' is not moved by an identified joint of robot "
            f"{robot.name}, so a payload on it changes no joint torque")
    return Attachment(link, robot.joint_ids.index(frame.parentJoint),
                      frame_transform(frame.placement), frame.placement)


def payload_regressor(attach: Attachment, Y: np.ndarray) -> np.ndarray:
    """The payload's regressor (N, n, 10), from the arm's regressor Y (N, n, p)."""
    return Y[:, :, attach.columns] @ attach.transform


@dataclass(frozen=True)
class ArmPrior:
    """What is known of the error delta = beta_true - beta_arm of the arm's base parameters
    (``base``: the arm's BaseParameters; delta multiplies the base regressor columns
    Y[..., base.base_index]), in information form: ``information`` (nb, nb) and ``vector``
    (nb,) with information @ mean = vector, in the units of the payload fit's weighted
    normal equations (inverse variances of the base parameters, SI)."""
    base: BaseParameters
    information: np.ndarray
    vector: np.ndarray

    @classmethod
    def from_covariance(cls, base: BaseParameters, covariance: np.ndarray
                        ) -> 'ArmPrior | None':
        """The prior of an estimate's base-parameter covariance (nb, nb), zero mean error;
        directions of infinite variance get no information; None when none is finite."""
        cov = np.asarray(covariance, dtype=float)
        nb = base.num_base
        if cov.shape != (nb, nb):
            raise IdentificationError(f'arm covariance of shape {cov.shape}, expected '
                                      f'({nb}, {nb}) for the robot\'s base parameters')
        known = np.isfinite(np.diag(cov)) & (np.diag(cov) > 0)
        known &= np.isfinite(cov[:, known]).all(axis=1) if known.any() else known
        if not known.any():
            return None
        info = np.zeros((nb, nb))
        info[np.ix_(known, known)] = _pinv_sym(cov[np.ix_(known, known)])
        return cls(base, info, np.zeros(nb))

    def mean(self) -> np.ndarray:
        """The prior's mean correction delta (nb,)."""
        return _pinv_sym(self.information) @ self.vector

    def updated(self, information: np.ndarray, vector: np.ndarray) -> 'ArmPrior':
        """The prior with the information of further data on delta added."""
        return ArmPrior(self.base, self.information + information, self.vector + vector)


def _scaled_eigen(A: np.ndarray, rcond: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(d, lam, V, keep): the eigen-decomposition of a symmetric positive semi-definite A
    scaled to unit diagonal (A / d d'), ``keep`` the eigenvalues above rcond x the largest
    (none when that is not positive)."""
    d = np.sqrt(np.maximum(np.diag(A), 0.0))
    d = np.where(d > 0, d, 1.0)
    lam, V = np.linalg.eigh(0.5 * (A + A.T) / np.outer(d, d))
    top = lam.max(initial=0.0)
    keep = lam > rcond * top if top > 0 else np.zeros(len(lam), dtype=bool)
    return d, lam, V, keep


def _pinv_sym(A: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """Pseudo-inverse of a symmetric positive semi-definite matrix, diagonally scaled."""
    d, lam, V, keep = _scaled_eigen(A, rcond)
    return ((V[:, keep] / lam[keep]) @ V[:, keep].T) / np.outer(d, d)


def read_arm(robot: RobotModel, estimate: str | None = None,
             base: BaseParameters | None = None) -> tuple[np.ndarray, ArmPrior | None]:
    """(the arm's standard parameters, the prior of their error): the model's own, taken as
    exact, or the ``standard_parameters`` of a saved estimate.yaml (~/save, identify --save)
    where it names the robot's parameters, with, given the arm's ``base``, the prior of its
    ``covariance`` (its base parameters must be ``base``'s, else IdentificationError)."""
    phi = robot.phi_model
    if not estimate:
        return phi, None
    doc = read_yaml(estimate, f'arm estimate {estimate}')
    given = doc.get('standard_parameters') if isinstance(doc, dict) else None
    if not isinstance(given, dict):
        raise IdentificationError(f'{estimate} has no standard_parameters mapping (an '
                                  'estimate.yaml written by the node\'s ~/save)')
    known = set(robot.param_names)
    used = 0
    for name, value in given.items():
        if name in known and isinstance(value, (int, float)) and math.isfinite(value):
            phi[robot.param_index(name)] = float(value)
            used += 1
    if used == 0:
        raise IdentificationError(f'{estimate}: no standard parameter of robot {robot.name}')
    cov = doc.get('covariance')
    names = [b.get('name') for b in doc.get('base_parameters') or () if isinstance(b, dict)]
    if base is None or cov is None or not names:
        return phi, None
    if names != list(base.names):
        raise IdentificationError(
            f'{estimate}: its base parameters are not those of robot {robot.name} with these '
            'settings (other joints or friction model): identify the arm with them')
    try:
        covariance = np.array(cov, dtype=float)
    except (TypeError, ValueError):
        raise IdentificationError(f'{estimate}: covariance is not a matrix of numbers') from None
    return phi, ArmPrior.from_covariance(base, covariance)


@dataclass
class PayloadEstimate:
    """A fitted payload: parameters ``phi`` (10, frame of ``link``, about its origin) and
    their covariance; mass (kg), com (3,) m and inertia (6,) kg m^2 about the centre of mass
    (INERTIA_KEYS order), all in the link's frame; ``stddev`` per QUANTITIES name (inf where
    not excited); ``excited`` the quantities known within tolerance; ``arm_correction``
    the fitted correction of the arm's base parameters (ArmPrior; empty without one)."""
    link: str
    phi: np.ndarray
    covariance: np.ndarray
    stddev: dict
    excited: list
    num_samples: int
    consistent: bool
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = field(default_factory=lambda: np.zeros(6))
    arm_correction: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def not_excited(self) -> list:
        return [q for q in QUANTITIES if q not in self.excited]

    def values(self) -> np.ndarray:
        return np.concatenate([[self.mass], self.com, self.inertia])

    def document(self) -> dict:
        """The ``payload`` object of the JSON output: values and stddev, null where the motion
        did not excite a quantity (named in ``not_excited``); ``fitted``: the same for every
        quantity with a finite stddev, within the tolerance or not (kg, m, kg m^2, link
        frame; null where the data do not determine it)."""
        vals = dict(zip(QUANTITIES, self.values().tolist()))

        def values(which) -> dict:
            def pick(source: dict, q: str):
                v = source[q]
                return float(v) if which(q) and math.isfinite(v) else None
            return {'mass': pick(vals, 'mass'),
                    'com': [pick(vals, f'com.{k}') for k in COM_KEYS],
                    'inertia': [pick(vals, f'inertia.{k}') for k in INERTIA_KEYS],
                    'stddev': {'mass': pick(self.stddev, 'mass'),
                               'com': [pick(self.stddev, f'com.{k}') for k in COM_KEYS],
                               'inertia': [pick(self.stddev, f'inertia.{k}')
                                           for k in INERTIA_KEYS]}}
        doc = {'link': self.link, **values(lambda q: q in self.excited),
               'excited': list(self.excited), 'not_excited': self.not_excited,
               'fitted': values(lambda q: math.isfinite(self.stddev[q])),
               'num_samples': int(self.num_samples), 'physically_consistent': self.consistent}
        if not self.excited:
            doc['status'] = 'not excited'
        return doc


def quantities(phi: np.ndarray) -> np.ndarray:
    """(mass, com (3), inertia about the com (6)) of 10 parameters about a frame's origin."""
    m, c, Ic = link_inertia(phi)
    return np.concatenate([[m], c, [Ic[a, b] for a, b in _SYM]])


def _jacobian(phi: np.ndarray) -> np.ndarray:
    """d quantities / d phi (10, 10) by central differences (smooth for m != 0)."""
    J = np.empty((10, 10))
    scale = np.maximum(np.abs(phi), 1e-6 * max(abs(phi[0]), 1e-3))
    for k in range(10):
        h = 1e-6 * scale[k]
        d = np.zeros(10)
        d[k] = h
        J[:, k] = (quantities(phi + d) - quantities(phi - d)) / (2 * h)
    return J


_NAMES = tuple(f'payload.{k}' for k in ('m', 'mx', 'my', 'mz', 'Ixx', 'Ixy', 'Ixz', 'Iyy',
                                        'Iyz', 'Izz'))


def prepare_consistency() -> None:
    """Import cvxpy and solve one payload problem (seconds, once per process): the node does
    it at start-up, not in a run."""
    rows = np.eye(10)[None]
    bad = np.r_[1.0, 0, 0, 0, -1.0, 0, 0, 0, 0, 0]
    consistent_payload(NormalEquations.from_rows(rows, rows @ bad), 1.0, bad)


def consistent_payload(ne: NormalEquations, weights: np.ndarray | float, phi: np.ndarray
                       ) -> np.ndarray:
    """The physically consistent parameters minimising the weighted data term of the
    payload's normal equations ``ne`` (10 columns, per-joint ``weights``, inverse noise
    variances): consistency.ConsistentSolver on one body with K = 1, J(x) - eps 1 >= 0 with
    eps = PSEUDO_INERTIA_EPS, Clarabel then SCS. Its log-det regulariser (default weight,
    1e-3 in chi-square units) pulls toward the least-squares fit ``phi`` itself, which the
    solver replaces by its nearest consistent pseudo-inertia (eigenvalues raised to 1e-3 of
    the largest): a weak prior of the payload's own size, where a fixed one (a sphere of the
    fitted mass) scaled the solve badly for large payloads. Its own region and no mass term
    (the arm's defaults are for a URDF prior, not for the fit itself). ``phi`` when it is
    consistent already."""
    if np.linalg.eigvalsh(pseudo_inertia(phi))[0] >= PSEUDO_INERTIA_EPS:
        return phi
    base = BaseParameters(_NAMES, np.arange(10), np.eye(10))
    status = ''
    for solver in SOLVERS:
        options = ConsistencyOptions(margin=PSEUDO_INERTIA_EPS, solver=solver, mass_ratio=0.0,
                                     confidence=PAYLOAD_CONFIDENCE, mass_weight=0.0,
                                     time_limit=PAYLOAD_TIME_LIMIT)
        result = ConsistentSolver(base, phi, [Body('payload', 0)], options).solve(ne, weights)
        if result.phi is not None:   # result.ok
            return result.phi
        status = result.status
    raise IdentificationError(f'payload consistency solve failed: {status}')


def _weights(noise_variance: np.ndarray) -> np.ndarray:
    """Per joint 1 / noise variance, 0 where the variance is not a positive number."""
    var = np.asarray(noise_variance, dtype=float)
    return np.where(np.isfinite(var) & (var > 0), 1.0 / np.maximum(var, 1e-300), 0.0)


def _eliminate_arm(G: np.ndarray, b: np.ndarray, prior: ArmPrior):
    """(S, h, delta): the payload's weighted normal equations (10) with the arm's correction
    (the further columns, held by ``prior``) eliminated, and the correction's mean given a
    payload phi."""
    C = G[:10, 10:]
    H = _pinv_sym(G[10:, 10:] + prior.information)
    hb = b[10:] + prior.vector
    S = G[:10, :10] - C @ H @ C.T
    return 0.5 * (S + S.T), b[:10] - C @ H @ hb, lambda phi: H @ (hb - C.T @ phi)


def arm_information(ne: NormalEquations, noise_variance: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(information, vector) that normal equations of the payload's and then the arm's base
    columns (a span of constant payload) bring on the arm's correction, the payload
    eliminated: ArmPrior.updated's arguments."""
    G, b, _ = ne.combined(_weights(noise_variance))
    P = _pinv_sym(G[:10, :10], 1e-10)
    C = G[10:, :10]
    info = G[10:, 10:] - C @ P @ C.T
    return 0.5 * (info + info.T), b[10:] - C @ P @ b[:10]


def fit_payload(ne: NormalEquations, noise_variance: np.ndarray, link: str,
                tolerance: Mapping[str, float] | None = None, rcond: float = 1e-10,
                prior: ArmPrior | None = None) -> PayloadEstimate:
    """The payload from the normal equations of residual = Y_payload phi (10 columns, then
    the arm's base columns where ``prior`` is given: their correction is fitted with it,
    and the payload's covariance includes the arm's uncertainty; further columns without
    a prior are left out), each joint weighted by 1 / its (long-run) noise variance (N m)^2.
    Directions of the parameter space the data do not determine get no information
    (covariance inf there); a quantity is ``excited`` when its standard deviation is at most
    ``tolerance`` (DEFAULT_TOLERANCE: 'mass' kg, 'com' m, 'inertia' kg m^2). Never NaN: no
    data gives nothing excited."""
    tol = dict(DEFAULT_TOLERANCE, **(tolerance or {}))
    arm = 0 if prior is None else prior.base.num_base
    if ne.num_params < 10 or (prior is not None and ne.num_params != 10 + arm):
        raise IdentificationError(f'payload normal equations need {10 + arm} columns, got '
                                  f'{ne.num_params}')
    G, b, c = ne.combined(_weights(noise_variance))
    correction = None
    if prior is not None:
        G, b, correction = _eliminate_arm(G, b, prior)
    G, b = G[:10, :10], b[:10]
    payload_ne = NormalEquations(np.block([[G, b[:, None]], [b[None], np.array([[c]])]])[None],
                                 np.array([ne.count.max(initial=0)]))
    d, lam, V, keep = _scaled_eigen(G, rcond)
    Vk, Vn = V[:, keep], V[:, ~keep]
    cov_s = (Vk / lam[keep]) @ Vk.T
    phi_ls = (cov_s @ (b / d)) / d
    cov = cov_s / np.outer(d, d)
    if not keep.any() or phi_ls[0] <= 0:
        # no data, or a fitted mass that is not positive: the nearest body is none (and the
        # conic solvers, which often fail on such a fit, are not worth their time)
        phi = np.zeros(10)
    else:
        try:
            phi = consistent_payload(payload_ne, 1.0, phi_ls)
        except IdentificationError:   # the solvers failed: the least-squares fit
            phi = phi_ls
    consistent = not phi.any() or bool(np.linalg.eigvalsh(pseudo_inertia(phi))[0] > 0)
    stddev = dict.fromkeys(QUANTITIES, math.inf)

    def determined(g: np.ndarray) -> bool:   # g: a gradient in the scaled coordinates
        return not (Vn.shape[1] and np.linalg.norm(Vn.T @ g) > 1e-6 * np.linalg.norm(g))
    if keep.any() and determined(np.eye(10)[0] / d):
        # the mass is linear in phi: known also where it is nil (a detach)
        stddev['mass'] = float(np.sqrt(max(cov[0, 0], 0.0)))
    if keep.any() and phi[0] > 3.0 * stddev['mass']:
        # the centre of mass and inertia only where the mass is known to be positive
        Jq = _jacobian(phi)
        for i, q in enumerate(QUANTITIES[1:], 1):
            if determined(Jq[i] / d):     # not on an undetermined direction
                stddev[q] = float(np.sqrt(max(Jq[i] @ cov @ Jq[i], 0.0)))
    group = {'mass': 'mass', 'com': 'com', 'inertia': 'inertia'}
    excited = [q for q in QUANTITIES if stddev[q] <= tol[group[q.split('.')[0]]]]
    # the centre of mass means nothing without the mass, the inertia nothing without both
    if 'mass' not in excited:
        excited = []
    if any(f'com.{k}' not in excited for k in COM_KEYS):
        excited = [q for q in excited if not q.startswith('inertia.')]
    vals = quantities(phi) if phi[0] > 0 else np.zeros(10)
    return PayloadEstimate(link, phi, cov, stddev, excited, int(ne.count.max(initial=0)),
                           consistent, float(vals[0]), vals[1:4], vals[4:],
                           np.zeros(0) if correction is None else correction(phi))


def payload_parameters(mass: float, com: Sequence[float] | np.ndarray,
                       inertia: Sequence[float] | np.ndarray) -> np.ndarray:
    """10 parameters about the frame origin from mass (kg), com (3,) m and the inertia about
    the com (6,) kg m^2 (INERTIA_KEYS order): a user-given payload."""
    c = np.asarray(com, dtype=float)
    Ic = np.asarray(inertia, dtype=float)
    if not (math.isfinite(mass) and mass >= 0 and c.shape == (3,) and Ic.shape == (6,)
            and np.isfinite(c).all() and np.isfinite(Ic).all()):
        raise IdentificationError('a payload needs mass >= 0 (kg), com (3 values, m) and '
                                  'inertia (6 values ixx ixy ixz iyy iyz izz, kg m^2), finite')
    Icom = np.empty((3, 3))
    for k, (a, b) in enumerate(_SYM):
        Icom[a, b] = Icom[b, a] = Ic[k]
    Io = Icom + mass * (c @ c * np.eye(3) - np.outer(c, c))
    return np.concatenate([[mass], mass * c, [Io[a, b] for a, b in _SYM]])


def given_payload(link: str, phi: np.ndarray) -> PayloadEstimate:
    """A payload known exactly (e.g. set by a user): everything 'excited', stddev 0."""
    vals = quantities(phi) if phi[0] > 0 else np.zeros(10)
    return PayloadEstimate(link, np.asarray(phi, float), np.zeros((10, 10)),
                           dict.fromkeys(QUANTITIES, 0.0), list(QUANTITIES), 0,
                           bool(np.linalg.eigvalsh(pseudo_inertia(phi))[0] >= 0),
                           float(vals[0]), vals[1:4], vals[4:])


def with_payload(robot: RobotModel, attach: Attachment, phi_arm: np.ndarray,
                 payload: np.ndarray) -> np.ndarray:
    """The arm's standard parameters with the payload (10, attachment frame) added to the
    carrying link."""
    phi = np.array(phi_arm, dtype=float)
    phi[attach.columns] += attach.transform @ np.asarray(payload, dtype=float)
    return phi


@dataclass(frozen=True)
class PayloadChange:
    """A payload attached to ``link`` from ``time`` (s) on, replacing any before it; mass 0:
    none (detached). com (m, link frame), inertia about the com (6, kg m^2)."""
    time: float
    link: str | None
    mass: float
    com: tuple = (0.0, 0.0, 0.0)
    inertia: tuple = (0.0,) * 6

    def parameters(self) -> np.ndarray:
        return payload_parameters(self.mass, self.com, self.inertia)

    def document(self) -> dict:
        return {'time': self.time, 'link': self.link, 'mass': self.mass,
                'com': list(self.com), 'inertia': list(self.inertia)}


def read_payload_changes(spec: str) -> list[PayloadChange]:
    """Payload events from a YAML file or an inline YAML list of mappings ``{time: s, mass:
    kg, com: [x, y, z], inertia: [ixx, ixy, ixz, iyy, iyz, izz], link: L}`` (com, inertia
    and link optional: a point mass on the last identified link; mass 0: detach)."""
    import os
    text = str(spec)
    what = f'payload events {spec!r}'
    data = read_yaml(text, what) if os.path.isfile(text) else load_yaml(text, what)
    if isinstance(data, dict):
        data = [data]
    if not isinstance(data, list):
        raise IdentificationError(f'payload events {spec!r}: expected a list of mappings')
    out = []
    for k, item in enumerate(data):
        if not isinstance(item, dict) or 'time' not in item or set(item) - {
                'time', 'mass', 'com', 'inertia', 'link'}:
            raise IdentificationError(f'payload event {k}: {item!r} needs time (s) and may '
                                      'have mass, com, inertia, link only')
        try:
            change = PayloadChange(float(item['time']), item.get('link'),
                                   float(item.get('mass', 0.0)),
                                   tuple(float(v) for v in item.get('com', (0, 0, 0))),
                                   tuple(float(v) for v in item.get('inertia', (0,) * 6)))
            change.parameters()
        except (TypeError, ValueError, IdentificationError) as exc:
            raise IdentificationError(f'payload event {k}: {exc}') from None
        if not (math.isfinite(change.time) and change.time >= 0):
            raise IdentificationError(f'payload event {k}: time must be >= 0 s')
        out.append(change)
    return sorted(out, key=lambda c: c.time)


def true_parameter_changes(robot: RobotModel, phi_arm: np.ndarray,
                           changes: Sequence[PayloadChange]) -> list[tuple[float, np.ndarray]]:
    """(time, the arm's true standard parameters with that payload) for a simulated arm."""
    out = []
    for c in changes:
        phi = np.array(phi_arm, dtype=float)
        if c.mass > 0:
            phi = with_payload(robot, attachment(robot, c.link), phi, c.parameters())
        out.append((c.time, phi))
    return out


PAYLOAD_LINK = 'payload'


def urdf_with_payload(urdf: str, estimate: PayloadEstimate, name: str = PAYLOAD_LINK) -> str:
    """``urdf`` with the payload as a link ``name`` on a fixed joint ``<name>_joint`` at the
    origin of its link (or frame): <inertial> at the centre of mass, the inertia about it
    (the consistent fit's values, also where not excited; none without a positive mass)."""
    import xml.etree.ElementTree as ET
    root = ET.fromstring(urdf)
    if root.find(f"link[@name='{name}']") is not None:
        raise IdentificationError(f'the robot description has a link {name!r} already')
    link = ET.SubElement(root, 'link', name=name)
    m, c, Ic = link_inertia(estimate.phi)
    if m > 0:
        inertial = ET.SubElement(link, 'inertial')
        ET.SubElement(inertial, 'origin', xyz=' '.join(f'{v:.9g}' for v in c), rpy='0 0 0')
        ET.SubElement(inertial, 'mass', value=f'{m:.9g}')
        ET.SubElement(inertial, 'inertia', {
            k: f'{Ic[a, b]:.9g}' for k, (a, b) in zip(INERTIA_KEYS, _SYM)})
    joint = ET.SubElement(root, 'joint', name=f'{name}_joint', type='fixed')
    ET.SubElement(joint, 'parent', link=estimate.link)
    ET.SubElement(joint, 'child', link=name)
    ET.SubElement(joint, 'origin', xyz='0 0 0', rpy='0 0 0')
    ET.indent(root, space='  ')
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding='unicode') + '\n'
