"""hdrplenoxels: HDR radiance fields (Plenoxels + learned tone mapping) from photos with varying settings.

The names a script needs are exported here (docs/api.md has an example); each is imported on first use,
so importing the package changes nothing in the process. For the CPU speed settings the command line
uses, call `hdrplenoxels.core.process_settings.apply_process_settings()` before importing torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# name -> the module that defines it
_EXPORTS = {
    "load_scene": "hdrplenoxels.data",
    "SceneData": "hdrplenoxels.data.scene",
    "TrainConfig": "hdrplenoxels.train.config",
    "preset": "hdrplenoxels.train.presets",
    "apply_overrides": "hdrplenoxels.core.settings",
    "train_model": "hdrplenoxels.train.trainer",
    "Model": "hdrplenoxels.train.model",
    "load_model": "hdrplenoxels.train.model",
    "Picture": "hdrplenoxels.eval.renders",
    "render_pose": "hdrplenoxels.eval.renders",
    "evaluate": "hdrplenoxels.eval.evaluate",
    "write_exr": "hdrplenoxels.data.image_io",
    "write_png": "hdrplenoxels.data.image_io",
}

__all__ = [
    "Model",
    "Picture",
    "SceneData",
    "TrainConfig",
    "apply_overrides",
    "evaluate",
    "load_model",
    "load_scene",
    "preset",
    "render_pose",
    "train_model",
    "write_exr",
    "write_png",
]

if TYPE_CHECKING:
    from hdrplenoxels.core.settings import apply_overrides
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.data.image_io import write_exr, write_png
    from hdrplenoxels.data.scene import SceneData
    from hdrplenoxels.eval.evaluate import evaluate
    from hdrplenoxels.eval.renders import Picture, render_pose
    from hdrplenoxels.train.config import TrainConfig
    from hdrplenoxels.train.model import Model, load_model
    from hdrplenoxels.train.presets import preset
    from hdrplenoxels.train.trainer import train_model


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'hdrplenoxels' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
