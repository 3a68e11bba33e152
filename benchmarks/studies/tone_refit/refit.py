"""The tone refitted after training with the grid frozen: what a trained run's pictures and answers become
when its tone (curve, white balance, exposure, vignetting) is fitted again, on the unweighted error, to its
own renders. Training now ends this way (`tonemap.refit_steps`); this refits runs trained before, or again.

Each view's radiance is rendered once; the fit draws up to 60 000 pixels a view (training views whole, test
views' left halves only, as the protocol trains them) and runs Adam over them at a fixed rate, then makes
each curve monotonic as training does (`ToneMapper.constrain`). It scores the test views' right halves
before and after, and the cameras against their truth: a synthetic scene's (`eval.truth.truth_report`,
with the HDR error) or a real re-shoot's (`reshoot_gap/camera_truth.py`). The refitted model is written
to OUT/model.npz.

Usage: python benchmarks/studies/tone_refit/refit.py RUN OUT [--steps 300] [--lr 1e-3]
  RUN: a run of ours with its model.npz (its photos are read at the run's own downscale)
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.data import load_scene
from hdrplenoxels.data.protocol import left_width
from hdrplenoxels.eval.evaluate import check_same_scene, run_downscale, scored_picture, scored_region
from hdrplenoxels.eval.metrics import psnr
from hdrplenoxels.eval.truth import SynthTruth, truth_report
from hdrplenoxels.geometry.cameras import pixel_grid
from hdrplenoxels.train.model import Model
from hdrplenoxels.train.tone_refit import RefitPixels, refit_tone

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "reshoot_gap"))
from camera_truth import camera_truth  # noqa: E402

PIXELS_PER_VIEW = 60_000


def right_half_psnr(model: Model, radiance: dict, photos: dict) -> list[float]:
    """PSNR of each test view's right half through its own learned tone, as `hdrplenoxels eval` scores it."""
    out = []
    for i in model.test_ids:
        gt = scored_region(photos[i], "right-half")
        out.append(psnr(scored_picture(model, radiance[i], gt, i, "own", "right-half"), gt))
    return out


def fitting_pixels(model: Model, radiance: dict, photos: dict) -> RefitPixels:
    """The pixels the tone is fitted on, up to `PIXELS_PER_VIEW` a view."""
    g = torch.Generator().manual_seed(0)
    parts = []
    for i, rad in radiance.items():
        h, w = rad.shape[:2]
        rows, cols = pixel_grid(h, w)
        keep = torch.ones(h * w, dtype=torch.bool) if i in model.train_ids else cols < left_width(w)
        idx = torch.nonzero(keep).squeeze(1)
        idx = idx[torch.randperm(len(idx), generator=g)[:PIXELS_PER_VIEW]]
        ids = torch.full((len(idx),), i, dtype=torch.long)
        parts.append((rad.reshape(-1, 3)[idx], photos[i].reshape(-1, 3)[idx], ids, rows[idx], cols[idx]))
    return RefitPixels(*(torch.cat(column) for column in zip(*parts, strict=True)))


def refit(model: Model, pixels: RefitPixels, steps: int, lr: float) -> None:
    """The package's refit (`train.tone_refit.refit_tone`) over `pixels`, then the curves made monotonic."""
    tm = model.tonemapper
    refit_tone(tm, dataclasses.replace(tm.cfg, refit_steps=steps, refit_lr=lr), pixels)
    tm.constrain()


def answers(run: Path, truth: SynthTruth | None) -> dict:
    if truth is None:
        return camera_truth(run)
    return truth_report(Model.load(run / "model.npz", device="cpu"), truth)


def main() -> None:
    ap = argparse.ArgumentParser(description="A trained run's tone refitted with its grid frozen.")
    ap.add_argument("run", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--lr", type=float, default=1e-3)
    args = ap.parse_args()
    model = Model.load(args.run / "model.npz", device="cpu")
    scene = load_scene(model.data_path, run_downscale(model))
    check_same_scene(model, scene)
    radiance, photos = {}, {}
    for i in [*model.train_ids, *model.test_ids]:
        with torch.no_grad():
            radiance[i] = model.render_camera(i).float()
        photos[i] = torch.as_tensor(np.array(scene.images[i])).float() / 255.0
    before = right_half_psnr(model, radiance, photos)
    refit(model, fitting_pixels(model, radiance, photos), args.steps, args.lr)
    after = right_half_psnr(model, radiance, photos)
    args.out.mkdir(parents=True, exist_ok=True)
    model.save(args.out / "model.npz")
    truth = SynthTruth.load(model.data_path)
    print("| model | right halves (dB) | a | EV error | WB error | CRF RMSE | HDR error |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, run, scores in (("trained", args.run, before), ("refitted", args.out, after)):
        c = answers(run, truth)
        hdr = f"{c['hdr_error_stops']:.3f}" if "hdr_error_stops" in c else "–"
        print(
            f"| {name} | {np.mean(scores):.2f} | {c['exponent_a']:.3f} | {c['ev_error_stops']:.3f} | "
            f"{c['wb_error_stops']:.3f} | {c['crf_rmse']:.4f} | {hdr} |"
        )


if __name__ == "__main__":
    main()
