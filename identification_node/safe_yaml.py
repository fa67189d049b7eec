"""YAML input with limits: the one loader of every YAML file the package reads (parameter
files for the node and the CLI, bag metadata, trajectories, estimates, payload events).

yaml.safe_load builds no objects, but aliases let a small document stand for an exponential
one (a "YAML bomb": each level refers to the previous one twice), which code walking the
result then expands. Here the document's size in bytes and the number of nodes it stands for
with every alias expanded are bounded before anything is built; every failure (unreadable,
not UTF-8, not YAML, too large) is one IdentificationError line naming the file.

ROS parameter files (``ros=True``) take their plain scalars as rcl's parser does, so that a
file means the same to ``identify --config`` as to ``ros2 run --params-file``: ``1e-3`` and
``inf`` are numbers, ``y``/``n`` booleans, ``~`` and ``1_000`` strings (PyYAML reads these as
YAML 1.1 does), and names (mapping keys) stay strings.
"""
from __future__ import annotations

import math
import os
import re
import sys
from pathlib import Path
from typing import Any

import yaml

from identification_node.errors import IdentificationError

MAX_BYTES = 16 << 20        # 16 MiB: far beyond any parameter file or bag metadata
MAX_NODES = 1_000_000       # scalars and collections, with aliases expanded

_Loader = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
_ROS_SCALAR = '!ros_scalar'


class _RosLoader(_Loader):   # type: ignore[misc, valid-type]
    """The safe loader with rcl's plain scalars (tagged _ROS_SCALAR by _ros_tags)."""


# rcl_yaml_param_parser's get_value (parse.c): bool words, then strtol (base 0), then strtod
_TRUE = {'Y', 'y', 'yes', 'Yes', 'YES', 'true', 'True', 'TRUE', 'on', 'On', 'ON'}
_FALSE = {'N', 'n', 'no', 'No', 'NO', 'false', 'False', 'FALSE', 'off', 'Off', 'OFF'}
_SPECIAL = {f'{sign}.{word}' for sign in ('', '+', '-') for word in ('inf', 'Inf', 'INF')
            } | {'.nan', '.NaN', '.NAN'}
_INTEGER = re.compile(r'[+-]?(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)')
_DECIMAL = re.compile(r'[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?')
_HEX = re.compile(r'[+-]?0[xX]([0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)([pP][+-]?\d+)?')
_WORD = re.compile(r'[+-]?(inf|infinity|nan(\([0-9a-zA-Z_]*\))?)', re.IGNORECASE)


def ros_scalar(text: str) -> bool | int | float | str:
    """A plain (unquoted) scalar of a ROS parameter file as rcl reads it: a bool word, a C
    integer (decimal, 0x hex, 0 octal; within int64), a C double (what strtod takes whole:
    exponents, inf, nan, hex floats; not out of range), else the string itself."""
    if text in _TRUE or text in _FALSE:
        return text in _TRUE
    if _INTEGER.fullmatch(text):
        sign, digits = (-1, text[1:]) if text[0] == '-' else (1, text.lstrip('+'))
        base = 16 if digits[1:2] in ('x', 'X') else 8 if digits[:1] == '0' else 10
        body = (digits[2:] if base == 16 else digits).lstrip('0') or '0'
        integer = sign * int(body, base) if len(body) <= 22 else 2 ** 63   # more: beyond int64
        if -2 ** 63 <= integer < 2 ** 63:
            return integer
    if text in _SPECIAL:
        return float(text.replace('.', ''))
    if _WORD.fullmatch(text):
        return float(text.split('(')[0])
    if _DECIMAL.fullmatch(text):
        value, mantissa = float(text), re.split('[eE]', text.lstrip('+-'))[0]
    elif _HEX.fullmatch(text):
        value, mantissa = float.fromhex(text), re.split('[pP]', text.lstrip('+-'))[0][2:]
    else:
        return text
    tiny = abs(value) < sys.float_info.min and mantissa.strip('0.') != ''
    return text if math.isinf(value) or tiny else value   # strtod's ERANGE: rcl's string


_RosLoader.add_constructor(_ROS_SCALAR, lambda loader, node: ros_scalar(node.value))


def _ros_tags(node: yaml.Node) -> None:
    """Tag the plain scalars of a composed document for ros_scalar, its names as strings."""
    stack, seen = [(node, False)], set()
    while stack:
        n, key = stack.pop()
        if id(n) in seen:
            continue
        seen.add(id(n))
        if isinstance(n, yaml.MappingNode):
            stack.extend(p for k, v in n.value for p in ((k, True), (v, False)))
        elif isinstance(n, yaml.SequenceNode):
            stack.extend((c, False) for c in n.value)
        elif key:
            n.tag = 'tag:yaml.org,2002:str'
        elif n.style not in ('\'', '"'):   # plain or block, as rcl reads them
            n.tag = _ROS_SCALAR


def expanded_size(node: yaml.Node, limit: int = MAX_NODES) -> int:
    """The number of nodes of a composed document with every alias expanded (a shared node
    counts at each use), up to just past ``limit``; each distinct node is visited once."""
    sizes: dict[int, int] = {}
    stack: list[tuple[yaml.Node, bool]] = [(node, False)]
    while stack:
        n, children_done = stack.pop()
        if id(n) in sizes:
            continue
        if isinstance(n, yaml.MappingNode):
            children = [c for pair in n.value for c in pair]
        elif isinstance(n, yaml.SequenceNode):
            children = list(n.value)
        else:
            sizes[id(n)] = 1
            continue
        if children_done:
            sizes[id(n)] = min(limit + 1, 1 + sum(sizes[id(c)] for c in children))
        else:
            stack.append((n, True))
            stack.extend((c, False) for c in children if id(c) not in sizes)
    return sizes[id(node)]


def load_yaml(text: str | bytes, what: str = 'YAML', max_nodes: int = MAX_NODES,
              ros: bool = False) -> Any:
    """The data of one YAML document (safe types only; ``ros``: a ROS parameter file's
    scalars, see the module doc); IdentificationError naming ``what`` when it is not YAML,
    holds several documents, or stands for more than ``max_nodes`` nodes."""
    if isinstance(text, bytes):
        text = decode(text, what)
    if len(text) > MAX_BYTES:
        raise IdentificationError(f'{what}: {len(text)} characters, more than the '
                                  f'{MAX_BYTES >> 20} MiB a YAML input may have')
    loader = (_RosLoader if ros else _Loader)(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        size = expanded_size(node, max_nodes)
        if size > max_nodes:
            raise IdentificationError(
                f'{what}: its aliases expand to more than {max_nodes} YAML nodes (a "YAML '
                'bomb"?); not read')
        if ros:
            _ros_tags(node)
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        raise IdentificationError(f'{what} is not valid YAML: {yaml_problem(exc)}') from None
    except (ValueError, TypeError, OverflowError) as exc:   # a tagged or implicit value's
        raise IdentificationError(f'{what} is not valid YAML: {exc}') from None
    except RecursionError:
        raise IdentificationError(f'{what}: nested too deeply to be read') from None
    finally:
        loader.dispose()


def read_yaml(path: str | os.PathLike, what: str | None = None,
              max_nodes: int = MAX_NODES, ros: bool = False) -> Any:
    """The data of the YAML file ``path`` (see load_yaml); ``what`` names it in errors
    (default: 'file PATH')."""
    what = what or f'file {path}'
    try:
        size = os.stat(path).st_size
        if size > MAX_BYTES:
            raise IdentificationError(f'{what}: {size} bytes, more than the '
                                      f'{MAX_BYTES >> 20} MiB a YAML input may have')
        data = Path(path).read_bytes()
    except OSError as exc:
        raise IdentificationError(f'cannot read {what}: {exc.strerror or exc}') from None
    return load_yaml(data, what, max_nodes, ros)


def decode(data: bytes, what: str) -> str:
    """UTF-8 text of ``data``; IdentificationError naming ``what`` otherwise."""
    try:
        return data.decode('utf-8')
    except UnicodeDecodeError as exc:
        raise IdentificationError(f'{what} is not UTF-8 text (byte {exc.start}: '
                                  f'0x{data[exc.start]:02x}); is it a binary file?') from None


def yaml_problem(exc: yaml.YAMLError) -> str:
    """A YAML parser error as one line: the problem and its line and column."""
    problem = getattr(exc, 'problem', None)
    mark = getattr(exc, 'problem_mark', None)
    if problem is None:
        return ' '.join(str(exc).split())
    at = f' at line {mark.line + 1}, column {mark.column + 1}' if mark is not None else ''
    context = getattr(exc, 'context', None)
    return f'{context + ": " if context else ""}{problem}{at}'
