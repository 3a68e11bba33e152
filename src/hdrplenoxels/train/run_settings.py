"""The settings a run trains with: its config with what is left to the capture filled in from it
(`TrainConfig.resolved`), and a line for each thing the capture decided (tone mapping on or off, the
grid's TV for the number of photos)."""

from __future__ import annotations

from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.train.config import TrainConfig, tv_scale
from hdrplenoxels.train.ray_pool import pooled_views
from hdrplenoxels.train.tone_setup import tone_mapping_choice


def run_settings(
    cfg: TrainConfig, scene: SceneData, geometry: SceneGeometry
) -> tuple[TrainConfig, list[str]]:
    """`cfg` resolved for `scene` (config.json keeps `cfg` itself), and the lines that say what the capture
    decided."""
    photos = len(pooled_views(scene.train_ids, scene.test_ids, cfg.holdout))  # those the grid learns from
    tone_mapping, why = tone_mapping_choice(cfg, scene)
    settings = cfg.resolved(
        background_brightness=scene.background_brightness,
        wants_background=geometry.wants_background,
        levels=geometry.levels,
        photos=photos,
        tone_mapping=tone_mapping,
    )
    on = settings.tonemap.enabled
    note = f"tone mapping: {'on' if on else 'off'} ({why})"
    if cfg.tonemap.enabled is None:
        note += "; --no-tonemap trains plain Plenoxels" if on else "; --tonemap learns a tone per photo"
    notes = [note]
    scale = tv_scale(cfg.optim.tv_photos, photos)
    if scale != 1.0:
        notes.append(
            f"the grid's TV weights x{scale:.3g} for {photos} photos "
            f"(optim.tv_photos={cfg.optim.tv_photos:g})"
        )
    return settings, notes
