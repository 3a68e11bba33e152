"""Kernels compiled for one launch's features (`march_funcs.KernelVariant`, `march_kernel.kernel_variant`)
render and differentiate exactly as the general kernels, which read the same switches at run time, and as the
PyTorch oracle: fixing a switch at compile time may only drop code, never change arithmetic."""

from __future__ import annotations

import pytest
import torch
import warp as wp
from devices import FAST_DEVICE, on_fast
from render_helpers import cascade_grid, cascade_rays

from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels import march_kernel
from hdrplenoxels.kernels.grad_buffers import GridGradients
from hdrplenoxels.kernels.march_funcs import GENERAL, KernelVariant
from hdrplenoxels.kernels.sample_record import SampleRecord
from hdrplenoxels.render import RenderOptions, render_rays

N = 240


def _run(grid, o, d, opt, lanes, specialise, features, max_registers=None, shuffle_sum=None):
    """rgb, distortion sums, transmittance and the gradients of one forward + backward on the grid's
    device (tests/devices.py: CUDA where there is one), returned on the CPU."""
    gen = torch.Generator().manual_seed(5)
    upstream, dist_weight = on_fast(torch.randn(N, 3, generator=gen), torch.rand(N, generator=gen))
    behind = on_fast(torch.rand(N, 3, generator=gen))[0] if features else None
    transmittance = torch.empty(N, device=FAST_DEVICE) if features else None
    stats = torch.empty(N, 3, device=FAST_DEVICE) if features else None
    record = SampleRecord.empty(N, FAST_DEVICE, 3) if features and not lanes else None
    variant = {"specialise": specialise, "max_registers": max_registers, "shuffle_sum": shuffle_sum}
    rgb = march_kernel.render_forward(grid, o, d, opt, lanes, record, behind, transmittance, stats, **variant)
    grads = GridGradients(grid, parts=1 if lanes or FAST_DEVICE.type == "cuda" else 2)
    distortion = (stats, dist_weight) if features else None
    march_kernel.accumulate_backward(
        grid, o, d, rgb, upstream, opt, grads, lanes, record, distortion, **variant
    )
    return [t.cpu() for t in (rgb, stats, transmittance, *grads.total()) if t is not None]


def _problem(levels: int, basis: int = 9):
    grid = cascade_grid((9, 8, 7), basis, seed=levels, levels=levels, empty_fraction=0.2)
    o, d = cascade_rays(N, seed=levels + 1, levels=levels)
    return grid.to(FAST_DEVICE), *on_fast(o, d), grid


@pytest.mark.parametrize(
    ("lanes", "levels", "features"),
    [(0, 1, False), (0, 3, True), (8, 3, True)],
    ids=["thread-one-box-plain", "thread-cascade-every-feature", "lanes-cascade-every-feature"],
)
def test_a_specialised_kernel_equals_the_general_one_and_the_oracle(monkeypatch, lanes, levels, features):
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", lanes > 0)
    grid, o, d, cpu_grid = _problem(levels)
    opt = RenderOptions(stop_thresh=0.01, near_grad=1.5 if features else 0.0, background_brightness=0.3)
    general = _run(grid, o, d, opt, lanes, False, features)
    fixed = _run(grid, o, d, opt, lanes, True, features)
    assert len(general) == len(fixed) == (5 if features else 3)
    _assert_same(general, fixed)
    assert general[-1].abs().max() > 1e-3  # gradients really flow
    if not features:  # the general kernels meet the oracle with each feature on in their own tests
        _assert_meets_the_oracle(cpu_grid, o.cpu(), d.cpu(), opt, fixed)


@pytest.mark.parametrize("lanes", [0, 32], ids=["thread", "lanes"])
def test_a_register_capped_kernel_equals_the_general_one_and_the_oracle(monkeypatch, lanes):
    """On CUDA a cap moves registers to local memory, never the arithmetic (on a CPU there is no cap:
    the same kernels run)."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", lanes > 0)
    grid, o, d, cpu_grid = _problem(1)
    opt = RenderOptions(stop_thresh=0.01, background_brightness=0.3)
    general = _run(grid, o, d, opt, lanes, False, False)
    capped = _run(grid, o, d, opt, lanes, False, False, max_registers=64)
    _assert_same(general, capped)
    _assert_meets_the_oracle(cpu_grid, o.cpu(), d.cpu(), opt, capped)


@pytest.mark.parametrize("features", [False, True], ids=["plain", "every-feature"])
def test_a_shuffle_sum_kernel_equals_the_general_one_and_the_oracle(features):
    """The lanes' colour sum by warp shuffles (`shuffle_sum`) against the tile sum: on CUDA a warp of 32
    lanes a ray, the same colours and gradients to float rounding (another order of additions) and the
    oracle's; on a CPU, whose blocks have one lane, the same kernel with nothing to sum, to the bit."""
    grid, o, d, cpu_grid = _problem(3 if features else 1)
    opt = RenderOptions(stop_thresh=0.01, near_grad=1.5 if features else 0.0, background_brightness=0.3)
    general = _run(grid, o, d, opt, 32, False, features)
    shuffled = _run(grid, o, d, opt, 32, False, features, shuffle_sum=True)
    if FAST_DEVICE.type == "cuda":
        for a, b in zip(general, shuffled, strict=True):
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
    else:
        _assert_same(general, shuffled)
    if not features:
        _assert_meets_the_oracle(cpu_grid, o.cpu(), d.cpu(), opt, shuffled)


@pytest.mark.parametrize("per_block", [2, 4])
def test_rays_sharing_a_block_render_and_differentiate_as_a_block_a_ray(per_block):
    """`rays_per_block`: 2 rays of 16 lanes or 4 of 8 in a block of 32 (on CUDA; on a CPU each ray's one
    lane, the blocks' indexing and the last block's rays past the end the same) against a block a ray
    with the same lanes, and the oracle; 237 rays, so the last block is part empty."""
    grid, o, d, cpu_grid = _problem(2)
    o, d = o[:237], d[:237]
    opt = RenderOptions(stop_thresh=0.01, background_brightness=0.3)
    lanes = 32 // per_block
    upstream = on_fast(torch.randn(237, 3, generator=torch.Generator().manual_seed(5)))[0]
    out = []
    for rays_per_block in (1, per_block):
        layout = {"shuffle_sum": True, "rays_per_block": rays_per_block}
        rgb = march_kernel.render_forward(grid, o, d, opt, lanes, **layout)
        grads = GridGradients(grid, parts=1)
        march_kernel.accumulate_backward(grid, o, d, rgb, upstream, opt, grads, lanes, **layout)
        out.append([t.cpu() for t in (rgb, *grads.total())])
    if FAST_DEVICE.type == "cuda":
        for a, b in zip(*out, strict=True):
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
    else:
        _assert_same(*out)
    _assert_meets_the_oracle(cpu_grid, o.cpu(), d.cpu(), opt, out[1], upstream.cpu())


@pytest.mark.parametrize("cpu_blocks", [False, True], ids=["a-lane-a-ray", "blocks-of-lanes"])
def test_the_backward_taking_rows_from_the_corners_equals_reading_the_links(monkeypatch, cpu_blocks):
    """`rows_from_corners`: the lane backward's pending slots take each corner's row from the sample's
    `Corners` (empty corners -1, as the links give them), the same gradients, to the bit on a CPU (with a
    block of 32 lanes too: `enable_cpu_blocks`), in a cascade with empty voxels, and the oracle's."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", cpu_blocks)
    grid, o, d, cpu_grid = _problem(3)
    opt = RenderOptions(stop_thresh=0.01, background_brightness=0.3)
    upstream = on_fast(torch.randn(N, 3, generator=torch.Generator().manual_seed(5)))[0]
    rgb = march_kernel.render_forward(grid, o, d, opt, 32)
    out = []
    for from_corners in (False, True):
        grads = GridGradients(grid, parts=1)
        march_kernel.accumulate_backward(
            grid, o, d, rgb, upstream, opt, grads, 32, rows_from_corners=from_corners
        )
        out.append([t.cpu() for t in grads.total()])
    assert (cpu_grid.links < 0).any() and out[0][0].abs().max() > 1e-3  # empty corners, real gradients
    _assert_same([rgb.cpu(), *out[0]], [rgb.cpu(), *out[1]])
    _assert_meets_the_oracle(cpu_grid, o.cpu(), d.cpu(), opt, [rgb.cpu(), *out[1]], upstream.cpu())


def test_the_shuffle_sum_is_compiled_only_where_it_sums_nothing_wrong(monkeypatch):
    """`kernel_variant` asks for the shuffle kernel on CUDA, and on a CPU only with one lane a block."""
    grid = cascade_grid((9, 8, 7), 4, seed=1, levels=1)
    args = dict(distortion=False, per_ray_background=False, record=False, shuffle_sum=True)
    assert march_kernel.kernel_variant("cuda:0", grid, RenderOptions(), False, None, **args).shuffle_sum
    assert march_kernel.kernel_variant("cpu", grid, RenderOptions(), False, None, **args).shuffle_sum
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    assert not march_kernel.kernel_variant("cpu", grid, RenderOptions(), False, None, **args).shuffle_sum
    assert not march_kernel.kernel_variant(
        "cuda:0", grid, RenderOptions(), False, None, **args | {"shuffle_sum": None}
    ).shuffle_sum
    several = args | {"shuffle_sum": None, "rays_per_block": 4}  # several rays a block: summed by shuffles
    assert march_kernel.kernel_variant("cuda:0", grid, RenderOptions(), False, None, **several).shuffle_sum
    assert (
        march_kernel.kernel_variant("cpu", grid, RenderOptions(), False, None, **several).rays_per_block == 1
    )


def _assert_same(general: list[torch.Tensor], variant: list[torch.Tensor]) -> None:
    """Bit-equal outputs and gradients; on CUDA the gradients only to float rounding, because its atomic
    adds sum a voxel's terms in whatever order the rays arrive, so two runs of one kernel differ there."""
    for a, b in zip(general[:-2], variant[:-2]):  # rgb, distortion sums, transmittance
        assert torch.equal(a, b)
    for a, b in zip(general[-2:], variant[-2:]):  # the density and SH gradients
        if FAST_DEVICE.type == "cuda":
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
        else:
            assert torch.equal(a, b)


def _assert_meets_the_oracle(grid, o, d, opt, outputs, upstream: torch.Tensor | None = None) -> None:
    """The oracle's colours and gradients under `upstream` (default: `_run`'s) are `outputs`'."""
    if upstream is None:
        upstream = torch.randn(o.shape[0], 3, generator=torch.Generator().manual_seed(5))
    density, sh = grid.density.clone().requires_grad_(True), grid.sh.clone().requires_grad_(True)
    ref = render_rays(SparseGrid(grid.links, density, sh, grid.center, grid.radius), o, d, opt, "torch")
    (ref * upstream).sum().backward()
    for a, b in zip((ref.detach(), density.grad, sh.grad), outputs):
        assert (a - b).abs().max() <= 1e-5


def test_the_variant_fixes_what_the_launch_uses_only_when_asked():
    grid = cascade_grid((9, 8, 7), 4, seed=1, levels=2)
    features = dict(distortion=True, per_ray_background=False, record=True)
    opt = RenderOptions()
    assert march_kernel.kernel_variant("cuda:0", grid, opt, False, None, **features) == GENERAL
    assert march_kernel.kernel_variant("cuda:0", grid, opt, False, 96, **features) == KernelVariant(
        max_registers=96
    )
    assert (
        march_kernel.kernel_variant("cpu", grid, opt, False, 96, **features) == GENERAL
    )  # no registers to cap
    fixed = march_kernel.kernel_variant("cpu", grid, RenderOptions(near_grad=1.0), True, None, **features)
    assert fixed == KernelVariant(2, True, True, False, True)
    assert fixed.switches() == (2, 1, 1, 0, 1) and GENERAL.switches() == (0, -1, -1, -1, -1)
