"""The device the fast (Warp) path is tested on: CUDA when present, else the CPU.

The PyTorch reference always runs on the CPU, so on a GPU machine every parity test compares the CUDA
kernels with the CPU oracle. `HDRPLENOXELS_TEST_DEVICE=cpu` forces the CPU path there too.
"""

from __future__ import annotations

import os

import torch

FAST_DEVICE = torch.device(
    os.environ.get("HDRPLENOXELS_TEST_DEVICE") or ("cuda" if torch.cuda.is_available() else "cpu")
)


def on_fast(*tensors: torch.Tensor) -> list[torch.Tensor]:
    return [t.to(FAST_DEVICE) for t in tensors]
