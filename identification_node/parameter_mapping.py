"""Identified quantities as another node's parameters (ros/parameter_forwarder.py, ROS-free):
the mapping ``remote.parameter=quantity``, each quantity's value and standard deviation from
what the identification node publishes, the physical checks a value must pass, and the gate
that lets a change through only when it exceeds ``threshold`` standard deviations.

Quantities (SI units, the payload's in the frame of its link, ``payload.link``):

- ``payload.mass`` (kg), ``payload.weight`` (N, m g with g = GRAVITY),
  ``payload.com`` (3 values, m) or ``payload.com.x|y|z`` (from ``~/payload`` and
  ``~/payload/stddev``);
- ``<joint>.fv|fc|fo|Ia``, ``<link>.m`` or any other base parameter that is one standard
  parameter on its own (from the node's ``estimate.<name>`` / ``estimate_stddev.<name>``
  parameters); a regrouped base parameter (name ending in R) is refused.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from identification_node.errors import IdentificationError

GRAVITY = 9.80665   # m/s^2, standard gravity
PAYLOAD_QUANTITIES = ('payload.mass', 'payload.weight', 'payload.com', 'payload.com.x',
                      'payload.com.y', 'payload.com.z')
# the checks of model/urdf_export.consistency_problems, per quantity
POSITIVE = ('m',)               # > 0
NON_NEGATIVE = ('fv', 'fc', 'Ia')
# preset: its target node, the frame parameter and the mapping (remote parameter: quantity)
ADMITTANCE: dict[str, Any] = {
    'target': '/admittance_controller',
    'frame_parameter': 'gravity_compensation.frame.id',
    'mapping': {'gravity_compensation.CoG.pos': 'payload.com',
                'gravity_compensation.CoG.force': 'payload.weight'}}
PRESETS = {'admittance': ADMITTANCE}


def parse_mapping(items: Sequence[str] | Mapping[str, str]) -> dict[str, str]:
    """``['remote.parameter=quantity', ...]`` (or a mapping): checked syntax and payload
    quantity names; estimate quantities are checked when the node's names are known."""
    pairs = dict(items) if isinstance(items, Mapping) else {}
    if not isinstance(items, Mapping):
        for item in items:
            remote, sep, quantity = str(item).partition('=')
            if not sep or not remote.strip() or not quantity.strip():
                raise IdentificationError(f'mapping {item!r}: use remote.parameter=quantity')
            pairs[remote.strip()] = quantity.strip()
    if not pairs:
        raise IdentificationError('no parameters mapped')
    for remote, quantity in pairs.items():
        if quantity.startswith('payload.') and quantity not in PAYLOAD_QUANTITIES:
            raise IdentificationError(f'mapping {remote}={quantity}: payload quantities are '
                                      + ', '.join(PAYLOAD_QUANTITIES))
    return pairs


def check_estimate_quantity(quantity: str, base_names: Sequence[str]) -> str:
    """Why ``quantity`` cannot come from the base parameters ``base_names`` ('' when it can)."""
    if quantity.startswith('payload.'):
        return ''
    if quantity not in base_names:
        regrouped = [n for n in base_names if n == quantity + 'R']
        if regrouped:
            return (f'{quantity} is identified only regrouped with others ({regrouped[0]}); '
                    'it cannot be sent on its own')
        return (f'{quantity} is not a base parameter of the identified model (the motion and '
                'structure do not determine it on its own)')
    if quantity.endswith('R'):
        return f'{quantity} is a regrouped base parameter, not one link or joint quantity'
    return ''


@dataclass
class Quantity:
    """A value (float or a vector), its standard deviation (same shape; inf: not known) and
    why it must not be sent ('' when it may)."""
    value: np.ndarray
    stddev: np.ndarray
    problem: str = ''

    def as_parameter(self):
        """The value as a parameter value: a float, or a list of floats."""
        return float(self.value[0]) if self.value.size == 1 else [float(v) for v in self.value]


def payload_quantity(name: str, mass: float, com: Sequence[float], mass_sd: float,
                     com_sd: Sequence[float]) -> Quantity:
    """A payload quantity from the payload's mass (kg) and centre of mass (m) and their
    standard deviations (inf where not excited)."""
    centre, centre_sd = np.asarray(com, dtype=float), np.asarray(com_sd, dtype=float)
    if name == 'payload.mass':
        q = Quantity(np.array([mass]), np.array([mass_sd]))
    elif name == 'payload.weight':
        q = Quantity(np.array([mass * GRAVITY]), np.array([mass_sd * GRAVITY]))
    elif name == 'payload.com':
        q = Quantity(centre, centre_sd)
    else:
        k = 'xyz'.index(name[-1])
        q = Quantity(centre[k:k + 1], centre_sd[k:k + 1])
    if not mass > 0 or not math.isfinite(mass_sd):
        q.problem = f'payload mass {mass:.6g} kg is not physically consistent or not excited'
    elif not np.isfinite(q.stddev).all():
        q.problem = f'{name} not excited by the motion'
    return q


def estimate_quantity(name: str, value: float, stddev: float) -> Quantity:
    """A base parameter that is one standard parameter, with its physical check."""
    q = Quantity(np.array([float(value)]), np.array([float(stddev) if stddev >= 0
                                                     else math.inf]))
    kind = name.rsplit('.', 1)[-1]
    if not math.isfinite(value):
        q.problem = f'{name} = {value} is not finite'
    elif kind in POSITIVE and not value > 0:
        q.problem = f'{name} = {value:.6g} is not positive'
    elif kind in NON_NEGATIVE and value < 0:
        q.problem = f'{name} = {value:.6g} is negative'
    elif not math.isfinite(q.stddev[0]):
        q.problem = f'{name} not determined yet'
    return q


@dataclass
class ChangeGate:
    """Which values to send: the first one that passes its checks, then one that differs
    from the last sent in some element by more than ``threshold`` of its standard deviations."""
    threshold: float
    sent: dict = field(default_factory=dict)

    def due(self, key: str, q: Quantity) -> bool:
        if q.problem:
            return False
        last = self.sent.get(key)
        if last is None:
            return True
        return bool(np.any(np.abs(q.value - last) > self.threshold * q.stddev))

    def mark_sent(self, key: str, q: Quantity) -> None:
        self.sent[key] = q.value.copy()
