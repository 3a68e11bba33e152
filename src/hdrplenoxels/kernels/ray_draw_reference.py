"""A batch's rays from the pool's flat pixel indices in plain PyTorch: the oracle of
`kernels/ray_draw_kernel.py`, which draws them in one pass."""

from __future__ import annotations

import torch

from hdrplenoxels.geometry.cameras import NDCSpec, pixel_rays, to_ndc


def draw_rays_reference(
    flat: torch.Tensor,
    starts: torch.Tensor,
    used_width: torch.Tensor,
    full_width: torch.Tensor,
    slot_images: torch.Tensor,
    pixel_offsets: torch.Tensor,
    pixels: torch.Tensor,
    c2w: torch.Tensor,
    intrinsics: torch.Tensor,
    ndc: NDCSpec | None,
) -> tuple[torch.Tensor, ...]:
    """(origins, dirs, target, image_ids, rows, cols) of the pooled pixels `flat` (B,) (the oracle of
    `kernels/ray_draw_kernel.py`): slot s of the pool holds image `slot_images[s]`'s pixels from flat
    index `starts[s]` on, `used_width[s]` columns of each row (a test view's left half) of an image
    `full_width[s]` wide whose pixels start at row `pixel_offsets[s]` of `pixels` (P, 3) uint8."""
    slot = torch.searchsorted(starts, flat, right=True) - 1
    local = flat - starts[slot]
    rows = local // used_width[slot]
    cols = local % used_width[slot]
    image_ids = slot_images[slot]
    target = pixels[pixel_offsets[slot] + rows * full_width[slot] + cols].float() / 255.0
    o, d = pixel_rays(c2w[image_ids], intrinsics[image_ids], cols, rows)
    if ndc is not None:
        o, d = to_ndc(o, d, ndc)
    return o, d, target, image_ids, rows, cols
