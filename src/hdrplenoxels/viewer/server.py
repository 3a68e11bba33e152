"""The viewer's server: viser serves its bundled web client; every browser camera is rendered here with the
package's renderer and pushed as the scene's background image.

Rendering is progressive: while a camera moves, each new pose is rendered small (`preview_long_side`);
once it has rested for `rest_seconds`, at full size (capped at `full_long_side`). A change of exposure,
white balance, response or display mode only re-displays the last radiance image: no new render.
One lock serialises renders (the CPU kernels already use every core).
"""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from hdrplenoxels.core.atomic import atomic_write_text
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.camera_path import CameraPath, PathFrame, read_camera_path, write_camera_path
from hdrplenoxels.data.image_io import write_exr, write_png
from hdrplenoxels.geometry.cameras import opencv_to_opengl
from hdrplenoxels.geometry.paths import interpolate, mean_up
from hdrplenoxels.render import Backend
from hdrplenoxels.train.model import Model
from hdrplenoxels.viewer.display import (
    GEOMETRY_MODES,
    ViewState,
    depth_opacity_view,
    display_image,
    display_modes,
    geometry_image,
    histogram,
    legend,
    linear_exposed,
    response_choices,
)


@dataclass
class ViewerConfig:
    host: str = "127.0.0.1"
    port: int = 8765  # 0: any free port (tests)
    preview_long_side: int = 160
    full_long_side: int = 1024
    rest_seconds: float = 0.25
    backend: Backend = "warp"
    thumbnail_long_side: int = 48
    show_cameras: bool = True  # training cameras as frustums (also a checkbox in the viewer)


def check_port_free(host: str, port: int) -> None:
    """viser moves on to the next port by itself; a user who named a port should hear it is taken."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        try:
            probe.bind((host, port))
        except OSError as e:
            raise InputError(None, f"--port {port}: cannot listen on {host}:{port} ({e.strerror})") from None


def camera_matrix(position, wxyz) -> np.ndarray:
    """OpenCV camera-to-world from viser's camera (viser uses OpenCV axes: +z forward, +y down)."""
    import viser.transforms as tf

    c2w = np.eye(4)
    c2w[:3, :3] = tf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    c2w[:3, 3] = np.asarray(position, dtype=np.float64)
    return c2w


def intrinsics_for(fov_y: float, width: int, height: int) -> np.ndarray:
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    return np.array([focal, focal, width / 2.0, height / 2.0])


def fit_size(aspect: float, long_side: int) -> tuple[int, int]:
    if aspect >= 1.0:
        return long_side, max(1, round(long_side / aspect))
    return max(1, round(long_side * aspect)), long_side


@dataclass(frozen=True)
class Shown:
    c2w: np.ndarray
    fov: float
    radiance: torch.Tensor
    picture: np.ndarray
    state: ViewState
    at: float  # time.monotonic() when sent


@dataclass
class ClientView:
    """What one browser shows: its latest camera, what was rendered of it, and the render thread."""

    client: object
    pose_version: int = 0
    moved_at: float = 0.0
    preview_version: int = -1
    full_version: int = -1
    redisplay: bool = False
    radiance: torch.Tensor | None = None
    camera: tuple[np.ndarray, float, float] | None = None  # c2w, vertical fov, aspect
    last_picture: np.ndarray | None = None
    shown: Shown | None = None  # the last picture with what it was made of (for scripts and tests)
    wake: threading.Event = field(default_factory=threading.Event)


class Viewer:
    def __init__(self, model: Model, run: Path, cfg: ViewerConfig = ViewerConfig()):
        self.model, self.run, self.cfg = model, Path(run), cfg
        self.state = ViewState(response=response_choices(model)[0])
        self.render_lock = threading.Lock()
        self.clients: dict[int, ClientView] = {}
        self.keyframes: list[PathFrame] = []  # world frame; written in the dataset's frame
        self.running = False
        self.server = None
        self.saved: list[Path] = []
        self.frustums: list = []
        self.hidden: dict[int, int] = {}  # client id -> the training camera it sits in (frustum hidden)
        self.spacing = 1.0

    # ----------------------------------------------------------------------------- life cycle
    def start(self) -> int:
        import viser

        check_port_free(self.cfg.host, self.cfg.port)
        self.server = viser.ViserServer(host=self.cfg.host, port=self.cfg.port, verbose=False)
        self.running = True
        cams = self.model.cameras
        self.server.scene.set_up_direction(tuple(mean_up(cams.c2w)))
        self._add_gui()
        self._add_frustums()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        return self.server.get_port()

    def stop(self) -> None:
        self.running = False
        for view in list(self.clients.values()):
            view.wake.set()
        if self.server is not None:
            self.server.stop()

    # ----------------------------------------------------------------------------- rendering
    def _render(self, c2w: np.ndarray, fov: float, size: tuple[int, int]) -> torch.Tensor:
        with self.render_lock:
            return self.model.render_view(c2w, intrinsics_for(fov, *size), size, self.cfg.backend).cpu()

    def picture(self, c2w: np.ndarray, fov: float, radiance: torch.Tensor) -> np.ndarray:
        """What the current display mode shows of a camera whose radiance image is `radiance`."""
        if self.state.mode not in GEOMETRY_MODES:
            return display_image(self.model, radiance, self.state)
        h, w = radiance.shape[:2]  # depth and opacity: rendered for the same camera and size
        with self.render_lock:
            depth, opacity = depth_opacity_view(self.model, c2w, intrinsics_for(fov, w, h), (w, h))
        return geometry_image(depth, opacity, self.state.mode)

    def _show(self, view: ClientView, radiance: torch.Tensor) -> None:
        c2w, fov, _ = view.camera
        picture = self.picture(c2w, fov, radiance)
        if not self.running or view.client.client_id not in self.clients:
            return  # stopped or gone while rendering: nobody to show it to
        view.last_picture = picture
        view.shown = Shown(c2w, fov, radiance, picture, replace(self.state), time.monotonic())
        view.client.scene.set_background_image(picture, format="jpeg", jpeg_quality=92)
        if self._histogram is not None:
            self._histogram.image = histogram(linear_exposed(self.model, radiance, self.state))

    def _loop(self, view: ClientView) -> None:
        while self.running and view.client.client_id in self.clients:
            view.wake.wait(timeout=self.cfg.rest_seconds / 2)
            view.wake.clear()
            if view.camera is None:
                continue
            c2w, fov, aspect = view.camera
            version = view.pose_version
            if view.preview_version != version:
                size = fit_size(aspect, self.cfg.preview_long_side)
                self._show(view, self._render(c2w, fov, size))
                view.preview_version = version
            elif view.full_version != version and time.monotonic() - view.moved_at >= self.cfg.rest_seconds:
                view.radiance = self._render(c2w, fov, fit_size(aspect, self.cfg.full_long_side))
                view.full_version, view.redisplay = version, False
                self._show(view, view.radiance)
            elif view.redisplay and view.radiance is not None:
                view.redisplay = False
                self._show(view, view.radiance)

    def _camera_moved(self, view: ClientView) -> None:
        cam = view.client.camera
        width, height = max(cam.image_width, 1), max(cam.image_height, 1)
        view.camera = (camera_matrix(cam.position, cam.wxyz), float(cam.fov), width / height)
        inside = self.hidden.get(view.client.client_id)
        if inside is not None:
            gap = np.linalg.norm(view.camera[0][:3, 3] - self.model.cameras.c2w[inside][:3, 3])
            if gap > 0.5 * self.spacing:  # left the training camera: its frustum may show again
                self.frustums[self.hidden.pop(view.client.client_id)].visible = self._cameras_on.value
        view.pose_version += 1
        view.moved_at = time.monotonic()
        view.wake.set()

    def _connect(self, client) -> None:
        view = ClientView(client)
        self.clients[client.client_id] = view
        client.camera.on_update(lambda _cam: self._camera_moved(view))
        threading.Thread(target=self._start_client, args=(view,), daemon=True).start()

    def _start_client(self, view: ClientView) -> None:
        """Once the browser has reported its own camera (which would otherwise overwrite ours), move it to
        the first training view (whose picture then looks like its photo), then render for it until it
        leaves."""
        deadline = time.monotonic() + 30.0
        while view.client.camera.update_timestamp == 0.0 and time.monotonic() < deadline and self.running:
            time.sleep(0.02)
        first = self.model.train_ids[0] if self.model.train_ids else 0
        if self.model.tonemapper is not None:
            self.adopt_view(view.client, first)  # through that view's learned tone
        else:
            self._move_to_view(view.client, first)
        self._loop(view)

    def _disconnect(self, client) -> None:
        view = self.clients.pop(client.client_id, None)
        if view is not None:
            view.wake.set()

    def _controls_changed(self) -> None:
        for view in self.clients.values():
            view.redisplay = True
            view.wake.set()

    # ----------------------------------------------------------------------------- cameras
    def _move_to_view(self, client, i: int) -> None:
        import viser.transforms as tf

        cams = self.model.cameras
        c2w = cams.c2w[i]
        w, h = cams.size(i)
        if self.frustums:  # a camera inside frustum i would see its thumbnail, not the scene
            previous = self.hidden.pop(client.client_id, None)
            if previous is not None:
                self.frustums[previous].visible = self._cameras_on.value
            self.frustums[i].visible = False
            self.hidden[client.client_id] = i
        client.camera.fov = 2.0 * math.atan(0.5 * h / cams.intrinsics[i][1])
        client.camera.wxyz = tf.SO3.from_matrix(c2w[:3, :3]).wxyz
        client.camera.position = c2w[:3, 3]
        client.camera.look_at = c2w[:3, 3] + c2w[:3, 2]

    def adopt_view(self, client, i: int) -> None:
        """Fly to training view `i` and show it through that image's learned tone."""
        self._move_to_view(client, i)
        if self.model.tonemapper is not None:
            self.state.adopted = i
            self._status.content = f"showing view {i} ({self.model.names[i]}) through its learned tone"
        self._controls_changed()

    def _add_frustums(self) -> None:
        import viser.transforms as tf

        cams = self.model.cameras
        positions = cams.c2w[:, :3, 3]
        gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1) + np.diag(
            np.full(len(cams), np.inf)
        )
        self.spacing = float(np.median(gaps.min(1))) if len(cams) > 1 else 1.0  # frustums must not overlap
        for i in range(len(cams)):
            w, h = cams.size(i)
            tw, th = fit_size(w / h, self.cfg.thumbnail_long_side)
            k = cams.intrinsics_at(i, (tw, th))
            with self.render_lock:
                radiance = self.model.render_view(cams.c2w[i], k, (tw, th), self.cfg.backend)
            thumb = (self.model.to_ldr(radiance, i).cpu().numpy() * 255 + 0.5).astype(np.uint8)
            frustum = self.server.scene.add_camera_frustum(
                f"/training/{i:04d}",
                fov=2.0 * math.atan(0.5 * h / cams.intrinsics[i][1]),
                aspect=w / h,
                scale=0.3 * max(self.spacing, 1e-3),
                thickness=1.5,
                thickness_units="screen",
                wxyz=tf.SO3.from_matrix(cams.c2w[i][:3, :3]).wxyz,
                position=cams.c2w[i][:3, 3],
                image=thumb,
                color=(230, 140, 20) if i in self.model.test_ids else (40, 90, 200),
                visible=self.cfg.show_cameras,
            )
            frustum.on_click(lambda event, i=i: self.adopt_view(event.client, i))
            self.frustums.append(frustum)

    # ----------------------------------------------------------------------------- controls
    def _add_gui(self) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**{self.run.name}**: {len(self.model.names)} views, step {self.model.step}")
        self._ev = gui.add_slider("EV (stops)", min=-8.0, max=8.0, step=0.1, initial_value=0.0)
        self._auto = None  # a model trained before the tone controller has no auto exposure
        if self.model.controller is not None:
            self._auto = gui.add_checkbox("auto exposure (EV relative)", initial_value=self.state.auto)
        self._wb = [gui.add_slider(f"WB {c}", min=0.25, max=4.0, step=0.01, initial_value=1.0) for c in "RGB"]
        self._response = gui.add_dropdown(
            "response", response_choices(self.model), initial_value=self.state.response
        )
        self._mode = gui.add_dropdown("display", display_modes(self.model), initial_value=self.state.mode)
        lo, hi = self.state.false_colour_stops
        self._legend = gui.add_image(
            legend((lo, hi)), label=f"false colour: {lo:+g} (blue) to {hi:+g} (red) stops"
        )
        self._histogram = gui.add_image(
            np.zeros((64, 192, 3), np.uint8), label="log2 luminance, -16 to +8 stops"
        )
        for handle in (self._ev, *self._wb, self._response, self._mode, self._auto):
            if handle is not None:
                handle.on_update(lambda _event: self._read_controls())
        self._cameras_on = gui.add_checkbox("training cameras", initial_value=self.cfg.show_cameras)
        self._cameras_on.on_update(lambda _event: self._show_cameras(self._cameras_on.value))
        save = gui.add_button("Save view (PNG, EXR, pose)")
        save.on_click(lambda event: self.save_view(event.client))
        with gui.add_folder("Camera path"):
            self._frames = gui.add_number("frames", initial_value=120, min=2, max=10000, step=1)
            add = gui.add_button("Add keyframe (camera, EV, WB)")
            add.on_click(lambda event: self.add_keyframe(event.client))
            clear = gui.add_button("Clear keyframes")
            clear.on_click(lambda _event: self.clear_keyframes())
            write = gui.add_button("Save camera_path.json")
            write.on_click(lambda _event: self.save_camera_path())
            load = gui.add_button("Load camera_path.json")
            load.on_click(lambda _event: self.load_camera_path())
        self._status = gui.add_markdown("")

    def _show_cameras(self, on: bool) -> None:
        hidden = set(self.hidden.values())
        for i, frustum in enumerate(self.frustums):
            frustum.visible = on and i not in hidden

    def _read_controls(self) -> None:
        self.state.ev = float(self._ev.value)
        self.state.wb = tuple(float(s.value) for s in self._wb)
        self.state.response = str(self._response.value)
        self.state.mode = str(self._mode.value)
        self.state.auto = self._auto is not None and bool(self._auto.value)
        self.state.adopted = None
        self._controls_changed()

    def set_ev(self, ev: float) -> None:
        """As moving the EV slider does (for scripts and tests)."""
        self._ev.value = ev
        self._read_controls()

    # ----------------------------------------------------------------------------- outputs
    def save_view(self, client) -> Path:
        """PNG (as displayed) and float EXR (linear radiance) of this client's camera at full size, and its
        pose (dataset frame, OpenGL and OpenCV) with intrinsics as JSON, under RUN/views/."""
        view = self.clients[client.client_id]
        c2w, fov, aspect = view.camera
        size = fit_size(aspect, self.cfg.full_long_side)
        radiance = self._render(c2w, fov, size)
        folder = self.run / "views"
        stem = folder / f"view_{len(list(folder.glob('view_*.json'))) if folder.exists() else 0:03d}"
        write_png(stem.with_suffix(".png"), self.picture(c2w, fov, radiance) / 255.0)
        write_exr(stem.with_suffix(".exr"), self.model.hdr(radiance).cpu().numpy())
        pose = self.model.geometry.poses_to_data(c2w)
        record = {
            "camera_to_world_opengl": opencv_to_opengl(pose).tolist(),
            "camera_to_world_opencv": pose.tolist(),
            "intrinsics": intrinsics_for(fov, *size).tolist(),
            "size": list(size),
            "ev": self.state.ev,
            "wb": list(self.state.wb),
            "response": self.state.response,
            "display": self.state.mode,
        }
        atomic_write_text(stem.with_suffix(".json"), json.dumps(record, indent=1))
        self._status.content = f"saved {stem}.png, .exr and .json"
        self.saved.append(stem)
        return stem

    def add_keyframe(self, client) -> None:
        c2w, fov, _ = self.clients[client.client_id].camera
        self.keyframes.append(PathFrame(c2w, math.degrees(fov), self.state.ev, self.state.wb))
        self._status.content = f"{len(self.keyframes)} keyframe(s)"

    def clear_keyframes(self) -> None:
        self.keyframes.clear()
        self._status.content = "keyframes cleared"

    def camera_path(self, frames: int, size: tuple[int, int] = (800, 600), fps: float = 30.0) -> CameraPath:
        """The keyframes as nerfstudio's camera_path.json (dataset frame): poses slerped, EV, white balance
        and field of view interpolated linearly."""
        if len(self.keyframes) < 2:
            raise InputError(None, "a camera path needs at least two keyframes")
        poses = interpolate(np.stack([k.c2w for k in self.keyframes]), frames)
        u = np.linspace(0.0, len(self.keyframes) - 1.0, frames)
        idx = np.arange(len(self.keyframes))

        def lerp(values) -> np.ndarray:
            return np.interp(u, idx, np.asarray(values, dtype=np.float64))

        fov, ev = lerp([k.fov_y_deg for k in self.keyframes]), lerp([k.ev for k in self.keyframes])
        wb = np.stack([lerp([k.wb[c] for k in self.keyframes]) for c in range(3)], 1)
        data_poses = self.model.geometry.poses_to_data(poses)
        path = [
            PathFrame(p, float(f), float(e), tuple(map(float, g)))
            for p, f, e, g in zip(data_poses, fov, ev, wb)
        ]
        keys = [
            PathFrame(self.model.geometry.poses_to_data(k.c2w), k.fov_y_deg, k.ev, k.wb)
            for k in self.keyframes
        ]
        return CameraPath(path, size[0], size[1], fps, keys)

    def save_camera_path(self) -> Path | None:
        try:
            path = write_camera_path(self.run / "camera_path.json", self.camera_path(int(self._frames.value)))
        except InputError as e:
            self._status.content = str(e)
            return None
        self._status.content = (
            f"saved {path} (render it: hdrplenoxels render RUN --video out.mp4 --camera-path {path})"
        )
        return path

    def load_camera_path(self) -> None:
        try:
            loaded = read_camera_path(self.run / "camera_path.json")
        except InputError as e:
            self._status.content = str(e)
            return
        frames = loaded.keyframes or loaded.frames
        world = self.model.geometry.poses_to_world(np.stack([f.c2w for f in frames]))
        self.keyframes = [PathFrame(p, f.fov_y_deg, f.ev, f.wb) for p, f in zip(world, frames)]
        self._status.content = (
            f"loaded {len(self.keyframes)} keyframe(s) from {self.run / 'camera_path.json'}"
        )
