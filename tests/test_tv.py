"""TV regulariser (docs/method.md, "Training"): gradient equals autograd of the penalty; empty voxels,
edges, rho."""

from __future__ import annotations

import math

import pytest
import torch
from devices import FAST_DEVICE, on_fast

from hdrplenoxels.kernels.tv import TVTerm, sample_tv_cells
from hdrplenoxels.kernels.tv_reference import tv_grad_reference_, tv_value


def make_links(reso, seed=0, empty_frac=0.3) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    keep = torch.rand(reso, generator=g) >= empty_frac
    links = torch.full(reso, -1, dtype=torch.int32)
    # shuffled row order: row order must not matter
    links[keep] = torch.randperm(int(keep.sum()), generator=g).int()
    return links


def reference_penalty(links, values, cells, mode, weight, rho=(1.0, 1.0, 1.0)):
    """Cell-by-cell loop, written independently of the module: missing and out-of-range
    voxels as docs/method.md ("Training") states.

    With rho != 1 each difference passes `rho_a` times its gradient backwards (forward value unchanged),
    which is exactly the numerator-only anisotropic factor.
    """
    reso = links.shape
    zeros = torch.zeros(values.shape[1], dtype=values.dtype)

    def value_at(p):
        if any(p[a] >= reso[a] for a in range(3)):
            return None
        row = int(links[p])
        return None if row < 0 else values[row]

    total = torch.zeros((), dtype=values.dtype)
    for c in cells.tolist():
        x, y, z = c // (reso[1] * reso[2]), (c // reso[2]) % reso[1], c % reso[2]
        v0 = value_at((x, y, z))
        v0 = zeros if v0 is None else v0
        sq = torch.zeros_like(zeros)
        for a in range(3):
            p = [x, y, z]
            p[a] += 1
            vn = value_at(tuple(p))
            if vn is None:
                vn = zeros if mode == "zero" else v0
            d = vn - v0
            d = d * rho[a] + (d - d * rho[a]).detach()
            sq = sq + d**2
        total = total + torch.sqrt(sq + 1e-9).sum()
    return weight / len(cells) * total


def autograd_grad(links, values, cells, mode, weight, rho=(1.0, 1.0, 1.0)):
    v = values.clone().requires_grad_(True)
    reference_penalty(links, v, cells, mode, weight, rho).backward()
    return v.grad


@pytest.mark.parametrize("mode", ["zero", "self"])
def test_tv_gradient_matches_autograd_cubic(mode):
    reso = (5, 5, 5)
    links = make_links(reso, seed=1)
    m = int((links >= 0).sum())
    values = torch.randn(m, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    values[:4] = 0.0  # some zero differences too
    cells = torch.arange(125)
    grad = torch.zeros_like(values)
    tv_grad_reference_(TVTerm(links, values, 0.7, cells, mode, 5), grad)
    expected = autograd_grad(links, values, cells, mode, 0.7)
    assert torch.allclose(grad, expected, rtol=1e-9, atol=1e-12)
    # the value is the penalty whose gradient that is
    v = values.clone().requires_grad_(True)
    val = tv_value(links, v, cells, mode, weight=0.7)
    assert val.item() == pytest.approx(reference_penalty(links, values, cells, mode, 0.7).item(), rel=1e-12)
    val.backward()
    assert torch.allclose(v.grad, expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("mode", ["zero", "self"])
def test_tv_gradient_accumulates_on_a_wrapped_run_in_chunks(mode):
    reso = (4, 6, 5)
    links = make_links(reso, seed=3, empty_frac=0.4)
    m = int((links >= 0).sum())
    values = torch.randn(m, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    cells = (torch.arange(100, 150)) % 120  # wraps around the end
    start = torch.randn(m, 2, dtype=torch.float64)
    grad = start.clone()
    tv_grad_reference_(TVTerm(links, values, 1.3, cells, mode, 1), grad, chunk=7)  # rho = R: see next line
    rho = tuple(float(r) for r in reso)
    expected = start + autograd_grad(links, values, cells, mode, 1.3, rho)
    assert torch.allclose(grad, expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("mode", ["zero", "self"])
def test_tv_anisotropic_factor_on_numerator_only(mode):
    reso = (4, 5, 6)
    links = make_links(reso, seed=5)
    m = int((links >= 0).sum())
    values = torch.randn(m, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    cells = torch.arange(120)
    grad = torch.zeros_like(values)
    tv_grad_reference_(TVTerm(links, values, 0.5, cells, mode, 8), grad)
    rho = (4 / 8, 5 / 8, 6 / 8)
    assert torch.allclose(grad, autograd_grad(links, values, cells, mode, 0.5, rho), rtol=1e-9, atol=1e-12)
    # linear in rho: doubling the reference resolution halves the gradient
    grad2 = torch.zeros_like(values)
    tv_grad_reference_(TVTerm(links, values, 0.5, cells, mode, 16), grad2)
    assert torch.allclose(grad2, grad / 2, rtol=1e-12, atol=1e-15)
    # and it differs from the exact (isotropic) gradient on a non-cubic grid
    iso = autograd_grad(links, values, cells, mode, 0.5)
    assert not torch.allclose(grad, iso * (5 / 8), rtol=1e-3)


def test_tv_single_cell_by_hand():
    reso = (4, 5, 6)
    links = torch.arange(120, dtype=torch.int32).reshape(reso)
    values = torch.zeros(120, 1, dtype=torch.float64)
    centre, nx, ny, nz = int(links[1, 1, 1]), int(links[2, 1, 1]), int(links[1, 2, 1]), int(links[1, 1, 2])
    values[centre], values[nx], values[ny], values[nz] = 1.0, 3.0, 0.0, 2.0
    dx, dy, dz = 2.0, -1.0, 1.0
    u = 1.0 / math.sqrt(dx**2 + dy**2 + dz**2 + 1e-9)
    rho = (4 / 256, 5 / 256, 6 / 256)
    grad = torch.zeros_like(values)
    term = TVTerm(links, values, 2.0, torch.tensor([centre]), "zero")  # n = 1, default reference 256
    tv_grad_reference_(term, grad)
    assert grad[nx, 0].item() == pytest.approx(2.0 * u * rho[0] * dx, rel=1e-12)
    assert grad[ny, 0].item() == pytest.approx(2.0 * u * rho[1] * dy, rel=1e-12)
    assert grad[nz, 0].item() == pytest.approx(2.0 * u * rho[2] * dz, rel=1e-12)
    assert grad[centre, 0].item() == pytest.approx(-2.0 * u * (rho[0] * dx + rho[1] * dy + rho[2] * dz))
    assert int((grad != 0).sum()) == 4


def test_tv_edges_and_missing_voxels():
    reso = (2, 2, 2)
    links = torch.full(reso, -1, dtype=torch.int32)
    links[1, 1, 1] = 0  # last cell: every neighbour is past the edge
    links[0, 0, 0] = 1
    values = torch.tensor([[5.0], [1.0]], dtype=torch.float64)
    # zero mode: past-edge neighbours read 0 -> density pulled to 0, nothing leaks to row 0 from the edge
    grad = torch.zeros_like(values)
    tv_grad_reference_(TVTerm(links, values, 1.0, torch.tensor([7]), "zero", 2), grad)
    assert grad[0, 0].item() == pytest.approx(3 * 5.0 / math.sqrt(75.0 + 1e-9))
    assert grad[1, 0].item() == 0.0
    # self mode: missing / past-edge neighbours copy the cell -> no gradient at all
    grad = torch.zeros_like(values)
    tv_grad_reference_(TVTerm(links, values, 1.0, torch.tensor([7, 0]), "self", 2), grad)
    assert torch.equal(grad, torch.zeros_like(values))
    # missing centre counts as 0 in self mode; its existing +z neighbour (row 0 at (1,1,1)) gets gradient
    grad = torch.zeros_like(values)
    tv_grad_reference_(TVTerm(links, values, 1.0, torch.tensor([6]), "self", 2), grad)  # cell (1,1,0)
    assert grad[0, 0].item() == pytest.approx(5.0 / math.sqrt(25.0 + 1e-9))
    assert grad[1, 0].item() == 0.0


def test_tv_accepts_1d_density_and_float32():
    reso = (6, 6, 6)
    links = make_links(reso, seed=7)
    m = int((links >= 0).sum())
    density = torch.randn(m, generator=torch.Generator().manual_seed(8)) * 3
    grad = torch.zeros(m)
    cells = sample_tv_cells(reso, 0.5, torch.Generator().manual_seed(9))
    tv_grad_reference_(TVTerm(links, density, 5e-4, cells, "zero", 6), grad)
    expected = autograd_grad(links, density.double()[:, None], cells, "zero", 5e-4)[:, 0]
    assert torch.allclose(grad.double(), expected, rtol=1e-4, atol=1e-10)
    grad0 = torch.zeros(m)
    tv_grad_reference_(TVTerm(links, density, 0.0, cells, "zero"), grad0)
    assert torch.equal(grad0, torch.zeros(m))
    with pytest.raises(ValueError):
        tv_grad_reference_(TVTerm(links, density, 1.0, torch.tensor([216]), "zero"), grad0)
    with pytest.raises(ValueError):
        tv_grad_reference_(TVTerm(links, density, 1.0, cells, "edge"), grad0)  # type: ignore[arg-type]


def test_sample_tv_cells_contiguous_wrapping_run():
    reso = (10, 12, 9)
    total = 1080
    gen = torch.Generator().manual_seed(0)
    starts = set()
    wrapped = False
    for _ in range(200):
        cells = sample_tv_cells(reso, 0.05, gen)
        assert cells.dtype == torch.long and cells.shape == (54,)  # floor(0.05 * 1080)
        assert torch.all((cells[1:] - cells[:-1]) % total == 1)
        assert int(cells.min()) >= 0 and int(cells.max()) < total
        starts.add(int(cells[0]))
        wrapped |= bool((cells[1:] < cells[:-1]).any())
    assert wrapped and len(starts) > 150
    assert sample_tv_cells(reso, 1e-6, gen).shape == (1,)
    assert sample_tv_cells(reso, 2.0, gen).shape == (total,)
    a = sample_tv_cells(reso, 0.01, torch.Generator().manual_seed(5))
    b = sample_tv_cells(reso, 0.01, torch.Generator().manual_seed(5))
    assert torch.equal(a, b) and a.shape == (10,)


@pytest.mark.parametrize("per_channel", [False, True])
@pytest.mark.parametrize("mode", ["zero", "self"])
@pytest.mark.parametrize("channels", [0, 1, 12])
def test_warp_tv_kernel_equals_reference(mode, channels, per_channel):
    """Both layouts: a thread per cell, and per (cell, channel) (`per_channel`, a CUDA variant)."""
    from hdrplenoxels.kernels.tv_kernel import tv_grad_

    reso = (7, 6, 9)
    links = make_links(reso, seed=3)
    m = int((links >= 0).sum())
    shape = (m,) if channels == 0 else (m, channels)
    values = torch.randn(shape, generator=torch.Generator().manual_seed(4))
    values[:5] = 0.0
    cells = sample_tv_cells(reso, 0.3, torch.Generator().manual_seed(1))  # wraps past the last cell
    start = torch.randn(shape, generator=torch.Generator().manual_seed(5))  # added to, not overwritten
    expected, got = start.clone(), start.clone()
    tv_grad_reference_(TVTerm(links, values, 0.9, cells, mode, 8), expected)
    got, touched = got.to(FAST_DEVICE), torch.zeros(m, dtype=torch.uint8, device=FAST_DEVICE)
    fast_cells = cells.to(FAST_DEVICE)
    term = TVTerm(*on_fast(links, values), 0.9, fast_cells, mode, 8)
    tv_grad_(term, got, touched=touched, per_channel=per_channel)
    assert (got.cpu() - expected).abs().max() <= 1e-5
    assert (expected - start).abs().max() > 1e-2
    # The rows it adds to are marked for the optimiser, which visits only marked rows.
    written = (expected != start).reshape(m, -1).any(1)
    marked = touched.cpu() != 0
    assert not (written & ~marked).any() and not marked.all()


@pytest.mark.parametrize("mode", ["zero", "self"])
def test_warp_tv_shared_out_over_gradient_parts_sums_to_the_reference(mode, monkeypatch):
    """On the CPU the TV's cells are shared out over threads, each adding into its own gradient part
    (Warp's CPU atomics are plain adds): the parts sum to the reference, and each share is a mean over
    all the cells, not over its own."""
    import hdrplenoxels.kernels.tv_kernel as tv_kernel

    monkeypatch.setattr(tv_kernel, "cpu_workers", lambda: 3)
    monkeypatch.setattr(tv_kernel, "MIN_TV_CELLS_PER_THREAD", 256)
    reso = (16, 14, 18)  # 30 % of its cells give each of the 3 threads more than MIN_ITEMS_PER_WORKER
    links = make_links(reso, seed=3)
    m = int((links >= 0).sum())
    values = torch.randn((m, 4), generator=torch.Generator().manual_seed(4))
    cells = sample_tv_cells(reso, 0.3, torch.Generator().manual_seed(1))
    expected = torch.zeros_like(values)
    tv_grad_reference_(TVTerm(links, values, 0.9, cells, mode, 8), expected)
    parts, touched = torch.zeros((3, m, 4)), torch.zeros(m, dtype=torch.uint8)
    tv_kernel.tv_grad_(TVTerm(links, values, 0.9, cells, mode, 8), parts, touched)
    assert all((p != 0).any() for p in parts)  # every thread had cells to add
    assert (parts.sum(0) - expected).abs().max() <= 1e-5
    assert not ((expected != 0).any(1) & (touched == 0)).any()


@pytest.mark.parametrize("mode", ["zero", "self"])
def test_a_thread_per_channel_adds_and_marks_as_a_thread_per_cell(mode):
    """The per-(cell, channel) variant makes the same additions in the same order as the per-cell kernel:
    on the CPU the same gradient to the bit, and the same rows marked, with and without `marks_only`."""
    from hdrplenoxels.kernels.tv_kernel import tv_grad_

    reso = (9, 8, 7)
    links = make_links(reso, seed=6)
    m = int((links >= 0).sum())
    values = torch.randn((m, 27), generator=torch.Generator().manual_seed(7))
    cells = sample_tv_cells(reso, 0.4, torch.Generator().manual_seed(8))
    out = {}
    for per_channel in (False, True):
        grad, touched, read = (
            torch.zeros(m, 27),
            torch.zeros(m, dtype=torch.uint8),
            torch.zeros(m, dtype=torch.uint8),
        )
        term = TVTerm(links, values, 0.7, cells, mode, 8)
        tv_grad_(term, grad, touched=touched, per_channel=per_channel)
        tv_grad_(term, torch.zeros(m, 27), touched=read, marks_only=True, per_channel=per_channel)
        out[per_channel] = grad, touched, read
    assert torch.equal(out[False][0], out[True][0]) and out[True][0].abs().max() > 1e-3
    assert torch.equal(out[False][1], out[True][1]) and torch.equal(out[False][2], out[True][2])
    assert 0 < int(out[True][2].sum()) < m  # some rows read, not all
