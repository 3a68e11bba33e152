"""Writers for the `transforms.json` layouts (nerfstudio / instant-ngp, Blender NeRF-synthetic), and the
image writing every layout writer shares (LLFF's are in `llff.py`).

They write what `load_transforms` reads back exactly (poses to float64 precision: JSON keeps every digit),
so datasets can be converted between layouts and generated for tests. Every file is written atomically,
images before the JSON that names them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hdrplenoxels.core.atomic import atomic_write_text
from hdrplenoxels.data.image_io import write_png
from hdrplenoxels.geometry.cameras import Cameras, opencv_to_opengl

DEFAULT_NAME = "view_{:03d}.png"
BLENDER_SPLITS = ("train", "test")


def check_image_names(n: int, image_names: Sequence[str] | None = None, png: bool = True) -> list[str]:
    """`image_names` (default view_000.png, ...): n distinct plain file names; PNG ones when `png`, since
    the images we write go out as PNG (names of images already on disk may have any extension)."""
    names = [DEFAULT_NAME.format(i) for i in range(n)] if image_names is None else list(image_names)
    if len(names) != n or len(set(names)) != n:
        raise ValueError(f"need {n} distinct image names, got {names}")
    if any("/" in name or "\\" in name for name in names):
        raise ValueError(f"image names must be plain file names, got {names}")
    if png and any(not name.lower().endswith(".png") for name in names):
        raise ValueError(f"image names must be plain .png file names, got {names}")
    return names


def write_images(folder: Path, names: Sequence[str], images: Sequence[np.ndarray]) -> None:
    """Write images[i] as PNG `folder/names[i]`."""
    if len(images) != len(names):
        raise ValueError(f"got {len(images)} images for {len(names)} cameras")
    for name, image in zip(names, images, strict=True):
        write_png(Path(folder) / name, image)


def _intrinsics(cameras: Cameras, i: int) -> dict:
    fx, fy, cx, cy = (float(v) for v in cameras.intrinsics[i])
    w, h = cameras.size(i)
    return {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": w, "h": h}


def _shares_intrinsics(cameras: Cameras) -> bool:
    same_k = (cameras.intrinsics == cameras.intrinsics[0]).all()
    return bool(same_k and (cameras.sizes == cameras.sizes[0]).all())


def write_nerfstudio(
    folder: str | Path,
    cameras: Cameras,
    images: Sequence[np.ndarray] | None = None,
    image_names: Sequence[str] | None = None,
    per_frame_intrinsics: bool | None = None,
    extra: dict | None = None,
    frame_extra: Sequence[dict] | None = None,
) -> Path:
    """Write `transforms.json` (PINHOLE, OpenGL camera-to-world) and, when given, `images/`; returns its path.

    Intrinsics go to the top level when all cameras share them, else into every frame;
    `per_frame_intrinsics` forces either. `extra` adds top-level keys as they are (near_far, aabb,
    forward_facing, background, train_filenames, ...); `frame_extra[i]` adds keys to frame i.
    """
    folder = Path(folder)
    names = check_image_names(len(cameras), image_names, png=images is not None)
    per_frame = not _shares_intrinsics(cameras) if per_frame_intrinsics is None else per_frame_intrinsics
    if not per_frame and not _shares_intrinsics(cameras):
        raise ValueError("cameras have different intrinsics or sizes: they cannot share one set")
    shared = {} if per_frame else _intrinsics(cameras, 0)
    meta: dict = {"camera_model": "PINHOLE", **shared, **(extra or {})}
    meta["frames"] = [
        {
            "file_path": f"images/{name}",
            "transform_matrix": opencv_to_opengl(cameras.c2w[i]).tolist(),
            **(_intrinsics(cameras, i) if per_frame else {}),
            **(frame_extra[i] if frame_extra is not None else {}),
        }
        for i, name in enumerate(names)
    ]
    if images is not None:
        write_images(folder / "images", names, images)
    return atomic_write_text(folder / "transforms.json", json.dumps(meta, indent=1))


def _blender_camera_angle_x(cameras: Cameras) -> float:
    """The one horizontal FOV Blender files state; refuses cameras it cannot describe."""
    fx, fy, cx, cy = cameras.intrinsics[0]
    w, h = cameras.size(0)
    centred = np.allclose([fy, cx, cy], [fx, w / 2, h / 2], rtol=1e-9, atol=0.0)
    if not (_shares_intrinsics(cameras) and centred):
        raise ValueError("Blender layout needs one image size, fx == fy and a centred principal point")
    return 2.0 * math.atan(0.5 * w / fx)


def write_blender(
    folder: str | Path,
    cameras: Cameras,
    train_ids: Sequence[int],
    test_ids: Sequence[int],
    images: Sequence[np.ndarray] | None = None,
) -> tuple[Path, Path]:
    """Write `transforms_train.json` / `_test.json` and, when given, images `train/r_k.png` / `test/r_k.png`.

    File paths carry no extension, as in the NeRF-synthetic data. Returns the two JSON paths.
    """
    folder = Path(folder)
    angle = _blender_camera_angle_x(cameras)
    out = []
    for split, ids in zip(BLENDER_SPLITS, (train_ids, test_ids), strict=True):
        frames = []
        for k, i in enumerate(ids):
            if images is not None:
                write_png(folder / split / f"r_{k}.png", images[i])
            c2w = opencv_to_opengl(cameras.c2w[i]).tolist()
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": c2w})
        meta = {"camera_angle_x": angle, "frames": frames}
        out.append(atomic_write_text(folder / f"transforms_{split}.json", json.dumps(meta, indent=1)))
    return out[0], out[1]
