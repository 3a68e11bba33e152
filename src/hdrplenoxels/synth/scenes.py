"""The synthetic scenes: Mitsuba primitives, textures made in code, emitters, and their camera rigs.

World frame: y up. Each scene gives a Mitsuba scene dict, cameras (OpenCV camera-to-world) and what
the data loader needs to place the grid: a bounding box for 360-degree scenes, or `forward_facing`
(depth bounds are measured from rendered depth by the generator, as LLFF takes them from SfM points).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.geometry.rigs import arc_rig, corner_walk_rig, forward_facing_rig, orbit_rig, walk_rig
from hdrplenoxels.synth.mitsuba_render import mitsuba
from hdrplenoxels.synth.sky import SkySpec, sky_radiance

Vec3 = Sequence[float]


@dataclass
class SceneRig:
    scene: dict
    cameras: Cameras
    forward_facing: bool
    aabb: tuple[tuple[float, float, float], tuple[float, float, float]] | None
    description: str
    background: float | None = None  # radiance where rays leave the scene, when it is visible
    # instant-ngp's aabb_scale: the content reaches this many times beyond the box (open scenes)
    aabb_scale: float | None = None


# ----------------------------------------------------------------------------- geometry helpers
def transform(
    translate: Vec3 = (0.0, 0.0, 0.0), rotate_deg: Vec3 = (0.0, 0.0, 0.0), scale: Vec3 = (1.0, 1.0, 1.0)
) -> np.ndarray:
    """T @ Rz @ Ry @ Rx @ S as a 4x4 matrix."""
    rx, ry, rz = np.deg2rad(rotate_deg)
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    r = (
        np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    )
    m = np.eye(4)
    m[:3, :3] = r @ np.diag(scale)
    m[:3, 3] = translate
    return m


def _t(m: np.ndarray):  # -> mitsuba.ScalarTransform4f (mitsuba is imported lazily)
    return mitsuba().ScalarTransform4f(m.tolist())


def rect(
    center: Vec3, rotate_deg: Vec3, half_size: tuple[float, float], bsdf: dict, emitter: dict | None = None
) -> dict:
    """A rectangle (local [-1,1]^2 in xy, normal +z) placed by a rotation and a translation."""
    d = {"type": "rectangle", "to_world": _t(transform(center, rotate_deg, (*half_size, 1.0))), "bsdf": bsdf}
    if emitter:
        d["emitter"] = emitter
    return d


def cube(center: Vec3, half_size: Vec3, rotate_deg: Vec3, bsdf: dict) -> dict:
    return {"type": "cube", "to_world": _t(transform(center, rotate_deg, half_size)), "bsdf": bsdf}


def sphere(center: Vec3, radius: float, bsdf: dict, emitter: dict | None = None) -> dict:
    d = {"type": "sphere", "center": list(center), "radius": float(radius), "bsdf": bsdf}
    if emitter:
        d["emitter"] = emitter
    return d


def diffuse(rgb: Vec3) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(map(float, rgb))}}


def textured(texture: np.ndarray) -> dict:
    """Diffuse with a linear albedo bitmap (H, W, 3) in [0, 1]."""
    bitmap = mitsuba().Bitmap(np.ascontiguousarray(texture, dtype=np.float32))
    return {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": bitmap, "raw": True}}


def plastic(rgb: Vec3, roughness: float = 0.15) -> dict:
    """A glossy dielectric coating: view-dependent highlights for the SH to learn."""
    return {
        "type": "roughplastic",
        "diffuse_reflectance": {"type": "rgb", "value": list(map(float, rgb))},
        "alpha": float(roughness),
    }


def area_light(rgb: Vec3) -> dict:
    return {"type": "area", "radiance": {"type": "rgb", "value": list(map(float, rgb))}}


# ----------------------------------------------------------------------------- textures (made in code)
def checker(n: int, a: Vec3, b: Vec3, res: int = 128) -> np.ndarray:
    idx = (np.arange(res) * n // res)[:, None] + (np.arange(res) * n // res)[None, :]
    return np.where((idx % 2)[..., None] == 0, np.asarray(a, float), np.asarray(b, float))


def smooth_noise(res: int, seed: int, low: Vec3 | float, high: Vec3 | float, octaves: int = 4) -> np.ndarray:
    """Multi-octave value noise in [low, high] per channel: texture detail for SfM and for the grid."""
    rng = np.random.default_rng(seed)
    out = np.zeros((res, res, 3))
    for o in range(octaves):
        cells = 4 * 2**o
        coarse = rng.uniform(0, 1, size=(cells + 1, cells + 1, 3))
        x = np.linspace(0, cells, res)
        i = np.minimum(x.astype(int), cells - 1)
        f = x - i
        rows = coarse[i] * (1 - f)[:, None, None] + coarse[i + 1] * f[:, None, None]
        out += (rows[:, i] * (1 - f)[None, :, None] + rows[:, i + 1] * f[None, :, None]) / 2**o
    out = (out - out.min()) / (out.max() - out.min())
    return np.asarray(low) + out * (np.asarray(high) - np.asarray(low))


def blocks(res: int, cells: int, seed: int, low: Vec3, high: Vec3) -> np.ndarray:
    """Random colour squares: sharp, high-contrast corners at every scale SIFT looks at."""
    rng = np.random.default_rng(seed + 1000)
    grid = rng.uniform(0, 1, size=(cells, cells, 3))
    idx = np.arange(res) * cells // res
    return np.asarray(low) + grid[idx][:, idx] * (np.asarray(high) - np.asarray(low))


def stripes(res: int, n: int, a: Vec3, b: Vec3) -> np.ndarray:
    t = 0.5 + 0.5 * np.sin(np.linspace(0, 2 * np.pi * n, res))[None, :, None]
    return np.broadcast_to(np.asarray(a) * t + np.asarray(b) * (1 - t), (res, res, 3)).copy()


# ----------------------------------------------------------------------------- scenes
def _room_shell(seed: int, wall_albedo: tuple[float, float, float]) -> dict:
    """Floor, ceiling and walls of a 5 x 3 x 6.5 room (x in [-2.5, 2.5], y in [-1.2, 1.8], z in [-1.5, 5])."""
    wall = textured(smooth_noise(256, seed, np.asarray(wall_albedo) * 0.6, wall_albedo))
    floor_tex = checker(10, (0.55, 0.5, 0.42), (0.25, 0.2, 0.16), res=256) * smooth_noise(
        256, seed + 1, 0.7, 1.0
    )
    return {
        "floor": rect((0, -1.2, 1.75), (-90, 0, 0), (2.5, 3.25), textured(floor_tex)),
        "ceiling": rect((0, 1.8, 1.75), (90, 0, 0), (2.5, 3.25), diffuse((0.7, 0.7, 0.7))),
        "back": rect((0, 0.3, 5.0), (0, 180, 0), (2.5, 1.5), wall),
        "left": rect((-2.5, 0.3, 1.75), (0, 90, 0), (3.25, 1.5), wall),
        "right": rect((2.5, 0.3, 1.75), (0, -90, 0), (3.25, 1.5), wall),
        "front": rect((0, 0.3, -1.5), (0, 0, 0), (2.5, 1.5), diffuse((0.3, 0.3, 0.3))),
    }


def room(n_views: int, width: int, height: int) -> SceneRig:
    """Indoor, forward-facing: the window saturates at normal exposure (radiance ~6) but not at -3 EV,
    so every part of the scene is seen unclipped in some view; the corners stay dark."""
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 5}}
    scene.update(_room_shell(0, (0.6, 0.56, 0.5)))
    scene.update(
        {
            "window": rect(
                (1.2, 0.6, 4.98), (0, 180, 0), (0.7, 0.6), diffuse((0, 0, 0)), area_light((6.0, 5.7, 5.0))
            ),
            "lamp": rect(
                (-1.5, 1.79, 2.5), (90, 0, 0), (0.25, 0.25), diffuse((0, 0, 0)), area_light((1.2, 1.0, 0.8))
            ),
            "box": cube(
                (-0.8, -0.85, 3.0),
                (0.35, 0.35, 0.35),
                (0, 25, 0),
                textured(checker(4, (0.8, 0.2, 0.15), (0.9, 0.85, 0.7))),
            ),
            "ball": sphere((0.5, -0.8, 2.5), 0.4, plastic((0.15, 0.35, 0.8))),
            "pillar": cube(
                (1.6, -0.4, 3.8),
                (0.2, 0.8, 0.2),
                (0, 10, 0),
                textured(stripes(128, 6, (0.9, 0.8, 0.3), (0.3, 0.6, 0.3))),
            ),
            "shelf": cube((-1.8, 0.2, 4.2), (0.5, 0.05, 0.4), (0, 0, 0), diffuse((0.5, 0.35, 0.2))),
            "vase": sphere((-1.8, 0.45, 4.2), 0.2, plastic((0.85, 0.75, 0.2), 0.08)),
        }
    )
    cams = forward_facing_rig(n_views, width, height, 60.0, (0.0, -0.1, -0.8), (1.2, 0.5), (0.0, -0.3, 3.5))
    return SceneRig(scene, cams, True, None, "room with a bright window, forward-facing")


def objects360(n_views: int, width: int, height: int) -> SceneRig:
    """Objects on a pedestal seen from all around, lit by the sky and a sun."""
    scene = {
        "type": "scene",
        # The sky lights the scene but is hidden from camera rays: a black background is the same in
        # every exposure, white balance and response, so the grid's constant background can match it.
        "integrator": {"type": "path", "max_depth": 4, "hide_emitters": True},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
        "sun": {
            "type": "directional",
            "direction": [-0.5, -1.0, -0.3],
            "irradiance": {"type": "rgb", "value": [4.0, 3.8, 3.4]},
        },
        "pedestal": {
            "type": "cylinder",
            "p0": [0, -0.75, 0],
            "p1": [0, -0.55, 0],
            "radius": 0.85,
            "bsdf": textured(smooth_noise(128, 0, (0.3, 0.3, 0.35), (0.7, 0.7, 0.75))),
        },
        "top": {
            "type": "disk",
            "to_world": _t(transform((0, -0.55, 0), (-90, 0, 0), (0.85, 0.85, 1))),
            "bsdf": textured(checker(8, (0.85, 0.85, 0.8), (0.2, 0.25, 0.3))),
        },
        "globe": sphere(
            (-0.3, -0.2, 0.1), 0.35, textured(stripes(128, 8, (0.9, 0.3, 0.2), (0.95, 0.9, 0.8)))
        ),
        "crate": cube(
            (0.35, -0.3, -0.25),
            (0.25, 0.25, 0.25),
            (0, 35, 0),
            textured(smooth_noise(128, 2, (0.2, 0.5, 0.2), (0.6, 0.9, 0.4))),
        ),
        "gem": sphere((0.4, 0.05, 0.35), 0.18, plastic((0.2, 0.3, 0.9), 0.05)),
        "post": cube((-0.45, -0.05, -0.45), (0.07, 0.5, 0.07), (0, 20, 0), plastic((0.9, 0.8, 0.2))),
    }
    cams = orbit_rig(n_views, width, height, 40.0, 3.6, (5.0, 60.0))
    box = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    return SceneRig(scene, cams, False, box, "objects on a pedestal, 360-degree orbit", background=0.0)


def extreme(n_views: int, width: int, height: int) -> SceneRig:
    """A dark room lit by one bare bulb in view: radiance spans well over 12 stops."""
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 5}}
    scene.update(_room_shell(5, (0.25, 0.22, 0.2)))
    scene.update(
        {
            "bulb": sphere((0.9, 0.7, 3.6), 0.07, diffuse((0, 0, 0)), area_light((1000, 850, 650))),
            "table": cube(
                (0.3, -0.75, 3.3),
                (0.9, 0.05, 0.5),
                (0, 0, 0),
                textured(smooth_noise(128, 3, (0.35, 0.2, 0.1), (0.6, 0.4, 0.2))),
            ),
            "cup": sphere((0.6, -0.5, 3.2), 0.2, plastic((0.9, 0.9, 0.85), 0.05)),
            "book": cube(
                (-0.1, -0.62, 3.4),
                (0.3, 0.08, 0.22),
                (0, -15, 0),
                textured(checker(6, (0.1, 0.2, 0.6), (0.8, 0.8, 0.2))),
            ),
            "chair": cube((-1.3, -0.7, 2.6), (0.3, 0.5, 0.3), (0, 30, 0), diffuse((0.35, 0.1, 0.08))),
        }
    )
    cams = forward_facing_rig(n_views, width, height, 60.0, (0.0, -0.1, -0.8), (1.2, 0.5), (0.1, -0.3, 3.4))
    return SceneRig(scene, cams, True, None, "dark room with a bare bulb in view, forward-facing")


def glowing(texture: np.ndarray, scale: float = 1.0) -> tuple[dict, dict]:
    """(black BSDF, area emitter) whose radiance is `scale` * the bitmap: a self-lit textured surface."""
    bitmap = mitsuba().Bitmap(np.ascontiguousarray(texture * scale, dtype=np.float32))
    return diffuse((0, 0, 0)), {"type": "area", "radiance": {"type": "bitmap", "bitmap": bitmap, "raw": True}}


def gallery(n_views: int, width: int, height: int) -> SceneRig:
    """A room of self-lit, finely textured panels and blocks, walked around on an arc: the scene for
    structure from motion (`process`). The paper-style scenes are smooth and their Monte Carlo noise at
    test-suite sample counts breaks SIFT matching; emitted texture renders noise-free at any spp."""

    def fine(seed: int, low: Vec3, high: Vec3, scale: float = 0.3, cells: int = 40) -> tuple[dict, dict]:
        tex = 0.5 * blocks(512, cells, seed, low, high) + 0.5 * smooth_noise(512, seed, low, high)
        return glowing(tex, scale)

    def panel(center: Vec3, rotate: Vec3, half: tuple[float, float], look: tuple[dict, dict]) -> dict:
        return rect(center, rotate, half, *look)

    r = 3.5  # half-size of the room
    scene = {"type": "scene", "integrator": {"type": "direct"}}
    scene.update(
        {
            "floor": panel((0, -1.2, 0), (-90, 0, 0), (r, r), fine(10, (0.1, 0.08, 0.06), (0.8, 0.7, 0.55))),
            "wall_n": panel((0, 0.3, r), (0, 180, 0), (r, 1.5), fine(11, (0.1, 0.2, 0.3), (0.7, 0.8, 0.9))),
            "wall_s": panel((0, 0.3, -r), (0, 0, 0), (r, 1.5), fine(12, (0.3, 0.15, 0.1), (0.9, 0.75, 0.6))),
            "wall_w": panel((-r, 0.3, 0), (0, 90, 0), (r, 1.5), fine(13, (0.15, 0.3, 0.1), (0.75, 0.9, 0.6))),
            "wall_e": panel((r, 0.3, 0), (0, -90, 0), (r, 1.5), fine(14, (0.25, 0.2, 0.3), (0.85, 0.8, 0.9))),
            # Objects never have a repeated face, which would give SIFT look-alike matches.
            "ball": sphere((-0.5, -0.65, 0.4), 0.55, *fine(15, (0.1, 0.1, 0.1), (0.9, 0.6, 0.3), cells=12)),
            "board": panel(
                (0.7, -0.5, -0.6),
                (0, 15, 0),
                (0.5, 0.7),
                fine(16, (0.2, 0.1, 0.3), (0.6, 0.9, 0.9), cells=10),
            ),
        }
    )
    cams = arc_rig(n_views, width, height, 60.0, 2.6, (-70.0, 70.0), (10.0, 25.0), (0.0, -0.6, 0.0))
    box = ((-r - 0.1, -1.3, -r - 0.1), (r + 0.1, 1.9, r + 0.1))
    return SceneRig(scene, cams, False, box, "self-lit textured room walked around on an arc (for SfM)")


def facade(
    res: int, seed: int, wall: Vec3, floors: int, bays: int, plain: bool = False, stones: float = 0.75
) -> np.ndarray:
    """A building front: rough plaster with a grid of framed windows. Each window has its own size, frame
    colour and curtain, so no two look alike (repeated ones would give SfM look-alike matches). The
    plaster's stones are `stones` to 1 times the wall's colour; `plain`: smooth render with one column of
    windows, where SIFT finds little."""
    rng = np.random.default_rng(seed + 60)
    if plain:
        tex, bays = smooth_noise(res, seed, np.asarray(wall) * 0.85, wall), 1
    else:
        tex = 0.6 * smooth_noise(res, seed, np.asarray(wall) * 0.7, wall) + 0.4 * blocks(
            res, 48, seed, np.asarray(wall) * stones, wall
        )
    rows, cols = np.mgrid[0:res, 0:res] / res
    window = (rows * floors).astype(int) * bays + (cols * bays).astype(int)
    fy, fx = (rows * floors) % 1.0, (cols * bays) % 1.0
    half = rng.uniform(0.15, 0.3, size=(floors * bays, 2))[window]  # per window: half height, half width
    frame = (np.abs(fx - 0.5) < half[..., 1] + 0.05) & (np.abs(fy - 0.45) < half[..., 0] + 0.05)
    glass = (np.abs(fx - 0.5) < half[..., 1]) & (np.abs(fy - 0.45) < half[..., 0])
    blank = rows < 1.0 / floors  # one storey of plain wall
    frame_rgb = rng.uniform(0.3, 0.9, size=(floors * bays, 3))[window]
    curtain = rng.uniform(0.05, 0.6, size=(floors * bays, 3))[window]
    drawn = fx < rng.uniform(0.2, 0.8, size=floors * bays)[window]
    glass_rgb = smooth_noise(res, seed + 50, (0.03, 0.05, 0.08), (0.2, 0.25, 0.3))
    pane = np.where(drawn[..., None], curtain, glass_rgb)
    tex = np.where((frame & ~blank)[..., None], frame_rgb, tex)
    return np.where((glass & ~blank)[..., None], pane, tex)


def flagstones(res: int, cells: int, seed: int, tint: Vec3) -> np.ndarray:
    """Paving: rows of stones of random length and brightness, weathered by noise, with dark joints; the
    joints never line up from row to row, so the paving has no repeated corner pattern."""
    rng = np.random.default_rng(seed)
    row = (np.arange(res) * cells // res)[:, None]  # stone row of each texel row
    u = np.arange(res)[None, :] * cells / res  # position along a row, in mean stone lengths
    shift = rng.uniform(0, 1, size=(cells, 1))[row[:, 0]]
    edges = np.cumsum(rng.uniform(0.5, 1.5, size=(cells, 2 * cells)), axis=1)  # stone ends per row
    stone = np.stack([np.searchsorted(edges[r], u[0] + shift[i, 0]) for i, r in enumerate(row[:, 0])])
    start = np.take_along_axis(np.concatenate([np.zeros((cells, 1)), edges], 1)[row[:, 0]], stone, 1)
    end = np.take_along_axis(edges[row[:, 0]], stone, 1)
    along = u + shift
    v = np.arange(res)[:, None] * cells / res % 1.0
    joint = (np.minimum(along - start, end - along) < 0.06) | (np.minimum(v, 1.0 - v) < 0.06)
    brightness = rng.uniform(0.35, 1.0, size=(cells, 2 * cells + 1))[row[:, 0][:, None], stone]
    weathering = np.repeat(np.repeat(smooth_noise(res // 4, seed, 0.7, 1.0, octaves=6)[..., 0], 4, 0), 4, 1)
    shade = brightness * weathering * np.where(joint, 0.35, 1.0)
    return shade.astype(np.float32)[..., None] * np.asarray(tint, dtype=np.float32)


COURTYARD_BOX = ((-1.2, -1.1, -1.2), (1.2, 0.9, 1.2))  # the central objects, resting on the ground at y=-1
COURTYARD_PAVED = 16.0  # half-size of the paved square; meadow and hills beyond
COURTYARD_REACH = 36.0  # the farthest terrain from the centre, world units


def courtyard(n_views: int, width: int, height: int) -> SceneRig:
    """Objects on a plinth in an open courtyard: paving that runs out to buildings 11-16 units away, hills
    behind them and a procedural HDR sky (`synth/sky.py`) with a low sun, all visible to the cameras. Only
    the objects lie in the box; the sky (luminance ~0.3 at the zenith, ~2 at the horizon, up to ~8 beside
    the sun; the sun's disk ~1400) is the brightest content.
    One emitter (the sky) keeps Mitsuba's light sampling on the sun, so the path tracer converges fast."""
    ground_y = -1.0
    paving = flagstones(2048, 72, 20, (0.17, 0.155, 0.13))
    grass = smooth_noise(512, 19, (0.05, 0.09, 0.03), (0.16, 0.24, 0.08), octaves=6)
    scene: dict = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sky": {"type": "envmap", "bitmap": mitsuba().Bitmap(sky_radiance())},
        "paving": rect((0, ground_y, 0), (-90, 0, 0), (COURTYARD_PAVED, COURTYARD_PAVED), textured(paving)),
        "meadow": rect(
            (0, ground_y - 0.01, 0), (-90, 0, 0), (COURTYARD_REACH, COURTYARD_REACH), textured(grass)
        ),
        "plinth": {
            "type": "cylinder",
            "p0": [0, ground_y, 0],
            "p1": [0, ground_y + 0.25, 0],
            "radius": 0.95,
            "bsdf": textured(smooth_noise(256, 21, (0.2, 0.19, 0.17), (0.5, 0.48, 0.44))),
        },
        "plinth_top": {
            "type": "disk",
            "to_world": _t(transform((0, ground_y + 0.25, 0), (-90, 0, 0), (0.95, 0.95, 1))),
            "bsdf": textured(checker(8, (0.8, 0.78, 0.7), (0.25, 0.28, 0.3), res=256)),
        },
        "globe": sphere(
            (-0.35, ground_y + 0.65, 0.1), 0.4, textured(stripes(128, 8, (0.85, 0.3, 0.2), (0.9, 0.85, 0.75)))
        ),
        "crate": cube(
            (0.4, ground_y + 0.53, -0.3),
            (0.28, 0.28, 0.28),
            (0, 35, 0),
            textured(blocks(128, 6, 22, (0.15, 0.4, 0.15), (0.6, 0.85, 0.4))),
        ),
        "gem": sphere((0.45, ground_y + 0.45, 0.45), 0.2, plastic((0.2, 0.3, 0.85), 0.05)),
        "post": cube((-0.5, ground_y + 0.85, -0.5), (0.07, 0.6, 0.07), (0, 20, 0), plastic((0.9, 0.75, 0.2))),
    }
    rng = np.random.default_rng(23)
    # Buildings around the courtyard, with gaps that show the hills and the horizon.
    for k, azimuth in enumerate(np.arange(0.0, 360.0, 36.0) + rng.uniform(-6, 6, 10)):
        radius, half_w = rng.uniform(11.0, 16.0), rng.uniform(2.0, 4.0)
        half_h, half_d = rng.uniform(1.0, 2.6), rng.uniform(1.0, 2.0)
        a = np.deg2rad(azimuth)
        wall = tuple(rng.uniform(0.2, 0.5, 3))
        tex = facade(256, 30 + k, wall, int(2 * half_h // 1.5) + 1, int(2 * half_w // 1.5) + 1)
        centre = (radius * np.sin(a), ground_y + half_h, radius * np.cos(a))
        scene[f"building{k}"] = cube(centre, (half_w, half_h, half_d), (0, float(azimuth), 0), textured(tex))
    for k, azimuth in enumerate(np.arange(18.0, 360.0, 72.0)):  # hills beyond: big, mostly buried spheres
        a, r, top = np.deg2rad(azimuth), rng.uniform(14.0, 20.0), rng.uniform(2.5, 5.0)
        distance = COURTYARD_REACH - np.sqrt(2 * r * top - top**2)  # its foot ends at the terrain's reach
        centre = (distance * np.sin(a), ground_y - r + top, distance * np.cos(a))
        hillside = smooth_noise(512, 40 + k, (0.08, 0.15, 0.05), (0.3, 0.45, 0.15), octaves=6)
        scene[f"hill{k}"] = sphere(centre, r, textured(hillside))
    cams = orbit_rig(n_views, width, height, 65.0, 3.2, (1.0, 12.0), (0.0, -0.35, 0.0))
    return SceneRig(
        scene,
        cams,
        False,
        COURTYARD_BOX,
        "objects in an open courtyard under an HDR sky with a low sun, 360-degree orbit (unbounded)",
        aabb_scale=float(2 ** np.ceil(np.log2(COURTYARD_REACH / COURTYARD_BOX[1][0]))),  # NGP: a power of 2
    )


STREET_HALF_WIDTH = 4.0  # the facades stand this far either side of the street's axis (x = 0)
STREET_WALK = 12.0  # the cameras walk this far along +z
CORNER_LEGS = (10.0, 8.0)  # `corner`: the walk along the first street, then along the side street
CORNER_RADIUS = 4.0  # ... and the quarter circle between them, through the crossing
PAVEMENT = 1.5  # `corner`: the width of the paved pavement before each row of fronts


def _fronts(
    scene: dict,
    name: str,
    rng: np.random.Generator,
    seed: int,
    start: tuple[float, float],
    along: tuple[float, float],
    reach: float,
    facing: tuple[float, float],
    plain: Callable[[int], bool] = lambda k: False,
    exact: bool = False,
    stones: float = 0.75,
) -> None:
    """Self-lit building fronts of random length and storeys side by side from `start` (x, z) along the
    unit direction `along` until `reach` is covered (`exact`: the last one cut to end there), facing the
    street along the unit `facing`; front `k` is a plain rendered wall where `plain(k)`."""
    yaw = float(np.degrees(np.arctan2(*facing)))
    s, k = 0.0, 0
    while s < reach:
        length, storeys = rng.uniform(3.5, 5.5), int(rng.integers(2, 5))
        length = min(length, reach - s) if exact else length
        wall = tuple(rng.uniform(0.35, 0.8, 3))
        tex = facade(512, seed + 10 * k, wall, storeys, max(2, int(length // 1.4)), plain(k), stones)
        h = 1.6 * storeys + 0.6
        middle = s + length / 2
        centre = (start[0] + along[0] * middle, h / 2, start[1] + along[1] * middle)
        scene[f"{name}{k}"] = rect(centre, (0, yaw, 0), (length / 2, h / 2), *glowing(tex))
        s, k = s + length, k + 1


def street(n_views: int, width: int, height: int) -> SceneRig:
    """A street of self-lit building fronts on paving, walked straight down (+z) with a phone held at eye
    height: the forward motion that barely fixes a camera's focal length. Emitted textures render without
    Monte Carlo noise, as in `gallery`, so SIFT sees clean photos; a facade of its own closes the far end,
    and the sky is black."""
    rng = np.random.default_rng(70)
    half, far = STREET_HALF_WIDTH, STREET_WALK + 14.0
    paving = flagstones(1024, 40, 71, (0.5, 0.46, 0.4))
    scene: dict = {"type": "scene", "integrator": {"type": "direct"}}
    scene["paving"] = rect((0, 0, far / 2 - 2), (-90, 0, 0), (half, far / 2 + 2), *glowing(paving))
    _fronts(scene, "left", rng, 80, (-half, -3.0), (0.0, 1.0), far + 3.0, (1.0, 0.0))
    _fronts(scene, "right", rng, 81, (half, -3.0), (0.0, 1.0), far + 3.0, (-1.0, 0.0))
    end = facade(512, 99, (0.6, 0.5, 0.4), 4, 5)
    scene["end"] = rect((0, 3.5, far), (0, 180, 0), (half, 3.5), *glowing(end))
    cams = walk_rig(n_views, width, height, 60.0, STREET_WALK, eye=1.6)
    box = ((-half - 0.1, -0.1, -3.0), (half + 0.1, 8.0, far + 0.1))
    return SceneRig(scene, cams, False, box, "a street of building fronts walked straight down (for SfM)")


def corner(n_views: int, width: int, height: int) -> SceneRig:
    """`street`'s walk with what makes a real one hard for structure from motion: it turns a corner into
    a side street, a clear sky with no features fills the top of the photos and is brighter than the
    walls (so a phone's auto exposure darkens them), two fronts in three are plain rendered walls with one
    column of windows, and the road is smooth asphalt. Photo noise and JPEG come from the capture
    (`synth corner OUT --camera auto --noise --photos`)."""
    rng, looks = np.random.default_rng(72), np.random.default_rng(73)
    half, (first, second), radius = STREET_HALF_WIDTH, CORNER_LEGS, CORNER_RADIUS
    side_z = first + radius  # the side street's axis (z), walked along +x
    far_z, far_x = side_z + 12.0, radius + second + 10.0

    def fronts(name: str, seed: int, start: tuple[float, float], along, reach: float, facing) -> None:
        """A row of fronts, one in three plain, with a paved pavement before them."""

        def plain(k: int) -> bool:
            return bool(looks.uniform() < 1 / 3)

        _fronts(scene, name, rng, seed, start, along, reach, facing, plain=plain, exact=True, stones=0.3)
        middle = [start[i] + along[i] * reach / 2 + facing[i] * PAVEMENT / 2 for i in (0, 1)]
        size = (reach / 2, PAVEMENT / 2) if along[0] else (PAVEMENT / 2, reach / 2)
        paving = flagstones(1024, 40, seed + 1, (0.5, 0.46, 0.4))
        scene[f"{name}_pavement"] = rect((middle[0], 0.02, middle[1]), (-90, 0, 0), size, *glowing(paving))

    sky = sky_radiance(SkySpec(sun_azimuth_deg=20.0, sun_elevation_deg=55.0, clouds=0.0))
    asphalt = smooth_noise(1024, 74, (0.1, 0.1, 0.11), (0.26, 0.26, 0.27), octaves=7)
    scene: dict = {
        "type": "scene",
        "integrator": {"type": "direct"},
        "sky": {"type": "envmap", "bitmap": mitsuba().Bitmap(sky)},
        "road": rect(
            ((far_x - half) / 2, 0, (far_z - 3.0) / 2),
            (-90, 0, 0),
            ((far_x + half) / 2, (far_z + 3.0) / 2),
            *glowing(asphalt),
        ),
    }
    fronts("west", 180, (-half, -3.0), (0.0, 1.0), far_z + 3.0, (1.0, 0.0))
    fronts("east", 181, (half, -3.0), (0.0, 1.0), side_z - half + 3.0, (-1.0, 0.0))  # up to the corner
    fronts("corner_south", 182, (half, side_z - half), (1.0, 0.0), far_x - half, (0.0, 1.0))
    fronts("corner_north", 183, (half, side_z + half), (1.0, 0.0), far_x - half, (0.0, -1.0))
    fronts("east_beyond", 184, (half, side_z + half), (0.0, 1.0), far_z - side_z - half, (-1.0, 0.0))
    scene["end"] = rect(
        (0, 2.0, far_z), (0, 180, 0), (half, 2.0), *glowing(facade(512, 199, (0.6, 0.5, 0.4), 2, 5))
    )
    scene["side_end"] = rect(
        (far_x, 2.0, side_z), (0, -90, 0), (half, 2.0), *glowing(facade(512, 198, (0.5, 0.55, 0.6), 2, 5))
    )
    cams = corner_walk_rig(n_views, width, height, 60.0, CORNER_LEGS, radius, eye=1.6)
    box = ((-half - 0.1, -0.1, -3.0), (far_x + 0.1, 8.0, far_z + 0.1))
    return SceneRig(scene, cams, False, box, "a street walked down and round a corner under a sky (for SfM)")


INDOOR_BOX = ((-0.6, -1.2, -0.6), (0.6, 0.0, 0.6))  # the table and what stands on it


def indoor(n_views: int, width: int, height: int) -> SceneRig:
    """A real indoor capture's shape, with truth: cameras 1.3-1.6 from a table of objects in the middle of
    a furnished 4.4 x 2.6 x 4.4 room, the walls, a bookcase, a cabinet and an armchair 0.5-1.5 behind and
    beside them, and a window whose daylight (radiance ~6-9, a sky gradient with a bright patch) is the
    brightest content. Only the table is in the stated box; `aabb_scale` 4 says the room reaches beyond
    it, as instant-ngp's captures do."""
    half = 2.2
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 4}}
    wall = textured(
        0.5 * smooth_noise(256, 50, (0.35, 0.33, 0.3), (0.7, 0.66, 0.6))
        + 0.5 * stripes(256, 24, (0.62, 0.58, 0.52), (0.45, 0.42, 0.38))
    )
    floor_tex = flagstones(512, 16, 51, (0.55, 0.4, 0.28))
    daylight = np.ones((64, 64, 3)) * np.linspace(1.0, 0.65, 64)[:, None, None] * np.array([6.0, 6.6, 7.6])
    daylight[8:24, 40:56] *= 1.45  # a bright patch of sky: the scene's brightest radiance
    scene.update(
        {
            "floor": rect((0, -1.2, 0), (-90, 0, 0), (half, half), textured(floor_tex)),
            "ceiling": rect((0, 1.4, 0), (90, 0, 0), (half, half), diffuse((0.75, 0.75, 0.72))),
            "wall_n": rect((0, 0.1, half), (0, 180, 0), (half, 1.3), wall),
            "wall_s": rect((0, 0.1, -half), (0, 0, 0), (half, 1.3), wall),
            "wall_w": rect((-half, 0.1, 0), (0, 90, 0), (half, 1.3), wall),
            "wall_e": rect((half, 0.1, 0), (0, -90, 0), (half, 1.3), wall),
            "window": rect((0.4, 0.35, half - 0.01), (0, 180, 0), (0.8, 0.55), *glowing(daylight)),
            "lamp": rect(
                (0, 1.39, 0), (90, 0, 0), (0.3, 0.3), diffuse((0, 0, 0)), area_light((1.5, 1.3, 1.0))
            ),
            "table": cube(
                (0, -0.62, 0),
                (0.45, 0.04, 0.45),
                (0, 10, 0),
                textured(smooth_noise(128, 52, (0.3, 0.18, 0.1), (0.55, 0.35, 0.2))),
            ),
            "leg": cube((0, -0.92, 0), (0.06, 0.28, 0.06), (0, 10, 0), diffuse((0.2, 0.12, 0.08))),
            "vase": sphere((-0.15, -0.38, 0.1), 0.2, plastic((0.2, 0.45, 0.8), 0.08)),
            "box": cube(
                (0.2, -0.46, -0.12),
                (0.12, 0.12, 0.12),
                (0, 30, 0),
                textured(blocks(128, 5, 53, (0.6, 0.15, 0.1), (0.95, 0.8, 0.3))),
            ),
            "bookcase": cube(
                (-1.6, -0.3, 2.0),
                (0.45, 0.9, 0.15),
                (0, 0, 0),
                textured(blocks(256, 12, 54, (0.15, 0.1, 0.2), (0.8, 0.6, 0.5))),
            ),
            "cabinet": cube(
                (1.9, -0.75, -0.6),
                (0.25, 0.45, 0.5),
                (0, 0, 0),
                textured(smooth_noise(128, 55, (0.4, 0.3, 0.2), (0.7, 0.55, 0.35))),
            ),
            "armchair": cube(
                (-1.7, -0.85, -1.5),
                (0.35, 0.35, 0.35),
                (0, 40, 0),
                textured(checker(6, (0.5, 0.1, 0.1), (0.25, 0.05, 0.08))),
            ),
        }
    )
    cams = orbit_rig(n_views, width, height, 70.0, 1.45, (5.0, 30.0), (0.0, -0.45, 0.0))
    return SceneRig(
        scene,
        cams,
        False,
        INDOOR_BOX,
        "objects on a table in a furnished room with a daylit window, cameras among the furniture",
        aabb_scale=4.0,
    )


@dataclass(frozen=True)
class SceneSpec:
    build: Callable[[int, int, int], SceneRig]  # (views, width, height) -> scene and cameras
    width: int  # default (CPU) resolution
    height: int
    spp: int


SCENES: dict[str, SceneSpec] = {
    "room": SceneSpec(room, 160, 120, 512),
    "objects360": SceneSpec(objects360, 128, 128, 256),
    "extreme": SceneSpec(extreme, 160, 120, 256),
    # The built-in demo: the 360-degree scene small enough to render and train within the demo budget.
    "demo": SceneSpec(objects360, 128, 128, 64),
    "gallery": SceneSpec(gallery, 320, 240, 8),
    "courtyard": SceneSpec(courtyard, 160, 120, 128),
    "indoor": SceneSpec(indoor, 160, 120, 256),
    "street": SceneSpec(street, 480, 360, 4),
    "corner": SceneSpec(corner, 640, 480, 4),
}
