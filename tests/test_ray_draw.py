"""The ray draw (`kernels/ray_draw_kernel.py`) against its PyTorch oracle (`kernels/ray_draw_reference.py`):
every pixel of a pool with an empty slot and a half-width slot, world and NDC rays (one camera facing
away), and the trainer's pool."""

from __future__ import annotations

import torch
from devices import FAST_DEVICE

from hdrplenoxels.data.placement import setup_scene
from hdrplenoxels.geometry.cameras import NDCSpec
from hdrplenoxels.kernels.ray_draw import PooledPixels
from hdrplenoxels.kernels.ray_draw_kernel import draw_rays
from hdrplenoxels.kernels.ray_draw_reference import draw_rays_reference
from hdrplenoxels.train.ray_pool import RayPool


def rotation(g: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return (q if torch.det(q) > 0 else -q).float()


def pool_arrays(seed: int = 0):
    """Four images (7x5, 6x4, 9x3, 5x5) in slots [0, 2, 3, 1]: slot 1 empty, slot 2 its left 4 columns."""
    g = torch.Generator().manual_seed(seed)
    sizes = torch.tensor([[7, 5], [6, 4], [9, 3], [5, 5]])
    slot_images = torch.tensor([0, 2, 3, 1])
    full_width = sizes[slot_images, 0]
    used_width = torch.tensor([7, 0, 4, 6])
    heights = sizes[slot_images, 1]
    counts = used_width * heights
    starts = torch.cumsum(counts, 0) - counts
    pixel_counts = full_width * heights
    pixel_offsets = torch.cumsum(pixel_counts, 0) - pixel_counts
    pixels = torch.randint(0, 256, (int(pixel_counts.sum()), 3), generator=g, dtype=torch.uint8)
    c2w = torch.eye(4).repeat(4, 1, 1)
    for i in range(4):
        c2w[i, :3, :3] = rotation(g)
        c2w[i, :3, 3] = torch.randn(3, generator=g)
    c2w[3, :3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # faces away from NDC's +z
    intrinsics = torch.tensor(
        [[8.0, 8.5, 3.5, 2.5], [6.0, 6.0, 3.0, 2.0], [9.0, 7.0, 4.5, 1.5], [5.0, 5.0, 2.5, 2.5]]
    )
    arrays = (starts, used_width, full_width, slot_images, pixel_offsets, pixels, c2w, intrinsics)
    return int(counts.sum()), arrays


def compare(flat: torch.Tensor, arrays: tuple, ndc: NDCSpec | None) -> None:
    pool = PooledPixels(*arrays, ndc)
    want = draw_rays_reference(flat, pool)
    got = draw_rays(flat.to(FAST_DEVICE), pool.to(FAST_DEVICE))
    names = ("origins", "dirs", "target", "image_ids", "rows", "cols")
    for name, a, b in zip(names, got, want, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape, name
        torch.testing.assert_close(a.cpu(), b, rtol=1e-5, atol=1e-6, msg=name)


def test_every_pixel_of_a_pool_with_an_empty_and_a_half_slot_draws_as_the_oracle_does():
    total, arrays = pool_arrays()
    flat = torch.arange(total)
    want = draw_rays_reference(flat, PooledPixels(*arrays, None))
    assert set(want[3].tolist()) == {0, 1, 3} and want[5][want[3] == 3].max() == 3  # no slot 1; half of 3
    compare(flat, arrays, None)
    compare(flat, arrays, NDCSpec(1.7, 2.1, 0.8))
    _, dirs, *_ = draw_rays_reference(flat, PooledPixels(*arrays, NDCSpec(1.7, 2.1, 0.8)))
    assert (dirs == torch.tensor([0.0, 0.0, 1.0])).all(-1).any()  # the camera facing away


def test_a_batch_drawn_with_replacement_and_an_empty_one():
    total, arrays = pool_arrays(1)
    flat = torch.randint(0, total, (3000,), generator=torch.Generator().manual_seed(2))
    compare(flat, arrays, None)
    assert draw_rays(flat[:0], PooledPixels(*arrays, None))[0].shape == (0, 3)


def test_the_ray_pool_draws_with_the_kernel(tiny_scene, monkeypatch):
    """CUDA's path (`kernels.dispatch.kernels_on_cpu`): `RayPool.at` through the kernel, equal to the
    oracle's draw; outside the block the CPU draws with the oracle again."""
    from hdrplenoxels.kernels import dispatch
    from hdrplenoxels.train import ray_pool

    calls = []
    monkeypatch.setattr(ray_pool, "draw_rays", lambda *args: calls.append(1) or draw_rays(*args))
    cams, geom = setup_scene(tiny_scene)
    views = (tiny_scene.train_ids, tiny_scene.test_ids)
    pool = RayPool(tiny_scene.images, cams, geom, *views, "right-half", "cpu")
    flat = torch.randint(0, len(pool), (4000,), generator=torch.Generator().manual_seed(3))
    with dispatch.kernels_on_cpu():
        batch = pool.at(flat)
    pool.at(flat)
    want = draw_rays_reference(flat, pool.pooled())
    assert calls == [1] and not dispatch.KERNELS_ON_CPU
    for name, b in zip(("origins", "dirs", "target", "image_ids", "rows", "cols"), want, strict=True):
        torch.testing.assert_close(getattr(batch, name), b, rtol=1e-5, atol=1e-6, msg=name)
