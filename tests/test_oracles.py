"""One pairing rule for kernels and their PyTorch oracles (docs/design.md, "Kernels"): every module that
defines a Warp kernel names its oracle and its parity test in one line of its docstring; the oracle is a
`*_reference` function in a `*_reference.py` module beside the kernel module, whose docstring names the
kernel module back; neither module imports the other; and the parity test uses the oracle's module."""

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
        module, names = split_module(oracle)
        assert module in test_text or module.rsplit(".", 1)[-1] in test_text, (
            f"{test_file} never uses {module}"
        )
        package, oracle_module = module.rsplit(".", 1)
        kernel_module = "hdrplenoxels." + rel.removesuffix(".py").replace("/", ".")
        assert package == kernel_module.rsplit(".", 1)[0] and oracle_module.endswith("_reference"), (
            f"{rel}: its oracle's module {module} is not a *_reference module beside it"
        )
        assert names[-1].rstrip("_").endswith("_reference"), f"{oracle}: an oracle is named x_reference"
        oracle_path = PACKAGE / (module.removeprefix("hdrplenoxels.").replace(".", "/") + ".py")
        assert module not in imports(path), f"{rel} imports its oracle {module}"
        assert kernel_module not in imports(oracle_path), f"{module} imports its kernel module {rel}"


def imports(path: Path) -> set[str]:
    """The hdrplenoxels modules a file imports (at any depth of the file)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
    return out


def test_the_march_kernels_are_reached_only_through_the_launches():
    """One way into the render kernels, for training and evaluation alike: `kernels/march_kernel.py` (and for
    the MSI's, `kernels/background_kernel.py`) is the only module that imports them, besides the forward,
    which takes each layout's SH functions from its backward's module."""
    launchers = {
        "hdrplenoxels.kernels.march_forward": {"kernels/march_kernel.py"},
        "hdrplenoxels.kernels.march_threads": {"kernels/march_kernel.py", "kernels/march_forward.py"},
        "hdrplenoxels.kernels.march_lanes": {"kernels/march_kernel.py", "kernels/march_forward.py"},
        "hdrplenoxels.kernels.background_march": {"kernels/background_kernel.py"},
    }
    for kernel_module, allowed in launchers.items():
        users = {
            path.relative_to(PACKAGE).as_posix()
            for path in PACKAGE.rglob("*.py")
            if kernel_module in imports(path)
        }
        assert users == allowed, f"{kernel_module} is imported by {sorted(users)}"
