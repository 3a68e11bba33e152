"""Grids, rays and the backend comparison shared by the renderer tests."""

from __future__ import annotations

import torch

from hdrplenoxels.grid import SparseGrid
from hdrplenoxels.render import render_rays

TOL = 1e-5


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


def both_backends(grid, origins, dirs, opt, seed=7):
    weights = torch.randn(origins.shape[0], 3, generator=torch.Generator().manual_seed(seed))
    out = {}
    for backend in ("torch", "warp"):
        density = grid.density.clone().requires_grad_(True)
        sh = grid.sh.clone().requires_grad_(True)
        g = SparseGrid(grid.links, density, sh, grid.center, grid.radius)
        rgb = render_rays(g, origins, dirs, opt, backend=backend)
        (rgb * weights).sum().backward()
        out[backend] = (rgb.detach(), density.grad, sh.grad)
    return out


def assert_parity(out):
    for name, ref, fast in zip(("rgb", "d_density", "d_sh"), out["torch"], out["warp"]):
        err = (ref - fast).abs().max().item()
        assert err <= TOL, f"{name}: max |warp - torch| = {err:.2e}"
