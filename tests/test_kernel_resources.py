"""benchmarks/kernel_resources.py: a kernel's registers and local memory read from its CUDA binary
(compiled for sm_90 by Warp's NVRTC, no GPU needed), and the residency they allow."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, ensure_warp

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "kernel_resources.py"
vec16 = wp.types.vector(length=16, dtype=wp.float32)


def _bench():
    spec = importlib.util.spec_from_file_location("kernel_resources", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@KERNEL
def _copy(a: wp.array(dtype=wp.float32), b: wp.array(dtype=wp.float32)):
    i = wp.tid()
    b[i] = a[i] * 2.0


@KERNEL
def _indexed(a: wp.array(dtype=wp.float32), k: wp.array(dtype=wp.int32), b: wp.array(dtype=wp.float32)):
    i = wp.tid()
    v = vec16()
    for j in range(16):
        v[j] = a[i * 16 + j]
    b[i] = v[k[i]]  # a run-time index: the vector lives in local memory


def test_registers_and_local_memory_are_read_from_the_binary(tmp_path):
    ensure_warp()
    bench = _bench()
    registers, frame = bench.compiled_resources(_copy, 90, tmp_path)
    assert 1 <= registers <= 32 and frame == 0
    registers, frame = bench.compiled_resources(_indexed, 90, tmp_path)
    assert 1 <= registers <= 255 and frame >= 16 * 4  # the 16 floats, in the thread's frame
    with pytest.raises(ValueError, match="ELF"):
        bench.cubin_resources(b"not a binary")


def test_residency_follows_registers_blocks_and_the_architecture():
    bench = _bench()
    assert bench.resident_warps(255, 32, 90) == 8  # 12.5 % of 64: the figure of the first GPU profile
    assert bench.resident_warps(128, 32, 90) == 16
    assert bench.resident_warps(32, 32, 90) == 32  # one-warp blocks: at most 32 blocks
    assert bench.resident_warps(32, 256, 90) == 64
    assert bench.resident_warps(168, 256, 90) == 8  # a 256-thread block needs 8 warps' registers at once
    assert bench.resident_warps(32, 256, 86) == 48


def test_the_touched_update_keeps_a_row_out_of_registers_through_the_density(tmp_path):
    """The update of the touched rows with no pull (what a CPU run and a GPU run past the view prior
    take) stays well under the 128 registers on sm_90 it took when the SH row was read before the owed
    decay's loop rather than after it, which made the compiler hold the row through the density's update
    (benchmarks/RESULTS.md, "The optimiser's and the owed pull's kernels, again")."""
    from hdrplenoxels.kernels.rmsprop_kernel import _touched_kernel

    ensure_warp()
    registers, frame = _bench().compiled_resources(_touched_kernel(27, 1), 90, tmp_path)
    assert registers <= 100 and frame == 0
