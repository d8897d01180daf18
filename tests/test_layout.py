"""The package's import graph: no cycle, no import up a layer, and the filters never load the
simulator, the readers or the host drivers.

The layers, lowest first (docs/design.md, "Layout"): base (geometry, grids, the laser's
description, resampling), data (the log in memory, the readers and writers ``io``, the metrics),
models (motion and sensor models, the maps, the scan matcher), filters (the proposals, the
configuration, the RBPF's step, MCL with doors), runs (the drivers of whole logs: ``slam``, the
chunked host driver, checkpoints, refinement, the loop closure, islands, the simulators, the
diagnosis), front (the outputs, the figures, the command line).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "jaxslam"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """Module -> the jaxslam modules it imports (anywhere in the file, lazy imports included)."""
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets.add(node.module)
                targets |= {f"{node.module}.{a.name}" for a in node.names}
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of modules (the first found, depth first), or None. A package's ``__init__``
    importing its own submodules is not a cycle of concepts, so package -> its own
    submodule edges are skipped."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if nxt.startswith(node + "."):
                continue
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_find_cycle_can_fail():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"p": {"p.x"}, "p.x": set()}) is None


def test_the_import_graph_has_no_cycle():
    assert find_cycle(import_graph()) is None


def test_filters_do_not_import_the_simulator_or_the_experiments():
    graph = import_graph()
    core = [m for m in graph if not m.startswith(("jaxslam.sim", "jaxslam.cli.")) and m != "jaxslam.cli"]
    for module in core:
        assert not any(t.startswith("jaxslam.sim") for t in graph[module]), (module, graph[module])


def test_import_jaxslam_loads_no_simulator():
    code = ("import sys, jaxslam; bad = sorted(m for m in sys.modules if m.startswith('jaxslam.sim') "
            "or m.startswith('jaxslam.io')); print(bad); sys.exit(1 if bad else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    """Every module ``start`` imports, directly or through others (a subpackage's ``__init__``
    counts when one of its submodules is imported; the top package ``jaxslam``, which re-exports
    the public API, does not)."""
    seen, todo = set(), [start]
    while todo:
        node = todo.pop()
        for nxt in graph[node]:
            parts = nxt.split(".")
            for parent in (".".join(parts[:k]) for k in range(1, len(parts) + 1)):
                if parent in graph and parent not in seen and parent != "jaxslam":
                    seen.add(parent)
                    todo.append(parent)
    return seen


FILTER_LAYER = ("jaxslam.rbpf", "jaxslam.islands", "jaxslam.particle_filter", "jaxslam.proposals", "jaxslam.sensor_model",
                "jaxslam.localization.mcl", "jaxslam.localization.doors", "jaxslam.localization.grid_mcl")
"""The pure filters: what they import must not reach the readers, the outputs or the host drivers."""


def test_reachable_can_fail():
    assert reachable({"a": {"b.c"}, "b": set(), "b.c": {"d"}, "d": set()}, "a") == {"b", "b.c", "d"}


def test_the_filter_layer_imports_no_reader_output_or_host_driver():
    graph = import_graph()
    for module in FILTER_LAYER:
        bad = sorted(m for m in reachable(graph, module)
                     if m.startswith("jaxslam.io") or m in ("jaxslam.outputs", "jaxslam.slam", "jaxslam.cli",
                                                          "jaxslam.driver", "jaxslam.diagnose"))
        assert not bad, f"{module} reaches {bad}"


LAYERS: dict[str, int] = {
    # 0 base
    "geometry": 0, "warn": 0, "computed_once": 0, "compile_cache": 0, "grid": 0, "laser": 0,
    "binary_bayes": 0, "resampling": 0, "segment_map": 0, "proposals.base": 0, "sim.world": 0, "checks": 0,
    # 1 data
    "laserlog": 1, "io": 1, "metrics": 1,
    # 2 models
    "motion": 2, "occupancy": 2, "maps": 2, "map_view": 2, "likelihood_field": 2, "sensor_model": 2,
    "window_posterior": 2, "scan_matching": 2, "particle_filter": 2, "localization.beam_model": 2,
    # 3 filters
    "proposals": 3, "params": 3, "config": 3, "slip_search": 3, "rbpf": 3, "learning": 3, "localization.mcl": 3, "localization.doors": 3,
    "localization.grid_mcl": 3, "localization": 3,
    # 4 runs
    "driver": 4, "slam": 4, "checkpoint": 4, "refine": 4, "islands": 4, "island_runs": 4, "graph": 4, "resources": 4,
    "sim": 4,
    "diagnose": 4, "growth": 4, "pipeline": 4,
    # 5 front
    "outputs": 5, "plotting": 5, "localization.plotting": 5, "cli": 5, "": 5,
}
"""Each module's layer, by the longest dotted prefix below ``jaxslam`` listed here ("" is the
package's ``__init__``, which re-exports the API)."""

LAYER_NAMES = ("base", "data", "models", "filters", "runs", "front")


def layer_of(module: str) -> int:
    """The layer of ``jaxslam.x.y`` by its longest listed prefix; KeyError for a module none
    matches (a new module is given its layer here)."""
    parts = module.split(".")[1:]
    for n in range(len(parts), -1, -1):
        prefix = ".".join(parts[:n])
        if prefix in LAYERS and (n > 0 or not parts):
            return LAYERS[prefix]
    raise KeyError(f"{module} has no layer: add it to LAYERS in tests/test_layout.py")


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """``"a (layer) imports b (layer)"`` for every import to a higher layer; a package's
    ``__init__`` re-exporting its own submodules is not one, nor ``from jaxslam import x`` (the
    graph holds ``jaxslam.x`` for it)."""
    wrong = []
    for module, targets in sorted(graph.items()):
        for target in sorted(targets):
            if target == "jaxslam" or target.startswith(module + ".") or layer_of(target) <= layer_of(module):
                continue
            wrong.append(f"{module} ({LAYER_NAMES[layer_of(module)]}) imports {target} "
                         f"({LAYER_NAMES[layer_of(target)]})")
    return wrong


def test_upward_imports_can_fail():
    graph = {"jaxslam.io.bad": {"jaxslam.rbpf"}, "jaxslam.rbpf": {"jaxslam.io.trajectory"},
             "jaxslam.io.trajectory": set(), "jaxslam.graph": {"jaxslam.graph.closure"}, "jaxslam.graph.closure": set()}
    assert upward_imports(graph) == ["jaxslam.io.bad (data) imports jaxslam.rbpf (filters)"]
    with pytest.raises(KeyError, match="has no layer"):
        layer_of("jaxslam.brand_new_module")


def test_every_module_has_a_layer_and_no_import_points_up():
    graph = import_graph()
    for module in graph:
        layer_of(module)
    wrong = upward_imports(graph)
    assert not wrong, "imports that point up the layers:\n" + "\n".join(wrong)


MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def long_parts(source: str, name: str) -> list[str]:
    """What in one module's ``source`` is over the limits: the module over MAX_MODULE_LINES lines,
    any function (nested ones too) over MAX_FUNCTION_LINES, docstring included."""
    found = [f"{name}: {len(source.splitlines())} lines"] if len(source.splitlines()) > MAX_MODULE_LINES else []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            lines = node.end_lineno - node.lineno + 1
            if lines > MAX_FUNCTION_LINES:
                found.append(f"{name}.{node.name}: {lines} lines")
    return found


def test_long_parts_can_fail():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    assert long_parts(f"def f():\n{body}\n", "m") == [f"m.f: {MAX_FUNCTION_LINES + 1} lines"]
    assert long_parts("x = 1\n" * (MAX_MODULE_LINES + 1), "m") == [f"m: {MAX_MODULE_LINES + 1} lines"]


def test_no_module_over_600_lines_and_no_function_over_80():
    found = [part for path in sorted(PACKAGE.rglob("*.py")) for part in long_parts(path.read_text(), _module_name(path))]
    assert not found, found
