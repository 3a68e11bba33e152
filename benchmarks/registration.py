"""Registration of a photo folder under each choice `process` can make (JOURNAL.md,
"Registration of real captures").

The photos are staged as `process` stages them. For each feature source (the photos as taken,
histogram-equalised copies) and affine shape (on, off) features are extracted once; then for each
matcher (exhaustive; sequential in file-name order with loop closure) and seed (of the verification's
RANSAC and of the mapper) a copy of that database is matched, and mapped by each mapper (global,
incremental, and `global-strict`, the global mapping of strong pairs that decides where those two
disagree) with the EXIF focal held (where every camera has one) or fitted, with `process`'s own
functions and settings. Prints one Markdown row per variant: registered photos, reprojection error,
points, the focal found and the seconds of extraction, matching and mapping; with `--truth` (a
synthesized capture of the same views, e.g. `synth street OUT`'s `OUT/auto`), also the rotation,
position and focal errors against the true cameras after a similarity alignment
(`eval.registration`). `--json` also writes them, with the unregistered names.

Where the focal is fitted from an EXIF one, a further row per mapping says which `process`'s rule keeps
(`process.registration.weigh_focal`: the fitted model adjusted again with the focal free and with the
EXIF focal held, on the same observations, and the fitted focal kept only where it lowers the mean
reprojection error by more than `SfmConfig.min_focal_gain`), with both errors.

`--synthetic OUT` instead renders the two captures the focal rule is tested on (JOURNAL.md, "The
EXIF focal or a fitted one") into OUT and runs the whole `process` on each with each `--focal` setting
(auto, exif, fit): a phone walk round a street corner (`synth corner`, 29 views, auto exposure, shot
noise, JPEG) whose EXIF states the true lens, and the arc round a room (`synth gallery`, 20 views) whose
EXIF states a lens 20 % long; one row per run with the errors against the truth. Then the walk's kept
model is moved to a focal 31 % or 20 % short or 30 % long and adjusted there with it held (Cauchy
errors, as a mapper's robust adjustment settles a fit that drifted along a flat valley; every
observation kept), and the rule's two adjustments are made from there with squared (the rule's own),
soft-L1 and Cauchy errors: what carries the held adjustment back to the EXIF focal's minimum.

Usage: python benchmarks/registration.py PHOTOS [--features as-taken equalised] [--affine on off]
       [--matchers exhaustive sequential] [--mappers global incremental global-strict] [--focal exif free]
       [--seeds 0 1 2] [--max-image-size 3200] [--truth SYNTH_CAPTURE] [--json OUT.json]
       python benchmarks/registration.py --synthetic OUT [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from hdrplenoxels.data import load_scene
from hdrplenoxels.eval.registration import cameras_by_view, registration_errors
from hdrplenoxels.process import process_photos, sfm
from hdrplenoxels.process.photos import find_photos, stage_photos
from hdrplenoxels.process.registration import (
    EQUALISED,
    GLOBAL,
    INCREMENTAL,
    STRICT_GLOBAL,
    camera_groups,
    fit_wins,
    focal_hold,
    write_equalised,
)
from hdrplenoxels.synth.generate import SynthOptions, synthesize
from hdrplenoxels.synth.photos import write_photos
from hdrplenoxels.synth.pipeline import PipelineConfig

LOSSES = ("TRIVIAL", "SOFT_L1", "CAUCHY")  # the rule's adjustments: its own loss first
# (name, scene, views, phone noise, capture, the EXIF lens's error)
SYNTHETIC = (
    ("corner walk, EXIF right", "corner", 29, True, "auto", 0.0),
    ("gallery arc, EXIF 20 % long", "gallery", 20, False, "static", 0.2),
)


def model_facts(rec, names: list[str], truth: tuple[dict, dict] | None) -> dict:
    """What a row says of a mapping's largest model (`rec`, None if there is none)."""
    registered = [] if rec is None else [im.name for im in rec.images.values() if im.has_pose]
    facts = {
        "registered": len(registered),
        "unregistered": sorted(set(names) - set(registered)),
        "error_px": 0.0 if rec is None else float(rec.compute_mean_reprojection_error()),
        "points": 0 if rec is None else int(rec.num_points3D()),
        "focal_px": [] if rec is None else [round(f, 1) for f in sfm.model_focals(rec)],
    }
    if truth is not None and len(registered) >= 3:
        found_c2w = {Path(name).stem: c2w for name, c2w in sfm.camera_poses(rec).items()}
        found_focal = {
            Path(im.name).stem: float(rec.cameras[im.camera_id].mean_focal_length())
            for im in rec.images.values()
            if im.has_pose
        }
        facts["errors"] = registration_errors(found_c2w, found_focal, *truth).to_dict()
    return facts


def print_row(row: dict) -> None:
    e = row.get("errors")
    errors = (
        f"{e['rotation_deg_median']:.2f} / {e['rotation_deg_max']:.2f} | {100 * e['position_max']:.2f} | "
        f"{100 * e['focal_max']:.2f}"
        if e
        else "- | - | -"
    )
    extract_s, match_s, map_s = row["seconds"]
    print(
        f"| {row['features']} | {row['affine']} | {row['matcher']} | {row['seed']} | {row['mapper']} | "
        f"{row['focal']} | {row['registered']}/{row['of']} | {row['error_px']:.2f} | {row['points']} | "
        f"{', '.join(f'{f:.0f}' for f in row['focal_px']) or '-'} | {errors} | {extract_s:.1f} | "
        f"{match_s:.1f} | {map_s:.1f} |",
        flush=True,
    )


def map_both(
    database: Path,
    images: Path,
    cfg: sfm.SfmConfig,
    mapper: str,
    focals: list[str],
    names: list[str],
    truth: tuple[dict, dict] | None,
) -> dict[str, dict]:
    """One mapping of the matched `database` by `mapper` per focal setting ("exif": held where every
    camera has one; "free": fitted), summed up by `model_facts`, by setting; and the focal `process`
    keeps of the fitted one ("rule")."""
    made = {}
    for focal in focals:
        hold, _ = focal_hold(database, replace(cfg, focal="exif")) if focal == "exif" else (False, "")
        t0 = time.perf_counter()
        strict = cfg.strict_min_matches if mapper == STRICT_GLOBAL else None
        out = database.parent / f"sparse-{mapper}-{focal}"
        rec, _ = sfm.reconstruct(
            database, images, out, cfg, lambda: None, GLOBAL if strict else mapper, hold, strict
        )
        made[focal] = {
            "focal": focal if hold or focal == "free" else "free (no EXIF focal)",
            "map_s": round(time.perf_counter() - t0, 1),
        } | model_facts(rec, names, truth)
        priors = sfm.focal_priors(database)
        if focal == "free" and rec is not None and priors and all(p is not None for p in priors):
            made |= focal_rule_rows(made[focal], rec, priors)
    return made


def focal_rule_rows(free: dict, rec, priors: list[float]) -> dict[str, dict]:
    """Rows saying which focal `process` keeps for a mapping with the focal fitted (`free`, its row, and
    `rec`, its model) from the EXIF `priors`, with its two adjustments made with each loss (the rule's
    own, squared errors, then soft-L1 and Cauchy)."""
    rows = {}
    for loss in LOSSES:
        fitted_error, held, exif_error = sfm.adjusted_both_ways(rec, priors, loss)
        wins, reason = fit_wins(fitted_error, exif_error, sfm.SfmConfig.min_focal_gain)
        kept = "fitted" if wins else "EXIF"
        rows[f"rule {loss}"] = free | {
            "focal": f"rule, {loss.lower()}: {kept} ({exif_error:.3f} px EXIF, {fitted_error:.3f} px fitted)",
            "focal_px": free["focal_px"] if wins else sfm.model_focals(held),
        }
    return rows


def drifted(run: Path) -> list[dict]:
    """The rule's two adjustments from the kept model of a `process` run (`run/colmap`) moved to drifted
    focals first (module docstring), with each loss."""
    import pycolmap

    kept = json.loads((run / "transforms.json").read_text())["process"]
    folder = run / "colmap" / kept["features"] / f"sparse-{kept['mapper']}"
    priors = sfm.focal_priors(run / "colmap" / kept["features"] / "database.db")
    models = [pycolmap.Reconstruction(p) for p in folder.iterdir() if p.is_dir()]
    model = max(models, key=lambda m: m.num_reg_images())  # the one `process` kept
    print("\n| start (x EXIF focal) | loss | error px, focal free | error px, EXIF focal held |")
    print("|---:|---|---:|---:|")
    rows = []
    for scale in (0.69, 0.8, 1.3):
        start = pycolmap.Reconstruction(model)
        sfm.set_focals(start, [scale * p for p in priors])
        sfm.bundle_adjust(start, True, "CAUCHY")
        for loss in LOSSES:
            free_error, _, held_error = sfm.adjusted_both_ways(start, priors, loss)
            rows.append({"scale": scale, "loss": loss, "free_px": free_error, "held_px": held_error})
            print(f"| {scale} | {loss.lower()} | {free_error:.4f} | {held_error:.4f} |", flush=True)
    return rows


def synthetic(out: Path) -> list[dict]:
    """The whole `process` on the two synthetic captures of the focal rule (module docstring)."""
    print(
        "| capture | --focal | kept | registered | rotation ° (median / max) | position % | focal % | "
        "EXIF / fitted px | error px (EXIF / fitted) | register s |"
    )
    print("|---|---|---|---:|---:|---:|---:|---|---|---:|")
    rows = []
    for name, scene, views, noise, capture, focal_error in SYNTHETIC:
        root = out / scene
        if not (root / "synth.json").exists():
            synthesize(scene, root, SynthOptions(n_views=views), PipelineConfig(noise=noise), auto=True)
        photos = write_photos(root / capture, root / f"photos{focal_error:+.2f}", focal_error=focal_error)
        truth = cameras_by_view(load_scene(root / capture))
        for focal in ("auto", "exif", "fit"):
            run = root / f"process-{focal_error:+.2f}-{focal}"
            shutil.rmtree(run, ignore_errors=True)
            result = process_photos(photos, run, sfm.SfmConfig(focal=focal), log=lambda s: None)
            e = registration_errors(*cameras_by_view(load_scene(run)), *truth)
            choice = result.focal_choice or {}
            row = {"capture": name, "focal": focal, "kept": result.focal_source, "errors": e.to_dict()}
            row |= {"focal_px": result.focal_px, "choice": choice, "seconds": result.stage_seconds}
            rows.append(row)
            pair = (
                f"{choice['exif_px'][0]:.0f} / {choice['fitted_px'][0]:.0f} | "
                f"{choice['exif_error_px']:.3f} / {choice['fitted_error_px']:.3f}"
                if choice
                else f"{result.focal_px[0]:.0f} | {result.reprojection_error_px:.3f}"
            )
            print(
                f"| {name} | {focal} | {result.focal_source} | {e.registered}/{e.of} | "
                f"{e.rotation_deg_median:.2f} / {e.rotation_deg_max:.2f} | {100 * e.position_max:.2f} | "
                f"{100 * e.focal_max:.2f} | {pair} | {result.stage_seconds['register']:.1f} |",
                flush=True,
            )
    return rows + drifted(out / "corner" / "process-+0.00-auto")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("photos", type=Path, nargs="?")
    parser.add_argument(
        "--synthetic", type=Path, help="render and process the focal rule's two captures here"
    )
    parser.add_argument("--features", nargs="+", default=["as-taken", EQUALISED])
    parser.add_argument("--affine", nargs="+", default=["on", "off"])
    parser.add_argument("--matchers", nargs="+", default=["exhaustive", "sequential"])
    parser.add_argument("--max-image-size", type=int, default=sfm.SfmConfig.max_image_size)
    parser.add_argument(
        "--mappers", nargs="+", default=[GLOBAL, INCREMENTAL], choices=[GLOBAL, INCREMENTAL, STRICT_GLOBAL]
    )
    parser.add_argument("--focal", nargs="+", default=["exif", "free"], help="hold the EXIF focal, or fit it")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="matching and mapping seeds")
    parser.add_argument("--truth", type=Path, help="a synthesized capture of these views: pose errors")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    sfm.quiet_colmap()
    if args.synthetic:
        rows = synthetic(args.synthetic)
        if args.json:
            args.json.write_text(json.dumps({"synthetic": str(args.synthetic), "rows": rows}, indent=1))
        return
    if args.photos is None:
        parser.error("give PHOTOS or --synthetic OUT")
    rows = []
    truth = None if args.truth is None else cameras_by_view(load_scene(args.truth))
    print(
        "| features | affine | matcher | seed | mapper | focal | registered | px | points | focal px | "
        "rotation ° (median / max) | position % | focal % | extract s | match s | map s |"
    )
    print("|---|---|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory(prefix="registration-") as tmp:
        work = Path(tmp)
        photos = stage_photos(find_photos(args.photos), work / "photos")
        names = [p.name for p in photos]
        for features in args.features:
            images = work / "photos"
            if features == EQUALISED:
                images = work / EQUALISED
                write_equalised(photos, work / "photos", images)
            for affine in args.affine:
                cfg = sfm.SfmConfig(affine_shape=affine == "on", max_image_size=args.max_image_size)
                base = work / f"{features}-{affine}.db"
                t0 = time.perf_counter()
                sfm.extract(base, images, camera_groups(photos), cfg)
                extract_s = time.perf_counter() - t0
                for matcher, seed in ((m, s) for m in args.matchers for s in args.seeds):
                    cfg.seed = seed
                    run = work / f"{features}-{affine}-{matcher}-{seed}"
                    run.mkdir()
                    database = run / "database.db"
                    shutil.copy(base, database)
                    t0 = time.perf_counter()
                    sfm.match(database, matcher, cfg, names)
                    match_s = time.perf_counter() - t0
                    for mapper in args.mappers:
                        made = map_both(database, images, cfg, mapper, args.focal, names, truth)
                        for row in made.values():
                            row |= {"features": features, "affine": affine, "matcher": matcher, "seed": seed}
                            row |= {"mapper": mapper, "of": len(names)}
                            row["seconds"] = [round(extract_s, 1), round(match_s, 1), row["map_s"]]
                        for row in made.values():
                            rows.append(row)
                            print_row(row)
    if args.json:
        args.json.write_text(json.dumps({"photos": str(args.photos), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
