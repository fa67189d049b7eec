"""Self-collision and environment distances of a robot, from its URDF collision geometry.

pinocchio's collision support (coal): the URDF's ``<collision>`` elements are attached to the
identified joints of the RobotModel (its reduced model: geometry on locked links rides on
their parent), every pair of geometries on different joints is checked except pairs on
joints adjacent in the chain (parent and child, which touch at the joint by design), pairs
an SRDF disables (MoveIt ``<disable_collisions>``), and geometry fixed to the world against
the environment. The environment: an optional floor (a half space, z >= height in the world
frame) and boxes (size, centre xyz, rpy, world frame). Distances in m, signed (negative when
penetrating); joint arrays in the robot's joint order.

Meshes cost most of the time (GJK on bounding-volume trees): :meth:`CollisionChecker.hulls` is
the same checker with every mesh replaced by its convex hull (coal, Qhull), tens of times
faster. A hull contains its mesh, so hull distances are lower bounds of the exact ones: the
excitation optimiser's constraints use them (conservative), and :meth:`CollisionChecker.clearance`
computes the exact (mesh) distance only of the pairs and samples whose hull bound could be the
smallest. ``distances(q, within=...)`` leaves out the pairs whose bounding spheres (each
geometry's local AABB's) stay farther apart than asked, their spheres' distance standing in.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pinocchio as pin

from identification_node.config import Excitation
from identification_node.errors import IdentificationError

DEFAULT_MIN_DISTANCE = Excitation.min_distance   # m
HULL_TOLERANCE = 1e-6         # m: GJK's tolerance, allowed between a hull bound and the mesh


def has_collision_geometry(robot) -> bool:
    """Whether the robot's description (URDF) has any <collision> element."""
    return robot.kind == 'urdf' and '<collision' in robot.description


class CollisionChecker:
    """Distances between the checked geometry pairs of ``robot`` (a RobotModel from a URDF).

    ``package_dirs``: directories resolving ``package://`` mesh paths; ``srdf``: an SRDF file
    whose disabled pairs are not checked; ``min_distance`` (m): the clearance required by
    :meth:`clear`; ``floor``: a height (m) or a mapping ``{height: z}``; ``boxes``: mappings
    ``{size: [x, y, z], xyz: [x, y, z], rpy: [r, p, y], name: str}`` (m, rad, world frame);
    ``convex``: every mesh replaced by its convex hull (see :meth:`hulls`).
    """

    def __init__(self, robot, package_dirs: Sequence[str | os.PathLike] = (),
                 srdf: str | os.PathLike | None = None,
                 min_distance: float = DEFAULT_MIN_DISTANCE,
                 floor: float | Mapping | None = None, boxes: Sequence[Mapping] = (),
                 convex: bool = False):
        if robot.kind != 'urdf':
            raise IdentificationError(f'robot {robot.name}: collision checking needs a URDF')
        if not (isinstance(min_distance, (int, float)) and math.isfinite(min_distance)):
            raise IdentificationError(f'min_distance must be a number (m), got {min_distance!r}')
        self.robot = robot
        self.min_distance = float(min_distance)
        self.model = robot.model
        dirs = [str(d) for d in package_dirs]
        for d in dirs:
            if not Path(d).is_dir():
                raise IdentificationError(f'package directory {d} does not exist')
        try:
            geom = pin.buildGeomFromUrdfString(self.model, robot.description, pin.COLLISION,
                                               package_dirs=dirs)
        except (ValueError, RuntimeError) as exc:  # a mesh not found, a bad geometry
            raise IdentificationError(f'robot {robot.name}: collision geometry: {exc} '
                                      '(--package-dir resolves package:// paths)') from None
        self.robot_geometries = len(geom.geometryObjects)
        self.meshes = _mesh_objects(geom)
        self.convex = bool(convex)
        if convex:
            _to_hulls(geom, self.meshes)
        self._hulls = self if convex or not self.meshes else None
        self._args = (robot, dirs, srdf, self.min_distance, floor, boxes)
        self.srdf = srdf   # None: every pair on non-adjacent joints is checked
        geom.addAllCollisionPairs()   # every pair on different joints
        parents = self.model.parents
        # index pairs first: the elements of geom.collisionPairs refer into its vector
        for i, k in [(p.first, p.second) for p in geom.collisionPairs]:
            a = geom.geometryObjects[i].parentJoint
            b = geom.geometryObjects[k].parentJoint
            if parents[a] == b or parents[b] == a:
                geom.removeCollisionPair(pin.CollisionPair(i, k))
        if srdf is not None:
            try:
                text = Path(srdf).read_text()
            except (OSError, UnicodeDecodeError) as exc:
                raise IdentificationError(f'cannot read SRDF {srdf}: {exc}') from None
            before = len(geom.collisionPairs)
            try:
                pin.removeCollisionPairsFromXML(self.model, geom, text)
            except (ValueError, RuntimeError) as exc:
                raise IdentificationError(f'SRDF {srdf}: {exc}') from None
            self.srdf_removed = before - len(geom.collisionPairs)
        else:
            self.srdf_removed = 0
        robot_objects = list(range(self.robot_geometries))
        for obstacle in _obstacles(floor, boxes):
            index = geom.addGeometryObject(obstacle)
            for k in robot_objects:
                if geom.geometryObjects[k].parentJoint != 0:
                    geom.addCollisionPair(pin.CollisionPair(k, index))
        self.geometry = geom
        self.geometry_data = pin.GeometryData(geom)
        self.data = self.model.createData()
        self.pairs = [(geom.geometryObjects[p.first].name, geom.geometryObjects[p.second].name)
                      for p in geom.collisionPairs]
        self._own = {geom.geometryObjects[k].name for k in robot_objects}
        self._objects = np.array([[p.first, p.second] for p in geom.collisionPairs],
                                 dtype=int).reshape(-1, 2)
        self._joints = np.array([[geom.geometryObjects[int(i)].parentJoint for i in pair]
                                 for pair in self._objects], dtype=int).reshape(-1, 2)
        self._moving = sorted(set(self._joints.ravel().tolist()) - {0})   # the pairs' joints
        self._active = np.ones(self.num_pairs, dtype=bool)   # geometry_data's flags
        self._spheres: tuple[np.ndarray, np.ndarray, np.ndarray, list[int]] | None = None
        self._probe: tuple[Any, Any] | None = None   # closest_pair's own data

    @property
    def num_pairs(self) -> int:
        return len(self.pairs)

    def always_close(self, lower: np.ndarray, upper: np.ndarray, samples: int = 200,
                     seed: int = 0) -> list[tuple[str, str]]:
        """The pairs closer than min_distance in every one of ``samples`` random joint
        positions within [lower, upper] (n,) (rad, m): in contact by design, so no motion
        meets the constraint (the hulls' bounds first, the exact distances of the pairs they
        leave)."""
        if not self.num_pairs:
            return []
        q = np.random.default_rng(seed).uniform(lower, upper, size=(samples, self.robot.dof))
        close = np.flatnonzero((self.hulls().distances(q) < self.min_distance).all(axis=0))
        if len(close) and self.hulls() is not self:
            exact = self.distances(q[:20])[:, close]
            close = close[(exact < self.min_distance).all(axis=0)]
        return [self.pairs[i] for i in close]

    def self_pair(self, pair: tuple[str, str] | None) -> bool:
        """Whether a pair of :meth:`clearance` is two of the robot's own geometries."""
        return pair is not None and set(pair) <= self._own

    def hulls(self) -> CollisionChecker:
        """This checker with every mesh replaced by its convex hull (itself when it has no
        mesh or is that already): same pairs and obstacles, distances <= the exact ones."""
        if self._hulls is None:
            self._hulls = CollisionChecker(*self._args, convex=True)
        return self._hulls

    def distances(self, q: np.ndarray, within: np.ndarray | float | None = None) -> np.ndarray:
        """Signed distances (N, pairs) in m for joint positions q (N, n). With ``within`` (m,
        per pair or one for all), a pair whose geometries' bounding spheres are farther apart
        than that at a sample is not computed there: the spheres' distance, a lower bound of
        its distance above ``within``, stands in."""
        Q = self.robot.configuration(np.atleast_2d(q))
        model, data, geom, gdata = self.model, self.data, self.geometry, self.geometry_data
        if within is None:
            self._activate(np.ones(self.num_pairs, dtype=bool))
            return self._every_pair(Q, data, gdata)
        out = np.empty((Q.shape[0], self.num_pairs))
        results = gdata.distanceResults
        for k in range(Q.shape[0]):
            pin.forwardKinematics(model, data, Q[k])
            bound = self._sphere_bounds()[0]
            near = ~(bound > within)
            self._activate(near)
            pin.updateGeometryPlacements(model, data, geom, gdata)
            pin.computeDistances(geom, gdata)
            out[k] = bound
            out[k, near] = [results[int(i)].min_distance for i in np.flatnonzero(near)]
        return out

    def _every_pair(self, Q: np.ndarray, data, gdata) -> np.ndarray:
        """Distances (N, pairs) of every active pair at pinocchio configurations Q (N, nq),
        on ``data`` and ``gdata`` (GJK warm-starts from what they computed last)."""
        out = np.empty((Q.shape[0], self.num_pairs))
        for k in range(Q.shape[0]):
            pin.computeDistances(self.model, data, self.geometry, gdata, Q[k])
            out[k] = [r.min_distance for r in gdata.distanceResults]
        return out

    def _activate(self, active: np.ndarray) -> None:
        """Set the pairs computeDistances computes (geometry_data's flags) to ``active``."""
        for i in np.flatnonzero(active != self._active):
            if active[i]:
                self.geometry_data.activateCollisionPair(int(i))
            else:
                self.geometry_data.deactivateCollisionPair(int(i))
        self._active = active.copy()

    def _bounding_spheres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
        """Per geometry object its parent joint and the centre (3,) of its local AABB's
        bounding sphere in that joint's frame; per pair the sum of its two radii (m; inf where
        one is unbounded, a floor: always computed); the joints they ride on."""
        if self._spheres is None:
            objects = self.geometry.geometryObjects
            joints = np.array([o.parentJoint for o in objects], dtype=int)
            centre, radius = np.zeros((len(objects), 3)), np.full(len(objects), np.inf)
            for k, o in enumerate(objects):
                o.geometry.computeLocalAABB()
                c, r = np.asarray(o.geometry.aabb_center), float(o.geometry.aabb_radius)
                if np.isfinite(c).all() and math.isfinite(r) and r >= 0:
                    centre[k], radius[k] = o.placement.act(c), r
            self._spheres = (joints, centre, radius[self._objects].sum(axis=1),
                             sorted({int(j) for j in joints}))
        return self._spheres

    def _sphere_bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At the joint placements in ``data`` (forward kinematics done): per pair the
        distance of its bounding spheres (m; -inf or NaN where one is unbounded), and their
        world centres (pairs, 3) on each side."""
        joints, centre, reach, used = self._bounding_spheres()
        R, p = np.zeros((self.model.njoints, 3, 3)), np.zeros((self.model.njoints, 3))
        for j in used:
            placement = self.data.oMi[j]
            R[j], p[j] = placement.rotation, placement.translation
        world = np.einsum('oij,oj->oi', R[joints], centre) + p[joints]
        a, b = world[self._objects[:, 0]], world[self._objects[:, 1]]
        return np.linalg.norm(a - b, axis=1) - reach, a, b

    def closest_pair(self, q: np.ndarray) -> tuple[float, tuple[str, str] | None]:
        """The smallest distance (m) over the pairs at one pose q (n,) and its pair (inf and
        None without pairs). Computed on data of its own: GJK's warm starts of the other
        methods (which the optimiser's path follows) are left as they were."""
        if not self.num_pairs:
            return math.inf, None
        if self._probe is None:
            self._probe = (self.model.createData(), pin.GeometryData(self.geometry))
        d = self._every_pair(self.robot.configuration(np.atleast_2d(q)), *self._probe)[0]
        i = int(np.argmin(d))
        return float(d[i]), self.pairs[i]

    def pair_distances(self, q: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """Signed distances (len(pairs),) in m of the pairs ``pairs`` (indices) at the joint
        positions q (n,)."""
        Q = self.robot.configuration(np.atleast_2d(q))[0]
        pin.updateGeometryPlacements(self.model, self.data, self.geometry, self.geometry_data, Q)
        return np.array([pin.computeDistance(self.geometry, self.geometry_data,
                                             int(i)).min_distance for i in pairs])

    def distances_and_gradients(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (N, pairs) and their gradients in the joint positions (N, pairs, n)."""
        d = self.distances(q)
        return d, self.gradients(q, np.ones(d.shape, dtype=bool))

    def gradients(self, q: np.ndarray, which: np.ndarray,
                  within: np.ndarray | float | None = None) -> np.ndarray:
        """Gradients (N, pairs, n) of the distances in the joint positions q (N, n), where
        ``which`` (N, pairs) is true (0 elsewhere): d(distance)/dq = normal . (J_p2 - J_p1),
        J_p the Jacobian of each witness point. Only those pairs' distances are recomputed,
        at only those samples. With ``within`` (as for distances), where the bounding
        spheres' distance stands in, its gradient (the witness points their centres)."""
        Q = self.robot.configuration(np.atleast_2d(q))
        N, n, P = Q.shape[0], self.robot.dof, self.num_pairs
        grad = np.zeros((N, P, n))
        ks, ps = np.nonzero(np.asarray(which, dtype=bool).reshape(N, P))
        if not len(ks):
            return grad
        model, data, cols = self.model, self.data, self.robot.idx_v
        geom, gdata, world = self.geometry, self.geometry_data, pin.ReferenceFrame.WORLD
        M = len(ks)
        normal, points = np.empty((M, 3)), np.empty((2, M, 3))
        J = np.empty((2, M, 6, n))
        joint_J = np.zeros((model.njoints, 6, n))   # the world (0) is still
        far = np.broadcast_to(np.inf if within is None else within, (P,))
        bounds = np.searchsorted(ks, np.arange(N + 1))
        for k in np.flatnonzero(np.diff(bounds)):   # only the calls into pinocchio per entry
            pin.updateGeometryPlacements(model, data, geom, gdata, Q[k])
            pin.computeJointJacobians(model, data, Q[k])
            for j in self._moving:
                joint_J[j] = pin.getJointJacobian(model, data, j, world)[:, cols]
            es = np.arange(bounds[k], bounds[k + 1])
            stand_in = np.zeros(len(es), dtype=bool)
            if within is not None:
                bound, a, b = self._sphere_bounds()
                stand_in = bound[ps[es]] > far[ps[es]]
                e, i = es[stand_in], ps[es[stand_in]]
                u = b[i] - a[i]
                normal[e] = u / np.linalg.norm(u, axis=1)[:, None]
                points[0, e], points[1, e] = a[i], b[i]
            for e in es[~stand_in]:
                r = pin.computeDistance(geom, gdata, int(ps[e]))
                normal[e] = r.normal
                points[0, e], points[1, e] = r.getNearestPoint1(), r.getNearestPoint2()
            J[:, es] = joint_J[self._joints[ps[es]].T]
        # velocity of the world point p carried by each side's joint: v + w x p
        Jp = J[:, :, :3] - np.cross(points[:, :, :, None], J[:, :, 3:], axisa=2, axisb=2,
                                    axisc=2)
        grad[ks, ps] = np.einsum('mi,min->mn', normal, Jp[1] - Jp[0])
        return grad

    def clearance(self, q: np.ndarray, bounds: tuple[np.ndarray, np.ndarray, np.ndarray]
                  | None = None) -> dict[str, Any]:
        """The smallest distance over samples q (N, n) and where: {'distance': m, 'pair':
        (name, name), 'sample': index}; distance inf when no pair is checked. With meshes,
        their exact distance is computed only where the hulls' lower bound does not rule the
        pair and sample out (branch and bound over the bounds in increasing order).
        ``bounds``: (sample indices, pair indices, the hulls' distances there), the only
        (sample, pair) entries considered; default every pair at every sample."""
        q = np.atleast_2d(q)
        if bounds is None:
            if not self.num_pairs or len(q) == 0:
                return {'distance': math.inf, 'pair': None, 'sample': None}
            d = self.hulls().distances(q)
            ks, ps = (a.ravel() for a in np.indices(d.shape))
            bound = d.ravel()
        else:
            ks, ps, bound = (np.asarray(a).ravel() for a in bounds)
        if not bound.size:
            return {'distance': math.inf, 'pair': None, 'sample': None}
        if self.hulls() is self:   # the bounds are the exact distances
            j = int(np.argmin(bound))
            return {'distance': float(bound[j]), 'pair': self.pairs[ps[j]], 'sample': int(ks[j])}
        Q = self.robot.configuration(q)
        best, where = math.inf, (0, 0)
        for j in np.argsort(bound):
            if bound[j] - HULL_TOLERANCE >= best:
                break
            k, i = int(ks[j]), int(ps[j])
            pin.updateGeometryPlacements(self.model, self.data, self.geometry,
                                         self.geometry_data, Q[k])
            d = pin.computeDistance(self.geometry, self.geometry_data, i).min_distance
            if d < best:
                best, where = d, (k, i)
        return {'distance': float(best), 'pair': self.pairs[where[1]], 'sample': where[0]}

    def summary(self) -> dict:
        """Plain data for YAML: pairs checked, SRDF-disabled count, minimum distance."""
        return {'pairs': self.num_pairs, 'robot_geometries': self.robot_geometries,
                'srdf_disabled': self.srdf_removed, 'min_distance': self.min_distance}


def _mesh_objects(geom) -> list[int]:
    """Indices of the geometry objects that are meshes (bounding-volume trees)."""
    import coal
    return [k for k, o in enumerate(geom.geometryObjects)
            if isinstance(o.geometry, coal.BVHModelBase)]


def _to_hulls(geom, meshes: Sequence[int]) -> None:
    """Replace the meshes ``meshes`` of ``geom`` by their convex hulls, in place; a mesh whose
    hull Qhull cannot build (flat or degenerate) stays as it is (exact, only slower)."""
    for k in meshes:
        obj = geom.geometryObjects[k]
        mesh = obj.geometry
        try:
            mesh.buildConvexHull(True, 'Qt')
        except (ValueError, RuntimeError):
            continue
        obj.geometry = mesh.convex


def _vector(where: str, value: Any, size: int) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        v = np.array([])
    if v.shape != (size,) or not np.all(np.isfinite(v)):
        raise IdentificationError(f'{where} must be {size} finite numbers, got {value!r}')
    return v


def _obstacles(floor: float | Mapping | None, boxes: Sequence[Mapping]) -> list:
    import coal
    out = []
    if floor is not None:
        height = floor.get('height', 0.0) if isinstance(floor, Mapping) else floor
        if isinstance(height, bool) or not isinstance(height, (int, float)) \
                or not math.isfinite(height):
            raise IdentificationError(f'floor height must be a number (m), got {floor!r}')
        # the solid half space n.x <= d, n = +z: everything below the floor's height
        out.append(pin.GeometryObject('floor', 0, 0, pin.SE3.Identity(),
                                      coal.Halfspace(np.array([0.0, 0.0, 1.0]),
                                                     float(height))))
    if not isinstance(boxes, (list, tuple)):
        raise IdentificationError(f'boxes must be a list of {{size, xyz, rpy}}, got {boxes!r}')
    for k, box in enumerate(boxes):
        if not isinstance(box, Mapping) or 'size' not in box:
            raise IdentificationError(f'box {k}: expected a mapping with size, xyz, rpy')
        unknown = set(box) - {'size', 'xyz', 'rpy', 'name'}
        if unknown:
            raise IdentificationError(f'box {k}: unknown keys {sorted(map(str, unknown))}')
        size = _vector(f'box {k} size', box['size'], 3)
        if not np.all(size > 0):
            raise IdentificationError(f'box {k} size must be > 0, got {box["size"]!r}')
        xyz = _vector(f'box {k} xyz', box.get('xyz', [0, 0, 0]), 3)
        rpy = _vector(f'box {k} rpy', box.get('rpy', [0, 0, 0]), 3)
        placement = pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)
        out.append(pin.GeometryObject(str(box.get('name', f'box{k}')), 0, 0, placement,
                                      coal.Box(*size)))
    return out
