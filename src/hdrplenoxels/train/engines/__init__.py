"""Radiance-field engines: what the trainer optimises, behind one interface (docs/design.md).

`build_engine` picks the implementation named by `TrainConfig.backend`; a new engine registers here and
needs no change to the trainer.
"""

from __future__ import annotations

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render.options import RenderOptions
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.engines.base import Engine, TrainingRays
from hdrplenoxels.train.engines.grid_engine import GridEngine
from hdrplenoxels.train.engines.torch_grid import TorchGridEngine
from hdrplenoxels.train.engines.warp_grid import WarpGridEngine

ENGINES: dict[str, type[GridEngine]] = {
    "warp": WarpGridEngine,
    "torch": TorchGridEngine,
}


def build_engine(field: SparseGrid, cfg: TrainConfig, render_opt: RenderOptions) -> Engine:
    """The engine `cfg.backend` names, optimising `field` (on the field's device); `new_field` makes
    the field a run starts from."""
    return engine_class(cfg.backend)(field, cfg, render_opt)


def engine_class(backend: str) -> type[GridEngine]:
    try:
        return ENGINES[backend]
    except KeyError:
        raise ValueError(f"unknown backend {backend!r}; choose one of {sorted(ENGINES)}") from None


__all__ = ["ENGINES", "Engine", "TorchGridEngine", "TrainingRays", "WarpGridEngine", "build_engine"]
