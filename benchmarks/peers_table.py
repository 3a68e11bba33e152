"""The peers table: ours and gsplat trained on the same capture kits on one GPU, one run after another,
each scored on the right halves of the kit's test views (JOURNAL.md, "3D Gaussian Splatting on
the same captures").

The kits are `benchmarks/capture_kit.py --reshoots`'s: KITS/NAME/{photos,static,varying}. For each kit,
in ORDER (the fixed camera and the varying one of the issue's targets first, so that a short session
measures what decides them), three runs: ours (`--preset`, tone mapping on, trained in this process as
`hdrplenoxels train` trains it: its seconds from the trainer's construction to its model saved), gsplat
at its default schedule (`peers.py`), and gsplat at ours' seconds (its schedule compressed by
`--steps-scaler` to the steps its default run made in that time). gsplat learns its exposure
compensation on the `varying` kits only, as people run it on such photos. `results.json` and
`results.md` are rewritten after every run, a failed run is a row with its error, no run starts past
`--deadline`, and `--results` continues an earlier session's file (rows of another preset or
configuration are run again).

Usage: python benchmarks/peers_table.py --kits KITS --out DIR [--preset balanced] [--results F]
       [--captures ...] [--sets ...] [--methods ...] [--deadline S] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import peers  # first: it applies the process settings before torch loads

# isort: split
import torch  # noqa: E402
from gpu_preset import config_digest  # noqa: E402
from real_captures import contact_sheet  # noqa: E402

from hdrplenoxels.core.settings import apply_overrides  # noqa: E402
from hdrplenoxels.data import load_scene  # noqa: E402
from hdrplenoxels.eval.evaluate import PROTOCOLS, evaluate  # noqa: E402
from hdrplenoxels.train.presets import preset  # noqa: E402
from hdrplenoxels.train.run_folder import LOG_FILE  # noqa: E402
from hdrplenoxels.train.trainer import Trainer  # noqa: E402

SETS = ("photos", "static", "varying")
CAPTURES = ("kermit", "asclepius", "brickstamp", "freiburg_office")
# kermit's photos are the one capture of a fixed camera; each static re-shoot is one too, each varying
# re-shoot the other target; the photos as taken (auto exposure) come last.
ORDER = [("kermit", "photos")] + [(c, s) for s in ("static", "varying") for c in CAPTURES[1:]]
ORDER += [("kermit", "static"), ("kermit", "varying")] + [(c, "photos") for c in CAPTURES[1:]]
METHODS = ("ours", "gsplat", "gsplat-same-time")


def ours_config(name: str, overrides: list[str], device: str):
    cfg = apply_overrides(preset(name), overrides)
    cfg.tonemap.enabled = True
    cfg.device = device
    return cfg


def run_ours(kit: Path, cfg, work: Path, sheet: Path, lpips: bool = True) -> dict[str, Any]:
    """Ours on `kit`, trained here: seconds from the trainer's construction to its model saved (the
    steps' share beside them), the test views' right halves, the peak GPU memory, and the contact sheet
    `benchmarks/real_captures.py` draws."""
    scene = load_scene(kit)
    cuda = cfg.device.startswith("cuda") or (cfg.device == "auto" and torch.cuda.is_available())
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    model = Trainer(scene, cfg, work, overwrite=True).run(progress=False)
    if cuda:
        torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    steps_seconds = json.loads((work / LOG_FILE).read_text().splitlines()[-1])["seconds"]
    result = evaluate(model, scene, lpips=lpips)
    contact_sheet(model, scene, sheet, f"{kit.parent.name} {kit.name} ours")
    row = {k: result[k] for k in ("psnr", "ssim", "lpips_vgg") if k in result}
    row |= {"seconds": seconds, "steps_seconds": steps_seconds, "steps": model.step}
    row |= {"test_views": result["num_test_views"], "voxels": model.grid.num_voxels}
    if cuda:
        row["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return row


def run_gsplat(
    kit: Path, scaler: float, seconds: float | None, appearance: bool, sheet: Path
) -> dict[str, Any]:
    """gsplat on `kit` (`peers.run`): its schedule scaled by `scaler`, stopped at `seconds` if sooner;
    its contact sheet of the same two test views as ours'."""
    row = peers.run(kit, 1, peers.Schedule(scaler), seconds, appearance, sheet)
    return row | {"scaler": scaler, "appearance": appearance}


def same_time_scaler(ours_row: dict, gsplat_row: dict) -> float:
    """The scaler that makes gsplat's schedule as many steps as its default run made in ours' seconds."""
    rate = gsplat_row["steps"] / gsplat_row["seconds"]
    return min(1.0, ours_row["seconds"] * rate / peers.Schedule().steps)


def find(rows: list[dict], failed: bool = False, **match) -> dict | None:
    """The row of `match`; one that failed only with `failed` (a failed run counts as run: it is not
    tried again, as an out-of-memory run would fail again)."""
    return next(
        (r for r in rows if all(r.get(k) == v for k, v in match.items()) and (failed or "error" not in r)),
        None,
    )


def markdown(report: dict) -> str:
    """A row per kit and method."""
    lines = [
        f"Ours (`{report['preset']}`, tone mapping on) and gsplat on {report['gpu']}. {report['protocol']}.",
        "",
    ]
    lines += ["| capture | photos | method | PSNR | SSIM | LPIPS (vgg) | seconds | steps | peak GPU MB |"]
    lines += ["|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        head = f"| {r['capture']} | {r['set']} | {r['method']} |"
        if "error" in r:
            lines.append(f"{head} failed: {r['error']} | | | | | |")
            continue
        lpips = f"{r['lpips_vgg']:.3f}" if "lpips_vgg" in r else "–"
        memory = f"{r['peak_gpu_mb']:.0f}" if "peak_gpu_mb" in r else "–"
        scores = f"{r['psnr']:.2f} | {r['ssim']:.3f} | {lpips}"
        lines.append(f"{head} {scores} | {r['seconds']:.0f} | {r['steps']} | {memory} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--kits", type=Path, required=True, help="capture_kit.py --reshoots folders: KITS/NAME/SET"
    )
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--preset", default="balanced", help="ours' preset")
    ap.add_argument(
        "--set", dest="overrides", action="append", default=[], help="ours' train --set, repeatable"
    )
    ap.add_argument("--results", type=Path, help="an earlier session's results.json to continue")
    ap.add_argument("--captures", nargs="+", default=list(CAPTURES))
    ap.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument(
        "--deadline", type=float, default=float("inf"), help="start no run after this many seconds"
    )
    ap.add_argument("--device", default="auto")
    ap.add_argument("--no-lpips", action="store_true", help="score ours without LPIPS")
    ap.add_argument(
        "--work", type=Path, default=Path("/tmp/peers-table"), help="ours' run folders (not brought back)"
    )
    args = ap.parse_args(argv)
    begun = time.perf_counter()
    cuda = torch.cuda.is_available()
    methods = [m for m in args.methods if cuda or m == "ours"]
    if methods != args.methods:
        print("peers_table: no CUDA device here; gsplat's kernels are CUDA only, so only ours runs")
    cfg = ours_config(args.preset, args.overrides, args.device)
    key = config_digest(cfg)  # a row timed from ours at another configuration is run again
    rows = json.loads(args.results.read_text())["rows"] if args.results else []
    kept = [r for r in rows if r["method"] == "gsplat" or r.get("config_key") == key]
    if len(kept) < len(rows):
        print(f"{len(rows) - len(kept)} rows timed from ours' other configuration dropped: run again")
    rows = kept
    report = {"preset": args.preset, "protocol": PROTOCOLS["right-half"], "rows": rows}
    report["gpu"] = torch.cuda.get_device_name(0) if cuda else "CPU"
    args.out.mkdir(parents=True, exist_ok=True)
    for capture, photos in ORDER:
        kit = args.kits / capture / photos
        if capture not in args.captures or photos not in args.sets or not (kit / "transforms.json").exists():
            continue
        for method in methods:
            same = {"capture": capture, "set": photos, "method": method}
            if method != "gsplat":
                same["config_key"] = key  # gsplat's own runs do not depend on ours
            if find(rows, failed=True, **same):
                continue
            if time.perf_counter() - begun > args.deadline:
                print(f"deadline: {capture} {photos} {method} and the rest not started")
                return 0
            sheet = args.out / "sheets" / f"{capture}-{photos}-{method}.png"
            try:
                if method == "ours":
                    row = run_ours(kit, cfg, args.work / f"{capture}-{photos}", sheet, not args.no_lpips)
                elif method == "gsplat":
                    row = run_gsplat(kit, 1.0, None, photos == "varying", sheet)
                else:
                    ours = find(rows, capture=capture, set=photos, method="ours", config_key=key)
                    default = find(rows, capture=capture, set=photos, method="gsplat")
                    if ours is None or default is None:
                        continue  # needs both runs it is timed from
                    scaler = same_time_scaler(ours, default)
                    row = run_gsplat(kit, scaler, ours["seconds"], photos == "varying", sheet)
            except (RuntimeError, torch.cuda.OutOfMemoryError) as err:  # a failed run is a row
                row = {"error": str(err).splitlines()[0][:200]}
            rows.append(same | row)
            if cuda:
                torch.cuda.empty_cache()  # the next run's peak is its own
            print(json.dumps(rows[-1]), flush=True)
            (args.out / "results.json").write_text(json.dumps(report, indent=2))
            (args.out / "results.md").write_text(markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
