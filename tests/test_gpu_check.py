"""`make gpu-check` (benchmarks/gpu_check.py): a clear no-op without CUDA, and its driver's summary."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "gpu_check.py"


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_without_cuda_it_says_so_and_exits_0(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "no CUDA device" in proc.stdout
    assert not out.exists()  # nothing measured, nothing written


def test_sections_run_in_their_own_processes_and_are_summarised(tmp_path):
    """The plumbing on the CPU: two sections, both summaries written, a figure in the markdown."""
    out = tmp_path / "out"
    args = ["--out", str(out), "--device", "cpu", "--demo-data", str(tmp_path), "--sections", "env", "lanes",
            "--lanes", "0", "--spike-rays", "64", "--render-rays", "32", "96", "--repeats", "1",
            "--limit-scale", "5"]  # fmt: skip
    proc = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((out / "gpu_check.json").read_text())
    assert [report["sections"][s]["status"] for s in ("env", "lanes")] == ["ok", "ok"]
    assert report["sections"]["env"]["result"]["torch"] == torch.__version__
    assert report["sections"]["lanes"]["result"]["lanes_0_train_rays_per_s"] > 0
    summary = (out / "gpu_check.md").read_text()
    assert "Lanes per ray (spike, 64 rays" in summary and "| lanes | ok |" in summary
    assert "96 rays" in summary and report["sections"]["lanes"]["result"]["render_96_lanes_32_rays_per_s"] > 0
