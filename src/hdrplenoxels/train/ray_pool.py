"""The training ray pool: pixels of training views plus, under the HDR protocol, test views' left halves.

Rays are not precomputed: a batch is a set of (image, row, col) triples drawn uniformly with replacement
over the pool and turned into rays on the fly, so memory stays O(pixels) bytes, not O(pixels) rays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.data.protocol import left_width
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.kernels.dispatch import use_kernel
from hdrplenoxels.kernels.ray_draw import PooledPixels
from hdrplenoxels.kernels.ray_draw_kernel import draw_rays
from hdrplenoxels.kernels.ray_draw_reference import draw_rays_reference
from hdrplenoxels.tonemap.pixels import PixelTargets

RGB_BYTES = 3  # uint8 RGB per pixel, in the scene's images and in the pool alike


def pooled_views(train_ids: list[int], test_ids: list[int], holdout: str) -> list[int]:
    """The views whose pixels the pool draws from, in order: every training view, and under the
    "right-half" holdout the test views too (their left halves only, which train their tone)."""
    return sorted(train_ids + (test_ids if holdout == "right-half" else []))


def pool_peak_bytes(sizes: np.ndarray, train_ids: list[int], test_ids: list[int], holdout: str) -> int:
    """Peak bytes of pixels while a `RayPool` is built over images of `sizes` (N, 2) W, H: the scene's
    decoded images, plus every pooled image twice (its flattened copy and the concatenated pool)."""
    pixels = sizes[:, 0].astype(np.int64) * sizes[:, 1]
    pooled = pooled_views(train_ids, test_ids, holdout)
    return RGB_BYTES * int(pixels.sum() + 2 * pixels[pooled].sum())


def pool_memory_warning(
    sizes: np.ndarray,
    train_ids: list[int],
    test_ids: list[int],
    holdout: str,
    budget_gb: float,
    downscale: int,
) -> str | None:
    """A warning with the smallest downscale factor that fits the budget, when the pool would exceed it
    (its pixels shrink with the square of the factor); None when it fits."""
    need = pool_peak_bytes(sizes, train_ids, test_ids, holdout)
    budget = budget_gb * 1e9
    if need <= budget:
        return None
    more = math.ceil(math.sqrt(need / budget))
    while need / more**2 > budget:
        more += 1
    return (
        f"the ray pool would hold {need / 1e9:.1f} GB of pixels at peak, over the budget of {budget_gb:g} GB "
        f"(data.pool_budget_gb); train with --downscale {downscale * more} (about {need / more**2 / 1e9:.1f} "
        "GB) or raise the budget"
    )


@dataclass
class RayBatch:
    origins: torch.Tensor  # (B, 3)
    dirs: torch.Tensor  # (B, 3)
    target: torch.Tensor  # (B, 3) in [0, 1]
    image_ids: torch.Tensor  # (B,) long, index over all images of the scene
    rows: torch.Tensor  # (B,) long
    cols: torch.Tensor  # (B,) long

    def reordered(self, order: torch.Tensor) -> RayBatch:
        """The same rays in the order `order` (indices into this batch)."""
        return RayBatch(*(getattr(self, f.name)[order] for f in fields(self)))

    def pixels(self) -> PixelTargets:
        """The photo pixels the rays were drawn from, as the tone mapper's loss takes them."""
        return PixelTargets(self.image_ids, self.rows, self.cols, self.target)


class RayPool:
    """Uniform sampling of training pixels across images of any sizes."""

    def __init__(
        self,
        images: list[np.ndarray],
        cameras: Cameras,
        geometry: SceneGeometry,
        train_ids: list[int],
        test_ids: list[int],
        holdout: str,
        device: torch.device,
    ):
        self.geometry = geometry
        self.device = device
        ids, widths = [], []
        for i in pooled_views(train_ids, test_ids, holdout):
            w, _ = cameras.size(i)
            ids.append(i)
            widths.append(w if i in train_ids else left_width(w))
        self.image_ids = torch.tensor(ids, dtype=torch.long, device=device)
        self.used_width = torch.tensor(widths, dtype=torch.long, device=device)
        self.full_width = torch.tensor(cameras.sizes[ids, 0], dtype=torch.long, device=device)
        self.heights = torch.tensor(cameras.sizes[ids, 1], dtype=torch.long, device=device)
        counts = self.used_width * self.heights
        self.starts = torch.cumsum(counts, 0) - counts
        self.total = int(counts.sum())
        # Pixels of every pooled image, flattened; offsets index each full image.
        flat = [torch.as_tensor(np.array(images[i], dtype=np.uint8).reshape(-1, 3)) for i in ids]
        sizes = torch.tensor([f.shape[0] for f in flat], dtype=torch.long)
        self.pixel_offsets = (torch.cumsum(sizes, 0) - sizes).to(device)
        self.pixels = torch.cat(flat).to(device)  # uint8
        self.c2w = torch.as_tensor(cameras.c2w, dtype=torch.float32, device=device)
        self.intrinsics = torch.as_tensor(cameras.intrinsics, dtype=torch.float32, device=device)

    def __len__(self) -> int:
        return self.total

    def sample(self, batch_size: int, generator: torch.Generator) -> RayBatch:
        """A batch drawn uniformly with replacement over every pooled pixel, on the generator's device
        (the training device's: a GPU then never waits for indices from the host)."""
        flat = torch.randint(0, self.total, (batch_size,), generator=generator, device=generator.device)
        return self.at(flat.to(self.device))

    def at(self, flat: torch.Tensor) -> RayBatch:
        """Rays and targets of pooled pixels given by their flat index in [0, len(self))."""
        draw = draw_rays if use_kernel(flat) else draw_rays_reference
        return RayBatch(*draw(flat, self.pooled()))

    def pooled(self) -> PooledPixels:
        """What a draw reads besides the indices (`kernels.ray_draw_kernel.draw_rays` and its oracle)."""
        ndc = self.geometry.ndc if self.geometry.mode == "ndc" else None
        return PooledPixels(self.starts, self.used_width, self.full_width, self.image_ids, self.pixel_offsets,
                            self.pixels, self.c2w, self.intrinsics, ndc)  # fmt: skip

    def linear_channel_means(self, n_images: int, gamma: float) -> torch.Tensor:
        """Per-image, per-channel mean of (pixel / 255)^gamma over pooled (training) pixels only, (N, 3).

        Images with no pooled pixels (test views under the full hold-out) get the mean over the others.
        """
        means = torch.full((n_images, 3), float("nan"), device=self.device)
        for slot, image in enumerate(self.image_ids.tolist()):
            h, w, used = int(self.heights[slot]), int(self.full_width[slot]), int(self.used_width[slot])
            start = int(self.pixel_offsets[slot])
            px = self.pixels[start : start + h * w].reshape(h, w, 3)[:, :used].float() / 255.0
            means[image] = (px**gamma).reshape(-1, 3).mean(0)
        pooled = ~torch.isnan(means[:, 0])
        means[~pooled] = means[pooled].mean(0)
        return means

    def iter_all(self, stride: int = 1, chunk: int = 1 << 14):
        """Every `stride`-th pooled pixel's rays, in chunks (for the weight-based pruning pass)."""
        idx = torch.arange(0, self.total, stride, device=self.device)
        for i in range(0, idx.shape[0], chunk):
            yield self.at(idx[i : i + chunk])
