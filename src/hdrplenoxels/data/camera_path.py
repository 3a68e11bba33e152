"""nerfstudio's `camera_path.json`: read and write, with this package's exposure and white balance per frame.

The file is nerfstudio's: `camera_path` holds one entry per frame with `camera_to_world` (16 numbers,
row-major, OpenGL axes), `fov` (vertical, degrees) and `aspect`; `render_width`, `render_height`, `fps`
and `seconds` describe the video; `keyframes` are what an editor placed. Poses are in the dataset's own
frame (that of its transforms.json or COLMAP model). Each frame may carry an `hdrplenoxels` object with
`ev` (stops) and `wb` (three gains), which nerfstudio ignores; frames without one use EV 0 and unit gains.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hdrplenoxels.core.atomic import atomic_write_text
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.validate import check_pose, read_json
from hdrplenoxels.geometry.cameras import opencv_to_opengl, opengl_to_opencv


@dataclass
class PathFrame:
    """One frame: an OpenCV camera-to-world pose in the dataset's frame, its vertical field of view and
    the exposure and white balance to show it with."""

    c2w: np.ndarray
    fov_y_deg: float
    ev: float = 0.0
    wb: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass
class CameraPath:
    frames: list[PathFrame]
    width: int
    height: int
    fps: float
    keyframes: list[PathFrame] = field(default_factory=list)

    def intrinsics(self, frame: PathFrame) -> np.ndarray:
        """fx, fy, cx, cy of a frame at this path's resolution (square pixels, centred principal point)."""
        focal = 0.5 * self.height / math.tan(math.radians(frame.fov_y_deg) / 2.0)
        return np.array([focal, focal, self.width / 2.0, self.height / 2.0])


def _frame(entry: dict, where: str, path: Path) -> PathFrame:
    if not isinstance(entry, dict) or not isinstance(entry.get("hdrplenoxels") or {}, dict):
        raise InputError(path, f"{where}: expected an object with camera_to_world, fov (and hdrplenoxels)")
    try:
        matrix = entry.get("camera_to_world", entry.get("matrix"))
        if isinstance(matrix, str):  # nerfstudio's keyframes hold the matrix as a JSON string
            matrix = json.loads(matrix)
        c2w = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
        fov = float(entry["fov"])
        extra = entry.get("hdrplenoxels") or {}
        ev = float(extra.get("ev", 0.0))
        wb = tuple(float(g) for g in extra.get("wb", (1.0, 1.0, 1.0)))
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"{where}: needs camera_to_world (16 numbers) and fov ({e})") from None
    check_pose(path, f"{where}: ", c2w)
    if not 0.0 < fov < 180.0:
        raise InputError(path, f"{where}: fov must be in (0, 180) degrees, got {fov:g}")
    if len(wb) != 3 or not all(g > 0 and math.isfinite(g) for g in wb) or not math.isfinite(ev):
        raise InputError(path, f"{where}: hdrplenoxels.ev must be finite and wb three positive gains")
    return PathFrame(opengl_to_opencv(c2w), fov, ev, wb)


def read_camera_path(path: Path) -> CameraPath:
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("camera_path"), list) or not data["camera_path"]:
        raise InputError(
            path, "no camera_path: expected nerfstudio's camera_path.json with one entry per frame"
        )
    if not isinstance(data.get("keyframes") or [], list):
        raise InputError(path, "keyframes must be a list (nerfstudio's camera_path.json)")
    frames = [_frame(e, f"camera_path[{i}]", path) for i, e in enumerate(data["camera_path"])]
    keyframes = [_frame(e, f"keyframes[{i}]", path) for i, e in enumerate(data.get("keyframes") or [])]
    try:
        width, height = int(data["render_width"]), int(data["render_height"])
        fps = float(data.get("fps", 24))
    except (KeyError, TypeError, ValueError):
        raise InputError(path, "needs render_width and render_height (pixels)") from None
    if not (0 < width <= 16384 and 0 < height <= 16384 and 0 < fps <= 1000):
        raise InputError(path, f"render size {width}x{height} or fps {fps} out of range")
    return CameraPath(frames, width, height, fps, keyframes)


def _entry(frame: PathFrame, aspect: float) -> dict:
    return {
        "camera_to_world": opencv_to_opengl(frame.c2w).reshape(-1).tolist(),
        "fov": frame.fov_y_deg,
        "aspect": aspect,
        "hdrplenoxels": {"ev": frame.ev, "wb": list(frame.wb)},
    }


def write_camera_path(path: Path, camera_path: CameraPath) -> Path:
    """Write nerfstudio's layout (atomically); keyframes get nerfstudio's string-matrix form."""
    aspect = camera_path.width / camera_path.height
    keyframes = []
    for frame in camera_path.keyframes:
        entry = _entry(frame, aspect)
        keyframes.append({"matrix": json.dumps(entry.pop("camera_to_world")), **entry})
    data = {
        "camera_type": "perspective",
        "render_width": camera_path.width,
        "render_height": camera_path.height,
        "fps": camera_path.fps,
        "seconds": len(camera_path.frames) / camera_path.fps,
        "keyframes": keyframes,
        "camera_path": [_entry(f, aspect) for f in camera_path.frames],
    }
    return atomic_write_text(path, json.dumps(data, indent=1))
