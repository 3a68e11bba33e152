"""Truth recovery on synthetic scenes: how well a trained model recovered the simulated cameras and the
HDR radiance (beyond the paper, which scores LDR images only).

Self-calibration has an exponential ambiguity (Grossberg & Nayar): radiance^a, exposures^a and a
response CRF(x^(1/a)) explain the images equally well. So every score is taken after fitting that
exponent `a` and a per-channel gain, and `a` is reported on its own (1 means the true scale was found;
known exposures fix it after training). `a` comes from the per-view gains, whose spread of several stops fixes
it well; the radiance gain is fitted on training views, never on the scored test pixels.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.data.image_io import read_exr
from hdrplenoxels.data.protocol import left_width
from hdrplenoxels.render import Backend
from hdrplenoxels.tonemap.response import ResponseCurve
from hdrplenoxels.train.model import Model

MU = 5000.0  # mu-law compression for HDR PSNR (as in HDR imaging papers)
BLACK_CODE = 0.5 / 255.0  # an 8-bit pixel below this reads 0 and carries no radiance information
GAIN_FIT_VIEWS = 8  # training views rendered to fit the radiance gain
BRIGHTEST_PERCENTILE = 99.0  # "the brightest content": scored pixels above this percentile of luminance
CRF_SAMPLES = 256


@dataclass
class SynthTruth:
    """What the simulated cameras did, from a synth dataset's camera_truth.json."""

    true_log2_gain: np.ndarray  # (N, 3): EV + log2 of the white-balance gains
    evs: np.ndarray  # (N,)
    curves: np.ndarray  # (N, 256): each view's response at x = i / 255 (same for all channels)
    hdr_paths: list[Path]

    @classmethod
    def load(cls, data_path: str | Path) -> SynthTruth | None:
        """The truth beside a dataset (folder or its transforms.json), or None if it is not synthetic: no
        camera_truth.json, or one without true radiance (real photos re-shot through simulated cameras,
        `benchmarks/real_captures.py`)."""
        folder = Path(data_path)
        folder = folder if folder.is_dir() else folder.parent
        try:
            views = json.loads((folder / "camera_truth.json").read_text())["views"]
        except (OSError, ValueError, KeyError):
            return None
        if not all("hdr" in v for v in views):
            return None
        evs = np.array([v["ev"] for v in views], dtype=np.float64)
        gains = np.log2(np.array([v["wb_gains"] for v in views], dtype=np.float64))
        return cls(
            true_log2_gain=evs[:, None] + gains,
            evs=evs,
            curves=np.array([v["crf_curve"] for v in views], dtype=np.float64),
            hdr_paths=[folder / v["hdr"] for v in views],
        )


def fit_exponent(learned: np.ndarray, true: np.ndarray) -> tuple[float, np.ndarray]:
    """Least squares `learned ~ a * true + b_c` over views (N, 3), one slope, one offset per channel."""
    tc = true - true.mean(0)
    lc = learned - learned.mean(0)
    denom = float((tc * tc).sum())
    a = float((tc * lc).sum() / denom) if denom > 1e-12 else 1.0
    return a, learned.mean(0) - a * true.mean(0)


def gain_errors(learned: np.ndarray, true: np.ndarray, a: float, offset: np.ndarray) -> dict:
    """Per-view exposure error (channel mean) and white-balance error (the rest), in stops."""
    aligned = (learned - offset) / a
    resid = aligned - true
    ev = resid.mean(1)
    return {
        "ev_error_stops": float(np.abs(ev - ev.mean()).mean()),
        "wb_error_stops": float(np.abs(resid - resid.mean(1, keepdims=True)).mean()),
    }


def crf_rmse(curve: ResponseCurve, true_curve: np.ndarray, a: float) -> tuple[float, np.ndarray]:
    """RMSE over x in [0, 1] and channels between learned f^_c(s_c x^a) and the true f(x); s_c fitted."""
    x = np.linspace(0.0, 1.0, len(true_curve))
    log_s = np.linspace(-1.0, 1.0, 401)
    xs = torch.as_tensor(np.exp2(log_s)[:, None, None] * (x[None, :, None] ** a), dtype=torch.float32)
    err = ((curve(xs.expand(-1, -1, 3)).double().numpy() - true_curve[None, :, None]) ** 2).mean(1)  # (S, 3)
    best = err.argmin(0)
    return float(math.sqrt(err[best, range(3)].mean())), np.exp2(log_s[best])


def recordable(truth: SynthTruth, radiance: np.ndarray, views: list[int]) -> np.ndarray:
    """Mask (..., 3): channels that at least one of `views` recorded neither clipped nor black."""
    ok = np.zeros(radiance.shape, dtype=bool)
    x = np.linspace(0.0, 1.0, truth.curves.shape[1])
    for i in views:
        gain = np.exp2(truth.true_log2_gain[i])
        lowest = np.interp(BLACK_CODE, truth.curves[i], x)  # irradiance of the first non-zero code
        e = radiance * gain
        ok |= (e >= lowest) & (e < 1.0)
    return ok & (radiance > 0)


def interior(mask: np.ndarray) -> np.ndarray:
    """`mask` (H, W, C) eroded by a 3x3 square: pixels whose 8 neighbours are in the mask too.

    Pixels beside unrecorded ones (a black background, a clipped light) mix both in their footprint: a
    64^3 grid's edge lands a fraction of a pixel off and its error in stops is unbounded there (a few
    such pixels carry much of the mean: JOURNAL.md, "Other measured choices"); scored on their
    own, the rest measure the radiance the tone mapper recovered rather than the geometry's edges."""
    padded = np.pad(mask, ((1, 1), (1, 1), (0, 0)), constant_values=False)
    h, w = mask.shape[:2]
    out = mask.copy()
    for dy in range(3):
        for dx in range(3):
            out &= padded[dy : dy + h, dx : dx + w]
    return out


def mu_law(x: np.ndarray) -> np.ndarray:
    return np.log1p(MU * x) / math.log1p(MU)


@dataclass
class RadianceAlignment:
    """The learned gauge against the truth: log2 L^ = a log2 L + log2 g_c (a from the per-view gains,
    g from training views' renders), so that learned and true radiance can be compared or swapped."""

    a: float
    log2_g: np.ndarray  # (3,)

    def to_true(self, learned: np.ndarray) -> np.ndarray:
        return np.exp2((np.log2(np.maximum(learned, 1e-12)) - self.log2_g) / self.a)

    def to_learned(self, true: np.ndarray) -> np.ndarray:
        return np.exp2(self.a * np.log2(np.maximum(true, 1e-30)) + self.log2_g)


def radiance_gain(model: Model, truth: SynthTruth, a: float, backend: Backend = "warp") -> np.ndarray:
    """log2 g_c: the median of log2 L^ - a log2 L over training views' recordable pixels (never test)."""
    fit_views = model.train_ids[:: max(1, len(model.train_ids) // GAIN_FIT_VIEWS)][:GAIN_FIT_VIEWS]
    diffs = [[], [], []]
    for i in fit_views:
        pred = model.hdr(model.render_camera(i, backend)).cpu().numpy().astype(np.float64)
        hdr = read_exr(truth.hdr_paths[i]).astype(np.float64)
        ok = recordable(truth, hdr, model.train_ids) & (pred > 0)
        for c in range(3):
            diffs[c].append(np.log2(pred[..., c][ok[..., c]]) - a * np.log2(hdr[..., c][ok[..., c]]))
    return np.array([float(np.median(np.concatenate(d))) for d in diffs])


def learned_log2_gains(model: Model) -> np.ndarray:
    """Every view's learned log2 white balance (with exposure), (N, 3), in the output gauge."""
    if model.tonemapper is None:
        raise ValueError("truth recovery needs a model trained with the tone mapper")
    return model.tonemapper.linear_log_wb().cpu().numpy().astype(np.float64) / math.log(2.0)


def align_radiance(model: Model, truth: SynthTruth, backend: Backend = "warp") -> RadianceAlignment:
    a, _ = fit_exponent(learned_log2_gains(model), truth.true_log2_gain)
    return RadianceAlignment(a, radiance_gain(model, truth, a, backend))


def camera_recovery(model: Model, true_log2_gain: np.ndarray, curves: np.ndarray) -> dict:
    """Exponent, EV / white-balance error and CRF RMSE of the learned cameras against the true ones
    (each view's log2 gains (N, 3) and response (N, 256)): what needs no true radiance, so a real
    capture re-shot through simulated cameras is scored by it too."""
    learned = learned_log2_gains(model)
    tm = model.tonemapper
    a, offset = fit_exponent(learned, true_log2_gain)
    out = {"exponent_a": a, "known_exposure": bool(tm.cfg.known_exposure)}
    out.update(gain_errors(learned, true_log2_gain, a, offset))
    pairs = {(int(tm.crf_group[i]), i) for i in range(len(curves))}
    rmses = [crf_rmse(tm.curve(i), curves[i], a)[0] for _, i in sorted(pairs)]
    out["crf_rmse"] = float(np.mean(rmses))
    return out


def truth_report(model: Model, truth: SynthTruth, backend: Backend = "warp") -> dict:
    """Exponent, CRF RMSE, EV / white-balance error, HDR error in stops and mu-law PSNR (right halves)."""
    out = camera_recovery(model, truth.true_log2_gain, truth.curves)
    a = out["exponent_a"]

    alignment = RadianceAlignment(a, radiance_gain(model, truth, a, backend))
    errors, inner_errors, bright_errors, sq_mu, n_valid, n_total = [], [], [], [], 0, 0
    test_hdrs = {i: read_exr(truth.hdr_paths[i]).astype(np.float64) for i in model.test_ids}
    scale = max(float(h.max()) for h in test_hdrs.values())
    halves = [h[:, left_width(h.shape[1]) :] for h in test_hdrs.values()]
    bright = np.percentile(np.concatenate([h.mean(-1).ravel() for h in halves]), BRIGHTEST_PERCENTILE)
    for i, hdr in test_hdrs.items():
        pred = model.hdr(model.render_camera(i, backend)).cpu().numpy().astype(np.float64)
        half = slice(left_width(hdr.shape[1]), None)
        pred, hdr = pred[:, half], hdr[:, half]
        aligned = alignment.to_true(pred)
        ok = recordable(truth, hdr, model.train_ids)
        err = np.abs(np.log2(aligned) - np.log2(np.maximum(hdr, 1e-30)))
        errors.append(err[ok])
        inner_errors.append(err[interior(ok)])
        bright_errors.append(err[ok & (hdr.mean(-1, keepdims=True) >= bright)])
        n_valid, n_total = n_valid + int(ok.sum()), n_total + ok.size
        mu_pred, mu_true = (mu_law(np.clip(x / scale, 0.0, 1.0)) for x in (aligned, hdr))
        sq_mu.append(np.mean((mu_pred - mu_true) ** 2))
    out["hdr_error_stops"] = float(np.mean(np.concatenate(errors)))
    out["hdr_error_median_stops"] = float(np.median(np.concatenate(errors)))
    out["hdr_error_interior_stops"] = float(np.mean(np.concatenate(inner_errors)))
    # The brightest content (indoor's window, courtyard's sky by the sun), the hardest to record.
    brightest = np.concatenate(bright_errors)
    out["hdr_error_brightest_stops"] = float(np.mean(brightest)) if brightest.size else float("nan")
    out["hdr_psnr_mu"] = float(-10.0 * math.log10(max(float(np.mean(sq_mu)), 1e-12)))
    out["hdr_valid_fraction"] = n_valid / max(n_total, 1)
    out["radiance_gain_log2"] = alignment.log2_g.tolist()
    return out
