"""The layout's promises, checked from the import statements of the package."""

from __future__ import annotations

import ast
from pathlib import Path

from conftest import ROOT

# The floors of the house, bottom up, as the data flows: a module imports its own floor and the
# floors below it, never one above. `pipeline.io` (the outside world) spans three floors: its file
# formats stand on the ground, its sources sit below SLAM (they cannot reach it), and its outputs
# (what a run leaves), beside what a person watches, sit above the stages that carry frames through SLAM.
FLOORS: list[tuple[str, tuple[str, ...]]] = [
    ("ground", ("pipeline.errors", "pipeline.extras", "pipeline.config", "pipeline.geometry", "pipeline.frame",
                "pipeline.source", "pipeline.devices", "pipeline.compile_cache", "pipeline.package_builds", "pipeline.processes",
                "pipeline.io.files")),
    ("sources", ("pipeline.io.sources",)),
    ("maths", ("pipeline.render", "pipeline.slam", "pipeline.metrics")),
    ("stages", ("pipeline.stages", "pipeline.runtime")),
    ("sinks", ("pipeline.io.outputs", "pipeline.ui")),
    ("commands", ("pipeline.app", "pipeline.__main__")),
]  # fmt: skip
MATHS_AND_STAGES = ("pipeline.slam", "pipeline.render", "pipeline.stages", "pipeline.geometry", "pipeline.metrics")
OUTSIDE_WORLD = (
    "pipeline.io.files", "pipeline.io.sources", "pipeline.io.outputs", "pipeline.ui", "pipeline.app",
    "aiortc", "aiohttp", "viser", "cyclonedds", "av",
)  # fmt: skip


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
    """module -> every module it imports anywhere in its file (function-level imports too)."""
    graph: dict[str, set[str]] = {}
    for path in (ROOT / "pipeline").rglob("*.py"):
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module:
                found.add(node.module)
                found.update(f"{node.module}.{alias.name}" for alias in node.names)
        graph[_module_name(path)] = found
    return graph


def _internal(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """Edges between the package's modules; importing a.b.c also runs a and a.b."""
    modules = set(graph)
    edges: dict[str, set[str]] = {}
    for name, targets in graph.items():
        inside = set()
        for target in targets:
            parts = target.split(".")
            for i in range(1, len(parts) + 1):
                prefix = ".".join(parts[:i])
                if prefix in modules and prefix != name and not name.startswith(prefix + "."):
                    inside.add(prefix)
        edges[name] = inside
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in edges[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while (top := stack.pop()) != node:
                component.append(top)
            component.append(node)
            if len(component) > 1:
                found.append(sorted(component))

    for node in edges:
        if node not in index:
            visit(node)
    return found


def test_no_import_cycle_in_the_package() -> None:
    assert _cycles(_internal(_imports())) == []


def test_the_maths_and_the_stages_import_nothing_of_the_outside_world() -> None:
    offending = {
        (name, target)
        for name, targets in _imports().items()
        if name.startswith(MATHS_AND_STAGES)
        for target in targets
        if target.startswith(OUTSIDE_WORLD)
    }
    assert offending == set()


def test_only_the_commands_import_the_commands() -> None:
    offending = {
        (name, target)
        for name, targets in _imports().items()
        if not name.startswith("pipeline.app") and name != "pipeline.__main__"
        for target in targets
        if target.startswith("pipeline.app")
    }
    assert offending == set()


def _floor(module: str) -> int:
    """The floor of `module` (the packages `pipeline` and `pipeline.io` themselves stand on the ground)."""
    for level, (_, packages) in enumerate(FLOORS):
        if any(module == p or module.startswith(p + ".") for p in packages):
            return level
    assert module in ("pipeline", "pipeline.io"), f"{module} is on no floor: add it to FLOORS"
    return 0


def test_every_module_stands_on_a_floor_and_imports_nothing_above_it() -> None:
    upward = {
        (name, target, FLOORS[_floor(target)][0])
        for name, targets in _internal(_imports()).items()
        for target in targets
        if _floor(target) > _floor(name)
    }
    assert upward == set()


def test_sources_import_neither_slam_nor_what_sits_above_it() -> None:
    above = tuple(p for _, packages in FLOORS[2:] for p in packages)
    offending = {
        (name, target)
        for name, targets in _imports().items()
        if name.startswith("pipeline.io.sources")
        for target in targets
        if target.startswith(above)
    }
    assert offending == set()


WINGS = ("pipeline.slam.tracking", "pipeline.slam.mapping", "pipeline.slam.loops")
# A wing may import what sits beside the wings (the map, keyframes, kernels, the hand-off types) and
# the wings named here; tracking and mapping meet only through pipeline.slam.handoff. Loop closure
# verifies a candidate with tracking's dense alignment.
WING_MAY_IMPORT = {
    "pipeline.slam.tracking": (),
    "pipeline.slam.mapping": ("pipeline.slam.loops",),
    "pipeline.slam.loops": ("pipeline.slam.tracking",),
}


def test_slams_wings_import_no_other_wing_but_the_ones_they_build_on() -> None:
    offending = {
        (name, target)
        for name, targets in _internal(_imports()).items()
        for wing in WINGS
        if name.startswith(wing + ".")
        for target in targets
        if target.startswith(WINGS) and not target.startswith((wing, *WING_MAY_IMPORT[wing]))
    }
    assert offending == set()
