"""Registration of a photo folder under each choice `process` can make (docs/performance.md,
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

Usage: python benchmarks/registration.py PHOTOS [--features as-taken equalised] [--affine on off]
       [--matchers exhaustive sequential] [--mappers global incremental global-strict] [--focal exif free]
       [--seeds 0 1 2] [--max-image-size 3200] [--truth SYNTH_CAPTURE] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from hdrplenoxels.data import load_scene
from hdrplenoxels.eval.registration import cameras_by_view, registration_errors
from hdrplenoxels.process import sfm
from hdrplenoxels.process.photos import find_photos, stage_photos
from hdrplenoxels.process.registration import (
    EQUALISED,
    GLOBAL,
    INCREMENTAL,
    STRICT_GLOBAL,
    camera_groups,
    focal_hold,
    write_equalised,
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("photos", type=Path)
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
                    for mapper, focal in ((m, f) for m in args.mappers for f in args.focal):
                        hold, _ = focal_hold(database, cfg) if focal == "exif" else (False, "")
                        t0 = time.perf_counter()
                        out = run / f"sparse-{mapper}-{focal}"
                        strict = cfg.strict_min_matches if mapper == STRICT_GLOBAL else None
                        kind = GLOBAL if strict else mapper
                        rec, _ = sfm.reconstruct(database, images, out, cfg, lambda: None, kind, hold, strict)
                        map_s = time.perf_counter() - t0
                        row = {
                            "features": features,
                            "affine": affine,
                            "matcher": matcher,
                            "seed": seed,
                            "mapper": mapper,
                            "focal": focal if hold or focal == "free" else "free (no EXIF focal)",
                            "of": len(names),
                            "seconds": [round(extract_s, 1), round(match_s, 1), round(map_s, 1)],
                        } | model_facts(rec, names, truth)
                        rows.append(row)
                        print_row(row)
    if args.json:
        args.json.write_text(json.dumps({"photos": str(args.photos), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
