"""Scene loading: one entry point that recognises the dataset layout and returns a `SceneData`.

Layouts supported so far: nerfstudio / instant-ngp `transforms.json` and Blender NeRF-synthetic folders.
LLFF and COLMAP layouts will be dispatched from here too.
"""

from __future__ import annotations

from pathlib import Path

from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.transforms_json import BLENDER_FILES, NERFSTUDIO_FILE, load_transforms
from hdrplenoxels.errors import InputError

__all__ = ["SceneData", "load_scene", "load_transforms"]


def load_scene(path: str | Path) -> SceneData:
    """Load the scene at `path` (a dataset folder or its JSON file), whatever its layout."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file or folder")
    if path.is_dir():
        if (path / NERFSTUDIO_FILE).is_file() or (path / BLENDER_FILES[0]).is_file():
            return load_transforms(path)
        raise InputError(
            path,
            f"unrecognised scene folder: expected {NERFSTUDIO_FILE} (nerfstudio / instant-ngp) "
            f"or {BLENDER_FILES[0]} (Blender synthetic)",
        )
    if path.suffix.lower() == ".json":
        return load_transforms(path)
    raise InputError(path, "unrecognised scene file: give a dataset folder or its transforms .json file")
