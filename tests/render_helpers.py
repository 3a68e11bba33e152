"""Grids, rays and the backend comparison shared by the renderer tests."""

from __future__ import annotations

import torch
from devices import FAST_DEVICE

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.occupancy_kernel import occupancy_for
from hdrplenoxels.render import render_rays

TOL = 1e-5
BACKEND_DEVICES = (("torch", torch.device("cpu")), ("warp", FAST_DEVICE))  # the oracle stays on the CPU


def random_sparse_grid(reso, basis_dim, seed, empty_fraction=0.35, center=(0.1, -0.2, 0.05)):
    g = torch.Generator().manual_seed(seed)
    grid = SparseGrid.create(reso, center=center, radius=(1.0, 1.2, 0.9), basis_dim=basis_dim)
    grid.density = torch.rand(grid.num_voxels, generator=g) * 12.0 - 3.0  # some negative: ReLU'd away
    grid.sh = torch.randn(grid.num_voxels, 3 * basis_dim, generator=g) * 0.4
    return grid.prune(torch.rand(grid.num_voxels, generator=g) > empty_fraction)


def inward_rays(n, seed, center=(0.1, -0.2, 0.05)):
    g = torch.Generator().manual_seed(seed)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 3.0 + torch.tensor(center)
    d = torch.nn.functional.normalize(torch.tensor(center) - o + 0.4 * torch.randn(n, 3, generator=g), dim=-1)
    return o, d


def both_backends(grid, origins, dirs, opt, seed=7, block=None):
    """(rgb, d density, d SH) of the reference on the CPU and of the Warp path on FAST_DEVICE (with
    occupancy blocks of `block` cells, None: the default), returned on the CPU."""
    weights = torch.randn(origins.shape[0], 3, generator=torch.Generator().manual_seed(seed))
    out = {}
    for backend, device in BACKEND_DEVICES:
        density = grid.density.to(device, copy=True).requires_grad_(True)
        sh = grid.sh.to(device, copy=True).requires_grad_(True)
        g = SparseGrid(grid.links.to(device), density, sh, grid.center, grid.radius)
        if backend == "warp" and block is not None:
            occupancy_for(g, block)  # the renders of this grid use this block size
        rgb = render_rays(g, origins.to(device), dirs.to(device), opt, backend=backend)
        (rgb * weights.to(device)).sum().backward()
        out[backend] = (rgb.detach().cpu(), density.grad.cpu(), sh.grad.cpu())
    return out


def render_on(device, grid, origins, dirs, opt, backend):
    """Render on `device` (the result back on the CPU)."""
    return render_rays(grid.to(device), origins.to(device), dirs.to(device), opt, backend=backend).cpu()


def assert_parity(out):
    """Equal to TOL, relative to values above 1 (a huge background is only as exact as float32)."""
    for name, ref, fast in zip(("rgb", "d_density", "d_sh"), out["torch"], out["warp"]):
        err = ((ref - fast).abs() / ref.abs().clamp(min=1.0)).max().item()
        assert err <= TOL, f"{name}: max |warp - torch| / max(1, |torch|) = {err:.2e}"


def blob_grid(reso=(20, 18, 16), basis_dim=4, seed=0) -> SparseGrid:
    """Density only in a small off-centre ball: most blocks are empty, some rays cross the ball."""
    g = torch.Generator().manual_seed(seed)
    grid = SparseGrid.create(reso, center=(0.1, -0.2, 0.05), radius=(1.0, 1.2, 0.9), basis_dim=basis_dim)
    coords = torch.stack(torch.meshgrid(*[torch.arange(r) for r in reso], indexing="ij"), -1).reshape(-1, 3)
    ball = ((coords.float() - torch.tensor([12.0, 7.0, 9.0])) ** 2).sum(-1) < 16.0
    grid.density = torch.where(ball, 6.0 + 4.0 * torch.rand(grid.num_voxels, generator=g), -1.0)
    grid.sh = torch.randn(grid.num_voxels, 3 * basis_dim, generator=g) * 0.4
    return grid.prune(ball | (torch.rand(grid.num_voxels, generator=g) > 0.5))


def cascade_grid(reso, basis_dim, seed, levels=3, empty_fraction=0.35, center=(0.1, -0.2, 0.05)):
    """A random cascade of `levels` boxes (level 0 of half-sides (1, 1.2, 0.9)), some voxels pruned."""
    g = torch.Generator().manual_seed(seed)
    grid = SparseGrid.create(reso, center, (1.0, 1.2, 0.9), basis_dim, levels=levels)
    grid.density = torch.rand(grid.num_voxels, generator=g) * 12.0 - 3.0
    grid.sh = torch.randn(grid.num_voxels, 3 * basis_dim, generator=g) * 0.4
    return grid.prune(torch.rand(grid.num_voxels, generator=g) > empty_fraction)


def cascade_rays(n, seed, levels=3, center=(0.1, -0.2, 0.05)):
    """Rays from inside every level's box and from outside them all, in every direction (inward,
    outward, grazing), so that they cross every boundary between levels from both sides."""
    g = torch.Generator().manual_seed(seed)
    reach = 1.2 * 2.0 ** torch.arange(-1, levels + 1, dtype=torch.float32)  # in level 0, ..., outside all
    dist = reach[torch.randint(0, reach.numel(), (n,), generator=g)] * (0.5 + torch.rand(n, generator=g))
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * dist[:, None]
    o = o + torch.tensor(center)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    inward = torch.nn.functional.normalize(torch.tensor(center) - o, dim=-1)
    d[: n // 2] = torch.nn.functional.normalize(inward[: n // 2] + 0.5 * d[: n // 2], dim=-1)
    return o, d
