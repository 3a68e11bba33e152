"""A model from an existing Plenoxels (svox2) checkpoint and the dataset it was trained on."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from hdrplenoxels.data import load_scene
from hdrplenoxels.data.placement import setup_scene
from hdrplenoxels.grid.io import import_svox2
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.train.model import Model


def model_from_svox2(
    ckpt: Path, data: Path, scene_mode: Literal["auto", "bbox", "bbox+background", "cascade", "ndc"]
) -> Model:
    """The svox2 grid placed as svox2 placed it (its own centre and radius, no normalisation of the
    cameras), without a tone mapper; test views are scored in full (svox2 trained on none of their pixels)."""
    grid = import_svox2(ckpt)
    scene = load_scene(data)
    cams, geometry = setup_scene(scene, scene_mode, normalise=False)  # the grid is in svox2's frame
    geometry.center, geometry.radius = grid.center, grid.radius
    geometry.levels = 1  # svox2 has one box, and no MSI comes with its grid
    geometry.wants_background = False
    opt = RenderOptions(background_brightness=scene.background_brightness)
    return Model(
        grid,
        geometry,
        opt,
        cams,
        scene.names,
        scene.train_ids,
        scene.test_ids,
        str(scene.source),
        {"holdout": "full"},
    )
