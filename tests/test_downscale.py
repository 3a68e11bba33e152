"""`--downscale N`: the area filter, exact intrinsics, distortion undone first, `images_N` copies, the ray
pool's memory warning, and render/eval at the run's own factor (and `train`'s line on the scene's box)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from hdrplenoxels.cli.main import main
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.description import Distortion
from hdrplenoxels.data.downscale import block_average, scaled_intrinsics
from hdrplenoxels.data.image_io import read_image, write_png
from hdrplenoxels.data.undistort import undistort
from hdrplenoxels.eval.evaluate import run_downscale
from hdrplenoxels.geometry.cameras import pixel_rays
from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.train.ray_pool import pool_memory_warning, pool_peak_bytes

W, H = 13, 10  # not multiples of 2 or 3: the remainder is cropped


def _dataset(folder: Path, n: int = 3, w: int = W, h: int = H, **meta) -> Path:
    """A nerfstudio scene of `n` random `w`x`h` PNGs seen by cameras on a line."""
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        name = f"images/img_{i}.png"
        write_png(folder / name, rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * i, 0.0, 3.0]
        frames.append({"file_path": name, "transform_matrix": pose.tolist()})
    base = {
        "fl_x": 12.0,
        "fl_y": 11.0,
        "cx": 6.2,
        "cy": 4.9,
        "w": w,
        "h": h,
        "aabb": [[-1, -1, -1], [1, 1, 1]],
    }
    (folder / "transforms.json").write_text(json.dumps({**base, **meta, "frames": frames}))
    return folder


def test_block_average_is_the_mean_of_each_block_and_crops_the_remainder():
    img = np.arange(5 * 7 * 3, dtype=np.uint8).reshape(5, 7, 3)
    out = block_average(img, 2)
    assert out.shape == (2, 3, 3) and out.dtype == np.uint8
    assert out[1, 2, 0] == np.rint(img[2:4, 4:6, 0].astype(float).mean())
    assert out[0, 0, 1] == np.rint(img[0:2, 0:2, 1].astype(float).mean())
    ones = np.array([[0, 1], [1, 1]], dtype=np.uint8)[..., None]
    assert block_average(ones, 2)[0, 0, 0] == 1  # 0.75 rounds to the nearest value
    hdr = np.random.default_rng(1).random((4, 4, 3)).astype(np.float32) * 100
    np.testing.assert_allclose(block_average(hdr, 4)[0, 0], hdr.reshape(-1, 3).mean(0), rtol=1e-6)


@pytest.mark.parametrize("factor", [2, 3])
def test_a_reduced_pixel_sees_along_its_block_centre(factor):
    """The ray through reduced pixel (j, i) is the full-size ray through its block's centre."""
    k = (12.0, 11.0, 6.2, 4.9)
    c2w = torch.eye(4, dtype=torch.float64)[None].expand(4, 4, 4)
    j, i = torch.tensor([0, 1, 2, 3]), torch.tensor([0, 2, 1, 2])
    _, small = pixel_rays(
        c2w, torch.tensor([scaled_intrinsics(k, factor)], dtype=torch.float64).expand(4, 4), j, i
    )
    # Block centre (j + 0.5) N in full-size pixel coordinates, i.e. at the pixel index (j + 0.5) N - 0.5.
    cols, rows = (j + 0.5) * factor - 0.5, (i + 0.5) * factor - 0.5
    _, full = pixel_rays(c2w, torch.tensor([k], dtype=torch.float64).expand(4, 4), cols, rows)
    torch.testing.assert_close(small, full, rtol=0, atol=1e-12)


def test_load_scene_downscales_images_and_intrinsics(tmp_path):
    folder = _dataset(tmp_path / "scene")
    full, half = load_scene(folder), load_scene(folder, downscale=2)
    assert half.images[1].shape == (H // 2, W // 2, 3)
    np.testing.assert_array_equal(half.images[1], block_average(full.images[1], 2))
    np.testing.assert_allclose(half.cameras.intrinsics, full.cameras.intrinsics / 2)
    assert half.cameras.sizes.tolist() == [[W // 2, H // 2]] * 3
    assert half.extras["downscale"] == 2


def test_a_distorted_image_is_undistorted_at_full_size_then_reduced(tmp_path):
    lens = {"k1": 0.2, "k2": 0.02, "p1": 0.001, "p2": -0.001}
    folder = _dataset(tmp_path / "scene", w=40, h=30, **lens)
    half = load_scene(folder, downscale=2)
    raw = read_image(folder / "images/img_0.png")
    coeffs = (lens["k1"], lens["k2"], lens["p1"], lens["p2"], 0.0, 0.0, 0.0, 0.0)
    pinhole, k = undistort(raw, (12.0, 11.0, 6.2, 4.9), Distortion("FULL_OPENCV", coeffs))
    np.testing.assert_array_equal(half.images[0], block_average(pinhole, 2))
    np.testing.assert_allclose(half.cameras.intrinsics[0], scaled_intrinsics(k, 2))


def test_images_n_copies_are_used_when_their_size_fits(tmp_path):
    folder = _dataset(tmp_path / "scene", w=16, h=12)
    for i in range(3):  # the layout's own reduced copies, distinguishable from our area filter
        write_png(folder / f"images_4/img_{i}.png", np.full((3, 4, 3), 7 * i + 1, dtype=np.uint8))
    scene = load_scene(folder, downscale=4)
    assert scene.images[2].shape == (3, 4, 3) and (scene.images[2] == 15).all()
    np.testing.assert_allclose(scene.cameras.intrinsics[0], (3.0, 2.75, 6.2 / 4, 4.9 / 4))
    # A copy of the wrong size is not the image reduced 4 times: the full-size image is reduced instead.
    write_png(folder / "images_4/img_1.png", np.zeros((5, 5, 3), dtype=np.uint8))
    scene = load_scene(folder, downscale=4)
    full = load_scene(folder)
    np.testing.assert_array_equal(scene.images[1], block_average(full.images[1], 4))
    assert (scene.images[0] == 1).all()


def test_the_pool_warning_suggests_a_factor_that_fits_the_budget():
    sizes = np.array([[1920, 1080]] * 50)
    train, test = list(range(1, 50)), [0]
    need = pool_peak_bytes(sizes, train, test, "right-half")
    assert need == 3 * 1920 * 1080 * (50 + 2 * 50)
    assert pool_memory_warning(sizes, train, test, "right-half", need / 1e9, 1) is None
    warning = pool_memory_warning(sizes, train, test, "right-half", need / 1e9 / 5, 1)
    assert warning is not None and "--downscale 3" in warning  # 2x2 = 4 < 5 <= 9 = 3x3
    assert "--downscale 6" in pool_memory_warning(sizes, train, test, "right-half", need / 1e9 / 5, 2)


def run_cli(argv: list[str]) -> None:
    try:
        main(argv)
    except SystemExit as e:
        assert e.code in (0, None), f"hdrplenoxels {' '.join(argv)} exited with {e.code}"


def test_train_downscale_is_recorded_and_used_by_eval_and_render(tmp_path, capsys):
    folder = _dataset(tmp_path / "scene", n=9, w=48, h=24)  # the scored right halves fit SSIM's window
    run = tmp_path / "run"
    run_cli(
        ["train", str(folder), "--out", str(run), "--iters", "2", "--downscale", "2", "--quiet"]
        + ["--set", "data.pool_budget_gb=1e-6"]
    )
    out = capsys.readouterr()
    assert "--downscale 10" in out.err  # 23,328 B of pixels at factor 2: 933 B at 10
    assert "scene: bounding box from 'aabb' in transforms.json, 2 x 2 x 2 units;" in out.out
    assert json.loads((run / "config.json").read_text())["data"]["downscale"] == 2
    model = Model.load(run / MODEL_FILE)
    assert run_downscale(model) == 2 and model.cameras.sizes.tolist() == [[24, 12]] * 9
    run_cli(["eval", str(run), "--no-lpips", "--backend", "torch", "--json", str(tmp_path / "m.json")])
    assert json.loads((tmp_path / "m.json").read_text())["num_test_views"] == 2
    run_cli(["render", str(run), "--out", str(tmp_path / "r"), "--backend", "torch"])
    assert read_image(tmp_path / "r" / "img_0.png").shape == (12, 24, 3)
