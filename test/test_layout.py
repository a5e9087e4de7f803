"""The package layout keeps its shape: layers that import downwards only, no import cycles,
short modules.

Imports are read from the source (module level, inside functions and under TYPE_CHECKING
alike), so a cycle hidden in a function-level or type-only import is caught too.
"""
from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ('fhld_ros', 'msg_adapters')
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 80
# The allowed directions: a module imports from its own layer's package or from a layer below.
# core: fhld_ros's top-level modules (pipeline, grid, detectors, parameters, geometry, ...) with
# model/ and importing/. Packages sharing a layer (sim, annotation) do not import each other.
LAYERS = (
    ('msg_adapters',),  # messages <-> numpy, no fhld_ros
    ('core',),
    ('camera',),  # calibration, 2D labels, camera topics
    ('sim', 'annotation'),
    ('data',),  # windows with lanes: simulated, cached, from bags
    ('evaluation',),
    ('training',),
    ('salad',),  # the camera detector: its data, model, training and scoring
    ('ros',),  # the node and its plumbing
    ('commands',),  # `fhld ...`
)


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((REPO / package).rglob('*.py')):
            parts = path.relative_to(REPO).with_suffix('').parts
            found['.'.join(parts[:-1] if parts[-1] == '__init__' else parts)] = path
    return found


def _imported(tree: ast.AST, known: dict[str, Path]) -> set[str]:
    """Project modules a module imports; `from a import b` counts a.b when b is a module."""
    out: set[str] = set()
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.add(node.module)
            out.update(f'{node.module}.{alias.name}' for alias in node.names)
        stack.extend(ast.iter_child_nodes(node))
    return {name for name in out if name in known}


def _import_graph() -> dict[str, set[str]]:
    known = _modules()
    graph = {}
    for name, path in known.items():
        edges = _imported(ast.parse(path.read_text()), known)
        # a package's __init__ runs first, but it importing nothing is the point being tested:
        # only explicit imports are edges
        graph[name] = edges - {name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_no_import_cycles():
    assert _cycles(_import_graph()) == []


def test_cycle_finder_finds_a_cycle():
    assert _cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]


def _group(module: str) -> str:
    parts = module.split('.')
    if parts[0] == 'msg_adapters':
        return 'msg_adapters'
    if module == 'fhld_ros.cli':  # it runs any subcommand: calling it is using commands
        return 'commands'
    packages = {name for layer in LAYERS for name in layer}
    return parts[1] if len(parts) > 1 and parts[1] in packages else 'core'


def _upward_imports(graph: dict[str, set[str]]) -> list[str]:
    layer_of = {name: depth for depth, layer in enumerate(LAYERS) for name in layer}
    found = []
    for module, edges in sorted(graph.items()):
        for target in sorted(edges):
            a, b = _group(module), _group(target)
            if a != b and layer_of[b] >= layer_of[a]:
                found.append(f'{module} ({a}) -> {target} ({b})')
    return found


def test_layers_import_downwards():
    assert _upward_imports(_import_graph()) == []


def test_layer_check_finds_an_upward_import():
    graph = {'fhld_ros.pipeline': {'fhld_ros.ros.node'},
             'fhld_ros.sim.x': {'fhld_ros.annotation.y'},
             'fhld_ros.ros.node': {'fhld_ros.pipeline'}}
    assert _upward_imports(graph) == [
        'fhld_ros.pipeline (core) -> fhld_ros.ros.node (ros)',
        'fhld_ros.sim.x (sim) -> fhld_ros.annotation.y (annotation)']


def test_msg_adapters_import_nothing_from_fhld_ros():
    graph = _import_graph()
    leaks = {name: sorted(e for e in edges if e.startswith('fhld_ros'))
             for name, edges in graph.items() if name.startswith('msg_adapters')}
    assert {name: edges for name, edges in leaks.items() if edges} == {}


def test_modules_and_functions_stay_short():
    long_modules, long_functions = [], []
    for name, path in _modules().items():
        text = path.read_text()
        if text.count('\n') > MAX_MODULE_LINES:
            long_modules.append(f'{name} ({text.count(chr(10))} lines)')
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long_functions.append(f'{name}.{node.name} ({length} lines)')
    assert long_modules == []
    assert long_functions == []
