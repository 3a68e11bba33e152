"""A built-in scene rendered from a known procedural grid, for the demo and the tests.

Two soft-edged objects (a sphere and a box) with smooth colour gradients and mild view dependence
sit in the box [-1, 1]^3; cameras on a sphere look at the origin. Because the images come from our own
renderer, a model can in principle reproduce them exactly, which makes PSNR targets meaningful.

The unbounded variant (`ProceduralSceneSpec.unbounded`) adds a known MSI background beyond the box
(`make_sky`: an opaque shell with a sky-like gradient, walls and a sun) and says so in its
transforms.json (`aabb_scale` 4), so that the placement models what lies beyond the box (docs/method.md,
"Background"). The walled variant (`ProceduralSceneSpec.walls`, `TINY_WALLED`) is a real indoor capture's
shape: the cameras stand inside a room whose textured walls are a unit behind them, the truth a cascade of
three boxes (docs/method.md, "Cascade").
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.core.atomic import atomic_write_text
from hdrplenoxels.data.image_io import write_png
from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.geometry.cameras import Cameras, opengl_to_opencv
from hdrplenoxels.geometry.rigs import orbit_rig
from hdrplenoxels.geometry.sh import SH_C0
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.kernels.occupancy_kernel import voxel_coords
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.train.model import Model


@dataclass(frozen=True)
class ProceduralSceneSpec:
    """A procedural scene: its true grid, its cameras and what surrounds it."""

    grid_reso: int = 48
    """Voxels per side of the true grid in the box [-1, 1]^3."""
    num_views: int = 40
    """Cameras on the sphere (every 8th a test view)."""
    width: int = 64
    """Image width in pixels."""
    height: int = 64
    """Image height in pixels."""
    fov_deg: float = 45.0
    """Horizontal field of view."""
    camera_distance: float = 3.0
    """Cameras' distance from the origin, which they look at."""
    background_brightness: float = 0.5
    """Brightness seen where rays leave the scene (without `unbounded`)."""
    seed: int = 0
    """Seed of the grid's blobs and colours."""
    unbounded: bool = False
    """A known MSI surround beyond the box (`make_sky`)."""
    walls: bool = False
    """A room around the cameras (`make_room`): the truth is a cascade of 3 boxes."""


# The tiny unbounded scene of the tests and benchmarks/studies/background/background_training.py: 16 views
# (test views 0 and 8) from 2.4 units with a 90-degree field of view, so that a third of every image sees
# past the box.
TINY_UNBOUNDED = ProceduralSceneSpec(
    grid_reso=16, num_views=16, width=32, height=32, fov_deg=90.0, camera_distance=2.4, unbounded=True
)


# The tiny walled scene of the tests: 16 views from 2 units, inside walls 3 units from the centre.
TINY_WALLED = ProceduralSceneSpec(
    grid_reso=16, num_views=16, width=32, height=32, fov_deg=80.0, camera_distance=2.0, walls=True
)
ROOM_HALF = 3.0  # the walls' inner faces, world units from the centre
ROOM_LEVELS = 3  # the truth's cascade: level 2 reaches 4 units, past the walls


def make_grid(reso: int) -> SparseGrid:
    """The ground-truth grid: density up to 60 inside the objects, degree-1 SH colours."""
    lin = (torch.arange(reso, dtype=torch.float32) + 0.5) / reso * 2 - 1  # voxel centres in [-1, 1]
    x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
    density, sh = _objects(x, y, z)
    keep = density > 0.05
    return SparseGrid.from_dense(density, sh.reshape(reso, reso, reso, 12), (0, 0, 0), (1, 1, 1), keep)


def make_room(reso: int) -> SparseGrid:
    """The walled variant's truth: the objects, and a closed room of textured walls (a checker of two
    shades per wall, brightening towards a window-like patch) `ROOM_HALF` from the centre, in a cascade
    of `ROOM_LEVELS` boxes at `reso` voxels per axis each."""
    grid = SparseGrid.create((reso,) * 3, basis_dim=4, levels=ROOM_LEVELS)
    coords = voxel_coords(grid.links, grid.num_voxels)
    p = grid.grid_to_world(coords[:, 1:].float(), coords[:, 0].long())
    x, y, z = p.unbind(-1)
    density, sh = _objects(x, y, z)
    inf_norm = p.abs().amax(-1)
    wall = (inf_norm > ROOM_HALF) & (inf_norm < ROOM_HALF + 0.6)
    axis = p.abs().argmax(-1)
    u = torch.where(axis == 0, z, x)
    v = torch.where(axis == 1, z, y)
    check = ((torch.floor(u * 2.0) + torch.floor(v * 2.0)) % 2).float()
    tint = torch.stack([0.35 + 0.15 * (axis == 0), 0.4 + 0.15 * (axis == 1), 0.45 + 0.15 * (axis == 2)], -1)
    glow = torch.exp(-((u - 1.0) ** 2 + (v - 0.5) ** 2) / 0.5)[:, None]
    colour = (tint * (0.7 + 0.6 * check[:, None]) + 0.5 * glow).clamp(0.05, 0.95)
    wall_sh = torch.zeros_like(sh)
    wall_sh[..., 0] = (colour - 0.5) / SH_C0
    grid.density = torch.where(wall, torch.full_like(density, 60.0), density)
    # Away from the objects every voxel has the walls' colour, so that a sample at a wall's face blends
    # no other colour into it.
    grid.sh = torch.where((inf_norm > 1.5)[:, None, None], wall_sh, sh).reshape(-1, 12)
    return grid


def _objects(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Density and degree-1 SH (…, 3, 4) of the sphere and the box at points (x, y, z)."""
    sphere = torch.sqrt((x + 0.3) ** 2 + (y - 0.05) ** 2 + z**2) - 0.45
    q = torch.stack([(x - 0.4).abs() - 0.28, (y + 0.15).abs() - 0.32, (z + 0.1).abs() - 0.25])
    box = q.clamp(min=0).norm(dim=0) + q.amax(dim=0).clamp(max=0)
    sdf = torch.minimum(sphere, box)
    density = 60.0 * torch.sigmoid(-sdf / 0.04)
    colour = torch.where(
        (sphere < box)[..., None],
        torch.stack([0.85 - 0.3 * y, 0.35 + 0.25 * x, 0.25 + 0.2 * z], dim=-1),
        torch.stack([0.2 + 0.2 * z, 0.55 + 0.25 * y, 0.8 - 0.2 * x], dim=-1),
    ).clamp(0.05, 0.95)
    sh = torch.zeros((*x.shape, 3, 4))
    sh[..., 0] = (colour - 0.5) / SH_C0
    sh[..., 1:] = 0.08 * torch.stack([x, y, z], dim=-1)[..., None, :]  # mild view dependence
    return density, sh


def make_sky(grid: SparseGrid, layers: int = 4, height: int = 8, width: int = 16) -> MSIBackground:
    """The unbounded variant's surround: an opaque shell on layer L - 2 (in front of it the MSI is
    empty) whose colour darkens from the horizon towards both poles, changes with azimuth like walls of
    different shades, and holds a bright sun; values in about [0.1, 1] so that 8-bit images keep them."""
    bg = MSIBackground.create(grid, layers, height, width, density=0.0)
    bg.density[layers - 2] = 40.0
    polar = (torch.arange(height, dtype=torch.float32) + 0.5) / height * torch.pi  # from +z
    azimuth = -torch.pi + (torch.arange(width, dtype=torch.float32) + 0.5) / width * 2 * torch.pi
    p, a = torch.meshgrid(polar, azimuth, indexing="ij")
    horizon = torch.sin(p)  # 1 at the equator of the spheres, 0 at the poles
    walls = 0.5 + 0.5 * torch.cos(2 * a)
    sun = torch.exp(-((p - 1.2) ** 2 + (a - 0.8) ** 2) / 0.15)
    sky = torch.stack([0.15 + 0.45 * horizon * walls, 0.25 + 0.4 * horizon, 0.6 - 0.3 * walls * horizon], -1)
    bg.color[:] = (sky + 0.55 * sun[..., None]).clamp(0.05, 1.0)
    return bg


def orbit_cameras(spec: ProceduralSceneSpec) -> Cameras:
    """Cameras on a sphere facing the origin, elevations -35..55 degrees."""
    n, w, h = spec.num_views, spec.width, spec.height
    return orbit_rig(n, w, h, spec.fov_deg, spec.camera_distance, (-35.0, 55.0))


def write_procedural_scene(out: Path, spec: ProceduralSceneSpec = ProceduralSceneSpec()) -> Path:
    """Render the scene into `out` as a nerfstudio `transforms.json` with PNG images; returns the json."""
    out = Path(out)
    grid = make_room(spec.grid_reso) if spec.walls else make_grid(spec.grid_reso)
    cams = orbit_cameras(spec)
    geometry = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4), levels=grid.levels)
    truth = Model(
        grid, geometry, RenderOptions(background_brightness=spec.background_brightness), cams, [], [], [], ""
    )
    truth.background = make_sky(grid) if spec.unbounded else None
    frames = []
    for i in range(len(cams)):
        img = truth.render_camera(i).clamp(0, 1).numpy()
        name = f"images/frame_{i:03d}.png"
        write_png(out / name, img)
        frames.append({"file_path": name, "transform_matrix": opengl_to_opencv(cams.c2w[i]).tolist()})
    fx, fy, cx, cy = cams.intrinsics[0]
    meta = {
        "camera_model": "PINHOLE",
        "fl_x": fx,
        "fl_y": fy,
        "cx": cx,
        "cy": cy,
        "w": spec.width,
        "h": spec.height,
        "aabb": [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]],
        **({"aabb_scale": 4} if spec.unbounded or spec.walls else {}),
        "generator": {"name": "hdrplenoxels procedural", **spec.__dict__},
        "frames": frames,
    }
    path = out / "transforms.json"
    atomic_write_text(path, json.dumps(meta, indent=1))
    return path
