"""`hdrplenoxels process SOURCE OUT`: a folder of photos or a video to a dataset `train` reads, in one step.

Stages: check and stage the photos (or choose the sharp frames of a video), register them (SIFT features,
matching, and global or incremental mapping, with the features and the mapper chosen per capture, and
the EXIF focal held or a fitted one kept where it explains the photos better: `process.registration`),
undistortion to pinhole, then scene bounds from the sparse points and a nerfstudio-convention
`OUT/transforms.json` (plus `OUT/images/`, the sparse points and the views that saw them in
`OUT/sparse_points.npz` for the free-space prior, and COLMAP's databases and models under `OUT/colmap/`).
Everything is built in a sibling `OUT.partial-*` folder and renamed into place at the end, so an
interrupted run or a failure never leaves a half-written OUT, and `--overwrite` replaces an old result
only once the new one is done.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

from tqdm import tqdm

from hdrplenoxels.core.atomic import new_folder_mode
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.colmap import read_reconstruction, scene_from_reconstruction
from hdrplenoxels.data.placement import is_forward_facing
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.sight_lines import POINTS_FILE, POINTS_KEY, write_sight_lines
from hdrplenoxels.data.video import VIDEO_EXTENSIONS, is_video, video_info
from hdrplenoxels.data.writers import write_nerfstudio
from hdrplenoxels.process import sfm
from hdrplenoxels.process.photos import Photo, find_photos, stage_photos
from hdrplenoxels.process.registration import register
from hdrplenoxels.process.video import DEFAULT_FRAMES, stage_video

MIN_REGISTERED = 3

__all__ = ["ProcessResult", "process_photos"]


@dataclass
class ProcessResult:
    out: Path
    n_photos: int  # photos, or frames chosen from a video
    registered: list[str]
    unregistered: list[str]
    forward_facing: bool
    stage_seconds: dict[str, float] = field(default_factory=dict)
    reprojection_error_px: float = 0.0
    n_points: int = 0
    features: str = ""  # which copies the kept model's features came from (process.registration)
    mapper: str = ""  # which mapping made the kept model
    focal_px: list[float] = field(default_factory=list)  # its cameras' focal lengths
    focal_source: str = ""  # registration.FOCAL_EXIF, FOCAL_REFINED or FOCAL_SELF
    focal_choice: dict | None = None  # registration.FocalChoice.summary(), where one was made
    tried: list[dict] = field(default_factory=list)  # every registration attempt, in order


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


def _register(photos: list[Photo], work: Path, cfg: sfm.SfmConfig, matcher: str, log):
    @contextmanager
    def progress():
        with tqdm(total=len(photos), desc="      registered", unit="img", leave=False) as bar:
            yield bar.update

    return register(photos, work / "colmap" / "photos", work / "colmap", cfg, matcher, log, progress)


def write_transforms(
    work: Path, scene: SceneData, photos: dict[str, Photo], forward_facing: bool, info: dict
) -> None:
    """`work/transforms.json` for the undistorted images in `work/images`, with bounds, EXIF and stats."""
    extra: dict = {"forward_facing": forward_facing}
    if scene.near_far is not None:
        extra["near_far"] = list(scene.near_far)
    if scene.scene_box is not None:
        extra["aabb"] = [list(scene.scene_box[0]), list(scene.scene_box[1])]
    if scene.sight_lines is not None:  # written first: transforms.json never names a missing file
        write_sight_lines(work / POINTS_FILE, scene.sight_lines, scene.names)
        extra[POINTS_KEY] = POINTS_FILE
    box_from = scene.bounds_notes.get("box")  # which sparse points the box fits, for train's scene line
    extra["process"] = info if box_from is None else info | {"box_from": box_from}
    frame_extra = []
    for name in scene.names:
        e = photos[name].exif
        exif = {} if e is None else {"exif": e.to_dict(), "exposure_init_ev": e.stops}
        frame_extra.append(exif | photos[name].extra)
    write_nerfstudio(work, scene.cameras, image_names=scene.names, extra=extra, frame_extra=frame_extra)


def process_photos(
    source: str | Path,
    out: str | Path,
    cfg: sfm.SfmConfig | None = None,
    overwrite: bool = False,
    log: Callable[[str], None] = print,
    frames: int = DEFAULT_FRAMES,
) -> ProcessResult:
    """Run the whole pipeline on a folder of photos or a video file (`frames` of it chosen); raises
    InputError (naming the file) on bad input or failed registration."""
    cfg = cfg or sfm.SfmConfig()
    source, out = Path(source), Path(out)
    video = source.is_file() and is_video(source)
    if video:
        info = video_info(source)  # a file that is no decodable video fails before anything is written
        paths = [source]
        cfg = replace(cfg, max_image_size=min(cfg.max_image_size, cfg.video_image_size))
    elif source.is_file():
        raise InputError(source, f"is neither a folder of photos nor a video ({', '.join(VIDEO_EXTENSIONS)})")
    else:
        paths = find_photos(source)
    _claim(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    work.chmod(new_folder_mode())  # mkdtemp's folder is owner-only; OUT is a folder like any other
    try:
        staging = work / "colmap" / "photos"
        stages = _Stages(log, 4)
        if video:
            what = f"choosing {frames} sharp frames of {source} ({info.width} x {info.height})"
            photos, facts = stages.run("frames", what, lambda: stage_video(source, info, staging, frames))
            log(
                f"      {len(photos)} of {facts['frames_decoded']} frames; sharpness (median) "
                f"{facts['sharpness_chosen_median']:.1f}, evenly spaced frames "
                f"{facts['sharpness_even_median']:.1f}"
            )
        else:
            what = f"checking {len(paths)} photos in {source}"
            photos, facts = stages.run("check", what, lambda: stage_photos(paths, staging)), {}
        result = _run(photos, source, out, work, cfg, stages, facts | {"sequence": video}, log)
        _publish(work, out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    log(f"wrote {out / 'transforms.json'}  (train with: hdrplenoxels train {out} --out RUN)")
    return result


def _run(
    photos: list[Photo], source: Path, out: Path, work: Path, cfg: sfm.SfmConfig, stages: _Stages, facts, log
) -> ProcessResult:
    sfm.quiet_colmap()
    n = len(photos)
    staged = work / "colmap" / "photos"
    by_name = {p.name: p for p in photos}
    matcher = sfm.choose_matcher(cfg, n, facts["sequence"])
    mapping = "global and incremental" if cfg.mapper == "auto" else cfg.mapper
    chosen, tried, choice = stages.run(
        "register",
        f"registering: SIFT features, {matcher} matching, {mapping} mapping",
        lambda: _register(photos, work, cfg, matcher, log),
    )
    registered = chosen.registered
    if len(registered) < MIN_REGISTERED:
        raise InputError(
            source,
            f"only {len(registered)} of {n} photos could be registered (need at least {MIN_REGISTERED}): "
            "photos need overlapping views of textured, static content",
        )
    unregistered = chosen.unregistered
    if unregistered:
        shown = ", ".join(unregistered[:8]) + (" ..." if len(unregistered) > 8 else "")
        log(f"      warning: {len(unregistered)} of {n} photos not registered and left out: {shown}")
    undistorted = work / "colmap" / "undistorted"
    stages.run(
        "undistort",
        "undistorting to pinhole",
        lambda: sfm.undistort(chosen.model_dir, staged, undistorted, cfg),
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
        "photos": str(source.resolve()),
        "n_photos": n,
        "registered": len(registered),
        "unregistered": unregistered,
        "camera_model": cfg.camera_model,
        "matcher": matcher,
        "features": chosen.features,
        "mapper": chosen.mapper,
        "focal": {"px": [round(f, 1) for f in chosen.focal_px], "source": chosen.focal_source}
        | ({} if choice is None else {"choice": choice.summary()}),
        "tried": [a.summary() for a in tried],
        "points": chosen.points,
        "mean_reprojection_error_px": chosen.reprojection_error_px,
        "seconds": {k: round(v, 2) for k, v in stages.seconds.items()},
    } | {k: v for k, v in facts.items() if k != "sequence"}
    write_transforms(work, scene, by_name, forward, info)
    return ProcessResult(
        out=out,
        n_photos=n,
        registered=registered,
        unregistered=unregistered,
        forward_facing=forward,
        stage_seconds=dict(stages.seconds),
        reprojection_error_px=chosen.reprojection_error_px,
        n_points=chosen.points,
        features=chosen.features,
        mapper=chosen.mapper,
        focal_px=chosen.focal_px,
        focal_source=chosen.focal_source,
        focal_choice=None if choice is None else choice.summary(),
        tried=[a.summary() for a in tried],
    )
