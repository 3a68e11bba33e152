"""One place that says whether an operation runs as its Warp kernel or as its PyTorch reference.

The kernels that replace runs of small PyTorch operators (the tone mapper's loss, the ray draw, the tone
parameters' RMSProp, the MSI's dense TV) run on CUDA, where each operator they replace is a kernel launch
and a node of a replayed step. On a CPU PyTorch's vectorised operators on every core are as fast or faster
than Warp's one thread (JOURNAL.md, "Fused kernels"), so the references run there, unless a test or a
benchmark asks for CUDA's path on the CPU (`kernels_on_cpu`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

KERNELS_ON_CPU = False
"""Whether tensors on a CPU take the kernels too: CUDA's path, for tests and benchmarks."""


def use_kernel(t: torch.Tensor) -> bool:
    """Whether an operation on `t` runs its kernel (on CUDA, or on a CPU with `KERNELS_ON_CPU`) rather
    than its reference."""
    return t.is_cuda or KERNELS_ON_CPU


@contextmanager
def kernels_on_cpu(on: bool = True) -> Iterator[None]:
    """Within the block, CPU tensors take the kernels (`on`) or the references; restored after."""
    global KERNELS_ON_CPU
    before, KERNELS_ON_CPU = KERNELS_ON_CPU, on
    try:
        yield
    finally:
        KERNELS_ON_CPU = before
