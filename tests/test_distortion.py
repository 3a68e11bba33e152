"""The distortion loss (docs/method.md, "Distortion"): its reference against the definition, and the Warp
kernels' forward value and hand-written gradients (thread and lane, with and without the sample record,
one box and a cascade, stopping early) against autograd through the reference."""

from __future__ import annotations

import pytest
import torch
import warp as wp
from devices import FAST_DEVICE
from render_helpers import TOL, cascade_grid, cascade_rays, inward_rays, random_sparse_grid

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels import march_kernel
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.march_reference import distortion_loss
from hdrplenoxels.kernels.sample_record import SampleRecord
from hdrplenoxels.render import RenderOptions, render_rays


def test_reference_equals_the_double_sum():
    g = torch.Generator().manual_seed(0)
    w = torch.rand(7, 40, generator=g) * (torch.rand(7, 40, generator=g) > 0.6) / 8
    behind = torch.rand(7, generator=g) * 0.5
    end = torch.randint(30, 41, (7,), generator=g)
    w = torch.where(torch.arange(40) < end[:, None], w, 0.0)  # no sample past a ray's end
    full = torch.cat([w, torch.zeros(7, 1)], 1)
    full[torch.arange(7), end] += behind  # the background: one more sample, at the ray's end
    s = torch.arange(41.0)
    pairs = (full[:, :, None] * full[:, None, :] * (s[:, None] - s[None, :]).abs()).sum((1, 2))
    expected = (pairs + (full**2).sum(1) / 3.0) / end  # along s = i / n
    assert torch.allclose(distortion_loss(w, behind, end), expected, rtol=1e-5)
    one = torch.zeros(1, 40)
    one[0, 12] = 0.9  # all the weight in one sample, the rest behind far away: mostly its own term
    solid = distortion_loss(one, torch.zeros(1), torch.tensor([40]))
    assert torch.allclose(solid, torch.tensor([0.81 / 3.0 / 40]))
    spread = torch.zeros(1, 40)
    spread[0, [3, 30]] = 0.45  # the same weight split far apart costs far more
    assert distortion_loss(spread, torch.zeros(1), torch.tensor([40])) > 20 * solid
    # A floater in front of a background costs too: the grid cannot empty itself into the background.
    floater = torch.zeros(1, 40)
    floater[0, 2] = 0.5
    assert distortion_loss(floater, torch.tensor([0.5]), torch.tensor([40])) > 20 * solid


def both(grid, o, d, opt, seed=1):
    """(rgb, distortion, d density, d SH) of both backends for loss = <rgb, a> + <distortion, b>."""
    gen = torch.Generator().manual_seed(seed)
    a, b = torch.randn(o.shape[0], 3, generator=gen), torch.rand(o.shape[0], generator=gen)
    out = {}
    for backend, device in (("torch", torch.device("cpu")), ("warp", FAST_DEVICE)):
        density = grid.density.to(device, copy=True).requires_grad_(True)
        sh = grid.sh.to(device, copy=True).requires_grad_(True)
        g = SparseGrid(grid.links.to(device), density, sh, grid.center, grid.radius)
        rgb, dist = render_rays(g, o.to(device), d.to(device), opt, backend, distortion=True)
        ((rgb * a.to(device)).sum() + (dist * b.to(device)).sum()).backward()
        out[backend] = [t.detach().cpu() for t in (rgb, dist, density.grad, sh.grad)]
    return out


def assert_close(out):
    for name, ref, fast in zip(("rgb", "distortion", "d_density", "d_sh"), out["torch"], out["warp"]):
        err = ((ref - fast).abs() / ref.abs().clamp(min=1.0)).max().item()
        assert err <= 3 * TOL, f"{name}: {err:.2e}"


@pytest.mark.parametrize("levels", [1, 3])
@pytest.mark.parametrize("stop", [1e-7, 0.05])
def test_thread_kernels_match_autograd(levels, stop):
    if levels == 1:
        grid, (o, d) = random_sparse_grid((10, 9, 8), 4, seed=2), inward_rays(300, seed=3)
    else:
        grid, (o, d) = cascade_grid((10, 9, 8), 4, seed=2), cascade_rays(300, seed=3)
    out = both(grid, o, d, RenderOptions(stop_thresh=stop))
    assert_close(out)
    assert (
        out["torch"][1].max() > 0.2
    )  # weight spread along the rays: a real loss (1/3 at most when gathered)


def test_the_distortion_gradient_is_not_the_colour_gradient():
    """With the colour term switched off, the density still gets a gradient that autograd agrees with."""
    grid, (o, d) = cascade_grid((8, 8, 8), 1, seed=4), cascade_rays(200, seed=5)
    density = grid.density.clone().requires_grad_(True)
    _, dist = render_rays(
        SparseGrid(grid.links, density, grid.sh, grid.center, grid.radius),
        o,
        d,
        RenderOptions(),
        "torch",
        distortion=True,
    )
    dist.sum().backward()
    rgb = march_kernel.render_forward(grid, o, d, RenderOptions(), distortion=(stats := torch.empty(200, 3)))
    grads = GridGradients(grid, parts=2)
    march_kernel.accumulate_backward(
        grid, o, d, rgb, torch.zeros(200, 3), RenderOptions(), grads, distortion=(stats, torch.ones(200))
    )
    assert density.grad.abs().max() > 1e-2
    assert torch.allclose(grads.total()[0], density.grad, atol=1e-4, rtol=1e-4)
    assert grads.total()[1].abs().max() == 0  # distortion never touches colour


def test_record_replay_and_lane_kernels_match(monkeypatch):
    grid, (o, d) = cascade_grid((9, 8, 7), 9, seed=6, empty_fraction=0.2), cascade_rays(250, seed=7)
    opt = RenderOptions(stop_thresh=0.01)
    gen = torch.Generator().manual_seed(3)
    a, b = torch.randn(250, 3, generator=gen), torch.rand(250, generator=gen)
    results = []
    for lanes, capacity in ((0, None), (0, 2), (0, 1000), (8, None), (32, None)):
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", lanes > 0)
        stats = torch.empty(250, 3)
        record = None if capacity is None else SampleRecord.empty(250, "cpu", capacity)
        rgb = march_kernel.render_forward(grid, o, d, opt, lanes=lanes, record=record, distortion=stats)
        grads = GridGradients(grid, parts=1 if lanes else 2)
        march_kernel.accumulate_backward(
            grid, o, d, rgb, a, opt, grads, lanes=lanes, record=record, distortion=(stats, b)
        )
        results.append((stats[:, 2].clone(), *grads.total()))
    for other in results[1:]:
        for x, y in zip(results[0], other):
            assert (x - y).abs().max() <= 1e-5 * max(1.0, float(x.abs().max()))
    _, dist = render_rays(grid, o, d, opt, "torch", distortion=True)
    assert torch.allclose(results[0][0], dist, rtol=1e-5, atol=1e-5)
