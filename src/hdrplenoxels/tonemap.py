"""The HDR-Plenoxels camera model: linear radiance -> LDR pixel, learned per image (method-spec §4).

    I = CRF_g(clip(V_i(row, col) * exp(w_i) * L))

- `w_i` (3,) log white balance per image and channel; it also carries exposure. The reference image's
  white balance is frozen at its data-derived initial value: that fixes the scale and colour gauge of
  the radiance field (without it, radiance x k and gains / k explain the images equally well).
- `V_i` optional vignetting 1 + k1 r^2 + k2 r^4 about a learned centre, r from (row/H, col/W) offsets
  (one convention in training and at test: the reference code transposes them, §7.3).
- `CRF_g` a piecewise-linear response per channel on 256 equal segments of [0, 1] with fixed ends 0 -> 0
  and 1 -> 1, initialised to x^(1/2.2), shared per camera (default), per image (the paper), or per scene. The
  lookup gathers each ray's own curve (the reference code's row-index bug, §4.6, is not copied).
- While training, irradiance outside [0, 1] continues with a small slope (`leak`) so that saturated
  pixels still pass gradient; at test time the curve clips.

Works after any renderer: it takes radiance, image indices and pixel coordinates, nothing else.
Per-ray parameters are fetched with `index_select`, whose backward is deterministic on CPU (advanced
indexing accumulates with atomics), so a resumed run reproduces an unbroken one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import nn

CRF_SEGMENTS = 256
INIT_GAMMA = 2.2
EPS = 1e-6

CrfSharing = Literal["image", "camera", "scene"]


@dataclass
class ToneMapConfig:
    enabled: bool = False  # on in the paper presets; opt-in for `fast` until its schedule is tuned for it
    # One curve per camera (a physical camera has one response). Measured with the fast preset on the
    # synthetic varying scenes: objects360 32.94 dB (camera/scene) vs 32.02 (per image, the paper's
    # choice); room 36.48 vs 35.17. Per image remains available for data with mixed responses.
    crf_sharing: CrfSharing = "camera"
    leak: float = 0.01  # slope beyond [0, 1] while training
    lambda_crf_smooth: float = 1e-3  # weight of the squared second differences of the knots ([-1, 1] units)
    vignetting: bool = False
    saturation_weighting: bool = False  # down-weight near-black and near-white targets in the loss
    lr: float = 1e-2
    lr_final: float = 5e-6
    lr_decay_steps: int = 250_000
    wb_init_from_data: bool = True


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


def piecewise_linear(x: torch.Tensor, knots: torch.Tensor) -> torch.Tensor:
    """Evaluate per-element curves: `knots` (..., K+1) at K equal segments of [0, 1]; x (...) in [0, 1]."""
    k = knots.shape[-1] - 1
    pos = x.clamp(0.0, 1.0) * k
    idx = pos.floor().clamp(max=k - 1).long()
    frac = pos - idx
    lo = torch.gather(knots, -1, idx[..., None])[..., 0]
    hi = torch.gather(knots, -1, idx[..., None] + 1)[..., 0]
    return lo + frac * (hi - lo)


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
        interior = (torch.arange(1, CRF_SEGMENTS, dtype=torch.float32) / CRF_SEGMENTS) ** (1.0 / INIT_GAMMA)
        self.crf_interior = nn.Parameter(interior[None, None, :].repeat(n_groups, 3, 1).contiguous())
        # Vignetting: centre offset (row, col) in units of H and W, and k1, k2.
        self.vignetting = nn.Parameter(torch.zeros(n_images, 4), requires_grad=cfg.vignetting)
        self.register_buffer("reference", torch.tensor(int(reference)))
        self.register_buffer("reference_log_wb", torch.zeros(3))

    # ----------------------------------------------------------------------------- gauge and init
    def set_reference(self, index: int, log_wb: torch.Tensor | None = None) -> None:
        """Freeze image `index`'s white balance (at `log_wb`, default its current value)."""
        with torch.no_grad():
            self.reference.fill_(int(index))
            value = self.log_wb[index] if log_wb is None else log_wb.to(self.log_wb)
            self.log_wb[index] = value
            self.reference_log_wb.copy_(value)

    @torch.no_grad()
    def init_from_images(self, channel_means: torch.Tensor) -> int:
        """White balance from linearised training-pixel statistics; picks and freezes the reference.

        `channel_means` (N, 3): per-image, per-channel means of (pixel / 255)^2.2 over *training* pixels
        only (full training views and left halves of test views). g_ic = ln(mu_ic / mean_i mu_ic); the
        reference is the image whose overall mean is closest to the dataset's. Returns its index.
        """
        mu = channel_means.clamp(min=EPS)
        self.log_wb.copy_(torch.log(mu / mu.mean(0, keepdim=True)))
        overall = mu.mean(1)
        reference = int(torch.argmin((overall - overall.mean()).abs()))
        self.set_reference(reference)
        return reference

    # ----------------------------------------------------------------------------- the model
    def knots(self) -> torch.Tensor:
        """All knots (groups, 3, 257) including the fixed ends 0 and 1."""
        g, c, _ = self.crf_interior.shape
        zeros = self.crf_interior.new_zeros(g, c, 1)
        return torch.cat([zeros, self.crf_interior, zeros + 1.0], dim=-1)

    def white_balance(self, image_ids: torch.Tensor) -> torch.Tensor:
        """exp(w_i) per ray (B, 3); the reference image's gains are the frozen constant (no gradient)."""
        log_wb = self.log_wb.index_select(0, image_ids)
        is_ref = (image_ids == self.reference)[:, None]
        return torch.exp(torch.where(is_ref, self.reference_log_wb.expand_as(log_wb), log_wb))

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
        knots = self.knots().index_select(0, groups)  # (B, 3, 257): each ray gathers its own curve
        y = piecewise_linear(e, knots)
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

    def loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Photometric loss (optionally saturation-weighted, really entering the loss) + CRF smoothness."""
        err = (pred - target) ** 2
        if self.cfg.saturation_weighting:
            err = err * saturation_weights(target)
        return err.mean() + self.cfg.lambda_crf_smooth * self.smoothness_loss()

    # ----------------------------------------------------------------------------- user controls
    def basis_log_wb(self) -> torch.Tensor:
        """The neutral camera for user controls: the mean of all views' log white balance (3,)."""
        return self.log_wb.detach().mean(0)

    def curve(self, image_id: int) -> torch.Tensor:
        """The response knots (3, 257) image `image_id` uses (to transfer to other renders)."""
        return self.knots().detach()[int(self.crf_group[image_id])]

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
            wb = torch.exp(self.log_wb).cpu()
            return {
                "reference": int(self.reference),
                "crf_sharing": self.cfg.crf_sharing,
                "white_balance": wb.tolist(),
                "log2_gain": torch.log2(wb).tolist(),
                "crf_group": self.crf_group.cpu().tolist(),
                "crf_knots": self.knots().cpu().tolist(),
                "vignetting": self.vignetting.detach().cpu().tolist() if self.cfg.vignetting else None,
            }


def controlled_ldr(radiance: torch.Tensor, log_gains: torch.Tensor, knots: torch.Tensor) -> torch.Tensor:
    """Radiance (..., 3) through chosen gains exp(log_gains) (3,) and one response (3, 257), clipped."""
    e = radiance * torch.exp(log_gains)
    flat = e.reshape(-1, 3)
    y = piecewise_linear(flat, knots[None].expand(flat.shape[0], -1, -1))
    return y.reshape(radiance.shape).clamp(0.0, 1.0)


def make_optimizer(tonemapper: ToneMapper) -> torch.optim.RMSprop:
    """torch RMSprop (alpha 0.95, as HDR-Plenoxels) over the trainable tone parameters; lr set per step."""
    params = [p for p in tonemapper.parameters() if p.requires_grad]
    return torch.optim.RMSprop(params, lr=tonemapper.cfg.lr, alpha=0.95, eps=1e-8)


def optimizer_arrays(opt: torch.optim.Optimizer) -> dict[str, np.ndarray]:
    out = {}
    for i, p in enumerate(opt.param_groups[0]["params"]):
        for key, value in opt.state.get(p, {}).items():
            out[f"{i}/{key}"] = torch.as_tensor(value).detach().cpu().numpy()
    return out


def load_optimizer_arrays(opt: torch.optim.Optimizer, arrays: dict[str, np.ndarray]) -> None:
    params = opt.param_groups[0]["params"]
    for name, value in arrays.items():
        i, key = name.split("/", 1)
        p = params[int(i)]
        device = p.device if key != "step" else "cpu"
        opt.state.setdefault(p, {})[key] = torch.as_tensor(value, device=device)
