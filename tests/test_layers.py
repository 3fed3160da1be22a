"""The package's import graph: no cycle, every import to a lower or equal layer, and the systems
named only inside ``systems/`` and by the few modules that are about one system by nature.

Every module of ``torchslam`` is parsed (not imported); every ``import`` and ``from ... import``
counts, at module level, inside functions and under ``TYPE_CHECKING`` alike. ``torchslam/slam/``
(the old paths, thin aliases of the new modules) is left out.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

from ._helpers import REPO_ROOT

PACKAGE = REPO_ROOT / "torchslam"
ALIASES = "torchslam.slam"

# Layer ranks, lowest first: a module may import modules of its own layer or of lower ones.
LAYERS: dict[str, int] = {
    # leaves: errors and helpers that import nothing of torchslam but errors
    "torchslam.errors": 0,
    "torchslam.strictjson": 0,
    "torchslam.environment": 0,
    "torchslam.threads": 0,
    "torchslam.allocator": 0,
    "torchslam._moved": 0,
    "torchslam.cache": 0,
    "torchslam.devices": 0,
    "torchslam.stamps": 0,
    "torchslam.diagnostics": 0,
    "torchslam.config": 1,
    "torchslam.checkpoint": 1,
    "torchslam.geometry": 2,
    "torchslam.optim": 3,
    # algorithms on geometry and the solvers
    "torchslam.imu": 4,
    "torchslam.features": 4,
    "torchslam.fastgo": 4,
    "torchslam.kcc": 4,
    "torchslam.backend": 4,
    "torchslam.loop": 4,
    # data (with IMU simulation) and registration (features + FastGO)
    "torchslam.data": 5,
    "torchslam.registration": 5,
    "torchslam.eval": 6,
    "torchslam.systems": 7,
    "torchslam.learn": 8,
    "torchslam.app": 9,
    "torchslam.cli": 10,
    "torchslam.__main__": 10,
}

SYSTEM_PACKAGES = ("torchslam.systems.nislam", "torchslam.systems.gcslam")
# Modules outside systems/ that may import one system directly, and why.
SYSTEM_SPECIFIC = {
    "torchslam.learn": "learn/ trains NI-SLAM's KCC parameters (NISlamConfig) and FastGO's pair weights",
    "torchslam.cli": "the calibrate-time command calibrates NI-SLAM's attitude stream clock (NISlamConfig, attitude_stream)",
    "torchslam.app.calibrate_time": "calibrates NI-SLAM's attitude stream clock",
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO_ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    mods = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {m: p for m, p in mods.items() if m != ALIASES and not m.startswith(ALIASES + ".")}


def _resolve(module: str, is_package: bool, level: int, target: str | None) -> str:
    """The absolute name of ``from <level dots><target> import ...`` written in ``module``."""
    base = module.split(".") if is_package else module.split(".")[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def _import_graph() -> dict[str, set[str]]:
    """module -> the torchslam modules it imports (anywhere in its source)."""
    mods = _modules()
    edges: dict[str, set[str]] = defaultdict(set)
    for mod, path in mods.items():
        is_package = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                base = _resolve(mod, is_package, node.level, node.module) if node.level else (node.module or "")
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            edges[mod].update(t for t in targets if t in mods and t != mod)
    return edges


def _layer(module: str) -> str:
    return ".".join(module.split(".")[:2])


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    nodes = sorted(set(edges) | {b for bs in edges.values() for b in bs})
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return _import_graph()


def test_the_graph_sees_the_package(graph):
    # A sanity check of the parser: known edges, relative and absolute, lazy and at module level.
    assert "torchslam.errors" in graph["torchslam.config"]
    assert "torchslam.app.run" in graph["torchslam.cli"]  # imported inside a function
    assert "torchslam.app.batch.runner" in graph["torchslam.app.batch"]
    assert not any(m.startswith(ALIASES) for m in graph)


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle(graph):
    assert _cycles(graph) == []


def test_every_module_has_a_layer():
    missing = sorted({_layer(m) for m in _modules()} - set(LAYERS) - {"torchslam"})
    assert not missing, f"add these to LAYERS: {missing}"


def test_imports_go_to_lower_or_equal_layers(graph):
    upward = [
        f"{a} ({LAYERS[_layer(a)]}) imports {b} ({LAYERS[_layer(b)]})"
        for a, bs in sorted(graph.items())
        for b in sorted(bs)
        if _layer(a) in LAYERS and _layer(b) in LAYERS and LAYERS[_layer(b)] > LAYERS[_layer(a)]
    ]
    assert not upward, "\n".join(upward)


def test_systems_are_imported_by_name_only_inside_systems(graph):
    def allowed(module: str) -> bool:
        return module.startswith("torchslam.systems.") or any(
            module == m or module.startswith(m + ".") for m in SYSTEM_SPECIFIC
        )

    offenders = [
        f"{a} imports {b}"
        for a, bs in sorted(graph.items())
        for b in sorted(bs)
        if not allowed(a) and any(b == s or b.startswith(s + ".") for s in SYSTEM_PACKAGES)
    ]
    assert not offenders, "\n".join(offenders) + "\n(go through torchslam.systems.registry)"
