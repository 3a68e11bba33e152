"""Which features and which mapper register a capture, decided per capture by mapping, not by a flag.

Neither copy of the photos registers every capture best. Histogram-equalised copies lost matches on real
photos (brickstamp: 24 of 25 with half the points of the photos as taken; a sunny phone walk: 2 of 29
against 24) but win where the photos as taken hold too little contrast (asclepius, white marble in a dim
gallery: 51 of 53 against 29 for two mapping seeds of three; photos darkened 3 stops: 20 of 20 against
7). So `auto` maps the photos as taken first and, only when they register fewer than
`SfmConfig.retry_below` (95 %) of the photos, maps equalised copies too and keeps the model that
registers more photos (the lower reprojection error on a tie); a photo or two that nothing registers (a
finger over the lens) does not double the time. Undistortion and training always use the photos as
taken.

Each set of features is mapped twice, globally and incrementally, and the two models are compared
camera by camera (`eval.registration.model_agreement`). Either mapper can return a whole wrong model that
registers every photo at a low reprojection error: incremental mapping on a forward walk, global mapping
where weak image pairs (a repeated floor pattern) turn it; the count and the error pass both, but two
mappings that go wrong go wrong differently. Where the two agree, the one registering more photos (the
lower error on a tie) is kept. Where they disagree, a third mapping decides: global again, from strong pairs
only (`SfmConfig.strict_min_matches`), and the better of the two models that agree is kept; where none
agree, the global model, with a warning. The EXIF focal length starts the fit, or is held fixed on
request (`focal_hold`). Measurements: docs/performance.md, "Registration of real captures".
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path

from PIL import Image, ImageOps

from hdrplenoxels.eval.registration import model_agreement
from hdrplenoxels.process import sfm
from hdrplenoxels.process.photos import Photo

AS_TAKEN, EQUALISED = "as-taken", "equalised"
GLOBAL, INCREMENTAL, STRICT_GLOBAL = "global", "incremental", "global-strict"
FOCAL_EXIF, FOCAL_REFINED, FOCAL_SELF = "EXIF, held fixed", "EXIF prior, refined", "self-calibrated"
# Opens a progress display for one mapping; what it yields is called as each image is registered.
Progress = Callable[[], AbstractContextManager[Callable[[], None]]]


@dataclass
class Attempt:
    """One mapping of the whole capture, from one set of features."""

    features: str  # AS_TAKEN or EQUALISED
    mapper: str  # GLOBAL, INCREMENTAL or STRICT_GLOBAL
    names: list[str]  # every photo of the capture
    registered: list[str]  # the photos the largest model holds
    reprojection_error_px: float
    points: int
    focal_px: list[float] = field(default_factory=list)  # the model's cameras' focal lengths
    focal_source: str = ""  # FOCAL_EXIF, FOCAL_REFINED or FOCAL_SELF
    focal_uncertainty: list[float] = field(default_factory=list)  # fitted: sd / focal, per camera
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
            "mapper": self.mapper,
            "registered": len(self.registered),
            "unregistered": self.unregistered,
            "mean_reprojection_error_px": round(self.reprojection_error_px, 3),
            "points": self.points,
            "focal_px": [round(f, 1) for f in self.focal_px],
            "focal_source": self.focal_source,
            "focal_uncertainty": [round(u, 4) if u != float("inf") else None for u in self.focal_uncertainty],
            "seconds": {k: round(v, 2) for k, v in self.seconds.items()},
        }


def better(a: Attempt, b: Attempt) -> Attempt:
    """More registered photos wins; on a tie, the lower reprojection error."""
    key_a = (len(a.registered), -a.reprojection_error_px)
    key_b = (len(b.registered), -b.reprojection_error_px)
    return b if key_b > key_a else a


def agree(a: Attempt, b: Attempt, cfg: sfm.SfmConfig) -> bool:
    """Whether two models place their common photos' cameras alike (`SfmConfig.max_disagreement_*`);
    under 3 common photos there is nothing to compare, and they count as agreeing."""
    if a.rec is None or b.rec is None:
        return True
    found = model_agreement(sfm.camera_poses(a.rec), sfm.camera_poses(b.rec))
    return found is None or (
        found.rotation_deg_max <= cfg.max_disagreement_deg
        and found.position_max <= cfg.max_disagreement_position
    )


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


def features_and_matches(
    features: str, photos: list[Photo], staged: Path, folder: Path, cfg: sfm.SfmConfig, matcher: str
) -> tuple[Path, Path, dict[str, float]]:
    """SIFT features of `features` copies of the photos and their verified matches, under `folder`:
    (database, the images the features came from, seconds of each stage)."""
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
    sfm.match(database, matcher, cfg, [p.name for p in photos])
    seconds["matching"] = time.perf_counter() - t0
    return database, images, seconds


def focal_hold(database: Path, cfg: sfm.SfmConfig) -> tuple[bool, str]:
    """Whether mapping holds the cameras' focal lengths, and their source: the EXIF focal, held where
    every camera has one and `cfg.hold_exif_focal`, else refined from it; without one, self-calibrated."""
    priors = sfm.focal_priors(database)
    exif = bool(priors) and all(p is not None for p in priors)
    hold = cfg.hold_exif_focal and exif
    return hold, FOCAL_EXIF if hold else (FOCAL_REFINED if exif else FOCAL_SELF)


def attempt(
    features: str,
    mapper: str,
    photos: list[Photo],
    prepared: tuple[Path, Path, dict[str, float]],
    folder: Path,
    cfg: sfm.SfmConfig,
    log: Callable[[str], None],
    progress: Progress,
) -> Attempt:
    """One mapping by `mapper` of the `prepared` database (`features_and_matches`) into `folder`. A
    focal fitted from the EXIF one that the capture does not fix (`SfmConfig.max_focal_uncertainty`) is
    mapped again with the EXIF focal held."""
    database, images, prep_seconds = prepared
    hold, source = focal_hold(database, cfg)
    result = _map(features, mapper, photos, database, images, folder, cfg, hold, source, progress)
    result.seconds = prep_seconds | result.seconds
    if source == FOCAL_REFINED and result.rec is not None:
        result.focal_uncertainty = sfm.focal_uncertainties(result.rec)
        if max(result.focal_uncertainty) > cfg.max_focal_uncertainty:
            _log(result, log)
            log(
                f"      the photos do not fix the focal (sd {max(result.focal_uncertainty):.0%} of it): "
                "mapped again with the EXIF focal held"
            )
            held = _map(features, mapper, photos, database, images, folder.with_name(folder.name + "-held"),
                        cfg, True, FOCAL_EXIF, progress)  # fmt: skip
            held.seconds["mapping"] += result.seconds["mapping"]
            held.seconds = prep_seconds | held.seconds
            held.focal_uncertainty = result.focal_uncertainty
            result = held
    _log(result, log)
    return result


def _map(
    features: str,
    mapper: str,
    photos: list[Photo],
    database: Path,
    images: Path,
    folder: Path,
    cfg: sfm.SfmConfig,
    hold: bool,
    source: str,
    progress: Progress,
) -> Attempt:
    """One mapping, its model summed up (no focal uncertainty yet)."""
    names = [p.name for p in photos]
    t0 = time.perf_counter()
    strict = cfg.strict_min_matches if mapper == STRICT_GLOBAL else None
    with progress() as on_image:
        rec, model_dir = sfm.reconstruct(
            database, images, folder, cfg, on_image, GLOBAL if strict else mapper, hold, strict
        )
    seconds = {"mapping": time.perf_counter() - t0}
    if rec is None:
        return Attempt(features, mapper, names, [], 0.0, 0, [], source, seconds=seconds)
    registered = sorted(im.name for im in rec.images.values() if im.has_pose)
    error = float(rec.compute_mean_reprojection_error())
    focals, points = sfm.model_focals(rec), int(rec.num_points3D())
    return Attempt(
        features, mapper, names, registered, error, points, focals, source, [], seconds, model_dir, rec
    )


def _log(result: Attempt, log: Callable[[str], None]) -> None:
    focal = ", ".join(f"{f:.0f}" for f in result.focal_px) or "-"
    seconds = ", ".join(f"{k} {v:.1f} s" for k, v in result.seconds.items())
    log(
        f"      {result.features}, {result.mapper} mapping: {len(result.registered)} of "
        f"{len(result.names)} registered, {result.reprojection_error_px:.2f} px, focal {focal} px "
        f"({result.focal_source}; {seconds})"
    )


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
    chosen: Attempt | None = None
    for features in order:
        prepared = features_and_matches(features, photos, staged, colmap / features, cfg, matcher)

        def mapped(mapper: str, features: str = features, prepared: tuple = prepared) -> Attempt:
            """One `attempt` of `mapper` on these features, added to `tried`; the first mapping of a set of
            features carries the seconds of its features and matching, the later ones reuse them."""
            first = all(t.features != features for t in tried)
            made = prepared if first else (*prepared[:2], {})
            folder = colmap / features / f"sparse-{mapper}"
            tried.append(attempt(features, mapper, photos, made, folder, cfg, log, progress))
            return tried[-1]

        here = mapped(cfg.mapper) if cfg.mapper != "auto" else _vote(mapped, cfg, log)
        chosen = here if chosen is None else better(chosen, here)
        if len(chosen.registered) >= cfg.retry_below * len(photos):
            break
    assert chosen is not None
    if len(tried) > 1:
        log(f"      kept the {chosen.mapper} model from the photos {chosen.features.replace('-', ' ')}")
    return chosen, tried


def _vote(mapped: Callable[[str], Attempt], cfg: sfm.SfmConfig, log: Callable[[str], None]) -> Attempt:
    """`auto`'s model from one set of features: global and incremental mapping, and where they disagree
    a strict global mapping to decide (see the module docstring)."""
    first, second = mapped(GLOBAL), mapped(INCREMENTAL)
    if agree(first, second, cfg):
        return better(first, second)
    log("      the two models disagree, so one is wrong: a global mapping of strong pairs decides")
    third = mapped(STRICT_GLOBAL)
    for other in (first, second):
        if agree(other, third, cfg):
            return better(other, third)
    log(
        "      warning: no two of the three models agree; kept the global one. Check the cameras in the "
        "viewer, or force --mapper"
    )
    return first
