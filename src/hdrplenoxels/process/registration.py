"""Which features register a capture, decided per capture by mapping, not by a fixed flag.

Neither copy of the photos registers every capture best. Histogram-equalised copies lost matches on real
photos (brickstamp: 24 of 25 with half the points of the photos as taken; a sunny phone walk: 2 of 29
against 24) but win where the photos as taken hold too little contrast (asclepius, white marble in a dim
gallery: 51 of 53 against 29 for two mapping seeds of three; photos darkened 3 stops: 20 of 20 against
7). So `auto` maps the photos as taken first and, only when they register fewer than
`SfmConfig.retry_below` (95 %) of the photos, maps equalised copies too and keeps the model that
registers more photos (the lower reprojection error on a tie); a photo or two that nothing registers (a
finger over the lens) does not double the time. Undistortion and training always use the photos as
taken. Measurements: docs/performance.md, "Registration of real captures".
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path

from PIL import Image, ImageOps

from hdrplenoxels.process import sfm
from hdrplenoxels.process.photos import Photo

AS_TAKEN, EQUALISED = "as-taken", "equalised"
# Opens a progress display for one mapping; what it yields is called as each image is registered.
Progress = Callable[[], AbstractContextManager[Callable[[], None]]]


@dataclass
class Attempt:
    """One extraction, matching and mapping of the whole capture."""

    features: str  # AS_TAKEN or EQUALISED
    names: list[str]  # every photo of the capture
    registered: list[str]  # the photos the largest model holds
    reprojection_error_px: float
    points: int
    seconds: dict[str, float] = field(default_factory=dict)  # features, matching, mapping
    model_dir: Path | None = None  # the largest model's folder (None: mapping found none)
    rec: object = None  # its pycolmap.Reconstruction

    @property
    def unregistered(self) -> list[str]:
        return sorted(set(self.names) - set(self.registered))

    def summary(self) -> dict:
        """What transforms.json records of this attempt."""
        return {
            "features": self.features,
            "registered": len(self.registered),
            "unregistered": self.unregistered,
            "mean_reprojection_error_px": round(self.reprojection_error_px, 3),
            "points": self.points,
            "seconds": {k: round(v, 2) for k, v in self.seconds.items()},
        }


def better(a: Attempt, b: Attempt) -> Attempt:
    """More registered photos wins; on a tie, the lower reprojection error."""
    key_a = (len(a.registered), -a.reprojection_error_px)
    key_b = (len(b.registered), -b.reprojection_error_px)
    return b if key_b > key_a else a


def camera_groups(photos: list[Photo]) -> list[list[str]]:
    """Photo names by size, one COLMAP camera each: a portrait photo among landscapes, or a burst of
    another size, gets its own camera instead of every photo getting one."""
    groups: dict[tuple[int, int], list[str]] = {}
    for p in photos:
        groups.setdefault((p.width, p.height), []).append(p.name)
    return list(groups.values())


def write_equalised(photos: list[Photo], staged: Path, target: Path) -> None:
    """Histogram-equalised copies of the staged photos, keeping their EXIF (COLMAP's focal prior)."""
    target.mkdir(parents=True, exist_ok=True)
    for p in photos:
        with Image.open(staged / p.name) as img:
            exif = img.getexif()
            equalised = ImageOps.equalize(img.convert("RGB"))
        if p.name.lower().endswith((".jpg", ".jpeg")):
            equalised.save(target / p.name, quality=95, exif=exif)
        else:
            equalised.save(target / p.name, exif=exif)


def attempt(
    features: str,
    photos: list[Photo],
    staged: Path,
    folder: Path,
    cfg: sfm.SfmConfig,
    matcher: str,
    log: Callable[[str], None],
    progress: Progress,
) -> Attempt:
    """Features from `features` copies of the photos, matching and mapping, all under `folder`."""
    names = [p.name for p in photos]
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    images = staged
    if features == EQUALISED:
        images = folder / "equalised"
        write_equalised(photos, staged, images)
    database = folder / "database.db"
    sfm.extract(database, images, camera_groups(photos), cfg)
    seconds["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sfm.match(database, matcher, cfg, names)
    seconds["matching"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with progress() as on_image:
        rec, model_dir = sfm.reconstruct(database, images, folder / "sparse", cfg, on_image)
    seconds["mapping"] = time.perf_counter() - t0
    if rec is None:
        result = Attempt(features, names, [], 0.0, 0, seconds)
    else:
        registered = sorted(im.name for im in rec.images.values() if im.has_pose)
        error = float(rec.compute_mean_reprojection_error())
        result = Attempt(features, names, registered, error, int(rec.num_points3D()), seconds, model_dir, rec)
    log(
        f"      {features}: {len(result.registered)} of {len(names)} registered, "
        f"{result.reprojection_error_px:.2f} px ({', '.join(f'{k} {v:.1f} s' for k, v in seconds.items())})"
    )
    return result


def register(
    photos: list[Photo],
    staged: Path,
    colmap: Path,
    cfg: sfm.SfmConfig,
    matcher: str,
    log: Callable[[str], None],
    progress: Progress,
) -> tuple[Attempt, list[Attempt]]:
    """The chosen attempt and every attempt made, in order (see the module docstring)."""
    order = [AS_TAKEN, EQUALISED] if cfg.features == "auto" else [cfg.features]
    tried: list[Attempt] = []
    for features in order:
        tried.append(attempt(features, photos, staged, colmap / features, cfg, matcher, log, progress))
        if len(tried[-1].registered) >= cfg.retry_below * len(photos):
            break
    chosen = tried[0]
    for other in tried[1:]:
        chosen = better(chosen, other)
    if len(tried) > 1:
        log(f"      kept the model from the photos {chosen.features.replace('-', ' ')}")
    return chosen, tried
