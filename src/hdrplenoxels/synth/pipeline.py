"""The simulated camera: linear HDR radiance in, 8-bit LDR image out, one small function per step.

Order (PIPELINE_ORDER), matching the tone-mapping model HDR-Plenoxels learns, I = CRF(clip(wb * V * L)):
  exposure (x 2^EV) -> vignetting (radial falloff) -> shot noise (Poisson-Gaussian on the sensor signal)
  -> white balance (per-channel digital gains, which amplify the noise as in a camera)
  -> clip to [0, 1] (saturation) -> camera response curve -> 8-bit quantisation.
Every step except noise, clipping and quantisation is invertible on unclipped pixels; the inverses are
here too, so tests (and truth scoring) can recover each parameter.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

CRF_SAMPLES = 256  # the recorded response curve: CRF at x = i / 255, i = 0..255
PIPELINE_ORDER = "radiance * 2^ev -> vignetting -> shot noise -> white balance -> clip [0,1] -> crf -> 8 bit"


# ----------------------------------------------------------------------------- steps
def apply_exposure(radiance: np.ndarray, ev: float) -> np.ndarray:
    """Scale by 2^EV: +1 EV doubles the light reaching the sensor."""
    return radiance * np.float32(2.0**ev)


def vignetting_factor(height: int, width: int, k1: float, k2: float) -> np.ndarray:
    """Radial falloff 1 + k1 r^2 + k2 r^4 about the image centre, r from (row/H, col/W) offsets; (H, W, 1).

    Normalised (row / H, col / W) coordinates, the convention the tone-mapping module uses too.
    """
    rows = (np.arange(height, dtype=np.float64) + 0.5) / height - 0.5
    cols = (np.arange(width, dtype=np.float64) + 0.5) / width - 0.5
    r2 = rows[:, None] ** 2 + cols[None, :] ** 2
    return np.clip(1.0 + k1 * r2 + k2 * r2**2, 0.0, None)[..., None].astype(np.float32)


def apply_white_balance(x: np.ndarray, gains) -> np.ndarray:
    return x * np.asarray(gains, dtype=np.float32)


def add_shot_noise(
    x: np.ndarray, full_well: float, read_noise: float, rng: np.random.Generator
) -> np.ndarray:
    """Poisson-Gaussian sensor noise: photo-electrons ~ Poisson(x * full_well), plus Gaussian read noise.

    `x = 1` is a full well, so a darker exposure collects fewer electrons and is relatively noisier,
    as on a real sensor at fixed ISO. `read_noise` is in electrons.
    """
    electrons = rng.poisson(np.clip(x, 0.0, None) * full_well).astype(np.float64)
    electrons += rng.normal(0.0, read_noise, size=x.shape)
    return (electrons / full_well).astype(np.float32)


def clip_unit(x: np.ndarray) -> np.ndarray:
    """Sensor saturation (and no negative light)."""
    return np.clip(x, 0.0, 1.0)


def quantize_8bit(y: np.ndarray) -> np.ndarray:
    return np.round(np.clip(y, 0.0, 1.0) * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------- response curves
def crf_gamma(x: np.ndarray, gamma: float = 3.0) -> np.ndarray:
    """The paper's response: x^(1/gamma) with gamma 3."""
    return np.power(np.clip(x, 0.0, 1.0), 1.0 / gamma)


def crf_gamma_inverse(y: np.ndarray, gamma: float = 3.0) -> np.ndarray:
    return np.power(np.clip(y, 0.0, 1.0), gamma)


FILMIC_P = 1.6  # contrast of the S-curve


def crf_filmic(x: np.ndarray) -> np.ndarray:
    """A filmic-like S-curve on a log-ish base: toe and shoulder, f(0)=0, f(1)=1, strictly increasing.

    f(x) = s^p / (s^p + (1 - s)^p) with s = sqrt(x): the square root lifts mid-tones like a display
    gamma, the logistic-in-logit shape adds the toe and the shoulder.
    """
    s = np.sqrt(np.clip(x, 0.0, 1.0))
    a = np.power(s, FILMIC_P)
    return a / (a + np.power(1.0 - s, FILMIC_P))


def crf_filmic_inverse(y: np.ndarray) -> np.ndarray:
    """s / (1 - s) = (y / (1 - y))^(1/p), written symmetrically so that y = 0 and y = 1 need no guard."""
    y = np.clip(y, 0.0, 1.0)
    a = np.power(y, 1.0 / FILMIC_P)
    s = a / (a + np.power(1.0 - y, 1.0 / FILMIC_P))
    return s**2


def crf_srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1)."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def crf_srgb_inverse(y: np.ndarray) -> np.ndarray:
    y = np.clip(y, 0.0, 1.0)
    return np.where(y <= 0.04045, y / 12.92, np.power((y + 0.055) / 1.055, 2.4))


CRFS: dict[str, tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]]] = {
    "gamma3": (crf_gamma, crf_gamma_inverse),
    "filmic": (crf_filmic, crf_filmic_inverse),
    "srgb": (crf_srgb, crf_srgb_inverse),
}


def crf_curve(name: str) -> list[float]:
    """The response sampled at CRF_SAMPLES evenly spaced irradiances in [0, 1] (for camera_truth.json)."""
    x = np.linspace(0.0, 1.0, CRF_SAMPLES)
    return [float(v) for v in CRFS[name][0](x)]


# ----------------------------------------------------------------------------- per-view settings
@dataclass
class CameraSettings:
    """Everything the simulated camera did to one view (recorded in camera_truth.json)."""

    ev: float = 0.0
    wb_gains: tuple[float, float, float] = (1.0, 1.0, 1.0)
    crf: str = "gamma3"
    vignetting: tuple[float, float] = (0.0, 0.0)  # k1, k2
    noise: dict | None = None  # {"full_well": electrons, "read_noise": electrons, "seed": int}

    def to_dict(self) -> dict:
        d = asdict(self)
        d["crf_curve"] = crf_curve(self.crf)
        return d


@dataclass
class PipelineConfig:
    """What varies between views, and how (the varying variant; the static one fixes everything)."""

    ev_set: tuple[float, ...] = (-3.0, 0.0, 3.0)
    wb_gain: float = 1.25  # one channel per view is multiplied by this, as in the paper
    crfs: tuple[str, ...] = ("gamma3",)
    vignetting: tuple[float, float] = (0.0, 0.0)
    noise: bool = False
    full_well: float = 4000.0
    read_noise: float = 3.0
    seed: int = 0


def exposure_set(ev_range: float) -> tuple[float, ...]:
    """{-3, 0, +3} for the paper's +-3 EV; five evenly spaced levels for wider ranges (+-4, +-5, +-6)."""
    if ev_range == 3:
        return (-3.0, 0.0, 3.0)
    return tuple(float(v) for v in np.linspace(-ev_range, ev_range, 5))


def view_seed(seed: int, purpose: int, view: int) -> int:
    """Independent 31-bit seeds per (run seed, purpose, view), with no collisions between views."""
    return int(np.random.SeedSequence([seed, purpose, view]).generate_state(1)[0] >> 1)


SEED_SETTINGS, SEED_NOISE, SEED_RENDER, SEED_AUTO = 0, 1, 2, 3

# A phone's auto exposure and white balance (`auto_settings`): what a camera in the wild does, so that a
# model predicting a view's tone from the scene has a truth to be scored against.
AE_TARGET = 0.18  # the centre-weighted mean luminance the exposure brings the sensor to (18 % grey)
AE_CENTRE_SIGMA = 0.25  # the meter's centre weighting: a Gaussian of this many half-diagonals
AE_METER_NOISE = 0.1  # the meter's own error, stops (one standard deviation)
AWB_STRENGTH = 0.8  # the fraction of the grey-world cast the white balance removes
AWB_BIAS = (1.04, 1.0, 0.96)  # a warm bias on top, as phones keep some of a scene's warmth
AWB_NOISE = 0.02  # per-channel gain error (one standard deviation, relative)


def draw_settings(view: int, variant: str, cfg: PipelineConfig) -> CameraSettings:
    """The seeded settings of one view; `static` gives every view the same neutral settings (0 EV)."""
    noise = None
    if cfg.noise:
        seed = view_seed(cfg.seed, SEED_NOISE, view)
        noise = {"full_well": cfg.full_well, "read_noise": cfg.read_noise, "seed": seed}
    if variant == "static":
        return CameraSettings(0.0, (1.0, 1.0, 1.0), cfg.crfs[0], cfg.vignetting, noise)
    if variant != "varying":
        raise ValueError(f"unknown variant {variant!r}")
    rng = np.random.default_rng(view_seed(cfg.seed, SEED_SETTINGS, view))
    ev = float(rng.choice(cfg.ev_set))
    gains = [1.0, 1.0, 1.0]
    gains[int(rng.integers(0, 3))] = cfg.wb_gain
    crf = str(cfg.crfs[int(rng.integers(0, len(cfg.crfs)))])
    return CameraSettings(ev, tuple(gains), crf, cfg.vignetting, noise)


def auto_settings(view: int, radiance: np.ndarray, cfg: PipelineConfig) -> CameraSettings:
    """The camera a phone would choose for this view's linear radiance (H, W, 3): exposure from a
    centre-weighted mean of the luminance (plus the meter's noise), a grey-world white balance that removes
    AWB_STRENGTH of the cast, with a bias and noise; green's gain is 1. Response, vignetting and noise as
    the static variant's."""
    rng = np.random.default_rng(view_seed(cfg.seed, SEED_AUTO, view))
    h, w = radiance.shape[:2]
    rows = (np.arange(h) + 0.5) / h - 0.5
    cols = (np.arange(w) + 0.5) / w - 0.5
    weight = np.exp(-(rows[:, None] ** 2 + cols[None, :] ** 2) / 0.5 / (2 * AE_CENTRE_SIGMA**2))
    lum = radiance.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    metered = float((weight * lum).sum() / weight.sum())
    ev = np.log2(AE_TARGET / max(metered, 1e-8)) + AE_METER_NOISE * rng.standard_normal()
    ev = float(np.clip(ev, -8.0, 8.0))
    means = np.maximum(radiance.reshape(-1, 3).astype(np.float64).mean(0), 1e-8)
    gains = (means[1] / means) ** AWB_STRENGTH * np.asarray(AWB_BIAS)
    gains *= 1.0 + AWB_NOISE * rng.standard_normal(3)
    gains /= gains[1]
    noise = draw_settings(view, "static", cfg).noise  # the static variant's noise draw
    return CameraSettings(ev, tuple(float(g) for g in gains), cfg.crfs[0], cfg.vignetting, noise)


def sensor_irradiance(radiance: np.ndarray, s: CameraSettings) -> np.ndarray:
    """Light on the sensor after exposure and vignetting, before noise, white balance and clipping."""
    h, w = radiance.shape[:2]
    x = apply_exposure(radiance.astype(np.float32), s.ev)
    if s.vignetting != (0.0, 0.0):
        x = x * vignetting_factor(h, w, *s.vignetting)
    return x


def capture(radiance: np.ndarray, s: CameraSettings) -> np.ndarray:
    """The whole pipeline for one view: float32 (H, W, 3) linear radiance -> uint8 (H, W, 3)."""
    x = sensor_irradiance(radiance, s)
    if s.noise:
        rng = np.random.default_rng(s.noise["seed"])
        x = add_shot_noise(x, s.noise["full_well"], s.noise["read_noise"], rng)
    x = apply_white_balance(x, s.wb_gains)
    return quantize_8bit(CRFS[s.crf][0](clip_unit(x)))
