"""What both grid engines share: the Plenoxels schedules, TV, view-prior and free-space gradients,
coarse-to-fine resampling with pruning, and svox2's RMSProp over density and SH (docs/method.md,
"Training"); and the optional MSI background behind the box, with its own RMSProp, schedules, TV and sparsity
(docs/method.md, "Background")."""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import torch

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.geometry.sh import basis_dim_for_degree
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.background_kernel import MSIGradients
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.resample_kernel import resample
from hdrplenoxels.kernels.tv import TVTerm, sample_tv_cells
from hdrplenoxels.render import Backend, RenderOptions, render_rays
from hdrplenoxels.train.background_tv import BackgroundTraining, msi_sparsity, msi_tv_grad_
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.engines.base import TrainingRays
from hdrplenoxels.train.free_space import SightSegments
from hdrplenoxels.train.optim import ExpSchedule, StepClock, StepRates, Svox2RMSProp
from hdrplenoxels.train.priors import Prior, free_space, grid_priors, surface
from hdrplenoxels.train.pruning import max_weight_score
from hdrplenoxels.train.view_coverage import PooledFrustums, prune_unseen, seen_enough

BG_STATE = "bg/"  # prefix of the MSI optimiser's arrays in `state_arrays()`


@functools.cache
def view_prior_pull(basis: int, weight: float, device: torch.device) -> torch.Tensor | None:
    """The view prior `weight * sum of squared non-DC SH coefficients` as the optimiser's pull on the SH
    columns (`Svox2RMSProp.step`): 2 * weight on each colour's non-DC coefficients, 0 on its DC; None
    when off. The optimiser adds it within its pass over the grid: no pass of its own writes it into the
    gradient buffers."""
    if weight <= 0 or basis <= 1:
        return None
    pull = torch.full((3, basis), 2.0 * weight, device=device)
    pull[:, 0] = 0.0
    return pull.reshape(-1)


class GridEngine:
    """A sparse voxel grid being optimised. Subclasses supply the render backend's forward and backward,
    how TV gradients are added, and how the optimiser reads the gradient buffers."""

    render_backend: Backend
    fused_optimiser: bool
    """The optimiser runs the fused Warp update (`kernels/rmsprop_kernel.py`), else its PyTorch reference."""

    def __init__(
        self,
        field: SparseGrid,
        cfg: TrainConfig,
        render_opt: RenderOptions,
        background: MSIBackground | None = None,
    ):
        require_resolved(cfg)
        o, b = cfg.optim, cfg.background
        self.field = field
        self.background = background
        self.cfg = cfg
        self.render_opt = replace(render_opt, near_grad=cfg.optim.near_grad)  # what trains, not what is saved
        self.device = field.device
        self.lr_sigma = ExpSchedule(
            o.lr_sigma, o.lr_sigma_final, o.lr_decay_steps, o.lr_sigma_delay_steps, o.lr_sigma_delay_mult
        )
        self.lr_sh = ExpSchedule(o.lr_sh, o.lr_sh_final, o.lr_decay_steps)
        self.optimiser = Svox2RMSProp(beta=o.rms_beta)
        self.lr_bg_sigma = ExpSchedule(b.lr_sigma, b.lr_sigma_final, b.lr_decay_steps)
        self.lr_bg_color = ExpSchedule(b.lr_color, b.lr_color_final, b.lr_decay_steps)
        self.bg_optimiser = Svox2RMSProp(beta=o.rms_beta)  # svox2 optimises its background with RMSProp too
        # The four rates on the device, read there at the step's count at every step.
        schedules = [self.lr_sigma, self.lr_sh, self.lr_bg_sigma, self.lr_bg_color]
        self.rates = StepRates(schedules, self.device, o.n_iters)
        self.bg_weights = BackgroundTraining(
            b.lr_sigma, b.lr_color, b.lambda_tv_sigma, b.lambda_tv_color, b.lambda_sparsity, b.tv_sparsity
        )
        self._level = 0
        self._grads: GridGradients | None = None
        self._bg_grads: MSIGradients | None = None
        # Each step's priors, in the order they add (`train/priors.py`); the sight priors join when set.
        self.priors: list[Prior] = grid_priors(cfg.optim, self._add_tv)
        self._views: tuple[PooledFrustums, int] | None = None  # `restrict_to_views`' frustums and minimum

    @staticmethod
    def new_field(
        cfg: TrainConfig, geometry: SceneGeometry, n_images: int, device: torch.device
    ) -> SparseGrid:
        """The grid a run starts from: the schedule's first resolution, uniform density, in the scene box
        (or the scene's cascade of boxes)."""
        g = cfg.grid
        basis = basis_dim_for_degree(g.sh_degree)
        return SparseGrid.create(
            g.reso_schedule[0], geometry.center, geometry.radius, basis, g.init_sigma, device, geometry.levels
        )

    @staticmethod
    def new_background(cfg: TrainConfig, geometry: SceneGeometry, field: SparseGrid) -> MSIBackground | None:
        """The MSI a run starts from, around `field`'s (outermost) box, when `background.enabled`; else
        None."""
        if not require_resolved(cfg).background.enabled:
            return None
        b = cfg.background
        return MSIBackground.create(
            field, b.layers, b.height, b.width, b.init_sigma, b.init_color, b.samples_per_layer
        )

    @property
    def level(self) -> int:
        return self._level

    @property
    def distortion_weight(self) -> float:
        """The distortion loss's weight (`optim.lambda_distortion`, resolved: `TrainConfig.resolved`)."""
        return self.cfg.optim.lambda_distortion

    # ----------------------------------------------------------------------------- backend hooks
    def _gradient_parts(self) -> int:
        return 1

    def _background_parts(self) -> int:
        return 1

    def _add_tv(self, term: TVTerm, grad_parts: torch.Tensor, grads: GridGradients) -> None:
        """Add `term`'s gradient into `grad_parts` ((P, *values.shape), the density's or the SH's)."""
        raise NotImplementedError

    def _update_scope(self, grads: GridGradients) -> dict:
        """What the grid's update may visit and refresh besides the parameters (`step_accumulated`'s
        `occupancy`, `touched` and `owe_pull`); the dense reference update needs none."""
        return {}

    def settle(self) -> None:
        """Pay what the grid's voxels owe of the view prior's pull (`Svox2RMSProp.owing_pull`), so that
        `field` is what the dense update would have left: before anything outside a step reads it."""
        self.optimiser.settle()

    def graph_key(self) -> tuple:
        """The level, and whether voxels may owe the view prior's pull: a step that owes it pays the
        rows it reads first, work a step recorded before it owed does not hold."""
        return (self._level, self.optimiser.owing_pull)

    def _optimise(self, grads: GridGradients, lrs: torch.Tensor, pulls: list[torch.Tensor | None]) -> None:
        self.optimiser.step_accumulated(
            [self.field.density, self.field.sh],
            [grads.density, grads.sh],
            lrs,
            fused=self.fused_optimiser,
            pulls=pulls,
            **self._update_scope(grads),
        )

    # ----------------------------------------------------------------------------- the interface
    def gradients(self) -> GridGradients:
        """The gradient buffers of the current grid (new ones only after a resample)."""
        if self._grads is None or not self._grads.fits(self.field):
            self._grads = None  # free the old resolution's buffers before sizing and allocating new ones
            self._grads = GridGradients(self.field, self._gradient_parts())
        return self._grads

    def background_gradients(self) -> MSIGradients:
        """The MSI's gradient buffers (the MSI keeps its size, so they are made once)."""
        if self._bg_grads is None:
            self._bg_grads = MSIGradients(self.background, self._background_parts())
        return self._bg_grads

    def _regularise_background(self, generator: torch.Generator) -> None:
        """The MSI's TV (over every texel, or with `tv_sparsity` < 1 a sampled run of texels; in closed
        form) and sparsity (an autograd loss on its small arrays) into its gradient buffers."""
        bg, w = self.background, self.bg_weights
        grads = self.background_gradients()
        if w.lambda_tv_sigma > 0 or w.lambda_tv_color > 0:
            texels = None
            if w.tv_sparsity < 1.0:
                texels = sample_tv_cells(tuple(bg.density.shape), w.tv_sparsity, generator, self.device)
            msi_tv_grad_(bg.density[..., None], grads.density[0][..., None], w.lambda_tv_sigma, texels)
            msi_tv_grad_(bg.color, grads.color[0], w.lambda_tv_color, texels)
        if w.lambda_sparsity > 0:
            density = bg.density.detach().requires_grad_(True)
            leaves = MSIBackground(density, bg.color, bg.center, bg.radius, bg.samples_per_layer)
            (d_density,) = torch.autograd.grad(msi_sparsity(leaves, w), [density])
            grads.density[0].add_(d_density)

    def use_free_space(self, segments: SightSegments) -> None:
        if self.cfg.optim.lambda_free_space > 0:
            self.priors.append(free_space(segments, self.cfg.optim))

    def use_surface(self, windows: SightSegments) -> None:
        if self.cfg.optim.lambda_surface > 0:
            self.priors.append(surface(windows, self.cfg.optim))

    def restrict_to_views(self, frustums: PooledFrustums, min_views: int) -> None:
        self.settle()
        self.field = prune_unseen(self.field, frustums, min_views)
        self._views = (frustums, min_views)

    def regularise(self, generator: torch.Generator) -> None:
        grads = self.gradients()
        for prior in self.priors:
            prior.add_gradient(self.field, grads, generator)
        if self.background is not None:
            self._regularise_background(generator)

    def step(self, clock: StepClock, view_prior: float = 0.0) -> None:
        """The optimiser's step at the rates of `clock.count` (computed on the device: a replayed step
        reads nothing from the host); the view prior acts as its pull on the SH (`view_prior_pull`),
        which makes the update dense, or owed (`TrainConfig.view_prior_update`, the Warp grid)."""
        rates = self.rates(clock.count)
        pulls = [None, view_prior_pull(self.field.basis_dim, view_prior, self.device)]
        self._optimise(self.gradients(), rates[0:2], pulls)
        if self.background is not None:
            bg, grads = self.background, self.background_gradients()
            self.bg_optimiser.step_accumulated(
                [bg.density, bg.color], [grads.density, grads.color], rates[2:4], fused=self.fused_optimiser
            )

    def after_step(self, step: int) -> None:
        """Nothing to keep up between steps (the Warp engine's occupancy is)."""

    def upsample(self, step: int, rays: TrainingRays) -> str | None:
        g = self.cfg.grid
        last = self._level + 1 >= len(g.reso_schedule)
        if last or step % g.upsample_every != 0 or step >= self.cfg.optim.n_iters:
            return None  # never resample after the final step: the saved grid would be untrained
        self._level += 1
        reso = g.reso_schedule[self._level]
        # Both are discarded at a resample; freeing them first leaves the memory to the resample.
        self.settle()  # the resample reads every voxel
        self.optimiser.reset()
        self._grads = None
        score, thresh = None, g.density_thresh
        if g.prune == "weight":
            score = max_weight_score(self.field, reso, rays(g.weight_ray_stride), self.render_opt)
            thresh = g.weight_thresh / reso[2]
        allowed = (
            None if self._views is None else functools.partial(seen_enough, *self._views, reso, self.field)
        )
        self.field = resample(
            self.field, reso, score, thresh, dilate=g.dilate, max_voxels=g.max_voxels, allowed=allowed
        )
        if self.field.num_voxels == 0:
            raise RuntimeError(
                f"step {step}: no voxel passed the {g.prune} pruning threshold ({thresh:g}) when "
                f"resampling to {reso}; the scene has not formed yet — lower the threshold or upsample later"
            )
        return f"step {step}: resampled to {self.field.reso}, {self.field.num_voxels} voxels kept"

    @torch.no_grad()
    def render(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        self.settle()
        return render_rays(
            self.field, origins, dirs, self.render_opt, self.render_backend, background=self.background
        )

    def log_fields(self, step: int) -> dict[str, float | int]:
        out = {"lr_sigma": self.lr_sigma(step), "lr_sh": self.lr_sh(step), "voxels": self.field.num_voxels}
        if self.background is not None:
            out.update(lr_bg_sigma=self.lr_bg_sigma(step), lr_bg_color=self.lr_bg_color(step))
        return out

    def state_arrays(self) -> dict[str, np.ndarray]:
        arrays = self.optimiser.checkpoint_arrays()  # settles the grid (`settle`) first
        arrays.update({BG_STATE + k: v for k, v in self.bg_optimiser.checkpoint_arrays().items()})
        return arrays

    def restore(
        self,
        field: SparseGrid,
        level: int,
        arrays: dict[str, np.ndarray],
        background: MSIBackground | None = None,
    ) -> None:
        if (background is None) != (self.background is None):
            raise ValueError(
                "the checkpoint "
                + (
                    "has no background model, but this run trains one"
                    if background is None
                    else "has a background model, but this run trains none"
                )
            )
        self.field = field
        self.background = background
        self._level = level
        self._grads = None
        self._bg_grads = None
        grid_state = {k: v for k, v in arrays.items() if not k.startswith(BG_STATE)}
        self.optimiser.load_checkpoint_arrays(grid_state, self.device, [field.density, field.sh])
        bg_state = {k.removeprefix(BG_STATE): v for k, v in arrays.items() if k.startswith(BG_STATE)}
        self.bg_optimiser.load_checkpoint_arrays(bg_state, self.device)


def require_resolved(cfg: TrainConfig) -> TrainConfig:
    """`cfg`, once `TrainConfig.resolved` has filled its None defaults (a ValueError naming them if not)."""
    left = cfg.unresolved()
    if left:
        raise ValueError(f"a grid engine needs TrainConfig.resolved first; still None: {', '.join(left)}")
    return cfg
