"""Registration of a photo folder under each choice `process` can make (docs/performance.md,
"Registration of real captures").

The photos are staged as `process` stages them. For each feature source (the photos as taken,
histogram-equalised copies) and affine shape (on, off) features are extracted once; then for each
matcher (exhaustive; sequential in file-name order with loop closure) and seed (of the verification's
RANSAC and of the mapper) a copy of that database is matched and mapped, with `process`'s own functions
and settings. Prints one Markdown row per variant: registered photos, reprojection error, points and the
seconds of extraction, matching and mapping; `--json` also writes them, with the unregistered names.

Usage: python benchmarks/registration.py PHOTOS [--features as-taken equalised] [--affine on off]
       [--matchers exhaustive sequential] [--seeds 0 1 2] [--max-image-size 3200] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from hdrplenoxels.process import sfm
from hdrplenoxels.process.photos import find_photos, stage_photos
from hdrplenoxels.process.registration import EQUALISED, camera_groups, write_equalised


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("photos", type=Path)
    parser.add_argument("--features", nargs="+", default=["as-taken", EQUALISED])
    parser.add_argument("--affine", nargs="+", default=["on", "off"])
    parser.add_argument("--matchers", nargs="+", default=["exhaustive", "sequential"])
    parser.add_argument("--max-image-size", type=int, default=sfm.SfmConfig.max_image_size)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="matching and mapping seeds")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    sfm.quiet_colmap()
    rows = []
    print("| features | affine | matcher | seed | registered | px | points | extract s | match s | map s |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|")
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
                    t0 = time.perf_counter()
                    rec, _ = sfm.reconstruct(database, images, run / "sparse", cfg, lambda: None)
                    map_s = time.perf_counter() - t0
                    registered = [] if rec is None else [im.name for im in rec.images.values() if im.has_pose]
                    row = {
                        "features": features,
                        "affine": affine,
                        "matcher": matcher,
                        "seed": seed,
                        "registered": len(registered),
                        "of": len(names),
                        "unregistered": sorted(set(names) - set(registered)),
                        "error_px": 0.0 if rec is None else float(rec.compute_mean_reprojection_error()),
                        "points": 0 if rec is None else int(rec.num_points3D()),
                        "seconds": [round(extract_s, 1), round(match_s, 1), round(map_s, 1)],
                    }
                    rows.append(row)
                    print(
                        f"| {features} | {affine} | {matcher} | {seed} | {row['registered']}/{row['of']} | "
                        f"{row['error_px']:.2f} | {row['points']} | {extract_s:.1f} | {match_s:.1f} | "
                        f"{map_s:.1f} |",
                        flush=True,
                    )
    if args.json:
        args.json.write_text(json.dumps({"photos": str(args.photos), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
