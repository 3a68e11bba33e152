"""Sparse voxel grid: a dense int32 index grid (`links`) into compact density and SH arrays, in one box
or in a cascade of nested boxes.

Conventions follow svox2 (docs/method.md, "Grid"): voxel values live at integer grid coordinates, the box
`[center - radius, center + radius]` maps to `[-1/2, R - 1/2]` per axis, `links < 0` means empty, and SH
coefficients are stored channel-major (column `basis_dim * c + j`).

A cascade (docs/method.md, "Cascade") has `levels` boxes around the same centre, level `l` of half-size
`radius * 2^l` at the same resolution, as instant-ngp's: `links` is (levels, Rx, Ry, Rz), all levels index
one density and SH array, and a point belongs to the finest level whose box holds it. The voxels of a level
deep inside the next finer box are never read, so they are never allocated.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from hdrplenoxels.data.placement import MAX_LEVELS, SceneGeometry
from hdrplenoxels.geometry.sh import VALID_BASIS_DIMS

Vec3 = tuple[float, float, float]

CORNER_OFFSETS = torch.tensor(
    [[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.long
)  # (8, 3); corner bit order x, y, z as in svox2


@dataclass
class SparseGrid:
    """Density and SH at allocated voxels; `links[l, x, y, z]` is the row of that voxel of level `l` or -1."""

    links: torch.Tensor  # (levels, Rx, Ry, Rz) int32
    density: torch.Tensor  # (M,) float32
    sh: torch.Tensor  # (M, 3 * basis_dim) float32
    center: Vec3
    radius: Vec3  # level 0's half-sides; level l's are radius * 2^l

    def __post_init__(self) -> None:
        if self.links.dim() == 3:  # one box: a cascade of one level
            self.links = self.links[None]
        if self.links.dim() != 4 or min(self.links.shape[1:]) < 2:
            raise ValueError(
                f"links must be (levels, Rx, Ry, Rz) with at least 2 per axis, got {tuple(self.links.shape)}"
            )
        if not 1 <= self.links.shape[0] <= MAX_LEVELS:
            raise ValueError(f"a grid has 1 to {MAX_LEVELS} levels, got {self.links.shape[0]}")
        if self.sh.shape[1] % 3 or self.sh.shape[1] // 3 not in VALID_BASIS_DIMS:
            raise ValueError(f"sh must have 3 x (1, 4 or 9) columns, got {self.sh.shape[1]}")
        if self.density.shape[0] != self.sh.shape[0]:
            raise ValueError("density and sh must have the same number of rows")

    # ----------------------------------------------------------------------------- geometry
    @property
    def reso(self) -> tuple[int, int, int]:
        """Voxels per axis of every level."""
        return tuple(int(r) for r in self.links.shape[1:])  # type: ignore[return-value]

    @property
    def levels(self) -> int:
        return int(self.links.shape[0])

    @property
    def basis_dim(self) -> int:
        return self.sh.shape[1] // 3

    @property
    def num_voxels(self) -> int:
        return int(self.density.shape[0])

    @property
    def device(self) -> torch.device:
        return self.density.device

    def level_radius(self, level: int) -> Vec3:
        """Half-sides of level `level`'s box."""
        return tuple(float(r) * 2.0**level for r in self.radius)  # type: ignore[return-value]

    @property
    def outer_radius(self) -> Vec3:
        """Half-sides of the outermost box: what the grid covers (an MSI starts at its outer sphere)."""
        return self.level_radius(self.levels - 1)

    def to(self, device: torch.device | str) -> SparseGrid:
        """The same grid on `device` (sharing the tensors that are there already)."""
        return SparseGrid(
            self.links.to(device), self.density.to(device), self.sh.to(device), self.center, self.radius
        )

    def world_to_grid_affine(self, device=None, level: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """(scale, offset) with level `level`'s grid = world * scale + offset (float32 tensors on
        `device`, by default the grid's)."""
        scale, offset = self.world_to_grid_affine_of(self.reso, self.center, self.level_radius(level))
        device = self.device if device is None else device
        return scale.to(device), offset.to(device)

    @staticmethod
    def world_to_grid_affine_of(reso, center, radius) -> tuple[torch.Tensor, torch.Tensor]:
        """`world_to_grid_affine` of a box of `reso` voxels, `center` and `radius`, on the CPU (where
        kernels take them from, so that reading them never waits for a GPU)."""
        reso = torch.tensor(reso, dtype=torch.float64)
        center = torch.tensor(center, dtype=torch.float64)
        radius = torch.tensor(radius, dtype=torch.float64)
        scale = reso / (2.0 * radius)
        offset = (0.5 - center / (2.0 * radius)) * reso - 0.5
        return scale.float(), offset.float()

    def world_to_grid(self, points: torch.Tensor, level: int = 0) -> torch.Tensor:
        scale, offset = self.world_to_grid_affine(level=level)
        return points * scale + offset

    def grid_to_world(self, coords: torch.Tensor, level: int | torch.Tensor = 0) -> torch.Tensor:
        """World positions of grid coordinates `coords` (…, 3) of `level` (an int, or (…,) per point)."""
        return self.grid_to_world_of(self.reso, self.center, self.radius, coords, level)

    @staticmethod
    def grid_to_world_of(
        reso, center, radius, coords: torch.Tensor, level: int | torch.Tensor = 0
    ) -> torch.Tensor:
        """`grid_to_world` of a grid of `reso` voxels in the boxes of `center` and `radius` (level 0's):
        where a resample's new voxels will sit."""
        scale, offset = (
            t.to(coords.device) for t in SparseGrid.world_to_grid_affine_of(reso, center, radius)
        )
        # Level l's coordinates relative to the box centre are 2^-l times level 0's.
        mid = (torch.tensor(reso, dtype=coords.dtype, device=coords.device) - 1.0) / 2.0
        factor = torch.as_tensor(2.0, dtype=coords.dtype, device=coords.device) ** torch.as_tensor(
            level, device=coords.device
        )
        if factor.dim():
            factor = factor[..., None]
        return ((coords - mid) * factor + mid - offset) / scale

    # ----------------------------------------------------------------------------- construction
    @classmethod
    def create(
        cls,
        reso: tuple[int, int, int],
        center: Vec3 = (0.0, 0.0, 0.0),
        radius: Vec3 = (1.0, 1.0, 1.0),
        basis_dim: int = 9,
        init_sigma: float = 0.1,
        device: torch.device | str = "cpu",
        levels: int = 1,
    ) -> SparseGrid:
        """A grid of `levels` boxes with every voxel a ray can read allocated, density `init_sigma` and
        zero SH (grey 0.5 everywhere)."""
        keep = torch.ones((levels, *reso), dtype=torch.bool, device=device)
        keep[1:] &= ~shadowed_voxels(reso, device)
        links = torch.full((levels, *reso), -1, dtype=torch.int32, device=device)
        n = int(keep.sum())
        links[keep] = torch.arange(n, dtype=torch.int32, device=device)
        density = torch.full((n,), float(init_sigma), dtype=torch.float32, device=device)
        sh = torch.zeros((n, 3 * basis_dim), dtype=torch.float32, device=device)
        return cls(links, density, sh, tuple(map(float, center)), tuple(map(float, radius)))

    @classmethod
    def from_dense(
        cls,
        density: torch.Tensor,
        sh: torch.Tensor,
        center: Vec3,
        radius: Vec3,
        keep: torch.Tensor | None = None,
    ) -> SparseGrid:
        """Build from dense density (Rx,Ry,Rz) and SH (Rx,Ry,Rz,C), or with a leading levels axis for a
        cascade, keeping voxels where `keep` is true."""
        if keep is None:
            keep = torch.ones(density.shape, dtype=torch.bool, device=density.device)
        links = torch.full(density.shape, -1, dtype=torch.int32, device=density.device)
        n_keep = int(keep.sum())
        links[keep] = torch.arange(n_keep, dtype=torch.int32, device=density.device)
        return cls(
            links,
            density[keep].float().contiguous(),
            sh[keep].float().contiguous(),
            tuple(map(float, center)),
            tuple(map(float, radius)),
        )

    def to_dense(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Dense density (levels,Rx,Ry,Rz) and SH (levels,Rx,Ry,Rz,C), zero where empty (for tests and
        export)."""
        mask = self.links >= 0
        shape = tuple(self.links.shape)
        density = torch.zeros(shape, dtype=self.density.dtype, device=self.device)
        sh = torch.zeros((*shape, self.sh.shape[1]), dtype=self.sh.dtype, device=self.device)
        rows = self.links[mask].long()
        density[mask] = self.density.detach()[rows]
        sh[mask] = self.sh.detach()[rows]
        return density, sh

    # ----------------------------------------------------------------------------- resampling
    def prune(self, keep_voxel: torch.Tensor) -> SparseGrid:
        """Drop rows where `keep_voxel` (M,) is false and renumber the links."""
        with torch.no_grad():
            new_row = torch.cumsum(keep_voxel.long(), 0) - 1
            links = self.links.clone()
            occupied = links >= 0
            rows = links[occupied].long()
            links[occupied] = torch.where(keep_voxel[rows], new_row[rows], -1).int()
            return SparseGrid(
                links,
                self.density.detach()[keep_voxel].clone(),
                self.sh.detach()[keep_voxel].clone(),
                self.center,
                self.radius,
            )


def kept_voxels(score: torch.Tensor, thresh: float, dilate: int, max_voxels: int) -> torch.Tensor:
    """(levels, Rx, Ry, Rz) bool: the voxels a resample keeps, at most `max_voxels` of them in all.

    Voxels scoring at least `thresh` are kept with `dilate` voxels around them, less those no ray reads
    (`shadowed_voxels`). The cap bounds that final count, which is what memory pays for: dilation alone
    multiplies a thin surface's voxels several times, so a cap on the voxels that pass before it does
    not bound the grid. Past the cap the threshold rises to the cut whose dilated set fits, found at once
    from the max-filtered score (a voxel is kept at cut `c` exactly when its neighbourhood's best score is
    at least `c`).
    """
    shadowed = shadowed_voxels(tuple(score.shape[1:]), score.device)
    keep = dilate_mask(score >= thresh, dilate)
    keep[1:] &= ~shadowed
    if int(keep.sum()) <= max_voxels:
        return keep
    best = dilate_mask(score, dilate)
    best[1:].masked_fill_(shadowed, -torch.inf)
    ranked = best[keep]
    cut = torch.kthvalue(ranked, ranked.numel() - max_voxels + 1).values  # the max_voxels-th largest
    keep = best >= cut
    if int(keep.sum()) > max_voxels:  # ties at the cut (a neighbourhood shares its best score)
        keep = best > cut
    return keep


def shadowed_voxels(reso: tuple[int, int, int], device=None) -> torch.Tensor:
    """(Rx, Ry, Rz) bool: the voxels of a level > 0 that no sample reads, being deep inside the next
    finer box (the middle half of each axis), which that level renders.

    A level-l sample lies outside the finer box on some axis a, i.e. beyond `m_a -+ R_a / 4` (m the
    centre coordinate), and reads voxels `floor(p_a)` and `floor(p_a) + 1` there; one more voxel of
    margin covers rounding at the boundary."""
    masks = []
    for r in reso:
        mid, quarter = (r - 1) / 2.0, r / 4.0
        lo, hi = int(np.floor(mid - quarter)) + 2, int(np.floor(mid + quarter)) - 1
        i = torch.arange(r, device=device)
        masks.append((i > lo) & (i < hi))
    return masks[0][:, None, None] & masks[1][None, :, None] & masks[2][None, None, :]


def resample_axes(old: tuple[int, int, int], new: tuple[int, int, int], device) -> list[torch.Tensor]:
    """Per axis, the old-grid coordinate (R'_a,) of each new voxel centre (cell-centre alignment)."""
    return [
        (torch.arange(n, dtype=torch.float32, device=device) + 0.5) * (o / n) - 0.5 for o, n in zip(old, new)
    ]


def resampled_density(links: torch.Tensor, density: torch.Tensor, reso: tuple[int, int, int]) -> torch.Tensor:
    """The density trilinearly sampled at every voxel centre of resolution `reso` (R'x, R'y, R'z).

    torch's trilinear interpolation of the level made dense (empty voxels 0): its cell-centre alignment
    (`align_corners=False`) puts new voxel i at old coordinate `(i + 0.5) * R / R' - 0.5`, as
    `resample_axes` does, and its clamping at the edges is `corner_weights`'. (Gathering the 8 corners
    of every new voxel is the slow way of the same: JOURNAL.md, "Constants justified by
    timings".)
    """
    dense = torch.zeros(links.shape, dtype=density.dtype, device=density.device)
    present = links >= 0
    dense[present] = density.detach().reshape(-1)[links[present].long()]
    return F.interpolate(dense[None, None], size=tuple(reso), mode="trilinear", align_corners=False)[0, 0]


@functools.cache
def _corner_constants(reso: tuple[int, int, int], device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """A level's resolution and `CORNER_OFFSETS` (8, 3) on `device`, copied there once: a copy to a
    GPU at every call would make the host wait for it. Kept for good (a few bytes per resolution): a
    recorded CUDA graph reads them at their addresses (`train/step_graph.py`)."""
    return torch.tensor(reso, device=device), CORNER_OFFSETS.to(device)


def corner_weights(
    links: torch.Tensor, pos: torch.Tensor, level: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows (…, 8) of the 8 trilinear corners of grid points `pos` (…, 3) and their weights (…, 8).

    `links` is one level's (Rx, Ry, Rz), or a cascade's (levels, Rx, Ry, Rz) with each point's `level`
    (…,) in it (None: level 0). Positions are clamped to `[0, R-1]`, the base corner is
    `min(floor(p), R-2)`; empty corners get row -1 (their value counts as 0).
    """
    if links.dim() == 3:
        links = links[None]
    reso, offs = _corner_constants(tuple(links.shape[1:]), pos.device)
    p = torch.minimum(pos.clamp(min=0.0), (reso - 1).to(pos.dtype))
    base = torch.minimum(torch.floor(p).long(), reso - 2)
    frac = p - base.to(p.dtype)
    # One flat index per corner (the base's plus the corner's fixed offset), not a gather through four
    # index tensors, the slower way (JOURNAL.md, "Constants justified by timings").
    _, ry, rz = links.shape[1:]
    flat_base = (base[..., 0] * ry + base[..., 1]) * rz + base[..., 2]
    if level is not None:
        flat_base = flat_base + level * (links.shape[1] * ry * rz)
    flat_offs = (offs[:, 0] * ry + offs[:, 1]) * rz + offs[:, 2]
    rows = links.reshape(-1)[flat_base[..., None] + flat_offs].long()
    w_axis = torch.where(offs.bool(), frac[..., None, :], 1.0 - frac[..., None, :])  # (…, 8, 3)
    return rows, w_axis.prod(-1)


def dilate_mask(mask: torch.Tensor, times: int) -> torch.Tensor:
    """Dilation of a (…, X, Y, Z) bool mask with a 3x3x3 (26-neighbour) structuring element, `times`
    times, over the last three axes only (levels never mix); of scores, the same max filter, so that
    `dilate_mask(score, n) >= c` is `dilate_mask(score >= c, n)` for every cut `c`.

    The cube is separable: each pass takes every voxel's maximum with its two neighbours along one axis
    (a 3-D max filter is the slow way of the same; JOURNAL.md, "Constants justified by timings").
    """
    if times == 0:
        return mask.clone()
    m = mask
    for axis in (-3, -2, -1):
        n = m.shape[axis]
        for _ in range(times):
            grown = m.clone()
            ahead, behind = grown.narrow(axis, 1, n - 1), grown.narrow(axis, 0, n - 1)
            torch.maximum(ahead, m.narrow(axis, 0, n - 1), out=ahead)
            torch.maximum(behind, m.narrow(axis, 1, n - 1), out=behind)
            m = grown
    return m


def grid_in_data_frame(grid: SparseGrid, geometry: SceneGeometry) -> SparseGrid:
    """A bounding-box grid moved back to the dataset's frame (for exports): the box scaled and
    shifted back, density per unit length scaled by the same factor, so every render is unchanged."""
    if geometry.mode != "bbox":
        raise ValueError("only a bounding-box grid lives in the dataset's frame (NDC grids do not)")
    scale = geometry.scale()
    shift = geometry.world_from_data[:3, 3]
    center = tuple(float(v) for v in (np.asarray(grid.center) - shift) / scale)
    radius = tuple(float(r / scale) for r in grid.radius)
    return SparseGrid(grid.links, grid.density * scale, grid.sh, center, radius)
