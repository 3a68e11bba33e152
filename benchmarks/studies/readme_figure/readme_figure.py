"""The README's picture: photos a model was given, taken at different exposures, and what its HDR field
renders for a view it did not train on, at any exposure afterwards, with the field's log2 luminance.

    python benchmarks/studies/readme_figure/readme_figure.py RUN DATA OUT.png

RUN: a run trained with --tonemap on DATA, a `synth` scene's `varying` folder (its camera_truth.json
names each photo's EV). The README's picture is `indoor` (`synth indoor`, 160 x 120) at `fast`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from hdrplenoxels.data import load_scene
from hdrplenoxels.train.model import load_model
from hdrplenoxels.viewer.display import false_colour

EVS = (-3.0, 0.0, 3.0)
SCALE = 2  # tiles are drawn twice their size
LABEL_HEIGHT = 18


def tile(img: np.ndarray, label: str) -> Image.Image:
    """An image (H, W, 3) in [0, 1] or uint8, enlarged, with a caption above it."""
    a = img if img.dtype == np.uint8 else (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    h, w = a.shape[:2]
    picture = Image.fromarray(a).resize((w * SCALE, h * SCALE), Image.LANCZOS)
    out = Image.new("RGB", (picture.width, picture.height + LABEL_HEIGHT), "white")
    out.paste(picture, (0, LABEL_HEIGHT))
    ImageDraw.Draw(out).text((4, 3), label, fill="black")
    return out


def row(tiles: list[Image.Image], gap: int = 4) -> Image.Image:
    out = Image.new("RGB", (sum(t.width for t in tiles) + gap * (len(tiles) - 1), tiles[0].height), "white")
    x = 0
    for t in tiles:
        out.paste(t, (x, 0))
        x += t.width + gap
    return out


def stops_spanned(linear: torch.Tensor) -> float:
    """log2 of the 99.9th over the 1st percentile of a render's luminance."""
    lum = linear.reshape(-1, 3).mean(1).clamp(min=1e-6)
    return float(torch.log2(torch.quantile(lum, 0.999) / torch.quantile(lum, 0.01)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("data", type=Path)
    ap.add_argument("out", type=Path)
    args = ap.parse_args()
    model = load_model(args.run)
    scene = load_scene(args.data)
    truth = json.loads((args.data / "camera_truth.json").read_text())
    ev_of = {Path(v["file"]).name: v["ev"] for v in truth["views"]}
    photos = []
    for ev in EVS:
        i = next(i for i in model.train_ids if ev_of[Path(scene.names[i]).name] == ev)
        photos.append(tile(scene.images[i], f"photo {i}, EV {ev:+g}"))
    with torch.no_grad():  # the test view whose render spans the most stops (a window in view)
        radiances = {i: model.render_camera(i) for i in model.test_ids}
        view = max(radiances, key=lambda i: stops_spanned(model.hdr(radiances[i])))
        radiance = radiances[view]
        renders = [tile(model.to_ldr_controlled(radiance, ev).numpy(), f"render, EV {ev:+g}") for ev in EVS]
        linear = model.hdr(radiance).cpu()
    renders.append(tile(false_colour(linear, (-8.0, 4.0)), "log2 luminance, -8..+4"))
    top, bottom = row(photos), row(renders)
    out = Image.new("RGB", (max(top.width, bottom.width), top.height + bottom.height + 8), "white")
    out.paste(top, (0, 0))
    out.paste(bottom, (0, top.height + 8))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    out.save(args.out)
    print(f"wrote {args.out} ({out.width} x {out.height}); test view {view}")


if __name__ == "__main__":
    main()
