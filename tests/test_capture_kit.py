"""`benchmarks/capture_kit.py`: a processed capture reduced to carry, every view kept, loading as the
dataset does at that downscale."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from hdrplenoxels.data import load_scene

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "capture_kit.py"


def test_a_kit_keeps_every_view_and_loads_as_the_downscaled_dataset(tiny_scene_path, tmp_path):
    out = tmp_path / "kit"
    data = tiny_scene_path.parent  # the dataset folder of its transforms.json
    args = [sys.executable, str(SCRIPT), str(data), str(out), "--downscale", "2", "--quality", "0"]
    proc = subprocess.run(args, capture_output=True, text=True, cwd=SCRIPT.parent)
    assert proc.returncode == 0, proc.stderr
    assert "downscale 2" in proc.stdout
    kit, full = load_scene(out), load_scene(data, 2)
    assert len(kit.images) == len(full.images) and list(kit.test_ids) == list(full.test_ids)
    for a, b in zip(kit.images, full.images):
        assert a.shape == b.shape and np.array_equal(a, b)  # PNG: the very pixels `--downscale 2` reads
