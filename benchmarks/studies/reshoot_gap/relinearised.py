"""How much of ours' gap to a fixed camera on a real re-shoot is the varying photos' information, not the
tone mapper: each varying photo is brought back through its own true camera (the inverse of its response,
white balance and exposure, from the re-shoot's `camera_truth.json`) and captured again by the static
re-shoot's camera, so the photos keep exactly what the varying ones hold (their clipped highlights, their
dark views' coarse shadows) but need no tone mapping. Plain Plenoxels trained on them is what a tone
mapper that learned every camera exactly would give; it is scored on the right halves of the test views
of the static re-shoot, as plain Plenoxels on the static photos is (the left halves train both). Reads and
writes `benchmarks/real_captures.py`'s folders (README beside this script).

Usage: python benchmarks/studies/reshoot_gap/relinearised.py OUT [--captures kermit ...] [--preset fast]
       [--label LABEL] [--json R.json]
  OUT: real_captures.py's --out, holding NAME/{data,static,varying}/ (run it first with the re-shoots)
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # benchmarks/: the real-capture harness

from real_captures import downscale_for, score, train_run  # noqa: E402
from study import study_arguments  # noqa: E402  (beside this script)

from hdrplenoxels.core.atomic import atomic_write_files  # noqa: E402
from hdrplenoxels.synth.pipeline import CRFS, CameraSettings, capture  # noqa: E402


def relinearised(varying: Path, target: Path) -> Path:
    """`varying` with each photo inverted through its true camera and captured by the static one."""
    if (target / "transforms.json").exists():
        return target
    truth = json.loads((varying / "camera_truth.json").read_text())["views"]
    meta = json.loads((varying / "transforms.json").read_text())

    def write(work: Path) -> None:
        (work / "images").mkdir()
        for frame, view in zip(meta["frames"], truth, strict=True):
            photo = np.asarray(Image.open(varying / frame["file_path"]).convert("RGB"), dtype=np.float32)
            linear = CRFS[view["crf"]][1](photo / 255.0) / np.asarray(view["wb_gains"], np.float32)
            static = CameraSettings(crf=view["crf"])  # 0 EV, neutral white balance: the static re-shoot's
            image = capture((linear / 2.0 ** view["ev"]).astype(np.float32), static)
            Image.fromarray(image).save(work / frame["file_path"])
        shutil.copy(varying / "transforms.json", work / "transforms.json")

    return atomic_write_files(target, write)  # `transforms.json`, what marks it done, moved in last


def main() -> None:
    args, names = study_arguments(__doc__.splitlines()[0])
    print("Right halves of the static re-shoot's test views (left halves train); the last step.")
    rows = []
    for name in names:
        root = args.out / name
        data = relinearised(root / "varying", root / "relinearised")
        run = root / args.label / f"{args.preset}-plenoxels-relinearised"
        stats = train_run(data, run, args.preset, False, downscale_for(root / "data"), [])
        sheet = args.out / "sheets" / f"{name}-{args.label}-{args.preset}-plenoxels-relinearised.png"
        stats |= score(run, root / "static", sheet, f"{name} {args.preset} relinearised", False)
        rows.append({"capture": name, "preset": args.preset} | stats)
        print(f"  {name}: {stats['psnr_right']:.2f} dB / {stats['ssim_right']:.3f}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
