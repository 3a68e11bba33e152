"""Pure-PyTorch volume renderer: the readable oracle every kernel is tested against.

It samples every ray at the same points as the Warp kernel, interpolates density and SH trilinearly
(empty corners count as 0), composites front to back with the early stop, and relies on autograd for
gradients. Memory grows with rays x samples, so rays are processed in chunks.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hdrplenoxels.geometry.sh import eval_sh_basis
from hdrplenoxels.grid.sparse_grid import SparseGrid, corner_weights
from hdrplenoxels.render.options import RenderOptions

TINY_DIR = 1e-9  # a zero direction component is replaced by this in the slab test (both backends)
# A sample this close (in steps) before the far face of the box still counts. Rays parallel to an
# axis cross the box in a whole number of steps, where an exact count would hinge on the last ulp
# (CUDA fuses multiply-adds, the CPU may not): the slack moves that knife edge off the integers.
FAR_FACE_SLACK = 1e-3


@dataclass
class RaySegments:
    """Rays in grid units: origin, unit direction, world length per grid unit, sample range."""

    origin: torch.Tensor  # (N, 3) grid coordinates
    direction: torch.Tensor  # (N, 3) unit, grid space
    delta_scale: torch.Tensor  # (N,) world (or NDC) length of one grid unit along the ray
    t_min: torch.Tensor  # (N,)
    num_samples: torch.Tensor  # (N,) long; 0 for rays that miss the box


def ray_segments(
    grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions
) -> RaySegments:
    scale, offset = grid.world_to_grid_affine()
    o = origins * scale + offset
    d = dirs * scale
    norm = d.norm(dim=-1)
    delta_scale = 1.0 / norm
    d = d / norm[:, None]
    reso = torch.tensor(grid.reso, dtype=o.dtype, device=o.device)
    d_safe = torch.where(d == 0, torch.full_like(d, TINY_DIR), d)
    t1 = (-0.5 - o) / d_safe
    t2 = (reso - 0.5 - o) / d_safe
    t_min = torch.minimum(t1, t2).amax(-1).clamp(min=0.0)
    t_max = torch.maximum(t1, t2).amin(-1).clamp(max=opt.t_max)
    hit = t_min <= t_max
    n = torch.where(hit, torch.floor((t_max - t_min) / opt.step_size + FAR_FACE_SLACK).long() + 1, 0)
    return RaySegments(o, d, delta_scale, t_min, n)


def render_reference(
    grid: SparseGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions = RenderOptions(),
    chunk: int = 1024,
    background: torch.Tensor | None = None,
) -> torch.Tensor:
    """Linear radiance (N, 3) of rays `origins`, `dirs` (world or NDC units, unit dirs); autograd-able.

    `background`: per-ray radiance (N, 3) seen with the transmittance left after the march (e.g. the
    MSI's, docs/method.md, "Background"); None: the constant `opt.background`."""
    outs = [
        _render_chunk(
            grid,
            origins[i : i + chunk],
            dirs[i : i + chunk],
            opt,
            None if background is None else background[i : i + chunk],
        )
        for i in range(0, origins.shape[0], chunk)
    ]
    return torch.cat(outs) if outs else origins.new_zeros((0, 3))


def sample_points(seg: RaySegments, step_size: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Grid positions (N, S, 3) of every sample and a validity mask (N, S), S = max samples."""
    s_max = int(seg.num_samples.max()) if seg.num_samples.numel() else 0
    k = torch.arange(s_max, device=seg.origin.device)
    valid = k[None, :] < seg.num_samples[:, None]
    t = seg.t_min[:, None] + k[None, :].to(seg.t_min.dtype) * step_size
    pos = seg.origin[:, None, :] + t[..., None] * seg.direction[:, None, :]
    # Padding samples of shorter rays (and rays that miss, possibly with non-finite geometry) are parked
    # at the grid origin so that indexing stays valid; `valid` excludes them from compositing.
    pos = torch.where(valid[..., None], pos, torch.zeros_like(pos))
    return pos, valid


def composite_weights(
    sigma: torch.Tensor, valid: torch.Tensor, delta: torch.Tensor, opt: RenderOptions
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample weights w_k = T_k alpha_k (N, S) and the transmittance left for the background (N,).

    A sample counts iff it is valid, its density exceeds `sigma_thresh` and the transmittance before it
    is still >= `stop_thresh` (the kernel stops right after the sample that drops T below it, and then
    adds no background).
    """
    used = valid & (sigma > opt.sigma_thresh)
    tau = torch.where(used, sigma, torch.zeros_like(sigma)) * delta[:, None]
    log_t_after = -torch.cumsum(tau, dim=1)
    log_t_before = torch.cat([torch.zeros_like(log_t_after[:, :1]), log_t_after[:, :-1]], dim=1)
    t_before = torch.exp(log_t_before)
    active = used & (t_before >= opt.stop_thresh)
    weights = torch.where(active, t_before * (1.0 - torch.exp(-tau)), torch.zeros_like(tau))
    t_end = torch.exp(log_t_after[:, -1]) if tau.shape[1] else torch.ones_like(delta)
    t_end = torch.where(t_end < opt.stop_thresh, torch.zeros_like(t_end), t_end)
    return weights, t_end


def _render_chunk(grid: SparseGrid, origins, dirs, opt: RenderOptions, background) -> torch.Tensor:
    if grid.num_voxels == 0:  # nothing to hit: background only (there are no rows to gather from)
        behind = torch.full_like(origins, opt.background) if background is None else background
        return behind + 0.0 * (grid.density.sum() + grid.sh.sum())
    seg = ray_segments(grid, origins, dirs, opt)
    pos, valid = sample_points(seg, opt.step_size)
    rows, cw = corner_weights(grid.links, pos)  # (N, S, 8)
    present = (rows >= 0).to(grid.density.dtype)
    safe = rows.clamp(min=0)
    sigma = (cw * present * grid.density[safe]).sum(-1)  # (N, S)
    basis = eval_sh_basis(dirs, grid.basis_dim)  # (N, B); SH sees the ray's own (world/NDC) direction
    sh = (cw[..., None] * present[..., None] * grid.sh[safe]).sum(-2)  # (N, S, 3B)
    sh = sh.reshape(*sh.shape[:-1], 3, grid.basis_dim)
    color = torch.relu((sh * basis[:, None, None, :]).sum(-1) + 0.5)  # (N, S, 3)
    weights, t_end = composite_weights(sigma, valid, opt.step_size * seg.delta_scale, opt)
    if background is None:
        return (weights[..., None] * color).sum(1) + (t_end * opt.background)[:, None]
    return (weights[..., None] * color).sum(1) + t_end[:, None] * background
