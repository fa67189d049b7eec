"""Settings a user may change while the node runs (forgetting factor, payload detection
thresholds, plausibility margin), over DDS: validated as at start-up, applied to the running
pipeline and payload monitor; every other setting read-only."""
import numpy as np
import pytest
from rclpy.parameter import Parameter

from identification_node.model.robot import load_robot
from identification_node.config import PARAMETERS
from identification_node.ros.parameters import RUNTIME

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def node(ros):
    from identification_node.ros.node import IdentificationNode
    params = {'robot': 'mit_dd_arm', 'payload.enabled': True, 'smoother.half_window': 10}
    made = ros.add(IdentificationNode('runtime', context=ros.context, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()]))
    yield made
    ros.remove(made)


def test_forgetting_factor(ros, node):
    (ok,) = ros.set_parameters('/runtime', [Parameter('forgetting_factor', value=0.999)])
    assert ok.successful, ok.reason
    assert node.pipeline.rls.forgetting == 0.999 and node.settings['forgetting_factor'] == 0.999
    assert ros.get_parameters('/runtime', ['forgetting_factor']) == {'forgetting_factor': 0.999}
    (bad,) = ros.set_parameters('/runtime', [Parameter('forgetting_factor', value=0.5)])
    assert not bad.successful and 'forgetting_factor' in bad.reason
    assert node.pipeline.rls.forgetting == 0.999
    node.pipeline.reset()   # a reset's new estimator keeps the value
    assert node.pipeline.rls.forgetting == 0.999


def test_payload_thresholds(ros, node):
    detector = node.payload.monitor.detector
    results = ros.set_parameters('/runtime', [Parameter('payload.threshold', value=80.0),
                                              Parameter('payload.min_change', value=0.5)])
    assert all(r.successful for r in results), results
    assert (detector.threshold, detector.min_change) == (80.0, 0.5)
    (bad,) = ros.set_parameters('/runtime', [Parameter('payload.min_z', value=-1.0)])
    assert not bad.successful and 'payload.min_z' in bad.reason
    assert detector.min_z == PARAMETERS['payload.min_z'][0]


def test_plausibility_margin_widens_the_bounds(ros, node):
    robot = load_robot('mit_dd_arm')
    limits = np.asarray(robot.velocity_limits, dtype=float)
    rated = np.isfinite(limits) & (limits > 0)
    (ok,) = ros.set_parameters('/runtime', [Parameter('plausibility.margin', value=3.0)])
    assert ok.successful, ok.reason
    bounds = node.pipeline.samples.bounds
    assert bounds is node.pipeline.bounds   # the one object every stage checks against
    np.testing.assert_allclose(bounds.velocity[rated], 3.0 * limits[rated])
    (bad,) = ros.set_parameters('/runtime', [Parameter('plausibility.margin', value=0.5)])
    assert not bad.successful and 'margin' in bad.reason
    np.testing.assert_allclose(bounds.velocity[rated], 3.0 * limits[rated])


def test_everything_else_is_read_only(ros, node):
    for name, value in (('smoother.cutoff', 10.0), ('robot', 'crs_a465'),
                        ('payload.fit_time', 2.0)):
        assert name not in RUNTIME
        (res,) = ros.set_parameters('/runtime', [Parameter(name, value=value)])
        assert not res.successful, name
    assert node.settings['robot'] == 'mit_dd_arm'
