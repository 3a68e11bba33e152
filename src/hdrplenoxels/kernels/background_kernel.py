"""Launches of the MSI background kernels and their gradient buffers, for the trainer and autograd.

As for the grid (`kernels/grad_buffers.py`), Warp's CPU atomics are plain adds, so every CPU part of the
backward adds into its own buffers (as many as the memory share allows) and the optimiser sums them.
"""

from __future__ import annotations

import torch
import warp as wp

from hdrplenoxels.core.host_memory import available_memory_bytes
from hdrplenoxels.core.parallel import cpu_workers, split
from hdrplenoxels.core.warp_runtime import launch_split, to_warp, warp_device, warp_struct
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.kernels.background_march import (
    MSIGradientTargets,
    MSIView,
    msi_backward_kernel,
    msi_forward_kernel,
)
from hdrplenoxels.kernels.grad_buffers import SPARE_MEMORY_SHARE, part_buffers
from hdrplenoxels.kernels.march_kernel import march_params, prepared_rays, rays_input, vec3s
from hdrplenoxels.kernels.options import RenderOptions


class MSIGradients:
    """d(loss)/d(MSI density, colour), one part per CPU thread of the backward (one on CUDA)."""

    def __init__(self, bg: MSIBackground, parts: int = 1):
        # Stacked whole (each part contiguous, as the MSI's sampled TV needs): an MSI is far below the
        # sizes whose stride from part to part Warp cannot address, which `to_warp` would refuse.
        self.density = part_buffers(parts, tuple(bg.density.shape), 0, bg.device)
        self.color = part_buffers(parts, tuple(bg.color.shape), 0, bg.device)

    def total(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(d density, d colour) summed over the parts (new tensors)."""
        return self.density.sum(0), self.color.sum(0)


def msi_gradient_parts(bg: MSIBackground) -> int:
    """Buffers the backward over `bg` uses: one per CPU thread, as many as fit (`SPARE_MEMORY_SHARE`)."""
    if bg.device.type != "cpu":
        return 1
    workers = cpu_workers()
    part_bytes = bg.density.numel() * 4 * 4  # float32 density and 3 colour channels
    available = available_memory_bytes()
    if workers == 1 or available is None:
        return workers
    return max(1, min(workers, 1 + int(available * SPARE_MEMORY_SHARE) // part_bytes))


def _msi_view(bg: MSIBackground) -> MSIView:
    return warp_struct(
        MSIView,
        density=to_warp(bg.density.detach().contiguous(), "the MSI density"),
        color=vec3s(bg.color),
        center=wp.vec3(*bg.center),
        radius=bg.radius,
        layers=bg.layers,
        height=bg.height,
        width=bg.width,
        samples_per_layer=bg.samples_per_layer,
    )


def msi_forward(
    bg: MSIBackground, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions
) -> torch.Tensor:
    """Background radiance (N, 3) of world rays with unit directions (no autograd)."""
    device = warp_device(bg.density)
    origins, dirs, out = prepared_rays(origins, dirs)
    n = origins.shape[0]
    if n == 0:
        return out
    head = [_msi_view(bg), march_params(opt), rays_input(origins, dirs)]
    out_rgb = to_warp(out, "the radiance output", dtype=wp.vec3)
    launch_split(msi_forward_kernel, n, head, [out_rgb], device)
    return out


def msi_accumulate_backward(
    bg: MSIBackground,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    rgb: torch.Tensor,
    grad_rgb: torch.Tensor,
    opt: RenderOptions,
    grads: MSIGradients,
) -> None:
    """Add d(loss)/d(MSI density, colour) for rays whose background was `rgb` and whose upstream
    gradient w.r.t. it is `grad_rgb` (already times the foreground's transmittance) into `grads`."""
    device = warp_device(bg.density)
    n = origins.shape[0]
    if n == 0:
        return
    head = [_msi_view(bg), march_params(opt), rays_input(origins, dirs)]
    tail = [vec3s(rgb), vec3s(grad_rgb)]
    per_part = []
    for d, c in zip(grads.density, grads.color):
        color = to_warp(c, "an MSI colour gradient part", dtype=wp.vec3)
        targets = warp_struct(
            MSIGradientTargets, density=to_warp(d, "an MSI density gradient part"), color=color
        )
        per_part.append([*tail, targets])
    launch_split(msi_backward_kernel, n, head, lambda part: per_part[part], device, split(n, len(per_part)))
