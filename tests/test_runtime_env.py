"""Process-wide settings are explicit: importing the package sets nothing and starts no Warp; the command
line (and `apply_process_settings`) set up torch before it loads (`core/process_settings.py`)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

THP_SETTING = Path("/sys/kernel/mm/transparent_hugepage/enabled")

PROBE = """
import os
from hdrplenoxels.core.process_settings import apply_process_settings
apply_process_settings()  # before torch, as the command line does
import torch
x = torch.ones(64 * 2**20 // 4)  # 64 MiB, touched
huge = [l for l in open("/proc/self/smaps_rollup") if l.startswith("AnonHugePages")]
print(os.environ.get("THP_MEM_ALLOC_ENABLE"), os.environ.get("GOMP_SPINCOUNT"), huge[0].split()[1])
"""


def _probe(env: dict[str, str]) -> list[str]:
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return out.stdout.split()


def _thp_mode() -> str | None:
    try:
        match = re.search(r"\[(\w+)\]", THP_SETTING.read_text())
    except OSError:
        return None
    return match.group(1) if match else None


@pytest.mark.skipif(not Path("/proc/self/smaps_rollup").exists(), reason="needs Linux /proc")
def test_large_tensors_get_huge_pages_and_a_users_setting_wins():
    env = {k: v for k, v in os.environ.items() if k not in ("THP_MEM_ALLOC_ENABLE", "GOMP_SPINCOUNT")}
    thp, spin, huge_kb = _probe(env)
    assert (thp, spin) == ("1", "10000")
    off = _probe({**env, "THP_MEM_ALLOC_ENABLE": "0", "GOMP_SPINCOUNT": "5"})
    assert off[:2] == ["0", "5"]
    mode = _thp_mode()
    if mode not in ("madvise", "always"):
        return  # no huge pages on this machine: the setting is harmless, there is nothing to measure
    if int(huge_kb) == 0:  # memory too fragmented, or THP off for this process (containers can do that)
        pytest.skip("the kernel gave this process no huge page, so it cannot show the switch acting")
    if mode == "madvise":
        assert int(off[2]) == 0  # only torch's request gives huge pages here, so the switch is what acts


# Warp keeps its runtime in a private module (`warp._src.context` in 1.10+, `warp.context` before).
WARP_STARTED = """
import importlib
def WARP_STARTED():
    for name in ("warp._src.context", "warp.context"):
        try:
            return importlib.import_module(name).runtime is not None
        except (ImportError, AttributeError):
            continue
    raise RuntimeError("cannot tell whether Warp started")
"""

IMPORT_EVERYTHING = (
    WARP_STARTED
    + """
import os, importlib, pathlib
import hdrplenoxels
root = pathlib.Path(hdrplenoxels.__file__).parent
for path in sorted(root.rglob("*.py")):
    name = ".".join(("hdrplenoxels", *path.relative_to(root).with_suffix("").parts))
    name = name.removesuffix(".__init__")
    if name != "hdrplenoxels.__main__" and not name.startswith(SKIP):
        importlib.import_module(name)
print(os.environ.get("GOMP_SPINCOUNT"), os.environ.get("THP_MEM_ALLOC_ENABLE"), WARP_STARTED() is False)
"""
)


def test_importing_every_library_module_changes_nothing():
    """No environment variable set and Warp not started by imports alone (the CLI package is the entry
    point and applies the settings: it is the one exception, so it is checked apart)."""
    env = {k: v for k, v in os.environ.items() if k not in ("THP_MEM_ALLOC_ENABLE", "GOMP_SPINCOUNT")}

    def imported(skip: str) -> list[str]:
        script = f"SKIP = {skip!r}" + IMPORT_EVERYTHING
        return subprocess.run(
            [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
        ).stdout.split()

    assert imported(skip="hdrplenoxels.cli") == ["None", "None", "True"]
    assert imported(skip="(none)") == ["10000", "1", "True"]  # the entry point sets them, still no Warp


def test_warp_starts_on_first_kernel_use():
    script = (
        WARP_STARTED
        + """
import torch
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render import RenderOptions, render_rays
grid = SparseGrid.create((4, 4, 4), (0, 0, 0), (1, 1, 1), 1, 0.1, torch.device("cpu"))
before = WARP_STARTED()
render_rays(grid, torch.zeros(2, 3) - 2, torch.tensor([[1.0, 0, 0], [0, 1.0, 0]]), RenderOptions())
print(before, WARP_STARTED())
"""
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"]
