"""What the ray draw's kernel (`kernels/ray_draw_kernel.py`) and its oracle (`kernels/ray_draw_reference.py`)
share: the one argument structure both take, the pool a batch is drawn from."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from hdrplenoxels.geometry.cameras import NDCSpec


@dataclass(frozen=True)
class PooledPixels:
    """The training pixels of a pool, as a draw reads them: slot s holds image `slot_images[s]`'s pixels
    from flat index `starts[s]` on, `used_width[s]` columns of each row (a test view's left half) of an
    image `full_width[s]` wide whose pixels start at row `pixel_offsets[s]` of `pixels` (P, 3) uint8; the
    cameras (`c2w` (N, 4, 4), `intrinsics` (N, 4) by image) and the NDC warp (None: world rays)."""

    starts: torch.Tensor
    used_width: torch.Tensor
    full_width: torch.Tensor
    slot_images: torch.Tensor
    pixel_offsets: torch.Tensor
    pixels: torch.Tensor
    c2w: torch.Tensor
    intrinsics: torch.Tensor
    ndc: NDCSpec | None

    def to(self, device: torch.device | str) -> PooledPixels:
        """The same pool with every tensor on `device`."""
        moved = {
            f.name: getattr(self, f.name).to(device)
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), torch.Tensor)
        }
        return dataclasses.replace(self, **moved)
