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


def imported_modules(name: str, source: str, is_package: bool = False) -> list[str]:
    """The dotted names module ``name`` (a package's ``__init__`` where ``is_package``) imports in ``source``,
    relative imports resolved; ``from a import b`` imports ``a``, or where ``a`` has no layer (``tambridge``
    itself) ``a.b``."""
    package = name.split(".") if is_package else name.split(".")[:-1]
    imported = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else [])) \
                if node.level else node.module
            imported += [base] if layer_of(base) is not None else [f"{base}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            imported += [alias.name for alias in node.names]
    return imported


def upward_imports(name: str, source: str, is_package: bool = False) -> list[str]:
    """The imports of module ``name`` (source text ``source``) from a layer above its own, as messages."""
    own = layer_of(name)
    upward = []
    for module in dict.fromkeys(imported_modules(name, source, is_package)):
        other = layer_of(module) if module.startswith("tambridge.") else None
        if own is not None and other is not None and other > own:
            upward.append(f"{name} (layer {own}) imports {module} (layer {other})")
    return upward


def test_no_module_imports_a_layer_above_its_own():
    upward = [message for name, path in library_modules().items()
              for message in upward_imports(name, path.read_text(), path.name == "__init__.py")]
    assert upward == []


def test_the_check_sees_upward_imports_absolute_relative_and_of_submodules():
    name = "tambridge.frontend.orb.frontend"
    for source, module in (("from tambridge.mapping.stage import MappingStage", "tambridge.mapping.stage"),
                           ("import tambridge.mapping.stage", "tambridge.mapping.stage"),
                           ("from tambridge import io, mapping", "tambridge.mapping"),
                           ("from ...mapping import stage", "tambridge.mapping"),
                           ("from ...mapping.stage import MappingStage", "tambridge.mapping.stage")):
        assert upward_imports(name, source) == [f"{name} (layer 4) imports {module} (layer 7)"], source
    assert upward_imports("tambridge.frontend", "from ..mapping import stage", is_package=True) == [
        "tambridge.frontend (layer 4) imports tambridge.mapping (layer 7)"]
    for source in ("from tambridge.io.tum import Frame", "from ..io import tum", "from . import matching",
                   "import numpy", "from tambridge import camera", "from tambridge.camera import Camera"):
        assert upward_imports(name, source) == [], source
