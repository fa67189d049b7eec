"""Robust estimation: innovation gating of the recursive estimator's samples, which rejects
spikes without hiding a sustained residual shift.

Once the estimate has converged, a sample whose torque residual (measured minus predicted by
the current estimate) exceeds ``k`` standard deviations of that innovation on any joint is an
outlier: it is held back from the estimator and counted. The innovation's variance is the
residual's and the estimate's own on that sample, y P y' (large on motion the fit has not
seen yet). One sample, or a burst of a few per cent, then cannot move a converged estimate.
A payload change looks different: most samples miss the model, for as long as it lasts.
When at least ``shift_fraction`` of the last ``window`` samples were gated, the gate reports
a residual shift (``events``, ``listeners``), gives the held-back samples of the window to the
estimator after all and stops gating, so the estimate follows the new data instead of
rejecting it forever. Gating resumes once the gated fraction falls below half of
``shift_fraction``.

The gate arms once the estimate has converged and predicts the batch at hand: at most
``ARM_FRACTION`` of its samples beyond k sigma. A converged fit of the motion so far can still
miss motion it has not seen; gating then would hold good samples back.

Plain arrays in SI units (residuals in N m or N, per sample and joint); no ROS.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from identification_node.config import Robust
from identification_node.errors import IdentificationError

ARM_FRACTION = 0.05   # of a batch's samples beyond k sigma, at most, for the gate to arm


@dataclass
class RobustSettings:
    """The gate's settings (the node's ``robust.*`` parameters)."""
    enabled: bool = Robust.enabled
    k: float = Robust.k                     # innovation standard deviations beyond: gated
    window: int = Robust.window             # samples over which the gated fraction is watched
    shift_fraction: float = Robust.shift_fraction   # gated fraction that is a residual shift

    def validate(self) -> None:
        checks = [('k', math.isfinite(self.k) and self.k >= 2, 'finite and >= 2'),
                  ('window', int(self.window) >= 1, 'an integer >= 1'),
                  ('shift_fraction', 0 < self.shift_fraction <= 1, 'in (0, 1]')]
        for name, ok, expected in checks:
            if not ok:
                raise IdentificationError(
                    f'parameter robust.{name} = {getattr(self, name)!r} must be {expected}')


@dataclass
class ResidualShift:
    """A residual shift event: ``fraction`` of the last ``window`` samples were beyond k sigma
    of the estimate, up to the sample stamped ``stamp`` (s since the pipeline's epoch)."""
    stamp: float
    fraction: float
    window: int
    held: int          # samples the gate had held back and gave to the estimator after all


class InnovationGate:
    """Innovation gating of batches of samples (see the module doc); ``armed`` turns it on
    (the pipeline arms it once its estimate has converged)."""

    def __init__(self, settings: RobustSettings | None = None, events: int = 100):
        self.settings = settings or RobustSettings()
        self.settings.validate()
        self.listeners: list[Callable[[ResidualShift], Any]] = []
        self.events: collections.deque = collections.deque(maxlen=events)
        self.reset()

    def reset(self) -> None:
        """Disarmed, nothing held, counters at 0 (listeners stay)."""
        self.armed = False
        self.suspended = False     # gating stopped by a residual shift
        self.outliers = 0          # samples gated and not given back
        self.shifts = 0
        self._recent: collections.deque = collections.deque()   # [samples, gated, held]
        self._samples = self._gated = 0

    @property
    def gated_fraction(self) -> float:
        """Fraction of the last ``window`` samples beyond k sigma (0 while disarmed)."""
        return self._gated / max(self._samples, int(self.settings.window))

    def beyond(self, residuals: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Mask (N,) of the samples whose residual (N, n) exceeds k sigma ((n,) or (N, n)) on
        any joint (NaN residuals included; a non-finite sigma gates nothing)."""
        scale = np.where(np.isfinite(sigma) & (sigma > 0), sigma, np.inf)
        with np.errstate(invalid='ignore'):
            return (~(np.abs(residuals) <= self.settings.k * scale)).any(axis=1)

    def arm(self, residuals: np.ndarray, sigma: np.ndarray) -> bool:
        """Arm when at most ARM_FRACTION of the batch's residuals (N, n) of the converged
        estimate are beyond k sigma ((n,) or (N, n)): it predicts motion it has not been
        fitted to."""
        if len(residuals):
            self.armed = bool(np.mean(self.beyond(residuals, sigma)) <= ARM_FRACTION)
        return self.armed

    def screen(self, residuals: np.ndarray, sigma: np.ndarray, held: Any = None,
               stamp: float = math.nan) -> tuple[np.ndarray, list]:
        """Decide a batch: residuals (N, n) of the current estimate, sigma their standard
        deviation ((n,) per joint, or (N, n) per sample and joint), ``held`` what to keep of
        the gated samples (a callable taking the bool mask of the gated samples). Returns the
        mask (N,) of samples to use and the held-back items of earlier batches to use after
        all (a residual shift)."""
        N = len(residuals)
        keep = np.ones(N, dtype=bool)
        s = self.settings
        if not (s.enabled and self.armed) or N == 0:
            return keep, []
        gated = self.beyond(residuals, sigma)
        count = int(np.count_nonzero(gated))
        self._recent.append([N, count, None])
        self._samples += N
        self._gated += count
        while self._recent and self._samples - self._recent[0][0] >= s.window:
            old_n, old_gated, _ = self._recent.popleft()
            self._samples -= old_n
            self._gated -= old_gated
        fraction = self.gated_fraction
        if self.suspended:
            if fraction < 0.5 * s.shift_fraction:
                self.suspended = False
            return keep, []
        if fraction >= s.shift_fraction:
            return keep, self._shift(stamp, fraction)
        self.outliers += count
        if count and held is not None:
            self._recent[-1][2] = held(gated)
        return ~gated, []

    def _shift(self, stamp: float, fraction: float) -> list:
        """Residual shift: stop gating, give back what the window held, tell the listeners."""
        self.suspended = True
        self.shifts += 1
        given = [entry[2] for entry in self._recent if entry[2] is not None]
        back = sum(entry[1] for entry in self._recent if entry[2] is not None)
        for entry in self._recent:
            entry[2] = None
        self.outliers -= back
        event = ResidualShift(float(stamp), float(fraction), int(self.settings.window), back)
        self.events.append(event)
        for listener in list(self.listeners):
            listener(event)
        return given
