"""The tone controller: a view's exposure and white balance predicted from its rendered linear radiance,
as a camera's auto exposure and auto white balance set them from the scene (docs/method.md, "Tone
controller"). The response curve is not predicted: it stays the learned tone's.

A view's tone here is its log white balance in stops, t = (log gains) / ln 2 (3,), split into an exposure
E = mean(t) and a colour cast C = t - E. Each form of the controller is a small linear model of one
meter reading of the radiance (or none), fitted to the training views' learned tones:
  mean             E and C constant (the mean tone)
  meter            E = a + b * log-mean luminance (a geometric mean: highlights count little)
  centre           E = a + b * centre-weighted log-mean luminance
  average@g        E = a + b * log of the power mean of the luminance, (mean L^g)^(1/g) (average
                   metering: highlights count fully)
  centre-average@g E = a + b * log of the centre-weighted power mean
and each with "+grey": C = c + d * grey-world cast (log channel means minus their mean) instead of C
constant. The power g stands in for the gauge: without known exposures a model's "linear" radiance is
the true one to some power (docs/method.md, "Gauge"), which a geometric mean ignores but an average does
not; g in POWERS. The form is chosen by leaving each training view out in turn (`choose_form`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

POWERS = (0.5, 0.7, 1.0, 1.4, 2.0)  # the power means' exponents (see the module docstring)
READINGS = ("meter", "centre", *(f"{m}@{g:g}" for m in ("average", "centre-average") for g in POWERS))
FORMS = ("mean", *READINGS, *(f"{r}+grey" for r in READINGS))
LUMINANCE = (0.2126, 0.7152, 0.0722)  # Rec. 709 weights of linear RGB
LOG_FLOOR = 1e-4  # radiance below this meters as this (black pixels would pull a log-mean to -inf)
CENTRE_SIGMA = 0.35  # the centre weighting's Gaussian width, in half the image's diagonal
RIDGE = 1e-3  # per view, on the slopes: views that all meter alike leave them near 0, not undetermined
METER_PIXELS = 4096  # pixels metered per image at most (a strided subset: cheap at any frame size)
SETTLE_SECONDS = 0.3  # time constant of a video's auto exposure: a camera settles over a few frames


@dataclass(frozen=True)
class Readings:
    """What a camera meters in one image: `log2` of each reading in READINGS (geometric and power means of
    the luminance, over the whole image and centre-weighted), and the grey-world cast (3,), log2 channel
    means minus their mean."""

    log2: dict[str, float]
    grey: tuple[float, float, float]


def meter(linear: torch.Tensor) -> Readings:
    """The readings of a linear radiance image (H, W, 3)."""
    h, w = linear.shape[:2]
    stride = max(1, math.ceil(math.sqrt(h * w / METER_PIXELS)))
    img = linear[::stride, ::stride].float().clamp(min=0.0)
    lum = (img * torch.tensor(LUMINANCE, device=img.device)).sum(-1)
    log_lum = torch.log2(lum.clamp(min=LOG_FLOOR))
    rows = (torch.arange(img.shape[0], device=img.device, dtype=torch.float32) * stride + 0.5) / h - 0.5
    cols = (torch.arange(img.shape[1], device=img.device, dtype=torch.float32) * stride + 0.5) / w - 0.5
    r2 = (rows[:, None] ** 2 + cols[None, :] ** 2) / 0.5  # squared radius in half-diagonals
    weight = torch.exp(-r2 / (2 * CENTRE_SIGMA**2))
    log_means = torch.log2(img.reshape(-1, 3).mean(0).clamp(min=LOG_FLOOR))
    grey = log_means - log_means.mean()
    lum = lum.clamp(min=LOG_FLOOR)
    values = {"meter": log_lum.mean(), "centre": (weight * log_lum).sum() / weight.sum()}
    for g in POWERS:
        powered = lum**g
        values[f"average@{g:g}"] = torch.log2(powered.mean()) / g
        values[f"centre-average@{g:g}"] = torch.log2((weight * powered).sum() / weight.sum()) / g
    return Readings({k: float(v) for k, v in values.items()}, tuple(float(c) for c in grey))


def _exposure_feature(form: str, r: Readings) -> float | None:
    return r.log2.get(form.removesuffix("+grey"))


@dataclass
class ToneController:
    """A fitted controller: `form` (one of FORMS), exposure = exposure_w[0] + exposure_w[1] * reading,
    cast = cast_w[:3] + cast_w[3] * grey-world cast (slopes 0 where the form has none); stops."""

    form: str
    exposure_w: tuple[float, float]
    cast_w: tuple[float, float, float, float]

    def predict_stops(self, r: Readings) -> np.ndarray:
        """The camera's log white balance in stops (3,) for an image metered as `r`."""
        x = _exposure_feature(self.form, r)
        exposure = self.exposure_w[0] + self.exposure_w[1] * (x or 0.0)
        cast = np.asarray(self.cast_w[:3]) + self.cast_w[3] * np.asarray(r.grey)
        cast = cast - cast.mean()
        return exposure + cast

    def log_gains(self, linear: torch.Tensor) -> torch.Tensor:
        """Natural-log gains (3,) to apply to the linear radiance image `linear` (H, W, 3)."""
        stops = self.predict_stops(meter(linear))
        return torch.tensor(stops * math.log(2.0), dtype=torch.float32, device=linear.device)

    # ----------------------------------------------------------------------------- persistence
    def state_arrays(self) -> dict[str, np.ndarray]:
        return {
            "form": np.array(self.form),
            "exposure_w": np.asarray(self.exposure_w, dtype=np.float64),
            "cast_w": np.asarray(self.cast_w, dtype=np.float64),
        }

    @classmethod
    def from_state_arrays(cls, arrays: dict[str, np.ndarray]) -> ToneController:
        form = str(np.asarray(arrays["form"]))
        exposure_w, cast_w = np.asarray(arrays["exposure_w"]), np.asarray(arrays["cast_w"])
        if form not in FORMS or exposure_w.shape != (2,) or cast_w.shape != (4,):
            raise ValueError("malformed tone controller arrays")
        return cls(form, tuple(float(v) for v in exposure_w), tuple(float(v) for v in cast_w))


class ExposureTracker:
    """A video camera's auto exposure: each frame's gains move from the last frame's towards the
    controller's prediction with time constant `seconds` (exponentially, in stops), so a cut to a bright
    view is not corrected at once and a flicker of the meter does not show."""

    def __init__(self, controller: ToneController, fps: float, seconds: float = SETTLE_SECONDS):
        self.controller = controller
        self.rate = 1.0 - math.exp(-1.0 / (fps * seconds)) if seconds > 0 else 1.0
        self.gains: torch.Tensor | None = None

    def __call__(self, linear: torch.Tensor) -> torch.Tensor:
        """The natural-log gains (3,) of the next frame, whose linear radiance is `linear` (H, W, 3)."""
        target = self.controller.log_gains(linear)
        self.gains = target if self.gains is None else self.gains + self.rate * (target - self.gains)
        return self.gains


def _line(x: np.ndarray | None, y: np.ndarray) -> tuple[float, float]:
    """Intercept and slope of y on x by ridge-regularised least squares (slope 0 without x)."""
    if x is None or len(y) < 3:
        return float(y.mean()), 0.0
    xc = x - x.mean()
    slope = float((xc * (y - y.mean())).sum() / ((xc * xc).sum() + RIDGE * len(y)))
    return float(y.mean() - slope * x.mean()), slope


def fit(form: str, readings: list[Readings], stops: np.ndarray) -> ToneController:
    """The controller of `form` fitted to views metered as `readings` whose tones are `stops` (N, 3)."""
    if form not in FORMS:
        raise ValueError(f"unknown controller form {form!r}; choose one of {FORMS}")
    stops = np.asarray(stops, dtype=np.float64)
    exposure = stops.mean(1)
    cast = stops - exposure[:, None]
    x = _exposure_feature(form, readings[0])
    xs = None if x is None else np.array([_exposure_feature(form, r) for r in readings])
    exposure_w = _line(xs, exposure)
    if form.endswith("+grey") and len(readings) >= 3:
        grey = np.array([r.grey for r in readings])  # (N, 3)
        gc, cc = grey - grey.mean(0), cast - cast.mean(0)
        slope = float((gc * cc).sum() / ((gc * gc).sum() + RIDGE * grey.size))
        base = cast.mean(0) - slope * grey.mean(0)
    else:
        slope, base = 0.0, cast.mean(0)
    return ToneController(form, exposure_w, (*(float(b) for b in base), slope))


def leave_one_out_predictions(form: str, readings: list[Readings], stops: np.ndarray) -> np.ndarray:
    """Each view's tone in stops (N, 3) as predicted by the controller of `form` fitted to all the
    other views."""
    stops = np.asarray(stops, dtype=np.float64)
    out = []
    for i in range(len(readings)):
        keep = [j for j in range(len(readings)) if j != i]
        out.append(fit(form, [readings[j] for j in keep], stops[keep]).predict_stops(readings[i]))
    return np.array(out)


def leave_one_out_error(form: str, readings: list[Readings], stops: np.ndarray) -> float:
    """RMS error in stops (over views and channels) of `leave_one_out_predictions`."""
    predicted = leave_one_out_predictions(form, readings, stops)
    return float(np.sqrt(np.mean(np.square(predicted - np.asarray(stops)))))


def choose_form(readings: list[Readings], stops: np.ndarray) -> tuple[str, dict[str, float]]:
    """The form with the smallest leave-one-out error (ties: the simpler, earlier in FORMS), and every
    form's error; with fewer than 4 views, `mean`."""
    if len(readings) < 4:
        return "mean", {}
    errors = {form: leave_one_out_error(form, readings, stops) for form in FORMS}
    return min(FORMS, key=lambda f: (round(errors[f], 6), FORMS.index(f))), errors
