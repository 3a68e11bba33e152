"""The package's layers follow the data flow, and no module imports a layer above its own (docs/design.md)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "hdrplenoxels"

# Lowest first. A module may import its own layer and any layer listed before it.
LAYERS: list[set[str]] = [
    {"core"},
    {"geometry"},
    {"data"},
    {"grid"},
    {"kernels"},
    {"render"},
    {"tonemap"},
    {"train"},
    {"eval"},
    {"synth", "process"},
    {"experiments", "viewer"},
    {"cluster"},
    {"cli"},
]
RANK = {name: rank for rank, names in enumerate(LAYERS) for name in names}
TOP_LEVEL_FILES = {"__init__.py", "__main__.py"}


def _imported_units(path: Path, package_dir: Path) -> set[str]:
    """First components below the package of every `hdrplenoxels.*` module `path` imports."""
    rel = path.relative_to(package_dir).parts
    units = set()
    for node in ast.walk(ast.parse(path.read_text())):
        modules: list[str] = []
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing module's package
                base = list(rel[:-1])[: len(rel) - node.level]
                modules = [".".join(["hdrplenoxels", *base, *([node.module] if node.module else [])])]
            elif node.module:
                modules = [node.module]
            if modules[0] == "hdrplenoxels":  # `from hdrplenoxels import x`
                modules = [f"hdrplenoxels.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            modules = [a.name for a in node.names]
        for module in modules:
            parts = module.split(".")
            if parts[0] == "hdrplenoxels" and len(parts) > 1:
                units.add(parts[1])
    return units


def upward_imports(package_dir: Path) -> list[str]:
    """'importer -> imported' for each import of a higher layer (or of a unit with no layer)."""
    problems = []
    for path in sorted(package_dir.rglob("*.py")):
        rel = path.relative_to(package_dir)
        if len(rel.parts) == 1:
            if rel.name not in TOP_LEVEL_FILES:
                problems.append(f"{rel}: a module at the package top belongs in a layer")
            continue
        own = rel.parts[0]
        if own not in RANK:
            problems.append(f"{rel}: {own}/ is in no layer")
            continue
        for unit in _imported_units(path, package_dir):
            if unit not in RANK:
                problems.append(f"{rel} -> {unit}: not a layer")
            elif RANK[unit] > RANK[own]:
                problems.append(f"{rel} -> {unit}: imports a layer above its own ({own})")
    return problems


def test_no_module_imports_a_layer_above_its_own():
    assert upward_imports(PACKAGE) == []


def test_every_layer_exists():
    assert {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"} == set(RANK)


@pytest.mark.parametrize(
    "source",
    [
        "from hdrplenoxels.train.trainer import Trainer\n",
        "import hdrplenoxels.train.trainer\n",
        "from hdrplenoxels import train\n",
        "from ..train import trainer\n",
        "def lazy():\n    from hdrplenoxels.train import config\n",
    ],
)
def test_the_check_finds_an_upward_import(tmp_path, source):
    """A render module reaching up into training, however the import is spelled, is reported."""
    package = tmp_path / "hdrplenoxels"
    for layer in ("render", "train"):
        (package / layer).mkdir(parents=True)
        (package / layer / "__init__.py").write_text("")
    (package / "train" / "trainer.py").write_text("")
    (package / "render" / "kernels.py").write_text(source)
    assert upward_imports(package) == ["render/kernels.py -> train: imports a layer above its own (render)"]


def test_the_check_finds_a_module_outside_the_layers(tmp_path):
    package = tmp_path / "hdrplenoxels"
    package.mkdir()
    (package / "stray.py").write_text("")
    assert upward_imports(package) == ["stray.py: a module at the package top belongs in a layer"]
