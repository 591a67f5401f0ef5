"""The library's layers run one way: reader -> frontend -> bridge -> mapper -> exporters -> evaluation, shared
utilities below them all, the run-level config and checkpoints above; no module imports a layer above its own."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

LAYERS = [
    ("tambridge.errors", "tambridge.settings"),
    ("tambridge.files", "tambridge.state", "tambridge.threads", "tambridge.geometry", "tambridge.images"),
    ("tambridge.camera", "tambridge.rolling_shutter", "tambridge.trajectory", "tambridge.runlog", "tambridge.stop",
     "tambridge.run_folder"),
    ("tambridge.io",),
    ("tambridge.frontend",),
    ("tambridge.gaussians",),
    ("tambridge.bridge",),
    ("tambridge.mapping", "tambridge.device"),
    ("tambridge.export", "tambridge.viewer"),
    ("tambridge.evaluation",),
    ("tambridge.config", "tambridge.checkpoint"),
    ("tambridge.batch",),
]
"""Packages and modules from the bottom layer up; a module may import its own layer and the ones below."""


def layer_of(module: str) -> int | None:
    """The layer of a dotted module name (its longest listed prefix), None for ``tambridge`` itself."""
    matches = [(len(prefix), index) for index, layer in enumerate(LAYERS) for prefix in layer
               if module == prefix or module.startswith(prefix + ".")]
    return max(matches)[1] if matches else None


def library_modules() -> dict[str, Path]:
    modules = {}
    for path in (ROOT / "tambridge").rglob("*.py"):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        modules[name] = path
    return modules


def test_every_module_has_a_layer():
    unplaced = sorted(name for name in library_modules() if name != "tambridge" and layer_of(name) is None)
    assert unplaced == []


def test_no_module_imports_a_layer_above_its_own():
    upward = []
    for name, path in library_modules().items():
        own = layer_of(name)
        if own is None:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            imported = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported = [node.module]
            elif isinstance(node, ast.Import):
                imported = [alias.name for alias in node.names]
            for module in imported:
                other = layer_of(module) if module.startswith("tambridge.") else None
                if other is not None and other > own:
                    upward.append(f"{name} (layer {own}) imports {module} (layer {other})")
    assert upward == []


def test_the_layer_table_sees_an_upward_import():
    # The check itself: a frontend module importing the mapper would be caught.
    assert layer_of("tambridge.frontend.orb.frontend") < layer_of("tambridge.mapping.stage")
    assert layer_of("tambridge.gaussians.cpu_kernel") < layer_of("tambridge.evaluation.report")
