"""What importing the package sets up for torch before torch loads (see `hdrplenoxels/__init__.py`)."""

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
import hdrplenoxels  # before torch, as every entry point does
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
