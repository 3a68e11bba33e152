"""What a dataset states about a scene, before any pixel is read (docs/design.md, "Data loading").

Loading is two steps. Each layout's parser (`transforms_json`, `llff`, `colmap`) turns its files into one
`SceneDescription`: cameras as stated, image paths, split, names and scene hints, with every rule of the
layout applied and every mistake in its files reported. `images.load_images` then reads the pixels and
does what depends on them, the same way for every layout: alpha, image sizes, undistortion.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hdrplenoxels.data.sight_lines import SightLines

AlphaMode = Literal["drop", "white"]  # what the loader does with an alpha channel: drop it, or composite
BoxSource = Literal["stated", "points"]  # a scene box the layout states, or the extent of SfM points
Intrinsics = tuple[float, float, float, float]  # fx, fy, cx, cy in pixels


@dataclass(frozen=True)
class Distortion:
    """A lens the loader undoes (resampling to pinhole): a COLMAP camera model and its parameters other
    than the focal length(s) and principal point, e.g. FULL_OPENCV's (k1, k2, p1, p2, k3, k4, k5, k6)."""

    model: str
    coeffs: tuple[float, ...]


@dataclass(frozen=True)
class CameraDescription:
    """Intrinsics as the layout states them; the loader completes them from the image's actual size.

    A None entry is unstated: cx, cy default to the image centre; a focal length comes from `fov_x` /
    `fov_y` (radians) over the image's width / height, else it is the other axis's. `width`, `height` are
    the stated size the image must have, unless `resized_copies` (LLFF's `images_8` copied into `images/`):
    then an image of the same aspect ratio is a resized copy and the intrinsics scale with it.
    """

    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    fov_x: float | None = None
    fov_y: float | None = None
    width: int | None = None
    height: int | None = None
    resized_copies: bool = False
    shared: bool = False  # intrinsics shared by the `shared` views of one file: their sizes must agree
    distortion: Distortion | None = None


@dataclass
class ViewDescription:
    """One image of the scene: its file, pose and camera, and where it was described (for errors)."""

    name: str
    image_path: Path
    c2w: np.ndarray  # (4, 4) OpenCV camera-to-world, already checked to be rigid
    camera: CameraDescription
    described_in: Path  # the file stating this view (a JSON, a poses .npy, a COLMAP model folder)
    where: str  # how errors refer to the view's entry there, e.g. "transforms.json frame 3"


@dataclass
class SceneDescription:
    """A parsed scene, no pixels read: what `load_images` needs to produce a `SceneData`.

    `scene_box`, `forward_facing` and `near_far` are the hints `SceneData` documents. `white_background`:
    the layout's images are known to be on white (Blender renders); otherwise the loader records white
    only when it composited some image's alpha onto it. `background_brightness`: the layout's own value.
    `exposure_init_ev`: each view's stated exposure in stops (EXIF, HDR-NeRF), never pinned.
    `extras` holds what only one layout states (e.g. COLMAP's per-image "exif"). `bounds_notes` says where
    the bounds came from, for the line `placement.placement_summary` prints: "box" (of `scene_box`),
    "near_far", and "beyond" when the data says content reaches beyond the box (instant-ngp's aabb_scale).
    `box_source`: "stated" when `scene_box` is a region of interest the layout states, "points" when it is
    the extent of structure-from-motion points (everything the cameras saw). `aabb_scale`: instant-ngp's,
    when the layout gives one. `sight_lines`: sparse points and the views that saw them, when known.
    """

    layout: str
    source: Path
    views: list[ViewDescription]
    train_ids: list[int]
    test_ids: list[int]
    alpha: AlphaMode = "drop"
    white_background: bool = False
    background_brightness: float | None = None
    scene_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    forward_facing: bool | None = None
    near_far: tuple[float, float] | None = None
    exposure_init_ev: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)
    bounds_notes: dict[str, str] = field(default_factory=dict)
    box_source: BoxSource = "stated"
    aabb_scale: float | None = None
    sight_lines: SightLines | None = None

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]

    @property
    def image_paths(self) -> list[Path]:
        return [v.image_path for v in self.views]
