"""Where the grid lives: a bounding box around the scene, a cascade of nested boxes around what the
cameras look at out to every camera and beyond, or NDC space for forward-facing captures.

A parser gives cameras in its own world frame. This module decides the scene mode (docs/method.md,
"Placement"), and for NDC moves the cameras into the LLFF frame (recentred on the average pose, looking
along +z, scaled so that the nearest content sits beyond the near plane z = 1). For a box or a cascade it
moves them into a frame where the (finest) box is centred at the origin with its largest half-side 1, as
svox2 normalises its scenes: density is per world unit, so the presets' density initialisation and
learning rates only mean the same thing on every dataset in one scale (JOURNAL.md, "Other
measured choices"). The similarity `world_from_data` is kept so that a user's pose in the dataset's own
frame can be rendered later, and exports can go back to the dataset's frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.geometry.cameras import Cameras, NDCSpec, pixel_rays, to_ndc

NDC_PADDING = 0.248  # grid margin beyond the image edge, as a fraction of the width (LLFF: 250 px of 1008)
FORWARD_FACING_DEG = 40.0  # every view within 40 deg of the mean view -> forward-facing
ALL_AROUND = 0.1  # length of the mean unit view direction below which views face every way
# NDC fits a camera that stays near one pose: cameras farther than this fraction of the nearest depth from
# their mean position travel through the scene, and get a cascade instead.
NDC_TRAVEL = 1.0
MAX_LEVELS = 8  # boxes of a cascade: the outermost is 2^7 times the finest
CAMERA_MARGIN = 1.1  # the outermost box reaches this far past the farthest camera (per axis)
CONVERGING = 0.25  # the views' axes pass the focus point within this fraction of its median distance
# ... and they differ enough in direction to fix a point: the focus system's smallest eigenvalue per view
# (sin^2 of the views' spread about the weakest axis) is at least sin^2(10 deg).
SPREAD = float(np.sin(np.radians(10.0)) ** 2)
SUBJECT = 0.5  # the finest box's half-side: this fraction of the cameras' median distance to the focus


@dataclass
class SceneGeometry:
    mode: Literal["bbox", "ndc"]
    center: tuple[float, float, float]
    radius: tuple[float, float, float]
    world_from_data: np.ndarray  # (4, 4) similarity applied to camera-to-world poses
    ndc: NDCSpec | None = None
    wants_background: bool = False  # content beyond the (outermost) box wants a background model
    levels: int = 1  # boxes of the cascade, level l of half-sides radius * 2^l (1: one box)

    def to_dict(self) -> dict:
        return {
            "mode": self.mode,
            "center": list(self.center),
            "radius": list(self.radius),
            "world_from_data": self.world_from_data.tolist(),
            "ndc": None if self.ndc is None else [self.ndc.coeff_x, self.ndc.coeff_y, self.ndc.near],
            "wants_background": self.wants_background,
            "levels": self.levels,
        }

    @classmethod
    def from_dict(cls, d: dict) -> SceneGeometry:
        if d["mode"] not in ("bbox", "ndc") or (d["mode"] == "ndc") != (d["ndc"] is not None):
            raise ValueError("geometry mode must be bbox, or ndc with its NDC parameters")
        ndc = None if d["ndc"] is None else NDCSpec(*d["ndc"])
        world_from_data = np.asarray(d["world_from_data"], dtype=np.float64)
        center, radius = np.asarray(d["center"], dtype=np.float64), np.asarray(d["radius"], dtype=np.float64)
        if world_from_data.shape != (4, 4) or center.shape != (3,) or radius.shape != (3,):
            raise ValueError("geometry needs a 4x4 world_from_data and 3-vectors center and radius")
        if not (np.isfinite(world_from_data).all() and np.linalg.det(world_from_data[:3, :3]) > 0):
            raise ValueError("geometry's world_from_data is not a finite similarity")
        # "background": its old name; models saved before the mode existed: False
        background = d.get("wants_background", d.get("background", False))
        if not isinstance(background, bool):
            raise ValueError(f"geometry's wants_background must be true or false, got {background!r}")
        levels = d.get("levels", 1)  # models saved before cascades: one box
        if not isinstance(levels, int) or isinstance(levels, bool) or not 1 <= levels <= MAX_LEVELS:
            raise ValueError(f"geometry's levels must be an integer from 1 to {MAX_LEVELS}, got {levels!r}")
        return cls(
            d["mode"],
            tuple(center.tolist()),
            tuple(radius.tolist()),
            world_from_data,
            ndc,
            background,
            levels,
        )

    def scale(self) -> float:
        """World units per dataset unit (the similarity's scale)."""
        return float(np.cbrt(np.linalg.det(self.world_from_data[:3, :3])))

    def poses_to_world(self, c2w_data: np.ndarray) -> np.ndarray:
        """OpenCV camera-to-world poses from the dataset frame into the grid's world frame."""
        out = self.world_from_data @ c2w_data
        out[..., :3, :3] /= self.scale()  # keep rotations orthonormal; only positions are scaled
        return out

    def poses_to_data(self, c2w_world: np.ndarray) -> np.ndarray:
        """The inverse of `poses_to_world`: grid-frame poses back into the dataset's frame."""
        out = np.array(c2w_world, dtype=np.float64)
        out[..., :3, :3] *= self.scale()
        return np.linalg.inv(self.world_from_data) @ out

    def rays(self, c2w: torch.Tensor, intrinsics: torch.Tensor, cols: torch.Tensor, rows: torch.Tensor):
        """Rays (world or NDC) for per-ray world-frame poses and intrinsics."""
        o, d = pixel_rays(c2w, intrinsics, cols, rows)
        if self.mode == "ndc":
            o, d = to_ndc(o, d, self.ndc)
        return o, d


def is_forward_facing(cameras: Cameras) -> bool:
    return _max_view_angle(cameras) < FORWARD_FACING_DEG


def _max_view_angle(cameras: Cameras) -> float:
    """Degrees between the mean view direction and the view farthest from it; 180 for views all around
    (their mean direction is too short to point anywhere)."""
    views = cameras.c2w[:, :3, 2]
    mean = views.mean(0)
    if np.linalg.norm(mean) < ALL_AROUND:
        return 180.0
    mean /= np.linalg.norm(mean)
    return float(np.degrees(np.arccos(np.clip(views @ mean, -1.0, 1.0)).max()))


def _facing(scene: SceneData) -> tuple[bool, str]:
    """Whether the views are forward-facing, and how that is known."""
    if scene.forward_facing is not None:
        return scene.forward_facing, "as the dataset states"
    angle = _max_view_angle(scene.cameras)
    if angle >= 180.0:
        return False, "views face every way"
    return (
        angle < FORWARD_FACING_DEG,
        f"views within {angle:.0f} deg of their mean, {FORWARD_FACING_DEG:.0f} the limit",
    )


SceneMode = Literal["bbox", "bbox+background", "cascade", "ndc"]
SCENE_MODES: tuple[str, ...] = ("bbox", "bbox+background", "cascade", "ndc")


def choose_mode(scene: SceneData, mode: str = "auto") -> SceneMode:
    """`mode`, or for "auto" (docs/method.md, "Placement"):

    - NDC when the views are forward-facing, near/far are known and the cameras stay near one pose;
    - a cascade (`cascade_reason`) when the box is the extent of SfM points (a real capture: what the
      cameras see runs from beside them to the far walls), when instant-ngp's aabb_scale says content
      reaches beyond the box, or when content beyond the box is seen from cameras outside it;
    - else a box, with a background model behind it when the data says content reaches beyond it.

    Forward-facing views with neither near/far nor a box are an error saying what to add: a box around
    the cameras' focus point means nothing when they all look one way (docs/method.md, "Grid")."""
    if mode in SCENE_MODES:
        return mode  # type: ignore[return-value]
    if mode != "auto":
        raise ValueError(f"unknown scene mode {mode!r}")
    forward, why = _facing(scene)
    if forward and scene.near_far is not None and _travel(scene) is None:
        return "ndc"
    if forward and scene.scene_box is None:
        raise InputError(
            scene.source,
            f"the views are forward-facing ({why}) but the data gives neither near/far depth bounds nor a "
            'box: add "near_far": [nearest, farthest scene depth] (or an "aabb") to it, or train with '
            "--scene-mode bbox",
        )
    if cascade_reason(scene):
        return "cascade"
    return "bbox+background" if content_beyond_box(scene) else "bbox"


def _travel(scene: SceneData) -> str | None:
    """Why the cameras do not stay near one pose (NDC's assumption), or None when they do."""
    if scene.near_far is None:
        return None
    positions = scene.cameras.c2w[:, :3, 3]
    travel = float(np.linalg.norm(positions - positions.mean(0), axis=1).max())
    near = scene.near_far[0]
    if travel <= NDC_TRAVEL * near:
        return None
    return (
        f"the cameras travel {travel:.3g} from their mean position, > {NDC_TRAVEL:g} x the near depth "
        f"{near:.3g}"
    )


def cascade_reason(scene: SceneData) -> str | None:
    """Why the scene wants a cascade of boxes reaching every camera, or None: the box is the extent of SfM
    points, or content beyond a stated box (instant-ngp's aabb_scale, a far depth bound) is seen from
    cameras outside it. A stated box that holds every camera keeps one box with the MSI beyond it
    (Plenoxels' practice for scenes whose box was drawn around the cameras)."""
    if scene.box_source == "points":
        return "the box is the extent of the sparse points: content from beside the cameras to the far walls"
    beyond = content_beyond_box(scene)
    if beyond and scene.scene_box is not None and not _cameras_inside(scene, _bbox_geometry(scene), 1):
        return f"content beyond the box ({beyond}) seen from cameras outside it"
    return None


def content_beyond_box(scene: SceneData) -> str | None:
    """Why the data says content lies beyond the box (instant-ngp's aabb_scale > 1 in
    `bounds_notes["beyond"]`, or a far depth bound past the box), or None."""
    return scene.bounds_notes.get("beyond") or _far_beyond_box(scene, _bbox_geometry(scene))


def placement_summary(scene: SceneData, mode: str = "auto") -> str:
    """One line saying what `setup_scene(scene, mode)` chooses and why, in the dataset's units."""
    chosen = choose_mode(scene, mode)
    forward, why = _facing(scene)
    notes = scene.bounds_notes
    asked = " (--scene-mode)" if mode != "auto" else ""
    facing = f"forward-facing: {'yes' if forward else 'no'} ({why})"
    if chosen == "ndc" and scene.near_far is not None:
        near, far = scene.near_far
        source = notes.get("near_far", "the dataset")
        return f"scene: NDC{asked}, near/far {near:.3g}-{far:.3g} from {source}; {facing}"
    travel = _travel(scene) if forward and scene.near_far is not None else None
    if travel:
        facing += f", but {travel}: not NDC"
    if chosen == "cascade":
        geom = cascade_geometry(scene)
        size = " x ".join(f"{2 * r:.3g}" for r in geom.radius)
        reason = cascade_reason(scene) or "asked for"
        return (
            f"scene: cascade of {geom.levels} boxes{asked} ({reason}), the finest {size} units around "
            f"{_subject_source(scene)}, each next twice as large, the outermost enclosing every camera and "
            f"what the data bounds; a multi-sphere background beyond it; {facing}"
        )
    geom = _bbox_geometry(scene)
    size = " x ".join(f"{2 * r:.3g}" for r in geom.radius)
    source = notes.get("box", "a box around the cameras' focus point (the data states no bounds)")
    kind = "bounding box + background" if chosen == "bbox+background" else "bounding box"
    line = f"scene: {kind}{asked} from {source}, {size} units; {facing}"
    if forward and scene.near_far is None:
        line += ", but no near/far for NDC"
    beyond = content_beyond_box(scene)
    if chosen == "bbox+background":
        why = f"content beyond the box ({beyond})" if beyond else "what lies beyond the box"
        line += f"; {why}: a multi-sphere background behind the box models it"
    elif beyond:
        line += (
            f"; content beyond the box ({beyond}): it renders as the background colour "
            "(--scene-mode bbox+background would model it)"
        )
    return line


def _far_beyond_box(scene: SceneData, geom: SceneGeometry) -> str | None:
    """A reason to think content lies beyond the box: the far depth bound exceeds every camera's
    distance to the box's farthest point."""
    if scene.near_far is None:
        return None
    reach = np.linalg.norm(scene.cameras.c2w[:, :3, 3] - np.asarray(geom.center), axis=1).max()
    reach += float(np.linalg.norm(geom.radius))
    far = scene.near_far[1]
    return (
        f"far depth {far:.3g} > {reach:.3g}, the farthest a camera sees of the box" if far > reach else None
    )


def setup_scene(
    scene: SceneData, mode: str = "auto", normalise: bool = True
) -> tuple[Cameras, SceneGeometry]:
    """Decide bbox (with or without a background model), cascade or NDC (`choose_mode`) and return the
    cameras in the grid's world frame plus the geometry. `normalise` False keeps a bounding box in the
    dataset's own units (a grid imported from svox2)."""
    mode = choose_mode(scene, mode)
    if mode == "ndc":
        return _ndc_setup(scene)
    if mode == "cascade":
        geom = cascade_geometry(scene)
    else:
        geom = _bbox_geometry(scene)
        geom.wants_background = mode == "bbox+background"
    if not normalise:
        return scene.cameras, geom
    geom = _normalised(geom)
    cams = scene.cameras
    return Cameras(geom.poses_to_world(cams.c2w), cams.intrinsics, cams.sizes), geom


def _bbox_geometry(scene: SceneData) -> SceneGeometry:
    if scene.scene_box is not None:
        lo, hi = np.asarray(scene.scene_box[0], float), np.asarray(scene.scene_box[1], float)
        center, radius = (lo + hi) / 2, (hi - lo) / 2
    else:
        center = _focus_point(scene.cameras)
        dist = np.linalg.norm(scene.cameras.c2w[:, :3, 3] - center, axis=1)
        radius = np.full(3, 0.5 * float(np.median(dist)))
    return SceneGeometry("bbox", tuple(center.tolist()), tuple(radius.tolist()), np.eye(4))


def cascade_geometry(scene: SceneData) -> SceneGeometry:
    """The cascade's finest box (`_subject_box`) and as many levels as enclose every camera (with
    `CAMERA_MARGIN`), the points' extent, and instant-ngp's aabb_scale when given; an MSI beyond."""
    center, radius = _subject_box(scene)
    reach = [scene.cameras.c2w[:, :3, 3]]
    margins = [CAMERA_MARGIN]
    if scene.scene_box is not None and scene.box_source == "points":
        reach.append(np.array(np.meshgrid(*zip(*scene.scene_box))).reshape(3, -1).T)  # the 8 corners
        margins.append(1.0)
    ratio = max(float((m * np.abs(p - center) / radius).max()) for p, m in zip(reach, margins, strict=True))
    levels = 1 + max(0, int(np.ceil(np.log2(max(ratio, 1.0)) - 1e-9)))
    if scene.aabb_scale is not None:
        levels = max(levels, 1 + int(np.ceil(np.log2(scene.aabb_scale) - 1e-9)))
    levels = min(levels, MAX_LEVELS)
    return SceneGeometry(
        "bbox",
        tuple(center.tolist()),
        tuple(radius.tolist()),
        np.eye(4),
        wants_background=True,
        levels=levels,
    )


def _converging(cameras: Cameras) -> np.ndarray | None:
    """The point the views' axes converge on, in front of most cameras (an object capture), or None
    (the cameras look every which way, as on a walk)."""
    views = cameras.c2w[:, :3, 2]
    system = sum(np.eye(3) - np.outer(d, d) for d in views) / len(views)
    if np.linalg.eigvalsh(system)[0] < SPREAD:
        return None  # (nearly) parallel views: no point they look at
    focus = _focus_point(cameras)
    to_focus = focus - cameras.c2w[:, :3, 3]
    dist = np.linalg.norm(to_focus, axis=1)
    miss = np.linalg.norm(np.cross(to_focus, views), axis=1)
    ahead = (to_focus * views).sum(1) > 0
    if np.median(miss) <= CONVERGING * np.median(dist) and ahead.mean() >= 0.9:
        return focus
    return None


def _subject_source(scene: SceneData) -> str:
    if scene.scene_box is not None and scene.box_source == "stated":
        return scene.bounds_notes.get("box", "the stated box")
    if _converging(scene.cameras) is not None:
        return "the point the cameras look at"
    return "the middle of the sparse points" if scene.scene_box is not None else "the cameras"


def _subject_box(scene: SceneData) -> tuple[np.ndarray, np.ndarray]:
    """(centre, half-sides) of the cascade's finest box: a stated box; else a cube around the point the
    views converge on, of half-side `SUBJECT` times their median distance to it, or less where the points
    end nearer on every axis; else (a walk) a cube of a quarter of the points' (or cameras') extent about
    its middle. A cube, so that every level grows alike in every direction."""
    if scene.scene_box is not None and scene.box_source == "stated":
        lo, hi = np.asarray(scene.scene_box[0], float), np.asarray(scene.scene_box[1], float)
        return (lo + hi) / 2, (hi - lo) / 2
    positions = scene.cameras.c2w[:, :3, 3]
    focus = _converging(scene.cameras)
    if focus is not None:
        half = SUBJECT * float(np.median(np.linalg.norm(positions - focus, axis=1)))
        if scene.scene_box is not None:
            lo, hi = np.asarray(scene.scene_box[0], float), np.asarray(scene.scene_box[1], float)
            extent = float(np.maximum(np.abs(lo - focus), np.abs(hi - focus)).max())
            half = min(half, extent)
        return focus, np.full(3, half)
    if scene.scene_box is not None:
        lo, hi = np.asarray(scene.scene_box[0], float), np.asarray(scene.scene_box[1], float)
    else:
        lo, hi = positions.min(0), positions.max(0)
    half = max(float((hi - lo).max()) / 4, 1e-6)
    return (lo + hi) / 2, np.full(3, half)


def _cameras_inside(scene: SceneData, geom: SceneGeometry, margin: float) -> bool:
    rel = np.abs(scene.cameras.c2w[:, :3, 3] - np.asarray(geom.center)) / np.asarray(geom.radius)
    return bool((margin * rel <= 1.0).all())


def _normalised(geom: SceneGeometry) -> SceneGeometry:
    """The same box (or cascade) moved to the origin and scaled to a finest largest half-side of 1."""
    scale = 1.0 / max(geom.radius)
    world_from_data = np.diag([scale, scale, scale, 1.0])
    world_from_data[:3, 3] = -scale * np.asarray(geom.center)
    radius = tuple(float(r * scale) for r in geom.radius)
    return SceneGeometry(
        "bbox",
        (0.0, 0.0, 0.0),
        radius,
        world_from_data,
        wants_background=geom.wants_background,
        levels=geom.levels,
    )


def _focus_point(cameras: Cameras) -> np.ndarray:
    """Least-squares point nearest to every camera's optical axis (the centre of an inward capture)."""
    origins = cameras.c2w[:, :3, 3]
    dirs = cameras.c2w[:, :3, 2]
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d in zip(origins, dirs):
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ o
    return np.linalg.lstsq(a, b, rcond=None)[0]


def _ndc_setup(scene: SceneData) -> tuple[Cameras, SceneGeometry]:
    if scene.near_far is None:
        raise InputError(
            scene.source, "NDC (forward-facing) mode needs near/far depth bounds, none were given"
        )
    if not scene.near_far[0] > 0:
        raise InputError(scene.source, f"NDC mode needs a positive near depth bound, got {scene.near_far[0]}")
    cams = scene.cameras
    # Average pose (LLFF recentring): centre = mean position, z = mean view direction, y = mean down.
    center = cams.c2w[:, :3, 3].mean(0)
    z = _normalise(cams.c2w[:, :3, 2].sum(0))
    y_down = cams.c2w[:, :3, 1].sum(0)
    x = _normalise(np.cross(y_down, z))
    y = np.cross(z, x)
    avg = np.eye(4)
    avg[:3, :3] = np.stack([x, y, z], axis=1)
    avg[:3, 3] = center
    scale = 1.0 / (0.75 * scene.near_far[0])
    world_from_data = np.diag([scale, scale, scale, 1.0]) @ np.linalg.inv(avg)
    geom = SceneGeometry("ndc", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), world_from_data)
    c2w = geom.poses_to_world(cams.c2w)
    fx, fy = cams.intrinsics[0, 0], cams.intrinsics[0, 1]
    w, h = cams.sizes[0]
    geom.ndc = NDCSpec(2.0 * fx / w, 2.0 * fy / h, 1.0)
    geom.radius = (1.0 + 2.0 * NDC_PADDING, 1.0 + 2.0 * NDC_PADDING * w / h, 1.0)
    return Cameras(c2w, cams.intrinsics, cams.sizes), geom


def _normalise(v: np.ndarray) -> np.ndarray:
    return v / (np.linalg.norm(v) + 1e-12)
