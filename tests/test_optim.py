"""Learning-rate schedules and the svox2 RMSProp (docs/method.md, "Training")."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from devices import FAST_DEVICE

from hdrplenoxels.grid.io import load_grid, save_grid
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.rmsprop import MEAN_SQUARE_FLOOR, RMSPropStep
from hdrplenoxels.kernels.torch_rmsprop_reference import descend_
from hdrplenoxels.train.optim import ExpSchedule, StepClock, StepRates, Svox2RMSProp, TorchRMSProp


def test_sigma_schedule_by_hand():
    lr = ExpSchedule(30.0, 0.05, 250_000, delay_steps=15_000, delay_mult=0.01)
    # step 0: D = 0.01, tau = 0 -> 0.01 * 30
    assert lr(0) == pytest.approx(0.3, rel=1e-12)
    # step 7500: D = 0.01 + 0.99 sin(pi/4), tau = 0.03
    expected = (0.01 + 0.99 * math.sqrt(0.5)) * 30**0.97 * 0.05**0.03
    assert lr(7500) == pytest.approx(expected, rel=1e-12)
    assert lr(7500) == pytest.approx(17.58, abs=0.01)
    # step 15000: warm-up over, tau = 0.06
    assert lr(15_000) == pytest.approx(30**0.94 * 0.05**0.06, rel=1e-12)
    # step 128000 (end of training): tau = 0.512, about 1.13 (docs/method.md, "Training")
    assert lr(128_000) == pytest.approx(30**0.488 * 0.05**0.512, rel=1e-12)
    assert lr(128_000) == pytest.approx(1.134, abs=1e-3)
    assert lr(250_000) == pytest.approx(0.05, rel=1e-12)
    assert lr(400_000) == pytest.approx(0.05, rel=1e-12)
    assert lr(-1) == 0.0


def test_sh_schedule_and_edge_cases():
    lr = ExpSchedule(1e-2, 5e-6, 250_000)
    assert lr(0) == pytest.approx(1e-2, rel=1e-12)
    assert lr(128_000) == pytest.approx(1e-2**0.488 * 5e-6**0.512, rel=1e-12)
    assert lr(128_000) == pytest.approx(2.0e-4, rel=0.03)
    assert ExpSchedule(0.0, 0.0, 100)(50) == 0.0
    with pytest.raises(ValueError):
        ExpSchedule(1.0, 0.0, 100)
    with pytest.raises(ValueError):
        ExpSchedule(1.0, 0.1, 0)


def test_rates_on_the_device_are_the_host_schedules_in_float32():
    """`StepRates` computes on the device what `ExpSchedule` does on the host, from a step count the
    device holds (a replayed CUDA graph's own step): to the float32 the kernels read, at every step of a
    paper-length schedule with its warm-up, past its end, and for a schedule switched off."""
    schedules = [
        ExpSchedule(30.0, 0.05, 250_000, delay_steps=15_000, delay_mult=0.01),
        ExpSchedule(1e-2, 5e-6, 250_000),
        ExpSchedule(0.0, 0.0, 100),
        ExpSchedule(0.1, 0.01, 300),
    ]
    rates = StepRates(schedules, FAST_DEVICE, last_step=400_000)
    steps = list(range(0, 20_000, 7)) + list(range(127_990, 128_010)) + [249_999, 250_000, 400_000, 10**7]
    got = torch.stack([rates(StepClock.at(k, FAST_DEVICE).count) for k in steps]).cpu()
    want = torch.tensor([[s(k) for s in schedules] for k in steps], dtype=torch.float32)
    assert got.dtype == torch.float32 and got.shape == (len(steps), 4)
    assert torch.equal(got, want)
    assert float(rates(torch.tensor([-1], device=FAST_DEVICE)).abs().max()) == 0.0
    # The table ends where every schedule has settled, however long the run.
    assert rates.table.shape[0] == 250_000 + 2


def test_rates_past_the_last_step_are_the_last_steps():
    """A count past the run's last step (none is taken) reads that step's rates: the table stops there."""
    schedule = ExpSchedule(1e-2, 5e-6, 250_000)
    rates = StepRates([schedule], FAST_DEVICE, last_step=1_000)
    assert rates.table.shape[0] == 1_002
    got = [float(rates(StepClock.at(k, FAST_DEVICE).count)[0]) for k in (999, 1_000, 5_000)]
    want = float(torch.tensor(schedule(1_000), dtype=torch.float32))
    assert got[0] != want and got[1] == got[2] == want


def test_a_rate_tensor_steps_exactly_as_the_same_float():
    """A rate read from a tensor (inside a replayed step) takes the very step a float does: torch's
    `addcdiv` rounding, the tone optimiser's, the fused kernels'."""
    g = torch.Generator().manual_seed(3)
    param, grad = torch.randn(300, generator=g), torch.randn(300, generator=g)
    denom = torch.rand(300, generator=g) + 0.1
    lr = 0.0123456
    rate = torch.tensor([lr], dtype=torch.float32)
    assert torch.equal(descend_(param.clone(), grad, denom, rate), descend_(param.clone(), grad, denom, lr))

    params = [torch.randn(4, 3, generator=g), torch.randn(7, generator=g)]
    by_float, by_tensor = TorchRMSProp([p.clone() for p in params]), TorchRMSProp([p.clone() for p in params])
    for _ in range(3):
        grads = [torch.randn(p.shape, generator=g) for p in params]
        by_float.step(grads, lr)
        by_tensor.step(grads, rate)
    assert all(torch.equal(a, b) for a, b in zip(by_float.params, by_tensor.params))
    assert by_float.steps == by_tensor.steps == 3

    from hdrplenoxels.kernels.rmsprop_kernel import fused_rmsprop_

    for per_element in (False, True):
        out = []
        for given in (lr, rate.to(FAST_DEVICE)):
            p = torch.randn(50, 12, generator=torch.Generator().manual_seed(0)).to(FAST_DEVICE)
            v = torch.zeros_like(p)
            grads = torch.randn(2, 50, 12, generator=torch.Generator().manual_seed(1)).to(FAST_DEVICE)
            fused_rmsprop_(RMSPropStep(p, v, grads, given, 0.9, 1e-8, -1e9), per_element=per_element)
            out.append(p)
        assert torch.equal(*out)
    with pytest.raises(ValueError, match="rate tensor"):
        fused_rmsprop_(RMSPropStep(p, v, grads, torch.tensor([[lr]], device=FAST_DEVICE), 0.9, 1e-8, -1e9))


def test_the_optimisers_count_their_steps_on_the_device():
    """A replayed step runs no Python: the grid optimiser's count, which its touched update reads, lives
    on the parameters' device and advances there; a checkpoint reads it back."""
    opt = Svox2RMSProp()
    p = [torch.zeros(5, device=FAST_DEVICE)]
    for _ in range(4):
        opt.step(p, [torch.ones(5, device=FAST_DEVICE)], torch.tensor([0.1], device=FAST_DEVICE))
    assert opt.count.device == p[0].device and int(opt.count[0]) == opt.steps == 4
    assert int(opt.checkpoint_arrays()["steps"]) == 4
    opt.reset()
    assert opt.steps == 0 and opt.count is None


def test_rmsprop_first_and_second_step():
    g = torch.Generator().manual_seed(0)
    theta0 = torch.randn(50, generator=g, dtype=torch.float64)
    sh0 = torch.randn(50, 27, generator=g, dtype=torch.float64)
    g1 = torch.randn(50, generator=g, dtype=torch.float64)
    s1 = torch.randn(50, 27, generator=g, dtype=torch.float64)
    g1[:5] = 0.0  # untouched voxels: state stays 0
    theta, sh = theta0.clone(), sh0.clone()
    opt = Svox2RMSProp(beta=0.95, eps=1e-8)
    opt.step([theta, sh], [g1, s1], [2.0, 0.1])
    # v = g^2 on the first step, so the update is lr * sign(g) * |g| / (|g| + eps)
    assert torch.allclose(theta, theta0 - 2.0 * torch.sign(g1) * g1.abs() / (g1.abs() + 1e-8), rtol=1e-12)
    assert torch.allclose(sh, sh0 - 0.1 * torch.sign(s1) * s1.abs() / (s1.abs() + 1e-8), rtol=1e-12)
    assert torch.equal(theta[:5], theta0[:5])

    g2 = torch.randn(50, generator=g, dtype=torch.float64)
    s2 = torch.zeros(50, 27, dtype=torch.float64)
    theta1, sh1 = theta.clone(), sh.clone()
    opt.step([theta, sh], [g2, s2], [1.5, 0.1])
    v2 = torch.where(g1 == 0, g2**2, 0.95 * g1**2 + 0.05 * g2**2)  # fresh (v == 0) entries restart at g^2
    assert torch.allclose(opt.state[0], v2, rtol=1e-12)
    assert torch.allclose(theta, theta1 - 1.5 * g2 / (v2.sqrt() + 1e-8), rtol=1e-12)
    # zero gradient everywhere (dense update): parameters unchanged, v decays by beta
    assert torch.equal(sh, sh1)
    assert torch.allclose(opt.state[1], 0.95 * s1**2, rtol=1e-12)


def test_rmsprop_lower_bound_and_none_grad():
    theta = torch.tensor([-1e9 + 10.0, 0.0, 5.0])
    opt = Svox2RMSProp()
    opt.step([theta], [torch.tensor([1.0, 0.0, -1.0])], [1e6])
    assert theta[0].item() == -1e9
    assert theta[1].item() == 0.0
    assert theta[2].item() == pytest.approx(5.0 + 1e6, rel=1e-6)
    before = theta.clone()
    opt.step([theta], [None], [1e6])
    assert torch.equal(theta, before)
    assert torch.allclose(opt.state[0], torch.tensor([0.95, 0.0, 0.95]))


def test_rmsprop_works_on_leaf_parameters():
    p = torch.nn.Parameter(torch.ones(4))
    (p * torch.arange(4.0)).sum().backward()
    Svox2RMSProp().step([p], [p.grad], [0.5])
    assert torch.allclose(p.detach(), torch.tensor([1.0, 0.5, 0.5, 0.5]))


def test_rmsprop_reset_and_shape_checks():
    opt = Svox2RMSProp()
    a = torch.zeros(4)
    opt.step([a], [torch.ones(4)], [0.1])
    with pytest.raises(ValueError, match="reset"):
        opt.step([torch.zeros(6)], [torch.ones(6)], [0.1])
    with pytest.raises(ValueError):
        opt.step([a, a], [torch.ones(4)], [0.1])
    opt.reset()
    b = torch.zeros(6)
    opt.step([b], [torch.ones(6)], [0.1])
    assert opt.state[0].shape == (6,)


def test_rmsprop_state_survives_a_checkpoint(tmp_path):
    grid = SparseGrid.create((3, 3, 3), basis_dim=4)
    g = torch.Generator().manual_seed(1)
    grads = [(torch.randn(27, generator=g), torch.randn(27, 12, generator=g)) for _ in range(3)]
    opt = Svox2RMSProp()
    opt.step([grid.density, grid.sh], list(grads[0]), [1.0, 0.1])
    save_grid(tmp_path / "ckpt.npz", grid, meta={"step": 1}, extra_arrays=opt.state_dict())

    grid2, meta, extra = load_grid(tmp_path / "ckpt.npz")
    opt2 = Svox2RMSProp()
    opt2.load_state_dict(extra)
    for gd, gs in grads[1:]:
        opt.step([grid.density, grid.sh], [gd, gs], [1.0, 0.1])
        opt2.step([grid2.density, grid2.sh], [gd, gs], [1.0, 0.1])
    assert torch.equal(grid.density, grid2.density) and torch.equal(grid.sh, grid2.sh)
    assert set(opt.state_dict()) == {"v0", "v1"}
    assert Svox2RMSProp().state_dict() == {}
    with pytest.raises(ValueError):
        opt2.load_state_dict({"v1": np.zeros(3)})


@pytest.mark.parametrize("pulled", [False, True])
def test_fused_rmsprop_per_element_equals_per_row(pulled):
    """CUDA's layout (a thread per element) against the CPU's (a thread per row), same gradients; with
    `pulled`, a pull and gradients on some rows only (the view prior's steps)."""
    from hdrplenoxels.kernels.rmsprop_kernel import fused_rmsprop_

    results = []
    for per_element in (False, True):
        g = torch.Generator().manual_seed(4)
        param = torch.randn(300, 27, generator=g)
        state = torch.zeros_like(param)
        for _ in range(3):
            hit = torch.rand(300, generator=g) < 0.4 if pulled else torch.ones(300, dtype=torch.bool)
            grads = torch.randn(2, 300, 27, generator=g) * hit[:, None]
            pull = torch.rand(27, generator=g) if pulled else None
            fused_rmsprop_(
                RMSPropStep(param, state, grads, 0.1, 0.9, 1e-8, -1e9, pull), per_element=per_element
            )
            assert (grads == 0).all()
        results.append((param, state))
    (p_rows, s_rows), (p_elems, s_elems) = results
    assert torch.allclose(p_rows, p_elems, atol=1e-6) and torch.allclose(s_rows, s_elems, atol=1e-6)
    assert s_rows.abs().min() > 0  # every element was updated


def test_the_fused_kernel_equals_its_oracle_step_by_step():
    """`rmsprop_kernel.fused_rmsprop_` against `rmsprop_reference.rmsprop_reference_` directly: three steps
    with a pull, a fresh state and a floor that clamps."""
    from hdrplenoxels.kernels.rmsprop_kernel import fused_rmsprop_
    from hdrplenoxels.kernels.rmsprop_reference import rmsprop_reference_

    g = torch.Generator().manual_seed(8)
    param, pull = torch.randn(200, 9, generator=g), torch.rand(9, generator=g)
    state = torch.zeros_like(param)
    fused_param, fused_state = param.to(FAST_DEVICE, copy=True), state.to(FAST_DEVICE, copy=True)
    for _ in range(3):
        grads = torch.randn(2, 200, 9, generator=g)
        rmsprop_reference_(RMSPropStep(param, state, grads, 0.5, 0.9, 1e-8, -1.5, pull))
        fast = grads.to(FAST_DEVICE, copy=True)
        fused_rmsprop_(
            RMSPropStep(fused_param, fused_state, fast, 0.5, 0.9, 1e-8, -1.5, pull.to(FAST_DEVICE))
        )
        assert (fast == 0).all() and (grads != 0).all()  # the kernel clears the parts, the oracle reads them
    assert torch.allclose(fused_param.cpu(), param, atol=1e-5) and torch.allclose(fused_state.cpu(), state)
    assert (param == -1.5).any() and (param > -1.5).any()  # the floor clamped some values, not all


def test_cpu_kernels_flush_subnormals_on_every_thread_and_restore_the_callers_mode(monkeypatch):
    """Warp's CPU kernels run with subnormals flushed (`warp_runtime.flushing_subnormals`): rows the pull
    alone moves, frozen at a subnormal value with a stalled mean square (a trained grid held millions,
    each many times slower a step on x86), end at 0, their mean square held at the floor, in both parts
    of a launch split over two threads, where the oracle (the mode left off) keeps the subnormal value;
    and the calling thread's own mode is left off, as it was. A subnormal stall from an older checkpoint
    is raised to the floor on loading, so that it is not read as a fresh state."""
    from hdrplenoxels.core import warp_runtime
    from hdrplenoxels.kernels import rmsprop_kernel
    from hdrplenoxels.kernels.rmsprop_reference import rmsprop_reference_

    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU has no flush-to-zero mode torch can set")
    monkeypatch.setattr(rmsprop_kernel, "cpu_workers", lambda: 2)
    monkeypatch.setattr(warp_runtime, "cpu_workers", lambda: 2)
    param = torch.full((4096, 27), -1.05e-41)
    opt = Svox2RMSProp()
    opt.load_state_dict({"v0": np.full((4096, 27), 1.26e-44, np.float32)})
    state = opt.state[0]
    assert (state == MEAN_SQUARE_FLOOR).all()
    pull = torch.full((27,), 2e-6)
    oracle_param, oracle_state = param.clone(), state.clone()
    zero = torch.zeros(1, 4096, 27)
    rmsprop_kernel.fused_rmsprop_(RMSPropStep(param, state, zero, 5e-3, 0.95, 1e-8, -1e9, pull))
    rmsprop_reference_(RMSPropStep(oracle_param, oracle_state, zero, 5e-3, 0.95, 1e-8, -1e9, pull))
    assert (param == 0).all() and (state == MEAN_SQUARE_FLOOR).all()
    assert (oracle_param == param.new_tensor(-1.05e-41)).all() and (oracle_state == MEAN_SQUARE_FLOOR).all()
    assert np.float32(MEAN_SQUARE_FLOOR) * np.float32(0.5) > 0  # this thread still keeps subnormals


def test_fused_rmsprop_equals_the_reference_and_clears_the_buffers():
    g = torch.Generator().manual_seed(3)
    density, sh = torch.randn(500, generator=g), torch.randn(500, 12, generator=g)
    fused_opt, ref_opt = Svox2RMSProp(beta=0.9), Svox2RMSProp(beta=0.9)
    fused_params = [density.to(FAST_DEVICE, copy=True), sh.to(FAST_DEVICE, copy=True)]
    ref_params = [density.clone(), sh.clone()]
    for step in range(4):
        grads = [torch.randn(2, 500, generator=g), torch.randn(2, 500, 12, generator=g)]
        for t in grads:
            t[:, : 50 * step] = 0.0  # untouched rows: their state only decays (and a fresh one stays 0)
        fused_grads = [t.to(FAST_DEVICE, copy=True) for t in grads]
        fused_opt.step_accumulated(fused_params, fused_grads, [0.3, 0.02], fused=True)
        ref_opt.step_accumulated(ref_params, grads, [0.3, 0.02], fused=False)
        assert all((t == 0).all() for t in fused_grads + grads)
    for a, b in zip(fused_params + fused_opt.state, ref_params + ref_opt.state):
        assert torch.allclose(a.cpu(), b, rtol=1e-5, atol=1e-7)
    assert (fused_params[1].cpu() - sh).abs().max() > 0.01


@pytest.mark.parametrize("per_element", [False, True])
def test_a_pull_is_added_to_the_gradient_in_the_fused_pass(per_element):
    """`pulls`: the fused update (a thread per row, or per element as on CUDA) adds `pull * param` to
    each row's gradient, as the reference step does."""
    from hdrplenoxels.kernels.rmsprop_kernel import fused_rmsprop_

    g = torch.Generator().manual_seed(5)
    density, sh = torch.randn(400, generator=g), torch.randn(400, 12, generator=g)
    pull = torch.rand(12, generator=g)
    pull[::4] = 0.0  # columns it leaves alone
    ref_opt, ref = Svox2RMSProp(beta=0.9), [density.clone(), sh.clone()]
    fused_sh, fused_state = sh.to(FAST_DEVICE, copy=True), torch.zeros(400, 12, device=FAST_DEVICE)
    for _ in range(3):
        grads = [torch.randn(2, 400, generator=g), torch.randn(2, 400, 12, generator=g) * 0.01]
        fast_grads = grads[1].to(FAST_DEVICE, copy=True)
        step = RMSPropStep(fused_sh, fused_state, fast_grads, 0.02, 0.9, 1e-8, -1e9, pull.to(FAST_DEVICE))
        fused_rmsprop_(step, per_element=per_element)
        ref_opt.step_accumulated(ref, grads, [0.3, 0.02], fused=False, pulls=[None, pull])
    assert torch.allclose(fused_sh.cpu(), ref[1], rtol=1e-5, atol=1e-6)
    unpulled = Svox2RMSProp(beta=0.9)
    alone = [density.clone(), sh.clone()]
    unpulled.step(alone, [None, None], [0.3, 0.02], pulls=[None, pull])
    moved = (alone[1] - sh).abs().amax(0)
    assert (moved[::4] == 0).all() and (moved[1::4] > 0).all()  # only the pulled columns move


def test_a_pulled_update_is_dense_even_with_touched_rows():
    """With a pull and touched rows, every row moves (the pull holds them all), the gradient parts are
    cleared, and the result is the dense reference's, equal to rounding; the mask is left cleared."""
    g = torch.Generator().manual_seed(6)
    m, c = 300, 12
    density, sh = torch.randn(m, generator=g), torch.randn(m, c, generator=g)
    pull = torch.full((c,), 0.5)
    fused_opt, ref_opt = Svox2RMSProp(beta=0.9), Svox2RMSProp(beta=0.9)
    fused = [density.to(FAST_DEVICE, copy=True), sh.to(FAST_DEVICE, copy=True)]
    ref = [density.clone(), sh.clone()]
    for _ in range(3):
        hit = torch.rand(m, generator=g) < 0.3
        grads = [torch.randn(2, m, generator=g) * hit, torch.randn(2, m, c, generator=g) * hit[:, None]]
        fused_grads = [t.to(FAST_DEVICE, copy=True) for t in grads]
        marks = hit.to(torch.uint8).to(FAST_DEVICE)
        fused_opt.step_accumulated(
            fused, fused_grads, [0.3, 0.02], touched=marks, pulls=[None, pull.to(FAST_DEVICE)]
        )
        ref_opt.step_accumulated(ref, grads, [0.3, 0.02], fused=False, pulls=[None, pull])
        assert not marks.any() and all((t == 0).all() for t in fused_grads)
    assert torch.allclose(fused[1].cpu(), ref[1], rtol=1e-5, atol=1e-6)
    assert torch.allclose(fused[0].cpu(), ref[0], rtol=1e-5, atol=1e-6)
    assert ((fused[1].cpu() - sh).abs().amax(1) > 0).all()  # every row moved, marked or not


@pytest.mark.parametrize("per_element", [False, True])
def test_a_dense_update_reads_only_the_touched_rows_gradients_with_the_same_result(per_element):
    """`fused_rmsprop_(touched=...)`, the view prior's dense steps: equal to the bit to the update that
    reads every row's gradient parts, as long as untouched rows' are 0; and it really leaves them
    unread (a gradient planted in an untouched row stays in the buffer and moves nothing)."""
    from hdrplenoxels.kernels.rmsprop_kernel import fused_rmsprop_

    g = torch.Generator().manual_seed(9)
    m, c = 300, 27
    sh, pull = torch.randn(m, c, generator=g), torch.rand(c, generator=g)
    runs = {}
    for scoped in (False, True):
        param, state = sh.to(FAST_DEVICE, copy=True), torch.zeros(m, c, device=FAST_DEVICE)
        gen = torch.Generator().manual_seed(10)
        for _ in range(3):
            hit = torch.rand(m, generator=gen) < 0.2
            grads = (torch.randn(2, m, c, generator=gen) * hit[:, None]).to(FAST_DEVICE)
            touched = hit.to(torch.uint8).to(FAST_DEVICE) if scoped else None
            step = RMSPropStep(param, state, grads, 0.02, 0.9, 1e-8, -1e9, pull)
            fused_rmsprop_(step, per_element=per_element, touched=touched)
            assert (grads == 0).all()
        runs[scoped] = (param.cpu(), state.cpu())
    assert torch.equal(runs[True][0], runs[False][0]) and torch.equal(runs[True][1], runs[False][1])
    param, state = sh.to(FAST_DEVICE, copy=True), torch.zeros(m, c, device=FAST_DEVICE)
    grads = torch.zeros(1, m, c, device=FAST_DEVICE)
    grads[0, 5] = 100.0  # a row with a gradient, not marked
    touched = torch.zeros(m, dtype=torch.uint8, device=FAST_DEVICE)
    fused_rmsprop_(
        RMSPropStep(param, state, grads, 0.02, 0.9, 1e-8, -1e9), per_element=per_element, touched=touched
    )
    assert (grads[0, 5] == 100.0).all() and torch.equal(param[5].cpu(), sh[5])


def test_a_pulled_step_reads_the_gradients_of_the_touched_rows_only():
    """`step_accumulated` with a pull and a touched mask hands the mask to the dense pass: a gradient
    planted in an unmarked row (which the mask's contract rules out) is left in its buffer, unread."""
    m, c = 64, 12
    params = [torch.zeros(m, device=FAST_DEVICE), torch.full((m, c), 0.5, device=FAST_DEVICE)]
    grads = [torch.zeros(2, m, device=FAST_DEVICE), torch.zeros(2, m, c, device=FAST_DEVICE)]
    grads[1][:, 3] = 1.0  # row 3: a gradient, unmarked
    grads[1][:, 7] = 1.0  # row 7: a gradient, marked
    marks = torch.zeros(m, dtype=torch.uint8, device=FAST_DEVICE)
    marks[7] = 1
    pull = torch.full((c,), 0.5, device=FAST_DEVICE)
    Svox2RMSProp(beta=0.9).step_accumulated(params, grads, [0.3, 0.02], touched=marks, pulls=[None, pull])
    assert (grads[1][:, 3] == 1.0).all() and (grads[1][:, 7] == 0.0).all() and not marks.any()


def test_touched_rows_update_equals_the_dense_update():
    """Visiting only the touched rows (paying an untouched row's decay when it is next touched) gives
    the dense update: same values every step, same state once caught up, buffers and marks cleared.
    Rows go untouched for stretches of every length, some are never touched (a fresh state stays 0),
    some are marked without a gradient, and a dense fused step in the middle pays what is owed."""
    g = torch.Generator().manual_seed(8)
    rows, columns, parts = 400, 9, 2
    start = [torch.randn(rows, generator=g), torch.randn(rows, columns, generator=g)]
    lazy_opt, dense_opt = Svox2RMSProp(beta=0.9), Svox2RMSProp(beta=0.9)
    lazy = [t.to(FAST_DEVICE, copy=True) for t in start]
    dense = [t.clone() for t in start]
    never = torch.arange(rows) < 40
    for step in range(30):
        hit = (torch.rand(rows, generator=g) < 0.15 + 0.1 * (step % 3)) & ~never
        grads = [
            torch.randn(parts, rows, generator=g) * hit,
            torch.randn(parts, rows, columns, generator=g) * hit[None, :, None],
        ]
        marks = (hit | (torch.rand(rows, generator=g) < 0.05)).to(torch.uint8)  # extra marks: g = 0
        lazy_grads = [t.to(FAST_DEVICE, copy=True) for t in grads]
        lazy_marks = None if step == 17 else marks.to(FAST_DEVICE)  # step 17: a dense fused step
        lazy_opt.step_accumulated(lazy, lazy_grads, [0.3, 0.05], fused=True, touched=lazy_marks)
        dense_opt.step_accumulated(dense, grads, [0.3, 0.05], fused=False)
        assert all((t == 0).all() for t in lazy_grads)
        assert lazy_marks is None or (lazy_marks == 0).all()
        for a, b in zip(lazy, dense):
            assert torch.allclose(a.cpu(), b, rtol=1e-5, atol=1e-6)
    assert lazy_opt.last_step is not None  # decay is owed: the states differ until it is paid
    assert not torch.allclose(lazy_opt.state[1].cpu(), dense_opt.state[1], rtol=1e-3)
    lazy_states, dense_states = lazy_opt.state_dict(), dense_opt.state_dict()
    for key in ("v0", "v1"):
        np.testing.assert_allclose(lazy_states[key], dense_states[key], rtol=1e-5, atol=1e-12)
        assert (dense_states[key][:40] == 0).all() and (dense_states[key][40:] > 0).all()
    assert (lazy[1].cpu() - start[1]).abs().max() > 0.1


@pytest.mark.parametrize("pulled", [False, True])
def test_the_touched_update_of_listed_rows_is_a_thread_per_rows(pulled):
    """CUDA's variant of the touched update (the touched rows listed, then a thread per value,
    `listed=True`) against a thread per row: rows that missed 0 to 9 steps, some fresh, two gradient
    parts, the occupancy marked; the same values, mean squares, last steps, marks and cleared buffers
    (to the bit on the CPU)."""
    from render_helpers import blob_grid

    from hdrplenoxels.kernels.occupancy_kernel import occupancy_for
    from hdrplenoxels.kernels.rmsprop_kernel import fused_grid_rmsprop_touched_

    g = torch.Generator().manual_seed(11)
    start = blob_grid()
    n, columns = start.num_voxels, start.sh.shape[1]
    states = [torch.rand(n, generator=g), torch.rand(n, columns, generator=g) * 1e-2]
    states[0][:9] = 0.0  # fresh
    grads = [torch.randn(2, n, generator=g), torch.randn(2, n, columns, generator=g)]
    touched = (torch.rand(n, generator=g) < 0.4).to(torch.uint8)
    grads = [t * touched.reshape(1, n, *[1] * (t.dim() - 2)) for t in grads]
    last_step = 19 - torch.randint(0, 10, (n,), generator=g, dtype=torch.int32)
    pull = torch.rand(columns, generator=g) * 0.5 if pulled else None
    rates = torch.rand(64, generator=g) * 0.1
    got = []
    for listed in (False, True):
        grid = start.to(FAST_DEVICE)
        grid.density, grid.sh = grid.density.clone(), grid.sh.clone()
        occ = occupancy_for(grid, 2)
        run = [t.to(FAST_DEVICE, copy=True) for t in (*states, *grads, touched, last_step, rates)]
        fused_grid_rmsprop_touched_(
            (grid.density, grid.sh), (run[0], run[1]), (run[2], run[3]),
            (torch.tensor([0.3], device=FAST_DEVICE), torch.tensor([0.05], device=FAST_DEVICE)),
            run[4], run[5], torch.tensor([20], dtype=torch.int32, device=FAST_DEVICE), 0.9, 1e-8, -1e9, occ,
            pull=None if pull is None else pull.to(FAST_DEVICE), rates=run[6], listed=listed,
        )  # fmt: skip
        assert (run[2] == 0).all() and (run[3] == 0).all() and (run[4] == 0).all()  # buffers cleared
        got.append((grid.density, grid.sh, run[0], run[1], run[5], run[6], occ.cells.clone()))
    exact = FAST_DEVICE.type == "cpu"
    for a, b in zip(*got, strict=True):
        torch.testing.assert_close(b, a, rtol=0 if exact else 1e-5, atol=0 if exact else 1e-6)
    hit = touched.bool()
    assert torch.equal(got[0][4].cpu()[hit], torch.full((int(hit.sum()),), 20, dtype=torch.int32))
    assert not torch.equal(got[0][1].cpu()[hit], start.sh[hit]) and torch.equal(
        got[0][1].cpu()[~hit], start.sh[~hit]
    )


@pytest.mark.parametrize("read_state", [False, True])
@pytest.mark.parametrize("beta", [0.95, 0.5])
def test_a_row_untouched_for_thousands_of_steps_is_not_fresh_again(beta, read_state):
    """A positive mean square's decay stops at the smallest normal float (`MEAN_SQUARE_FLOOR`), so a row
    touched again after 3000 steps takes the decayed-state step (~lr / sqrt(1 - beta)), not a fresh
    state's step (lr), dense or owed, whatever beta: beta^3000 alone underflows to 0, which would read as
    fresh, and float32 decay by beta <= 0.5 reaches 0 too. Owed, the decay is paid by the touched-row
    kernel, or by `catch_up` in torch when the state is read first (as a checkpoint does)."""
    rows = 300
    gradient = [torch.full((rows,), 0.01), torch.full((rows, 3), 0.01)]
    lazy_opt, dense_opt = Svox2RMSProp(beta=beta), Svox2RMSProp(beta=beta)
    lazy = [torch.zeros(rows, device=FAST_DEVICE), torch.zeros(rows, 3, device=FAST_DEVICE)]
    dense = [torch.zeros(rows), torch.zeros(rows, 3)]

    def steps(touch: bool) -> None:
        grads = [(t if touch else torch.zeros_like(t))[None].to(FAST_DEVICE, copy=True) for t in gradient]
        marks = torch.full((rows,), int(touch), dtype=torch.uint8, device=FAST_DEVICE)
        lazy_opt.step_accumulated(lazy, grads, [0.1, 0.1], touched=marks)
        dense_opt.step(dense, gradient if touch else [None, None], [0.1, 0.1])

    steps(True)
    for _ in range(3000):
        steps(False)
    assert (dense_opt.state[1] == MEAN_SQUARE_FLOOR).all()  # held at the floor, not subnormal, not zero
    if read_state:
        lazy_opt.state_dict()
        assert (lazy_opt.state[1] == MEAN_SQUARE_FLOOR).all()
    before = [t.clone() for t in dense]
    steps(True)
    for a, b, was in zip(lazy, dense, before):
        moved = was - b
        assert torch.allclose(moved, torch.full_like(moved, 0.1 / (1 - beta) ** 0.5), rtol=1e-4)
        assert torch.allclose(a.cpu(), b, rtol=1e-5)


def test_a_checkpoint_taken_between_touched_row_steps_resumes_the_same():
    g = torch.Generator().manual_seed(2)
    rows = 200
    params = [torch.randn(rows, generator=g), torch.randn(rows, 4, generator=g)]
    hits = [torch.rand(rows, generator=g) < 0.3 for _ in range(6)]
    grads = [
        [torch.randn(1, rows, generator=g) * h, torch.randn(1, rows, 4, generator=g) * h[:, None]]
        for h in hits
    ]
    opt = Svox2RMSProp()

    def step(optimiser, p, grad, hit):
        optimiser.step_accumulated(p, [t.clone() for t in grad], [0.3, 0.1], touched=hit.to(torch.uint8))

    for grad, hit in zip(grads[:3], hits[:3]):
        step(opt, params, grad, hit)
    saved = opt.state_dict()
    resumed_params, resumed = [t.clone() for t in params], Svox2RMSProp()
    for grad, hit in zip(grads[4:], hits[4:]):  # a used optimiser, with decay owed, is overwritten
        step(resumed, [t.clone() for t in params], grad, hit)
    assert resumed.last_step is not None
    resumed.load_state_dict(saved)
    for grad, hit in zip(grads[3:], hits[3:]):
        step(opt, params, grad, hit)
        step(resumed, resumed_params, grad, hit)
    for a, b in zip(params, resumed_params):
        assert torch.allclose(a, b, rtol=1e-6)
    for key, value in opt.state_dict().items():
        np.testing.assert_allclose(value, resumed.state_dict()[key], rtol=1e-5)


def test_touched_rows_add_to_the_occupancy_until_it_is_rebuilt_exactly():
    """The touched-row update marks the cells of voxels it leaves with density > 0 without clearing the
    others (a superset of the exact occupancy: skipping stays exact), however many such updates run
    (a replayed CUDA graph launches the same update every step), until `rebuild` (which the training
    engine calls between steps, tests/test_sync_free_step.py)."""
    from render_helpers import blob_grid

    from hdrplenoxels.kernels.occupancy_kernel import occupancy_for
    from hdrplenoxels.kernels.occupancy_reference import occupancy_reference

    grid = blob_grid().to(FAST_DEVICE)
    occ = occupancy_for(grid, 2)
    opt = Svox2RMSProp()
    g = torch.Generator().manual_seed(5)
    n = grid.num_voxels
    for i in range(40):
        occupied = grid.density.cpu() > 0
        # Step 0 empties every occupied voxel; later ones empty and fill voxels at random.
        hit = occupied if i == 0 else torch.rand(n, generator=g) < 0.3
        sign = torch.where(occupied, 1.0, -1.0)
        grads = [torch.rand(1, n, generator=g) * sign * hit, torch.zeros(1, *grid.sh.shape)]
        marks = hit.to(torch.uint8).to(FAST_DEVICE)
        opt.step_accumulated(
            [grid.density, grid.sh],
            [t.to(FAST_DEVICE) for t in grads],
            [12.0, 0.1],
            fused=True,
            occupancy=occ,
            touched=marks,
        )
        cells, blocks = occupancy_reference(grid.links.cpu(), grid.density.cpu(), 2)
        got_cells, got_blocks = occ.cells.cpu(), occ.blocks.cpu()
        assert not (cells & ~got_cells).any() and not (blocks & ~got_blocks).any()  # a superset
        assert occ.density_stamp.matches(grid.density)  # renders will not rebuild it
        if i == 0:
            assert cells.sum() == 0 and got_cells.sum() > 0  # every voxel emptied, the marks left stale
    assert (got_cells > cells).any()  # still more than exact after 40 updates
    occ.rebuild(grid.density)
    assert torch.equal(occ.cells.cpu(), cells) and torch.equal(occ.blocks.cpu(), blocks)  # rebuilt exactly


def test_a_touched_row_update_handed_a_stale_occupancy_rebuilds_it_first():
    """The touched-row update only adds marks, so an occupancy that does not hold for the density it
    starts from (here: a dense reference step filled voxels behind its back) is rebuilt first."""
    from render_helpers import blob_grid

    from hdrplenoxels.kernels.occupancy_kernel import occupancy_for
    from hdrplenoxels.kernels.occupancy_reference import occupancy_reference

    grid = blob_grid()
    occ = occupancy_for(grid, 2)
    opt, n = Svox2RMSProp(), grid.num_voxels
    fill = [-torch.ones(1, n), torch.zeros(1, *grid.sh.shape)]  # every voxel's density rises by 5
    opt.step_accumulated([grid.density, grid.sh], fill, [5.0, 0.1], fused=False)
    nothing = [torch.zeros(1, n), torch.zeros(1, *grid.sh.shape)]
    opt.step_accumulated(
        [grid.density, grid.sh],
        nothing,
        [5.0, 0.1],
        fused=True,
        occupancy=occ,
        touched=torch.zeros(n, dtype=torch.uint8),
    )
    cells, _ = occupancy_reference(grid.links, grid.density, 2)
    assert not (cells & ~occ.cells).any() and occ.density_stamp.matches(grid.density)


def test_fused_rmsprop_of_params_with_more_axes_equals_the_reference():
    """The MSI's density (L, H, W) and colour (L, H, W, 3) take the fused update, in rows over their last
    axes (one row per (L, H) pair)."""
    g = torch.Generator().manual_seed(5)
    start = [torch.rand(4, 5, 6, generator=g), torch.rand(4, 5, 6, 3, generator=g)]
    fused_opt, ref_opt = Svox2RMSProp(beta=0.9), Svox2RMSProp(beta=0.9)
    fused, ref = [t.clone() for t in start], [t.clone() for t in start]
    for _ in range(3):
        grads = [torch.randn(2, *t.shape, generator=g) for t in start]
        fused_grads = [t.clone() for t in grads]
        fused_opt.step_accumulated(fused, fused_grads, [0.3, 0.02], fused=True)
        ref_opt.step_accumulated(ref, grads, [0.3, 0.02], fused=False)
        assert all((t == 0).all() for t in fused_grads)
    for a, b in zip(fused + fused_opt.state, ref + ref_opt.state, strict=True):
        assert a.shape == b.shape and torch.allclose(a, b, rtol=1e-5, atol=1e-7)
    assert (fused[1] - start[1]).abs().max() > 0.01


def test_the_tone_parameters_rmsprop_kernel_steps_as_its_oracle():
    """`torch_rmsprop_` (what `TorchRMSProp` runs on CUDA) against `torch_rmsprop_reference_` over several
    steps, from a fresh state, with a float rate and a tensor rate; and `TorchRMSProp` takes it under
    `kernels.dispatch.KERNELS_ON_CPU`."""
    from hdrplenoxels.kernels.torch_rmsprop import TorchRMSPropStep
    from hdrplenoxels.kernels.torch_rmsprop_kernel import torch_rmsprop_
    from hdrplenoxels.kernels.torch_rmsprop_reference import torch_rmsprop_reference_

    g = torch.Generator().manual_seed(4)
    shape = (2, 3, 255)
    start, grads = torch.randn(shape, generator=g), [torch.randn(shape, generator=g) * 1e-3 for _ in range(4)]
    for lr in (0.01, torch.tensor([0.01])):
        want_p, want_v = start.clone(), torch.zeros(shape)
        got_p, got_v = start.clone().to(FAST_DEVICE), torch.zeros(shape, device=FAST_DEVICE)
        fast_lr = lr.to(FAST_DEVICE) if isinstance(lr, torch.Tensor) else lr
        for grad in grads:
            torch_rmsprop_reference_(TorchRMSPropStep(want_p, want_v, grad, lr, 0.95, 1e-8))
            torch_rmsprop_(TorchRMSPropStep(got_p, got_v, grad.to(FAST_DEVICE), fast_lr, 0.95, 1e-8))
        torch.testing.assert_close(got_v.cpu(), want_v, rtol=1e-5, atol=0)
        torch.testing.assert_close(got_p.cpu(), want_p, rtol=1e-5, atol=1e-7)
        assert (want_p - start).abs().mean() > 0.01  # they moved: a first step is about lr
    with pytest.raises(ValueError, match="grad must be contiguous float32"):
        torch_rmsprop_(
            TorchRMSPropStep(start.clone(), torch.zeros(shape), grads[0].double(), 0.01, 0.95, 1e-8)
        )


def test_the_tone_optimiser_takes_the_kernel_on_the_fused_path(monkeypatch):
    from hdrplenoxels.kernels import dispatch
    from hdrplenoxels.train import optim

    calls = []
    monkeypatch.setattr(optim, "torch_rmsprop_", lambda step: calls.append(step.param.shape))
    params = [torch.zeros(4, 3), torch.zeros(7)]
    TorchRMSProp(params).step([torch.ones(4, 3), torch.ones(7)], 0.1)
    assert calls == [] and (params[0] != 0).all()  # a CPU: PyTorch's operators
    monkeypatch.setattr(dispatch, "KERNELS_ON_CPU", True)
    TorchRMSProp(params).step([torch.ones(4, 3), torch.ones(7)], 0.1)
    assert calls == [(4, 3), (7,)]
