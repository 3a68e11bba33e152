"""Warp, initialised once and quietly on first use, for every module that launches kernels.

Importing the package starts nothing: Warp's runtime (and its CUDA context, where there is a GPU) starts
at the first `warp_device` call, which every launch goes through. Every kernel here has a hand-written
backward (or none), so Warp's automatic adjoints are never generated: `KERNEL` is the decorator all our
kernels use.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import torch
import warp as wp

from hdrplenoxels.core.parallel import cpu_workers, run_parts

KERNEL = functools.partial(wp.kernel, module="unique", enable_backward=False)


@functools.cache
def ensure_warp() -> None:
    """Start Warp's runtime once, without its start-up banner or per-module load lines."""
    wp.config.log_level = logging.WARNING
    wp.init()


def to_warp(t: torch.Tensor, **kwargs) -> wp.array:
    """`wp.from_torch`, starting Warp first: every tensor a kernel sees goes through here."""
    ensure_warp()
    return wp.from_torch(t, **kwargs)


def warp_struct(struct_type, **fields):
    """An instance of a Warp struct with these fields set: Warp's struct constructors take no
    arguments, so every kernel argument would otherwise be built one assignment per line."""
    instance = struct_type()
    for name, value in fields.items():
        setattr(instance, name, value)
    return instance


def warp_device(t) -> str:
    """Warp's name for the device of torch tensor `t` (starting Warp on first use)."""
    ensure_warp()
    return "cpu" if t.device.type == "cpu" else f"cuda:{t.device.index or 0}"


def launch_parts(
    device: str, n: int, parts: list[tuple[int, int]], launch: Callable[[int, int, int], None]
) -> None:
    """`launch(start, stop, part)` over [0, n): on CPU once per part, on the CPU's threads (Warp runs a
    CPU kernel as one sequential loop); on CUDA once for all of it, on torch's current stream."""
    if device == "cpu":
        run_parts(parts, launch, cpu_workers())
    else:
        with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream())):
            launch(0, n, 0)


@wp.func
def mark_touched(touched: wp.array(dtype=wp.uint8), row: int):
    """Mark a row for the optimiser. Written only when unset: CPU threads marking rows in one cache
    line would otherwise take it from each other on every store."""
    if touched[row] == wp.uint8(0):
        touched[row] = wp.uint8(1)
