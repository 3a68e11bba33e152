"""The grid on the PyTorch reference renderer, differentiated by autograd: the readable oracle the Warp
engine is tested against, and a fallback that needs no kernels."""

from __future__ import annotations

import torch

from hdrplenoxels.render import render_rays
from hdrplenoxels.render.grad_buffers import GridGradients
from hdrplenoxels.train.engines.grid_engine import GridEngine
from hdrplenoxels.train.ray_pool import RayBatch
from hdrplenoxels.train.tv import tv_grad_


class TorchGridEngine(GridEngine):
    render_backend = "torch"

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._rgb: torch.Tensor | None = None

    def forward(self, batch: RayBatch) -> tuple[torch.Tensor, RayBatch]:
        self.field.density.requires_grad_(True)
        self.field.sh.requires_grad_(True)
        self._rgb = render_rays(self.field, batch.origins, batch.dirs, self.render_opt, "torch")
        return self._rgb.detach().requires_grad_(True), batch

    def backward(self, grad_rgb: torch.Tensor) -> None:
        rgb, self._rgb = self._rgb, None
        d_density, d_sh = torch.autograd.grad(rgb, [self.field.density, self.field.sh], grad_rgb)
        grads = self.gradients()
        grads.density[0].add_(d_density)
        grads.sh[0].add_(d_sh)

    def _add_tv(self, args: tuple, grads: GridGradients) -> None:
        tv_grad_(*args)

    def _optimise(self, grads: GridGradients, lrs: list[float]) -> None:
        self.optimizer.step_accumulated(
            [self.field.density, self.field.sh], [grads.density, grads.sh], lrs, False, None, touched=None
        )
