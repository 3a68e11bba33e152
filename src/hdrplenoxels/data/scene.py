"""A loaded scene: what `images.load_images` makes of a parser's `SceneDescription` (docs/design.md,
"Data loading"), and what training, evaluation and the experiments read."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hdrplenoxels.data.sight_lines import SightLines
from hdrplenoxels.geometry.cameras import Cameras


@dataclass
class SceneData:
    """Images, cameras and split of one scene, in the parser's world coordinates.

        `images[i]` is uint8 (H, W, 3) RGB of camera i. `scene_box` is an optional (min, max) corner pair of
        the region of interest when the layout states one; `forward_facing` is a hint (None = unknown) that
        the scene-setup step uses to pick NDC or a bounding box. `near_far` are optional depth bounds.
    `exposures`, when known (EXIF, or a synthetic scene's truth), fix the gauge of a self-calibrated model.
    `bounds_notes`: where the bounds came from; `box_source` and `aabb_scale` as in `SceneDescription`.
    """

    images: list[np.ndarray]
    cameras: Cameras
    names: list[str]
    train_ids: list[int]
    test_ids: list[int]
    source: Path
    scene_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    forward_facing: bool | None = None
    near_far: tuple[float, float] | None = None
    extras: dict = field(default_factory=dict)
    exposures: np.ndarray | None = None  # known EV per view (stops), when the user supplies them
    bounds_notes: dict[str, str] = field(default_factory=dict)
    box_source: str = "stated"
    aabb_scale: float | None = None
    sight_lines: SightLines | None = None  # sparse points and the views that saw them (free space)

    @property
    def background_brightness(self) -> float:
        """Background brightness to render with: the layout's own value when it states one, white (1.0)
        where the loader composited alpha onto white, else the HDR-Plenoxels / svox2 value 0.5."""
        if "background" in self.extras:
            return float(self.extras["background"])
        return 1.0 if self.extras.get("alpha_background") == "white" else 0.5

    def __post_init__(self) -> None:
        n = len(self.cameras)
        if len(self.images) != n or len(self.names) != n:
            raise ValueError("images, names and cameras must have the same length")
