"""Pure-PyTorch MSI background: the readable oracle the background kernels are tested against.

Sample k of K = `samples_per_layer` x (L - 1) lies on the sphere of inverse radius s_k = (1 - (k + 1/2) / K)
/ r0 around the box's centre, where the ray leaves that sphere (the far root; a sphere the ray's line
misses, or leaves behind the origin, gives no sample). Its layer coordinate is z_k = (1 - r0 s_k)(L - 1);
density and colour are trilinear in (z, polar row, azimuth column), the azimuth wrapping around, then
ReLU'd; samples composite front to back with optical depth sigma / `samples_per_layer` each, and what
transmittance is left sees the constant `RenderOptions.background_brightness` (docs/method.md, "Background").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.kernels.march_reference import composite_weights
from hdrplenoxels.kernels.options import RenderOptions


@dataclass
class MSISamples:
    """Every ray's K background samples: layer coordinate, unit direction from the centre, validity."""

    z: torch.Tensor  # (N, K) in [0, L - 1]
    direction: torch.Tensor  # (N, K, 3)
    valid: torch.Tensor  # (N, K) bool


def msi_samples(bg: MSIBackground, origins: torch.Tensor, dirs: torch.Tensor) -> MSISamples:
    k_count = bg.num_samples
    k = torch.arange(k_count, device=origins.device, dtype=origins.dtype)
    s = 1.0 - (k + 0.5) / float(k_count)  # inverse radius in units of 1 / r0, (K,)
    radius = bg.radius / s  # (K,)
    o = origins - torch.tensor(bg.center, dtype=origins.dtype, device=origins.device)
    b = (o * dirs).sum(-1)  # (N,)
    disc = b[:, None] ** 2 - ((o * o).sum(-1)[:, None] - radius[None, :] ** 2)  # (N, K)
    t = -b[:, None] + torch.sqrt(disc.clamp(min=0.0))
    valid = (disc >= 0.0) & (t > 0.0)
    p = o[:, None, :] + t[..., None] * dirs[:, None, :]
    p = torch.where(valid[..., None], p, torch.tensor([0.0, 0.0, 1.0], dtype=p.dtype, device=p.device))
    direction = p / p.norm(dim=-1, keepdim=True)
    z = ((k + 0.5) / float(bg.samples_per_layer)).expand(origins.shape[0], k_count)
    return MSISamples(z, direction, valid)


def msi_corners(bg: MSIBackground, z: torch.Tensor, direction: torch.Tensor):
    """The 8 (layer, row, column) corners of each sample and their trilinear weights, each (..., 8)."""
    layers, height, width = bg.layers, bg.height, bg.width
    theta = torch.acos(direction[..., 2].clamp(-1.0, 1.0))
    phi = torch.atan2(direction[..., 1], direction[..., 0])
    row = (theta * (height / math.pi) - 0.5).clamp(0.0, height - 1.0)
    col = (phi + math.pi) * (width / (2.0 * math.pi)) - 0.5
    z = z.clamp(0.0, layers - 1.0)
    l0 = torch.floor(z).clamp(max=layers - 2)
    r0 = torch.floor(row).clamp(max=height - 2)
    c0 = torch.floor(col)
    fz, fr, fc = z - l0, row - r0, col - c0
    idx_l, idx_r, idx_c, weights = [], [], [], []
    for n in range(8):
        a, b, c = n >> 2, (n >> 1) & 1, n & 1
        idx_l.append(l0.long() + a)
        idx_r.append(r0.long() + b)
        idx_c.append(torch.remainder(c0.long() + c, width))
        wz = fz if a else 1.0 - fz
        wr = fr if b else 1.0 - fr
        wc = fc if c else 1.0 - fc
        weights.append(wz * wr * wc)
    return torch.stack(idx_l, -1), torch.stack(idx_r, -1), torch.stack(idx_c, -1), torch.stack(weights, -1)


def render_background_reference(
    bg: MSIBackground,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    opt: RenderOptions = RenderOptions(),
    chunk: int = 1024,
) -> torch.Tensor:
    """Background radiance (N, 3) of world rays with unit directions; autograd-able w.r.t. the MSI.
    The oracle of kernels/background_march.py. Memory grows with rays x samples, so rays are processed
    in chunks."""
    outs = [
        _background_chunk(bg, origins[i : i + chunk], dirs[i : i + chunk], opt)
        for i in range(0, origins.shape[0], chunk)
    ]
    return torch.cat(outs) if outs else origins.new_zeros((0, 3))


def _background_chunk(bg: MSIBackground, origins, dirs, opt: RenderOptions) -> torch.Tensor:
    smp = msi_samples(bg, origins, dirs)
    li, ri, ci, w = msi_corners(bg, smp.z, smp.direction)
    sigma = (w * bg.density[li, ri, ci]).sum(-1)  # (N, K)
    color = torch.relu((w[..., None] * bg.color[li, ri, ci]).sum(-2))  # (N, K, 3)
    delta = torch.full_like(sigma, 1.0 / bg.samples_per_layer)
    weights, t_end = composite_weights(sigma, smp.valid, delta, opt)
    return (weights[..., None] * color).sum(1) + (t_end * opt.background_brightness)[:, None]
