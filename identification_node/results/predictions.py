"""``identify --predictions OUT``: measured and predicted joint torque per sample.

``OUT`` is written as an mcap rosbag2 bag and ``OUT.csv`` beside it; an ``OUT`` ending in
``.csv`` gives the CSV alone. Each evaluated bag (``training``, ``validation1``, ...) has two
sensor_msgs/JointState topics, ``/<label>/measured_effort`` and ``/<label>/predicted_effort``:
joint names, effort (N m; N for prismatic joints), header stamp = log time = the sample's
stamp, so PlotJuggler and Foxglove plot them as recorded. The CSV has one row per sample:
``bag`` (the label), ``stamp_ns``, ``t`` (s after the bag's first message), then
``measured.<joint>`` and ``predicted.<joint>``. Both files are written atomically.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from identification_node.bags.writer import BagWriter, check_replaceable
from identification_node.errors import IdentificationError
from identification_node.fileio import atomic_file
from identification_node.wire.cdr import JOINT_STATE, encode_joint_states

__all__ = ['prediction_paths', 'check_predictions', 'PredictionsWriter']


def prediction_paths(out: str | os.PathLike) -> tuple[Path | None, Path]:
    """(bag directory or None, CSV file) of ``--predictions out``."""
    out = Path(out)
    if out.suffix.lower() == '.csv':
        return None, out
    return out, out.with_name(out.name + '.csv')


def check_predictions(out: str | os.PathLike) -> None:
    """IdentificationError before any computation when ``out`` would replace something
    that is not a bag (a directory without metadata.yaml, or a file)."""
    bag, _ = prediction_paths(out)
    if bag is not None:
        check_replaceable(bag, '--predictions')


class PredictionsWriter:
    """Streams the samples of evaluated bags into the predictions bag and CSV."""

    def __init__(self, out: str | os.PathLike, joints: list[str]):
        check_predictions(out)
        self.joints = list(joints)
        self.bag_path, self.csv_path = prediction_paths(out)
        self._stack = contextlib.ExitStack()
        self._origin: dict[str, int] = {}
        self._bag = None
        try:
            self._csv = self._stack.enter_context(atomic_file(self.csv_path))
            self._csv.write(','.join(['bag', 'stamp_ns', 't']
                                     + [f'measured.{j}' for j in self.joints]
                                     + [f'predicted.{j}' for j in self.joints]) + '\n')
            if self.bag_path is not None:
                self._bag = BagWriter(self.bag_path, 'mcap', overwrite=True)
        except BaseException:
            self._stack.close()
            raise

    def begin(self, label: str, origin_ns: int) -> None:
        """Samples of ``label`` follow; ``origin_ns``: its bag's first log time (CSV t = 0)."""
        self._origin[label] = int(origin_ns)
        if self._bag is not None:
            for kind in ('measured', 'predicted'):
                self._bag.add_topic(f'/{label}/{kind}_effort', JOINT_STATE)

    def add(self, label: str, stamps_ns: np.ndarray, measured: np.ndarray,
            predicted: np.ndarray) -> None:
        """Samples (N,) int64 ns with measured and predicted torque (N, n)."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        if self._bag is not None:
            for kind, values in (('measured', measured), ('predicted', predicted)):
                topic = f'/{label}/{kind}_effort'
                for stamp, cdr in zip(stamps_ns.tolist(), encode_joint_states(
                        stamps_ns, self.joints, effort=values)):
                    self._bag.write_raw(topic, max(stamp, 0), cdr)
        rows = np.empty((len(stamps_ns), 3 + 2 * len(self.joints)), dtype=object)
        rows[:, 0] = label
        rows[:, 1] = stamps_ns.astype(object)
        rows[:, 2] = (stamps_ns - self._origin.get(label, 0)) * 1e-9
        rows[:, 3:] = np.hstack([measured, predicted])
        np.savetxt(self._csv, rows, fmt='%s,%d' + ',%.17g' * (rows.shape[1] - 2))

    def close(self) -> None:
        """Commit both files (the bag first: the CSV then lands only with it)."""
        if self._bag is not None:
            self._bag.close()
        self._stack.close()

    def abort(self) -> None:
        if self._bag is not None:
            self._bag.abort()
        self._stack.__exit__(IdentificationError, IdentificationError('aborted'), None)

    def __enter__(self) -> PredictionsWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
