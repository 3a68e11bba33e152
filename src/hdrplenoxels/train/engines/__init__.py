"""Radiance-field engines: what the trainer optimises, behind one interface (docs/design.md).

`engine_class` picks the implementation a config names: `TrainConfig.model` chooses the family (a voxel
grid or a NeRF) and, for the grid, `TrainConfig.backend` its renderer. A new engine registers here and
needs no change to the trainer.
"""

from __future__ import annotations

import torch

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.kernels.options import RenderOptions
from hdrplenoxels.render.fields import Field
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.engines.base import Engine, GridHooks, TrainingRays
from hdrplenoxels.train.engines.nerf import NerfEngine
from hdrplenoxels.train.engines.torch_grid import TorchGridEngine
from hdrplenoxels.train.engines.warp_grid import WarpGridEngine

# Keyed by `engine_key`: the grid per backend, the NeRF once (it renders with PyTorch on any device).
ENGINES: dict[str, type] = {
    "warp": WarpGridEngine,
    "torch": TorchGridEngine,
    "nerf": NerfEngine,
}


def engine_key(cfg: TrainConfig) -> str:
    """The `ENGINES` entry of a config: the grid's backend, or the model family's name."""
    return cfg.backend if cfg.model == "grid" else cfg.model


def build_engine(
    field: Field, cfg: TrainConfig, render_opt: RenderOptions, background: MSIBackground | None = None
) -> Engine:
    """The engine `cfg` names, optimising `field` (on the field's device) and `background`; its class's
    `new_field` and `new_background` make those a run starts from."""
    return engine_class(engine_key(cfg))(field, cfg, render_opt, background)


def engine_class(key: str) -> type:
    try:
        return ENGINES[key]
    except KeyError:
        raise ValueError(f"unknown engine {key!r}; choose one of {sorted(ENGINES)}") from None


def new_engine(
    settings: TrainConfig,
    geometry: SceneGeometry,
    n_cameras: int,
    render_opt: RenderOptions,
    device: torch.device,
) -> Engine:
    """The engine `settings` name, with the field and background a run starts from (its class's
    `new_field` and `new_background`)."""
    engine = engine_class(engine_key(settings))
    field = engine.new_field(settings, geometry, n_cameras, device)
    return build_engine(field, settings, render_opt, engine.new_background(settings, geometry, field))


__all__ = [
    "ENGINES",
    "Engine",
    "GridHooks",
    "NerfEngine",
    "TorchGridEngine",
    "TrainingRays",
    "WarpGridEngine",
    "build_engine",
    "engine_class",
    "engine_key",
    "new_engine",
]
