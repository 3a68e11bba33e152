"""A batch's rays from the pool's flat pixel indices in plain PyTorch: the oracle of
`kernels/ray_draw_kernel.py`, which draws them in one pass."""

from __future__ import annotations

import torch

from hdrplenoxels.geometry.cameras import pixel_rays, to_ndc
from hdrplenoxels.kernels.ray_draw import PooledPixels


def draw_rays_reference(flat: torch.Tensor, pool: PooledPixels) -> tuple[torch.Tensor, ...]:
    """(origins, dirs, target, image_ids, rows, cols) of the pooled pixels `flat` (B,) of `pool` (the
    oracle of `kernels/ray_draw_kernel.py`)."""
    starts, used_width, full_width = pool.starts, pool.used_width, pool.full_width
    slot = torch.searchsorted(starts, flat, right=True) - 1
    local = flat - starts[slot]
    rows = local // used_width[slot]
    cols = local % used_width[slot]
    image_ids = pool.slot_images[slot]
    target = pool.pixels[pool.pixel_offsets[slot] + rows * full_width[slot] + cols].float() / 255.0
    o, d = pixel_rays(pool.c2w[image_ids], pool.intrinsics[image_ids], cols, rows)
    if pool.ndc is not None:
        o, d = to_ndc(o, d, pool.ndc)
    return o, d, target, image_ids, rows, cols
