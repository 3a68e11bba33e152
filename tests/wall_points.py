"""Sparse points on the walled room's walls, truth standing in for structure from motion: the lines of
sight the free-space and surface priors read, at a test's size."""

from __future__ import annotations

import dataclasses

import numpy as np

from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.sight_lines import SightLines
from hdrplenoxels.synth.procedural import ROOM_HALF


def with_wall_points(scene: SceneData, per_view: int, reach: float) -> SceneData:
    """`scene` with `per_view` points seen by each training view, each `reach` of the way from its camera
    to the wall straight behind a random direction (1: on the wall)."""
    rng = np.random.default_rng(0)
    points, view = [], []
    for i in scene.train_ids:
        c = scene.cameras.c2w[i, :3, 3]
        for d in rng.normal(size=(per_view, 3)):
            d /= np.linalg.norm(d)
            points.append(c + reach * ((np.sign(d) * ROOM_HALF - c) / d).min() * d)
            view.append(i)
    lines = SightLines(np.array(points), np.array(view), np.arange(len(points)))
    return dataclasses.replace(scene, sight_lines=lines)
