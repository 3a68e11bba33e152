"""The HDR-Plenoxels camera model: linear radiance -> LDR pixel, learned per image (method-spec §4).

    I = CRF_g(clip(V_i(row, col) * exp(w_i) * L))

- `w_i` (3,) log white balance per image and channel; it also carries exposure. The reference image's
  white balance is frozen at its data-derived initial value: that fixes the scale and colour gauge of
  the radiance field (without it, radiance x k and gains / k explain the images equally well).
- `V_i` optional vignetting 1 + k1 r^2 + k2 r^4 about a learned centre, r from (row/H, col/W) offsets
  (one convention in training and at test: the reference code transposes them, §7.3).
- `CRF_g` a piecewise-linear response per channel on 256 equal segments of [0, 1] with fixed ends 0 -> 0
  and 1 -> 1, initialised to a straight line (the paper: x^(1/2.2); see `init_gamma`), shared per camera
  (default), per image (the paper), or per scene. The lookup gathers each ray's own curve (the reference
  code's row-index bug, §4.6, is not copied).
- While training, irradiance outside [0, 1] continues with a small slope (`leak`) so that saturated
  pixels still pass gradient; at test time the curve clips.

Works after any renderer: it takes radiance, image indices and pixel coordinates, nothing else.
Per-ray parameters are fetched with `index_select`, whose backward is deterministic on CPU (advanced
indexing accumulates with atomics), so a resumed run reproduces an unbroken one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import nn

CRF_SEGMENTS = 256
EPS = 1e-6
# The log-log prior samples the top 6 stops of the curve's input (below, 256 even knots get too coarse:
# the first segment alone spans every stop under 2^-8), a quarter stop apart, with the response clamped
# to a floor: codes this dark constrain nothing, and in log2 they would rule the prior (with 1e-5, the
# black background of objects360 drove the curve's foot down and its two-exposure median render fell
# from 25.3 to 14.6 dB on validation renders). Power laws steeper than x^1.6 reach the floor at 2^-6.
LOGLOG_STEPS_PER_STOP = 4
LOGLOG_SAMPLES = 6 * LOGLOG_STEPS_PER_STOP + 1
LOGLOG_FLOOR = 1e-3
# ToneMapConfig settings for brackets of few exposures far apart (the median-exposure experiment,
# `train --sparse-bracket`), chosen on validation renders trained on -3 and +3 EV views only: see
# ToneMapConfig.lambda_crf_loglog and ToneMapConfig.saturation_weighting.
SPARSE_BRACKET = {"lambda_crf_loglog": 1e-2, "saturation_weighting": True}

CrfSharing = Literal["image", "camera", "scene"]


@dataclass
class ToneMapConfig:
    enabled: bool = False  # on in the paper presets; opt-in for `fast` until its schedule is tuned for it
    # One curve per camera (a physical camera has one response; cameras are told apart by image size,
    # `Cameras.body_ids`). Measured with the fast preset on the synthetic varying scenes (one camera, so
    # camera = scene): objects360 32.94 dB vs 32.02 per image (the paper's choice); room 36.48 vs 35.17.
    # Per image remains available for data with mixed responses.
    crf_sharing: CrfSharing = "camera"
    leak: float = 0.01  # slope beyond [0, 1] while training
    lambda_crf_smooth: float = 1e-3  # weight of the squared second differences of the knots ([-1, 1] units)
    # Weight of the squared second differences of log2 response vs log2 irradiance (a power law is a
    # straight line there, so every gauge a of the exponential ambiguity costs nothing). With few exposure
    # ratios, self-calibration has more than that one ambiguity (Grossberg & Nayar): a wiggle of the
    # curve periodic in log irradiance, with the ratio as its period, fits the images equally well, and
    # the paper's smoothness on linear knots barely sees it. Measured on validation renders (30 other
    # views, other capture seed, fast preset). With only -3 and +3 EV views the median exposure between
    # them lands mid-period and needs the prior: room 26.3 dB without, 28.2 at 1e-4, 30.4 at 1e-3, 32.2 at
    # 1e-2 (SPARSE_BRACKET, `train --sparse-bracket`). With -3/0/+3 EV views the data fix the
    # curve: 1e-4 is within noise (room 34.72 vs 34.57 dB, objects360 32.81 vs 32.71; a table-s1 run at
    # 1e-4 moved the gap to static by +0.13 dB on room and -0.49 on objects360) and 3e-4 / 1e-3 / 1e-2
    # cost room 0.2 / 0.7 / 1.7 dB, so it is off unless asked for.
    lambda_crf_loglog: float = 0.0
    # Knot k sits at irradiance (k / 256)^(1 / knot_power). 1 is the paper's even spacing; smaller values
    # put more knots in the shadows, where camera responses are steepest (gamma 3 climbs to code 40 in
    # the first even segment, a straight line that cannot follow it).
    knot_power: float = 1.0
    # The starting response x^(1 / init_gamma); the white balance starts from image means linearised by
    # the same gamma. The start sets the gauge the grid learns in (about radiance^(1 / (3 init_gamma)) ..
    # radiance^(2 / (3 init_gamma)) for a gamma-3 camera), and the grid fits better near the pixels' own
    # encoding: with the true camera frozen in the gauge a = 1, 1/2, 1/3 the room scene reaches 31.4,
    # 35.3, 39.0 dB (static Plenoxels 38.8). So the curve starts linear, not at the paper's 2.2, which
    # left the grid at radiance^0.5 (validation renders, fast preset: room 30.2 -> 34.1 dB, static 34.2;
    # objects360 31.8 -> 32.2, static 31.9). Outputs are put back in a linear gauge (output_prior_gamma).
    init_gamma: float = 1.0
    vignetting: bool = False
    # Down-weight near-black and near-white targets in the loss (method-spec §4.8). Off by default: on
    # -3/0/+3 EV validation captures it moved PSNR by -0.12 / +0.16 / -0.44 dB (room / objects360 /
    # extreme), within run-to-run spread. With only -3 and +3 EV views most samples are black or clipped
    # codes, and it lifted the 0 EV render between them: room 31.75 -> 32.94 dB, extreme 27.19 -> 28.76,
    # objects360 25.62 -> 25.31 (SPARSE_BRACKET, `train --sparse-bracket`).
    saturation_weighting: bool = False
    lr: float = 1e-2
    lr_final: float = 5e-6
    lr_decay_steps: int = 250_000
    wb_init_from_data: bool = True
    # Start each view's exposure from the dataset's metadata (EXIF via `process`, HDR-NeRF exposure
    # times) instead of image statistics; colour balance still starts from the data. A start only.
    exposure_init_from_metadata: bool = False
    # Known exposure values (EXIF, or the generator's EVs) fix the exponential ambiguity of
    # self-calibration (radiance^a, exposures^a and CRF(x^(1/a)) fit the images equally well): after
    # training, a is fitted to the learned vs known exposures and every output is linearised by it. (Pinning
    # the exposures during training instead was measured on the room scene, fast preset: 26.5 dB vs 37.4.)
    known_exposure: bool = False
    # L2 on the grid's SH coefficients beyond the DC term, with the tone mapper only. Without it the SH
    # absorb a per-view exposure that varies smoothly with the view direction (a near-gauge between the
    # per-view white balance and view-dependent colour), which biases the learned EVs and novel views'
    # radiance. The weight was scanned on the experiment scenes (objects360, fast preset: EV error 0.162
    # -> 0.081 stops, HDR error 0.397 -> 0.254, -0.2 dB PSNR) and checked on validation renders: room EV
    # 0.211 -> 0.028, 34.1 -> 34.6 dB; objects360 EV 0.276 -> 0.192, 32.2 -> 32.7 dB. RMSProp normalises
    # the gradient, so even a small weight acts as a steady decay where the photometric gradient is weak.
    lambda_sh_view: float = 1e-6
    # The view prior applies for this fraction of the schedule only. Where a step's rays leave a voxel
    # untouched, RMSProp's running mean square decays until the prior's tiny gradient is all it sees, and
    # then moves the coefficient by about one learning rate per step: a steady pull of fine detail
    # towards no view dependence. Without cameras that vary, the prior cost room 1.0 dB (ours on its
    # static captures, fast preset: 37.17 dB, 38.20 without; Plenoxels 38.78). The exposure bias it
    # prevents forms early, so it stops at two thirds of the schedule. Validation renders (30 other
    # views, capture seed 7), prior always on -> until 2/3 (-> until 250 of 600 steps): PSNR room 35.49
    # -> 35.66 (35.78), objects360 32.71 -> 32.94 (32.92), extreme 32.42 -> 32.63 (32.83); EV error
    # .022 -> .019 (.014), .192 -> .209 (.245), .012 -> .012 (.024); median exposure +0.35..+0.81 dB.
    sh_view_until: float = 2.0 / 3.0
    # Without known exposures the exponent is a free gauge; outputs (EXR, EV controls, the exported
    # curves) use the one in which the learned response is closest to x^(1 / output_prior_gamma), the
    # usual display-referred camera response. None: the learned gauge, which follows from the start
    # (a linear start leaves the grid near the pixels' own encoding, about radiance^(1/3) here).
    output_prior_gamma: float | None = 2.2


def crf_group_ids(n_images: int, sharing: CrfSharing, camera_ids: list[int] | None = None) -> torch.Tensor:
    """Which response curve each image uses."""
    if sharing == "image":
        return torch.arange(n_images)
    if sharing == "scene":
        return torch.zeros(n_images, dtype=torch.long)
    if sharing == "camera":
        ids = camera_ids if camera_ids is not None else [0] * n_images
        _, inverse = np.unique(np.asarray(ids), return_inverse=True)
        return torch.as_tensor(inverse, dtype=torch.long)
    raise ValueError(f"unknown CRF sharing {sharing!r}")


def piecewise_linear(x: torch.Tensor, curves: torch.Tensor, curve_ids: torch.Tensor) -> torch.Tensor:
    """Evaluate element-wise curves: element j of `x` (in [0, 1]) through row `curve_ids[j]` of `curves`
    (M, K+1), knots at K equal segments of [0, 1].

    Two `index_select`s on the flattened table fetch each element's bracketing knots: O(elements), not
    O(elements x knots) as gathering whole curves per ray would be, and deterministic in backward.
    """
    k = curves.shape[-1] - 1
    pos = x.clamp(0.0, 1.0) * k
    idx = pos.floor().clamp(max=k - 1).long()
    frac = pos - idx
    flat_idx = (curve_ids * (k + 1) + idx).reshape(-1)
    table = curves.reshape(-1)
    lo = table.index_select(0, flat_idx).reshape(x.shape)
    hi = table.index_select(0, flat_idx + 1).reshape(x.shape)
    return lo + frac * (hi - lo)


WARP_EPS = 1e-6  # keeps the knot-coordinate warp's slope finite at 0


def knot_coordinate(x: torch.Tensor, power: float) -> torch.Tensor:
    """Irradiance in [0, 1] -> position on the knot axis in [0, 1] (identity for even spacing)."""
    x = x.clamp(0.0, 1.0)
    if power == 1.0:
        return x
    lo, hi = WARP_EPS**power, (1.0 + WARP_EPS) ** power
    return ((x + WARP_EPS) ** power - lo) / (hi - lo)


def knot_positions(n_knots: int, power: float) -> np.ndarray:
    """The irradiance of every knot (inverse of `knot_coordinate` at k / (n_knots - 1))."""
    u = np.linspace(0.0, 1.0, n_knots)
    if power == 1.0:
        return u
    lo, hi = WARP_EPS**power, (1.0 + WARP_EPS) ** power
    x = np.clip((u * (hi - lo) + lo) ** (1.0 / power) - WARP_EPS, 0.0, 1.0)
    x[0], x[-1] = 0.0, 1.0  # exact ends (rounding leaves ~1e-22)
    return x


@dataclass
class ResponseCurve:
    """One camera response per channel: knot values (3, K+1) on the knot axis of `power`, taking
    irradiance^exponent (the model's gauge) when called with linear irradiance."""

    knots: torch.Tensor
    power: float = 1.0
    exponent: float = 1.0

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """x (..., 3) linear irradiance -> pixel values (..., 3), clipped to [0, 1]."""
        flat = x.reshape(-1, 3).clamp(min=0.0) ** self.exponent
        ids = torch.arange(3, device=flat.device).expand_as(flat)
        y = piecewise_linear(knot_coordinate(flat, self.power), self.knots.to(flat), ids)
        return y.reshape(x.shape).clamp(0.0, 1.0)


def saturation_weights(target: torch.Tensor) -> torch.Tensor:
    """Loss weight per target value (method-spec §4.8): 1 on [0.15, 0.9], falling to 0.25 at 0 and 1."""
    low = ((target + 0.15) / 0.3) ** 2
    high = ((target - 1.1) / 0.2) ** 2
    return torch.where(target < 0.15, low, torch.where(target > 0.9, high, torch.ones_like(target)))


class ToneMapper(nn.Module):
    """Per-image white balance (with exposure), optional vignetting and grouped response curves."""

    def __init__(
        self,
        n_images: int,
        image_sizes: np.ndarray,
        cfg: ToneMapConfig,
        camera_ids: list[int] | None = None,
        reference: int = 0,
    ):
        super().__init__()
        self.cfg = cfg
        groups = crf_group_ids(n_images, cfg.crf_sharing, camera_ids)
        self.register_buffer("crf_group", groups)
        sizes = torch.as_tensor(np.asarray(image_sizes), dtype=torch.float32)
        self.register_buffer("sizes", sizes)  # (N, 2): W, H
        self.log_wb = nn.Parameter(torch.zeros(n_images, 3))
        n_groups = int(groups.max()) + 1
        positions = knot_positions(CRF_SEGMENTS + 1, cfg.knot_power)[1:-1]
        interior = torch.as_tensor(positions, dtype=torch.float32) ** (1.0 / cfg.init_gamma)
        self.crf_interior = nn.Parameter(interior[None, None, :].repeat(n_groups, 3, 1).contiguous())
        # Vignetting: centre offset (row, col) in units of H and W, and k1, k2.
        self.vignetting = nn.Parameter(torch.zeros(n_images, 4), requires_grad=cfg.vignetting)
        self.register_buffer("reference", torch.tensor(int(reference)))
        self.register_buffer("reference_log_wb", torch.zeros(3))
        self.register_buffer("known_log_exposure", torch.zeros(n_images))  # ln(2) * EV, when known
        self.register_buffer("exponent", torch.tensor(1.0))  # a: learned radiance ~ linear radiance^a

    # ----------------------------------------------------------------------------- gauge and init
    def set_reference(self, index: int, log_wb: torch.Tensor | None = None) -> None:
        """Freeze image `index`'s white balance (at `log_wb`, default its current value)."""
        with torch.no_grad():
            self.reference.fill_(int(index))
            value = self.log_wb[index] if log_wb is None else log_wb.to(self.log_wb)
            self.log_wb[index] = value
            self.reference_log_wb.copy_(value)

    @torch.no_grad()
    def init_from_images(self, channel_means: torch.Tensor, candidates: list[int] | None = None) -> int:
        """White balance from linearised training-pixel statistics; picks and freezes the reference.

        `channel_means` (N, 3): per-image, per-channel means of pixels / 255 linearised by the starting
        response (raised to `init_gamma`: 1 by default, the paper's 2.2 as an option) over *training* pixels
        only (full training views and left halves of test views). g_ic = ln(mu_ic / mean_i mu_ic); the
        reference is the image among `candidates` (default: all) whose overall mean is closest to the
        dataset's. Returns its index.

        Pass the full training views as candidates. The grid and the other views can drift together in
        scale, which only the reference's own pixels resist; a test view has only its left half to do
        that, and its frozen white balance is then wrong on the scored right half (objects360, view 32:
        29.2 dB, 30.5 with its training twins' mean white balance).
        """
        mu = channel_means.clamp(min=EPS)
        self.log_wb.copy_(torch.log(mu / mu.mean(0, keepdim=True)))
        overall = mu.mean(1)
        ids = torch.as_tensor(candidates if candidates is not None else range(len(mu)), dtype=torch.long)
        reference = int(ids[torch.argmin((overall[ids] - overall.mean()).abs())])
        self.set_reference(reference)
        return reference

    @torch.no_grad()
    def init_exposures(self, evs: torch.Tensor) -> None:
        """Replace each view's channel-mean log gain by its metadata EV (stops, relative to the reference),
        keeping the per-channel colour balance; the reference stays frozen at its own value."""
        log_ev = torch.as_tensor(evs, dtype=self.log_wb.dtype, device=self.log_wb.device) * math.log(2.0)
        ref = int(self.reference)
        log_ev = log_ev - log_ev[ref] + self.log_wb[ref].mean()
        self.log_wb.add_(log_ev[:, None] - self.log_wb.mean(1, keepdim=True))
        self.set_reference(ref)

    @torch.no_grad()
    def set_known_exposures(self, evs: torch.Tensor) -> None:
        """Each view's exposure value in stops (N,); only differences between views matter."""
        if not self.cfg.known_exposure:
            raise ValueError("known exposures given but the tone-mapping config has known_exposure off")
        self.known_log_exposure.copy_(torch.as_tensor(evs, dtype=torch.float32) * math.log(2.0))

    # ----------------------------------------------------------------------------- the model
    def effective_log_wb(self) -> torch.Tensor:
        """The log white balance every image uses (N, 3), the reference's frozen (learned gauge)."""
        is_ref = (torch.arange(self.log_wb.shape[0], device=self.log_wb.device) == self.reference)[:, None]
        return torch.where(is_ref, self.reference_log_wb.expand_as(self.log_wb), self.log_wb)

    @torch.no_grad()
    def fit_exponent_to_response_prior(self, gamma: float) -> float:
        """Pick the output gauge of a self-calibrated model: the exponent e (learned radiance = linear^e)
        whose response f(X^e) over linear X in [0, 1] is closest to X^(1 / gamma), over all curves."""
        x = torch.linspace(0.0, 1.0, 257, dtype=torch.float64)[:, None].expand(-1, 3)
        target = x ** (1.0 / gamma)
        candidates = torch.logspace(math.log10(0.05), math.log10(5.0), 401, dtype=torch.float64)
        learned = x[None] ** candidates[:, None, None]  # (candidates, 257, 3): X^e for every candidate
        groups = sorted({int(g): i for i, g in enumerate(self.crf_group.tolist())}.values())
        errors = torch.zeros(len(candidates), dtype=torch.float64)
        for i in groups:
            curve = self.curve(i)
            curve = ResponseCurve(curve.knots.double(), curve.power)  # takes learned radiance as it is
            errors += ((curve(learned.to(curve.knots.device)).cpu() - target) ** 2).mean((1, 2))
        exponent = float(candidates[int(errors.argmin())])
        self.exponent.fill_(exponent)
        return exponent

    @torch.no_grad()
    def fit_exponent_to_known(self) -> float:
        """Fit a (least squares slope of learned vs known per-view log exposure) and store it."""
        level = self.effective_log_wb().mean(1).double()
        known = self.known_log_exposure.double()
        kc = known - known.mean()
        if float((kc * kc).sum()) < 1e-12:
            raise ValueError("the known exposures are all equal: they cannot fix the exponent")
        a = float((kc * (level - level.mean())).sum() / (kc * kc).sum())
        if not a > 0.05:
            raise ValueError(f"learned exposures do not follow the known ones (fitted exponent {a:.3g})")
        self.exponent.fill_(a)
        return a

    # Linear outputs: the grid holds radiance^a in the learned gauge; users get it linearised by 1 / a
    # (a = 1 unless known exposures fixed it), so that EXR files and EV controls are in true stops.
    def linear_radiance(self, radiance: torch.Tensor) -> torch.Tensor:
        return radiance.clamp(min=0.0) ** (1.0 / float(self.exponent))

    def learned_radiance(self, linear: torch.Tensor) -> torch.Tensor:
        """The inverse of `linear_radiance`: what the grid would render for a linear radiance."""
        return linear.clamp(min=0.0) ** float(self.exponent)

    def linear_log_wb(self) -> torch.Tensor:
        return self.effective_log_wb().detach() / float(self.exponent)

    def knots(self) -> torch.Tensor:
        """All knots (groups, 3, 257) including the fixed ends 0 and 1."""
        g, c, _ = self.crf_interior.shape
        zeros = self.crf_interior.new_zeros(g, c, 1)
        return torch.cat([zeros, self.crf_interior, zeros + 1.0], dim=-1)

    def white_balance(self, image_ids: torch.Tensor) -> torch.Tensor:
        """exp(w_i) per ray (B, 3); the reference image's gains are the frozen constant (no gradient)."""
        return torch.exp(self.effective_log_wb().index_select(0, image_ids))

    def vignetting_factor(
        self, image_ids: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor
    ) -> torch.Tensor:
        """1 + k1 r^2 + k2 r^4 (B, 1), clamped >= 0, r from ((row+0.5)/H - 0.5 - a, (col+0.5)/W - 0.5 - b)."""
        p = self.vignetting.index_select(0, image_ids)
        w, h = self.sizes[image_ids].unbind(-1)
        dr = (rows.float() + 0.5) / h - 0.5 - p[:, 0]
        dc = (cols.float() + 0.5) / w - 0.5 - p[:, 1]
        r2 = dr * dr + dc * dc
        return (1.0 + p[:, 2] * r2 + p[:, 3] * r2 * r2).clamp(min=0.0)[:, None]

    def irradiance(self, radiance, image_ids, rows=None, cols=None) -> torch.Tensor:
        """What reaches the response curve: white-balanced (and vignetted) radiance, (B, 3)."""
        e = radiance * self.white_balance(image_ids)
        if self.cfg.vignetting:
            e = e * self.vignetting_factor(image_ids, rows, cols)
        return e

    def apply_crf(self, e: torch.Tensor, groups: torch.Tensor, training: bool) -> torch.Tensor:
        """Per-ray, per-channel curve lookup; leaky beyond [0, 1] while training, clipped at test."""
        curve_ids = groups[:, None] * 3 + torch.arange(3, device=e.device)  # each ray's own curves
        u = knot_coordinate(e, self.cfg.knot_power)
        y = piecewise_linear(u, self.knots().reshape(-1, CRF_SEGMENTS + 1), curve_ids)
        if training and self.cfg.leak > 0:
            y = y + self.cfg.leak * ((e - 1.0).clamp(min=0.0) + e.clamp(max=0.0))
        return y

    def forward(
        self,
        radiance: torch.Tensor,
        image_ids: torch.Tensor,
        rows: torch.Tensor | None = None,
        cols: torch.Tensor | None = None,
        training: bool = True,
    ) -> torch.Tensor:
        """LDR values (B, 3) of rays with linear `radiance` (B, 3) from images `image_ids` (B,)."""
        e = self.irradiance(radiance, image_ids, rows, cols)
        return self.apply_crf(e, self.crf_group[image_ids], training)

    def smoothness_loss(self) -> torch.Tensor:
        """Sum of squared second differences of every curve's knots, measured in [-1, 1] units (as trained
        in the paper, so the 1e-3 weight keeps its meaning)."""
        k = 2.0 * self.knots() - 1.0
        return ((k[..., :-2] - 2.0 * k[..., 1:-1] + k[..., 2:]) ** 2).sum()

    def loglog_smoothness_loss(self) -> torch.Tensor:
        """Sum of squared second differences of log2 f at irradiance 2^(-k/4), k = 0..LOGLOG_SAMPLES-1,
        over every curve: zero for any power law, so it leaves the exponential gauge free."""
        x = torch.exp2(-torch.arange(LOGLOG_SAMPLES, device=self.crf_interior.device) / LOGLOG_STEPS_PER_STOP)
        u = knot_coordinate(x, self.cfg.knot_power)
        curves = self.knots().reshape(-1, CRF_SEGMENTS + 1)
        ids = torch.arange(curves.shape[0], device=x.device)[:, None].expand(-1, LOGLOG_SAMPLES)
        y = torch.log2(piecewise_linear(u.expand_as(ids), curves, ids).clamp(min=LOGLOG_FLOOR))
        return ((y[:, :-2] - 2.0 * y[:, 1:-1] + y[:, 2:]) ** 2).sum()

    def loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Photometric loss (optionally saturation-weighted, really entering the loss) + CRF priors."""
        err = (pred - target) ** 2
        if self.cfg.saturation_weighting:
            err = err * saturation_weights(target)
        loss = err.mean() + self.cfg.lambda_crf_smooth * self.smoothness_loss()
        if self.cfg.lambda_crf_loglog > 0:
            loss = loss + self.cfg.lambda_crf_loglog * self.loglog_smoothness_loss()
        return loss

    # ----------------------------------------------------------------------------- user controls
    def basis_log_wb(self) -> torch.Tensor:
        """The neutral camera for user controls: the mean of all views' log white balance (3,)."""
        return self.linear_log_wb().mean(0)

    def curve(self, image_id: int) -> ResponseCurve:
        """The response image `image_id` uses, on linear irradiance (to transfer to other renders)."""
        knots = self.knots().detach()[int(self.crf_group[image_id])]
        return ResponseCurve(knots, self.cfg.knot_power, float(self.exponent))

    # ----------------------------------------------------------------------------- persistence
    def state_arrays(self) -> dict[str, np.ndarray]:
        return {k: v.detach().cpu().numpy() for k, v in self.state_dict().items()}

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore from `state_arrays()`, whatever the number of curve groups the arrays hold."""
        device = self.log_wb.device
        for name, value in arrays.items():
            tensor = torch.as_tensor(value, device=device)
            current = getattr(self, name)
            if isinstance(current, nn.Parameter):
                trainable = current.requires_grad
                setattr(self, name, nn.Parameter(tensor.to(current.dtype), requires_grad=trainable))
            else:
                setattr(self, name, tensor.to(current.dtype))

    # ----------------------------------------------------------------------------- export
    def parameters_dict(self) -> dict:
        """Learned parameters as plain lists (for JSON): EV and gains per image, curves per group."""
        with torch.no_grad():
            wb = torch.exp(self.linear_log_wb()).cpu()
            return {
                "reference": int(self.reference),
                "crf_sharing": self.cfg.crf_sharing,
                "knot_power": self.cfg.knot_power,
                "known_exposure": self.cfg.known_exposure,
                "exponent": float(self.exponent),
                "white_balance": wb.tolist(),
                "log2_gain": torch.log2(wb).tolist(),
                "crf_group": self.crf_group.cpu().tolist(),
                "crf_knots": self.knots().cpu().tolist(),
                # In output (linear) units, where the white balance above is too.
                "crf_knot_irradiance": (
                    knot_positions(CRF_SEGMENTS + 1, self.cfg.knot_power) ** (1.0 / float(self.exponent))
                ).tolist(),
                "vignetting": self.vignetting.detach().cpu().tolist() if self.cfg.vignetting else None,
                "image_size": self.sizes.cpu().int().tolist(),
            }

    @classmethod
    def from_parameters_dict(cls, params: dict) -> ToneMapper:
        """The inverse of `parameters_dict` (a run's camera_params.json), so that learned cameras, or
        hand-edited ones, can be applied to other renders and runs by file. Raises ValueError naming
        what is missing or malformed."""
        try:
            wb = torch.as_tensor(params["white_balance"], dtype=torch.float32)
            knots = torch.as_tensor(params["crf_knots"], dtype=torch.float32)
            groups = torch.as_tensor(params["crf_group"], dtype=torch.long)
            exponent, reference = float(params["exponent"]), int(params["reference"])
            vignetting = params.get("vignetting")
            cfg = ToneMapConfig(
                enabled=True,
                crf_sharing=params["crf_sharing"],
                knot_power=float(params.get("knot_power", 1.0)),
                known_exposure=bool(params.get("known_exposure", False)),
                vignetting=vignetting is not None,
            )
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"not a camera_params.json: {type(e).__name__} {e}") from None
        n = len(wb)
        if wb.shape != (n, 3) or not bool((wb > 0).all()) or not exponent > 0:
            raise ValueError("white_balance must be positive (views, 3) gains and exponent positive")
        if knots.ndim != 3 or knots.shape[1:] != (3, CRF_SEGMENTS + 1):
            raise ValueError(f"crf_knots must be (curves, 3, {CRF_SEGMENTS + 1})")
        if groups.shape != (n,) or not 0 <= int(groups.min()) <= int(groups.max()) < len(knots):
            raise ValueError("crf_group must name one of the curves for every view")
        if not 0 <= reference < n:
            raise ValueError(f"reference {reference} is not a view (0..{n - 1})")
        sizes = np.asarray(params.get("image_size") or np.zeros((n, 2)), dtype=np.float32)
        tm = cls(n, sizes, cfg, reference=reference)
        arrays = {
            "crf_group": groups,
            "crf_interior": knots[:, :, 1:-1].contiguous(),
            "exponent": torch.tensor(exponent),
            "log_wb": torch.log(wb) * exponent,  # the file holds the linear (output) gauge
        }
        if vignetting is not None:
            arrays["vignetting"] = torch.as_tensor(vignetting, dtype=torch.float32)
        tm.load_state_arrays(arrays)
        tm.set_reference(reference)
        return tm


def controlled_ldr(radiance: torch.Tensor, log_gains: torch.Tensor, curve: ResponseCurve) -> torch.Tensor:
    """Linear radiance (..., 3) through gains exp(log_gains) (3,) and one response, clipped to [0, 1]."""
    return curve(radiance * torch.exp(log_gains))
