"""Pictures of the learned tones: response curves per channel, exposure and white balance per view."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hdrplenoxels.core.atomic import atomic_path

CHANNEL_COLOURS = ("tab:red", "tab:green", "tab:blue")


def plot_tone_params(params: dict, path: Path, truth: dict | None = None) -> Path:
    """Write a PNG with three panels from `ToneMapper.parameters_dict()` (+ names).

    Exposure is shown as log2 of the mean gain relative to the mean over views; white balance as each
    channel's gain over the view's mean gain. `truth` (a camera_truth.json dict), when given, overlays the
    simulated camera's values. Learned exposures are in the output gauge, whose stops are not the true
    tone's unless exposures were known (docs/method.md, "Gauge"): beside the truth they are drawn in the
    true gauge, scaled by the least-squares factor, and every panel says which gauge it shows.
    """
    # The figure alone, without pyplot's global state: this is drawn on a writer thread during training's
    # last phase (`train/run_end.py`), and never changes the caller's matplotlib backend.
    from matplotlib.figure import Figure

    knots = np.asarray(params["crf_knots"])  # (groups, 3, K+1)
    wb = np.asarray(params["white_balance"])  # (N, 3)
    log2 = np.log2(wb)
    ev = log2.mean(1) - log2.mean()
    balance = wb / wb.mean(1, keepdims=True)
    x = np.asarray(params.get("crf_knot_irradiance") or np.linspace(0.0, 1.0, knots.shape[-1]))

    fig = Figure(figsize=(13, 3.8))
    axes = fig.subplots(1, 3)
    for g in range(knots.shape[0]):
        for c in range(3):
            label = "RGB"[c] if g == 0 else None
            axes[0].plot(x, knots[g, c], color=CHANNEL_COLOURS[c], alpha=0.8 if knots.shape[0] == 1 else 0.3,
                         label=label)  # fmt: skip
    if truth is not None:
        axes[0].plot(np.linspace(0, 1, len(truth["views"][0]["crf_curve"])), truth["views"][0]["crf_curve"],
                     "k--", label="true (view 0)")  # fmt: skip
    axes[0].set(title=f"response curves ({params['crf_sharing']})", xlabel="irradiance", ylabel="pixel value")
    axes[0].legend(fontsize=8)

    views = np.arange(len(ev))
    shown, label, gauge = exposure_in_gauge(ev, params, truth)
    axes[1].bar(views, shown, color="0.5", label=label)
    if truth is not None:
        true_ev = np.array([v["ev"] for v in truth["views"]], dtype=float)
        axes[1].plot(views, true_ev - true_ev.mean(), "k.", label="true")
    axes[1].legend(fontsize=8)
    axes[1].axvline(params["reference"], color="tab:orange", lw=1, ls=":")
    axes[1].set(title="exposure per view (reference dotted)", xlabel="view", ylabel=f"EV (relative, {gauge})")

    for c in range(3):
        axes[2].plot(views, balance[:, c], ".", color=CHANNEL_COLOURS[c])
    axes[2].set(title="white balance per view", xlabel="view", ylabel="channel gain / mean gain")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)
    return Path(path)


def exposure_in_gauge(ev: np.ndarray, params: dict, truth: dict | None) -> tuple[np.ndarray, str, str]:
    """(relative EVs to draw, their legend label, the gauge's name). Known exposures fix the true gauge;
    otherwise, with a truth to compare against, the learned EVs are scaled onto it by least squares (the
    one factor self-calibration cannot know); without one they stay in the output gauge."""
    if params.get("known_exposure"):
        return ev, "learned", "true stops"
    if truth is None:
        return ev, "learned", "output gauge"
    true_ev = np.array([v["ev"] for v in truth["views"]], dtype=float)
    true_ev -= true_ev.mean()
    norm = float(ev @ ev)
    scale = float(ev @ true_ev) / norm if norm > 0 else 1.0
    return ev * scale, f"learned x {scale:.2f} (gauge fitted to the truth)", "true stops"
