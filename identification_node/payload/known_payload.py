"""Known-payload drive gains from the streaming pipeline's output (the node's counterpart of
``identify --known-payload-bag``): segments marked as carrying a known payload and the rest
summed into the per-joint normal equations of estimation/drive_gains.py (the current as the
output: tau_conf = Y psi + c tau_payload), with the pipeline's smoothed motion and torque.

Smoothed samples are correlated over the smoother's window, so every ``stride``-th is used
(default: the smoother's half window), which keeps the residuals nearly white and the stddev
honest.
"""
from __future__ import annotations

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.estimation.drive_gains import (DriveGain, known_payload_gains,
                                                        payload_equations)
from identification_node.estimation.normal_equations import NormalEquations
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.model.torque import TorqueConverter
from identification_node.payload.fit import attachment, with_payload


class KnownPayloadSegments:
    """``start(payload, link)`` / ``end()`` mark the segments; ``add`` takes pipeline outputs
    (stamps, q, qd, qdd, measured torque of the configured gains); ``gains`` solves."""

    def __init__(self, robot: RobotModel, base: BaseParameters, converter: TorqueConverter):
        self.robot, self.base, self.converter = robot, base, converter
        self.equations = NormalEquations.zeros(base.num_base + 1, robot.dof)
        self.samples = {'free': 0, 'loaded': 0}
        self.mass = 0.0
        self._d_beta: np.ndarray | None = None
        self._skip = 0

    @property
    def active(self) -> bool:
        return self._d_beta is not None

    def start(self, payload: np.ndarray, link: str | None = None) -> None:
        """From now on the arm carries ``payload`` (10 parameters in ``link``'s frame, about
        its origin; link default the last identified one)."""
        attach = attachment(self.robot, link)
        self._d_beta = self.base.to_base(with_payload(
            self.robot, attach, np.zeros(self.robot.num_params), payload))
        self.mass = float(payload[0])

    def end(self) -> None:
        """From now on the arm carries no payload."""
        self._d_beta = None

    def add(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, tau: np.ndarray,
            stride: int = 1) -> None:
        """Samples (N, n) of the current segment, every ``stride``-th used."""
        stride = max(int(stride), 1)
        pick = np.arange(self._skip, len(q), stride)
        self._skip = int(pick[-1] + stride - len(q)) if len(pick) else self._skip - len(q)
        if len(pick) == 0:
            return
        Yb = self.base.base_regressor(self.robot.regressor(q[pick], qd[pick], qdd[pick]))
        payload = Yb @ self._d_beta if self.active else None
        self.equations = self.equations + payload_equations(Yb, tau[pick], payload)
        self.samples['loaded' if self.active else 'free'] += len(pick)

    def gains(self) -> list[DriveGain]:
        """Gains of the current-driven joints; IdentificationError before both kinds of
        segment have samples."""
        if not (self.samples['free'] and self.samples['loaded']):
            raise IdentificationError(
                f"known payload: {self.samples['loaded']} samples with and "
                f"{self.samples['free']} without the payload; both are needed")
        configured = np.array([c.kt * c.gear_ratio for c in self.converter.configs])
        gains = known_payload_gains(self.robot.joint_names, self.equations, configured,
                                    self.mass)
        return [g for g in gains if g.joint in self.converter.current_joints]
