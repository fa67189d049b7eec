"""Handing an identified payload to a controller: a request filled field by field.

The payload (geometry_msgs/Inertia-shaped: m kg, com m, ixx ... izz kg m^2 about the com, all
in the frame of the payload link) goes into a service request by a mapping from request
field paths (dotted, e.g. ``camera_info.k``) to payload quantities:

- ``mass``; ``com`` (a Vector3-like field gets x, y, z; an array field 3 values);
  ``com.x`` ``com.y`` ``com.z``; ``ixx`` ... ``izz``;
- ``inertia_matrix``: the 3x3 inertia about the com as 9 values (row- and column-major are
  the same for a symmetric matrix);
- ``inertia``: a geometry_msgs/Inertia-shaped field (m, com, ixx ... izz) filled whole.

Presets for the drivers users ask about (those packages are not needed here; the service
type is imported by name when the forwarder starts):

- ``ur``: ur_msgs/srv/SetPayload (Universal Robots' ROS 2 driver, service
  ``/io_and_status_controller/set_payload``), in the tool flange frame ``tool0``: the
  older layout ``mass`` (kg) and ``center_of_gravity`` (Vector3, m); the newer adds the
  inertia about the centre of gravity (``ixx`` ... ``iyz``, kg m^2) and ``transition_time``
  (a Duration, s), or carries the payload whole (``payload``, geometry_msgs/Inertia) with a
  float ``transition_time``. Its fields are filled where the request has them (a preset's
  ``optional``), so every layout works; ``transition_time`` is the forwarder's parameter.
- ``franka``: franka_msgs/srv/SetLoad (franka_ros2, service ``/service_server/set_load``):
  ``mass`` (kg), ``center_of_mass`` (m, flange frame) and ``load_inertia`` (9 values, kg m^2,
  about the centre of mass, column-major).

No frame is transformed: the payload link (``payload.link``) must be the controller's frame.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

from identification_node.errors import IdentificationError

INERTIA_FIELDS = ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz')
QUANTITIES = ('mass', 'com', 'com.x', 'com.y', 'com.z', 'inertia_matrix', 'inertia',
              *INERTIA_FIELDS)
PRESETS: dict[str, dict[str, Any]] = {
    'ur': {'service_type': 'ur_msgs/srv/SetPayload', 'frame': 'tool0',
           'service': '/io_and_status_controller/set_payload',
           'fields': {'mass': 'mass', 'center_of_gravity': 'com', 'payload': 'inertia',
                      **{k: k for k in ('ixx', 'iyy', 'izz', 'ixy', 'ixz', 'iyz')}},
           'optional': True},
    'franka': {'service_type': 'franka_msgs/srv/SetLoad', 'frame': '',
               'service': '/service_server/set_load',
               'fields': {'mass': 'mass', 'center_of_mass': 'com',
                          'load_inertia': 'inertia_matrix'}},
}


def parse_fields(items: list[str] | Mapping[str, str]) -> dict[str, str]:
    """``['field.path=quantity', ...]`` (or a mapping) checked against QUANTITIES."""
    pairs = dict(items) if isinstance(items, Mapping) else {}
    if not isinstance(items, Mapping):
        for item in items:
            path, sep, quantity = str(item).partition('=')
            if not sep:
                raise IdentificationError(f'field mapping {item!r}: use field.path=quantity')
            pairs[path.strip()] = quantity.strip()
    for path, quantity in pairs.items():
        if quantity not in QUANTITIES or not path:
            raise IdentificationError(f'field mapping {path}={quantity}: quantity must be one '
                                      f'of {", ".join(QUANTITIES)}')
    if not pairs:
        raise IdentificationError('no request fields mapped')
    return pairs


def payload_values(inertia) -> dict[str, Any]:
    """The QUANTITIES of a geometry_msgs/Inertia-like object (m, com.x/y/z, ixx ...)."""
    com = [float(inertia.com.x), float(inertia.com.y), float(inertia.com.z)]
    i = {k: float(getattr(inertia, k)) for k in INERTIA_FIELDS}
    values = [float(inertia.m), *com, *i.values()]
    if not all(math.isfinite(v) for v in values):
        raise IdentificationError('payload has non-finite values')
    matrix = [i['ixx'], i['ixy'], i['ixz'], i['ixy'], i['iyy'], i['iyz'],
              i['ixz'], i['iyz'], i['izz']]
    return {'mass': float(inertia.m), 'com': com, 'com.x': com[0], 'com.y': com[1],
            'com.z': com[2], 'inertia_matrix': matrix, 'inertia': inertia, **i}


def fill_request(request: Any, fields: Mapping[str, str], inertia, optional: bool = False,
                 transition_time: float | None = None) -> Any:
    """``request`` with each mapped field set from the payload ``inertia`` (see module doc);
    ``optional``: fields the request does not have are left out (at least one must be
    there); ``transition_time`` (s): into the request's field of that name where it has one
    (a Duration or a number)."""
    values = payload_values(inertia)
    if optional:
        fields = {p: q for p, q in fields.items() if has_field(request, p)}
        if not fields:
            raise IdentificationError(f'request {type(request).__name__} has none of the '
                                      'preset\'s payload fields')
    if transition_time is not None and hasattr(request, 'transition_time'):
        if not (math.isfinite(transition_time) and transition_time >= 0):
            raise IdentificationError(f'transition_time {transition_time!r} must be >= 0 s')
        current = request.transition_time
        if hasattr(current, 'sec') and hasattr(current, 'nanosec'):
            ns = int(round(transition_time * 1e9))
            current.sec, current.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
        else:
            request.transition_time = float(transition_time)
    for path, quantity in fields.items():
        *parents, name = path.split('.')
        target = request
        for p in parents:
            if not hasattr(target, p):
                raise IdentificationError(f'request {type(request).__name__} has no field '
                                          f'{path}')
            target = getattr(target, p)
        if not hasattr(target, name):
            raise IdentificationError(f'request {type(request).__name__} has no field {path}')
        _assign(target, name, getattr(target, name), values[quantity], path)
    return request


def has_field(request: Any, path: str) -> bool:
    """Whether ``request`` has the dotted field ``path``."""
    target = request
    for name in path.split('.'):
        if not hasattr(target, name):
            return False
        target = getattr(target, name)
    return True


def _assign(target: Any, name: str, current: Any, value: Any, path: str) -> None:
    if hasattr(value, 'ixx'):   # a whole Inertia into an Inertia-shaped field
        current.m = float(value.m)
        _assign(current, 'com', current.com, [value.com.x, value.com.y, value.com.z], path)
        for k in INERTIA_FIELDS:
            setattr(current, k, float(getattr(value, k)))
        return
    if isinstance(value, list):
        if all(hasattr(current, a) for a in 'xyz') and len(value) == 3:
            current.x, current.y, current.z = (float(v) for v in value)
            return
        try:
            size = len(current)
        except TypeError:
            raise IdentificationError(f'field {path} cannot take {len(value)} values') from None
        if size not in (0, len(value)) and not _is_sequence_field(target, name):
            raise IdentificationError(f'field {path} has {size} elements, not {len(value)}')
        setattr(target, name, [float(v) for v in value])
        return
    if isinstance(current, bool) or not isinstance(current, (int, float)):
        raise IdentificationError(f'field {path} is not a number')
    setattr(target, name, float(value))


def _is_sequence_field(target: Any, name: str) -> bool:
    types = getattr(type(target), 'get_fields_and_field_types', None)
    return types is not None and types().get(name, '').startswith('sequence')
