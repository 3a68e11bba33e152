"""Warp, initialised once and quietly on first use, for every module that launches kernels.

Importing the package starts nothing: Warp's runtime (and its CUDA context, where there is a GPU) starts
at the first `warp_device` call, which every launch goes through. Every kernel here has a hand-written
backward (or none), so Warp's automatic adjoints are never generated: `KERNEL` is the decorator all our
kernels use.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import threading
from collections.abc import Callable

import numpy as np
import torch
import warp as wp

from hdrplenoxels.core.parallel import WARP_DEBUG_VARIABLE, cpu_workers, run_parts, split

KERNEL = functools.partial(wp.kernel, module="unique", enable_backward=False)


@functools.cache
def ensure_warp() -> None:
    """Start Warp's runtime once, without its start-up banner or per-module load lines. With
    `HDRPLENOXELS_WARP_DEBUG` set, kernels are built in Warp's debug mode, which checks every array
    access and aborts on one out of bounds (slow, and on one CPU thread: for tests and bug hunts)."""
    wp.config.log_level = logging.WARNING
    if os.environ.get(WARP_DEBUG_VARIABLE):
        wp.config.mode = "debug"
    wp.init()


# Warp keeps an array's shape and byte strides as 32-bit ints (JOURNAL.md, "Large arrays"): a
# larger stride wraps to another address, so kernels would read and write outside the tensor.
WARP_INDEX_LIMIT = 2**31 - 1


class WarpAddressingError(ValueError):
    """A tensor Warp cannot address: a stride in bytes or an extent past 32 bits."""


def check_addressable(name: str, shape, byte_strides) -> None:
    """Raise `WarpAddressingError` naming `name` unless Warp addresses every element of an array of
    `shape` and `byte_strides` correctly. A stride over an axis of extent 1 is never multiplied by a
    non-zero index, so only the others must fit."""
    too_long = [n for n in shape if n > WARP_INDEX_LIMIT]
    too_wide = [s for n, s in zip(shape, byte_strides) if n > 1 and not 0 <= s <= WARP_INDEX_LIMIT]
    if too_long or too_wide:
        size = "x".join(str(n) for n in shape)
        raise WarpAddressingError(
            f"{name} ({size}, byte strides {tuple(byte_strides)}) cannot be handed to a Warp kernel: Warp "
            f"addresses extents and byte strides up to {WARP_INDEX_LIMIT} only; lay it out with the "
            "large axis last or split it"
        )


def to_warp(t: torch.Tensor, name: str = "a tensor", **kwargs) -> wp.array:
    """`wp.from_torch`, starting Warp first: every tensor a kernel sees goes through here, and one Warp
    cannot address is refused (`check_addressable`) instead of handed over to corrupt memory. Warp
    keeps no gradient of it (our kernels have hand-written backwards)."""
    ensure_warp()
    check_addressable(name, tuple(t.shape), tuple(s * t.element_size() for s in t.stride()))
    return wp.from_torch(t, **{"requires_grad": False, **kwargs})


def check_launch_size(name: str, n: int) -> None:
    """Raise unless a launch of `n` threads numbers them in Warp's 32-bit thread index."""
    if n > WARP_INDEX_LIMIT:
        raise WarpAddressingError(
            f"{name}: {n} threads in one launch, past Warp's 32-bit thread index ({WARP_INDEX_LIMIT})"
        )


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


_first_launch = threading.Lock()
_launched: set[tuple] = set()


def launch_kernel(kernel, dim, inputs: list, device: str, **kwargs) -> None:
    """`wp.launch`, with a kernel's first launch on a device (and block size) made under a lock. Warp
    compiles and loads a module at its first launch, and two threads launching it at once each load
    it, one replacing the other under the first's running kernel (JOURNAL.md, "Large
    arrays"): a crash in Warp's debug build, a race in any. On CUDA it launches on torch's current
    stream of `device` unless given another (`torch_stream`); on a CPU with subnormals flushed
    (`flushing_subnormals`)."""
    if device != "cpu":
        kwargs.setdefault("stream", torch_stream(device))
        _launch(kernel, dim, inputs, device, kwargs)
        return
    with flushing_subnormals():
        _launch(kernel, dim, inputs, device, kwargs)


def _launch(kernel, dim, inputs: list, device: str, kwargs: dict) -> None:
    key = (kernel, device, kwargs.get("block_dim"))
    if key in _launched:
        wp.launch(kernel, dim=dim, inputs=inputs, device=device, **kwargs)
        return
    with _first_launch:
        wp.launch(kernel, dim=dim, inputs=inputs, device=device, **kwargs)
        _launched.add(key)


_SMALLEST_NORMAL = np.float32(1.1754944e-38)


@contextlib.contextmanager
def flushing_subnormals():
    """This thread's CPU float arithmetic with subnormals read and written as 0 (x86's FTZ/DAZ, which
    Warp's CPU kernels obey: they run on the launching thread), restored after. Subnormal operands cost
    x86 cores many times a normal one's, and a trained grid holds millions (SH that only the view
    prior's pull moves; JOURNAL.md, "Why that pass is slow here: frozen subnormal SH"); CUDA
    runs them at full speed, and no colour or gradient that small matters. Where torch cannot set the
    mode (not x86), nothing changes."""
    was_on = _SMALLEST_NORMAL * np.float32(0.5) == 0  # the thread's current mode, by its effect
    if not was_on:
        torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if not was_on:
            torch.set_flush_denormal(False)


def launch_parts(
    device: str,
    n: int,
    launch: Callable[[int, int, int], None],
    parts: list[tuple[int, int]] | None = None,
) -> None:
    """`launch(start, stop, part)` over [0, n): on CPU once per part (default: a part per CPU thread,
    for work whose items cost alike), on the CPU's threads (Warp runs a CPU kernel as one sequential
    loop); on CUDA once for all of it, on torch's current stream. That stream does not wait for Warp's
    own first: our work is all on torch's, and a wait on another stream could not be recorded in a CUDA
    graph (`train/step_graph.py`)."""
    check_launch_size("a launch", n)
    if device == "cpu":
        workers = cpu_workers()
        run_parts(split(n, workers) if parts is None else parts, launch, workers)
    else:
        with wp.ScopedStream(torch_stream(device), sync_enter=False):
            launch(0, n, 0)


def launch_split(
    kernel,
    n: int,
    head: list,
    tail: list | Callable[[int], list],
    device: str,
    parts: list[tuple[int, int]] | None = None,
    columns: int | None = None,
) -> None:
    """Launch `kernel` over the items [0, n) in `launch_parts`' parts, a thread per item (per item and
    column with `columns`), its arguments `head`, the part's first item, then `tail`: one list for every
    part, or a function of the part's index where each part has its own (the CPU threads' gradient
    buffers)."""
    tail_for = tail if callable(tail) else (lambda _part: tail)

    def launch(start: int, stop: int, part: int) -> None:
        dim = stop - start if columns is None else (stop - start, columns)
        launch_kernel(kernel, dim=dim, inputs=[*head, start, *tail_for(part)], device=device)

    launch_parts(device, n, launch, parts)


_streams: dict[tuple[int, int], wp.Stream] = {}


def torch_stream(device: torch.device | str | None = None) -> wp.Stream:
    """Warp's handle on torch's current CUDA stream of `device` (default: the current device), made once
    per stream: every kernel runs in order with torch's work on one stream, and no new `wp.Stream` is
    wrapped per launch. Pass the tensors' device: each device's default stream has the same handle."""
    current = torch.cuda.current_stream(None if device is None else torch.device(device))
    key = (current.device_index, current.cuda_stream)
    stream = _streams.get(key)
    if stream is None:
        stream = _streams[key] = wp.stream_from_torch(current)
    return stream


# On a CPU a row is written only when unset: threads marking rows in one cache line would otherwise
# take it from each other on every store. On CUDA it is stored outright: a store does not wait, where
# reading first puts a round trip to memory on the thread's path for every mark (the compiler cannot
# move one mark's read above another's store), and threads storing the same byte need no atomic.
_MARK_TOUCHED = """
    wp::uint8* at = wp::address(touched, row);
#if defined(__CUDA_ARCH__)
    *at = wp::uint8(1);
#else
    if (*at == wp::uint8(0))
        *at = wp::uint8(1);
#endif
"""


@wp.func_native(_MARK_TOUCHED)
def mark_touched(touched: wp.array(dtype=wp.uint8), row: int):
    """Mark a row for the optimiser (`touched[row] = 1`)."""
    ...
