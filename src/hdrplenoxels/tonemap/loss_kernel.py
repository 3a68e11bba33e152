"""The tone mapper's photometric training loss and its gradients in one Warp pass over a batch's rays.

Through PyTorch the loss of a batch (white balance, vignetting, the curve lookup, the leak, the weighted
mean) and its autograd backward are about a hundred small operators a step, each a kernel of a replayed
step on a GPU (JOURNAL.md, "Fused kernels"). Here one thread per ray maps its radiance,
compares it with its pixel, writes d loss / d radiance beside the ray and adds the tone parameters'
gradients (white balance, vignetting, the knots either side of each lookup) with atomic adds, in the
same pass; the autograd function hands them on scaled by the loss's incoming gradient. The trainer takes
it on CUDA only (`kernels.dispatch.use_kernel`). On a CPU the launch runs on one thread, so the adds come in
ray order and a call repeats itself bit for bit.

The gradients follow PyTorch's conventions at the kinks: `clamp` passes gradient at its bounds, as the
oracle's clamps do.

Oracle: `hdrplenoxels.tonemap.loss_reference.training_loss_reference`; parity: tests/test_tone_loss.py.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, launch_kernel, to_warp, warp_device, warp_struct
from hdrplenoxels.kernels.ray_draw_kernel import DrawnPixels, drawn_pixels
from hdrplenoxels.tonemap.pixels import PixelTargets
from hdrplenoxels.tonemap.response import WARP_EPS

if TYPE_CHECKING:
    from hdrplenoxels.tonemap.module import ToneMapper


@wp.struct
class ToneLossSettings:
    """The constants of one batch's loss."""

    knot_power: float
    warp_lo: float
    """WARP_EPS^knot_power: where the knot-coordinate warp starts."""
    warp_span: float
    """(1 + WARP_EPS)^knot_power - WARP_EPS^knot_power."""
    leak: float
    vignetting: int
    saturation_weighting: int
    scale: float
    """1 / (3 B): the loss is a mean over the batch's rays and channels."""


@wp.struct
class ToneTables:
    """The tone parameters a batch's loss reads: per image (white balance, vignetting, size, curve group),
    the reference image fixing the gauge, and the curves' learned knots, a row per curve."""

    log_wb: wp.array2d(dtype=wp.float32)
    """(images, 3) log white balance, exposure its scale."""
    reference: wp.array(dtype=wp.int64)
    """The reference image's index (one element): its white balance is fixed."""
    reference_log_wb: wp.array(dtype=wp.float32)
    """(3,) the fixed white balance of the reference."""
    vignetting: wp.array2d(dtype=wp.float32)
    """(images, 4) the centre's offset (row, column), then k1, k2."""
    sizes: wp.array2d(dtype=wp.float32)
    """(images, 2) width, height."""
    groups: wp.array(dtype=wp.int64)
    """Each image's curve group (a camera shares its response)."""
    interior: wp.array2d(dtype=wp.float32)
    """(groups * 3, knots) the learned interior knots."""


@wp.struct
class ToneGrads:
    """Where the loss adds the gradients of `ToneTables`' learned parameters (the same shapes)."""

    log_wb: wp.array2d(dtype=wp.float32)
    """The white balance's (the reference's row stays 0)."""
    vignetting: wp.array2d(dtype=wp.float32)
    interior: wp.array2d(dtype=wp.float32)
    """The knots' (the fixed ends have none)."""


@wp.func
def saturation_weight(t: float) -> float:
    """`module.saturation_weights` of one target value."""
    if t < 0.15:
        low = (t + 0.15) / 0.3
        return low * low
    if t > 0.9:
        high = (t - 1.1) / 0.2
        return high * high
    return 1.0


@wp.func
def clamp_passes(x: float, lo: float, hi: float) -> float:
    """1 where `clamp(x, lo, hi)` passes gradient (its bounds included, as torch's), else 0."""
    return wp.where(x >= lo and x <= hi, 1.0, 0.0)


@wp.func
def knot(interior: wp.array2d(dtype=wp.float32), row: int, j: int) -> float:
    """Knot j of curve `row` (`ToneMapper.knots`): the fixed ends 0 and 1 around the learned interior."""
    if j == 0:
        return 0.0
    if j == interior.shape[1] + 1:
        return 1.0
    return interior[row, j - 1]


@wp.func
def add_to_knot(d_interior: wp.array2d(dtype=wp.float32), row: int, j: int, value: float):
    """Add to knot j's gradient; the fixed ends have none."""
    if j > 0 and j <= d_interior.shape[1]:
        wp.atomic_add(d_interior, row, j - 1, value)


@KERNEL
def _tone_loss(
    radiance: wp.array2d(dtype=wp.float32),
    pixels: DrawnPixels,
    tone: ToneTables,
    s: ToneLossSettings,
    ray_loss: wp.array(dtype=wp.float32),
    ray_mse: wp.array(dtype=wp.float32),
    d_radiance: wp.array2d(dtype=wp.float32),
    grads: ToneGrads,
):
    r = wp.tid()
    i = int(pixels.image_ids[r])
    frozen = i == int(tone.reference[0])  # the reference image's white balance: fixed, no gradient
    group = int(tone.groups[i])
    k = tone.interior.shape[1] + 1  # segments
    # Vignetting 1 + k1 r^2 + k2 r^4 about the learned centre, in the oracle's order of operations.
    v = wp.float32(1.0)
    v_raw = wp.float32(1.0)
    dr = wp.float32(0.0)
    dc = wp.float32(0.0)
    r2 = wp.float32(0.0)
    if s.vignetting != 0:
        dr = (float(pixels.rows[r]) + 0.5) / tone.sizes[i, 1] - 0.5 - tone.vignetting[i, 0]
        dc = (float(pixels.cols[r]) + 0.5) / tone.sizes[i, 0] - 0.5 - tone.vignetting[i, 1]
        r2 = dr * dr + dc * dc
        v_raw = 1.0 + tone.vignetting[i, 2] * r2 + tone.vignetting[i, 3] * r2 * r2
        v = wp.max(v_raw, 0.0)
    loss = wp.float32(0.0)
    mse = wp.float32(0.0)
    d_v = wp.float32(0.0)
    for c in range(3):
        wb = wp.exp(wp.where(frozen, tone.reference_log_wb[c], tone.log_wb[i, c]))
        e_wb = radiance[r, c] * wb
        e = e_wb
        if s.vignetting != 0:
            e = e_wb * v
        x = wp.clamp(e, 0.0, 1.0)
        u = x
        du_dx = wp.float32(1.0)
        if s.knot_power != 1.0:
            u = (wp.pow(x + WARP_EPS, s.knot_power) - s.warp_lo) / s.warp_span
            du_dx = s.knot_power * wp.pow(x + WARP_EPS, s.knot_power - 1.0) / s.warp_span
        pos = wp.clamp(u, 0.0, 1.0) * float(k)
        idx = wp.min(int(wp.floor(pos)), k - 1)
        frac = pos - float(idx)
        row = group * 3 + c
        lo = knot(tone.interior, row, idx)
        hi = knot(tone.interior, row, idx + 1)
        y = lo + frac * (hi - lo)
        if s.leak > 0.0:
            y = y + s.leak * (wp.max(e - 1.0, 0.0) + wp.min(e, 0.0))
        if wp.isnan(e):
            y = e  # NaN radiance: the clamps would hide it; a NaN loss and gradients show it
        t = pixels.target[r, c]
        diff = y - t
        err = diff * diff
        mse += err
        w = wp.float32(1.0)
        if s.saturation_weighting != 0:
            w = saturation_weight(t)
        loss += err * w
        # Backward: d loss / d y, then through the lookup, the warp and the clamps to the irradiance.
        g_y = 2.0 * diff * w * s.scale
        add_to_knot(grads.interior, row, idx, g_y - g_y * frac)
        add_to_knot(grads.interior, row, idx + 1, g_y * frac)
        g_u = g_y * (hi - lo) * float(k) * clamp_passes(u, 0.0, 1.0)
        g_e = g_u * du_dx * clamp_passes(e, 0.0, 1.0)
        if s.leak > 0.0:
            g_e += g_y * s.leak * (wp.where(e - 1.0 >= 0.0, 1.0, 0.0) + wp.where(e <= 0.0, 1.0, 0.0))
        g_e_wb = g_e
        if s.vignetting != 0:
            g_e_wb = g_e * v
            d_v += g_e * e_wb
        d_radiance[r, c] = g_e_wb * wb
        if not frozen:
            wp.atomic_add(grads.log_wb, i, c, g_e_wb * radiance[r, c] * wb)
    ray_loss[r] = loss * s.scale
    ray_mse[r] = mse * s.scale
    if s.vignetting != 0 and v_raw >= 0.0:
        g_r2 = (
            d_v * tone.vignetting[i, 2]
            + (d_v * r2) * tone.vignetting[i, 3]
            + d_v * (tone.vignetting[i, 3] * r2)
        )
        wp.atomic_add(grads.vignetting, i, 0, -(2.0 * g_r2 * dr))
        wp.atomic_add(grads.vignetting, i, 1, -(2.0 * g_r2 * dc))
        wp.atomic_add(grads.vignetting, i, 2, d_v * r2)
        wp.atomic_add(grads.vignetting, i, 3, d_v * r2 * r2)


@KERNEL
def _curve_smoothness(
    interior: wp.array2d(dtype=wp.float32),
    weight: float,
    prior: wp.array2d(dtype=wp.float32),
    d_interior: wp.array2d(dtype=wp.float32),
):
    """`ToneMapper.smoothness_loss` times `weight`: one thread per second difference (centred on
    interior knot j + 1) of one curve, in [-1, 1] units."""
    row, j = wp.tid()
    a = 2.0 * knot(interior, row, j) - 1.0
    b = 2.0 * knot(interior, row, j + 1) - 1.0
    c = 2.0 * knot(interior, row, j + 2) - 1.0
    second = a - 2.0 * b + c
    prior[row, j] = weight * second * second
    g = weight * 2.0 * second
    add_to_knot(d_interior, row, j, 2.0 * g)
    add_to_knot(d_interior, row, j + 1, -4.0 * g)
    add_to_knot(d_interior, row, j + 2, 2.0 * g)


def _settings(tonemapper: ToneMapper, n_rays: int) -> ToneLossSettings:
    cfg = tonemapper.cfg
    p = float(cfg.knot_power)
    lo, hi = WARP_EPS**p, (1.0 + WARP_EPS) ** p
    return warp_struct(
        ToneLossSettings,
        knot_power=p,
        warp_lo=lo,
        warp_span=hi - lo,
        leak=float(cfg.leak),
        vignetting=int(cfg.vignetting),
        saturation_weighting=int(cfg.saturation_weighting),
        scale=1.0 / (3 * max(n_rays, 1)),  # an empty batch: a loss of 0, not a division by 0
    )


class _ToneLoss(torch.autograd.Function):
    """The loss of a batch with the curves' smoothness (0-d) and its MSE (0-d, no gradient), the
    gradients computed with the loss."""

    @staticmethod
    def forward(ctx, radiance, log_wb, vignetting, interior, tonemapper, image_ids, rows, cols, target):
        n = radiance.shape[0]
        radiance, target = radiance.detach().contiguous(), target.detach().contiguous()
        shape = interior.shape
        interior = interior.detach().reshape(-1, shape[-1])  # a row per curve
        ray_loss, ray_mse = radiance.new_empty(n), radiance.new_empty(n)
        d_radiance = torch.empty_like(radiance)
        d_log_wb, d_vignetting = torch.zeros_like(log_wb), torch.zeros_like(vignetting)
        d_interior = torch.zeros_like(interior)
        device = warp_device(radiance)
        curves = to_warp(interior, "the curves' knots")
        d_curves = to_warp(d_interior, "the knots' gradient")
        tone = warp_struct(
            ToneTables,
            log_wb=to_warp(log_wb.detach(), "the white balance"),
            reference=to_warp(tonemapper.reference.reshape(1), "the reference image"),
            reference_log_wb=to_warp(tonemapper.reference_log_wb, "the reference's white balance"),
            vignetting=to_warp(vignetting.detach(), "the vignetting"),
            sizes=to_warp(tonemapper.sizes, "the image sizes"),
            groups=to_warp(tonemapper.crf_group, "the curve groups"),
            interior=curves,
        )
        grads = warp_struct(
            ToneGrads,
            log_wb=to_warp(d_log_wb, "the white balance gradient"),
            vignetting=to_warp(d_vignetting, "the vignetting gradient"),
            interior=d_curves,
        )
        inputs = [
            to_warp(radiance, "the radiance"),
            drawn_pixels(target, image_ids.contiguous(), rows.contiguous(), cols.contiguous()),
            tone,
            _settings(tonemapper, n),
            to_warp(ray_loss, "the rays' losses"),
            to_warp(ray_mse, "the rays' squared errors"),
            to_warp(d_radiance, "the radiance gradient"),
            grads,
        ]
        if n:
            launch_kernel(_tone_loss, dim=n, inputs=inputs, device=device)
        loss = ray_loss.sum()
        weight = float(tonemapper.cfg.lambda_crf_smooth)
        if weight > 0:
            prior = torch.empty_like(interior)
            inputs = [curves, weight, to_warp(prior, "the smoothness terms"), d_curves]
            dim = tuple(interior.shape)  # a thread per second difference: as many as interior knots
            launch_kernel(_curve_smoothness, dim=dim, inputs=inputs, device=device)
            loss = loss + prior.sum()
        ctx.save_for_backward(d_radiance, d_log_wb, d_vignetting, d_interior.reshape(shape))
        mse = ray_mse.sum()
        ctx.mark_non_differentiable(mse)
        return loss, mse

    @staticmethod
    def backward(ctx, grad_loss, _grad_mse):
        wanted = ctx.needs_input_grad[:4]  # radiance, white balance, vignetting, interior knots
        grads = [g * grad_loss if want else None for g, want in zip(ctx.saved_tensors, wanted, strict=True)]
        return (*grads, None, None, None, None, None)


def fused_training_loss(
    tonemapper: ToneMapper, radiance: torch.Tensor, pixels: PixelTargets
) -> tuple[torch.Tensor, torch.Tensor]:
    """`ToneMapper.loss` of the training forward of rays with linear `radiance` (B, 3) against their
    `pixels`' targets (B, 3) in [0, 1], differentiable in the radiance and the tone parameters, and the
    plain MSE (no gradient), both 0-d tensors on the radiance's device. The photometric loss and the curves'
    smoothness with their gradients come from the kernels; the other priors, when weighted, from
    PyTorch (`ToneMapper.pytorch_priors`)."""
    loss, mse = _ToneLoss.apply(
        radiance,
        tonemapper.log_wb,
        tonemapper.vignetting,
        tonemapper.crf_interior,
        tonemapper,
        pixels.image_ids,
        pixels.rows,
        pixels.cols,
        pixels.target,
    )
    return loss + tonemapper.pytorch_priors(), mse
