"""The grid on the PyTorch reference renderer, differentiated by autograd: the readable oracle the Warp
engine is tested against, and a fallback that needs no kernels. An MSI background renders through its
reference (`kernels/background_reference.py`) in the same graph."""

from __future__ import annotations

import torch

from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.tv import TVTerm
from hdrplenoxels.kernels.tv_reference import tv_grad_reference_
from hdrplenoxels.render import render_rays
from hdrplenoxels.train.engines.grid_engine import GridEngine
from hdrplenoxels.train.ray_pool import RayBatch


class TorchGridEngine(GridEngine):
    render_backend = "torch"
    fused_optimiser = False

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._rgb: torch.Tensor | None = None
        self._distortion: torch.Tensor | None = None

    def _leaves(self) -> list[torch.Tensor]:
        leaves = [self.field.density, self.field.sh]
        if self.background is not None:
            leaves += [self.background.density, self.background.color]
        return leaves

    def forward(self, batch: RayBatch) -> tuple[torch.Tensor, RayBatch]:
        for leaf in self._leaves():
            leaf.requires_grad_(True)
        self._rgb, self._distortion = render_rays(
            self.field,
            batch.origins,
            batch.dirs,
            self.render_opt,
            "torch",
            background=self.background,
            distortion=True,
        )
        return self._rgb.detach().requires_grad_(True), batch

    def backward(self, grad_rgb: torch.Tensor) -> None:
        rgb, self._rgb = self._rgb, None
        loss = (rgb * grad_rgb).sum() + self.distortion_weight * self._distortion.mean()
        self._distortion = None
        d_density, d_sh, *d_bg = torch.autograd.grad(loss, self._leaves())
        grads = self.gradients()
        grads.density[0].add_(d_density)
        grads.sh[0].add_(d_sh)
        if d_bg:
            bg_grads = self.background_gradients()
            bg_grads.density[0].add_(d_bg[0])
            bg_grads.color[0].add_(d_bg[1])

    def _add_tv(self, term: TVTerm, grad_parts: torch.Tensor, grads: GridGradients) -> None:
        tv_grad_reference_(term, grad_parts[0])
