"""Finds what a piece of code reads back from tensors on the host: on a GPU each such read (`.item()`,
`int(t)`, `.tolist()`, a boolean-mask index, `nonzero`, ...) makes the CPU wait for the GPU, and a
`torch.tensor(...)` made in a step is a copy from the host that waits too. On the CPU none of them
waits, so CUDA's `torch.cuda.set_sync_debug_mode` cannot see them there; this records them instead,
for a test to run on any machine.
"""

from __future__ import annotations

import contextlib
import traceback
from collections.abc import Iterator
from dataclasses import dataclass

import torch

READING_METHODS = (
    "item",
    "tolist",
    "__int__",
    "__float__",
    "__bool__",
    "__index__",
    "cpu",
    "numpy",
    "nonzero",
    "unique",
    "masked_select",
)
PACKAGE = "hdrplenoxels"


@dataclass(frozen=True)
class HostRead:
    what: str
    function: str
    where: str  # file:line in the package

    def __str__(self) -> str:
        return f"{self.what} in {self.function} ({self.where})"


def _caller() -> tuple[str, str] | None:
    """The innermost frame of the package's own code on the stack: (function, file:line)."""
    for frame in reversed(traceback.extract_stack()[:-2]):
        if f"/{PACKAGE}/" in frame.filename:
            return frame.name, f"{frame.filename.split(f'/{PACKAGE}/')[-1]}:{frame.lineno}"
    return None


def _has_mask(index) -> bool:
    index = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in index)


@contextlib.contextmanager
def host_reads(exempt: tuple[str, ...] = ()) -> Iterator[list[HostRead]]:
    """Record every host read made by the package's code (not by torch's or a test's own) inside the
    block, except in functions named in `exempt`."""
    found: list[HostRead] = []

    def note(what: str) -> None:
        caller = _caller()
        if caller is not None and caller[0] not in exempt:
            found.append(HostRead(what, *caller))

    def watching(name: str, original):
        def method(*args, **kwargs):
            note(name)
            return original(*args, **kwargs)

        return method

    originals = {name: getattr(torch.Tensor, name) for name in READING_METHODS}
    get, put = torch.Tensor.__getitem__, torch.Tensor.__setitem__
    functions = {"nonzero": torch.nonzero, "unique": torch.unique, "tensor": torch.tensor}

    def getitem(self, index):
        if _has_mask(index):
            note("a boolean-mask index")
        return get(self, index)

    def setitem(self, index, value):
        if _has_mask(index):
            note("a boolean-mask assignment")
        return put(self, index, value)

    try:
        for name, original in originals.items():
            setattr(torch.Tensor, name, watching(name, original))
        torch.Tensor.__getitem__, torch.Tensor.__setitem__ = getitem, setitem
        for name, original in functions.items():
            setattr(torch, name, watching(f"torch.{name}", original))
        yield found
    finally:
        for name, original in originals.items():
            setattr(torch.Tensor, name, original)
        torch.Tensor.__getitem__, torch.Tensor.__setitem__ = get, put
        for name, original in functions.items():
            setattr(torch, name, original)
