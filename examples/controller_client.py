"""Example controller-side client: feedforward torque from a running identification node.

The identification node exposes its running estimate as ROS parameters of its own:
``base_parameter_names`` (the order) and ``estimate.<name>`` / ``estimate_stddev.<name>`` (SI
units). A controller reads them with the standard GetParameters service and computes the
feedforward joint torque with the same robot model::

    import rclpy
    from controller_client import IdentifiedModel      # this file, on the Python path

    rclpy.init()
    node = rclpy.create_node('my_controller')
    model = IdentifiedModel.from_node(node, '/identification_node')
    tau_ff = model.feedforward(q, qd, qdd)      # (n,) N m, joints in model.joint_names order

``tau_ff = Yb(q, qd, qdd) theta``: Yb is the base regressor of the robot model the node
identifies (same robot description, joints, extras), theta the base parameter estimate. Call
``from_node`` again to pick up a newer estimate. The node's ``~/get_estimate``
Trigger service returns the same estimate as one JSON document, if you prefer that.
"""
from __future__ import annotations

import threading
from typing import Sequence

import numpy as np
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python

from identification_node.errors import IdentificationError
from identification_node.model.identifiability import BaseParameters
from identification_node.model.robot import RobotModel
from identification_node.settings import Settings

# The node parameters that define the identified model (see config.PARAMETERS).
MODEL_PARAMETERS = ('robot', 'robot_description', 'joints', 'extras', 'coulomb_velocity')


class ParameterClient:
    """GetParameters of one node ``target`` (e.g. '/identification_node'). Spins ``node``
    while waiting unless an executor already spins it."""

    def __init__(self, node: Node, target: str, timeout: float = 5.0):
        self.node, self.target, self.timeout = node, target.rstrip('/'), timeout
        self.client = node.create_client(GetParameters, f'{self.target}/get_parameters')
        if not self.client.wait_for_service(timeout_sec=timeout):
            self.close()
            raise IdentificationError(f'no GetParameters service of node {target}')

    def get(self, names: Sequence[str]) -> dict:
        """Values of parameters ``names``; unset ones are None."""
        future = self.client.call_async(GetParameters.Request(names=list(names)))
        executor = self.node.executor   # (rclpy leaves it set after spin_until_future_complete)
        if executor is None or self.node not in executor.get_nodes():
            import rclpy
            rclpy.spin_until_future_complete(self.node, future, timeout_sec=self.timeout)
        else:
            done = threading.Event()
            future.add_done_callback(lambda _: done.set())
            done.wait(self.timeout)
        if not future.done() or future.result() is None:
            raise IdentificationError(f'node {self.target} did not answer GetParameters')
        return {n: parameter_value_to_python(v)
                for n, v in zip(names, future.result().values)}

    def close(self) -> None:
        self.node.destroy_client(self.client)


class IdentifiedModel:
    """The identified base parameters ``theta`` of ``robot``, with their standard deviations
    ``stddev`` (-1 where the node has none yet)."""

    def __init__(self, robot: RobotModel, names: Sequence[str], theta: Sequence[float],
                 stddev: Sequence[float] | None = None):
        self.robot = robot
        self.base = BaseParameters.from_robot(robot)
        if list(names) != list(self.base.names):
            raise IdentificationError(
                f'base parameters {list(names)} do not match the model of {robot.name} '
                f'({self.base.names}): use the robot, joints and extras of the node')
        self.names = list(names)
        self.theta = np.asarray(theta, dtype=float)
        self.stddev = None if stddev is None else np.asarray(stddev, dtype=float)

    @property
    def joint_names(self) -> list[str]:
        return self.robot.joint_names

    @classmethod
    def from_node(cls, node: Node, target: str = '/identification_node',
                  robot: RobotModel | str | None = None,
                  timeout: float = 5.0) -> IdentifiedModel:
        """Fetch the current estimate of the identification node ``target``. ``robot``: the
        model (a RobotModel, or a bundled name or URDF path, identifying the node's joints);
        default: the one the node's parameters describe."""
        client = ParameterClient(node, target, timeout)
        try:
            names = client.get(['base_parameter_names'])['base_parameter_names']
            if not names:
                raise IdentificationError(f'node {target} has no base_parameter_names')
            values = client.get([f'estimate.{n}' for n in names]
                                + [f'estimate_stddev.{n}' for n in names] + list(MODEL_PARAMETERS))
        finally:
            client.close()
        if not isinstance(robot, RobotModel):
            model = {k: values[k] for k in MODEL_PARAMETERS if values[k] is not None}
            if values['extras'] is None:   # declared with its default unless given as []
                model['extras'] = []
            if isinstance(robot, str):
                model.update(robot=robot, robot_description='')
            robot = Settings.from_dict(model).load_robot()
        theta = [values[f'estimate.{n}'] for n in names]
        stddev = [values[f'estimate_stddev.{n}'] for n in names]
        return cls(robot, names, theta, stddev)

    def feedforward(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """Joint torques Yb(q, qd, qdd) theta (N m; N for prismatic joints) for one sample
        (n,) or many (N, n), joints in ``joint_names`` order."""
        q, qd, qdd = (np.asarray(a, dtype=float) for a in (q, qd, qdd))
        single = q.ndim == 1
        Yb = self.base.base_regressor(self.robot.regressor(
            np.atleast_2d(q), np.atleast_2d(qd), np.atleast_2d(qdd)))
        tau = Yb @ self.theta
        return tau[0] if single else tau
