"""The multi-sphere background (MSI) of Plenoxels: what the cameras see beyond the grid's box.

`L` concentric spheres around the box's centre, spaced uniformly in inverse radius from the box's outer
sphere (radius `r0`, half the box diagonal) towards infinity, each an equirectangular map (H rows of
polar angle from +z, W columns of azimuth) of raw density and raw linear RGB. The geometry, sampling
and activations are in docs/method.md, "Background"; the layout in docs/design.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from hdrplenoxels.grid.sparse_grid import SparseGrid, Vec3

MIN_LAYERS = 2  # interpolation in inverse radius needs two layers
MIN_HEIGHT = 2
MIN_WIDTH = 2


@dataclass
class MSIBackground:
    """Density (L, H, W) and colour (L, H, W, 3) of the layers; layer 0 is the outer sphere of the box."""

    density: torch.Tensor  # (L, H, W) float32, raw: ReLU'd after interpolation
    color: torch.Tensor  # (L, H, W, 3) float32, raw linear radiance: ReLU'd after interpolation
    center: Vec3  # world units: the box's centre
    radius: float  # r0, world units: the radius of layer 0 (the box's outer sphere)
    samples_per_layer: int = 2  # samples per layer spacing along a ray

    def __post_init__(self) -> None:
        if self.density.dim() != 3:
            raise ValueError(f"MSI density must be (layers, height, width), got {tuple(self.density.shape)}")
        layers, height, width = self.density.shape
        if layers < MIN_LAYERS or height < MIN_HEIGHT or width < MIN_WIDTH:
            raise ValueError(
                f"an MSI needs >= {MIN_LAYERS} layers and maps of >= {MIN_HEIGHT} x {MIN_WIDTH}, "
                f"got {layers} layers of {height} x {width}"
            )
        if tuple(self.color.shape) != (layers, height, width, 3):
            raise ValueError(
                f"MSI colour must be {(layers, height, width, 3)}, got {tuple(self.color.shape)}"
            )
        if not self.radius > 0.0 or self.samples_per_layer < 1:
            raise ValueError(
                f"MSI radius must be > 0 and samples_per_layer >= 1, "
                f"got {self.radius} and {self.samples_per_layer}"
            )

    @classmethod
    def create(
        cls,
        grid: SparseGrid,
        layers: int,
        height: int,
        width: int,
        density: float = 0.0,
        color: float = 0.5,
        samples_per_layer: int = 2,
    ) -> MSIBackground:
        """A constant MSI around `grid`'s (outermost) box, on the grid's device, of the size asked for
        (a run's sizes are `BackgroundConfig`'s). Density 0 leaves it transparent (the constant
        background shows through) until training makes it opaque."""
        device = grid.device
        r0 = math.sqrt(sum(float(r) ** 2 for r in grid.outer_radius))
        return cls(
            density=torch.full((layers, height, width), float(density), device=device),
            color=torch.full((layers, height, width, 3), float(color), device=device),
            center=tuple(float(c) for c in grid.center),  # type: ignore[arg-type]
            radius=r0,
            samples_per_layer=samples_per_layer,
        )

    @property
    def layers(self) -> int:
        return int(self.density.shape[0])

    @property
    def height(self) -> int:
        return int(self.density.shape[1])

    @property
    def width(self) -> int:
        return int(self.density.shape[2])

    @property
    def num_samples(self) -> int:
        """Samples per ray: `samples_per_layer` per layer spacing, L - 1 spacings."""
        return self.samples_per_layer * (self.layers - 1)

    @property
    def device(self) -> torch.device:
        return self.density.device

    def to(self, device: torch.device | str) -> MSIBackground:
        return MSIBackground(
            self.density.to(device), self.color.to(device), self.center, self.radius, self.samples_per_layer
        )
