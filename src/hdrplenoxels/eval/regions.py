"""Image regions to score separately: the pixels whose rays never enter the grid's box, which only a
background model can fit (docs/method.md, "Background")."""

from __future__ import annotations

import torch

from hdrplenoxels.geometry.cameras import pixel_grid
from hdrplenoxels.kernels.march_reference import ray_segments
from hdrplenoxels.train.model import Model


@torch.no_grad()
def outside_box(model: Model, i: int) -> torch.Tensor:
    """(H, W) bool on the CPU: view `i`'s pixels whose rays miss the grid's box (no sample in it)."""
    cams = model.cameras
    w, h = cams.size(i)
    device = model.grid.device
    rows, cols = pixel_grid(h, w, device)
    c2w = torch.as_tensor(cams.c2w[i], dtype=torch.float32, device=device).expand(h * w, 4, 4)
    k = torch.as_tensor(cams.intrinsics[i], dtype=torch.float32, device=device).expand(h * w, 4)
    o, d = model.geometry.rays(c2w, k, cols, rows)
    return (ray_segments(model.grid, o, d, model.render_opt).num_samples == 0).reshape(h, w).cpu()
