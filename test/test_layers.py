"""The package's import graph (issue 26): every import, at module level or inside a function,
points down the layers or stays within its own; no module imports another that imports it
back, and none imports another's underscore names. Read from the source with ast, so a lazy
import counts as much as a top-level one."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'identification_node'

# from the bottom; a package or top-level module may import only its own layer or lower ones
LAYERS = [
    {'errors', 'config', 'safe_yaml', 'error_lines', 'fileio', 'parameter_mapping'},
    {'model'},
    {'wire', 'bags'},
    {'pipeline', 'estimation'},
    {'settings'},
    {'excitation'},
    {'payload'},
    {'simulation'},
    {'batch', 'replay', 'results'},
    {'fleet'},
    {'ros'},
    {'cli', 'programs', '__main__', '__init__'},
]


def layer(unit: str) -> int:
    return next(i for i, names in enumerate(LAYERS) if unit in names)


def unit(module: str) -> str:
    """The package or top-level module of ``identification_node.<unit>...``."""
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else '__init__'


def imports() -> dict[str, set[str]]:
    """Module name: the package's modules it imports (absolute imports only)."""
    graph: dict[str, set[str]] = {}
    for path in PACKAGE.rglob('*.py'):
        parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
        module = '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)
        names: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names.add(node.module)
            elif isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
        graph[module] = {n for n in names if n.split('.')[0] == 'identification_node'}
    return graph


def test_every_unit_has_a_layer():
    units = {unit(m) for m in imports()}
    assert units <= set().union(*LAYERS), units - set().union(*LAYERS)


def test_no_upward_import():
    upward = [(m, n) for m, names in imports().items() for n in names
              if layer(unit(n)) > layer(unit(m))]
    assert not upward, upward


def test_no_module_cycle():
    graph = imports()
    modules = set(graph)

    def target(name: str) -> str | None:   # a name imported from a package is its __init__
        while name and name not in modules:
            name = name.rpartition('.')[0]
        return name or None

    edges = {m: {t for n in names if (t := target(n)) and t != m} for m, names in graph.items()}
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in edges[m]:
            if state.get(n) == 1:
                cycles.append(path[path.index(n):] + [n])
            elif n not in state:
                visit(n, path + [n])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [m])
    assert not cycles, cycles


def test_no_module_imports_another_modules_private_names():
    private = []
    for path in PACKAGE.rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or '').startswith(
                    'identification_node'):
                private += [(str(path.relative_to(PACKAGE)), a.name) for a in node.names
                            if a.name.startswith('_') and not a.name.startswith('__')]
    assert not private, private
