"""A tone controller scored against true tones (synthetic captures record them in camera_truth.json).

A self-calibrated model's tones are the truth up to a gauge (docs/method.md, "Gauge"): the gauge is
fitted on the training views alone, then each test view (unseen with `--holdout full`) is scored through
the controller's tone, the mean learned tone and its true tone brought into the model's gauge.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.data.image_io import read_image
from hdrplenoxels.eval.metrics import image_metrics
from hdrplenoxels.render import Backend
from hdrplenoxels.tonemap.response import controlled_ldr
from hdrplenoxels.train.controller_fit import learned_stops
from hdrplenoxels.train.model import Model

TRUTH_FILE = "camera_truth.json"


def data_folder(model: Model) -> Path:
    """The folder of the model's dataset (its data path may name the transforms.json in it)."""
    path = Path(model.data_path)
    return path if path.is_dir() else path.parent


def truth_stops(model: Model) -> np.ndarray | None:
    """Each view's true tone in stops (N, 3), EV + log2 white-balance gains, from the dataset's
    camera_truth.json; None where there is none (photos)."""
    path = data_folder(model) / TRUTH_FILE
    if not path.exists():
        return None
    views = {Path(v["file"]).stem: v for v in json.loads(path.read_text())["views"]}
    rows = [views[Path(n).stem] for n in model.names]
    return np.array([[v["ev"] + math.log2(g) for g in v["wb_gains"]] for v in rows])


def gauge_fit(learned: np.ndarray, true: np.ndarray) -> tuple[float, np.ndarray]:
    """true ~ s * learned + o (s shared, o per channel) by least squares over the given views."""
    lc, tc = learned - learned.mean(0), true - true.mean(0)
    s = float((lc * tc).sum() / max((lc * lc).sum(), 1e-12))
    return s, true.mean(0) - s * learned.mean(0)


@torch.no_grad()
def truth_scores(model: Model, truth: np.ndarray, backend: Backend = "warp") -> dict:
    """On the test views: exposure error (RMS, stops) and white-balance error (the largest per-channel
    gain-ratio error, averaged) of the controller's tone (`auto`) and of the mean learned tone
    (`mean`), and whole-image PSNR through those and through the true tone (`true`)."""
    train, test = list(model.train_ids), list(model.test_ids)
    s, o = gauge_fit(learned_stops(model, train), truth[train])
    tm, folder = model.tonemapper, data_folder(model)
    mean = (model.mean_log_wb() / math.log(2.0)).cpu().numpy()
    errors: dict[str, list] = {"auto": [], "mean": []}
    psnr: dict[str, list] = {"auto": [], "mean": [], "true": []}
    for i in test:
        linear = tm.linear_radiance(model.render_camera(i, backend))
        tones = {
            "auto": model.controller.log_gains(linear).cpu().numpy() / math.log(2.0),
            "mean": mean,
            "true": (truth[i] - o) / s,  # the true tone in the model's gauge
        }
        photo = torch.tensor(read_image(folder / model.names[i]), dtype=torch.float32) / 255.0
        for name, stops in tones.items():
            gains = torch.tensor(stops * math.log(2.0), dtype=torch.float32, device=linear.device)
            ldr = controlled_ldr(linear, gains, tm.curve(int(tm.reference))).cpu()
            psnr[name].append(image_metrics(ldr, photo)["psnr"])
            if name in errors:
                as_true = s * stops + o
                cast = (as_true - as_true.mean()) - (truth[i] - truth[i].mean())
                errors[name].append((as_true.mean() - truth[i].mean(), np.abs(2.0**cast - 1.0).max()))
    out: dict = {"gauge_slope": s, "views": len(test)}
    for name, e in errors.items():
        e = np.array(e)
        out[f"{name}_exposure_rms_stops"] = float(np.sqrt(np.mean(e[:, 0] ** 2)))
        out[f"{name}_wb_ratio_error"] = float(np.mean(e[:, 1]))
    out |= {f"{name}_psnr": float(np.mean(v)) for name, v in psnr.items()}
    return out
