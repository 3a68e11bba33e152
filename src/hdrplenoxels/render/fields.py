"""Every kind of radiance field behind one render call (docs/design.md, "Engine interface"); their files
are `train/field_io.py`'s."""

from __future__ import annotations

import torch

from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render import Backend, RenderOptions, render_rays
from hdrplenoxels.render.nerf import Appearance, NerfField

Field = SparseGrid | NerfField


def render_field(
    field: Field,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions,
    backend: Backend = "warp",
    appearance: Appearance | None = None,
    background: MSIBackground | None = None,
) -> torch.Tensor:
    """Linear radiance (N, 3) of rays with unit directions, no gradients. `backend` picks the grid's
    renderer; `appearance` the appearance of a NeRF-A (other fields have none and ignore it); `background`
    the grid's MSI, composited behind it (None: the constant `opt.background_brightness`)."""
    if isinstance(field, SparseGrid):
        with torch.no_grad():
            return render_rays(field, origins, dirs, opt, backend, background=background)
    if background is not None:
        raise ValueError("only a voxel grid renders with an MSI background")
    return field.render(origins, dirs, opt.background_brightness, appearance)
