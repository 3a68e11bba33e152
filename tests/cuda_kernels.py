"""CUDA's kernel choices on the CPU, for tests of what only a GPU would otherwise run: a warp of lanes
per ray (no sample record: the backward re-marches), one gradient buffer, the fused kernels and the owed
pull's paying pass a thread per value."""

from __future__ import annotations

import functools

from hdrplenoxels.kernels import dispatch, march_kernel, rmsprop_kernel
from hdrplenoxels.train.engines import warp_grid


def use_cuda_kernels(monkeypatch, lanes: int = march_kernel.CUDA_LANES) -> None:
    """Patch, for the test, what the package picks by device to what it picks on CUDA."""
    monkeypatch.setattr(dispatch, "KERNELS_ON_CPU", True)
    monkeypatch.setattr(
        march_kernel, "lanes_for", lambda device, given, rays=0: lanes if given is None else given
    )
    monkeypatch.setattr(warp_grid, "gradient_parts", lambda field: 1)  # CUDA's one buffer
    paying = rmsprop_kernel.pay_owed_rows_
    monkeypatch.setattr(rmsprop_kernel, "pay_owed_rows_", functools.partial(paying, per_element=True))
