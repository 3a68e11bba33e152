"""The MSI background: Warp kernels (forward and hand-written backward) against the PyTorch oracle, the
composition C = C_fg + T_fg C_bg, a hand-computed case, and the TV regulariser."""

from __future__ import annotations

import math

import pytest
import torch
from devices import FAST_DEVICE
from render_helpers import inward_rays, random_sparse_grid

from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid, corner_weights
from hdrplenoxels.kernels import march_kernel
from hdrplenoxels.kernels.background_reference import msi_samples, render_background_reference
from hdrplenoxels.kernels.march_reference import (
    composite_weights,
    optical_lengths,
    ray_segments,
    sample_points,
)
from hdrplenoxels.render import RenderOptions, render_rays
from hdrplenoxels.render.autograd import render_background_warp
from hdrplenoxels.train.background_tv import (
    BackgroundTraining,
    msi_param_groups,
    msi_sparsity,
    msi_tv,
    msi_tv_grad_,
)

TOL = 1e-5
CENTER = (0.1, -0.2, 0.05)


def random_msi(grid: SparseGrid, layers: int, height: int, width: int, spl: int, seed: int) -> MSIBackground:
    g = torch.Generator().manual_seed(seed)
    bg = MSIBackground.create(grid, layers, height, width, samples_per_layer=spl)
    bg.density = torch.rand(bg.density.shape, generator=g) * 3.0 - 0.5  # some negative: ReLU'd away
    bg.color = torch.rand(bg.color.shape, generator=g) * 6.0 - 1.0  # HDR: well above 1, some below 0
    return bg


def axis_and_random_rays(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """From the box's centre and from inside the box: the 6 axis directions (poles and the azimuth
    seam at phi = +-pi included), then directions uniform over the sphere."""
    g = torch.Generator().manual_seed(seed)
    axes = torch.tensor(
        [[1, 0, 0], [-1, 0, 0], [-1, -0.0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
        dtype=torch.float32,
    )
    d = torch.cat([axes, torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)])
    o = torch.tensor(CENTER).expand_as(d).clone()
    o[len(axes) :] += (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    return o, d


def both(grid, bg, o, d, opt, seed=3):
    """(rgb, d density, d SH, d MSI density, d MSI colour) of both backends, on the CPU."""
    weights = torch.randn(o.shape[0], 3, generator=torch.Generator().manual_seed(seed))
    out = {}
    for backend, device in (("torch", torch.device("cpu")), ("warp", FAST_DEVICE)):
        leaves = [
            t.to(device, copy=True).requires_grad_(True)
            for t in (grid.density, grid.sh, bg.density, bg.color)
        ]
        g = SparseGrid(grid.links.to(device), leaves[0], leaves[1], grid.center, grid.radius)
        b = MSIBackground(leaves[2], leaves[3], bg.center, bg.radius, bg.samples_per_layer)
        rgb = render_rays(g, o.to(device), d.to(device), opt, backend=backend, background=b)
        (rgb * weights.to(device)).sum().backward()
        out[backend] = [rgb.detach().cpu()] + [t.grad.cpu() for t in leaves]
    return out


def assert_parity(out):
    names = ("rgb", "d_density", "d_sh", "d_bg_density", "d_bg_color")
    for name, ref, fast in zip(names, out["torch"], out["warp"]):
        err = ((ref - fast).abs() / ref.abs().clamp(min=1.0)).max().item()
        assert err <= TOL, f"{name}: max |warp - torch| / max(1, |torch|) = {err:.2e}"


@pytest.mark.parametrize(("layers", "height", "width", "spl"), [(2, 2, 2, 1), (4, 6, 10, 2), (7, 5, 16, 3)])
def test_parity_rays_leaving_the_box_at_all_angles(layers, height, width, spl):
    grid = random_sparse_grid((9, 8, 7), 9, seed=layers)
    grid.density = grid.density * 0.1  # thin: most rays reach the background
    bg = random_msi(grid, layers, height, width, spl, seed=layers)
    o, d = axis_and_random_rays(200, seed=layers)
    out = both(grid, bg, o, d, RenderOptions())
    assert_parity(out)
    assert out["torch"][3].abs().max() > 1e-3 and out["torch"][4].abs().max() > 1e-3  # gradients flow
    assert out["torch"][1].abs().max() > 1e-3  # and into the grid too


def test_parity_for_cameras_outside_the_box_and_rays_that_miss_it():
    grid = random_sparse_grid((8, 8, 8), 4, seed=1)
    bg = random_msi(grid, 5, 6, 12, 2, seed=1)
    o, d = inward_rays(120, seed=4, center=CENTER)
    o[:40] = torch.tensor([4.0, 3.0, -2.0])
    d[:40] = torch.nn.functional.normalize(torch.tensor([1.0, 0.3, 0.2]) + 0.3 * torch.randn(40, 3), dim=-1)
    assert (ray_segments(grid, o, d, RenderOptions()).num_samples[:40] == 0).all()  # they miss the box
    out = both(grid, bg, o, d, RenderOptions(background_brightness=0.3))
    assert_parity(out)
    # With the box missed, T_fg = 1: the ray sees the MSI alone.
    alone = render_background_reference(bg, o[:40], d[:40], RenderOptions(background_brightness=0.3))
    assert torch.allclose(out["warp"][0][:40], alone, atol=1e-5)


def test_rays_stopping_early_in_the_foreground_see_no_background():
    grid = random_sparse_grid((10, 10, 10), 9, seed=4, empty_fraction=0.05)
    grid.density = grid.density.abs() * 40.0  # opaque: most rays stop early
    bg = random_msi(grid, 4, 4, 8, 2, seed=2)
    bg.color = bg.color * 1e4  # a sun: if stopped rays saw it, their radiance would be huge
    o, d = inward_rays(150, seed=5, center=CENTER)
    opt = RenderOptions(stop_thresh=1e-3)
    out = both(grid, bg, o, d, opt)
    assert_parity(out)
    stopped = (out["torch"][0] < 50).all(-1)
    assert stopped.float().mean() > 0.5
    # Stopped rays leave T_fg = 0: no gradient reaches the MSI from them.
    blocked = both(grid, bg, o[stopped], d[stopped], opt)
    assert_parity(blocked)
    for backend in ("torch", "warp"):
        assert blocked[backend][3].abs().max() == 0 and blocked[backend][4].abs().max() == 0


def test_transmittance_is_returned_and_the_scalar_path_is_unchanged():
    grid = random_sparse_grid((9, 8, 7), 4, seed=2)
    o, d = inward_rays(100, seed=6, center=CENTER)
    opt = RenderOptions(background_brightness=0.7)
    plain = march_kernel.render_forward(grid, o, d, opt)
    t_fg = torch.empty(100)
    behind = torch.rand(100, 3) * 5.0
    per_ray = march_kernel.render_forward(grid, o, d, opt, behind=behind, transmittance=t_fg)
    seg = ray_segments(grid, o, d, opt)
    pos, level, _, valid = sample_points(seg, opt.step_size)
    rows, cw = corner_weights(grid.links, pos, level)
    sigma = (cw * (rows >= 0) * grid.density[rows.clamp(min=0)]).sum(-1)
    _, t_ref = composite_weights(sigma, valid, optical_lengths(seg, valid, opt), opt)
    assert torch.allclose(t_fg, t_ref, atol=1e-6) and (t_fg > 0.05).any() and (t_fg < 0.95).any()
    assert torch.allclose(per_ray, plain + t_fg[:, None] * (behind - 0.7), atol=1e-5)
    # A transparent MSI shows the constant background: the same image as without one.
    clear = MSIBackground.create(grid, 3, 4, 8, density=0.0)
    with_msi = render_rays(grid, o, d, opt, background=clear)
    assert torch.allclose(with_msi, render_rays(grid, o, d, opt), atol=1e-6)


def test_lane_kernels_composite_the_per_ray_background():
    grid = random_sparse_grid((9, 8, 7), 9, seed=3)
    o, d = inward_rays(80, seed=7, center=CENTER)
    behind = torch.rand(80, 3) * 3.0
    t_thread, t_lane = torch.empty(80), torch.empty(80)
    thread = march_kernel.render_forward(
        grid, o, d, RenderOptions(), lanes=0, behind=behind, transmittance=t_thread
    )
    lane = march_kernel.render_forward(
        grid, o, d, RenderOptions(), lanes=1, behind=behind, transmittance=t_lane
    )
    assert torch.allclose(thread, lane, atol=1e-5) and torch.allclose(t_thread, t_lane, atol=1e-6)


def test_uniform_msi_seen_from_the_centre_matches_the_closed_form():
    """Every sample of a ray from the centre is valid; K samples of optical depth sigma / spl each give
    C_bg = c (1 - exp(-sigma (L - 1))) + exp(-sigma (L - 1)) B, whatever the direction."""
    grid = SparseGrid.create((4, 4, 4), center=CENTER, radius=(1.0, 1.0, 1.0), basis_dim=1)
    bg = MSIBackground.create(grid, layers=5, height=4, width=8, density=0.3, color=7.5, samples_per_layer=3)
    _, d = axis_and_random_rays(50, seed=8)
    o = torch.tensor(CENTER).expand_as(d)
    assert msi_samples(bg, o, d).valid.all()
    t = math.exp(-0.3 * 4)
    expect = torch.full_like(d, 7.5 * (1 - t) + 0.5 * t)
    for backend in ("torch", "warp"):
        got = render_background_warp(bg, o, d) if backend == "warp" else render_background_reference(bg, o, d)
        assert torch.allclose(got, expect, rtol=1e-5), backend


def test_msi_samples_are_beyond_the_box_and_front_to_back():
    grid = SparseGrid.create((4, 4, 4), center=CENTER, radius=(1.0, 0.5, 2.0), basis_dim=1)
    bg = MSIBackground.create(grid, layers=4, height=4, width=8)
    assert bg.radius == pytest.approx(math.sqrt(1 + 0.25 + 4))  # the box's outer sphere
    o, d = axis_and_random_rays(30, seed=9)
    smp = msi_samples(bg, o, d)
    assert smp.valid.all() and (smp.z[:, 1:] > smp.z[:, :-1]).all()
    assert smp.z.max() < bg.layers - 1 and smp.z.min() > 0


def test_msi_rejects_bad_shapes():
    with pytest.raises(ValueError, match="layers"):
        MSIBackground(torch.zeros(1, 4, 4), torch.zeros(1, 4, 4, 3), CENTER, 1.0)
    with pytest.raises(ValueError, match="colour"):
        MSIBackground(torch.zeros(2, 4, 4), torch.zeros(2, 4, 5, 3), CENTER, 1.0)


def test_tv_is_zero_for_a_constant_msi_and_pulls_outliers_back():
    grid = SparseGrid.create((4, 4, 4), center=CENTER, radius=(1.0, 1.0, 1.0), basis_dim=1)
    bg = MSIBackground.create(grid, layers=3, height=4, width=6, density=2.0, color=1.5)
    weights = BackgroundTraining(lambda_tv_sigma=1.0, lambda_tv_color=0.0)
    assert msi_tv(bg, weights).item() == pytest.approx(math.sqrt(1e-9), rel=1e-3)  # density only: one channel
    bg.density[1, 2, 0] = 5.0  # an outlier on the azimuth seam: its wrapped neighbour is column 5
    bg.density.requires_grad_(True)
    bg.color.requires_grad_(True)
    msi_tv(bg, weights).backward()
    assert bg.density.grad[1, 2, 0] > 0 and bg.density.grad[1, 2, 5] < 0  # wrap-around neighbour
    assert bg.color.grad.abs().max() == 0  # colour TV weight 0
    groups = msi_param_groups(bg, BackgroundTraining(lr_sigma=2.0, lr_color=0.25))
    assert [g["lr"] for g in groups] == [2.0, 0.25] and groups[0]["params"][0] is bg.density


def _tv_per_texel(values: torch.Tensor) -> torch.Tensor:
    """The oracle: (L, H, W) of sqrt(sum of squared forward differences + eps) summed over channels, one
    texel at a time (the azimuth wraps; the last layer and row have no forward neighbour)."""
    layers, height, width, _ = values.shape
    out = torch.zeros(layers, height, width, dtype=values.dtype)
    for z in range(layers):
        for y in range(height):
            for x in range(width):
                v = values[z, y, x]
                d_layer = values[z + 1, y, x] - v if z + 1 < layers else torch.zeros_like(v)
                d_row = values[z, y + 1, x] - v if y + 1 < height else torch.zeros_like(v)
                d_col = values[z, y, (x + 1) % width] - v
                out[z, y, x] = torch.sqrt(d_layer**2 + d_row**2 + d_col**2 + 1e-9).sum()
    return out


def test_sampled_tv_is_the_mean_over_its_texels():
    g = torch.Generator().manual_seed(3)
    grid = SparseGrid.create((4, 4, 4), center=CENTER, radius=(1.0, 1.0, 1.0), basis_dim=1)
    bg = MSIBackground.create(grid, layers=3, height=4, width=5)
    bg.density = torch.randn(3, 4, 5, generator=g, dtype=torch.float64)
    bg.color = torch.randn(3, 4, 5, 3, generator=g, dtype=torch.float64)
    weights = BackgroundTraining(lambda_tv_sigma=0.7, lambda_tv_color=0.3)
    per_texel = 0.7 * _tv_per_texel(bg.density[..., None]) + 0.3 * _tv_per_texel(bg.color)
    assert msi_tv(bg, weights).item() == pytest.approx(per_texel.mean().item(), rel=1e-12)
    texels = torch.tensor([19, 20, 21, 22, 58, 59, 0])  # a row's end, the seam, the last layer
    sampled = msi_tv(bg, weights, texels).item()
    assert sampled == pytest.approx(per_texel.reshape(-1)[texels].mean().item(), rel=1e-12)
    assert msi_tv(bg, weights, torch.arange(60)).item() == pytest.approx(per_texel.mean().item(), rel=1e-12)


@pytest.mark.parametrize("sampled", [False, True])
def test_tv_gradient_in_closed_form_matches_autograd(sampled):
    g = torch.Generator().manual_seed(4)
    grid = SparseGrid.create((4, 4, 4), center=CENTER, radius=(1.0, 1.0, 1.0), basis_dim=1)
    bg = MSIBackground.create(grid, layers=3, height=4, width=5)
    values = torch.randn(3, 4, 5, 3, generator=g, dtype=torch.float64)
    bg.color = values.clone().requires_grad_(True)
    run = torch.tensor([17, 18, 19, 20, 21, 55, 56, 57, 58, 59])  # across a row end and the seam
    texels = run if sampled else None
    colour_only = BackgroundTraining(lambda_tv_sigma=0.0, lambda_tv_color=0.3)
    (expected,) = torch.autograd.grad(msi_tv(bg, colour_only, texels), [bg.color])
    grad = torch.full_like(values, 0.25)  # the data term's gradient already there
    msi_tv_grad_(values, grad, 0.3, texels)
    assert torch.allclose(grad - 0.25, expected, rtol=1e-10, atol=1e-12)
    assert (expected != 0).sum() > (texels.numel() if sampled else 59)  # neighbours receive gradient too


@pytest.mark.parametrize("shape", [(3, 4, 5, 3), (2, 6, 2, 1), (1, 3, 7, 3)])
def test_the_msi_tv_kernel_adds_the_closed_forms_gradient(shape):
    """`msi_tv_kernel.msi_tv_grad_dense_` (CUDA's path) against `msi_tv_grad_reference_`: every texel, the
    first and last layers and rows, the seam, two columns (each texel both neighbours of the other), one
    layer, and a gradient already there."""
    from hdrplenoxels.kernels.msi_tv_kernel import msi_tv_grad_dense_
    from hdrplenoxels.kernels.msi_tv_reference import msi_tv_grad_reference_

    g = torch.Generator().manual_seed(5)
    values = torch.randn(shape, generator=g)
    start = torch.randn(shape, generator=g)
    want = start.clone()
    msi_tv_grad_reference_(values, want, 0.3)
    got = start.clone().to(FAST_DEVICE)
    msi_tv_grad_dense_(values.to(FAST_DEVICE), got, 0.3)
    torch.testing.assert_close(got.cpu(), want, rtol=1e-5, atol=1e-7)
    assert (want != start).all()
    with pytest.raises(ValueError, match="MSI TV"):
        msi_tv_grad_dense_(values, torch.zeros(shape).transpose(0, 1), 0.3)


def test_the_msi_tv_takes_the_kernel_on_the_fused_path(monkeypatch):
    from hdrplenoxels.kernels import dispatch
    from hdrplenoxels.train import background_tv

    calls = []
    monkeypatch.setattr(background_tv, "msi_tv_grad_dense_", lambda *args: calls.append(args[2]))
    values = torch.randn(2, 3, 4, 1)
    msi_tv_grad_(values, torch.zeros_like(values), 0.5)
    assert calls == []
    monkeypatch.setattr(dispatch, "KERNELS_ON_CPU", True)
    msi_tv_grad_(values, torch.zeros_like(values), 0.5)
    msi_tv_grad_(values, torch.zeros_like(values), 0.5, torch.arange(3))  # a sampled run: PyTorch's
    assert calls == [0.5]


def test_engine_samples_the_msi_tv_when_asked():
    """With `background.tv_sparsity` < 1 one step's TV reaches only its sampled run of texels and their
    neighbours; at 1 (the default) every texel."""
    from hdrplenoxels.data.placement import SceneGeometry
    from hdrplenoxels.train.config import TrainConfig
    from hdrplenoxels.train.engines.torch_grid import TorchGridEngine

    geometry = SceneGeometry("bbox", CENTER, (1.0, 1.0, 1.0), torch.eye(4).numpy(), wants_background=True)
    touched = {}
    for fraction in (1.0, 0.05):
        cfg = TrainConfig()
        cfg.background.layers, cfg.background.height, cfg.background.width = 4, 8, 16
        cfg.background.tv_sparsity = fraction
        cfg.optim.lambda_tv_sigma = cfg.optim.lambda_tv_sh = 0.0
        cfg = cfg.resolved(background_brightness=0.5, wants_background=True, levels=1)
        field = TorchGridEngine.new_field(cfg, geometry, 1, torch.device("cpu"))
        background = TorchGridEngine.new_background(cfg, geometry, field)
        background.density = torch.randn(4, 8, 16, generator=torch.Generator().manual_seed(0))
        engine = TorchGridEngine(field, cfg, RenderOptions(), background)
        engine.regularise(torch.Generator().manual_seed(1))
        touched[fraction] = int((engine.background_gradients().total()[0] != 0).sum())
    assert touched[1.0] == 4 * 8 * 16
    assert 0 < touched[0.05] <= 4 * 25  # 25 sampled texels, each with at most 3 neighbours


def test_fitting_an_msi_recovers_an_hdr_surround_outside_the_box():
    """A tiny unbounded scene: an empty box inside a bright, textured surround (values up to ~9). Rays from
    inside the outer sphere are fitted through the Warp path; held-out rays that miss the box are scored."""
    grid = SparseGrid.create((6, 6, 6), center=CENTER, radius=(0.5, 0.5, 0.5), basis_dim=1)
    grid.density = torch.full_like(grid.density, -1.0)
    truth = MSIBackground.create(grid, layers=3, height=8, width=16, density=1.5)
    rows = torch.linspace(0, 1, 8)[None, :, None, None]
    cols = torch.cos(torch.linspace(0, 2 * math.pi, 17)[:-1])[None, None, :, None]
    truth.color = (1.0 + 4.0 * rows * (1 + cols) * torch.tensor([1.0, 0.8, 0.5])).expand(3, 8, 16, 3).clone()

    def rays(n, seed):
        g = torch.Generator().manual_seed(seed)
        o = torch.tensor(CENTER) + torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 0.8
        return o, torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)

    o, d = rays(3000, seed=10)
    target = render_background_reference(truth, o, d)
    to, td = rays(500, seed=11)
    outside = ray_segments(grid, to, td, RenderOptions()).num_samples == 0
    assert outside.sum() > 100
    test_target = render_background_reference(truth, to, td)[outside]

    model = MSIBackground.create(grid, layers=3, height=8, width=16, density=0.5, color=0.5)
    model.density.requires_grad_(True)
    model.color.requires_grad_(True)
    optim = torch.optim.Adam(msi_param_groups(model, BackgroundTraining(lr_sigma=0.1, lr_color=0.3)))
    for _ in range(150):
        optim.zero_grad()
        loss = ((render_rays(grid, o, d, background=model) - target) ** 2).mean()
        loss = loss + msi_tv(model, BackgroundTraining(lambda_tv_sigma=1e-4, lambda_tv_color=1e-4))
        loss.backward()
        optim.step()
    with torch.no_grad():
        fitted = render_rays(grid, to, td, background=model)[outside]
    flat_mse = ((test_target - RenderOptions().background_brightness) ** 2).mean()
    fitted_mse = ((fitted - test_target) ** 2).mean()
    assert 10 * torch.log10(flat_mse / fitted_mse) > 25.0  # dB over the flat grey background (43 measured)


def test_sparsity_pulls_density_towards_zero():
    grid = SparseGrid.create((4, 4, 4), center=CENTER, radius=(1.0, 1.0, 1.0), basis_dim=1)
    bg = MSIBackground.create(grid, layers=2, height=2, width=4)
    bg.density = torch.tensor([0.0, 0.5, -2.0, 3.0]).repeat(4).reshape(2, 2, 4).requires_grad_(True)
    loss = msi_sparsity(bg, BackgroundTraining(lambda_sparsity=2.0))
    assert loss.item() == pytest.approx(2.0 * torch.log1p(2 * bg.density.detach() ** 2).mean().item())
    loss.backward()
    assert (bg.density.grad.sign() == bg.density.detach().sign()).all()  # descent shrinks |density|
    assert msi_sparsity(bg).item() == 0.0  # off by default
