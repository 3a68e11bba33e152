"""Per-thread gradient buffers are sized to the memory left, and fewer of them change no result."""

from __future__ import annotations

import torch
from render_helpers import inward_rays, random_sparse_grid

from hdrplenoxels.core.host_memory import available_memory_bytes
from hdrplenoxels.kernels import grad_buffers, march_kernel
from hdrplenoxels.kernels.grad_buffers import GridGradients, gradient_parts
from hdrplenoxels.render import RenderOptions


def write(path, text: str):
    path.write_text(text)
    return path


def test_available_memory_is_meminfo_capped_by_the_cgroup_headroom(tmp_path):
    meminfo = write(tmp_path / "meminfo", "MemTotal: 16000 kB\nMemFree: 100 kB\nMemAvailable: 8000 kB\n")
    limited = (write(tmp_path / "max", "5000000\n"), write(tmp_path / "current", "1000000\n"))
    unlimited_v2 = (write(tmp_path / "max2", "max\n"), tmp_path / "current")
    unlimited_v1 = (write(tmp_path / "limit1", "9223372036854771712\n"), tmp_path / "current")
    missing = (tmp_path / "absent", tmp_path / "absent too")

    assert available_memory_bytes(meminfo, [missing]) == 8000 * 1024
    assert available_memory_bytes(meminfo, [missing, limited]) == 4_000_000  # the container's limit wins
    assert available_memory_bytes(meminfo, [unlimited_v2, limited]) == 8000 * 1024  # first found decides
    assert available_memory_bytes(meminfo, [unlimited_v1]) == 8000 * 1024
    assert available_memory_bytes(tmp_path / "no meminfo", [limited]) == 4_000_000
    assert available_memory_bytes(tmp_path / "no meminfo", [missing]) is None
    assert available_memory_bytes(write(tmp_path / "odd", "MemAvailable: lots\n"), [missing]) is None


def test_gradient_parts_take_at_most_half_the_memory_left(monkeypatch):
    grid = random_sparse_grid((12, 10, 9), 9, seed=1)
    part_bytes = grid.num_voxels * 28 * 4
    monkeypatch.setattr(grad_buffers, "cpu_workers", lambda: 8)
    for available, parts in ((None, 8), (100 * part_bytes, 8), (6 * part_bytes, 4), (part_bytes, 1), (0, 1)):
        monkeypatch.setattr(grad_buffers, "available_memory_bytes", lambda a=available: a)
        assert gradient_parts(grid) == parts
    monkeypatch.setattr(grad_buffers, "cpu_workers", lambda: 1)
    assert gradient_parts(grid) == 1


def test_fewer_gradient_parts_than_threads_give_the_same_gradients(monkeypatch):
    grid = random_sparse_grid((12, 10, 9), 9, seed=7)
    o, d = inward_rays(2000, seed=8)
    weights = torch.randn(2000, 3)
    rgb = march_kernel.render_forward(grid, o, d, RenderOptions())
    totals = []
    for workers, parts in ((1, 1), (3, 1), (3, 2)):
        monkeypatch.setattr(march_kernel, "cpu_workers", lambda w=workers: w)
        grads = GridGradients(grid, parts)
        march_kernel.accumulate_backward(grid, o, d, rgb, weights, RenderOptions(), grads)
        totals.append(grads.total())
    assert totals[0][1].abs().max() > 0
    for density, sh in totals[1:]:
        assert torch.allclose(density, totals[0][0], atol=1e-5)
        assert torch.allclose(sh, totals[0][1], atol=1e-5)
