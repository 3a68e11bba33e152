"""The HDR-Plenoxels tone mapper: linear radiance -> LDR pixel, a tone learned per image (docs/method.md,
"Tone mapping").

    I = CRF_g(clip(V_i(row, col) * exp(w_i) * L))

- `w_i` (3,) log white balance per image and channel; it also carries exposure. The reference image's
  white balance is frozen at its data-derived initial value: that fixes the scale and colour gauge of
  the radiance field (without it, radiance x k and gains / k explain the images equally well).
- `V_i` optional vignetting 1 + k1 r^2 + k2 r^4 about a learned centre, r from (row/H, col/W) offsets
  (one convention in training and at test: the reference code transposes them; docs/method.md, "Fixes to
  the reference code").
- `CRF_g` a piecewise-linear response per channel (`response.py`), initialised to a straight line (the
  paper: x^(1/2.2); see `init_gamma`), shared per camera (default), per image (the paper), or per scene.
  The lookup gathers each ray's own curve (the reference code's row-index bug is not copied).
- While training, irradiance outside [0, 1] continues with a small slope (`leak`) so that saturated
  pixels still pass gradient; at test time the curve clips.

Works after any renderer: it takes radiance, image indices and pixel coordinates, nothing else.
Per-ray parameters are fetched with `index_select`, whose backward is deterministic on CPU (advanced
indexing accumulates with atomics), so a resumed run reproduces an unbroken one.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from hdrplenoxels.kernels.dispatch import use_kernel
from hdrplenoxels.tonemap.config import CrfSharing, ToneMapConfig
from hdrplenoxels.tonemap.gauge import known_exposure_exponent, response_prior_exponent
from hdrplenoxels.tonemap.loss_kernel import fused_training_loss
from hdrplenoxels.tonemap.loss_reference import training_loss_reference
from hdrplenoxels.tonemap.params_io import parameters_dict, parse_parameters
from hdrplenoxels.tonemap.pixels import PixelTargets
from hdrplenoxels.tonemap.response import (
    CRF_SEGMENTS,
    ResponseCurve,
    knot_coordinate,
    knot_positions,
    piecewise_linear,
)

EPS = 1e-6
# The log-log prior samples the top 6 stops of the curve's input (below, 256 even knots get too coarse:
# the first segment alone spans every stop under 2^-8), a quarter stop apart, with the response clamped
# to a floor: codes this dark constrain nothing, and in log2 they would rule the prior (a lower floor let
# a black background drive the curve's foot down: JOURNAL.md). Power laws steeper than x^1.6
# reach the floor at 2^-6.
LOGLOG_STEPS_PER_STOP = 4
LOGLOG_SAMPLES = 6 * LOGLOG_STEPS_PER_STOP + 1
LOGLOG_FLOOR = 1e-3


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


def saturation_weights(target: torch.Tensor) -> torch.Tensor:
    """Loss weight per target value: 1 on [0.15, 0.9], falling to 0.25 at 0 and 1 (docs/method.md, "Tone
    mapping": darker and brighter codes say less about the response)."""
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
        # The exposures the photos state, in stops (N,), where training holds the learned ones' ratios to
        # them, else None; not saved: each run (a resumed one too) sets it from its scene (`tone_setup`).
        self.register_buffer("stated_stops", None, persistent=False)

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
        that, and its frozen white balance is then wrong on the scored right half (JOURNAL.md).
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

    @torch.no_grad()
    def set_stated_exposures(self, evs: torch.Tensor) -> None:
        """The exposures the photos state, in stops (N,): a `--known-exposure` file's or their EXIF, to whose
        ratios `exposure_ratio_loss` holds the learned ones."""
        stops = torch.as_tensor(evs, dtype=torch.float32, device=self.log_wb.device)
        if stops.shape != (self.log_wb.shape[0],):
            raise ValueError(f"{stops.shape[0]} stated exposures for {self.log_wb.shape[0]} views")
        self.stated_stops = stops

    # ----------------------------------------------------------------------------- the model
    def effective_log_wb(self) -> torch.Tensor:
        """The log white balance every image uses (N, 3), the reference's frozen (learned gauge)."""
        is_ref = (torch.arange(self.log_wb.shape[0], device=self.log_wb.device) == self.reference)[:, None]
        return torch.where(is_ref, self.reference_log_wb.expand_as(self.log_wb), self.log_wb)

    @torch.no_grad()
    def fit_exponent_to_response_prior(self, gamma: float) -> float:
        """Pick and store the output gauge of a self-calibrated model: the exponent whose responses are
        closest to X^(1 / gamma) (`gauge.response_prior_exponent`), one curve per group."""
        groups = sorted({int(g): i for i, g in enumerate(self.crf_group.tolist())}.values())
        exponent = response_prior_exponent([self.curve(i).knots for i in groups], self.cfg.knot_power, gamma)
        self.exponent.fill_(exponent)
        return exponent

    @torch.no_grad()
    def fit_exponent_to_exposures(self, evs: torch.Tensor) -> float:
        """Fit and store a from learned per-view log exposures against `evs` (stops, e.g. the photos'
        EXIF), which then count as the known exposures; a ValueError (nothing changed) where they cannot
        fix it (`gauge.known_exposure_exponent`)."""
        known = torch.as_tensor(evs, dtype=torch.float32, device=self.log_wb.device) * math.log(2.0)
        a = known_exposure_exponent(self.effective_log_wb().mean(1), known)
        self.known_log_exposure.copy_(known)
        self.exponent.fill_(a)
        return a

    @torch.no_grad()
    def fit_exponent_to_known(self) -> float:
        """Fit and store a from learned vs known per-view log exposures (`gauge.known_exposure_exponent`)."""
        a = known_exposure_exponent(self.effective_log_wb().mean(1), self.known_log_exposure)
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

    def exposure_ratio_loss(self) -> torch.Tensor:
        """Mean squared departure of each view's learned log exposure (the channel mean of its log white
        balance) from the least-squares line in its stated exposure (`stated_stops`): zero for every
        slope, the exponent self-calibration leaves free (docs/method.md, "Gauge"), and every offset."""
        if self.stated_stops is None:
            raise ValueError("no stated exposures set (set_stated_exposures)")
        level = self.effective_log_wb().mean(1)
        stated = self.stated_stops - self.stated_stops.mean()
        centred = level - level.mean()
        slope = (stated * centred).sum() / (stated * stated).sum().clamp(min=1e-12)
        return ((centred - slope * stated) ** 2).mean()

    def pytorch_priors(self) -> torch.Tensor | float:
        """The priors PyTorch computes on either path of the training loss (the fused one computes the
        curves' smoothness in its kernel): the log-log prior and the exposure ratios', where weighted."""
        prior: torch.Tensor | float = 0.0
        if self.cfg.lambda_crf_loglog > 0:
            prior = prior + self.cfg.lambda_crf_loglog * self.loglog_smoothness_loss()
        if self.cfg.lambda_exposure_ratios > 0 and self.stated_stops is not None:
            prior = prior + self.cfg.lambda_exposure_ratios * self.exposure_ratio_loss()
        return prior

    def loss(self, pred: torch.Tensor, target: torch.Tensor, weighted: bool | None = None) -> torch.Tensor:
        """Photometric loss (saturation-weighted, really entering the loss, where `weighted` says so;
        default: `cfg.saturation_weighting`) + the curves' and the exposures' priors."""
        err = (pred - target) ** 2
        if weighted is None:
            weighted = self.cfg.saturation_weighting
        if weighted:
            err = err * saturation_weights(target)
        return err.mean() + self.cfg.lambda_crf_smooth * self.smoothness_loss() + self.pytorch_priors()

    def training_loss(
        self, radiance: torch.Tensor, pixels: PixelTargets
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`loss(self(radiance, ..., training=True), pixels.target)` and the plain MSE (no gradient) of a
        training batch. On CUDA the loss and its gradients come from two kernels (`loss_kernel.py`: a
        hundred fewer small kernels a step), on a CPU from PyTorch's operators, which are faster there
        (`kernels.dispatch.use_kernel`). An empty batch is refused (its mean is undefined)."""
        if radiance.shape[0] == 0:
            raise ValueError("the tone mapper's training loss needs at least one ray")
        loss = fused_training_loss if use_kernel(radiance) else training_loss_reference
        return loss(self, radiance, pixels)

    @torch.no_grad()
    def constrain(self) -> None:
        """Each curve non-decreasing and within [0, 1] when `cfg.response` is "monotonic" (else nothing):
        the mean of its running maximum from the dark end and its running minimum from the bright end,
        both non-decreasing, so their mean is too, and a curve already in order is left as it is. The
        trainer calls it once, after the last step."""
        if self.cfg.response != "monotonic":
            return
        k = self.crf_interior.clamp(0.0, 1.0)
        rising = torch.cummax(k, dim=-1).values
        falling = torch.flip(torch.cummin(torch.flip(k, [-1]), dim=-1).values, [-1])
        self.crf_interior.copy_(0.5 * (rising + falling))

    # ----------------------------------------------------------------------------- user controls
    def basis_log_wb(self, ids: list[int] | None = None) -> torch.Tensor:
        """The neutral tone for user controls: the mean log white balance (3,) of views `ids` (default:
        all)."""
        learned = self.linear_log_wb()
        return learned.mean(0) if ids is None else learned[ids].mean(0)

    def curve(self, image_id: int) -> ResponseCurve:
        """The response image `image_id` uses, on linear irradiance (to transfer to other renders)."""
        knots = self.knots().detach()[int(self.crf_group[image_id])]
        return ResponseCurve(knots, self.cfg.knot_power, float(self.exponent))

    # ----------------------------------------------------------------------------- persistence
    def state_arrays(self) -> dict[str, np.ndarray]:
        """Copies, never views of a CPU tone mapper's tensors: a checkpoint written on another thread keeps
        the values of when it was taken (`train/run_end.py` fits the gauge meanwhile)."""
        return {k: v.detach().cpu().numpy().copy() for k, v in self.state_dict().items()}

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore from `state_arrays()`, whatever the number of curve groups the arrays hold; a
        ValueError (nothing changed) when the arrays do not describe this many images."""
        device = self.log_wb.device
        tensors = self._checked_state(arrays)
        for name, tensor in tensors.items():
            tensor = tensor.to(device)
            current = getattr(self, name)
            if isinstance(current, nn.Parameter):
                trainable = current.requires_grad
                setattr(self, name, nn.Parameter(tensor.to(current.dtype), requires_grad=trainable))
            else:
                setattr(self, name, tensor.to(current.dtype))

    def _checked_state(self, arrays: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """`arrays` (all or some of the state) as tensors, checked against this module's state: known
        names, the same shapes except for the number of curve groups, indices in range."""
        current = self.state_dict()
        unknown = sorted(set(arrays) - set(current))
        if unknown:
            raise ValueError(f"unknown tone-mapping state {unknown}; it holds {sorted(current)}")
        tensors = {}
        for name, value in arrays.items():
            value = np.asarray(value)
            if value.dtype.kind not in "biuf":
                raise ValueError(f"tone-mapping {name} must be numbers, got {value.dtype}")
            tensors[name] = torch.as_tensor(value.astype(np.float64 if value.dtype.kind == "f" else np.int64))
            want, got = tuple(current[name].shape), tuple(tensors[name].shape)
            free_groups = name == "crf_interior" and len(got) == 3 and got[0] >= 1 and got[1:] == want[1:]
            if got != want and not free_groups:
                raise ValueError(f"tone-mapping {name} must have shape {want}, got {got}")
        merged = current | tensors
        groups, n_images = merged["crf_interior"].shape[0], self.log_wb.shape[0]
        if not bool(((merged["crf_group"] >= 0) & (merged["crf_group"] < groups)).all()):
            raise ValueError(f"tone-mapping crf_group must index the {groups} curve groups")
        if not 0 <= int(merged["reference"]) < n_images:
            raise ValueError(f"tone-mapping reference must be an image index below {n_images}")
        return tensors

    # ----------------------------------------------------------------------------- export
    def parameters_dict(self) -> dict:
        """Learned parameters as plain lists for tone_params.json (`params_io.parameters_dict`)."""
        return parameters_dict(self)

    @classmethod
    def from_parameters_dict(cls, params: dict) -> ToneMapper:
        """The inverse of `parameters_dict` (a run's tone_params.json), so that learned tones, or
        hand-edited ones, can be applied to other renders and runs by file. Raises ValueError naming
        what is missing or malformed."""
        p = parse_parameters(params)
        tm = cls(len(p.state["log_wb"]), p.image_size, p.cfg, reference=p.reference)
        tm.load_state_arrays(p.state)
        tm.set_reference(p.reference)
        return tm
