"""YAML input with limits: the one loader of every YAML file the package reads (parameter
files for the node and the CLI, bag metadata, trajectories, estimates, payload events).

yaml.safe_load builds no objects, but aliases let a small document stand for an exponential
one (a "YAML bomb": each level refers to the previous one twice), which code walking the
result then expands. Here the document's size in bytes and the number of nodes it stands for
with every alias expanded are bounded before anything is built; every failure (unreadable,
not UTF-8, not YAML, too large) is one IdentificationError line naming the file.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from identification_node.errors import IdentificationError

MAX_BYTES = 16 << 20        # 16 MiB: far beyond any parameter file or bag metadata
MAX_NODES = 1_000_000       # scalars and collections, with aliases expanded

_Loader = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)


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


def load_yaml(text: str | bytes, what: str = 'YAML', max_nodes: int = MAX_NODES) -> Any:
    """The data of one YAML document (safe types only); IdentificationError naming ``what``
    when it is not YAML, holds several documents, or stands for more than ``max_nodes``
    nodes."""
    if isinstance(text, bytes):
        text = decode(text, what)
    if len(text) > MAX_BYTES:
        raise IdentificationError(f'{what}: {len(text)} characters, more than the '
                                  f'{MAX_BYTES >> 20} MiB a YAML input may have')
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        size = expanded_size(node, max_nodes)
        if size > max_nodes:
            raise IdentificationError(
                f'{what}: its aliases expand to more than {max_nodes} YAML nodes (a "YAML '
                'bomb"?); not read')
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        raise IdentificationError(f'{what} is not valid YAML: {yaml_problem(exc)}') from None
    except RecursionError:
        raise IdentificationError(f'{what}: nested too deeply to be read') from None
    finally:
        loader.dispose()


def read_yaml(path: str | os.PathLike, what: str | None = None,
              max_nodes: int = MAX_NODES) -> Any:
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
    return load_yaml(data, what, max_nodes)


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
