"""How each view's learned exposure moves during a `fast` run: whether it passes the value it ends at and
comes back (overshoot), and how far it still wanders over the last fifth of the steps (README beside
this script).

    python benchmarks/studies/tone_rates/trace.py DATA OUT LABEL [SECTION.KEY=VALUE ...]

DATA is a varying capture; the run trains into OUT with the tone mapper on and the given settings.
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np

from hdrplenoxels.core.settings import apply_overrides
from hdrplenoxels.data import load_scene
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.trainer import Trainer


def main() -> None:
    data, out, label = sys.argv[1], sys.argv[2], sys.argv[3]
    overrides = dict(a.split("=", 1) for a in sys.argv[4:])
    cfg = apply_overrides(preset("fast"), {"tonemap.enabled": "true", **overrides})
    scene = load_scene(data)
    trainer = Trainer(scene, cfg, out, overwrite=True)
    trace = []  # after each step: each view's exposure, the mean of its log gains, in stops
    while trainer.step < cfg.optim.n_iters:
        trainer.train_step()
        trainer.upsample()
        trace.append(trainer.tonemapper.log_wb.detach().mean(1).cpu().numpy() / math.log(2))
    views = list(scene.train_ids)
    to_end = np.array(trace)[:, views] - trace[-1][views]  # each step's distance to the final value
    start = to_end[0]
    overshoot = np.where(np.sign(start)[None, :] * to_end < 0, np.abs(to_end), 0.0).max(0)
    late = np.abs(to_end[int(0.8 * len(to_end)) :]).max(0)
    print(json.dumps({
        "label": label,
        "views": len(views),
        "mean_start_to_end_stops": float(np.abs(start).mean()),
        "mean_overshoot_stops": float(overshoot.mean()),
        "max_overshoot_stops": float(overshoot.max()),
        "mean_last_fifth_wander_stops": float(late.mean()),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
