"""What the MSI background gains on the tiny unbounded scene (JOURNAL.md, "Background training").

Trains the procedural scene `TINY_UNBOUNDED` (a known grid in the box [-1, 1]^3 inside the known surround
of `make_sky`) with the background model (the scene mode's choice) and without it, on the same schedule
(the fast preset at one 16^3 grid, 4 x 8 x 16 MSI, 1024-ray batches), and scores the test views (every
8th view, held out whole: `holdout=full`) on all pixels and on the pixels whose rays miss the box.
`--validation` scores a second rig of the same world instead (24 views from 2.6 units, 85 degrees), the
one to compare settings on; `--set` passes config overrides (e.g. background.init_sigma=1.0);
`--image PATH` writes the first test view as a PNG: truth, with the MSI, with the constant (4x, nearest).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.data import load_scene
from hdrplenoxels.data.image_io import write_png
from hdrplenoxels.eval.regions import outside_box
from hdrplenoxels.synth.procedural import TINY_UNBOUNDED, write_procedural_scene
from hdrplenoxels.train.config import apply_overrides
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.trainer import Trainer

VALIDATION = dataclasses.replace(TINY_UNBOUNDED, num_views=24, fov_deg=85.0, camera_distance=2.6)


def config(steps: int, enabled: bool | None, overrides: list[str]):
    cfg = apply_overrides(
        preset("fast"),
        {
            "device": "cpu",
            "holdout": "full",
            "grid.reso_schedule": [(16, 16, 16)],
            "optim.n_iters": steps,
            "optim.batch_size": 1024,
            "optim.lr_decay_steps": steps,
            "optim.lr_sigma_delay_steps": steps // 6,
            "background.layers": 4,
            "background.height": 8,
            "background.width": 16,
            "checkpoint_every": 0,
        },
    )
    cfg = apply_overrides(cfg, overrides)
    cfg.background.enabled = enabled
    return cfg


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10.0 * torch.log10(((a - b) ** 2).mean()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--validation", action="store_true")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--image", type=Path)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        spec = VALIDATION if args.validation else TINY_UNBOUNDED
        scene = load_scene(write_procedural_scene(Path(tmp) / "scene", spec))
        print(f"{'background':12s} {'seconds':>8s} {'PSNR all':>9s} {'outside box':>12s}")
        first = torch.as_tensor(np.array(scene.images[scene.test_ids[0]])).float() / 255.0
        panels = [first]
        for enabled, name in ((None, "MSI"), (False, "constant")):
            start = time.perf_counter()
            cfg = config(args.steps, enabled, args.overrides)
            model = Trainer(scene, cfg, Path(tmp) / name).run(progress=False)
            seconds = time.perf_counter() - start
            pred, truth, outside = [], [], []
            for i in scene.test_ids:
                pred.append(model.render_camera(i).clamp(0.0, 1.0))
                truth.append(torch.as_tensor(np.array(scene.images[i])).float() / 255.0)
                outside.append(outside_box(model, i))
            p, t, o = torch.stack(pred), torch.stack(truth), torch.stack(outside)
            panels.append(p[0])
            print(f"{name:12s} {seconds:8.1f} {psnr(p, t):9.2f} {psnr(p[o], t[o]):12.2f}")
        if args.image is not None:
            strip = torch.cat(panels, 1).repeat_interleave(4, 0).repeat_interleave(4, 1)
            write_png(args.image, strip.numpy())


if __name__ == "__main__":
    main()
