"""Records what a piece of code launches, as a CUDA graph would hold it: every torch op and Warp launch in
order, with its scalar arguments and the address of each tensor it reads or writes that was made before
the block (an "outside" tensor). Tensors made inside the block are written "inside": a graph keeps them at
addresses of its own. Two steps whose logs are equal replay correctly from one capture; a difference is
a scalar or an address the capture would have frozen (`train/step_graph.py`).
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator

import torch
import warp as wp
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten


class _Log(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.entries: list[tuple] = []
        self.inside: list[tuple[int, int]] = []  # [start, end) of the storages made in the block

    def where(self, address: int) -> object:
        if any(start <= address < end for start, end in self.inside):
            return "inside"
        return ("outside", address)

    def describe(self, value) -> object:
        if isinstance(value, torch.Tensor):
            return ("tensor", str(value.dtype), tuple(value.shape), self.where(value.data_ptr()))
        if isinstance(value, wp.array):
            return ("array", str(value.dtype), tuple(value.shape), self.where(value.ptr))
        if isinstance(value, (list, tuple)):
            return tuple(self.describe(v) for v in value)
        if isinstance(value, dict):
            return tuple((k, self.describe(v)) for k, v in sorted(value.items()))
        struct = getattr(value, "_cls", None)
        if struct is not None:  # a Warp struct: its fields
            return tuple((name, self.describe(getattr(value, name))) for name in struct.vars)
        if isinstance(value, torch.Generator):  # a new wrapper each call: a graph registers the generator
            return "generator"
        return repr(value)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        self.entries.append((str(func), self.describe(args), self.describe(kwargs)))
        out = func(*args, **kwargs)
        sources = {t.untyped_storage().data_ptr() for t in tree_flatten((args, kwargs))[0] if _is_tensor(t)}
        for t in tree_flatten(out)[0]:
            if _is_tensor(t) and t.untyped_storage().data_ptr() not in sources:  # new memory, not a view
                start = t.untyped_storage().data_ptr()
                self.inside.append((start, start + t.untyped_storage().nbytes()))
        return out


def _is_tensor(t) -> bool:
    return isinstance(t, torch.Tensor) and t.device.type != "meta"


@contextlib.contextmanager
def launch_log() -> Iterator[list[tuple]]:
    """The block's launches: (op, arguments) for each torch op, ("warp", kernel, dim, inputs) for each
    Warp launch."""
    log = _Log()
    launch = wp.launch

    def logged(kernel, dim, inputs=(), *args, **kwargs):
        log.entries.append(("warp", kernel.key, log.describe(dim), log.describe(list(inputs))))
        return launch(kernel, dim, inputs, *args, **kwargs)

    wp.launch = logged
    try:
        with log:
            yield log.entries
    finally:
        wp.launch = launch
        log.entries[:] = in_launch_order(log.entries)


def in_launch_order(entries: list[tuple]) -> list[tuple]:
    """`entries` with each run of one Warp kernel's consecutive launches sorted: on the CPU one launch is
    split into parts that the worker threads take as they come free (`core.parallel.run_parts`), so the
    parts reach the log in an order that depends on the machine's load, not on the code."""
    out: list[tuple] = []
    for kernel, group in itertools.groupby(entries, key=lambda e: e[1] if e[0] == "warp" else None):
        run = list(group)
        out += run if kernel is None else sorted(run, key=repr)
    return out
