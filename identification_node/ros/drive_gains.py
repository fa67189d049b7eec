"""The node's back-EMF drive gains (``drive_gains.back_emf``), wiring a BackEmfStream.

Subscribes to ``motor_voltages`` (sensor_msgs/JointState shaped as ``motor_currents``: volts in
effort) and takes a copy of the joint states and currents the pipeline gets; the processing
thread sums them (pipeline/back_emf.py). Outputs, at every estimate refresh: the node
parameters ``drive_gain.<joint>`` (N m/A at the joint, K_T x gear ratio; -1 while not
determined; read-only) and, in diagnostics, ``drive_gain.<joint>`` with its stddev, the
configured kt x gear_ratio and their ratio, or why it is not determined, and a warning when
they differ by more than 3 stddev and 5 %.
"""
from __future__ import annotations

from typing import Callable

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.parameter import Parameter

from identification_node.errors import IdentificationError
from identification_node.estimation.drive_gains import DriveGain
from identification_node.model.torque import TorqueConverter
from identification_node.pipeline.back_emf import BackEmfStream

PREFIX = 'drive_gain.'
UNKNOWN = -1.0


class DriveGainOutputs:
    """Back-EMF gains of ``node`` (an IdentificationNode); ``tee`` the pipeline's input
    handlers through ``joint_states``/``currents``, then ``process`` in the processing thread
    and read ``parameters``/``diagnostics`` under the node's lock."""

    def __init__(self, node, converter: TorqueConverter, align_tolerance: float):
        self.stream = BackEmfStream(converter, align_tolerance)
        self.joints = [j for j, c in zip(converter.joint_names, converter.configs)
                       if c.source != 'measured']
        self.error = ''
        self._gains: list[DriveGain] = []
        for j in self.joints:
            node.declare_parameter(PREFIX + j, UNKNOWN, ParameterDescriptor(
                description=f'drive gain of {j} from the back-EMF, N m/A at the joint '
                '(-1: not determined yet)'))
        node._estimate_names.update(PREFIX + j for j in self.joints)
        self.voltages = node._subscribe('motor_voltages', self.stream.voltages.add_cdr)

    def tee(self, joint_states: Callable, currents: Callable) -> tuple[Callable, Callable]:
        """The pipeline's handlers, each also copying its messages into the stream."""
        def js(messages: list[bytes]) -> None:
            joint_states(messages)
            self.stream.joint_states.add_cdr(messages)

        def cur(messages: list[bytes]) -> None:
            currents(messages)
            self.stream.currents.add_cdr(messages)
        return js, cur

    def process(self) -> None:
        """Sum what came in; bad voltages are dropped and reported (diagnostics)."""
        try:
            self.stream.process()
        except IdentificationError as exc:
            self.error = str(exc)

    def _refresh(self) -> list[DriveGain]:
        if self.stream.samples:
            self._gains = self.stream.gains()
        return self._gains

    def parameters(self) -> list[Parameter]:
        gains = {g.joint: g for g in self._refresh()}
        return [Parameter(PREFIX + j, value=float(gains[j].value) if j in gains
                          and gains[j].value is not None else UNKNOWN) for j in self.joints]

    def diagnostics(self) -> dict:
        out = {'drive_gains.samples': self.stream.samples}
        if self.error:
            out['drive_gains.error'] = self.error
        for g in self._gains:
            key = PREFIX + g.joint
            if g.value is None:
                out[key] = f'not determined: {g.reason}'
            else:
                out[key] = f'{g.value:.6g} +- {g.stddev:.2g} (back_emf)'
                out[key + '.configured'] = f'{g.configured:.6g}'
                out[key + '.ratio'] = f'{g.ratio:.5f}'
            if g.warning and g.value is not None:
                out[key + '.warning'] = g.warning
        return out
