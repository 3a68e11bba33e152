"""One render API over two backends: the Warp kernel (fast, CPU and CUDA) and the PyTorch reference."""

from __future__ import annotations

import torch

from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.dispatch import BACKENDS, Backend, kernels_for
from hdrplenoxels.kernels.options import RenderOptions


def render_rays(
    grid: SparseGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions = RenderOptions(),
    backend: Backend = "warp",
    background: MSIBackground | None = None,
    distortion: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Linear radiance (N, 3) of rays with unit directions, differentiable w.r.t. density and SH (and
    the MSI's density and colour): C = C_fg + T_fg C_bg, where C_bg is `background`'s radiance
    along the ray or, without one, the constant `opt.background_brightness` (docs/method.md, "Background").
    `distortion`: also each ray's distortion loss (N,) of the grid's samples, differentiable."""
    if kernels_for(backend):
        from hdrplenoxels.render.autograd import render_background_warp, render_warp

        behind = None if background is None else render_background_warp(background, origins, dirs, opt)
        return render_warp(grid, origins, dirs, opt, behind=behind, distortion=distortion)
    from hdrplenoxels.kernels.background_reference import render_background_reference
    from hdrplenoxels.kernels.march_reference import render_reference

    behind = None if background is None else render_background_reference(background, origins, dirs, opt)
    return render_reference(grid, origins, dirs, opt, behind=behind, distortion=distortion)


__all__ = ["BACKENDS", "Backend", "MSIBackground", "RenderOptions", "render_rays"]
