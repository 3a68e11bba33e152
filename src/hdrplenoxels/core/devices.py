"""Which torch device a run uses: checked up front, so a missing GPU is one clear error."""

from __future__ import annotations

import torch

from hdrplenoxels.core.errors import InputError


def pick_device(name: str) -> torch.device:
    """`auto`: CUDA when torch sees a GPU, else the CPU; otherwise the named device, which must exist
    (asking for a missing GPU is an `InputError`, not torch's traceback deep inside the first kernel)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise InputError(None, f"--device {name}: not a device (use auto, cpu, cuda or cuda:N)") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise InputError(None, f"--device {name}: the Warp kernels run on cpu or cuda only")
    if not torch.cuda.is_available():
        why = "this torch is a CPU-only build" if torch.version.cuda is None else "torch sees no GPU"
        raise InputError(None, f"--device {name}: no CUDA device ({why}); use --device cpu or auto")
    if device.index is not None and device.index >= torch.cuda.device_count():
        count = torch.cuda.device_count()
        raise InputError(None, f"--device {name}: torch sees {count} GPU(s), numbered from 0")
    return device
