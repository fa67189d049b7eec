"""The node's drive gains (``drive_gains.back_emf``, ``drive_gains.known_payload``).

- back-EMF: subscribes to ``motor_voltages`` (sensor_msgs/JointState shaped as
  ``motor_currents``: volts in effort) and takes a copy of the joint states and currents the
  pipeline gets; the processing thread sums them (pipeline/back_emf.py).
- known payload: the service ``~/drive_gains/known_payload`` (rcl_interfaces/SetParameters)
  marks segments: ``mass`` (double, > 0), ``com`` (double array, 3), ``inertia`` (double
  array ixx ixy ixz iyy iyz izz, about the com) and ``link`` (string, default the last
  identified link), as ``~/payload/set`` takes them, start a segment carrying that payload;
  ``mass`` 0 ends it. The pipeline's output in and out of the segments is summed
  (payload/known_payload.py).

Outputs, at every estimate refresh: the node parameters ``drive_gain.<joint>`` (N m/A at the
joint, K_T x gear ratio, the determined gain of least relative stddev; -1 while none is;
read-only) and, in diagnostics, ``drive_gain.<joint>.<method>`` (N m/A, or ``not
determined``) with ``.stddev``, ``.configured`` (kt x gear_ratio), ``.ratio``, ``.reason``
when not determined, and a ``.warning`` when they differ by more than 3 stddev and 5 %. The
node keeps its configured kt.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter

from identification_node.errors import IdentificationError
from identification_node.estimation.drive_gains import DriveGain, mark_used
from identification_node.payload.fit import attachment, payload_parameters
from identification_node.pipeline.back_emf import BackEmfStream
from identification_node.payload.known_payload import KnownPayloadSegments
from identification_node.ros.service_requests import Outcome, failed

PREFIX = 'drive_gain.'
UNKNOWN = -1.0
COMMAND = 'known_payload'


class DriveGainOutputs:
    """Drive gains of a node: ``tee`` the pipeline's input handlers (back-EMF), then
    ``process`` in the processing thread and read ``parameters`` / ``diagnostics`` under the
    node's lock. ``outputs`` (parameters.OutputParameters) declares ``drive_gain.<joint>``;
    ``subscribe(topic, handle)`` gives the node's polled input subscription."""

    def __init__(self, settings, pipeline, services, requests, outputs,
                 subscribe: Callable[[str, Callable[[list[bytes]], None]], Any]):
        converter = pipeline.converter
        if not converter.needs_currents:
            raise IdentificationError('parameters drive_gains.*: drive gains need '
                                      'current-driven joints (torque_source current or '
                                      'three_phase)')
        self.pipeline, self.requests = pipeline, requests
        self.stream = (BackEmfStream(converter, settings['align_tolerance'])
                       if settings['drive_gains.back_emf'] else None)
        self.segments = (KnownPayloadSegments(pipeline.robot, pipeline.base, converter)
                         if settings['drive_gains.known_payload'] else None)
        self.joints = converter.current_joints
        self.error = ''
        self._gains: list[DriveGain] = []
        for j in self.joints:
            outputs.declare(PREFIX + j, UNKNOWN, f'identified drive gain of {j}, N m/A at the '
                            'joint (-1: not determined yet)')
        self.voltages = (subscribe('motor_voltages', self.stream.voltages.add_cdr)
                         if self.stream is not None else None)
        if self.segments is not None:
            services.add(SetParameters, '~/drive_gains/known_payload', self._srv_known_payload)

    def tee(self, joint_states: Callable, currents: Callable) -> tuple[Callable, Callable]:
        """The pipeline's handlers, each also copying its messages into the back-EMF stream."""
        stream = self.stream
        if stream is None:
            return joint_states, currents

        def js(messages: list[bytes]) -> None:
            joint_states(messages)
            stream.joint_states.add_cdr(messages)

        def cur(messages: list[bytes]) -> None:
            currents(messages)
            stream.currents.add_cdr(messages)
        return js, cur

    def process(self, out) -> None:
        """Sum what came in (``out``: the pipeline's output); bad voltages are dropped and
        reported in diagnostics."""
        if self.stream is not None:
            try:
                self.stream.process()
            except IdentificationError as exc:
                self.error = str(exc)
        if self.segments is not None and len(out.stamps_ns):
            stride = self.pipeline.row_builder.half_window or 1
            self.segments.add(out.q, out.qd, out.qdd, out.measured, stride)

    def apply(self, argument) -> None:
        """The known-payload command (under the node's lock): (payload, link) or None."""
        assert self.segments is not None   # the command's service exists with them only
        if argument is None:
            self.segments.end()
        else:
            self.segments.start(*argument)

    def _refresh(self) -> list[DriveGain]:
        gains = []
        if self.stream is not None and self.stream.samples:
            gains += self.stream.gains()
        if self.segments is not None:
            try:
                gains += self.segments.gains()
            except IdentificationError:
                pass   # not both kinds of segment yet
        self._gains = mark_used(gains)
        return self._gains

    def parameters(self) -> list[Parameter]:
        used = {g.joint: g.value for g in self._refresh() if g.used and g.value is not None}
        return [Parameter(PREFIX + j, value=float(used.get(j, UNKNOWN))) for j in self.joints]

    def diagnostics(self) -> dict:
        out: dict[str, Any] = {}
        if self.stream is not None:
            out['drive_gains.back_emf_samples'] = self.stream.samples
        if self.segments is not None:
            out['drive_gains.known_payload_samples'] = (
                f"{self.segments.samples['loaded']} with, {self.segments.samples['free']} "
                'without the payload' + (' (segment open)' if self.segments.active else ''))
        if self.error:
            out['drive_gains.error'] = self.error
        for g in self._gains:
            key = f'{PREFIX}{g.joint}.{g.method}'
            out[key] = g.value           # None: 'not determined' (ros/diagnostics.py)
            out[key + '.stddev'] = g.stddev
            out[key + '.configured'] = g.configured
            out[key + '.ratio'] = g.ratio
            if g.value is None:
                out[key + '.reason'] = g.reason
            elif g.warning:
                out[key + '.warning'] = g.warning
        return out

    # the service: validated here, applied by the node's processing thread in order
    def _srv_known_payload(self, req: SetParameters.Request, reply: Callable) -> None:
        res = SetParameters.Response()
        given = {p.name: Parameter.from_parameter_msg(p).value for p in req.parameters}
        try:
            unknown = set(given) - {'mass', 'com', 'inertia', 'link'}
            if unknown or 'mass' not in given:
                raise IdentificationError(f'give mass (and com, inertia, link) only; got '
                                          f'{sorted(given)}')
            mass = float(given['mass'])
            argument = None
            if mass != 0:
                phi = payload_parameters(mass, np.asarray(given.get('com', [0.0] * 3), float),
                                         np.asarray(given.get('inertia', [0.0] * 6), float))
                link = given.get('link') or None
                attachment(self.pipeline.robot, link)   # refuse an unknown link now
                argument = (phi, link)
        except (IdentificationError, TypeError, ValueError) as exc:
            reply(failed(res, str(exc)))
            return
        text = 'known-payload segment ' + ('started' if argument is not None else 'ended')

        def answer(outcome: Outcome) -> None:
            if outcome.error:
                reply(failed(res, outcome.error))
            else:
                res.results = [SetParametersResult(successful=True, reason=text)]
                reply(res)
        self.requests.command(COMMAND, argument, answer)
