"""How close a registration's cameras are to a synthetic capture's true ones, up to the similarity
transform (scale, rotation, translation) that structure from motion leaves free."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from hdrplenoxels.data.scene import SceneData


@dataclass
class RegistrationErrors:
    registered: int
    of: int
    rotation_deg_median: float  # camera orientations, after the best rotation of the whole model
    rotation_deg_max: float
    position_max: float  # camera centres after the best similarity, as a fraction of the truth's extent
    focal_max: float  # the largest |focal / true focal - 1|

    def to_dict(self) -> dict:
        return asdict(self)


def cameras_by_view(scene: SceneData) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """A scene's cameras by view name (its file's stem, which a synthetic capture and `process` share):
    camera-to-world and focal length, as `registration_errors` takes them."""
    stems = [Path(n).stem for n in scene.names]
    return dict(zip(stems, scene.cameras.c2w)), dict(zip(stems, scene.cameras.intrinsics[:, 0]))


def registration_errors(
    found_c2w: dict[str, np.ndarray], found_focal: dict[str, float], truth_c2w: dict[str, np.ndarray],
    truth_focal: dict[str, float],
) -> RegistrationErrors:  # fmt: skip
    """Errors of the registered views (`found_*`, by view name; OpenCV camera-to-world 3x4 or 4x4) against
    the truth of every view (`truth_*`). Needs at least 3 registered views."""
    names = sorted(set(found_c2w) & set(truth_c2w))
    found = np.stack([found_c2w[n][:3] for n in names])
    truth = np.stack([truth_c2w[n][:3] for n in names])
    rot, scale, shift = _alignment(found, truth)
    centres = scale * found[:, :, 3] @ rot.T + shift
    extent = _extent(np.stack([m[:3, 3] for m in truth_c2w.values()]))
    angles = _angles_deg(rot @ found[:, :, :3], truth[:, :, :3])
    focal = [abs(found_focal[n] / truth_focal[n] - 1.0) for n in names]
    return RegistrationErrors(
        registered=len(names),
        of=len(truth_c2w),
        rotation_deg_median=float(np.median(angles)),
        rotation_deg_max=float(angles.max()),
        position_max=float(np.linalg.norm(centres - truth[:, :, 3], axis=1).max() / extent),
        focal_max=float(max(focal)),
    )


@dataclass
class Agreement:
    """How far apart two registrations of the same photos put their common cameras, after the rotation,
    scale and shift between the two models."""

    common: int  # photos both registered
    rotation_deg_max: float  # the largest angle between a camera's two orientations
    position_max: float  # the largest distance between its two centres, over the second's extent


def model_agreement(a_c2w: dict[str, np.ndarray], b_c2w: dict[str, np.ndarray]) -> Agreement | None:
    """`Agreement` of two models' camera-to-world matrices (by photo name), aligned by `_alignment`; None
    under 3 common photos."""
    names = sorted(set(a_c2w) & set(b_c2w))
    if len(names) < 3:
        return None
    a = np.stack([a_c2w[n][:3] for n in names])
    b = np.stack([b_c2w[n][:3] for n in names])
    rot, scale, shift = _alignment(a, b)
    angles = _angles_deg(rot @ a[:, :, :3], b[:, :, :3])
    distances = np.linalg.norm(scale * a[:, :, 3] @ rot.T + shift - b[:, :, 3], axis=1)
    distances /= max(_extent(b[:, :, 3]), 1e-12)
    return Agreement(len(names), float(angles.max()), float(distances.max()))


def _alignment(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(R, s, t) taking cameras `a` onto cameras `b` ((N, 3, 4) camera-to-world each): the rotation that
    best turns `a`'s orientations onto `b`'s, then the scale and shift of the centres. The orientations fix
    the rotation even where the centres cannot: on one line (a straight walk), or in a plane whose
    outline is nearly symmetric (a walk round a corner), where fitting the centres alone can turn a right
    model over."""
    u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", b[:, :, :3], a[:, :, :3]))  # R with R a ~ b
    rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    centres_a = a[:, :, 3] @ rot.T
    da, db = centres_a - centres_a.mean(0), b[:, :, 3] - b[:, :, 3].mean(0)
    scale = float((da * db).sum() / max(float((da**2).sum()), 1e-12))
    return rot, scale, b[:, :, 3].mean(0) - scale * centres_a.mean(0)


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angle in degrees of each rotation between orientations `a[i]` and `b[i]` ((N, 3, 3) each)."""
    cos = (np.einsum("nij,nij->n", a, b) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _extent(points: np.ndarray) -> float:
    """The largest distance between two of `points` (N, 3)."""
    return float(max(np.linalg.norm(points - p, axis=1).max() for p in points))
