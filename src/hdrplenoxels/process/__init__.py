"""`hdrplenoxels process PHOTOS OUT`: a folder of photos to a dataset `train` reads, in one command.

Stages: check and stage the photos, SIFT features, matching, incremental mapping, undistortion to
pinhole, then scene bounds from the sparse points and a nerfstudio-convention `OUT/transforms.json`
(plus `OUT/images/`, and COLMAP's database and models under `OUT/colmap/`). Everything is built in a
sibling `OUT.partial-*` folder and renamed into place at the end, so an interrupted run or a failure
never leaves a half-written OUT, and `--overwrite` replaces an old result only once the new one is done.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.colmap import read_reconstruction, scene_from_reconstruction
from hdrplenoxels.data.placement import is_forward_facing
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.writers import write_nerfstudio
from hdrplenoxels.process import sfm
from hdrplenoxels.process.photos import Photo, find_photos, stage_photos

MIN_REGISTERED = 3

__all__ = ["ProcessResult", "process_photos"]


@dataclass
class ProcessResult:
    out: Path
    n_photos: int
    registered: list[str]
    unregistered: list[str]
    forward_facing: bool
    stage_seconds: dict[str, float] = field(default_factory=dict)
    reprojection_error_px: float = 0.0
    n_points: int = 0


class _Stages:
    """Numbered progress lines with each stage's wall time."""

    def __init__(self, log: Callable[[str], None], total: int):
        self.log, self.total, self.index, self.seconds = log, total, 0, {}

    def run(self, name: str, what: str, fn: Callable):
        self.index += 1
        self.log(f"[{self.index}/{self.total}] {what} ...")
        t0 = time.perf_counter()
        result = fn()
        self.seconds[name] = time.perf_counter() - t0
        self.log(f"      done in {self.seconds[name]:.1f} s")
        return result


def _claim(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InputError(out, "is not empty; pass --overwrite to replace it once the new result is complete")


def _publish(work: Path, out: Path) -> None:
    """Move the finished work folder onto OUT, removing an old OUT only after the move succeeded."""
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{time.time_ns()}")
        out.rename(old)
    work.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _map(database: Path, staged: Path, work: Path, cfg: sfm.SfmConfig, n: int):
    with tqdm(total=n, desc="      registered", unit="img", leave=False) as bar:
        rec, model_dir = sfm.reconstruct(
            database, staged, work / "colmap" / "sparse", cfg, lambda: bar.update()
        )
    return rec, model_dir


def write_transforms(
    work: Path, scene: SceneData, photos: dict[str, Photo], forward_facing: bool, info: dict
) -> None:
    """`work/transforms.json` for the undistorted images in `work/images`, with bounds, EXIF and stats."""
    extra: dict = {"forward_facing": forward_facing}
    if scene.near_far is not None:
        extra["near_far"] = list(scene.near_far)
    if scene.scene_box is not None:
        extra["aabb"] = [list(scene.scene_box[0]), list(scene.scene_box[1])]
    box_from = scene.bounds_notes.get("box")  # which sparse points the box fits, for train's scene line
    extra["process"] = info if box_from is None else info | {"box_from": box_from}
    exifs = [photos[name].exif for name in scene.names]
    frame_extra = [{} if e is None else {"exif": e.to_dict(), "exposure_init_ev": e.stops} for e in exifs]
    write_nerfstudio(work, scene.cameras, image_names=scene.names, extra=extra, frame_extra=frame_extra)


def process_photos(
    photos_dir: str | Path,
    out: str | Path,
    cfg: sfm.SfmConfig | None = None,
    overwrite: bool = False,
    log: Callable[[str], None] = print,
) -> ProcessResult:
    """Run the whole pipeline; raises InputError (naming the file) on bad input or failed registration."""
    cfg = cfg or sfm.SfmConfig()
    photos_dir, out = Path(photos_dir), Path(out)
    paths = find_photos(photos_dir)
    _claim(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        result = _run(paths, photos_dir, out, work, cfg, log)
        _publish(work, out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    log(f"wrote {out / 'transforms.json'}  (train with: hdrplenoxels train {out} --out RUN)")
    return result


def _run(
    paths: list[Path], photos_dir: Path, out: Path, work: Path, cfg: sfm.SfmConfig, log
) -> ProcessResult:
    sfm.quiet_colmap()
    n = len(paths)
    stages = _Stages(log, 6)
    staged = work / "colmap" / "photos"
    features_from = work / "colmap" / "equalised" if cfg.equalise else staged
    photos = stages.run(
        "check",
        f"checking {n} photos in {photos_dir}",
        lambda: stage_photos(paths, staged, features_from if cfg.equalise else None),
    )
    by_name = {p.name: p for p in photos}
    same_size = len({(p.width, p.height) for p in photos}) == 1
    database = work / "colmap" / "database.db"
    names = [p.name for p in photos]
    stages.run(
        "features",
        f"SIFT features ({cfg.camera_model}, {'one shared camera' if same_size else 'a camera per photo'})",
        lambda: sfm.extract(database, features_from, names, same_size, cfg),
    )
    matcher = sfm.choose_matcher(cfg, n)
    stages.run("matching", f"{matcher} matching", lambda: sfm.match(database, matcher, cfg))
    rec, model_dir = stages.run(
        "mapping", "incremental mapping", lambda: _map(database, features_from, work, cfg, n)
    )
    registered = [] if rec is None else sorted(im.name for im in rec.images.values() if im.has_pose)
    if len(registered) < MIN_REGISTERED:
        raise InputError(
            photos_dir,
            f"only {len(registered)} of {n} photos could be registered (need at least {MIN_REGISTERED}): "
            "photos need overlapping views of textured, static content",
        )
    unregistered = sorted(set(names) - set(registered))
    if unregistered:
        shown = ", ".join(unregistered[:8]) + (" ..." if len(unregistered) > 8 else "")
        log(f"      warning: {len(unregistered)} of {n} photos not registered and left out: {shown}")
    undistorted = work / "colmap" / "undistorted"
    stages.run(
        "undistort", "undistorting to pinhole", lambda: sfm.undistort(model_dir, staged, undistorted, cfg)
    )
    (undistorted / "images").rename(work / "images")
    scene = stages.run(
        "bounds",
        "scene bounds from the sparse points",
        lambda: scene_from_reconstruction(
            read_reconstruction(undistorted / "sparse"), work / "images", out, upright=True
        ),
    )
    forward = is_forward_facing(scene.cameras)
    kind = "forward-facing (NDC)" if forward else "inward / 360 (bounding box)"
    log(f"      {kind}; near/far {scene.near_far}")
    info = {
        "photos": str(photos_dir.resolve()),
        "n_photos": n,
        "registered": len(registered),
        "unregistered": unregistered,
        "camera_model": cfg.camera_model,
        "matcher": matcher,
        "points": int(rec.num_points3D()),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "seconds": {k: round(v, 2) for k, v in stages.seconds.items()},
    }
    write_transforms(work, scene, by_name, forward, info)
    return ProcessResult(
        out=out,
        n_photos=n,
        registered=registered,
        unregistered=unregistered,
        forward_facing=forward,
        stage_seconds=dict(stages.seconds),
        reprojection_error_px=info["mean_reprojection_error_px"],
        n_points=info["points"],
    )
