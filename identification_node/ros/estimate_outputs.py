"""The node's estimate outputs, published from each snapshot of the pipeline (on the
consistency worker's thread, ros/solver_worker.py):

- ``~/base_parameters`` (Float64MultiArray: row 0 values, row 1 standard deviations (-1: not
  determined yet), row 2 the unconstrained values; row 0 is the physically consistent
  estimate when its solve succeeded, else rows 0 and 2 agree),
- the output parameters (ros/parameters.py: ``estimate.*``, ``estimate_stddev.*``,
  ``estimate_unconstrained.*``, ``drive_gain.*``), in one parameter event,
- ``~/robot_description`` (String, transient local: URDF with the identified inertials and
  the payload), rebuilt only when new samples or a payload changed it,
- ``~/links/<link>/inertia`` (ros/link_outputs.py),

and the answer to the services the snapshot covers: ``~/get_estimate``'s JSON and what
``~/save`` writes.
"""
from __future__ import annotations

import json
import math
import os
import threading
from typing import Any, Callable

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String

from identification_node.errors import IdentificationError
from identification_node.estimation.consistency import ConsistentEstimate
from identification_node.model.urdf_export import consistency_problems, identified_urdf
from identification_node.payload.fit import urdf_with_payload
from identification_node.pipeline import EstimateReport
from identification_node.results.documents import plain, snapshot_document, write_results
from identification_node.ros.link_outputs import LinkOutputs
from identification_node.ros.parameters import (ESTIMATE_PREFIX, STDDEV_PREFIX,
                                                UNCONSTRAINED_PREFIX, OutputParameters)
from identification_node.ros.service_requests import Outcome, Snapshot

__all__ = ['LATCHED_QOS', 'EstimateOutputs']

LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


class EstimateOutputs:
    """The estimate's publishers of ``node`` (see the module doc). ``lock`` guards
    ``pipeline``, ``payload`` (PayloadOutputs or None) and ``drive_gains`` (DriveGainOutputs
    or None); ``save`` writes into ``output_directory`` (inconsistent estimates only with
    ``save_inconsistent``)."""

    def __init__(self, node: Node, pipeline, lock: threading.Lock,
                 parameters: OutputParameters, payload, drive_gains,
                 output_directory: str | os.PathLike, save_inconsistent: bool):
        self.node, self.pipeline, self.robot = node, pipeline, pipeline.robot
        self.parameters, self.payload, self.drive_gains = parameters, payload, drive_gains
        self._lock = lock
        self._output_directory, self._save_inconsistent = output_directory, save_inconsistent
        self.params = node.create_publisher(Float64MultiArray, '~/base_parameters', 10)
        self.urdf = node.create_publisher(String, '~/robot_description', LATCHED_QOS)
        self.links = LinkOutputs(node, self.robot)
        self.problems: list[str] = []   # why the published URDF is not physically consistent
        self._urdf_samples: Any = 0
        self._publish_lock = threading.Lock()

    def publish_snapshot(self, job: Snapshot,
                         solve: Callable[[tuple, bool], ConsistentEstimate]) -> Outcome:
        """Solve (physical consistency) with ``solve(equations, wait)`` (a save waits for the
        solver process's start-up), publish and, if asked, save ``job``: the answer to the
        requests it covers."""
        if job.error:
            return Outcome(error=job.error)
        est = job.estimate
        consistent = None if job.equations is None else solve(job.equations, job.save)
        values = self.publish(est, consistent)
        outcome = Outcome(estimate=json.dumps(plain({
            'names': est.names, 'values': values.tolist(),
            'stddev': est.stddev.tolist(), 'unconstrained_values': est.values.tolist(),
            'consistency_status': 'disabled' if consistent is None else consistent.status,
            'num_samples': est.num_samples, 'time': est.stamp, 'converged': est.converged,
            'condition_number': est.condition_number})))
        if job.save:
            doc = snapshot_document(self.robot, self.pipeline.base, est, job.covariance,
                                    job.rejected, consistent)
            if job.payload is not None:
                doc['payload'] = plain(job.payload.document())
            try:
                paths = write_results(self._output_directory, doc, self.robot, job.payload,
                                      self._save_inconsistent)
                outcome.saved = [str(p) for p in paths]
            except OSError as exc:
                outcome.save_error = f'cannot save: {exc}'
            except IdentificationError as exc:   # an inconsistent estimate, not asked for
                self.node.get_logger().error(str(exc))
                outcome.save_error = str(exc)
        return outcome

    def publish(self, est: EstimateReport, consistent: ConsistentEstimate | None
                ) -> np.ndarray:
        """Publish ``est`` (the consistent estimate where ``consistent`` succeeded); returns
        the values published (row 0)."""
        theta = None if consistent is None else consistent.theta   # None: it failed
        values = est.values if theta is None else theta
        phi_c = None if consistent is None else consistent.phi
        b = len(est.names)
        msg = Float64MultiArray()
        msg.layout.dim = [MultiArrayDimension(label='value_stddev_unconstrained', size=3,
                                              stride=3 * b),
                          MultiArrayDimension(label='base_parameter', size=b, stride=b)]
        stddev = np.where(np.isfinite(est.stddev), est.stddev, -1.0)   # -1: not determined yet
        msg.data = np.concatenate([values, stddev, est.values]).tolist()
        params = [Parameter(ESTIMATE_PREFIX + n, value=float(v))
                  for n, v in zip(est.names, values)]
        params += [Parameter(STDDEV_PREFIX + n, value=float(s))
                   for n, s in zip(est.names, stddev)]
        params += [Parameter(UNCONSTRAINED_PREFIX + n, value=float(v))
                   for n, v in zip(est.names, est.values)]
        if self.drive_gains is not None:
            with self._lock:
                params += self.drive_gains.parameters()
        with self._publish_lock:
            self.params.publish(msg)
            self.parameters.set(params)   # one parameter event, one snapshot
            # The URDF topic is latched: rebuild it only when new samples or the solve changed
            # the estimate.
            version = (est.num_samples, self.payload.version if self.payload else 0,
                       phi_c is not None)
            if est.num_samples and version != self._urdf_samples and self.robot.kind == 'urdf':
                self._urdf_samples = version
                with self._lock:
                    phi = phi_c if phi_c is not None else self.pipeline.standard_parameters()
                    payload = self.payload.current if self.payload else None
                self.problems = consistency_problems(self.robot, phi)
                urdf = identified_urdf(self.robot, phi)
                if payload is not None:
                    urdf = urdf_with_payload(urdf, payload)
                self.urdf.publish(String(data=urdf))
            if est.num_samples and math.isfinite(est.stamp):
                with self._lock:
                    phi = phi_c if phi_c is not None else self.pipeline.standard_parameters()
                self.links.publish(phi, int(round(est.stamp * 1e9)))
        return values
