"""Every figure the README's results print comes from one committed results file (`docs/results.json`):
each table made from it (`benchmarks/readme_results.py`) stands in the README, word for word, under its
marker."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tables() -> dict[str, str]:
    spec = importlib.util.spec_from_file_location("readme_results", ROOT / "benchmarks" / "readme_results.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.tables(module.load())


def test_the_readmes_tables_are_the_results_files():
    tables = _tables()
    assert set(tables) == {"synthetic", "real", "demo", "times"}
    readme = (ROOT / "README.md").read_text()
    for name, table in tables.items():
        assert f"<!-- {name} -->\n{table}\n" in readme, f"README's {name} table is not the results file's"


def test_a_changed_figure_is_caught():
    tables = _tables()
    readme = (ROOT / "README.md").read_text()
    first = tables["synthetic"].splitlines()[2]
    changed = first.replace(first.split(" | ")[1], "99.99")
    assert changed != first and readme.replace(first, changed).count(tables["synthetic"]) == 0
