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


def test_reshoot_kits_are_the_photos_and_both_reshoots_reduced_with_their_camera_truth(
    tiny_scene_path, tmp_path
):
    sys.path.insert(0, str(SCRIPT.parent))
    from real_captures import reshoot

    data, out = tiny_scene_path.parent, tmp_path / "kits"
    args = [
        sys.executable,
        str(SCRIPT),
        str(data),
        str(out),
        "--downscale",
        "2",
        "--quality",
        "0",
        "--reshoots",
    ]
    proc = subprocess.run(args, capture_output=True, text=True, cwd=SCRIPT.parent)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["photos", "static", "varying"]  # the work folder gone
    photos = load_scene(out / "photos")
    for a, b in zip(photos.images, load_scene(data, 2).images):
        assert np.array_equal(a, b)
    for variant in ("static", "varying"):
        kit, full = load_scene(out / variant), load_scene(reshoot(data, tmp_path / "full", variant), 2)
        assert list(kit.test_ids) == list(photos.test_ids)
        np.testing.assert_allclose(kit.cameras.c2w, photos.cameras.c2w)
        for a, b in zip(kit.images, full.images):
            assert np.array_equal(a, b)  # the re-shoot at full size, then reduced as `--downscale 2`
        assert (out / variant / "camera_truth.json").read_text() == (
            tmp_path / "full" / variant / "camera_truth.json"
        ).read_text()
    static, varying = load_scene(out / "static"), load_scene(out / "varying")
    assert any(not np.array_equal(a, b) for a, b in zip(static.images, varying.images))
