"""Diagnostics values as text a controller or a dashboard parses: a number (integers as they
are, other numbers to 6 significant digits, SI units as the key says), ``true``/``false``,
a word or sentence, or the literal ``not determined`` (no value yet: no samples, not chosen,
not finite, not known with this middleware) or ``not excited`` (the motion did not excite
the quantity). Never Python syntax (None, lists, reprs)."""
from __future__ import annotations

import math
from numbers import Integral, Real
from typing import Any, Mapping, Sequence

import numpy as np
from diagnostic_msgs.msg import KeyValue

NOT_DETERMINED = 'not determined'
NOT_EXCITED = 'not excited'
# SmootherChoice.source in words ('automatic' stays)
SMOOTHER_SOURCES = {'half_window': 'given half window', 'cutoff': 'given cut-off',
                    'automatic': 'automatic', 'fallback': 'fallback cut-off'}


def plain(value: Any) -> str:
    """One value as diagnostics text (see the module docstring)."""
    if value is None:
        return NOT_DETERMINED
    if isinstance(value, (bool, np.bool_)):
        return 'true' if value else 'false'
    if isinstance(value, Integral):
        return str(int(value))
    if isinstance(value, Real):
        return f'{float(value):.6g}' if math.isfinite(value) else NOT_DETERMINED
    if isinstance(value, str):
        return value
    raise TypeError(f'diagnostics value {value!r}: give a number, bool, str or None '
                    '(vectors as one key per element)')


def vector(key: str, names: Sequence[str], values: Sequence[Any] | np.ndarray,
           excited: Sequence[bool] | None = None) -> dict[str, Any]:
    """``key.<name>`` per element; ``not excited`` where ``excited`` is false."""
    flags = [True] * len(names) if excited is None else excited
    return {f'{key}.{n}': (v if ok else NOT_EXCITED)
            for n, v, ok in zip(names, values, flags)}


def key_values(values: Mapping[str, Any]) -> list[KeyValue]:
    """``values`` (key -> plain value) as diagnostic_msgs KeyValues, in order."""
    return [KeyValue(key=k, value=plain(v)) for k, v in values.items()]
