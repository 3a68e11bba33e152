"""The priors a run takes from where its cameras looked: the free-space and surface priors along the
lines of sight to the sparse points, and the grid kept to voxels enough views see (docs/method.md,
"Real captures"). Each is handed to the engine once, before the first step, with a line saying what it
uses."""

from __future__ import annotations

import torch

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.engines import GridHooks
from hdrplenoxels.train.free_space import (
    ObservedLines,
    SightSegments,
    line_stretches,
    near_segments,
    observed_lines,
)
from hdrplenoxels.train.ray_pool import RayPool
from hdrplenoxels.train.view_coverage import pooled_frustums


def use_sight_priors(
    engine: GridHooks | None,
    cfg: TrainConfig,
    scene: SceneData,
    cameras: Cameras,
    geometry: SceneGeometry,
    pool: RayPool,
    device: torch.device,
) -> str | None:
    """Hand `engine` the free-space and surface priors' segments when they are on; a line saying what
    they use."""
    o, lines = cfg.optim, scene.sight_lines
    if o.lambda_free_space <= 0 and o.lambda_surface <= 0:
        return None
    why = sight_priors_off(engine, scene, geometry)
    if why is not None or engine is None:
        return f"free space and surfaces: off ({why})"
    tests = set(scene.test_ids)
    views = [i for i in scene.train_ids if i not in tests]
    seen = observed_lines(lines, cameras.c2w, geometry.world_from_data, views)
    margin, notes = o.free_space_margin, []
    if o.lambda_free_space > 0:
        segments = line_stretches(seen, 0.0, 1.0 - margin, device)
        note = (
            f"free space: {len(segments):,} lines of sight to {len(lines.points):,} sparse points "
            f"from {len(views)} training views (weight {o.lambda_free_space:g})"
        )
        if o.free_space_near > 0:
            near, words = _near_cameras(seen, tests, cameras, pool, o.free_space_near, device)
            segments = segments + near
            note += f", and {len(near):,} near the cameras ({words})"
        engine.use_free_space(segments)
        notes.append(note)
    if o.lambda_surface > 0:
        windows = line_stretches(seen, 1.0 - margin, 1.0 + o.surface_behind, device)
        engine.use_surface(windows)
        notes.append(f"surfaces: {len(windows):,} windows at the points (weight {o.lambda_surface:g})")
    return "; ".join(notes)


def _near_cameras(
    seen: ObservedLines, tests: set[int], cams: Cameras, pool: RayPool, fraction: float, device: torch.device
) -> tuple[SightSegments, str]:
    """The near-camera segments of the training views and of the pooled test views' left halves; what
    the note says of them."""
    pooled = zip(pool.image_ids.tolist(), pool.used_width.tolist(), strict=True)
    halves = {i: w for i, w in pooled if i in tests}
    near = near_segments(seen, cams.c2w, cams.intrinsics, cams.sizes, fraction, device, halves)
    words = f"{fraction:g} of their nearest points"
    if not halves:
        return near, words
    held = "1 test view's left half" if len(halves) == 1 else f"{len(halves)} test views' left halves"
    return near, f"{words}; {held} among them"


def sight_priors_off(engine: GridHooks | None, scene: SceneData, geometry: SceneGeometry) -> str | None:
    """Why the sight priors cannot run on this engine and dataset, or None."""
    if engine is None:
        return "it is the voxel grid's prior; the NeRF engine ignores it"
    if scene.sight_lines is None:
        return "the dataset has no sparse points"
    if geometry.mode != "bbox":
        return "NDC has no metric segments"
    return None


def restrict_to_views(
    engine: GridHooks | None, cfg: TrainConfig, geometry: SceneGeometry, pool: RayPool
) -> str | None:
    """Keep the grid to voxels `grid.min_views` pooled views see, when set; a line saying what it
    dropped."""
    k = cfg.grid.min_views
    if k <= 0:
        return None
    if engine is None or geometry.mode != "bbox":
        where = f"{cfg.model}, {geometry.mode}"
        return f"views per voxel: off (it is the voxel grid's, in a box scene; this is {where})"
    frustums = pooled_frustums(pool.c2w, pool.intrinsics, pool.image_ids, pool.used_width, pool.heights)
    before = engine.field.num_voxels
    engine.restrict_to_views(frustums, k)
    dropped = before - engine.field.num_voxels
    return f"views per voxel: at least {k}; {dropped:,} of {before:,} voxels seen by fewer dropped"
