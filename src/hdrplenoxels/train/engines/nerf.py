"""A NeRF MLP being optimised (docs/method.md, "NeRF engine"): plain PyTorch autograd and Adam.

The forward returns the coarse and the fine network's radiance as one (2N, 3) tensor over the batch
twice, so the trainer's loss (through the tone-mapping module, unchanged) is vanilla NeRF's sum of the
coarse and fine losses (halved: a mean over both). The training jitter is drawn from the engine's own
generator, which checkpoints carry, so a resumed run repeats an unbroken one.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import torch

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.kernels.options import RenderOptions
from hdrplenoxels.render.nerf import Appearance, NerfField
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.optim import ExpSchedule, StepClock
from hdrplenoxels.train.ray_pool import RayBatch


def _twice(batch: RayBatch) -> RayBatch:
    return RayBatch(*(torch.cat([getattr(batch, f.name)] * 2) for f in fields(batch)))


class NerfEngine:
    """Coarse and fine MLPs (and NeRF-A's appearance codes) under Adam with a log-linear decay."""

    background = None  # the MSI is a grid component; a NeRF renders the constant background

    def __init__(self, field: NerfField, cfg: TrainConfig, render_opt: RenderOptions, background=None):
        if background is not None:
            raise ValueError("the NeRF engine has no background model (the MSI is a grid component)")
        self.cfg = cfg
        self.render_opt = render_opt
        self.lr = ExpSchedule(cfg.nerf.lr, cfg.nerf.lr_final, cfg.nerf.lr_decay_steps)
        self.generator = torch.Generator(field.device).manual_seed(cfg.seed)
        self._use(field)
        self._out: torch.Tensor | None = None

    def _use(self, field: NerfField) -> None:
        self.field = field
        self.device = field.device
        self.optimiser = torch.optim.Adam(field.parameters(), lr=self.cfg.nerf.lr)

    @staticmethod
    def new_field(
        cfg: TrainConfig, geometry: SceneGeometry, n_images: int, device: torch.device
    ) -> NerfField:
        """Freshly initialised networks inside the scene's box (a cascade's outermost)."""
        radius = tuple(r * 2.0 ** (geometry.levels - 1) for r in geometry.radius)
        with torch.random.fork_rng(devices=[]):  # the initial weights follow the run's seed alone
            torch.manual_seed(cfg.seed)
            return NerfField(cfg.nerf.network(), geometry.center, radius, n_images).to(device)

    @staticmethod
    def new_background(cfg: TrainConfig, geometry: SceneGeometry, field: NerfField) -> None:
        """None: only the grid engines train an MSI; forcing one on is refused (`TrainConfig.check`, which
        the trainer calls)."""
        return None

    @property
    def level(self) -> int:
        return 0

    def forward(self, batch: RayBatch) -> tuple[torch.Tensor, RayBatch]:
        coarse, fine = self.field(
            batch.origins,
            batch.dirs,
            self.render_opt.background_brightness,
            batch.image_ids,
            generator=self.generator,
        )
        self._out = torch.cat([coarse, fine])
        return self._out.detach().requires_grad_(True), _twice(batch)

    def backward(self, grad_rgb: torch.Tensor) -> None:
        out, self._out = self._out, None
        out.backward(grad_rgb)

    def step(self, clock: StepClock, view_prior: float = 0.0) -> None:
        """Adam's step at the rate of `clock.step` (this engine never runs from a CUDA graph);
        `view_prior` is ignored: it acts on SH coefficients, which an MLP has not."""
        for group in self.optimiser.param_groups:
            group["lr"] = self.lr(clock.step)
        self.optimiser.step()
        self.optimiser.zero_grad(set_to_none=True)

    def graph_key(self) -> tuple:
        return (self.level,)

    def render(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """A NeRF-A renders with image 0's appearance here (`Model.render_view` chooses per view)."""
        return self.field.render(origins, dirs, self.render_opt.background_brightness, Appearance(0))

    def log_fields(self, step: int) -> dict[str, float | int]:
        return {"lr": self.lr(step), "params": sum(p.numel() for p in self.field.parameters())}

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Adam's moments and step per parameter, and the jitter generator's state: copies, even of what
        Adam keeps on the host beside CUDA parameters (its step), so a checkpoint written behind the next
        steps holds this one's."""
        out = {"generator": self.generator.get_state().numpy()}
        for i, p in enumerate(self.field.parameters()):
            state = self.optimiser.state.get(p)
            if state:
                for key, value in state.items():
                    host = value.detach().cpu().numpy()
                    out[f"{i}/{key}"] = host.copy() if value.device.type == "cpu" else host
        return out

    def restore(
        self, field: NerfField, level: int, arrays: dict[str, np.ndarray], background: None = None
    ) -> None:
        self._use(field)
        self.generator.set_state(torch.from_numpy(arrays["generator"]))
        for i, p in enumerate(field.parameters()):
            keys = [k for k in arrays if k.startswith(f"{i}/")]
            if keys:
                state = {k.split("/", 1)[1]: torch.from_numpy(arrays[k]) for k in keys}
                self.optimiser.state[p] = {
                    k: (v if k == "step" else v.to(self.device)) for k, v in state.items()
                }
