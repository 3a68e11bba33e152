"""What both grid engines share: the Plenoxels schedules, TV and view-prior gradients, coarse-to-fine
resampling with pruning, and svox2's RMSProp over density and SH (docs/method.md, "Training")."""

from __future__ import annotations

import numpy as np
import torch

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.geometry.sh import basis_dim_for_degree
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render import Backend, RenderOptions, render_rays
from hdrplenoxels.render.grad_buffers import GridGradients
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.engines.base import TrainingRays
from hdrplenoxels.train.optim import ExpSchedule, GridRMSProp
from hdrplenoxels.train.pruning import max_weight_score
from hdrplenoxels.train.tv import sample_tv_cells


class GridEngine:
    """A sparse voxel grid being optimised. Subclasses supply the render backend's forward and backward,
    how TV gradients are added, and how the optimiser reads the gradient buffers."""

    render_backend: Backend

    def __init__(self, field: SparseGrid, cfg: TrainConfig, render_opt: RenderOptions):
        o = cfg.optim
        self.field = field
        self.cfg = cfg
        self.render_opt = render_opt
        self.device = field.device
        self.lr_sigma = ExpSchedule(
            o.lr_sigma, o.lr_sigma_final, o.lr_decay_steps, o.lr_sigma_delay_steps, o.lr_sigma_delay_mult
        )
        self.lr_sh = ExpSchedule(o.lr_sh, o.lr_sh_final, o.lr_decay_steps)
        self.optimizer = GridRMSProp(beta=o.rms_beta)
        self._level = 0
        self._grads: GridGradients | None = None

    @staticmethod
    def new_field(
        cfg: TrainConfig, geometry: SceneGeometry, n_images: int, device: torch.device
    ) -> SparseGrid:
        """The grid a run starts from: the schedule's first resolution, uniform density, in the scene box."""
        g = cfg.grid
        basis = basis_dim_for_degree(g.sh_degree)
        return SparseGrid.create(
            g.reso_schedule[0], geometry.center, geometry.radius, basis, g.init_sigma, device
        )

    @property
    def level(self) -> int:
        return self._level

    # ----------------------------------------------------------------------------- backend hooks
    def _gradient_parts(self) -> int:
        return 1

    def _add_tv(self, args: tuple, grads: GridGradients) -> None:
        raise NotImplementedError

    def _optimise(self, grads: GridGradients, lrs: list[float]) -> None:
        raise NotImplementedError

    # ----------------------------------------------------------------------------- the interface
    def gradients(self) -> GridGradients:
        """The gradient buffers of the current grid (new ones only after a resample)."""
        if self._grads is None or not self._grads.fits(self.field):
            self._grads = None  # free the old resolution's buffers before sizing and allocating new ones
            self._grads = GridGradients(self.field, self._gradient_parts())
        return self._grads

    def regularise(self, generator: torch.Generator, view_prior: float) -> None:
        grads = self.gradients()
        o, grid = self.cfg.optim, self.field
        terms = (
            (o.lambda_tv_sigma, grid.density, grads.density[0], "zero"),
            (o.lambda_tv_sh, grid.sh, grads.sh[0], "self"),
        )
        for weight, values, grad, missing in terms:
            if weight > 0:
                cells = sample_tv_cells(grid.reso, o.tv_sparsity, generator, self.device)
                self._add_tv(
                    (grid.links, values.detach(), grad, weight, cells, missing, o.tv_reference_reso), grads
                )
        basis = grid.basis_dim
        if view_prior > 0 and basis > 1:  # gradient of view_prior * sum of squared non-DC SH coefficients
            sh = grid.sh.detach().view(-1, 3, basis)[..., 1:]
            grads.sh[0].view(-1, 3, basis)[..., 1:].add_(sh, alpha=2.0 * view_prior)
            grads.mark_all()  # a gradient on every row: the optimiser's update is dense

    def step(self, step: int) -> None:
        self._optimise(self.gradients(), [self.lr_sigma(step), self.lr_sh(step)])

    def upsample(self, step: int, rays: TrainingRays) -> str | None:
        g = self.cfg.grid
        last = self._level + 1 >= len(g.reso_schedule)
        if last or step % g.upsample_every != 0 or step >= self.cfg.optim.n_iters:
            return None  # never resample after the final step: the saved grid would be untrained
        self._level += 1
        reso = g.reso_schedule[self._level]
        # Both are discarded at a resample; freeing them first leaves the memory to the resample.
        self.optimizer.reset()
        self._grads = None
        score, thresh = None, g.density_thresh
        if g.prune == "weight":
            score = max_weight_score(self.field, reso, rays(g.weight_ray_stride), self.render_opt)
            thresh = g.weight_thresh / reso[2]
        self.field = self.field.resample(reso, score, thresh, dilate=g.dilate, max_voxels=g.max_voxels)
        if self.field.num_voxels == 0:
            raise RuntimeError(
                f"step {step}: no voxel passed the {g.prune} pruning threshold ({thresh:g}) when "
                f"resampling to {reso}; the scene has not formed yet — lower the threshold or upsample later"
            )
        return f"step {step}: resampled to {self.field.reso}, {self.field.num_voxels} voxels kept"

    @torch.no_grad()
    def render(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        return render_rays(self.field, origins, dirs, self.render_opt, self.render_backend)

    def log_fields(self, step: int) -> dict[str, float | int]:
        return {"lr_sigma": self.lr_sigma(step), "lr_sh": self.lr_sh(step), "voxels": self.field.num_voxels}

    def state_arrays(self) -> dict[str, np.ndarray]:
        return self.optimizer.checkpoint_arrays()

    def restore(self, field: SparseGrid, level: int, arrays: dict[str, np.ndarray]) -> None:
        self.field = field
        self._level = level
        self._grads = None
        self.optimizer.load_checkpoint_arrays(arrays, self.device, [field.density, field.sh])
