"""The benchmark scripts import against the package as it is: a name renamed or removed in the package
fails here, on the CPU, rather than in a timed run on a GPU machine (none of them is run by a test)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


@pytest.mark.parametrize("script", sorted(str(p.relative_to(BENCHMARKS)) for p in BENCHMARKS.rglob("*.py")))
def test_every_benchmark_script_imports(script, monkeypatch):
    """The suite's scripts at the top of benchmarks/, and each study's under benchmarks/studies/."""
    path = BENCHMARKS / script
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    monkeypatch.syspath_prepend(str(path.parent))
    module = importlib.import_module(path.stem)
    assert callable(getattr(module, "main", None)), f"benchmarks/{script} has no main()"
    sys.modules.pop(path.stem, None)
