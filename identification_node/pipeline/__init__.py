"""The identification pipeline: stamped joint states and currents in, base-parameter estimate
out. The node (its processing thread copies the polled messages in as CDR bytes) and bag
replay feed the same IdentificationPipeline; ``process`` does the numerical work for
everything queued, in batches, one stage per module:

1. ``intake``: the queued inputs, JointState CDR decoded in blocks (bagio.decode_joint_states),
2. ``validate``: names, lengths and values checked, mapped to the robot's joints; every
   rejection counted by reason (``REJECT_REASONS``), never an exception or a NaN,
3. ``order``: out-of-order and repeated stamps rejected, a large backward jump a restart,
4. ``align``: motor currents matched to joint states by header stamp, and the joint torque,
5. ``rows``: the fixed-lag smoother on positions (and measured velocities) and torque alike,
   pinocchio's regressor, the base rows,
6. ``estimate``: recursive least squares (unless frozen), residual statistics, uncertainty
   and convergence; ``core`` composes them and predicts the torque.

Stages 1-4 together are ``TorqueSamples``, which batch identification (offline) runs too.
``window`` (SegmentWindow, optional) makes a pipeline process one time segment of a stream:
messages fed before stage 1, rows kept before stage 6 (parallel replay and fleet).
"""
from identification_node.pipeline.config import PipelineConfig
from identification_node.pipeline.core import IdentificationPipeline, PipelineOutput
from identification_node.pipeline.estimate import EstimateReport, converged
from identification_node.pipeline.samples import Samples
from identification_node.pipeline.status import PipelineStatus
from identification_node.pipeline.torque_samples import TorqueSamples
from identification_node.pipeline.validate import REJECT_REASONS
from identification_node.pipeline.window import SegmentWindow

__all__ = ['IdentificationPipeline', 'PipelineConfig', 'PipelineOutput', 'PipelineStatus',
           'EstimateReport', 'REJECT_REASONS', 'Samples', 'SegmentWindow', 'TorqueSamples',
           'converged']
