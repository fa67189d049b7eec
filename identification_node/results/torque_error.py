"""Relative torque errors of parameter sets, and the torque errors of an estimate on one bag
(BagError). Percent; torques N m."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from identification_node.bags.windows import TimeWindow
from identification_node.results.identification import TorqueSeries

__all__ = ['TorqueError', 'relative_error', 'ErrorSums', 'BagError']


@dataclass
class TorqueError:
    """Relative error (percent): ``stacked`` over all joints, ``per_joint`` (n,)."""
    stacked: float
    per_joint: np.ndarray


def relative_error(measured: np.ndarray, predicted: np.ndarray) -> TorqueError:
    """100 ||measured - predicted|| / ||measured|| of (N, n) torques, stacked and per joint."""
    sums = ErrorSums(np.shape(measured)[1], 1)
    sums.add(measured, np.asarray(predicted)[None])
    return sums.error(0)


class ErrorSums:
    """Sums of squares for the relative errors of k predictions of n joint torques."""

    def __init__(self, n: int, k: int):
        self.reference = np.zeros(n)        # sum tau^2 per joint
        self.residual = np.zeros((k, n))    # sum (tau - tau_hat)^2 per prediction and joint
        self.count = 0

    def add(self, measured: np.ndarray, predicted: np.ndarray) -> None:
        """measured (N, n), predicted (k, N, n)."""
        measured = np.asarray(measured, dtype=float)
        self.reference += np.einsum('ij,ij->j', measured, measured)
        r = measured[None] - np.asarray(predicted, dtype=float)
        self.residual += np.einsum('kij,kij->kj', r, r)
        self.count += len(measured)

    def error(self, k: int) -> TorqueError:
        """The relative errors of prediction k (inf where the reference is 0, 0 if both)."""
        with np.errstate(divide='ignore', invalid='ignore'):
            joint = np.where(self.residual[k] == 0, 0.0,
                             100.0 * np.sqrt(self.residual[k] / self.reference))
            stacked = (0.0 if self.residual[k].sum() == 0 else
                       100.0 * np.sqrt(self.residual[k].sum() / self.reference.sum()))
        return TorqueError(float(stacked), joint)


@dataclass
class BagError:
    """Torque errors of several parameter vectors on one bag (``errors`` name -> TorqueError,
    against the raw torque; ``smoothed``: the same against the smoothed torque), over
    ``num_samples`` samples; ``series``: a subsample (stamps ns, raw torque, base regressor
    rows, positions) for plots and checks."""
    bag: str
    joints: list[str]
    num_samples: int
    errors: dict[str, TorqueError]
    smoothed: dict[str, TorqueError]
    window: TimeWindow | None = None
    series: TorqueSeries | None = None
    rejected: dict = field(default_factory=dict)
    # per joint std of the torque sensor's noise (N m): of raw minus smoothed torque, whose
    # white-noise variance is (1 - gain) of the raw one (the smoother's centre weight is its
    # gain, signals.smoothing_noise_gain); nan where unknown
    noise_std: np.ndarray | None = None

    @property
    def relative_error(self) -> np.ndarray:
        """Per-joint error of the estimate (percent)."""
        return self.errors['estimate'].per_joint

    def document(self) -> dict:
        """JSON-ready: per parameter set the stacked and per-joint errors (percent)."""
        def one(e: TorqueError) -> dict:
            return {'stacked': e.stacked, 'per_joint': dict(zip(self.joints,
                                                                e.per_joint.tolist()))}
        return {'bag': self.bag, 'num_samples': self.num_samples,
                'window_s': None if self.window is None or self.window.whole
                else self.window.describe(),
                'reference': 'raw torque (measured, or converted from currents), every '
                             'sample the smoother gives motion for',
                **{k: one(e) for k, e in self.errors.items()},
                'smoothed_torque': {k: one(e) for k, e in self.smoothed.items()}}
