"""Scene loading: one entry point that recognises the dataset layout and returns a `SceneData`.

A folder is tried in this order (the first layout found wins, so a folder holding several, like the
synthetic scenes with both `transforms.json` and `poses_bounds.npy`, loads the richest description):
1. nerfstudio / instant-ngp `transforms.json`, or Blender `transforms_train.json`;
2. HDR-NeRF `poses_bounds_exps.npy`, then LLFF `poses_bounds.npy` (with `hwf_cxcy.npy` if present); LLFF
   folders made by COLMAP keep their `sparse/`, and the LLFF file is what such datasets are used through;
3. COLMAP: `sparse/0/cameras.bin|txt` or `sparse/cameras.bin|txt`.
A file path may name a transforms .json or an LLFF / HDR-NeRF .npy.
Each layout's `load_*` is two steps (docs/design.md, "Data loading"): its parser's `describe_*` reads only
the layout's own files into a `SceneDescription`, then `images.load_images` reads the pixels.
"""

from __future__ import annotations

from pathlib import Path

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.llff import LLFF_FILES, POSES_BOUNDS, POSES_BOUNDS_EXPS, load_llff
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.transforms_json import BLENDER_FILES, NERFSTUDIO_FILE, load_transforms

__all__ = ["SceneData", "load_llff", "load_scene", "load_transforms", "scene_layout"]

COLMAP_MODEL_DIRS = ("sparse/0", "sparse")


def _is_colmap(folder: Path) -> bool:
    return any((folder / d / f"cameras.{ext}").is_file() for d in COLMAP_MODEL_DIRS for ext in ("bin", "txt"))


def scene_layout(folder: Path) -> str | None:
    """The layout `load_scene` reads `folder` as ("transforms", "llff" or "colmap"), or None when it holds
    none of them (a folder of photos, say)."""
    if (folder / NERFSTUDIO_FILE).is_file() or (folder / BLENDER_FILES[0]).is_file():
        return "transforms"
    if any((folder / name).is_file() for name in LLFF_FILES):
        return "llff"
    return "colmap" if _is_colmap(folder) else None


def _load_folder(path: Path, downscale: int) -> SceneData:
    layout = scene_layout(path)
    if layout == "transforms":
        return load_transforms(path, downscale)
    if layout == "llff":
        return load_llff(path, downscale)
    if layout == "colmap":
        from hdrplenoxels.data.colmap import load_colmap  # only loaded for COLMAP folders

        return load_colmap(path, downscale)
    raise InputError(
        path,
        f"unrecognised scene folder: expected {NERFSTUDIO_FILE} (nerfstudio / instant-ngp), "
        f"{BLENDER_FILES[0]} (Blender synthetic), {POSES_BOUNDS} (LLFF), {POSES_BOUNDS_EXPS} (HDR-NeRF) "
        "or sparse/0/cameras.bin (COLMAP); for your own photos, give `train` the folder that holds them "
        "(or run `hdrplenoxels process PHOTOS OUT` first)",
    )


def load_scene(path: str | Path, downscale: int = 1) -> SceneData:
    """Load the scene at `path` (a dataset folder, its JSON file or its LLFF .npy), whatever its layout,
    with its images `downscale` times smaller on each side (`downscale.py`)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file or folder")
    if path.is_dir():
        return _load_folder(path, downscale)
    if path.suffix.lower() == ".json":
        return load_transforms(path, downscale)
    if path.name in LLFF_FILES:
        return load_llff(path, downscale)
    raise InputError(
        path,
        "unrecognised scene file: give a dataset folder, its transforms .json file or its LLFF .npy file",
    )
