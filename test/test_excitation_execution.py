"""Excitations a real arm can run: ramps from and back to rest, limits with margins checked on
dense grids (torques by pinocchio's RNEA), self-collision checked with a geometry model of our
own on dense grids, the floor by the closed-form lowest point of each primitive, the
optimiser's outcome, the outputs, and identification from a simulated run, ramps included."""
import json
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml
from arms import ARMS, arm_urdf, robots_dir

from identification_node.bags.reader import BagReader, iter_messages
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.excitation.criteria import base_of, criterion_value
from identification_node.excitation import design as ex
from identification_node.excitation.initial_guess import (REST_TORQUE, initial_trajectory,
                                                          rest_pose, shrink_into_limits, to_x)
from identification_node.excitation.problem import (COLLISION_CULL_PAIRS, COLLISION_PAD,
                                                    COLLISION_SCALE, DesignProblem)
from identification_node.excitation.result import DEFAULT_LIMIT_MARGIN
from identification_node.excitation.limits import (LIMIT_KINDS, ExcitationLimits,
                                                   estimate_parameters, limit_ratios)
from identification_node.excitation.collision import CollisionChecker, has_collision_geometry
from identification_node.excitation.sampled import SampledTrajectory
from identification_node.excitation.trajectories import (FourierTrajectory, FramedTrajectory,
                                                         load_trajectory, match_joints)
from identification_node.model.robot import load_robot

FIXTURES = Path(__file__).resolve().parent / 'fixtures'
PANDA = str(FIXTURES / 'panda_collision.urdf')
SRDF = str(FIXTURES / 'panda_collision.srdf')
DENSE = 1000.0      # Hz: kinematic checks
DENSE_TORQUE = 200.0
DENSE_COLLISION = 500.0
BOX = {'size': [0.3, 0.3, 0.3], 'xyz': [0.6, 0.0, 0.4]}
CASES = {'mit_dd_arm': dict(harmonics=3, period=2.0, periods=2),
         'crs_a465': dict(harmonics=3, period=4.0, periods=2),
         'panda': dict(harmonics=2, period=4.0, periods=2)}


@pytest.fixture(scope='module')
def designs():
    out = {}
    for name, kw in CASES.items():
        robot = load_robot(PANDA if name == 'panda' else name)
        checker = (CollisionChecker(robot, floor=0.0, boxes=[BOX]) if name == 'panda'
                   else None)
        res = ex.optimize_excitation(robot, criterion='cond', maxiter=15, num_samples=60,
                                     checker=checker, **kw)
        out[name] = (robot, res)
    return out


def dense_times(framed, rate):
    return np.append(np.arange(0.0, framed.duration, 1.0 / rate), framed.duration)


# -- the framing ----------------------------------------------------------------------------
def test_framed_trajectory_closed_form():
    rng = np.random.default_rng(5)
    p = FourierTrajectory(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), [0.4, -0.2], 2.0,
                          ['a', 'b'])
    start = np.array([1.0, -1.0])
    f = FramedTrajectory(p, start, 1.5, 2.5, 3)
    assert f.parts() == pytest.approx({'ramp_in': 1.5, 'periodic': 6.0, 'ramp_out': 2.5,
                                       'total': 10.0})
    assert f.periodic_window == (1.5, 7.5) and f.period is None
    # derivatives by central differences of q and qd
    t, h = np.linspace(0.01, 9.99, 997), 1e-5
    q, qd, qdd = f.sample(t)
    np.testing.assert_allclose((f.sample(t + h)[0] - f.sample(t - h)[0]) / (2 * h), qd,
                               atol=1e-6)
    np.testing.assert_allclose((f.sample(t + h)[1] - f.sample(t - h)[1]) / (2 * h), qdd,
                               atol=1e-5)
    # the periodic part is p from phase 0; ramps blend start and p: positions between them
    mid = (t >= 1.5) & (t <= 7.5)
    np.testing.assert_allclose(q[mid], p.sample(t[mid] - 1.5)[0], atol=1e-12)
    pq = p.sample(t - 1.5)[0]
    lo, hi = np.minimum(start, pq), np.maximum(start, pq)
    assert np.all(q >= lo - 1e-12) and np.all(q <= hi + 1e-12)
    # at rest at both ends and outside
    q, qd, qdd = f.sample([-1.0, 0.0, 10.0, 12.0])
    np.testing.assert_allclose(q, np.tile(start, (4, 1)), atol=1e-12)
    np.testing.assert_array_equal(qd, 0.0)
    np.testing.assert_array_equal(qdd, 0.0)
    # YAML round trip and joint reordering
    back = FramedTrajectory.from_dict(yaml.safe_load(yaml.safe_dump(f.to_dict())))
    np.testing.assert_allclose(back.sample(t)[2], f.sample(t)[2], atol=1e-12)
    swapped = match_joints(back, type('R', (), {'joint_names': ['b', 'a']})())
    np.testing.assert_allclose(swapped.sample(t)[0], f.sample(t)[0][:, ::-1], atol=1e-12)
    default = FramedTrajectory(p)
    np.testing.assert_array_equal(default.start, p.q0)
    for kwargs, match in [({'periods': 0}, 'periods'), ({'ramp_in': 0.0}, 'ramp_in'),
                          ({'start': [1.0]}, 'start'), ({'ramp_out': math.nan}, 'ramp_out')]:
        with pytest.raises(IdentificationError, match=match):
            FramedTrajectory(p, **kwargs)
    with pytest.raises(IdentificationError, match='periodic'):
        FramedTrajectory(SampledTrajectory([0, 1, 2], [[0], [1], [0]]))


@pytest.mark.parametrize('name', CASES)
def test_starts_and_ends_at_rest(designs, name):
    robot, res = designs[name]
    f = res.framed
    assert isinstance(f, FramedTrajectory) and f.periods == CASES[name]['periods']
    np.testing.assert_array_equal(f.start, res.trajectory.q0)   # default: the offset
    q, qd, qdd = f.sample([0.0, f.duration])
    np.testing.assert_allclose(q, np.tile(f.start, (2, 1)), atol=1e-12)
    np.testing.assert_allclose(qd, 0.0, atol=1e-12)
    np.testing.assert_allclose(qdd, 0.0, atol=1e-12)
    # position, velocity and acceleration continuous where the ramps join the motion
    for tj in f.periodic_window:
        before, after = f.sample([tj - 1e-9]), f.sample([tj + 1e-9])
        for a, b in zip(before, after):
            np.testing.assert_allclose(a, b, atol=1e-6)
    t0, t1 = f.periodic_window
    t = np.linspace(t0, t1, 777)
    np.testing.assert_allclose(f.sample(t)[0], res.trajectory.sample(t - t0)[0], atol=1e-12)


@pytest.mark.parametrize('name', CASES)
def test_within_limits_with_margin_densely(designs, name):
    robot, res = designs[name]
    limits = ExcitationLimits.from_robot(robot)
    keep = 1.0 - DEFAULT_LIMIT_MARGIN
    f = res.framed
    t = dense_times(f, DENSE)
    q, qd, qdd = f.sample(t)
    finite = np.isfinite(limits.position_limits).all(axis=1)
    lo, hi = np.where(finite[:, None], limits.position_limits, 0.0).T
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    assert np.all(np.abs(q - centre)[:, finite] <= keep * half[finite] + 1e-12)
    assert np.all(np.abs(qd) <= keep * limits.velocity_limits + 1e-12)
    assert np.all(np.abs(qdd) <= keep * limits.acceleration_limits + 1e-12)
    k = np.searchsorted(t, dense_times(f, DENSE_TORQUE))
    tau = robot.rnea(q[k], qd[k], qdd[k])   # pinocchio's RNEA, not the regressor
    assert np.all(np.abs(tau) <= keep * limits.effort_limits + 1e-9)
    assert max(res.ratios[k] for k in LIMIT_KINDS) <= keep + 1e-9
    assert res.margin == DEFAULT_LIMIT_MARGIN


@pytest.mark.parametrize('name', CASES)
def test_criterion_beats_initial_guess(designs, name):
    robot, res = designs[name]
    assert res.value < res.initial_value
    assert res.value == pytest.approx(criterion_value(robot, res.trajectory, 'cond',
                                                      num_samples=60))
    assert res.value == pytest.approx(criterion_value(robot, res.framed, 'cond',
                                                      num_samples=60))


def _independent_geometry():
    """The fixture's collision model built here from the file: pinocchio's own pairs minus
    those on adjacent joints (parent and child)."""
    model = pin.buildModelFromUrdf(PANDA)
    geom = pin.buildGeomFromUrdf(model, PANDA, pin.COLLISION)
    geom.addAllCollisionPairs()
    joint = [o.parentJoint for o in geom.geometryObjects]
    adjacent = [(p.first, p.second) for p in geom.collisionPairs
                if model.parents[joint[p.first]] == joint[p.second]
                or model.parents[joint[p.second]] == joint[p.first]]
    for i, k in adjacent:
        geom.removeCollisionPair(pin.CollisionPair(i, k))
    return model, geom


def _lowest_point(obj, placement) -> float:
    """World z of the lowest point of a sphere, box or z-axis cylinder at ``placement``."""
    shape, R, z = obj.geometry, placement.rotation, placement.translation[2]
    name = type(shape).__name__
    if name == 'Sphere':
        return z - shape.radius
    if name == 'Box':
        return z - np.abs(R[2]) @ shape.halfSide
    if name == 'Cylinder':
        c = abs(R[2, 2])
        return z - c * shape.halfLength - shape.radius * math.sqrt(max(0.0, 1 - c * c))
    raise AssertionError(f'unexpected primitive {name}')


@pytest.mark.slow
def test_no_self_collision_on_a_dense_grid(designs):
    robot, res = designs['panda']
    assert has_collision_geometry(robot) and res.collision['pairs'] > 0
    model, geom = _independent_geometry()
    data, gdata = model.createData(), pin.GeometryData(geom)
    assert len(geom.collisionPairs) == 33
    f = res.framed
    q = f.sample(dense_times(f, DENSE_COLLISION))[0]
    # the verification grid keeps the arm within 5 mm of travel between its samples
    floor = [k for k, o in enumerate(geom.geometryObjects) if o.parentJoint != 0]
    smallest, lowest = math.inf, math.inf
    for qk in q:
        assert not pin.computeCollisions(model, data, geom, gdata, qk, False)
        pin.computeDistances(model, data, geom, gdata, qk)
        smallest = min(smallest, min(r.min_distance for r in gdata.distanceResults))
        lowest = min(lowest, min(_lowest_point(geom.geometryObjects[k], gdata.oMg[k])
                                 for k in floor))
    assert smallest >= 0.01 - 0.005
    assert lowest >= 0.01 - 0.005        # the floor at z = 0, minimum distance 1 cm
    assert res.clearance['distance'] >= 0.01


def test_collision_checker_pairs_srdf_obstacles_and_gradients():
    robot = load_robot(PANDA)
    plain = CollisionChecker(robot)
    assert plain.num_pairs == 33 and plain.srdf_removed == 0
    joints = {o.name: o.parentJoint for o in plain.geometry.geometryObjects}
    parents = robot.model.parents
    for a, b in plain.pairs:   # no pair on one joint or on a parent and its child
        ja, jb = joints[a], joints[b]
        assert ja != jb and parents[ja] != jb and parents[jb] != ja
    assert ('link3_0', 'link5_0') in plain.pairs and ('link3_0', 'link4_0') not in plain.pairs
    srdf = CollisionChecker(robot, srdf=SRDF)
    assert srdf.srdf_removed == 3
    # no pair of this arm touches in every configuration; at a 2 m minimum distance all do
    lo, hi = robot.position_limits.T
    assert plain.always_close(lo, hi) == []
    assert CollisionChecker(robot, min_distance=2.0).always_close(lo, hi) == plain.pairs
    disabled = {('link4_0', 'link6_0'), ('link5_0', 'hand_0'), ('link5_0', 'hand_1')}
    assert set(plain.pairs) - set(srdf.pairs) == disabled
    # the floor: distance = lowest point of the primitive above the floor's height
    env = CollisionChecker(robot, floor={'height': 0.05}, boxes=[BOX])
    assert env.num_pairs == 33 + 2 * 9   # floor and box against every moving geometry
    rng = np.random.default_rng(3)
    lo, hi = robot.position_limits.T
    q = rng.uniform(lo, hi, size=(6, 7))
    d, g = env.distances_and_gradients(q)
    names = [o.name for o in env.geometry.geometryObjects]
    for k in range(len(q)):
        env.distances(q[k:k + 1])
        for i, (a, b) in enumerate(env.pairs):
            if b == 'floor':
                obj = env.geometry.geometryObjects[names.index(a)]
                low = _lowest_point(obj, env.geometry_data.oMg[names.index(a)])
                assert d[k, i] == pytest.approx(low - 0.05, abs=1e-5)
    # gradients against central differences (GJK's tolerance limits the step)
    h = 1e-4
    fd = np.stack([(env.distances(q + h * e) - env.distances(q - h * e)) / (2 * h)
                   for e in np.eye(7)], axis=-1)
    np.testing.assert_allclose(g, fd, atol=2e-2)
    assert np.median(np.abs(g - fd)) < 1e-4
    assert not has_collision_geometry(load_robot('crs_a465'))
    for kwargs, match in [({'boxes': [{'size': [1, 1]}]}, 'size'),
                          ({'boxes': [{'size': [1, 1, 1], 'colour': 1}]}, 'unknown keys'),
                          ({'floor': 'low'}, 'floor'), ({'srdf': '/no/such.srdf'}, 'SRDF'),
                          ({'package_dirs': ['/no/such/dir']}, 'package directory')]:
        with pytest.raises(IdentificationError, match=match):
            CollisionChecker(robot, **kwargs)


def test_pairs_that_touch_by_design_are_refused_before_optimising():
    """A pair within the minimum distance in every configuration (here every pair, at 0.2 m)
    leaves no feasible motion: said at once, naming the pairs, without an iteration."""
    robot = load_robot(PANDA)
    lines = []
    with pytest.raises(IdentificationError, match=r'^no feasible excitation: \w+ - \w+, '
                       r'.* and \d+ more are within the minimum distance in every configuration'
                       r' sampled \(they touch by design: .*--srdf'):
        ex.optimize_excitation(robot, 3, 4.0, maxiter=50, num_samples=60, periods=1,
                               checker=CollisionChecker(robot, min_distance=0.2),
                               progress=lines.append)
    assert lines == []
    # at 1 cm no pair touches in every configuration: the screen passes
    assert ex._touching_by_design(CollisionChecker(robot, min_distance=0.01),
                                  ExcitationLimits.from_robot(robot), ex.TOUCH_SCREEN) == ''


@pytest.mark.slow
def test_pairs_the_start_breaks_are_held_no_closer_and_the_design_converges(monkeypatch):
    """TIAGo Pro's left arm (example-robot-data; meshes, no SRDF: 531 pairs). The start at 3
    harmonics (scaled until it keeps the minimum distance) has a pair closer than the
    optimiser's padded constraints ask for; SLSQP could not restore it (the distances'
    gradients are not smooth at that scale) and ran off to constraint violations of 1e6
    (kept: a blend with the start, cond 44 -> 34.5). The pair is held no closer than at the
    start instead, and the final dense check keeps the minimum distance."""
    robot = load_robot(str(arm_urdf('tiago_pro')), ARMS['tiago_pro'][1])
    checker = CollisionChecker(robot, [robots_dir().parent.parent])
    assert checker.num_pairs == 531
    limits = ExcitationLimits.from_robot(robot).with_margin(DEFAULT_LIMIT_MARGIN)
    design = DesignProblem(robot, base_of(robot, None), limits, 3, 10.0, 60, 'cond', None,
                           ex.MARGIN, None, checker)
    x0 = to_x(ex._out_of_collision(initial_trajectory(robot, None, limits, 3, 10.0, 0),
                                   design, limits))
    pairs = checker.num_pairs
    before, need = design.constraint(x0)[-pairs:], design.need.copy()
    held = design.hold_collisions_at(x0)
    after = design.constraint(x0)[-pairs:]
    assert held.size and np.array_equal(held, np.flatnonzero(before < 0))
    np.testing.assert_allclose(after[held], 0.0, atol=1e-9)
    np.testing.assert_allclose(need[held] - design.need[held], -before[held] * COLLISION_SCALE)
    kept = np.setdiff1d(np.arange(pairs), held)
    assert np.array_equal(after[kept], before[kept])
    lines = []
    monkeypatch.setattr(ex, 'PROGRESS_INTERVAL', 0.0)   # a line at every evaluation
    res = ex.optimize_excitation(robot, 3, 10.0, maxiter=15, num_samples=60, periods=1,
                                 checker=checker, progress=lines.append)
    assert any(' - ' in line and 'held no closer' in line for line in lines)
    worst = [float(line.split('worst constraint ')[1].split()[0]) for line in lines
             if line.startswith('iteration ')]
    assert min(worst, default=0.0) > -10.0       # no run-off
    assert res.initial_feasible and not res.warnings
    assert res.value < 0.4 * res.initial_value
    assert res.clearance['distance'] >= checker.min_distance
    # the verification checks each pair on its own schedule (far pairs seldom), 5 mm of
    # travel apart at least: on a uniform 100 Hz grid of the framed trajectory, every pair's
    # hull distance (a lower bound of the meshes') within that of the minimum, and the
    # closest pair's mesh distance that reported
    f = res.framed
    q = f.sample(dense_times(f, 100.0))[0]
    assert checker.hulls().distances(q).min() >= checker.min_distance - 0.005
    closest = checker.pairs.index(res.clearance['pair'])
    mesh = min(checker.pair_distances(qk, [closest])[0] for qk in q)
    assert res.clearance['distance'] == pytest.approx(mesh, abs=1e-3)


@pytest.mark.slow
def test_a_start_in_collision_is_scaled_until_clear_even_where_the_padding_is_unmet():
    """Unitree Z1 (example-robot-data; meshes, an SRDF that disables no pair): the
    least-squares start collides, and no scaling towards the centre of the ranges meets the
    optimiser's padded constraints. The least scaled start that keeps the minimum distance is
    taken, not the colliding one (from which SLSQP ran off and the initial guess, shrunk to
    cond 8e4, was all it kept)."""
    urdf = arm_urdf('z1')
    robot = load_robot(str(urdf), ARMS['z1'][1])
    checker = CollisionChecker(robot, [robots_dir().parent.parent],
                               urdf.parent.parent / 'srdf' / 'z1.srdf')
    limits = ExcitationLimits.from_robot(robot).with_margin(DEFAULT_LIMIT_MARGIN)
    design = DesignProblem(robot, base_of(robot, None), limits, 5, 10.0, 100, 'cond', None,
                           ex.MARGIN, None, checker)
    lsq = initial_trajectory(robot, None, limits, 5, 10.0, 0)
    assert design.collision_distances(to_x(lsq)).min() < checker.min_distance
    start = to_x(ex._out_of_collision(lsq, design, limits))
    assert design.collision_distances(start).min() >= checker.min_distance
    assert design.collision_ks(start, False)[0].max() > ex.MARGIN    # padding unmet
    res = ex.optimize_excitation(robot, maxiter=20, checker=checker)
    assert res.initial_feasible and not res.warnings
    assert res.value < 0.2 * res.initial_value < 100.0
    assert res.clearance['distance'] >= checker.min_distance


@pytest.mark.slow
def test_an_arm_the_centre_of_its_ranges_holds_out_is_designed_within_its_torque_limits():
    """Talos' left arm (example-robot-data, its meshes and SRDF, the shipped defaults): at the
    centre of its position ranges the static torque of arm_left_2_joint is 1.08 times its
    limit with the margin, so no motion scaled towards that centre kept the torque limits
    ("infeasible limits"; --no-effort was the way out). The motion is centred on and scaled
    towards the rest pose instead: the pose nearest the centre, within the middle three
    quarters of the ranges, whose static torque keeps within REST_TORQUE of every limit. The
    UR5's centre (0.44) is kept. The optimiser's last iterates then hold a torque limit that
    slower motion breaks: shrunk into the limits the first came to 272 (0.21 x the start);
    later candidates are now verified while they may beat that."""
    robot = load_robot(str(arm_urdf('talos')), ARMS['talos'][1])
    work = ExcitationLimits.from_robot(robot).with_margin(DEFAULT_LIMIT_MARGIN)
    zero = np.zeros(robot.dof)
    lo, hi = work.position_limits.T
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)

    def static(q: np.ndarray) -> np.ndarray:   # pinocchio's RNEA, not the regressor
        return np.abs(robot.rnea(q, zero, zero)[0]) / work.effort_limits

    assert static(centre).max() > 1.0
    guess = initial_trajectory(robot, None, ExcitationLimits.from_robot(robot, effort=False)
                               .with_margin(DEFAULT_LIMIT_MARGIN), 5, 10.0, 0)
    with pytest.raises(IdentificationError, match='near the centre of the position ranges'):
        shrink_into_limits(guess, robot, work)
    rest = rest_pose(robot, work)
    assert np.all(np.abs(rest - centre) <= 0.75 * half + 1e-12)
    assert static(rest).max() <= REST_TORQUE * (1 + 1e-6)
    # the nearest such pose: a step towards the centre (down the distance's gradient) breaks it
    down = (centre - rest) / (0.75 * half) ** 2
    assert static(rest + 1e-3 * down / np.linalg.norm(down)).max() > REST_TORQUE
    checker = CollisionChecker(robot, [robots_dir().parent.parent],
                               robots_dir() / 'talos_data/srdf/talos.srdf')
    lines: list[str] = []
    res = ex.optimize_excitation(robot, checker=checker, progress=lines.append)
    assert any('holds arm_left_2_joint at 1.08 x its torque limit' in line for line in lines)
    assert not res.warnings and res.value < 0.05 * res.initial_value
    assert res.clearance['distance'] >= checker.min_distance
    keep = 1.0 - DEFAULT_LIMIT_MARGIN
    f = res.framed
    q, qd, qdd = f.sample(dense_times(f, DENSE_TORQUE))
    tau = robot.rnea(q, qd, qdd)
    assert np.all(np.abs(tau) <= keep * ExcitationLimits.from_robot(robot).effort_limits + 1e-9)
    ur5 = load_robot(str(arm_urdf('ur5')))
    assert rest_pose(ur5, ExcitationLimits.from_robot(ur5).with_margin(0.1)) is None


@pytest.mark.slow
def test_an_arm_in_collision_at_the_centre_of_its_ranges_is_centred_on_a_clear_pose():
    """Alex's left arm (example-robot-data; meshes, no SRDF: 118 pairs): at the centre of its
    position ranges the shoulder's and the wrist's links are 5.6 mm apart, under the 10 mm
    minimum distance, so no motion scaled towards that centre was clear ("no feasible
    excitation found"). The rest pose is the nearest clear one (COLLISION_PAD beyond the
    minimum on the hulls, which bound the meshes), and the design starts there."""
    robot = load_robot(str(arm_urdf('alex')), ARMS['alex'][1])
    checker = CollisionChecker(robot, [robots_dir().parent.parent])
    work = ExcitationLimits.from_robot(robot).with_margin(DEFAULT_LIMIT_MARGIN)
    lo, hi = work.position_limits.T
    centre = checker.clearance(0.5 * (lo + hi)[None])
    assert centre['distance'] < checker.min_distance
    assert centre['pair'] == ('LeftShoulderYawLink_0', 'LeftWristYawLink_0')
    hulls = checker.hulls()
    rest = rest_pose(robot, work, clearance=lambda q: hulls.closest_pair(q)[0]
                     - hulls.min_distance, pad=COLLISION_PAD)
    assert checker.clearance(rest[None])['distance'] >= checker.min_distance + COLLISION_PAD
    lines: list[str] = []
    res = ex.optimize_excitation(robot, 3, 10.0, maxiter=15, num_samples=60, periods=1,
                                 checker=checker, progress=lines.append)
    assert any('is in collision (LeftShoulderYawLink_0 - LeftWristYawLink_0)' in line
               for line in lines)
    assert res.clearance['distance'] >= checker.min_distance
    assert res.value < res.initial_value


def test_coefficient_bounds_hold_every_trajectory_within_the_limits(designs):
    """DesignProblem.bounds, SLSQP's box: the designs and the initial guesses (inside the
    limits by construction) keep them, and a single harmonic at the velocity limit (a
    Fourier coefficient at most 4 / pi times its signal's peak) is within them."""
    for name, (robot, res) in designs.items():
        kw = CASES[name]
        limits = res.limits.with_margin(res.margin)
        design = DesignProblem(robot, base_of(robot, None), limits, kw['harmonics'],
                               kw['period'], 60, 'cond', None, ex.MARGIN)
        lo, hi = (np.array([np.inf * s if b is None else b for b in side])
                  for s, side in zip((-1, 1), zip(*design.bounds())))
        for traj in [res.trajectory] + [initial_trajectory(robot, None, limits,
                                                           kw['harmonics'], kw['period'], s)
                                        for s in range(3)]:
            x = to_x(traj)
            assert np.all(lo <= x) and np.all(x <= hi), name
        k = np.arange(design.k * robot.dof).reshape(robot.dof, design.k)
        vel = np.minimum(limits.velocity_limits, limits.acceleration_limits * kw['period']
                         / (2 * np.pi))
        np.testing.assert_array_less(vel, hi[k[:, 0]])     # a_1 at the limit: inside
        assert np.all(hi[k[:, 0]] < 1.5 * vel)


def test_design_constraint_jacobian_with_torque_models_and_collisions():
    robot = load_robot(PANDA)
    limits = ExcitationLimits.from_robot(robot).with_margin(0.1)
    base = base_of(robot, None)
    checker = CollisionChecker(robot, floor=0.0)
    design = DesignProblem(robot, base, limits, 2, 4.0, 40, 'cond', None, 1.0,
                           [robot.phi_model, 1.5 * robot.phi_model], checker)
    x = to_x(initial_trajectory(robot, None, limits, 2, 4.0, 1))
    c, J = design.constraint(x), design.constraint_jac(x)
    assert c.shape == (7 * 3 + 7 + checker.num_pairs,) and J.shape == (c.size, x.size)
    rng = np.random.default_rng(4)
    for _ in range(3):
        v, h = rng.normal(size=x.size), 1e-4
        fd = (design.constraint(x + h * v) - design.constraint(x - h * v)) / (2 * h)
        k = 7 * 3 + 7   # limits (torques under both models), then the collision pairs
        np.testing.assert_allclose(fd[:k], (J @ v)[:k], rtol=1e-4, atol=1e-6)
        # distances come from GJK with a 1e-6 m tolerance: a few per cent at this step
        np.testing.assert_allclose(fd[k:], (J @ v)[k:], rtol=0.05, atol=0.05)


def test_collision_jacobian_skips_only_negligible_samples(monkeypatch):
    """The collision constraints' Jacobian computes distance gradients only where a sample's
    KS weight in its pair exceeds GRADIENT_WEIGHT: equal to the Jacobian of every gradient
    to 1e-6 of its scale (GJK's warm start differs with the distances computed before: 1e-7
    here; a weight floor of 1e-6 gives 3e-6), with most (sample, pair) gradients skipped."""
    import identification_node.excitation.problem as problem
    robot = load_robot(PANDA)
    limits = ExcitationLimits.from_robot(robot).with_margin(0.1)
    x = to_x(initial_trajectory(robot, None, limits, 2, 4.0, 1))
    asked, jacobians = [], []
    for floor in (problem.GRADIENT_WEIGHT, -1.0):    # -1: every sample's gradient
        monkeypatch.setattr(problem, 'GRADIENT_WEIGHT', floor)
        checker = CollisionChecker(robot, floor=0.0)   # GJK's warm starts from scratch
        full_gradients = checker.gradients

        def gradients(q, which, within=None, full_gradients=full_gradients):
            asked.append(np.mean(which))
            return full_gradients(q, which, within)
        monkeypatch.setattr(checker, 'gradients', gradients)
        design = DesignProblem(robot, base_of(robot, None), limits, 2, 4.0, 40, 'cond', None,
                               1.0, None, checker)
        jacobians.append(design.collision_ks(x, True)[1])
    assert asked[1] == 1.0 and asked[0] < 0.5, asked
    np.testing.assert_allclose(jacobians[0], jacobians[1], rtol=0,
                               atol=1e-6 * np.abs(jacobians[1]).max())


def test_package_dir_resolves_meshes(tmp_path):
    mesh = tmp_path / 'pkg' / 'meshes' / 'part.stl'
    mesh.parent.mkdir(parents=True)
    facets = [((0, 0, 0), (0.05, 0, 0), (0, 0.05, 0)), ((0, 0, 0), (0, 0, 0.05), (0.05, 0, 0)),
              ((0, 0, 0), (0, 0.05, 0), (0, 0, 0.05)), ((0.05, 0, 0), (0, 0, 0.05), (0, 0.05, 0))]
    mesh.write_text('solid t\n' + ''.join(
        'facet normal 0 0 0\nouter loop\n' + ''.join(f'vertex {x} {y} {z}\n' for x, y, z in f)
        + 'endloop\nendfacet\n' for f in facets) + 'endsolid t\n')
    urdf = tmp_path / 'mesh.urdf'
    urdf.write_text(Path(PANDA).read_text().replace(
        '<box size="0.12 0.08 0.08"/>', '<mesh filename="package://pkg/meshes/part.stl"/>'))
    robot = load_robot(str(urdf))
    with pytest.raises(IdentificationError, match='package-dir'):
        CollisionChecker(robot)
    assert CollisionChecker(robot, package_dirs=[tmp_path]).num_pairs == 33


def test_hulls_bound_the_meshes_and_clearance_is_the_exact_minimum():
    """example-robot-data's Panda (meshes, its SRDF): the convex hulls' distances never exceed
    the meshes' (a hull contains its mesh), and clearance, which computes mesh distances
    only where the hulls cannot rule a pair out, equals the minimum over every pair and
    sample of the meshes' distances."""
    urdf = arm_urdf('panda')
    robot = load_robot(str(urdf), ARMS['panda'][1])
    exact = CollisionChecker(robot, [robots_dir().parent.parent],
                             urdf.parent.parent / 'srdf' / 'panda.srdf')
    hulls = exact.hulls()
    assert exact.meshes and hulls.convex and not exact.convex
    assert hulls.pairs == exact.pairs and hulls.hulls() is hulls
    kinds = {type(o.geometry).__name__ for o in hulls.geometry.geometryObjects}
    assert 'BVHModelOBBRSS' not in kinds and 'Convex' in kinds
    rng = np.random.default_rng(8)
    lo, hi = robot.position_limits.T
    q = rng.uniform(lo, hi, size=(25, 7))
    mesh, bound = exact.distances(q), hulls.distances(q)
    clear = mesh > 0
    assert np.all(bound[clear] <= mesh[clear] + 1e-6)
    for part in (q, q[mesh.min(axis=1) > 0]):   # penetrating samples, then only clear ones
        d = exact.distances(part)
        k, i = np.unravel_index(np.argmin(d), d.shape)
        c = exact.clearance(part)
        assert c['distance'] == pytest.approx(d[k, i], abs=1e-6)
        assert c['pair'] == exact.pairs[i] and c['sample'] == k


def test_distances_within_leave_out_only_pairs_their_bounding_spheres_keep_farther():
    """CollisionChecker.distances(q, within): TIAGo Pro's arm (531 pairs on its hulls, no
    SRDF) and a floor, on a smooth path through its ranges. Every pair closer than ``within``
    is computed, as without it (GJK's warm starts differ by its tolerance); where a pair is
    left out, what stands in is a lower bound of its distance above ``within``, and the
    gradients are those of what stands in; the floor, unbounded, is always computed. Most
    pairs are left out: the excitation optimiser's collision constraints cost a third
    (COLLISION_CULL_PAIRS)."""
    robot = load_robot(str(arm_urdf('tiago_pro')), ARMS['tiago_pro'][1])
    hulls = CollisionChecker(robot, [robots_dir().parent.parent], floor=-0.5).hulls()
    assert hulls.num_pairs > COLLISION_CULL_PAIRS
    lo, hi = ExcitationLimits.from_robot(robot).position_limits.T
    t = np.linspace(0.0, 1.0, 200)[:, None]
    q = lo + (hi - lo) * (0.5 + 0.4 * np.sin(2 * np.pi * t * np.arange(1, robot.dof + 1)))
    exact = hulls.distances(q)
    within = np.random.default_rng(3).uniform(0.05, 0.3, hulls.num_pairs)
    d = hulls.distances(q, within)
    close = exact < within - 1e-6
    np.testing.assert_allclose(d[close], exact[close], atol=2e-6)
    assert np.all(d <= exact + 2e-6)
    stand_in = np.abs(d - exact) > 2e-6
    assert np.all(d[stand_in] > np.broadcast_to(within, d.shape)[stand_in])
    floor = [i for i, pair in enumerate(hulls.pairs) if 'floor' in pair]
    assert floor and not stand_in[:, floor].any()
    assert stand_in.mean() > 0.8
    np.testing.assert_allclose(hulls.distances(q), exact, atol=2e-6)   # every pair again
    # gradients: the witness points' where computed, the spheres' (central differences of
    # what stands in) elsewhere
    k = slice(0, 200, 10)
    g = hulls.gradients(q[k], np.ones(d[k].shape, dtype=bool), within)
    # a warm-started GJK may pick another witness point along a polytope's edge or face
    same = np.abs(g - hulls.gradients(q[k], ~stand_in[k])).max(axis=2) < 1e-3
    assert same[~stand_in[k]].mean() > 0.99
    h = 1e-6
    for i in range(robot.dof):
        step = np.eye(robot.dof)[i] * h
        up, down = hulls.distances(q[k] + step, within), hulls.distances(q[k] - step, within)
        both = stand_in[k] & (np.abs(up - down) < 1e-3)   # stood in on both sides
        assert both.sum() > 1000
        np.testing.assert_allclose(g[..., i][both], ((up - down) / (2 * h))[both], atol=1e-7)


def test_closest_pair_leaves_the_other_distances_as_they_were():
    """CollisionChecker.closest_pair: the smallest distance at one pose and its pair, as
    distances gives them; computed on data of its own, so the distances after it are those
    of a checker that never made it, to the bit (the optimiser's path follows GJK's warm
    starts: a probe of the rest pose's clearance moved the Z1's design from 9.90 to 10.86)."""
    robot = load_robot(PANDA)
    rng = np.random.default_rng(4)
    lo, hi = robot.position_limits.T
    q = rng.uniform(lo, hi, size=(30, robot.dof))
    probed, plain = (CollisionChecker(robot, floor=0.0, boxes=[BOX]) for _ in range(2))
    first = probed.distances(q[:10])
    np.testing.assert_array_equal(first, plain.distances(q[:10]))
    for pose in q[10:20]:
        d, pair = probed.closest_pair(pose)
        row = plain.distances(pose[None])[0]
        assert d == pytest.approx(row.min(), abs=1e-6) and pair == plain.pairs[int(np.argmin(row))]
    plain = CollisionChecker(robot, floor=0.0, boxes=[BOX])
    plain.distances(q[:10])
    np.testing.assert_array_equal(probed.distances(q[20:]), plain.distances(q[20:]))


def test_a_flat_mesh_without_a_hull_stays_a_mesh(tmp_path):
    mesh = tmp_path / 'pkg' / 'meshes' / 'flat.stl'
    mesh.parent.mkdir(parents=True)
    mesh.write_text('solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 0.05 0 0\n'
                    'vertex 0 0.05 0\nendloop\nendfacet\nendsolid t\n')   # one triangle
    urdf = tmp_path / 'flat.urdf'
    urdf.write_text(Path(PANDA).read_text().replace(
        '<box size="0.12 0.08 0.08"/>', '<mesh filename="package://pkg/meshes/flat.stl"/>'))
    exact = CollisionChecker(load_robot(str(urdf)), package_dirs=[tmp_path])
    hulls = exact.hulls()
    k = exact.meshes[0]
    assert type(hulls.geometry.geometryObjects[k].geometry).__name__ == 'BVHModelOBBRSS'
    q = np.zeros((3, 7))
    np.testing.assert_allclose(hulls.distances(q), exact.distances(q), atol=1e-9)


# -- limits ----------------------------------------------------------------------------------
def test_assumed_limits_listed_and_overridden(tmp_path):
    robot = load_robot(PANDA)
    lim = ExcitationLimits.from_robot(robot)
    assert set(lim.assumed) == set(robot.joint_names)
    assert all(set(v) == {'acceleration'} for v in lim.assumed.values())   # URDF has none
    assert lim.assumed['joint1']['acceleration'] == pytest.approx(2 * 2.175)
    over = lim.updated({'joint1': {'acceleration': 10.0}, 'joint2': {'velocity': 1.0}})
    assert 'joint1' not in over.assumed
    assert over.assumed['joint2'] == {'acceleration': pytest.approx(2.0)}   # follows velocity
    assert any(line.startswith('joint3.acceleration: 4.35') for line in over.assumed_list())
    crs = ExcitationLimits.from_robot(load_robot('mit_dd_arm'))
    assert crs.assumed['joint1']['position'] is None   # continuous joints
    # margins: ranges about their centres, the rest scaled
    m = lim.with_margin(0.2)
    np.testing.assert_allclose(m.position_limits.mean(axis=1), lim.position_limits.mean(axis=1))
    np.testing.assert_allclose(np.diff(m.position_limits), 0.8 * np.diff(lim.position_limits))
    np.testing.assert_allclose(m.effort_limits, 0.8 * lim.effort_limits)
    for bad in (1.0, -0.1, math.nan):
        with pytest.raises(IdentificationError, match='margin'):
            lim.with_margin(bad)


def test_torque_limits_hold_under_an_estimate(tmp_path):
    robot = load_robot('mit_dd_arm')
    heavy = 1.6 * robot.phi_model    # torques exactly 1.6 times the model's
    traj = FourierTrajectory.random(robot, 3, 2.0, seed=2)
    base_ratio = limit_ratios(traj, robot)['effort']
    both = limit_ratios(traj, robot, phis=[robot.phi_model, heavy])['effort']
    assert both == pytest.approx(1.6 * base_ratio, rel=1e-9)
    # effort limits 1.2 times the model's peak torques: the estimate's need more
    unit = ExcitationLimits.from_robot(robot).updated(
        {j: {'effort': 1.0} for j in robot.joint_names})
    peak = limit_ratios(traj, robot, unit)['per_joint']['effort']     # N m
    limits = unit.updated({j: {'effort': 1.2 * p} for j, p in zip(robot.joint_names, peak)})
    res = ex.optimize_excitation(robot, 3, 2.0, limits=limits, maxiter=10, num_samples=60,
                                 periods=2, phis=[robot.phi_model, heavy])
    f = res.framed
    t = dense_times(f, DENSE_TORQUE)
    tau = robot.rnea(*f.sample(t), phi=heavy)
    assert np.all(np.abs(tau) <= 0.9 * limits.effort_limits + 1e-9)
    # the estimate file of the node / identify
    path = tmp_path / 'estimate.yaml'
    path.write_text(yaml.safe_dump({'standard_parameters': dict(zip(
        robot.param_names, map(float, heavy)))}))
    np.testing.assert_allclose(estimate_parameters(path, robot), heavy)
    path.write_text(yaml.safe_dump({'standard_parameters': {'link1.m': 1.0}}))
    with pytest.raises(IdentificationError, match='does not match'):
        estimate_parameters(path, robot)


# -- outcome ---------------------------------------------------------------------------------
def test_iteration_limit_is_said_not_warned_with_the_best_feasible_point():
    robot = load_robot('mit_dd_arm')
    res = ex.optimize_excitation(robot, 3, 2.0, maxiter=3, num_samples=60, periods=2)
    assert not res.success and res.status == 9
    assert 'stopped at the limit of 3 iterations' in res.message and not res.warnings
    assert res.value <= res.initial_value
    assert max(res.ratios[k] for k in LIMIT_KINDS) <= 0.9 + 1e-9


@pytest.mark.slow
def test_progress_lines_and_time_limit_keep_the_best_feasible_design(monkeypatch):
    robot = load_robot('crs_a465')
    lines = []
    monkeypatch.setattr(ex, 'PROGRESS_INTERVAL', 0.0)   # a line at every evaluation
    res = ex.optimize_excitation(robot, 3, 4.0, maxiter=5, num_samples=60, periods=1,
                                 progress=lines.append)
    assert any(line.startswith('optimising: 42 coefficients, 24 constraints')
               for line in lines)
    assert lines[-1].startswith('verifying') or 'verifying the best' in lines[-1]
    steps = [line for line in lines if line.startswith('iteration ')]
    assert steps and all('criterion cond' in line and 'worst constraint' in line
                         and line.endswith(' s') for line in steps)
    # a limit that passes before the first iteration: the initial guess is kept, verified
    res = ex.optimize_excitation(robot, 3, 4.0, maxiter=200, num_samples=60, periods=1,
                                 time_limit=1e-6)
    assert res.status == -1 and 'stopped at the time limit of 1e-06 s' in res.message
    assert res.iterations == 0 and res.value == pytest.approx(res.initial_value)
    assert max(res.ratios[k] for k in LIMIT_KINDS) <= 0.9 + 1e-9
    with pytest.raises(IdentificationError, match='time limit'):
        ex.optimize_excitation(robot, 3, 4.0, maxiter=1, time_limit=0)


def test_start_configuration(designs):
    robot, _ = designs['crs_a465']
    start = [0.1, -0.2, 0.3, 0.0, 0.2, -0.1]
    res = ex.optimize_excitation(robot, 3, 4.0, maxiter=5, num_samples=60, periods=1,
                                 start=start)
    np.testing.assert_allclose(res.framed.sample([0.0, res.framed.duration])[0],
                               [start, start], atol=1e-12)
    with pytest.raises(IdentificationError, match='outside the position limits'):
        ex.optimize_excitation(robot, 3, 4.0, maxiter=1, num_samples=60,
                               start=[3.0, 0, 0, 0, 0, 0])


@pytest.mark.parametrize('extra, match', [
    (['--robot', 'crs_a465', '--limits', 'EFFORT'], 'infeasible'),
    (['--urdf', PANDA, '--min-distance', '2.0', '--harmonics', '2', '--period', '4'],
     'no feasible excitation: '),   # said before optimising
    (['--urdf', PANDA, '--srdf', SRDF, '--min-distance', '2.0', '--harmonics', '2',
      '--period', '4'], 'no feasible excitation: '),
    (['--robot', 'mit_dd_arm', '--srdf', SRDF], 'no collision geometry'),
    (['--robot', 'mit_dd_arm', '--start', '1,2'], 'start configuration'),
    (['--robot', 'mit_dd_arm', '--margin', '1.5'], 'margin'),
    (['--robot', 'mit_dd_arm', '--config', 'CONFIG'], 'unknown keys'),
])
def test_cli_infeasible_or_bad_gives_a_clear_error_and_no_files(tmp_path, capsys, extra, match):
    effort = tmp_path / 'effort.yaml'
    effort.write_text('joint2: {effort: 1.0, position: [0.5, 1.0]}\n')  # < static torque
    config = tmp_path / 'config.yaml'
    config.write_text('limits: {}\nobstacles: []\n')
    extra = [str(effort) if a == 'EFFORT' else str(config) if a == 'CONFIG' else a
             for a in extra]
    out = tmp_path / 'o' / 'x.yaml'
    argv = ['excite', *extra, '--maxiter', '2', '--samples', '60', '--periods', '1',
            '--out', str(out), '--bag', str(tmp_path / 'o' / 'bag')]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith('error:') and match in err
    # pairs within the minimum distance wherever the arm is: named, with the SRDF as the way out
    stuck = '--min-distance' in extra
    assert ('are within the minimum distance in every configuration sampled' in err) == stuck
    assert ("the robot's SRDF (--srdf) leaves such pairs out" in err) == (
        stuck and '--srdf' not in extra), err
    assert ('disable them in the SRDF' in err) == (stuck and '--srdf' in extra), err
    assert not (tmp_path / 'o').exists() or not any((tmp_path / 'o').iterdir())


# -- outputs ---------------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_outputs_a_robot_can_execute(tmp_path, capsys):
    robot = load_robot(PANDA)
    limits = tmp_path / 'limits.yaml'
    limits.write_text('joint1: {acceleration: 3.0}\n')
    config = tmp_path / 'config.yaml'
    config.write_text(yaml.safe_dump({'margin': 0.15, 'periods': 2, 'floor': 0.0,
                                      'limits': {'joint7': {'velocity': 2.0}},
                                      'min_distance': 0.02}))
    out, bag = tmp_path / 'exc.yaml', tmp_path / 'bag'
    argv = ['excite', '--urdf', PANDA, '--harmonics', '2', '--period', '4', '--samples', '60',
            '--maxiter', '6', '--limits', str(limits), '--config', str(config), '--srdf', SRDF,
            '--rate', '50', '--out', str(out), '--bag', str(bag)]
    assert main(argv) == 0
    captured = capsys.readouterr()
    text = captured.out
    assert 'durations: ramp in' in text and 'assumed' in text and 'collision: 39 pairs' in text
    assert 'joint1.acceleration' not in text and 'joint2.acceleration: 4.35' in text
    assert 'stopped at the limit of 6 iterations' in text and 'warning:' not in captured.err
    assert 'iteration' not in captured.err   # progress lines go to stdout
    doc = yaml.safe_load(out.read_text())
    assert doc['limit_margin'] == 0.15 and doc['collision']['srdf_disabled'] == 3
    assert doc['collision']['min_distance'] == 0.02 and doc['collision']['clearance'] >= 0.02
    assert doc['limits']['joint1']['acceleration'] == 3.0
    assert doc['limits']['joint7']['velocity'] == 2.0
    assert 'joint1' not in doc['assumed_limits']
    assert doc['assumed_limits']['joint7'] == {'acceleration': pytest.approx(4.0)}
    assert 'stopped at the limit' in doc['optimisation']['message']
    assert doc['criterion']['value'] < doc['criterion']['initial']
    assert all(doc['limit_ratios'][k]['worst'] <= 0.85 + 1e-9 for k in LIMIT_KINDS)
    framed = load_trajectory(str(out), robot)
    assert isinstance(framed, FramedTrajectory) and framed.periods == 2
    assert doc['durations'] == pytest.approx(framed.parts())
    assert doc['framing']['ramp_in'] + 8.0 + doc['framing']['ramp_out'] == pytest.approx(
        framed.duration)
    # CSV: t, every joint's position, velocity, acceleration, ramps included, at --rate
    csv = out.with_suffix('.csv')
    header = csv.read_text().splitlines()[0].split(',')
    assert header == ['t'] + [f'{j}.{k}' for k in ('position', 'velocity', 'acceleration')
                              for j in robot.joint_names]
    data = np.loadtxt(csv, delimiter=',', skiprows=1)
    np.testing.assert_allclose(data[:, 0], np.arange(len(data)) / 50.0, atol=1e-9)
    assert data[-1, 0] == pytest.approx(framed.duration)
    q, qd, qdd = framed.sample(data[:, 0])
    np.testing.assert_allclose(data[:, 1:], np.hstack([q, qd, qdd]), atol=1e-12)
    np.testing.assert_allclose(data[[0, -1], 8:], 0.0, atol=1e-12)   # at rest
    # the plot and the bag
    assert out.with_suffix('.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    with BagReader(bag) as reader:
        msg = [m for *_, m in iter_messages(reader)][0]
    assert len(msg.points) == len(data)
    np.testing.assert_allclose(msg.points[0].velocities, 0.0, atol=1e-12)
    np.testing.assert_allclose(msg.points[-1].positions, framed.start, atol=1e-12)


@pytest.mark.slow
def test_identification_from_a_simulated_run_ramps_included(tmp_path, capsys):
    """excite -> simulate (ArmSimulator under computed torque, ramps included, torque noise)
    -> identify with the framed trajectory (periodic part only): every base parameter within
    4 standard deviations of the truth. Averaging the whole run as if periodic is far off."""
    exc, bag = tmp_path / 'mit.yaml', tmp_path / 'bag'
    assert main(['excite', '--robot', 'mit_dd_arm', '--harmonics', '3', '--period', '2',
                 '--periods', '3', '--maxiter', '30', '--samples', '60',
                 '--out', str(exc)]) == 0
    assert main(['simulate', '--robot', 'mit_dd_arm', '--trajectory', str(exc),
                 '--torque-std', '0.5', '--out', str(bag)]) == 0
    framed = load_trajectory(str(exc), load_robot('mit_dd_arm'))
    truth = yaml.safe_load((bag / 'true_parameters.yaml').read_text())
    assert truth['samples'] == int(round(framed.duration * 1000)) + 1   # the ramps were run
    capsys.readouterr()
    assert main(['identify', str(bag), '--robot', 'mit_dd_arm', '--trajectory', str(exc),
                 '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc['processing']['window_s'] == pytest.approx(list(framed.periodic_window))
    assert doc['processing']['periods'] == 3
    est = {p['name']: p for p in doc['base_parameters']}
    err = [(est[n]['estimate'] - v) / est[n]['stddev']
           for n, v in truth['base_parameters'].items()]
    assert np.all(np.abs(err) < 4.0), err
    assert main(['identify', str(bag), '--robot', 'mit_dd_arm', '--period', '2', '--json']) == 0
    whole = {p['name']: p for p in json.loads(capsys.readouterr().out)['base_parameters']}
    off = [abs(whole[n]['estimate'] - v) / whole[n]['stddev']
           for n, v in truth['base_parameters'].items()]
    assert max(off) > 20.0
