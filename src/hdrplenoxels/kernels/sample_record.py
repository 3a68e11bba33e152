"""What a training forward keeps for its backward, so the backward need not read the grid twice.

The backward kernel needs each contributing sample's density and colour. Recomputing them reads the
8 corners' density and SH rows again (108 bytes a row with degree-2 SH), which is most of the
backward's memory traffic besides the gradient adds themselves. The forward kernel writes, per ray,
up to `capacity` contributing samples: the sample's index and (density, r, g, b), 20 bytes. The
backward replays those and marches on, recomputing, only for a ray with more contributing samples
than that. Results are identical either way (`tests/test_render_acceleration.py`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

# Contributing samples kept per ray (20 bytes each); past it the backward re-marches the ray. The sample
# counts it was chosen on: JOURNAL.md, "Constants justified by timings".
RECORD_CAPACITY = 192


@dataclass
class SampleRecord:
    index: torch.Tensor  # (rays, capacity) int32: the sample's index along its ray
    values: torch.Tensor  # (rays, capacity, 4) float32: density, then the colour's r, g, b
    count: torch.Tensor  # (rays,) int32: how many of a ray's slots the forward filled

    @classmethod
    def empty(cls, rays: int, device: torch.device | str, capacity: int = RECORD_CAPACITY) -> SampleRecord:
        if capacity < 1:
            raise ValueError(f"a sample record needs a capacity of at least 1, not {capacity}")
        return cls(
            index=torch.empty((rays, capacity), dtype=torch.int32, device=device),
            values=torch.empty((rays, capacity, 4), dtype=torch.float32, device=device),
            count=torch.zeros(rays, dtype=torch.int32, device=device),
        )

    @property
    def rays(self) -> int:
        return self.count.shape[0]

    @property
    def capacity(self) -> int:
        return self.index.shape[1]
