"""The engine interface: a radiance field being optimised, as the trainer sees it (docs/design.md).

One training step, in the trainer's order:
`forward(batch)` -> linear radiance as a leaf tensor that requires grad (and the batch in the order the
engine marched it) -> the trainer's loss, through the tone-mapping module -> `backward(d loss / d rgb)`
-> `regularise(generator)` (`GridHooks`) -> `step(clock, view_prior)`, then, between steps,
`after_step(step)` and `upsample` (`GridHooks`). `Engine` is what every engine does; `GridHooks` what
only the voxel grid's do (priors, resampling, owed updates), which the trainer calls where an engine has
them.
Everything renderer-specific (gradient buffers, sample records, ray order, occupancy, fused optimisers)
stays inside the engine; the tone-mapping module only ever sees the radiance tensor. On CUDA the
trainer may replay everything from `forward` to `step` from a CUDA graph (`train/step_graph.py`), so
an engine that runs there reads the step from `clock.count`, on the device, never from the host.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.train.optim import StepClock
from hdrplenoxels.train.ray_pool import RayBatch

# `rays(stride)`: every `stride`-th pixel of the training pool as (origins, dirs) chunks (for pruning).
TrainingRays = Callable[[int], Iterator[tuple[torch.Tensor, torch.Tensor]]]


class Engine(Protocol):
    """A radiance field being optimised. `field` and `background` are the render-only state that models
    are saved with (render/fields.py saves, loads and renders every kind). The class also provides
    `new_field(cfg, geometry, n_images, device)`, the field a run starts from, and
    `new_background(cfg, geometry, field)`, the background model behind it (None: the constant), and
    is constructed as `cls(field, cfg, render_opt, background)`."""

    field: object
    background: MSIBackground | None  # the MSI composited behind the field (docs/method.md, "Background")
    device: torch.device

    def forward(self, batch: RayBatch) -> tuple[torch.Tensor, RayBatch]:
        """(N, 3) linear radiance of the batch's rays, a leaf that requires grad, and the batch in the
        order of those rows (an engine may reorder rays; targets and image ids move with them)."""
        ...

    def backward(self, grad_rgb: torch.Tensor) -> None:
        """Accumulate the field's gradient from d loss / d radiance of the last `forward`."""
        ...

    def step(self, clock: StepClock, view_prior: float = 0.0) -> None:
        """One optimiser step at the learning rates of the clock's step, with the view prior of weight
        `view_prior` (an argument, not state: each step says its own); the gradients are then cleared."""
        ...

    def graph_key(self) -> tuple:
        """What of the engine's state a recorded step holds besides its tensors' addresses (the level,
        and work a step does only in some states), for the CUDA graph's key (`train/step_graph.py`)."""
        ...

    def render(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """(N, 3) linear radiance, no gradients (render-only use)."""
        ...

    def log_fields(self, step: int) -> dict[str, float | int]:
        """Values for the training log at `step` (learning rates, size of the field)."""
        ...

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The optimiser state (and whatever else resuming needs beyond `field`), for checkpoints."""
        ...

    def restore(
        self,
        field: object,
        level: int,
        arrays: dict[str, np.ndarray],
        background: MSIBackground | None = None,
    ) -> None:
        """Continue from a checkpoint's field, schedule level, `state_arrays()` and background."""
        ...

    @property
    def level(self) -> int:
        """Index of the current resolution in the schedule."""
        ...


@runtime_checkable
class GridHooks(Protocol):
    """What the voxel grid's engines do besides `Engine`: the priors from the cameras' sight lines and
    views, their regularisers each step, the upkeep between steps, and the resolution schedule. An
    engine without them (the NeRF's) is never asked."""

    def use_free_space(self, segments: object) -> None:
        """Segments known to be empty (`train/free_space.SightSegments`), for the free-space prior."""
        ...

    def use_surface(self, windows: object) -> None:
        """Stretches of the lines of sight around their points (`train/free_space.line_stretches`), for the
        surface prior."""
        ...

    def restrict_to_views(self, frustums: object, min_views: int) -> None:
        """Keep the field to where at least `min_views` of the pooled views' frustums
        (`train/view_coverage.PooledFrustums`) look, now and at every resample."""
        ...

    def regularise(self, generator: torch.Generator) -> None:
        """Add the field's own regularisers' gradients (TV, the free-space prior, the background's).
        Random draws come from `generator`, so a resumed run repeats them."""
        ...

    def after_step(self, step: int) -> None:
        """Upkeep between steps, outside what a CUDA graph replays, once `step` steps are taken (the
        Warp grid's exact occupancy, every few steps)."""
        ...

    def settle(self) -> None:
        """Bring `field` up to date with the steps taken, before anything outside a step reads it (the
        Warp grid's voxels may owe the view prior's pull between the steps that read them)."""
        ...

    def upsample(self, step: int, rays: TrainingRays) -> str | None:
        """Move to the next resolution when the schedule says so at `step`; a line to show, or None."""
        ...
