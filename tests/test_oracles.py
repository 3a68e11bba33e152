"""One pairing rule for kernels and their PyTorch oracles (docs/design.md, "Kernels"): every module that
defines a Warp kernel names its oracle and its parity test in one line of its docstring, the oracle's
docstring names the kernel module back, and the parity test uses the oracle's module."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "hdrplenoxels"
TESTS = Path(__file__).resolve().parent
ORACLE_LINE = re.compile(r"Oracle: `([\w.]+)`; parity:\s+(tests/test_\w+\.py)\.")


def kernel_modules() -> list[Path]:
    """Every module with a function decorated as a Warp kernel (`@KERNEL` or `@wp.kernel`, with or
    without options)."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef) and any(
                ast.unparse(d.func if isinstance(d, ast.Call) else d) in ("KERNEL", "wp.kernel")
                for d in node.decorator_list
            ):
                out.append(path)
                break
    return out


def split_module(dotted: str) -> tuple[str, list[str]]:
    """A dotted path as (the longest importable module, the attribute names after it)."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        return ".".join(parts[:i]), parts[i:]
    raise ImportError(dotted)


def resolve(dotted: str):
    """The object a dotted path names: a module, then attributes (a class's method too)."""
    module, names = split_module(dotted)
    obj = importlib.import_module(module)
    for name in names:
        obj = getattr(obj, name)
    return obj


def test_every_kernel_module_names_an_oracle_that_names_it_back_and_a_parity_test_of_both():
    modules = kernel_modules()
    assert len(modules) >= 6  # thread, lane, MSI, occupancy, fused RMSProp, TV
    for path in modules:
        rel = path.relative_to(PACKAGE).as_posix()
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        match = ORACLE_LINE.search(" ".join(doc.split()))
        assert match, f"{rel}: its docstring has no 'Oracle: `module.function`; parity: tests/test_x.py.'"
        oracle, test_file = match.groups()
        assert rel in " ".join((resolve(oracle).__doc__ or "").split()), f"{oracle} does not name {rel}"
        test_text = (TESTS.parent / test_file).read_text()
        module = split_module(oracle)[0]
        assert module in test_text or module.rsplit(".", 1)[-1] in test_text, (
            f"{test_file} never uses {module}"
        )
