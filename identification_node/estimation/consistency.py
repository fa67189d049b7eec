"""Physically consistent estimates: the data's confidence region, then the prior inside it.

The data determine the base parameters beta = K phi (identifiability): the unconstrained
weighted least squares gives their centre c and information G (chi-square units when the
weights w_j are the inverse noise variances). The solve looks for the full standard parameters
phi (robot.py's order) minimising

    sum_i [d(J_i || J0_i) + w |m_i / m0_i - 1|] + sum_k ((x_k - x0_k) / s_k)^2 + t / gamma
    subject to  (K phi - c)' G_f (K phi - c) <= q + f + t,  t >= 0

(the prior, then the excess), and, per body i (an identified link with what is merged into
it), its own pseudo-inertia J_i - eps_i 1 >= 0 (Wensing, Kim and Slotine 2017: mass > 0,
inertia about the centre of mass positive definite, triangle inequalities), optional mass
bounds (absolute, a ratio to the description's, the total) and a box for its centre of mass,
and fv, fc, Ia >= 0 for the per-joint columns x. J is a block's pseudo-inertia
(model/pseudo_inertia.py). d is the log-det (Bregman) divergence of Lee, Wensing and Park 2020,
d(J || J0) = -log det(J0^-1 J) + tr(J0^-1 J) - 4, toward the description's own inertials. The
data never determine a link's mass alone, only combinations with its neighbours' masses and
first moments; d alone spreads a change of such a combination over every link in it, moving
light links the wrong way. The L1 term (``mass_weight`` w, of the description's masses m0_i)
moves as few masses as the data need. q is
the chi-square quantile of the stated ``confidence`` level with as many degrees of freedom as
the data determine, and f the chi-square of the best physically consistent fit (a first solve
with q = f = 0: its excess t): among the bodies the data cannot tell apart from their best
physical fit (a likelihood-ratio region), the one closest to the description. When the
unconstrained fit is physical, f = 0 and the region is the data's about it. Without f, a
recording whose region about the unconstrained fit held no physical body, or a sliver of
them (noise alone does that), left the prior no room: the solve followed the noise, and link
masses the data do not determine went to their bounds. That prior does not fade as the
recording grows: the region shrinks, and the prior still chooses inside it. The excess t
left in the second solve is the solver's tolerance; in the first, 1/gamma per unit of
chi-square makes it the best fit, with the prior of weight gamma to break ties. G_f is G with each
direction's variance floored at ``STDDEV_FLOOR`` of its parameters' typical size (from the
prior): noise-free data would ask the solver for a resolution below its tolerance. A body's own
part excludes the links of locked joints merged into it (``fixed`` F, e.g. a hand's fingers):
they are s_i F, s_i > 0 a variable of the solve with the divergence d(s_i J_F || J_F) beside
d(J_i || J0_i), so a link lighter than its description's locked parts alone stays reachable;
the split is model/pseudo_inertia.py's ``locked_scale``, which the exported URDF writes.

Solved by cvxpy on a parametrised problem built once (re-solving with new normal equations,
the node at every refresh, skips the canonicalisation): the configured solver, then the other
conic one (Clarabel, SCS) when it fails. A solution within the solver's tolerance is projected
onto the feasible set (eigenvalues raised to the margin, then re-checked). When both fail, the
unconstrained estimate projected onto physical bodies is given, marked ``method``
'projection'. The result says which path was taken; ``ok`` false only when nothing gave a
consistent estimate (the caller then keeps the unconstrained one and says so as an error).
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from identification_node.config import Consistency, default
from identification_node.errors import IdentificationError
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.model.identifiability import BaseParameters
from identification_node.model.pseudo_inertia import (FROM_J, from_pseudo_inertia, locked_scale,
                                                      pseudo_inertia, regularised, repaired)

NOTE_LEVEL = 0.99          # a consistent estimate beyond this region of the data is reported
STDDEV_FLOOR = 1e-5        # relative: the region's resolution, of a parameter's typical size
EXTRA_SCALE = 1e-2         # s_k floor of the per-joint columns' regulariser (SI)
NONNEGATIVE = ('fv', 'fc', 'Ia')
SOLVERS = ('CLARABEL', 'SCS')
PROJECTION = 'projection'   # method of the last resort


@dataclass(frozen=True)
class Body:
    """One rigid body of the solve: its 10 columns start at ``start`` in phi. ``fixed``: the
    standard parameters (10,) of the locked bodies merged into it, at their description's
    inertials (scaled in the solve: pseudo_inertia.locked_scale; its own part is the rest);
    ``mass`` (lo, hi) bounds and ``com_box`` ((3,) lo, (3,) hi, m, in the body frame) apply to
    the whole body (own part plus fixed)."""
    name: str
    start: int
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(10))
    mass: tuple[float, float] | None = None
    com_box: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class ConsistentEstimate:
    """Outcome of a solve: ``phi`` the standard parameters, ``theta`` = K phi the base
    estimate and ``stddev`` its standard deviations from the data's information (the
    unconstrained ones; inf where undetermined); None for phi and theta when nothing gave a
    consistent estimate. ``status``: 'optimal' (a conic solver's, projected within its
    tolerance), 'projected' (both solvers failed: the unconstrained estimate projected onto
    physical bodies), or why it failed ('time_limit', 'infeasible', 'solver_error: ...');
    ``method`` the path that gave phi (a solver's name, 'projection', '' when none);
    ``attempts`` the failed attempts before it ('SOLVER: status'); ``solve_time`` s;
    ``notes``: adjustments made (repaired priors, projections, active bounds);
    ``best_chi_square`` the best physical fit's chi-square about the unconstrained fit (the
    region's floor), ``excess`` how far beyond the data's confidence region that is (0
    inside)."""
    status: str
    phi: np.ndarray | None
    theta: np.ndarray | None
    stddev: np.ndarray
    solve_time: float
    notes: list[str] = field(default_factory=list)
    method: str = ''
    attempts: list[str] = field(default_factory=list)
    excess: float = 0.0
    best_chi_square: float = 0.0

    @property
    def ok(self) -> bool:
        return self.phi is not None


@dataclass(frozen=True)
class ConsistencyOptions:
    """Settings of the solve (parameters ``consistency.*``). ``mass_ratio`` r > 1: each
    body's mass within [m0 / r, r m0] of the description's m0 (0: no bound); ``total_mass``
    (lo, hi) kg of the identified bodies together, or empty."""
    weight: float = Consistency.weight   # gamma: prior weight outside the confidence region
    margin: float = Consistency.margin   # eps: J - eps 1 >= 0 (kg, kg m^2)
    solver: str = Consistency.solver
    time_limit: float = Consistency.time_limit   # s per solve
    geometry_box: bool = Consistency.geometry_box   # CoM box from the URDF's shapes
    mass_min: Sequence[float] = tuple(default('consistency.mass_min'))   # per link (kg)
    mass_max: Sequence[float] = tuple(default('consistency.mass_max'))
    com_box: Sequence[float] = tuple(default('consistency.com_box'))   # 6 per link: lo, hi xyz
    confidence: float = Consistency.confidence   # chi-square level of the data's region
    mass_ratio: float = Consistency.mass_ratio   # link masses within [1/r, r] x description's
    total_mass: Sequence[float] = tuple(default('consistency.total_mass'))
    mass_weight: float = Consistency.mass_weight   # w of |m / m0 - 1| beside the log-det

    def validate(self, num_links: int | None = None) -> None:
        """IdentificationError naming the first bad setting (``consistency.<name>``)."""
        checks = [('weight', self.weight > 0, '> 0'), ('margin', self.margin > 0, '> 0'),
                  ('time_limit', self.time_limit > 0, '> 0'),
                  ('solver', self.solver in SOLVERS, f'one of {SOLVERS}'),
                  ('confidence', 0 <= self.confidence < 1, 'in [0, 1)'),
                  ('mass_ratio', self.mass_ratio == 0 or self.mass_ratio > 1, '0 or > 1'),
                  ('mass_weight', self.mass_weight >= 0, '>= 0'),
                  ('total_mass', len(self.total_mass) == 0 or (
                      len(self.total_mass) == 2 and 0 <= self.total_mass[0]
                      < self.total_mass[1]), 'empty or [lo, hi] with 0 <= lo < hi')]
        if num_links is not None:
            n = num_links
            checks += [
                ('mass_min', len(self.mass_min) in (0, n), f'empty or {n} values'),
                ('mass_max', len(self.mass_max) in (0, n), f'empty or {n} values'),
                ('com_box', len(self.com_box) in (0, 6 * n), f'empty or {6 * n} values')]
        lo = np.broadcast_to(np.asarray(self.mass_min, dtype=float), (len(self.mass_min),))
        hi = np.asarray(self.mass_max, dtype=float)
        if len(lo) and len(hi) == len(lo):
            checks.append(('mass_max', bool(np.all(hi > lo)), 'above mass_min'))
        checks.append(('mass_min', bool(np.all(lo >= 0)), '>= 0'))
        box = np.asarray(self.com_box, dtype=float).reshape(-1, 6)
        checks.append(('com_box', bool(np.all(box[:, 3:] > box[:, :3])),
                       'lo x y z below hi x y z for every link'))
        for name, ok, expected in checks:
            value = getattr(self, name)
            finite = name == 'solver' or np.isfinite(np.asarray(value, dtype=float)).all()
            if not ok or not finite:
                raise IdentificationError(
                    f'parameter consistency.{name} = {value!r} must be {expected}')


class ConsistentSolver:
    """The constrained solve for standard parameters ``param_names`` with base map ``base``
    (K), prior ``phi_prior`` (the description's own), rigid ``bodies`` and the per-joint
    columns (every column in no body; named ``<joint>.<fv|fc|fo|Ia>``). Build it once and call
    ``solve`` with each new set of normal equations (base-parameter order)."""

    def __init__(self, base: BaseParameters, phi_prior: np.ndarray, bodies: Sequence[Body],
                 options: ConsistencyOptions | None = None):
        import cvxpy as cp

        self.options = options or ConsistencyOptions()
        self.options.validate()
        self.base, self.bodies = base, list(bodies)
        p, b = base.num_params, base.num_base
        phi_prior = np.asarray(phi_prior, dtype=float)
        if phi_prior.shape != (p,) or not np.isfinite(phi_prior).all():
            raise IdentificationError(f'prior parameters must be {p} finite values')
        self.notes: list[str] = []
        in_body = np.zeros(p, dtype=bool)
        for body in self.bodies:
            in_body[body.start:body.start + 10] = True
        self._extra = np.flatnonzero(~in_body)
        kinds = [base.param_names[k].rsplit('.', 1)[-1] for k in self._extra]
        self._nonneg = self._extra[[k in NONNEGATIVE for k in kinds]] if kinds else self._extra
        eps_opt, gamma = self.options.margin, self.options.weight
        ratio = self.options.mass_ratio

        # Scaled variables, so that the solver sees numbers of order one: per body Jt with
        # J = D Jt D (D from the prior's mass and size: J >= 0 iff Jt >= 0), the per-joint
        # columns x = x0 + s xt; the region in whitened coordinates M (K phi) - m (parameters).
        self._J = [cp.Variable((4, 4), symmetric=True, name=f'J_{b_.name}') for b_ in bodies]
        ne = len(self._extra)
        self._x = cp.Variable(ne, name='extras') if ne else None
        self._t = cp.Variable(nonneg=True, name='excess')
        self._M = cp.Parameter((b, b), name='whitening')
        self._m = cp.Parameter(b, name='whitened_centre')
        self._q = cp.Parameter(nonneg=True, name='region')
        constraints, regulariser = [], 0
        phi = np.zeros(p)
        self.eps, self._mass_bounds, masses = [], [], []
        self._own_priors: list[np.ndarray] = []   # per body: its own part's prior pseudo-inertia
        for body, Jt in zip(self.bodies, self._J):
            own_prior = phi_prior[body.start:body.start + 10] - body.fixed
            J0 = pseudo_inertia(own_prior)
            ev = np.linalg.eigvalsh(J0)
            J0, degenerate = regularised(J0, 10 * eps_opt)
            eps = eps_opt if degenerate else min(eps_opt, 1e-2 * ev[0])
            if degenerate:
                self.notes.append(f'{body.name}: the prior is not physically consistent '
                                  '(pseudo-inertia eigenvalues '
                                  + ', '.join(f'{e:.4g}' for e in ev)
                                  + '); regularised toward its nearest consistent one')
            self.eps.append(eps)
            m0 = J0[3, 3]
            size = np.sqrt(max(np.linalg.eigvalsh(J0[:3, :3])[-1], 1e-12 * m0) / m0)
            D = np.sqrt(m0) * np.diag([size, size, size, 1.0])
            Dinv2 = np.diag(1.0 / np.diag(D) ** 2)
            constraints.append(Jt >> eps * Dinv2)
            regulariser += -cp.log_det(Jt) + cp.trace((D @ np.linalg.inv(J0) @ D) @ Jt)
            total = FROM_J @ cp.vec(D @ Jt @ D, order='C')
            self._own_priors.append(J0)
            if body.fixed[0] > 0:   # the locked bodies' share s F: d(s J_F || J_F) (+ 4)
                share = cp.Variable(nonneg=True, name=f'locked_{body.name}')
                regulariser += 4 * (share - cp.log(share))
                total = total + share * body.fixed
            masses.append(total[0])
            S = np.zeros((p, 10))
            S[body.start:body.start + 10] = np.eye(10)
            phi = phi + S @ total
            lo, hi = body.mass if body.mass is not None else (0.0, np.inf)
            whole = phi_prior[body.start]
            if self.options.mass_weight and whole > 0:
                regulariser += self.options.mass_weight * cp.abs(total[0] / whole - 1)
            if ratio and whole > 0:
                lo, hi = max(lo, whole / ratio), min(hi, whole * ratio)
            self._mass_bounds.append((lo, hi))
            if lo > 0:
                constraints.append(total[0] >= lo)
            if np.isfinite(hi):
                constraints.append(total[0] <= hi)
            if body.com_box is not None:
                com_lo, com_hi = body.com_box
                constraints += [total[1:4] >= total[0] * com_lo, total[1:4] <= total[0] * com_hi]
        if len(self.options.total_mass) and masses:
            lo, hi = self.options.total_mass
            constraints += [sum(masses) >= lo, sum(masses) <= hi]
        if self._x is not None:
            x0 = phi_prior[self._extra]
            scale = np.maximum(np.abs(x0), EXTRA_SCALE)
            x = x0 + cp.multiply(scale, self._x)
            nonneg = [i for i, k in enumerate(kinds) if k in NONNEGATIVE]
            if nonneg:
                constraints.append(x[nonneg] >= 0)
            regulariser += cp.sum_squares(self._x)
            S = np.zeros((p, ne))
            S[self._extra, np.arange(ne)] = 1.0
            phi = phi + S @ x
        self._phi: Any = phi   # a cvxpy expression (cvxpy has no type information)
        constraints.append(cp.sum_squares(self._M @ (base.K @ phi) - self._m)
                           <= self._q + self._t)
        self.problem = cp.Problem(cp.Minimize(regulariser + self._t / gamma), constraints)
        self._phi_prior = phi_prior
        # a base parameter's typical size: its terms' prior magnitudes (the floor's unit)
        self._typical = np.abs(base.K) @ np.maximum(np.abs(phi_prior), EXTRA_SCALE)
        self._solved: set[str] = set()

    @classmethod
    def for_robot(cls, robot, base: BaseParameters,
                  options: ConsistencyOptions | None = None) -> ConsistentSolver:
        """The solver for a RobotModel: one body per identified link (with its locked
        subtrees, scaled as one), the description's parameters as the prior."""
        from identification_node.estimation.prior import safe_prior

        options = options or ConsistencyOptions()
        options.validate(robot.dof)
        return cls(base, safe_prior(robot)[0], robot_bodies(robot, options), options)

    def data_factor(self, equations: NormalEquations, weights: np.ndarray | float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R (b, b), z (b,), covariance (b, b)) with sum_j w_j ||tau_j - Y_j beta||^2 =
        ||R beta - z||^2 + const, from the information's eigenvectors; the covariance is its
        pseudo-inverse, inf on the diagonal where the data determine nothing."""
        R, z, cov, _ = self._factor(equations, weights)
        return R, z, cov

    def _factor(self, equations: NormalEquations, weights: np.ndarray | float):
        if equations.num_params != self.base.num_base:
            raise IdentificationError(
                f'normal equations of {equations.num_params} parameters, expected '
                f'{self.base.num_base} base parameters')
        w = np.broadcast_to(np.asarray(weights, dtype=float), (equations.num_joints,))
        if not (np.isfinite(w).all() and (w >= 0).all()):
            raise IdentificationError('weights must be finite and >= 0')
        G, g, _ = equations.combined(w)
        if not (np.isfinite(G).all() and np.isfinite(g).all()):
            raise IdentificationError('normal equations are not finite')
        s, V = np.linalg.eigh(0.5 * (G + G.T))
        keep = s > 1e-12 * max(s[-1], 0.0) if s[-1] > 0 else np.zeros(len(s), dtype=bool)
        root = np.where(keep, np.sqrt(np.where(keep, s, 1.0)), 0.0)
        R = root[:, None] * V.T
        z = np.where(keep, (V.T @ g) / np.where(keep, root, 1.0), 0.0)
        cov = (V[:, keep] / s[keep]) @ V[:, keep].T
        var = np.diag(cov).copy()
        undetermined = np.abs(V[:, ~keep]).max(axis=1, initial=0.0) > 1e-9
        var[undetermined] = np.inf
        np.fill_diagonal(cov, var)
        return R, z, cov, (s, V, keep)

    def region(self, equations: NormalEquations, weights: np.ndarray | float = 1.0,
               model_error: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """(M (b, b), c (b,), q, covariance (b, b)): the data's confidence region
        ||M (beta - c)||^2 <= q about the unconstrained solution c, each direction's variance
        floored at (STDDEV_FLOOR x its typical size)^2 (rows of M are 0 where undetermined);
        q the chi-square quantile of ``confidence`` at the determined directions' count.
        ``model_error`` (k, b) or (b,), base-parameter offsets: the region of the covariance
        plus sum_i d_i d_i' (each a rank-one update of M'M, Sherman-Morrison)."""
        from scipy.stats import chi2

        R, z, cov, (s, V, keep) = self._factor(equations, weights)
        centre = np.linalg.lstsq(R, z, rcond=None)[0]
        floor = STDDEV_FLOOR * (np.abs(V.T) @ self._typical)
        sd = np.sqrt(1.0 / np.where(keep, s, 1.0) + floor ** 2)
        M = np.where(keep[:, None], V.T / sd[:, None], 0.0)
        for d in np.atleast_2d(model_error) if model_error is not None else ():
            v = M @ d
            size = float(v @ v)
            if size > 0 and np.isfinite(size):   # M'M becomes ((M'M)^-1 + d d')^-1
                u = v / np.sqrt(size)
                M = M - (1.0 - 1.0 / np.sqrt(1.0 + size)) * np.outer(u, u @ M)
        q = float(chi2.ppf(self.options.confidence, max(int(keep.sum()), 1)))
        return M, centre, q, cov

    def solve(self, equations: NormalEquations, weights: np.ndarray | float = 1.0,
              model_error: np.ndarray | None = None) -> ConsistentEstimate:
        """The consistent estimate for ``equations`` (base-parameter order) with per-joint
        ``weights`` (inverse noise variances: the unconstrained WLS's objective); the region
        widened by ``model_error`` (``region``)."""
        start = time.perf_counter()
        M, centre, q, cov = self.region(equations, weights, model_error)
        stddev = np.sqrt(np.diag(cov))
        self._M.value, self._m.value = M, M @ centre
        # First the best physical fit (region 0: the excess is its chi-square), then the
        # prior's choice among the bodies the data cannot tell from it (the module doc)
        self._q.value = 0.0
        phi, method, attempts = self._conic_any()
        floor = excess = 0.0
        if phi is not None:
            floor = float(np.sum((M @ (self.base.to_base(phi) - centre)) ** 2))
            excess = max(floor - q, 0.0)
            self._q.value = q + floor
            chosen, solver, more = self._conic_any()
            attempts += more
            if chosen is not None:   # else the best physical fit stands
                phi, method = chosen, solver
        notes = list(self.notes)
        if phi is None:   # the last resort: the unconstrained estimate, made physical
            phi, method = self.base.closest_standard(centre, self._phi_prior), PROJECTION
        finite = bool(np.isfinite(phi).all())
        phi, moved = self._projected(phi) if finite else (phi, [])
        problems = self.violations(phi) if finite else ['not finite']
        if problems:
            status, phi = 'infeasible_result: ' + '; '.join(problems[:3]), None
            method = ''
        else:
            status = 'projected' if method == PROJECTION else 'optimal'
            notes += moved + self.active_bounds(phi) + self.locked_notes(phi)
            if method == PROJECTION:
                notes.append('no conic solver succeeded (' + '; '.join(attempts) + '): the '
                             'unconstrained estimate projected onto physical bodies is given')
            from scipy.stats import chi2
            q_note = chi2.ppf(NOTE_LEVEL, max(int(np.any(M, axis=1).sum()), 1))
            beyond = floor - q_note
            if beyond > 1e-3 * q_note:   # not the solver's tolerance on the region's edge
                notes.append('the consistent bodies lie outside the data\'s '
                             f'{100 * NOTE_LEVEL:g} % confidence region by chi-square '
                             f'{beyond:.3g}: the data disagree with a physical arm')
        return ConsistentEstimate(status, phi, None if phi is None else self.base.to_base(phi),
                                  stddev, time.perf_counter() - start, notes, method, attempts,
                                  excess, floor)

    def _conic_any(self) -> tuple[np.ndarray | None, str, list[str]]:
        """(phi or None, the solver that gave it, the failed attempts before it): the
        configured solver, then the other conic one."""
        first = self.options.solver
        attempts: list[str] = []
        for solver in [first] + [s for s in SOLVERS if s != first]:
            status, phi = self._conic(solver)
            if phi is not None:
                return phi, solver, attempts
            attempts.append(f'{solver}: {status}')
        return None, '', attempts

    def _conic(self, solver: str) -> tuple[str, np.ndarray | None]:
        """(status, phi or None) of one conic solver on the current parameters."""
        import cvxpy as cp

        opts = {'solver': solver, 'warm_start': solver in self._solved}
        if solver == 'CLARABEL':
            opts['time_limit'] = self.options.time_limit
        else:   # first order, ~1e-5 accurate: its answers are projected (violations)
            opts['time_limit_secs'] = self.options.time_limit
            opts['eps_abs'] = opts['eps_rel'] = 1e-6
        begin = time.perf_counter()
        try:
            with warnings.catch_warnings():   # an inaccurate answer is checked below
                warnings.filterwarnings('ignore', 'Solution may be inaccurate', UserWarning)
                self.problem.solve(**opts)
            status = self.problem.status
        except (cp.error.SolverError, ValueError, ArithmeticError) as exc:
            status = f'solver_error: {exc}'
        late = time.perf_counter() - begin >= 0.5 * self.options.time_limit
        if status == cp.USER_LIMIT or (status == cp.OPTIMAL_INACCURATE and late):
            status = 'time_limit' if late else 'iteration_limit'   # it stopped early
        if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or self._phi.value is None:
            return status, None
        phi = np.asarray(self._phi.value, dtype=float).reshape(-1)
        if not np.isfinite(phi).all():
            return 'solver_error: not finite', None
        self._solved.add(solver)
        return status, phi

    def _projected(self, phi: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """``phi`` with each body's own pseudo-inertia eigenvalues raised to its margin and the
        non-negative columns clipped at 0; notes on what moved beyond rounding."""
        phi = np.array(phi, dtype=float)
        notes = []
        for k, (body, eps) in enumerate(zip(self.bodies, self.eps)):
            sl = slice(body.start, body.start + 10)
            locked = self._locked(k, phi)
            J = pseudo_inertia(phi[sl] - locked)
            ev = np.linalg.eigvalsh(J)
            if ev[0] < eps:
                phi[sl] = from_pseudo_inertia(repaired(J, eps)) + locked
                if ev[0] < -1e-9 * max(1.0, ev[-1]):
                    notes.append(f'{body.name}: pseudo-inertia eigenvalue {ev[0]:.3g} raised to '
                                 f'the margin {eps:.3g} (projection)')
        phi[self._nonneg] = np.maximum(phi[self._nonneg], 0.0)
        return phi, notes

    def _locked(self, k: int, phi: np.ndarray) -> np.ndarray:
        """Body k's locked share s F in ``phi`` (zero when nothing is locked into it)."""
        body = self.bodies[k]
        if not body.fixed[0] > 0:
            return body.fixed
        sl = slice(body.start, body.start + 10)
        return locked_scale(phi[sl], body.fixed, self._own_priors[k]) * body.fixed

    def locked_notes(self, phi: np.ndarray) -> list[str]:
        """Notes naming the bodies whose locked parts do not fit at their description's
        inertials (the own part would not be physical): the scale they are given instead."""
        out = []
        for k, body in enumerate(self.bodies):
            sl = slice(body.start, body.start + 10)
            if body.fixed[0] > 0 and np.linalg.eigvalsh(
                    pseudo_inertia(phi[sl] - body.fixed))[0] <= 0:
                s = locked_scale(phi[sl], body.fixed, self._own_priors[k])
                out.append(f'{body.name}: the locked links merged into it do not fit at their '
                           f'description\'s inertials ({body.fixed[0]:.4g} kg): scaled by '
                           f'{s:.3g}, as identified.urdf writes them')
        return out

    def active_bounds(self, phi: np.ndarray, rtol: float = 1e-4) -> list[str]:
        """Notes naming the mass bounds ``phi`` is at (within ``rtol``)."""
        out = []
        for body, (lo, hi) in zip(self.bodies, self._mass_bounds):
            m = phi[body.start]
            for bound, what in ((lo, 'lower'), (hi, 'upper')):
                if bound > 0 and np.isfinite(bound) and abs(m - bound) <= rtol * bound:
                    out.append(f'{body.name}: mass {m:.4g} kg at its {what} bound (the '
                               'data ask for more; consistency.mass_ratio, mass_min/max)')
        if len(self.options.total_mass):
            total = sum(phi[body.start] for body in self.bodies)
            for bound, what in zip(self.options.total_mass, ('lower', 'upper')):
                if abs(total - bound) <= rtol * max(bound, 1e-9):
                    out.append(f'total mass {total:.4g} kg at its {what} bound')
        return out

    def violations(self, phi: np.ndarray, tol: float = 1e-9) -> list[str]:
        """What in ``phi`` breaks the hard constraints beyond ``tol`` (empty when feasible):
        each body's own pseudo-inertia positive definite, the non-negative columns."""
        out = []
        for i, body in enumerate(self.bodies):
            J = pseudo_inertia(phi[body.start:body.start + 10] - self._locked(i, phi))
            ev = np.linalg.eigvalsh(J)
            if ev[0] <= -tol * max(1.0, ev[-1]):
                out.append(f'{body.name}: pseudo-inertia eigenvalue {ev[0]:.3g}')
        for k in self._extra:
            name = self.base.param_names[k]
            if name.rsplit('.', 1)[-1] in NONNEGATIVE and phi[k] < -tol:
                out.append(f'{name} = {phi[k]:.3g}')
        return out


def robot_bodies(robot, options: ConsistencyOptions) -> list[Body]:
    """The Bodies of a RobotModel's identified links, with the bounds of ``options``; the
    default CoM box is the bounding box of the link's collision and visual primitives (with
    what is merged into it), widened to hold the description's own centre of mass."""
    from identification_node.model.urdf_export import merged_bodies

    bodies = []
    box = np.asarray(options.com_box, dtype=float).reshape(-1, 6)
    phi = robot.phi_model
    for i, link in enumerate(robot.link_names):
        fixed, corners = merged_bodies(robot, i)
        com_box = None
        if len(box):
            com_box = box[i, :3], box[i, 3:]
        elif options.geometry_box and corners is not None:
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            m = phi[10 * i]
            if m > 0:
                c = phi[10 * i + 1:10 * i + 4] / m
                lo, hi = np.minimum(lo, c), np.maximum(hi, c)
            com_box = lo, hi
        mass = None
        if len(options.mass_min) or len(options.mass_max):
            mass = (float(options.mass_min[i]) if len(options.mass_min) else 0.0,
                    float(options.mass_max[i]) if len(options.mass_max) else np.inf)
        bodies.append(Body(link, 10 * i, fixed, mass, com_box))
    return bodies


def pipeline_equations(pipeline) -> tuple[NormalEquations, float]:
    """An IdentificationPipeline's current information: its RLS's normal equations (forgotten,
    weighted rows) and the weight that makes their information its covariance's inverse,
    1 / the mean long-run residual variance (1 while that is not known)."""
    equations = pipeline.rls.normal_equations()
    noise = float(np.mean(pipeline.noise_variance()))
    return equations, (1.0 / noise if np.isfinite(noise) and noise > 0 else 1.0)
