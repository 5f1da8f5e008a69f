"""The architecture as a test: packages in layers, each importing only from layers below it
(or from itself), so the dependency graph between packages has no cycle.

    base        rig (errors, clock, realtime)
    drivers     the slider and load-cell drivers (folder drivers/)
    sim         the simulated rig (folder sim_device/)
    models      tissue models: plain functions and the catalogue
    specs       config, protocols, their YAML binding, the moves
    recording   log message types, the MCAP writer and reader, recovery
    records     instrument files read as the instruments wrote them
    control     the trial loop and its safety, stopping, the estimator, the devices
    views       what a person reads: progress, status, replay, figures, spy decoding
    analysis    the model lab: fits, explain, design, reports
    service     the daemon and its clients, a trial in the foreground, the live view
    diagnostics probe, ports, benchmarks
    web         the lab in a browser: a client of the daemon's socket, a reader of logs and tables
    cli         argument parsing and printing

Inside `analysis`, the subpackages are layers of their own, in the order of
`rig.analysis.LAYERS` (stats, trials, fitting, intervals, diagnosis, material, workflow, batch).

Imports inside functions count too: a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ["base", "drivers", "sim", "models", "specs", "recording", "records", "control", "views",
          "analysis", "service", "diagnostics", "web", "cli"]
BASE = {"rig", "rig.errors", "rig.clock", "rig.realtime", "rig.progress"}
FOLDERS = {"rig": ROOT / "rig", "rig.drivers": ROOT / "drivers", "rig.sim": ROOT / "sim_device"}


def modules() -> dict[str, Path]:
    out = {}
    for prefix, folder in FOLDERS.items():
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            name = ".".join((prefix, *parts)).removesuffix(".__init__")
            out[name] = path
    return out


def layer_of(module: str) -> str:
    if module in BASE:
        return "base"
    if module in ("rig.cli", "rig.__main__"):
        return "cli"
    return module.split(".")[1]


def imports(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
            # `from rig import x`: x may be a module of its own
            found |= {f"{node.module}.{a.name}" for a in node.names}
    return {m for m in found if m == "rig" or m.startswith("rig.")}


def test_every_module_belongs_to_a_layer():
    unknown = {m: layer_of(m) for m in modules() if layer_of(m) not in LAYERS}
    assert not unknown, f"modules outside the layers (add their package to LAYERS): {unknown}"


def test_no_package_imports_a_higher_layer():
    mods = modules()
    wrong = []
    for name, path in sorted(mods.items()):
        own = LAYERS.index(layer_of(name))
        for target in sorted(imports(path)):
            if target not in mods:  # `from rig.x import name` also yields rig.x.name
                continue
            if LAYERS.index(layer_of(target)) > own:
                wrong.append(f"{name} ({layer_of(name)}) imports {target} ({layer_of(target)})")
    assert not wrong, "lower layers import higher ones:\n" + "\n".join(wrong)


def test_no_import_cycle_between_packages():
    """Follows from the layering; checked on its own so a cycle is named when one appears."""
    mods = modules()
    graph: dict[str, set[str]] = {layer: set() for layer in LAYERS}
    for name, path in mods.items():
        graph[layer_of(name)] |= {layer_of(t) for t in imports(path) if t in mods} - {layer_of(name)}
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*trail, node, nxt]))
            if nxt not in state:
                visit(nxt, [*trail, node])
        state[node] = 2

    for layer in LAYERS:
        if layer not in state:
            visit(layer, [])


def test_no_analysis_subpackage_imports_one_above_it():
    from rig.analysis import LAYERS as SUBS

    mods = modules()
    inside = {name: path for name, path in mods.items() if name.startswith("rig.analysis.")}
    unknown = sorted(name for name in inside if name.split(".")[2] not in SUBS)
    assert not unknown, f"analysis modules outside its subpackages (add to rig.analysis.LAYERS): {unknown}"
    wrong = []
    for name, path in sorted(inside.items()):
        own = SUBS.index(name.split(".")[2])
        for target in sorted(imports(path)):
            if target == "rig.analysis":
                wrong.append(f"{name} imports the facade rig.analysis (import from the subpackage)")
            elif target in inside and SUBS.index(target.split(".")[2]) > own:
                wrong.append(f"{name} ({SUBS[own]}) imports {target} ({target.split('.')[2]})")
    assert not wrong, "analysis subpackages import ones above them:\n" + "\n".join(wrong)


def test_the_analysis_facade_names_only_what_exists():
    import importlib

    import rig.analysis as analysis

    for name, where in analysis._PUBLIC.items():
        module = importlib.import_module(f"rig.analysis.{where}")
        assert getattr(analysis, name) is getattr(module, name)


def test_the_installed_package_lists_every_subpackage():
    """pyproject's explicit package list (needed for the folder mapping) misses none."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    present = {name for name, path in modules().items() if path.name == "__init__.py"}
    assert present == listed, (present ^ listed)
