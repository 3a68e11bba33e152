"""Pure-PyTorch volume renderer: the readable oracle of the march's kernels (`kernels/march_funcs.py`, the
thread and lane kernels), `render_reference` to their `render_rays`.

It samples every ray at the same points as the Warp kernel, interpolates density and SH trilinearly
(empty corners count as 0), composites front to back with the early stop, and relies on autograd for
gradients. Memory grows with rays x samples, so rays are processed in chunks.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hdrplenoxels.geometry.sh import eval_sh_basis
from hdrplenoxels.grid.sparse_grid import SparseGrid, corner_weights
from hdrplenoxels.kernels.options import FAR_FACE_SLACK, TINY_DIR, RenderOptions, near_distance


@dataclass
class RaySegments:
    """Rays in level-0 grid units and the segments of each ray that each level of the grid renders.

    Slot `j` of the `2 L - 1` (L = levels) is rendered by level `|j - (L - 1)|`, in order along the ray:
    the outer levels' entry segments, outermost first, then level 0's box, then the exit segments,
    innermost first (docs/method.md, "Cascade"). A slot's samples sit at `t0 + k * step * 2^level`,
    k < its count; empty slots have count 0."""

    origin: torch.Tensor  # (N, 3) level-0 grid coordinates
    direction: torch.Tensor  # (N, 3) unit, grid space
    delta_scale: torch.Tensor  # (N,) world (or NDC) length of one level-0 grid unit along the ray
    t0: torch.Tensor  # (N, 2L - 1) first sample of each slot, level-0 grid units
    count: torch.Tensor  # (N, 2L - 1) long, samples in each slot
    levels: int
    reso: tuple[int, int, int]

    @property
    def num_samples(self) -> torch.Tensor:
        """(N,) long; 0 for rays that miss the grid."""
        return self.count.sum(-1)

    @property
    def slot_level(self) -> torch.Tensor:
        """(2L - 1,) long: the level rendering each slot."""
        return (torch.arange(2 * self.levels - 1, device=self.count.device) - (self.levels - 1)).abs()


def box_interval(
    o: torch.Tensor, d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, t_far: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where rays (N, 3) cross the box [lo, hi] (3,), clamped to [0, t_far]: (t_in, t_out), each (N,);
    t_in > t_out for a miss."""
    d_safe = torch.where(d == 0, torch.full_like(d, TINY_DIR), d)
    t1 = (lo - o) / d_safe
    t2 = (hi - o) / d_safe
    return torch.minimum(t1, t2).amax(-1).clamp(min=0.0), torch.maximum(t1, t2).amin(-1).clamp(max=t_far)


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
    mid, half = (reso - 1.0) / 2.0, reso / 2.0
    levels = grid.levels
    t_in, t_out = [], []
    for level in range(levels):  # box l is [mid - 2^l R / 2, mid + 2^l R / 2] in level-0 units
        f = 2.0**level
        a, b = box_interval(o, d, mid - f * half, mid + f * half, opt.t_max * f)
        t_in.append(a)
        t_out.append(b)
    zero = torch.zeros_like(t_in[0], dtype=torch.long)
    t0, count = [], []
    for j in range(2 * levels - 1):
        level = abs(j - (levels - 1))
        step = opt.step_size * 2.0**level
        a, b = t_in[level], t_out[level]
        hit = a <= b
        inner_hit = t_in[level - 1] <= t_out[level - 1] if level > 0 else torch.zeros_like(hit)
        whole = torch.floor((b - a) / step + FAR_FACE_SLACK).long() + 1
        if j < levels - 1 or level == 0:  # an entry slot (or level 0): [a, inner's a), or all of [a, b]
            part = (
                torch.ceil((t_in[level - 1] - a) / step - FAR_FACE_SLACK).long().clamp(min=0)
                if level
                else zero
            )
            n = torch.where(inner_hit, part, torch.where(hit, whole, zero))
            start = a
        else:  # an exit slot: (inner's b, b], its samples counted back from b
            n = torch.where(
                inner_hit & hit, torch.ceil((b - t_out[level - 1]) / step - FAR_FACE_SLACK).long(), zero
            )
            n = n.clamp(min=0)
            start = b - (n - 1).clamp(min=0).to(b.dtype) * step
        t0.append(start)
        count.append(n)
    return RaySegments(o, d, delta_scale, torch.stack(t0, -1), torch.stack(count, -1), levels, grid.reso)


def render_reference(
    grid: SparseGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions = RenderOptions(),
    chunk: int = 1024,
    behind: torch.Tensor | None = None,
    distortion: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Linear radiance (N, 3) of rays `origins`, `dirs` (world or NDC units, unit dirs); autograd-able.
    The oracle of kernels/march_forward.py, kernels/march_threads.py and kernels/march_lanes.py.

    `behind`: per-ray radiance (N, 3) seen with the transmittance left after the march (the background
    model's, docs/method.md, "Background"); None: the constant `opt.background_brightness`. `distortion`:
    also return each ray's `distortion_loss` (N,)."""
    outs = [
        _render_chunk(
            grid,
            origins[i : i + chunk],
            dirs[i : i + chunk],
            opt,
            None if behind is None else behind[i : i + chunk],
            distortion,
        )
        for i in range(0, origins.shape[0], chunk)
    ]
    rgb = torch.cat([o[0] for o in outs]) if outs else origins.new_zeros((0, 3))
    if not distortion:
        return rgb
    return rgb, torch.cat([o[1] for o in outs]) if outs else origins.new_zeros(0)


def distortion_loss(weights: torch.Tensor, behind: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
    """Per ray (N,): mip-NeRF 360's distortion loss of the sample weights (N, S) along the ray's normalised
    coordinate s = i / n, sample i of the ray's n = `end` (N,) samples: a step of any level is one unit of
    the index, and the whole march spans [0, 1] as mip-NeRF 360's normalised distance does. What lies behind
    the grid (the MSI or the constant background) is one more sample, of weight `behind` (N,) (the
    transmittance left), at s = 1:

        sum_i sum_j w_i w_j |s_i - s_j| + sum_i w_i^2 / (3 n)

    It is smallest when the weight gathers at one place along the ray: it pulls floaters in front of the
    cameras into the surfaces behind them, or into the background (docs/method.md, "Distortion"). The
    double sum is taken as 2 sum_i w_i (i W_i - S_i) / n, W_i and S_i the sums of w_j and w_j j over j < i."""
    s = torch.arange(weights.shape[1], dtype=weights.dtype, device=weights.device)[None]
    w_before = torch.cumsum(weights, 1) - weights
    ws_before = torch.cumsum(weights * s, 1) - weights * s
    grid = 2.0 * (weights * (s * w_before - ws_before)).sum(1) + weights.square().sum(1) / 3.0
    end = end.to(weights.dtype)
    last = 2.0 * behind * (end * weights.sum(1) - (weights * s).sum(1)) + behind.square() / 3.0
    return (grid + last) / end.clamp(min=1.0)


def sample_distances(
    seg: RaySegments, step_size: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every sample's distance from the ray's origin in level-0 grid units (N, S), its level, its step and
    a validity mask (N, S)."""
    num = seg.num_samples
    s_max = int(num.max()) if num.numel() else 0
    k = torch.arange(s_max, device=seg.origin.device)
    valid = k[None, :] < num[:, None]
    ends = torch.cumsum(seg.count, -1)  # (N, slots): one past each slot's last sample
    slot = torch.searchsorted(ends, k[None, :].expand(num.shape[0], -1).contiguous(), right=True)
    slot = slot.clamp(max=seg.count.shape[1] - 1)
    first = (ends - seg.count).gather(1, slot)
    level = seg.slot_level[slot]
    step = step_size * torch.pow(2.0, level.to(seg.t0.dtype))
    t = seg.t0.gather(1, slot) + (k[None, :] - first).to(seg.t0.dtype) * step
    return t, level, step, valid


def near_gradient_scale(x: torch.Tensor, t: torch.Tensor, near: float) -> torch.Tensor:
    """`x` (N, S, ...) unchanged, its gradient scaled by min(1, (t / near)^2) per sample (kernels:
    `march_funcs.near_factor`; `RenderOptions.near_grad`)."""
    if near <= 0.0:
        return x
    scale = (t / near).square().clamp(max=1.0).reshape(*t.shape, *([1] * (x.dim() - t.dim())))
    return x * scale + (x * (1.0 - scale)).detach()


def sample_points(
    seg: RaySegments, step_size: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every sample's grid position in its own level (N, S, 3), that level (N, S), its step in level-0
    grid units (N, S), and a validity mask (N, S); S = max samples."""
    t, level, step, valid = sample_distances(seg, step_size)
    pos, level = sample_positions(seg, t, level, valid)
    return pos, level, step, valid


def sample_positions(
    seg: RaySegments, t: torch.Tensor, level: torch.Tensor, valid: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The grid positions (N, S, 3) of the samples at distances `t` (`sample_distances`), each in its own
    level's coordinates, and their levels; padding samples parked at level 0's origin."""
    pos = seg.origin[:, None, :] + t[..., None] * seg.direction[:, None, :]
    if seg.levels > 1:  # level l's coordinates: 2^-l times level 0's about the centre
        mid = (torch.tensor(seg.reso, dtype=pos.dtype, device=pos.device) - 1.0) / 2.0
        scaled = (pos - mid) * torch.pow(0.5, level.to(pos.dtype))[..., None] + mid
        pos = torch.where((level > 0)[..., None], scaled, pos)
    # Padding samples of shorter rays (and rays that miss, possibly with non-finite geometry) are parked
    # at the grid origin so that indexing stays valid; `valid` excludes them from compositing.
    pos = torch.where(valid[..., None], pos, torch.zeros_like(pos))
    level = torch.where(valid, level, torch.zeros_like(level))
    return pos, level


def optical_lengths(seg: RaySegments, valid: torch.Tensor, opt: RenderOptions) -> torch.Tensor:
    """Every sample's optical length (N, S): a level-0 step's world length, whatever its level. A level's
    density is per voxel of that level (2^l times the world density), so that initialisation, learning
    rates, TV and pruning thresholds mean the same opacity per voxel at every level (docs/method.md,
    "Cascade")."""
    return (opt.step_size * seg.delta_scale)[:, None].expand_as(valid).to(seg.delta_scale.dtype)


def composite_weights(
    sigma: torch.Tensor, valid: torch.Tensor, delta: torch.Tensor, opt: RenderOptions
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample weights w_k = T_k alpha_k (N, S) and the transmittance left for the background (N,),
    each sample k with its own length `delta` (N, S).

    A sample counts iff it is valid, its density exceeds `sigma_thresh` and the transmittance before it
    is still >= `stop_thresh` (the kernel stops right after the sample that drops T below it, and then
    adds no background).
    """
    used = valid & (sigma > opt.sigma_thresh)
    tau = torch.where(used, sigma, torch.zeros_like(sigma)) * delta
    log_t_after = -torch.cumsum(tau, dim=1)
    log_t_before = torch.cat([torch.zeros_like(log_t_after[:, :1]), log_t_after[:, :-1]], dim=1)
    t_before = torch.exp(log_t_before)
    active = used & (t_before >= opt.stop_thresh)
    weights = torch.where(active, t_before * (1.0 - torch.exp(-tau)), torch.zeros_like(tau))
    t_end = torch.exp(log_t_after[:, -1]) if tau.shape[1] else tau.new_ones(tau.shape[0])
    t_end = torch.where(t_end < opt.stop_thresh, torch.zeros_like(t_end), t_end)
    return weights, t_end


def _render_chunk(
    grid: SparseGrid, origins, dirs, opt: RenderOptions, behind, distortion: bool = False
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(radiance (N, 3), distortion loss (N,) or None) of a chunk of rays."""
    if grid.num_voxels == 0:  # nothing to hit: background only (there are no rows to gather from)
        seen = torch.full_like(origins, opt.background_brightness) if behind is None else behind
        zero = 0.0 * (grid.density.sum() + grid.sh.sum())
        return seen + zero, origins.new_zeros(origins.shape[0]) + zero
    seg = ray_segments(grid, origins, dirs, opt)
    t, level, _, valid = sample_distances(seg, opt.step_size)
    pos, level = sample_positions(seg, t, level, valid)
    near = near_distance(opt, tuple(grid.reso))
    rows, cw = corner_weights(grid.links, pos, level)  # (N, S, 8)
    present = (rows >= 0).to(grid.density.dtype)
    safe = rows.clamp(min=0)
    sigma = near_gradient_scale((cw * present * grid.density[safe]).sum(-1), t, near)  # (N, S)
    basis = eval_sh_basis(dirs, grid.basis_dim)  # (N, B); SH sees the ray's own (world/NDC) direction
    sh = (cw[..., None] * present[..., None] * grid.sh[safe]).sum(-2)  # (N, S, 3B)
    sh = near_gradient_scale(sh, t, near)
    sh = sh.reshape(*sh.shape[:-1], 3, grid.basis_dim)
    color = torch.relu((sh * basis[:, None, None, :]).sum(-1) + 0.5)  # (N, S, 3)
    weights, t_end = composite_weights(sigma, valid, optical_lengths(seg, valid, opt), opt)
    seen = (t_end * opt.background_brightness)[:, None] if behind is None else t_end[:, None] * behind
    loss = distortion_loss(weights, t_end, seg.num_samples) if distortion else None
    return (weights[..., None] * color).sum(1) + seen, loss


@torch.no_grad()
def read_rows_reference(
    grid: SparseGrid, origins: torch.Tensor, dirs: torch.Tensor, opt: RenderOptions
) -> tuple[torch.Tensor, torch.Tensor]:
    """The rows a forward of these rays reads the SH of with a weight (of the samples it composites,
    up to and with the one that ends the ray), and the rows of every corner of every sample of the rays:
    two bool masks over the rows, the bounds of `kernels/march_read_rows.py`'s marks."""
    needed = torch.zeros(grid.num_voxels, dtype=torch.bool, device=grid.density.device)
    possible = needed.clone()
    if grid.num_voxels == 0 or origins.shape[0] == 0:
        return needed, possible
    seg = ray_segments(grid, origins, dirs, opt)
    t, level, _, valid = sample_distances(seg, opt.step_size)
    pos, level = sample_positions(seg, t, level, valid)
    rows, cw = corner_weights(grid.links, pos, level)  # (N, S, 8)
    present = rows >= 0
    sigma = (cw * present * grid.density[rows.clamp(min=0)]).sum(-1)
    weights, _ = composite_weights(sigma, valid, optical_lengths(seg, valid, opt), opt)
    composited = valid & (sigma > opt.sigma_thresh) & (weights > 0)
    needed[rows[composited[..., None] & present]] = True
    possible[rows[valid[..., None] & present]] = True
    return needed, possible
