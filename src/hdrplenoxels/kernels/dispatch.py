"""One place that says whether an operation runs as its Warp kernel or as its PyTorch reference: by the
backend a caller names (`kernels_for`), or, for the operations below, by the tensor's device (`use_kernel`).

The kernels that replace runs of small PyTorch operators (the tone mapper's loss, the ray draw, the tone
parameters' RMSProp, the MSI's dense TV) run on CUDA, where each operator they replace is a kernel launch
and a node of a replayed step. On a CPU PyTorch's vectorised operators on every core are as fast or faster
than Warp's one thread (JOURNAL.md, "Fused kernels"), so the references run there, unless a test or a
benchmark asks for CUDA's path on the CPU (`kernels_on_cpu`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Literal

import torch

Backend = Literal["warp", "torch"]
"""How a caller that names its path chooses: "warp", the kernels (CPU and CUDA alike: the march, TV and
the grid's RMSProp are the fast path on both), or "torch", the references (`render_rays(backend=)`,
`TrainConfig.backend`)."""
BACKENDS: tuple[str, ...] = ("warp", "torch")


def kernels_for(backend: str) -> bool:
    """Whether `backend` takes the kernels ("warp") or the references ("torch"); another name is refused."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    return backend == "warp"


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
