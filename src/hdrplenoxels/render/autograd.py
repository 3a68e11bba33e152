"""The Warp render as a differentiable torch function, for code that renders through autograd
(`render_rays`, evaluation, tests); training calls `kernels/march_kernel.py` directly.

Warp's automatic adjoint is never used (`docs/method.md`, "Rendering"): the backward is the
hand-written re-march of `kernels/march_threads.py` / `kernels/march_lanes.py`, summed over the
per-thread gradient buffers, and for the MSI background that of `kernels/background_march.py`.
"""

from __future__ import annotations

import torch

from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.background_kernel import (
    MSIGradients,
    msi_accumulate_backward,
    msi_forward,
    msi_gradient_parts,
)
from hdrplenoxels.kernels.grad_buffers import GridGradients, gradient_parts
from hdrplenoxels.kernels.march_kernel import accumulate_backward, render_forward
from hdrplenoxels.kernels.options import RenderOptions


class _WarpRender(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density, sh, behind, grid: SparseGrid, origins, dirs, opt: RenderOptions):
        transmittance = None if behind is None else origins.new_empty(origins.shape[0])
        stats = origins.new_empty((origins.shape[0], 3))
        out = render_forward(
            grid, origins, dirs, opt, behind=behind, transmittance=transmittance, distortion=stats
        )
        ctx.save_for_backward(origins, dirs, out, transmittance, stats)
        ctx.grid = grid
        ctx.opt = opt
        ctx.set_materialize_grads(False)  # an unused distortion output costs its backward nothing
        return out, stats[:, 2].clone()

    @staticmethod
    def backward(ctx, grad_out, grad_distortion):
        origins, dirs, out, transmittance, stats = ctx.saved_tensors
        if grad_out is None:
            grad_out = torch.zeros_like(out)
        grads = GridGradients(ctx.grid, gradient_parts(ctx.grid))
        distortion = None if grad_distortion is None else (stats, grad_distortion)
        accumulate_backward(ctx.grid, origins, dirs, out, grad_out, ctx.opt, grads, distortion=distortion)
        grad_density, grad_sh = grads.total()
        # C = C_fg + T_fg C_bg, and T_fg does not depend on C_bg.
        grad_behind = None if transmittance is None else transmittance[:, None] * grad_out
        return grad_density, grad_sh, grad_behind, None, None, None, None


class _WarpBackground(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density, color, bg: MSIBackground, origins, dirs, opt: RenderOptions):
        out = msi_forward(bg, origins, dirs, opt)
        ctx.save_for_backward(origins, dirs, out)
        ctx.bg = bg
        ctx.opt = opt
        return out

    @staticmethod
    def backward(ctx, grad_out):
        origins, dirs, out = ctx.saved_tensors
        grads = MSIGradients(ctx.bg, msi_gradient_parts(ctx.bg))
        msi_accumulate_backward(ctx.bg, origins, dirs, out, grad_out, ctx.opt, grads)
        grad_density, grad_color = grads.total()
        return grad_density, grad_color, None, None, None, None


def render_warp(
    grid: SparseGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions = RenderOptions(),
    behind: torch.Tensor | None = None,
    distortion: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Linear radiance (N, 3); differentiable w.r.t. `grid.density`, `grid.sh` and the per-ray radiance
    `behind` (N, 3) composited behind the march (None: the constant `opt.background_brightness`);
    `distortion`: also each ray's distortion loss (N,) (`march_reference.distortion_loss`), differentiable."""
    if origins.shape[0] == 0:
        empty = origins.new_zeros((0, 3))
        return (empty, origins.new_zeros(0)) if distortion else empty
    rgb, dist = _WarpRender.apply(grid.density, grid.sh, behind, grid, origins, dirs, opt)
    return (rgb, dist) if distortion else rgb


def render_background_warp(
    bg: MSIBackground, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions = RenderOptions()
) -> torch.Tensor:
    """The MSI's radiance (N, 3) along world rays; differentiable w.r.t. `bg.density` and `bg.color`."""
    if origins.shape[0] == 0:
        return origins.new_zeros((0, 3))
    return _WarpBackground.apply(bg.density, bg.color, bg, origins, dirs, opt)
