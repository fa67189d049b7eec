"""Stages 1-4 composed: queued inputs to validated samples with joint torque, in stamp order.

intake (decode) -> validate -> stamp order -> current alignment -> torque. The streaming
pipeline smooths and estimates what comes out; batch identification (batch/samples.py)
collects it. Both run exactly this.
"""
from __future__ import annotations

from identification_node.model.plausibility import PlausibilityBounds
from identification_node.model.robot import RobotModel
from identification_node.model.torque import JointTorqueConfig, TorqueConverter
from identification_node.pipeline.align import CurrentAlignment
from identification_node.pipeline.config import PipelineConfig
from identification_node.pipeline.intake import Intake
from identification_node.pipeline.order import StampOrder
from identification_node.pipeline.samples import Samples, stack_records
from identification_node.pipeline.validate import Counters, CurrentValidator, JointStateValidator
from identification_node.wire.records import JointStateRecord


class TorqueSamples:
    """The input stages of ``robot`` under ``config``: ``add_*`` queue, ``process`` returns the
    samples decided since the last call (all of the newest stream: a restart drops what the
    old one left pending), with counted rejections in ``counters``."""

    def __init__(self, robot: RobotModel, config: PipelineConfig):
        self.robot, self.config = robot, config
        configs = [config.torque.get(j, JointTorqueConfig()) for j in robot.joint_names]
        self.converter = TorqueConverter(robot.joint_names, configs)
        self.counters = Counters()
        self.bounds = PlausibilityBounds.from_robot(
            robot, config.plausibility, [c.gear_ratio for c in configs], [c.kt for c in configs])
        self.joint_states, self.motor_currents = Intake(self.counters), Intake(self.counters)
        limits = (config.max_names, config.layout_cache_bytes)
        self.validate = JointStateValidator(robot, self.converter, config.velocity,
                                            self.counters, self.bounds, *limits)
        self.validate_currents = CurrentValidator(robot, self.converter, self.counters,
                                                  self.bounds, *limits)
        self.alignment = CurrentAlignment(self.converter, robot.dof, config.align_tolerance,
                                          config.hold_time, self.counters, self.bounds)
        self.order = StampOrder(
            config.restart_jump, self.counters,
            lambda newest: self.alignment.restart(newest, config.restart_jump))

    def reset(self) -> None:
        """Forget all queued and buffered data; counters restart too."""
        self.counters.reset()
        self.validate.reset()
        self.order.reset()
        self.alignment.reset()
        self.joint_states.clear()
        self.motor_currents.clear()

    # -- input ----------------------------------------------------------------------------------
    def add_joint_state(self, record: JointStateRecord) -> None:
        self.joint_states.add(record)

    def add_joint_states(self, block: JointStateRecord) -> None:
        self.joint_states.add_block(block)

    def add_joint_state_cdr(self, messages: list[bytes]) -> None:
        self.joint_states.add_cdr(messages)

    def add_currents(self, record: JointStateRecord) -> None:
        self.motor_currents.add(record)

    def add_currents_cdr(self, messages: list[bytes]) -> None:
        self.motor_currents.add_cdr(messages)

    def add_malformed(self, log_ns: int | None = None) -> None:
        """Count a message that could not even be decoded (received, and rejected; by its
        log time ``log_ns`` when given: Counters.malformed)."""
        self.joint_states.malformed(log_ns)

    @property
    def pending(self) -> int:
        """Queued inputs not yet processed."""
        return len(self.joint_states) + len(self.motor_currents)

    @property
    def velocity_measured(self) -> bool:
        return self.validate.velocity_measured

    # -- processing -----------------------------------------------------------------------------
    def process(self, flush: bool = False) -> Samples:
        """Work through everything queued; ``flush`` decides joint states still waiting for
        currents (end of a bag) instead of holding them for ``hold_time``."""
        js = self.joint_states.take()
        cur = self.motor_currents.take()
        if cur:
            self.alignment.add_currents(self.validate_currents(cur))
        for block in stack_records(js):
            # in order after validation; a restart there drops what is pending: add after
            self.alignment.add_joint_states(self.order(self.validate(block)))
        return self.alignment.ready(flush)
