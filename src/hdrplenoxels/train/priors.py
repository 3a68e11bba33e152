"""The grid's priors, each a small object the grid engine registers and asks, once a step after the
backward, to add its gradient (`GridEngine.regularise`, in the order registered: their random draws come
from the step's generator in that order, so a resumed run repeats them). The engine registers the
sparsity and TV priors itself; the sight priors come when `train/sight_setup.py` hands it their
segments. What the voxel grid prunes by (the views per voxel, the weights) acts at a resample instead."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.tv import MissingMode, TVTerm, sample_tv_cells
from hdrplenoxels.train.config import OptimConfig
from hdrplenoxels.train.free_space import SightSegments, free_space_grad_
from hdrplenoxels.train.sparsity import cauchy_sparsity_grad_
from hdrplenoxels.train.surface import surface_grad_


class Prior(Protocol):
    def add_gradient(self, grid: SparseGrid, grads: GridGradients, generator: torch.Generator) -> None:
        """Add this prior's gradient for `grid` into `grads`."""
        ...


@dataclass
class Sparsity:
    """The Cauchy sparsity of the densities the step's rays read (`train/sparsity.py`); first, while
    only the rays' rows are marked."""

    o: OptimConfig

    def add_gradient(self, grid: SparseGrid, grads: GridGradients, generator: torch.Generator) -> None:
        cauchy_sparsity_grad_(grid.density, grads.density, self.o.lambda_sparsity)


@dataclass
class TotalVariation:
    """TV over a random 1 % run of the dense cells (`kernels/tv.py`) of the density ("density",
    missing neighbours read as 0) or the SH ("sh", missing neighbours as the cell's own value), at its
    weight in `o` as it stands (0: nothing, no draw); `add` is the engine's kernel or reference
    (`GridEngine._add_tv`)."""

    values: str
    o: OptimConfig
    add: Callable[[TVTerm, torch.Tensor, GridGradients], None]

    def add_gradient(self, grid: SparseGrid, grads: GridGradients, generator: torch.Generator) -> None:
        o, density = self.o, self.values == "density"
        weight = o.lambda_tv_sigma if density else o.lambda_tv_sh
        if weight <= 0:
            return
        values, parts = (grid.density, grads.density) if density else (grid.sh, grads.sh)
        missing: MissingMode = "zero" if density else "self"
        cells = sample_tv_cells(tuple(grid.links.shape), o.tv_sparsity, generator, grid.device)
        term = TVTerm(grid.links, values.detach(), weight, cells, missing, o.tv_reference_reso)
        self.add(term, parts, grads)


@dataclass
class SightPrior:
    """A prior along the cameras' lines of sight to the sparse points: density pulled down before the
    points (`free_space`, `train/free_space.py`) or rays stopped at them (`surface`, `train/surface.py`).
    `add(grid, generator, density_grad, touched)` adds its gradient into part 0 of the density's."""

    add: Callable[[SparseGrid, torch.Generator, torch.Tensor, torch.Tensor], None]

    def add_gradient(self, grid: SparseGrid, grads: GridGradients, generator: torch.Generator) -> None:
        self.add(grid, generator, grads.density[0], grads.touched)


def free_space(segments: SightSegments, o: OptimConfig) -> SightPrior:
    lines, samples = o.free_space_lines, o.free_space_samples
    return SightPrior(lambda grid, gen, grad, touched: free_space_grad_(
        grid, segments, o.lambda_free_space, lines, samples, gen, grad, touched, o.free_space_spread
    ))  # fmt: skip


def surface(windows: SightSegments, o: OptimConfig) -> SightPrior:
    lines, samples = o.free_space_lines, o.free_space_samples
    return SightPrior(lambda grid, gen, grad, touched: surface_grad_(
        grid, windows, o.lambda_surface, o.surface_target, lines, samples, gen, grad, touched
    ))  # fmt: skip


def grid_priors(o: OptimConfig, add_tv: Callable[[TVTerm, torch.Tensor, GridGradients], None]) -> list[Prior]:
    """The priors every grid run has, in their order: sparsity, then the density's and the SH's TV, each
    reading its weight from `o` when it acts."""
    return [Sparsity(o), TotalVariation("density", o, add_tv), TotalVariation("sh", o, add_tv)]
