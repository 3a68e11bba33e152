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
agree, the global model, with a warning.

Where every photo's EXIF gives a focal length, the kept model is bundle-adjusted again twice, with the
focal free and with the EXIF focal held, on the same observations of the same registered photos, and
the fitted focal is kept only where it lowers the mean reprojection error by more than
`SfmConfig.min_focal_gain` (`weigh_focal`). A walk straight ahead barely constrains its camera's focal,
and the fit then drifts along a flat valley of the error that the bundle adjustment's covariance at its
bottom does not show (a real street walk: 719 px fitted, 1 035 px in EXIF, at the same error); a photo's
EXIF can also be wrong (a phone's 35 mm equivalent describes its whole sensor, not a 16:9 crop of it),
and there the fit wins by far. Mapping again with the focal held would not do: a mapper drops the
observations a wrong focal cannot explain and then reports a lower error over those left (asclepius:
1.24 px held at its wrong EXIF focal, 1.44 px fitted). Measurements: JOURNAL.md,
"Registration of real captures".
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field, replace
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
    every camera has one and `cfg.focal` is "exif", else refined from it; without one, self-calibrated."""
    priors = sfm.focal_priors(database)
    exif = bool(priors) and all(p is not None for p in priors)
    hold = cfg.focal == "exif" and exif
    return hold, FOCAL_EXIF if hold else (FOCAL_REFINED if exif else FOCAL_SELF)


@dataclass
class FocalChoice:
    """What `weigh_focal` compared, and what it kept."""

    kept: str  # FOCAL_EXIF or FOCAL_REFINED
    reason: str
    exif_px: list[float]
    fitted_px: list[float]
    exif_error_px: float  # mean reprojection errors, the same observations adjusted both ways
    fitted_error_px: float
    seconds: float

    def summary(self) -> dict:
        """What transforms.json records of the choice."""
        return {
            "kept": self.kept,
            "reason": self.reason,
            "exif_px": [round(f, 1) for f in self.exif_px],
            "fitted_px": [round(f, 1) for f in self.fitted_px],
            "exif_error_px": round(self.exif_error_px, 4),
            "fitted_error_px": round(self.fitted_error_px, 4),
            "seconds": round(self.seconds, 2),
        }


def fit_wins(fitted_error: float, exif_error: float, min_gain: float) -> tuple[bool, str]:
    """Whether a fitted focal explains the photos clearly better than the EXIF one: its mean reprojection
    error lower by more than `min_gain` (a fraction). One free focal a camera always lowers the error a
    little; a focal the photos really fix wins by more. And why, in words."""
    gain = 1.0 - fitted_error / exif_error if exif_error > 0 else 0.0
    wins = gain > min_gain
    found = (
        f"lowers the mean reprojection error by {'' if wins else 'only '}{gain:.1%}"
        if gain > 0
        else f"explains the photos no better ({abs(gain):.1%} higher error)"
    )
    return wins, f"the fitted focal {found}, and must win by more than {min_gain:.0%}"


def weigh_focal(
    fitted: Attempt, priors: list[float], folder: Path, cfg: sfm.SfmConfig
) -> tuple[Attempt, FocalChoice]:
    """`fitted` (a model whose focal was fitted from the EXIF `priors`), or the same model adjusted with
    the EXIF focal held, written to `folder`: the fitted one only where `fit_wins` (module docstring)."""
    t0 = time.perf_counter()
    fitted_error, held_rec, exif_error = sfm.adjusted_both_ways(fitted.rec, priors)
    wins, reason = fit_wins(fitted_error, exif_error, cfg.min_focal_gain)
    chosen = fitted
    if not wins:
        folder.mkdir(parents=True, exist_ok=True)
        held_rec.write(folder)
        chosen = replace(
            fitted,
            reprojection_error_px=float(held_rec.compute_mean_reprojection_error()),
            points=int(held_rec.num_points3D()),
            focal_px=sfm.model_focals(held_rec),
            focal_source=FOCAL_EXIF,
            model_dir=folder,
            rec=held_rec,
        )
    choice = FocalChoice(
        FOCAL_REFINED if wins else FOCAL_EXIF,
        reason,
        list(priors),
        fitted.focal_px,
        exif_error,
        fitted_error,
        time.perf_counter() - t0,
    )
    return chosen, choice


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
    """One mapping by `mapper` of the `prepared` database (`features_and_matches`) into `folder`, the
    focal held as `cfg` says (`focal_hold`)."""
    database, images, prep_seconds = prepared
    hold, source = focal_hold(database, cfg)
    result = _map(features, mapper, photos, database, images, folder, cfg, hold, source, progress)
    result.seconds = prep_seconds | result.seconds
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
    """One mapping, its model summed up."""
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
        features, mapper, names, registered, error, points, focals, source, seconds, model_dir, rec
    )


def _log(result: Attempt, log: Callable[[str], None]) -> None:
    focal = _px(result.focal_px)
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
) -> tuple[Attempt, list[Attempt], FocalChoice | None]:
    """The chosen attempt, every attempt made, in order, and the focal choice where one was made (see
    the module docstring)."""
    order = [AS_TAKEN, EQUALISED] if cfg.features == "auto" else [cfg.features]
    tried: list[Attempt] = []
    prepared: dict[str, tuple[Path, Path, dict[str, float]]] = {}
    chosen: Attempt | None = None

    def mapped(features: str, mapper: str) -> Attempt:
        """One `attempt` of `mapper` on these features, added to `tried`; the first mapping of a set of
        features carries the seconds of its features and matching, the later ones reuse them."""
        first = all(t.features != features for t in tried)
        made = prepared[features] if first else (*prepared[features][:2], {})
        folder = colmap / features / f"sparse-{mapper}"
        tried.append(attempt(features, mapper, photos, made, folder, cfg, log, progress))
        return tried[-1]

    for features in order:
        prepared[features] = features_and_matches(features, photos, staged, colmap / features, cfg, matcher)
        here = (
            mapped(features, cfg.mapper)
            if cfg.mapper != "auto"
            else _vote(lambda mapper, f=features: mapped(f, mapper), cfg, log)
        )
        chosen = here if chosen is None else better(chosen, here)
        if len(chosen.registered) >= cfg.retry_below * len(photos):
            break
    assert chosen is not None
    if len(tried) > 1:
        log(f"      kept the {chosen.mapper} model from the photos {chosen.features.replace('-', ' ')}")
    choice = None
    if cfg.focal == "auto" and chosen.focal_source == FOCAL_REFINED and chosen.rec is not None:
        priors = sfm.focal_priors(prepared[chosen.features][0])
        folder = colmap / chosen.features / f"sparse-{chosen.mapper}-exif"
        chosen, choice = weigh_focal(chosen, priors, folder, cfg)
        kept = "fitted" if choice.kept == FOCAL_REFINED else "EXIF"
        log(
            f"      focal: kept the {kept} one, {_px(chosen.focal_px)} px; adjusted both ways, the EXIF "
            f"{_px(choice.exif_px)} px gives {choice.exif_error_px:.3f} px of error, the fitted "
            f"{_px(choice.fitted_px)} px {choice.fitted_error_px:.3f} px: {choice.reason}"
        )
    return chosen, tried, choice


def _px(focals: list[float]) -> str:
    return ", ".join(f"{f:.0f}" for f in focals) or "-"


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
