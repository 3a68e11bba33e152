"""The tone mapper's fused training loss (`tonemap/loss_kernel.py`) against its PyTorch oracle
(`tonemap/loss_reference.py`): the loss, the MSE and every gradient, over the settings that change its
arithmetic, at the clamps' kinks, and in training."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from devices import FAST_DEVICE

from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.loss_kernel import fused_training_loss
from hdrplenoxels.tonemap.loss_reference import training_loss_reference
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.tonemap.pixels import PixelTargets

SIZES = np.array([[40, 30]] * 3 + [[64, 48]] * 2)


def tone_mapper(seed: int = 0, **settings) -> ToneMapper:
    """Five images on two cameras, every parameter moved off its start (the reference's frozen)."""
    g = torch.Generator().manual_seed(seed)
    tm = ToneMapper(len(SIZES), SIZES, ToneMapConfig(enabled=True, **settings), camera_ids=[0, 0, 0, 1, 1])
    with torch.no_grad():
        tm.log_wb.copy_(torch.randn(tm.log_wb.shape, generator=g) * 0.5)
        tm.crf_interior.add_(torch.randn(tm.crf_interior.shape, generator=g) * 0.01)
        falloff = torch.tensor([0.0, 0.0, -0.3, 0.0])
        tm.vignetting.copy_(torch.randn(tm.vignetting.shape, generator=g) * 0.1 + falloff)
    tm.set_reference(1)
    if tm.cfg.exposure_hold == "always":
        tm.set_stated_exposures(torch.tensor([0.0, -1.0, 1.0, 2.0, 0.5]))
    return tm


def batch(n: int, seed: int = 1):
    """Rays over every image, radiance past both ends of the curve, with exact kinks: radiance 0, an
    irradiance of exactly 1 (the reference image's gains are 1 after `set_reference(1, zeros)`), and
    targets at 0 and 1 (the saturation weights' far ends)."""
    g = torch.Generator().manual_seed(seed)
    ids = torch.randint(0, len(SIZES), (n,), generator=g)
    size = torch.as_tensor(SIZES)[ids]
    rows = (torch.rand(n, generator=g) * size[:, 1]).long()
    cols = (torch.rand(n, generator=g) * size[:, 0]).long()
    radiance = torch.rand(n, 3, generator=g) * 1.6 - 0.1
    radiance[:8] = 0.0
    target = torch.rand(n, 3, generator=g)
    target[:16], target[16:32] = 0.0, 1.0
    return radiance, ids, rows, cols, target


def losses_and_grads(fn, tm: ToneMapper, rays, device: torch.device):
    tm = tm.to(device)
    radiance, *rest = (t.to(device) for t in rays)
    radiance = radiance.clone().requires_grad_(True)
    params = [p for p in tm.parameters() if p.requires_grad]
    loss, mse = fn(tm, radiance, PixelTargets(*rest))
    grads = torch.autograd.grad(loss, [radiance, *params])
    return [t.detach().cpu() for t in (loss, mse, *grads)]


SETTINGS = {
    "defaults": {},
    "vignetting, weighted, warped knots": {
        "vignetting": True,
        "saturation_weighting": True,
        "knot_power": 0.5,
    },
    "no leak, a curve per image, no smoothness": {
        "leak": 0.0,
        "crf_sharing": "image",
        "lambda_crf_smooth": 0.0,
    },
    "a strong smoothness and the log-log prior": {"lambda_crf_smooth": 1.0, "lambda_crf_loglog": 1e-2},
    "the exposure ratios' prior": {"exposure_hold": "always", "lambda_exposure_ratios": 1.0},
}


@pytest.mark.parametrize("settings", SETTINGS.values(), ids=SETTINGS.keys())
def test_the_fused_loss_and_its_gradients_match_the_oracle(settings):
    tm, rays = tone_mapper(**settings), batch(3000)
    want = losses_and_grads(training_loss_reference, tone_mapper(**settings), rays, torch.device("cpu"))
    got = losses_and_grads(fused_training_loss, tm, rays, FAST_DEVICE)
    names = ["loss", "mse", "radiance", *(n for n, p in tm.named_parameters() if p.requires_grad)]
    assert len(got) == len(want) == len(names) == (6 if settings.get("vignetting") else 5)
    for name, a, b in zip(names, got, want, strict=True):
        assert a.shape == b.shape, name
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-8, msg=name)
        assert b.abs().max() > 0, f"{name}: the oracle's is all zero, so the comparison says nothing"


def test_kinks_pass_gradient_as_the_oracle_clamps_do():
    """Irradiance exactly 0 and 1 (torch's clamp passes gradient at its bounds; the leak's clamps too)."""
    tm = tone_mapper()
    tm.set_reference(1, torch.zeros(3))
    radiance, ids, rows, cols, target = batch(64)
    ids[:] = 1
    radiance[:32:2], radiance[1:32:2] = 0.0, 1.0
    target[:32] = 0.5  # a pixel the kink's prediction misses
    rays = (radiance, ids, rows, cols, target)
    want = losses_and_grads(training_loss_reference, tm, rays, torch.device("cpu"))
    got = losses_and_grads(fused_training_loss, tm, rays, FAST_DEVICE)
    torch.testing.assert_close(got[2][:32], want[2][:32], rtol=1e-5, atol=1e-8)
    assert (want[2][:32] != 0).all()


def test_the_reference_image_gets_no_white_balance_gradient_and_an_empty_batch_no_error():
    tm = tone_mapper()
    _, _, d_radiance, d_log_wb, _ = losses_and_grads(fused_training_loss, tm, batch(500), FAST_DEVICE)
    assert (d_log_wb[1] == 0).all() and (d_log_wb[0] != 0).all()
    empty = [t[:0] for t in batch(10)]
    loss, mse, d_radiance, *_ = losses_and_grads(fused_training_loss, tm, empty, FAST_DEVICE)
    smoothness = float(tm.cfg.lambda_crf_smooth * tm.smoothness_loss().detach())
    assert float(loss) == pytest.approx(smoothness, rel=1e-5) and smoothness > 0  # the priors alone
    assert float(mse) == 0.0 and d_radiance.shape == (0, 3)


def test_a_nan_radiance_makes_the_loss_nan_not_a_silent_zero():
    """The clamps would map NaN into the curve; a NaN must show in the loss, as the oracle fails on it."""
    tm = tone_mapper()
    radiance, ids, rows, cols, target = batch(50)
    ids[0] = 0
    radiance[0, 1] = float("nan")
    loss, mse, d_radiance, d_log_wb, _ = losses_and_grads(
        fused_training_loss, tm, (radiance, ids, rows, cols, target), FAST_DEVICE
    )
    assert loss.isnan() and mse.isnan() and d_radiance[0, 1].isnan() and d_log_wb[0, 1].isnan()


def test_the_training_loss_refuses_an_empty_batch_on_either_path(monkeypatch):
    from hdrplenoxels.kernels import dispatch

    tm, empty = tone_mapper(), [t[:0] for t in batch(10)]
    for fused in (False, True):
        monkeypatch.setattr(dispatch, "KERNELS_ON_CPU", fused)
        with pytest.raises(ValueError, match="at least one ray"):
            tm.training_loss(empty[0], PixelTargets(*empty[1:]))


def test_on_a_cpu_the_fused_loss_repeats_itself_to_the_bit():
    """The kernel runs on one CPU thread, so its adds come in ray order: a resumed run repeats."""
    tm, rays = tone_mapper(vignetting=True), batch(2000)
    first = losses_and_grads(fused_training_loss, tm, rays, torch.device("cpu"))
    second = losses_and_grads(fused_training_loss, tm, rays, torch.device("cpu"))
    assert all(torch.equal(a, b) for a, b in zip(first, second, strict=True))


def test_training_loss_is_the_loss_of_the_training_forward_on_any_device():
    """The trainer's call: on a CPU PyTorch's path, to the bit; on CUDA the kernel's, to rounding."""
    tm = tone_mapper(lambda_crf_loglog=1e-2)
    radiance, ids, rows, cols, target = batch(400)
    pred = tm(radiance, ids, rows, cols, training=True)
    loss, mse = tm.training_loss(radiance, PixelTargets(ids, rows, cols, target))
    assert torch.equal(loss, tm.loss(pred, target)) and torch.equal(mse, torch.mean((pred - target) ** 2))
    fast = copy.deepcopy(tm).to(FAST_DEVICE)
    on_fast = [t.to(FAST_DEVICE) for t in (radiance, ids, rows, cols, target)]
    loss_fast, mse_fast = fast.training_loss(on_fast[0], PixelTargets(*on_fast[1:]))
    torch.testing.assert_close(loss_fast.detach().cpu(), loss.detach(), rtol=1e-6, atol=0)
    torch.testing.assert_close(mse_fast.cpu(), mse, rtol=1e-6, atol=0)


def test_a_training_through_the_fused_kernels_follows_the_cpu_paths(tiny_scene, tmp_path, monkeypatch):
    """A CUDA step's path (the fused loss and ray draw, `kernels.dispatch.KERNELS_ON_CPU`) trains as the
    CPU's: the same first steps, to rounding; after them the runs part, as any two runs whose gradients differ
    in the last bits do (RMSProp's first step on a voxel is a whole learning rate either way), but learn
    alike."""
    from test_train import tiny_config

    from hdrplenoxels.kernels import dispatch
    from hdrplenoxels.tonemap import module
    from hdrplenoxels.train import ray_pool
    from hdrplenoxels.train.trainer import Trainer

    cfg = tiny_config(12)
    cfg.tonemap.enabled = True

    def train(name: str) -> list[float]:
        trainer = Trainer(tiny_scene, cfg, tmp_path / name)
        return [float(trainer.train_step()) for _ in range(12)]

    cpu_losses = train("cpu")
    calls = {"loss": 0, "draw": 0}

    def counted(name, fn):
        def wrapper(*args):
            calls[name] += 1
            return fn(*args)

        return wrapper

    monkeypatch.setattr(dispatch, "KERNELS_ON_CPU", True)
    monkeypatch.setattr(module, "fused_training_loss", counted("loss", module.fused_training_loss))
    monkeypatch.setattr(ray_pool, "draw_rays", counted("draw", ray_pool.draw_rays))
    fused_losses = train("fused")
    assert calls["loss"] == 12 and calls["draw"] >= 12
    np.testing.assert_allclose(fused_losses[:2], cpu_losses[:2], rtol=1e-5)
    assert fused_losses[-1] < 0.5 * fused_losses[0] and cpu_losses[-1] < 0.5 * cpu_losses[0]
    # Single steps are noisy once the runs part; the last few together are not.
    assert abs(np.log(np.mean(fused_losses[-4:]) / np.mean(cpu_losses[-4:]))) < 0.3
