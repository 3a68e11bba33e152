"""`warp_runtime.mark_touched`, the one mark every kernel sets on a row (the optimiser's touched rows, the
rows a forward reads): one native snippet, checking first on a CPU and storing outright on CUDA."""

from __future__ import annotations

from pathlib import Path

import torch
import warp as wp
from devices import FAST_DEVICE

from hdrplenoxels.core.warp_runtime import (
    KERNEL,
    ensure_warp,
    launch_kernel,
    mark_touched,
    to_warp,
    warp_device,
)


@KERNEL
def _mark(touched: wp.array(dtype=wp.uint8), rows: wp.array(dtype=wp.int32)):
    mark_touched(touched, rows[wp.tid()])


def test_marks_set_the_rows_and_only_them_in_a_strided_view():
    """On the fast device (CUDA's side where there is one), rows marked twice and in one launch."""
    storage = torch.zeros(40, dtype=torch.uint8, device=FAST_DEVICE)
    storage[1::2] = 7  # between the view's bytes: never written
    rows = torch.tensor([1, 3, 3, 7, 19], dtype=torch.int32, device=FAST_DEVICE)
    marks = to_warp(storage[::2], "marks")
    launch_kernel(_mark, dim=5, inputs=[marks, to_warp(rows, "rows")], device=warp_device(storage))
    want = torch.zeros(20, dtype=torch.uint8, device=FAST_DEVICE)
    want[[1, 3, 7, 19]] = 1
    assert torch.equal(storage[::2], want) and (storage[1::2] == 7).all()


def test_the_cuda_branch_compiles_for_sm_90(tmp_path):
    """The snippet's CUDA side, which no CPU run executes, builds (Warp's NVRTC, no GPU needed)."""
    ensure_warp()
    (binary,) = wp.compile_aot_module(_mark.module, arch=90, module_dir=tmp_path, use_ptx=False)
    assert Path(binary).read_bytes()[:4] == b"\x7fELF"  # a CUDA binary
