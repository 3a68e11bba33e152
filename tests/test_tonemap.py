"""The tone-mapping module: curve lookup, gauge fixing, clipping modes, gradients, persistence."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.module import ToneMapper, crf_group_ids, saturation_weights
from hdrplenoxels.tonemap.response import (
    CRF_SEGMENTS,
    ResponseCurve,
    controlled_ldr,
    knot_coordinate,
    knot_positions,
    piecewise_linear,
)
from hdrplenoxels.train.optim import TorchRMSProp, make_tone_optimiser

N = 6
SIZES = np.tile([32, 24], (N, 1))


def mapper(**cfg) -> ToneMapper:
    """Per-image curves unless a test asks otherwise (so each view's curve can be set on its own), starting
    at x^(1/2.2) (a curve the tests can tell from the identity)."""
    cfg = {"crf_sharing": "image", "init_gamma": 2.2, **cfg}
    return ToneMapper(N, SIZES, ToneMapConfig(enabled=True, **cfg))


@pytest.mark.parametrize("gamma", [2.2, 1.0])
def test_initial_curve_is_the_init_gamma_with_fixed_ends(gamma):
    knots = mapper(init_gamma=gamma).knots().detach()
    assert knots.shape == (N, 3, CRF_SEGMENTS + 1)
    assert (knots[..., 0] == 0).all() and (knots[..., -1] == 1).all()
    x = torch.linspace(0, 1, 101)
    y = piecewise_linear(x.expand(3, -1), knots[0], torch.arange(3)[:, None].expand(3, 101))
    assert torch.allclose(y, x ** (1 / gamma), atol=5e-3)  # linear between knots


def test_a_monotonic_response_is_kept_rising_and_a_free_one_is_left_alone():
    """`constrain` after an update: a dip is flattened (the mean of the running max from below and the
    running min from above), knots leave [0, 1] no more, and a rising curve is untouched."""
    tm = ToneMapper(2, np.array([[8, 8]] * 2), ToneMapConfig(enabled=True))
    rising = tm.crf_interior.detach().clone()
    tm.constrain()
    assert torch.equal(tm.crf_interior, rising)
    with torch.no_grad():
        tm.crf_interior[0, 1, 100:110] -= 0.2  # a dip
        tm.crf_interior[0, 2, -3:] = 1.3  # past the top
    tm.constrain()
    steps = torch.diff(tm.knots(), dim=-1)
    assert bool((steps >= 0).all()) and float(tm.crf_interior.max()) <= 1.0
    assert torch.equal(tm.crf_interior[0, 0], rising[0, 0])  # other channels as they were
    free = ToneMapper(2, np.array([[8, 8]] * 2), ToneMapConfig(enabled=True, response="free"))
    with torch.no_grad():
        free.crf_interior[0, 1, 100:110] -= 0.2
    dipped = free.crf_interior.detach().clone()
    free.constrain()
    assert torch.equal(free.crf_interior, dipped)


@pytest.mark.parametrize("response", ["monotonic", "free"])
def test_training_ends_with_rising_curves_only_where_the_response_is_monotonic(
    tiny_scene, tmp_path, response
):
    """The knots train free (the paper's); with "monotonic" the run's final curves, in the model and in
    tone_params.json, are made non-decreasing before the gauge is fitted, while "free" keeps what it
    learned. A dip is put in after every tone step, so the last step leaves one."""
    from test_train import tiny_config

    from hdrplenoxels.train.trainer import Trainer

    cfg = tiny_config(6)
    cfg.tonemap.enabled = True
    cfg.tonemap.response = response
    trainer = Trainer(tiny_scene, cfg, tmp_path / response)
    step = trainer.tone_optimiser.step

    def dipping(*args):
        step(*args)
        with torch.no_grad():
            trainer.tonemapper.crf_interior[0, 1, 100:110] -= 0.05

    trainer.tone_optimiser.step = dipping
    model = trainer.run(progress=False)
    lowest = float(torch.diff(model.tonemapper.knots(), dim=-1).min())
    saved = np.array(json.loads((tmp_path / response / "tone_params.json").read_text())["crf_knots"])
    assert (lowest >= 0.0 and np.diff(saved, axis=-1).min() >= 0.0) == (response == "monotonic"), lowest


def test_each_ray_uses_its_own_images_curve():
    """The reference code looked up the wrong row for most rays (docs/method.md,
    "Fixes to the reference code"); ours gathers per ray."""
    tm = mapper()
    with torch.no_grad():
        tm.crf_interior[3] = torch.linspace(0, 1, CRF_SEGMENTS + 1)[1:-1]  # image 3: identity response
    radiance = torch.full((4, 3), 0.25)
    ids = torch.tensor([0, 3, 1, 3])
    tm.set_reference(0, torch.zeros(3))
    with torch.no_grad():
        tm.log_wb.zero_()
    out = tm(radiance, ids, training=False)
    assert torch.allclose(out[1], torch.full((3,), 0.25), atol=1e-6)
    assert torch.allclose(out[0], torch.full((3,), 0.25 ** (1 / 2.2)), atol=5e-3)


def test_leaky_beyond_one_while_training_clipped_at_test():
    tm = mapper(leak=0.01)
    tm.set_reference(0, torch.zeros(3))
    radiance = torch.tensor([[3.0, 0.5, 1.0]], requires_grad=True)
    ids = torch.tensor([0])
    test = tm(radiance, ids, training=False)
    assert test[0, 0] == 1.0
    train = tm(radiance, ids, training=True)
    assert train[0, 0].detach().item() == pytest.approx(1.0 + 0.01 * 2.0)
    (grad,) = torch.autograd.grad(train[0, 0], radiance)
    assert float(grad[0, 0]) == pytest.approx(0.01)  # saturated pixels still pass gradient


def test_reference_white_balance_is_frozen_and_fixes_the_gauge():
    tm = mapper()
    ref = tm.init_from_images(torch.tensor([[0.2, 0.2, 0.2], [0.4, 0.4, 0.4], [0.1, 0.2, 0.3]] * 2))
    assert ref in (0, 3)  # overall mean closest to the dataset's
    before = tm.log_wb.detach().clone()
    opt = make_tone_optimiser(tm)
    radiance = torch.rand(64, 3)
    ids = torch.arange(64) % N
    for _ in range(5):
        grads = torch.autograd.grad(tm.loss(tm(radiance, ids), torch.rand(64, 3)), opt.params)
        opt.step(list(grads), 3e-3)
    assert torch.equal(tm.log_wb[ref], before[ref])  # the reference never moves
    assert not torch.equal(tm.log_wb[1], before[1])  # the others learn
    assert torch.equal(tm.white_balance(torch.tensor([ref])), torch.exp(before[ref])[None])


def test_white_balance_init_uses_log_ratio_to_the_mean():
    tm = mapper()
    mu = torch.tensor([[0.1, 0.2, 0.4], [0.2, 0.4, 0.8]] * 3)
    tm.init_from_images(mu)
    expected = torch.log(mu / mu.mean(0, keepdim=True))
    assert torch.allclose(tm.log_wb, expected)


def test_gradients_reach_white_balance_curves_and_vignetting():
    tm = mapper(vignetting=True)
    tm.set_reference(0, torch.zeros(3))
    radiance = torch.rand(128, 3, requires_grad=True)
    ids = torch.arange(128) % N
    rows, cols = torch.randint(0, 24, (128,)), torch.randint(0, 32, (128,))
    loss = tm.loss(tm(radiance, ids, rows, cols), torch.rand(128, 3))
    loss.backward()
    assert tm.log_wb.grad[1:].abs().sum() > 0 and tm.log_wb.grad[0].abs().sum() == 0  # reference frozen
    assert tm.crf_interior.grad.abs().sum() > 0 and tm.vignetting.grad[:, 2].abs().sum() > 0
    assert radiance.grad.abs().sum() > 0


def test_vignetting_uses_row_over_height_and_col_over_width():
    tm = mapper(vignetting=True)
    with torch.no_grad():
        tm.vignetting[:, 2] = -1.0  # k1
    ids = torch.zeros(3, dtype=torch.long)
    rows, cols = torch.tensor([11, 0, 11]), torch.tensor([15, 15, 0])  # centre, top edge, left edge
    f = tm.vignetting_factor(ids, rows, cols)[:, 0].detach().tolist()
    assert f[0] == pytest.approx(1.0 - (0.5 / 24) ** 2 - (0.5 / 32) ** 2, abs=1e-6)
    # Top edge: row offset ~0.5 of H; left edge: col offset ~0.5 of W, both normalised the same way.
    assert f[1] == pytest.approx(f[2], abs=0.03) and f[1] < 0.8


def test_crf_smoothness_penalises_kinks_only():
    tm = mapper()
    with torch.no_grad():
        tm.crf_interior[:] = torch.linspace(0, 1, CRF_SEGMENTS + 1)[1:-1]
    assert tm.smoothness_loss().detach().item() == pytest.approx(0.0, abs=1e-9)
    with torch.no_grad():
        tm.crf_interior[0, 0, 100] += 0.01
    # One kink of height h gives second differences (h, -2h, h) in [0,1] units, x2 in [-1,1] units.
    assert tm.smoothness_loss().detach().item() == pytest.approx(6 * (2 * 0.01) ** 2, rel=1e-3)


def set_curves(tm: ToneMapper, f) -> None:
    """Every curve's interior knots to f(knot irradiance)."""
    x = torch.as_tensor(knot_positions(CRF_SEGMENTS + 1, tm.cfg.knot_power), dtype=torch.float32)
    with torch.no_grad():
        tm.crf_interior[:] = f(x)[1:-1]


@pytest.mark.parametrize("knot_power", [1.0, 1 / 2.2])
def test_loglog_prior_is_free_for_every_power_law_and_charges_a_log_periodic_wiggle(knot_power):
    tm = mapper(knot_power=knot_power)
    for exponent in (0.3, 0.45, 1.0, 1.5):  # the gauges of the exponential ambiguity above the floor
        set_curves(tm, lambda x, e=exponent: x**e)
        assert tm.loglog_smoothness_loss().item() < 0.01  # piecewise-linear interpolation only
    # The ambiguity it is there for: a wiggle periodic in log2 irradiance (here, a 2-stop period).
    set_curves(tm, lambda x: x**0.45 * torch.exp2(0.1 * torch.sin(torch.pi * torch.log2(x.clamp(min=1e-9)))))
    assert tm.loglog_smoothness_loss().item() > 0.3
    # And it enters the training loss with its weight.
    pred, target = torch.rand(8, 3), torch.rand(8, 3)
    without = mapper(knot_power=knot_power, lambda_crf_loglog=0.0)
    with_prior = mapper(knot_power=knot_power, lambda_crf_loglog=0.5)
    set_curves(without, lambda x: x**0.45 * (1 + 0.05 * torch.sin(8 * torch.log2(x.clamp(min=1e-9)))))
    with_prior.load_state_dict(without.state_dict())
    expected = without.loss(pred, target) + 0.5 * without.loglog_smoothness_loss()
    assert with_prior.loss(pred, target).item() == pytest.approx(expected.item(), rel=1e-6)
    with_prior.loss(pred, target).backward()
    assert with_prior.crf_interior.grad.abs().sum() > 0


def test_saturation_weights_enter_the_loss():
    assert torch.allclose(saturation_weights(torch.tensor([0.0, 0.5, 1.0])), torch.tensor([0.25, 1.0, 0.25]))
    pred, target = torch.zeros(2, 3), torch.tensor([[1.0] * 3, [0.5] * 3])
    plain = mapper(lambda_crf_smooth=0.0).loss(pred, target)
    weighted = mapper(lambda_crf_smooth=0.0, saturation_weighting=True).loss(pred, target)
    assert weighted < plain  # the saturated target counts a quarter


def test_crf_sharing_groups():
    assert crf_group_ids(4, "image").tolist() == [0, 1, 2, 3]
    assert crf_group_ids(4, "scene").tolist() == [0, 0, 0, 0]
    assert crf_group_ids(4, "camera", [7, 3, 7, 3]).tolist() == [1, 0, 1, 0]
    assert mapper(crf_sharing="scene").crf_interior.shape[0] == 1
    assert ToneMapConfig().crf_sharing == "camera"  # the measured better default (see ToneMapConfig)


def test_state_round_trip_and_parameters_dict():
    tm = mapper(crf_sharing="scene")
    tm.init_from_images(torch.rand(N, 3) + 0.1)
    with torch.no_grad():
        tm.crf_interior.add_(0.01 * torch.randn_like(tm.crf_interior))
    other = mapper()  # different group count: restored from the arrays anyway
    other.load_state_arrays(tm.state_arrays())
    radiance, ids = torch.rand(32, 3), torch.arange(32) % N
    assert torch.equal(other(radiance, ids, training=False), tm(radiance, ids, training=False))
    d = tm.parameters_dict()
    assert d["reference"] == int(tm.reference) and len(d["white_balance"]) == N
    assert np.asarray(d["crf_knots"]).shape == (1, 3, CRF_SEGMENTS + 1)


@pytest.mark.parametrize("sharing, cameras", [("image", None), ("camera", [0, 0, 1, 1, 2, 2])])
def test_parameters_round_trip_through_json(sharing, cameras):
    """tone_params.json holds every learned value: a tone mapper rebuilt from it maps radiance, with
    vignetting and a non-trivial output gauge, exactly as the original does."""
    cfg = ToneMapConfig(enabled=True, crf_sharing=sharing, vignetting=True, knot_power=0.5)
    sizes = np.array([[32, 24], [32, 24], [40, 30], [40, 30], [16, 16], [16, 16]])
    tm = ToneMapper(N, sizes, cfg, camera_ids=cameras)
    tm.init_from_images(torch.rand(N, 3) + 0.1, candidates=[1, 2, 3])
    with torch.no_grad():
        tm.log_wb.add_(0.3 * torch.randn_like(tm.log_wb))
        tm.crf_interior.add_(0.01 * torch.randn_like(tm.crf_interior))
        tm.vignetting.copy_(0.2 * torch.randn_like(tm.vignetting))
        tm.exponent.fill_(0.6)
    params = json.loads(json.dumps(tm.parameters_dict()))
    back = ToneMapper.from_parameters_dict(params)
    again = back.parameters_dict()
    assert again.keys() == params.keys()
    for key, value in params.items():
        if isinstance(value, list):
            assert np.allclose(np.asarray(again[key], float), np.asarray(value, float), atol=1e-6), key
        else:
            assert again[key] == value, key
    assert int(back.reference) == int(tm.reference) and back.cfg.knot_power == 0.5
    radiance, ids = torch.rand(64, 3), torch.arange(64) % N
    rows, cols = torch.rand(64) * 24, torch.rand(64) * 32
    expected = tm(radiance, ids, rows, cols, training=False)
    assert torch.allclose(back(radiance, ids, rows, cols, training=False), expected, atol=1e-5)
    x = torch.rand(8, 3)
    assert torch.allclose(back.curve(3)(x), tm.curve(3)(x), atol=1e-6)
    assert torch.allclose(back.linear_log_wb(), tm.linear_log_wb(), atol=1e-5)


@pytest.mark.parametrize(
    "change, problem",
    [
        (lambda p: p.pop("crf_knots"), "crf_knots"),
        (lambda p: p.update(white_balance=[[1.0, -1.0, 1.0]] * N), "positive"),
        (lambda p: p.update(crf_group=[0] * (N - 1) + [7]), "crf_group"),
        (lambda p: p.update(reference=N), "reference"),
        (lambda p: p.update(crf_knots=[[[0.0, 1.0]] * 3]), "crf_knots"),
    ],
)
def test_parameters_dict_errors_name_the_problem(change, problem):
    params = json.loads(json.dumps(mapper().parameters_dict()))
    change(params)
    with pytest.raises(ValueError, match=problem):
        ToneMapper.from_parameters_dict(params)


def test_controlled_rendering_exposure_white_balance_and_curve_transfer():
    tm = mapper()
    with torch.no_grad():
        tm.log_wb.copy_(torch.log(torch.tensor([[1.0, 1.0, 1.0], [4.0, 4.0, 4.0]] * 3)))  # basis: gains 2
        tm.crf_interior[2] = torch.linspace(0, 1, CRF_SEGMENTS + 1)[1:-1]  # view 2: identity response
    identity = tm.curve(2)
    radiance = torch.full((2, 2, 3), 0.1)
    basis = tm.basis_log_wb()
    assert torch.allclose(torch.exp(basis), torch.full((3,), 2.0))
    plus_one = controlled_ldr(radiance, basis + np.log(2.0), identity)
    assert torch.allclose(plus_one, torch.full_like(radiance, 0.4), atol=1e-6)  # 0.1 x 2 (basis) x 2 (+1 EV)
    tinted = controlled_ldr(radiance, basis + torch.log(torch.tensor([1.0, 2.0, 0.5])), identity)
    assert torch.allclose(tinted[0, 0], torch.tensor([0.2, 0.4, 0.1]), atol=1e-6)
    gamma = controlled_ldr(radiance, basis, tm.curve(0))  # another view's (gamma 2.2) curve
    assert gamma[0, 0, 0] == pytest.approx(0.2 ** (1 / 2.2), abs=5e-3)


def test_known_exposures_fix_the_exponent_and_linearise_every_output():
    """A model that learned exposures^a (a = 0.5) is linearised: EVs, HDR and LDR all agree with a = 1."""
    tm = mapper(known_exposure=True)
    evs = torch.tensor([0.0, 3.0, -3.0, 1.5, 0.0, -1.0])
    tint = torch.tensor([0.1, 0.0, -0.1])
    with torch.no_grad():
        tm.log_wb.copy_(0.5 * evs[:, None] * np.log(2.0) + tint)  # learned gauge: a = 0.5
        knots = torch.as_tensor(knot_positions(CRF_SEGMENTS + 1, 1.0), dtype=torch.float32)
        tm.crf_interior[:] = (knots ** (2 / 3))[1:-1]  # learned curve f(x^(1/a)) for true f = x^(1/3)
    tm.set_reference(0)
    tm.set_known_exposures(evs)
    radiance, ids = torch.rand(64, 3) * 0.05, torch.arange(64) % N
    before = tm(radiance, ids, training=False)
    assert tm.fit_exponent_to_known() == pytest.approx(0.5, abs=1e-5)
    assert torch.equal(tm(radiance, ids, training=False), before)  # the fit changes no LDR pixel
    log2 = tm.linear_log_wb() / np.log(2.0)
    assert torch.allclose(log2.mean(1) - log2.mean(1)[0], evs - evs[0], atol=1e-4)  # true stops again
    linear = tm.linear_radiance(radiance)
    assert torch.allclose(linear, radiance**2, atol=1e-6)
    # A view rendered from the linear outputs (its gains and curve) gives the same pixels.
    view = 3
    again = controlled_ldr(linear[ids == view], tm.linear_log_wb()[view], tm.curve(view))
    assert torch.allclose(again, before[ids == view], atol=2e-3)
    assert tm.parameters_dict()["exponent"] == pytest.approx(0.5, abs=1e-5)
    with pytest.raises(ValueError, match="known_exposure"):
        mapper().set_known_exposures(evs)


def test_the_exposure_ratio_prior_holds_stated_ratios_and_leaves_the_gauge_and_colour_free():
    evs = torch.tensor([0.0, 3.0, -3.0, 1.5, 0.0, -1.0])
    tm = mapper(lambda_exposure_ratios=1.0)
    tm.set_stated_exposures(evs)
    tint = torch.tensor([[0.1, 0.0, -0.1], [0.0, 0.2, -0.2], [0.3, -0.3, 0.0]]).repeat(2, 1)
    for a, offset in ((0.33, 0.0), (1.0, -0.7), (2.0, 0.4)):  # any gauge, any offset: no cost
        with torch.no_grad():
            tm.log_wb.copy_((a * evs * np.log(2.0) + offset)[:, None] + tint)
        tm.set_reference(0)
        assert tm.exposure_ratio_loss().item() < 1e-10
    # One view a tenth of a stop off its line (gauge a = 2): charged, and pulled back alone
    with torch.no_grad():
        tm.log_wb[4] += 2 * 0.1 * np.log(2.0)
    pred, target = torch.rand(8, 3), torch.rand(8, 3)
    plain = mapper()
    plain.load_state_dict(tm.state_dict())
    assert tm.loss(pred, target).item() == pytest.approx(
        (plain.loss(pred, target) + tm.exposure_ratio_loss()).item(), rel=1e-6
    )
    assert tm.exposure_ratio_loss().item() > 0.002
    tm.zero_grad()
    tm.exposure_ratio_loss().backward()
    grad = tm.log_wb.grad.mean(1)
    assert grad[4] > 0 and grad[4] > 3 * grad[[1, 2, 3, 5]].abs().max() and grad[0] == 0  # reference frozen
    with pytest.raises(ValueError, match="5 stated exposures for 6 views"):
        tm.set_stated_exposures(evs[:5])


@pytest.mark.parametrize("power", [1.0, 0.5, 1 / 3])
def test_knot_spacing_warp_inverts_and_fixes_the_ends(power):
    pos = knot_positions(CRF_SEGMENTS + 1, power)
    assert pos[0] == 0.0 and pos[-1] == pytest.approx(1.0) and np.all(np.diff(pos) > 0)
    u = knot_coordinate(torch.as_tensor(pos, dtype=torch.float64), power).numpy()
    assert np.allclose(u, np.linspace(0, 1, CRF_SEGMENTS + 1), atol=1e-9)


def test_denser_shadow_knots_follow_a_steep_response():
    """Gamma 3 climbs to code 40 within the first even segment; square-root spacing follows it."""
    x = torch.logspace(-6, 0, 400, dtype=torch.float64)[:, None].expand(-1, 3)
    truth = x ** (1 / 3)
    errors = {}
    for power in (1.0, 0.5):
        knots = torch.as_tensor(knot_positions(CRF_SEGMENTS + 1, power)) ** (1 / 3)
        curve = ResponseCurve(knots[None].expand(3, -1), power)
        errors[power] = float((curve(x) - truth).abs().max())
    assert errors[0.5] < 0.01 < errors[1.0]


def test_init_curve_is_gamma_2_2_for_any_knot_spacing():
    tm = mapper(knot_power=0.5)
    x = torch.linspace(0, 1, 101)[:, None].expand(-1, 3)
    assert torch.allclose(tm.curve(0)(x), x ** (1 / 2.2), atol=5e-3)


def test_tone_rmsprop_equals_torch_rmsprop_and_round_trips():
    params = [torch.randn(4, 3), torch.randn(2, 257)]
    ours = TorchRMSProp([p.clone() for p in params], alpha=0.95, eps=1e-8)
    theirs = [p.clone().requires_grad_(True) for p in params]
    torch_opt = torch.optim.RMSprop(theirs, lr=1e-2, alpha=0.95, eps=1e-8)
    g = torch.Generator().manual_seed(0)
    for _ in range(4):
        grads = [torch.randn(p.shape, generator=g) for p in params]
        ours.step(grads, 1e-2)
        for p, grad in zip(theirs, grads):
            p.grad = grad
        torch_opt.step()
    for a, b in zip(ours.params, theirs):
        assert torch.allclose(a, b.detach(), rtol=1e-6, atol=1e-7)
    # torch's own state names: checkpoints written with torch's optimiser still resume.
    assert set(ours.state_arrays()) == {f"{i}/{k}" for i in range(2) for k in ("square_avg", "step")}
    restored = TorchRMSProp([p.clone() for p in params], alpha=0.95, eps=1e-8)
    restored.load_state_arrays(ours.state_arrays())
    assert restored.steps == 4 and all(
        torch.equal(a, b) for a, b in zip(restored.square_avg, ours.square_avg)
    )


def test_self_calibrated_outputs_take_the_gauge_where_the_response_looks_like_gamma_2_2():
    """A learned curve y^(1/1.1) on learned radiance y = X^0.5 is X^(1/2.2) in output units: the prior
    picks exponent 0.5, and EV controls, EXR values and the exported curve positions follow it."""
    tm = mapper(crf_sharing="scene")
    with torch.no_grad():
        tm.crf_interior.copy_(torch.linspace(0, 1, CRF_SEGMENTS + 1)[1:-1] ** (1 / 1.1))
        tm.log_wb.copy_(torch.tensor([[-1.0], [0.0], [1.0], [0.5], [0.2], [-0.3]]).expand(-1, 3))
    tm.set_reference(1)
    assert tm.fit_exponent_to_response_prior(2.2) == pytest.approx(0.5, rel=0.02)
    assert torch.allclose(tm.linear_log_wb()[:, 0], tm.log_wb[:, 0] / float(tm.exponent))
    v = torch.rand(5, 3)
    assert torch.allclose(tm.linear_radiance(v), v ** (1 / float(tm.exponent)), rtol=1e-5)
    assert torch.allclose(tm.learned_radiance(tm.linear_radiance(v)), v, rtol=1e-5)
    x = np.asarray(tm.parameters_dict()["crf_knot_irradiance"])
    assert np.allclose(x, np.linspace(0, 1, CRF_SEGMENTS + 1) ** (1 / float(tm.exponent)))


def test_camera_plot_draws_learned_exposures_in_the_truths_gauge(tmp_path):
    """Learned EVs in the output gauge (here 0.63 of the true stops) are drawn scaled onto the true gauge
    beside the truth, and the axis names the gauge; known exposures and truth-less plots are not scaled."""
    from hdrplenoxels.tonemap.plots import exposure_in_gauge, plot_tone_params

    true_ev = np.array([-3.0, 0.0, 3.0, -3.0, 0.0, 3.0])
    truth = {"views": [{"ev": float(e), "crf_curve": list(np.linspace(0, 1, 8))} for e in true_ev]}
    learned = 0.63 * (true_ev - true_ev.mean()) + np.array([0.05, -0.02, 0.0, 0.01, 0.0, -0.04])
    shown, label, gauge = exposure_in_gauge(learned, {}, truth)
    assert gauge == "true stops" and "fitted" in label
    assert np.abs(shown - (true_ev - true_ev.mean())).max() < 0.1  # 3.8 stops apart -> 6
    assert exposure_in_gauge(learned, {"known_exposure": True}, truth)[2] == "true stops"
    assert np.array_equal(exposure_in_gauge(learned, {"known_exposure": True}, truth)[0], learned)
    assert exposure_in_gauge(learned, {}, None)[2] == "output gauge"
    params = {
        "crf_knots": np.tile(np.linspace(0, 1, 9), (1, 3, 1)).tolist(),
        "white_balance": np.exp2(learned)[:, None].repeat(3, 1).tolist(),
        "crf_sharing": "camera",
        "reference": 1,
    }
    path = plot_tone_params(params, tmp_path / "tone_params.png", truth)
    assert path.stat().st_size > 0
