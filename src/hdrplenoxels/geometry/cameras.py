"""Pinhole cameras, ray generation (+0.5 pixel centres) and the NDC warp for forward-facing scenes.

Poses are camera-to-world in the OpenCV convention (x right, y down, z forward). Parsers of OpenGL
layouts (nerfstudio, Blender, LLFF) convert with `opengl_to_opencv`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world (…, 4, 4) from OpenGL axes (x right, y up, z back) to OpenCV axes."""
    return c2w @ OPENGL_TO_OPENCV


opencv_to_opengl = opengl_to_opencv  # the same axis flip: it is its own inverse


@dataclass
class Cameras:
    """N pinhole cameras: OpenCV camera-to-world (N,4,4), intrinsics (N,4) fx,fy,cx,cy, sizes (N,2) W,H."""

    c2w: np.ndarray
    intrinsics: np.ndarray
    sizes: np.ndarray

    def __post_init__(self) -> None:
        self.c2w = np.asarray(self.c2w, dtype=np.float64).reshape(-1, 4, 4)
        self.intrinsics = np.asarray(self.intrinsics, dtype=np.float64).reshape(-1, 4)
        self.sizes = np.asarray(self.sizes, dtype=np.int64).reshape(-1, 2)
        n = len(self.c2w)
        if len(self.intrinsics) != n or len(self.sizes) != n:
            raise ValueError("c2w, intrinsics and sizes must describe the same number of cameras")

    def __len__(self) -> int:
        return len(self.c2w)

    def size(self, i: int) -> tuple[int, int]:
        """(W, H) of camera i."""
        w, h = self.sizes[i]
        return int(w), int(h)

    def intrinsics_at(self, i: int, size: tuple[int, int]) -> np.ndarray:
        """Camera i's intrinsics (4,) for an image of `size` (W, H) with the same field of view (a
        thumbnail, a metering render, a video frame)."""
        w, h = self.size(i)
        return self.intrinsics[i] * np.array([size[0] / w, size[1] / h, size[0] / w, size[1] / h])

    def body_ids(self) -> list[int]:
        """Which physical camera took each image, as far as the layouts tell: one id per image size.

        A response curve belongs to a camera body, whose photos share its resolution; intrinsics are no
        key, since zoom and SfM refinement change them between photos of one body (`process` solves a
        camera per photo when sizes differ). Bodies of one resolution share a curve, as with "scene".
        """
        _, inverse = np.unique(self.sizes, axis=0, return_inverse=True)
        return [int(i) for i in np.asarray(inverse).reshape(-1)]


def pixel_rays(
    c2w: torch.Tensor, intrinsics: torch.Tensor, cols: torch.Tensor, rows: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through pixel centres: origins (N,3) and unit directions (N,3).

    `c2w` (N,4,4) / `intrinsics` (N,4) are per ray (gather them by image index first); `cols`, `rows`
    are integer pixel indices. Direction in camera space: ((u + 0.5 - cx)/fx, (v + 0.5 - cy)/fy, 1).
    """
    fx, fy, cx, cy = intrinsics.unbind(-1)
    x = (cols.to(fx.dtype) + 0.5 - cx) / fx
    y = (rows.to(fy.dtype) + 0.5 - cy) / fy
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    d = torch.einsum("nij,nj->ni", c2w[:, :3, :3], d_cam)
    d = d / d.norm(dim=-1, keepdim=True)
    return c2w[:, :3, 3].clone(), d


def pixel_grid(height: int, width: int, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Row and column indices (H*W,) of every pixel, row-major."""
    rows, cols = torch.meshgrid(
        torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij"
    )
    return rows.reshape(-1), cols.reshape(-1)


def image_rays(cameras: Cameras, i: int, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """All rays of camera i, row-major (H*W, 3) each, in float32 on `device`."""
    w, h = cameras.size(i)
    rows, cols = pixel_grid(h, w)
    n = h * w
    c2w = torch.as_tensor(cameras.c2w[i], dtype=torch.float64).expand(n, 4, 4)
    k = torch.as_tensor(cameras.intrinsics[i], dtype=torch.float64).expand(n, 4)
    o, d = pixel_rays(c2w, k, cols, rows)
    return o.float().to(device), d.float().to(device)


@dataclass(frozen=True)
class NDCSpec:
    """NDC warp for forward-facing scenes: per-axis coefficients, near plane (docs/method.md "Rendering")."""

    coeff_x: float  # 2 fx / W
    coeff_y: float  # 2 fy / H
    near: float = 1.0


def to_ndc(origins: torch.Tensor, dirs: torch.Tensor, ndc: NDCSpec) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp world rays (cameras looking along +z) into NDC; returns origins and unit NDC directions.

    Depth z in [near, inf) maps to NDC z in [-1, 1). Rays that do not point forward (d_z <= 1e-6, only
    possible for user-given poses) cannot reach the NDC volume: they become rays starting beyond the far
    plane and pointing away, so every backend renders them as background.
    """
    forward = dirs[:, 2] > 1e-6
    dz = torch.where(forward, dirs[:, 2], torch.ones_like(dirs[:, 2]))
    t = (ndc.near - origins[:, 2]) / dz
    o = origins + t[:, None] * dirs
    ox, oy = o[:, 0], o[:, 1]
    oz = torch.full_like(ox, ndc.near)  # exactly on the near plane
    dx, dy = dirs[:, 0], dirs[:, 1]
    o_ndc = torch.stack([ndc.coeff_x * ox / oz, ndc.coeff_y * oy / oz, 1.0 - 2.0 * ndc.near / oz], dim=-1)
    d_ndc = torch.stack(
        [ndc.coeff_x * (dx / dz - ox / oz), ndc.coeff_y * (dy / dz - oy / oz), 2.0 * ndc.near / oz], dim=-1
    )
    d_ndc = d_ndc / d_ndc.norm(dim=-1, keepdim=True)
    beyond_far = torch.tensor([0.0, 0.0, 2.0], dtype=o_ndc.dtype, device=o_ndc.device)
    away = torch.tensor([0.0, 0.0, 1.0], dtype=d_ndc.dtype, device=d_ndc.device)
    o_ndc = torch.where(forward[:, None], o_ndc, beyond_far)
    d_ndc = torch.where(forward[:, None], d_ndc, away)
    return o_ndc, d_ndc
