"""The Warp render as a differentiable torch function, for code that renders through autograd
(`render_rays`, evaluation, tests); training calls `render/launch.py` directly.

Warp's automatic adjoint is never used (`docs/method.md`, "Rendering"): the backward is the
hand-written re-march of `render/thread_kernels.py` / `render/lane_kernels.py`, summed over the
per-thread gradient buffers.
"""

from __future__ import annotations

import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render.grad_buffers import GridGradients, gradient_parts
from hdrplenoxels.render.launch import accumulate_backward, render_forward
from hdrplenoxels.render.options import RenderOptions


class _WarpRender(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density, sh, grid: SparseGrid, origins, dirs, opt: RenderOptions):
        out = render_forward(grid, origins, dirs, opt)
        ctx.save_for_backward(origins, dirs, out)
        ctx.grid = grid
        ctx.opt = opt
        return out

    @staticmethod
    def backward(ctx, grad_out):
        origins, dirs, out = ctx.saved_tensors
        grads = GridGradients(ctx.grid, gradient_parts(ctx.grid))
        accumulate_backward(ctx.grid, origins, dirs, out, grad_out, ctx.opt, grads)
        grad_density, grad_sh = grads.total()
        return grad_density, grad_sh, None, None, None, None


def render_warp(
    grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions = RenderOptions()
) -> torch.Tensor:
    """Linear radiance (N, 3); differentiable w.r.t. `grid.density` and `grid.sh`."""
    if origins.shape[0] == 0:
        return origins.new_zeros((0, 3))
    return _WarpRender.apply(grid.density, grid.sh, grid, origins, dirs, opt)
