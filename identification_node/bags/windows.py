"""Time windows of a bag (``identify --start S --end S``).

A window keeps the messages whose log (recording) time lies in [start, end) seconds after the
bag's first message, as ``ros2 bag play --start-offset`` counts; it applies to every input
topic alike (joint states and motor currents), before the pipeline's stages.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from identification_node.errors import IdentificationError


@dataclass(frozen=True)
class TimeWindow:
    """[start, end) s after the bag's first message; None: from the start / to the end."""
    start: float | None = None
    end: float | None = None

    def validate(self) -> TimeWindow:
        """IdentificationError for a window that cannot hold anything; returns self."""
        for name, v in (('--start', self.start), ('--end', self.end)):
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v)
                                      and v >= 0):
                raise IdentificationError(f'{name} must be a finite number of seconds >= 0, '
                                          f'got {v!r}')
        if self.start is not None and self.end is not None and not self.end > self.start:
            raise IdentificationError(f'--end {self.end:g} s must be after --start '
                                      f'{self.start:g} s')
        return self

    @property
    def whole(self) -> bool:
        return self.start is None and self.end is None

    def bounds_ns(self, bag: str, start_ns: int, end_ns: int) -> tuple[int, int]:
        """Log-time bounds [lo, hi) ns of the window in a bag whose messages span
        [start_ns, end_ns]; IdentificationError when the window misses the bag."""
        self.validate()
        span = (end_ns - start_ns) * 1e-9   # a bound past the bag's end is its end
        lo = start_ns + (0 if self.start is None else int(round(min(self.start, span + 1)
                                                                * 1e9)))
        hi = end_ns + 1 if self.end is None or self.end > span else \
            start_ns + int(round(self.end * 1e9))
        if lo > end_ns:
            raise IdentificationError(
                f'{bag}: --start {self.start:g} s is after the end of the bag (its messages '
                f'span {(end_ns - start_ns) * 1e-9:.6g} s)')
        return lo, hi

    def describe(self) -> dict:
        """The window as a JSON-ready mapping (s; None: open end)."""
        return {'start': self.start, 'end': self.end}


def in_window(log_ns: np.ndarray, bounds: tuple[int, int] | None) -> np.ndarray:
    """Boolean mask of the log times (ns) inside ``bounds`` (None: all)."""
    log_ns = np.asarray(log_ns, dtype=np.int64)
    if bounds is None:
        return np.ones(log_ns.shape, dtype=bool)
    return (log_ns >= bounds[0]) & (log_ns < bounds[1])


def empty_window_error(bag: str, window: TimeWindow) -> IdentificationError:
    """The error for a window that kept no message of the bag."""
    return IdentificationError(
        f'{bag}: no messages between --start {window.start or 0:g} s and --end '
        f'{"the end" if window.end is None else f"{window.end:g} s"}')
