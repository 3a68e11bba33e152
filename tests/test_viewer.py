"""The HDR viewer: its pictures for every control (without a browser), the `view` command's refusals, and
the real thing in headless Chromium: first frame, the picture matching a direct render, the EV control."""

from __future__ import annotations

import io
import math
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.viewer.display import (
    STANDARD_RESPONSES,
    ViewState,
    display_image,
    false_colour,
    histogram,
    legend,
    linear_exposed,
    response_choices,
    turbo,
)
from hdrplenoxels.viewer.server import Viewer, ViewerConfig, intrinsics_for


@pytest.fixture(scope="module")
def run(tonemapped_run) -> Path:
    return tonemapped_run


@pytest.fixture(scope="module")
def model(tonemapped_run) -> Model:
    return Model.load(tonemapped_run / MODEL_FILE)


def test_each_control_acts_on_the_picture_as_the_tone_mapper_says(model):
    radiance = model.render_camera(model.test_ids[0])
    base = ViewState()
    linear = linear_exposed(model, radiance, base)
    assert torch.allclose(linear_exposed(model, radiance, ViewState(ev=1.0)), 2 * linear)
    red = linear_exposed(model, radiance, ViewState(wb=(2.0, 1.0, 1.0)))
    assert torch.allclose(red[..., 0], 2 * linear[..., 0]) and torch.equal(red[..., 1:], linear[..., 1:])
    # Tone-mapped with the reference's learned curve is exactly the controlled render of the model.
    expected = (model.to_ldr_controlled(radiance).clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    assert np.array_equal(display_image(model, radiance, base), expected)
    adopted = display_image(model, radiance, ViewState(adopted=3))
    assert np.array_equal(adopted, (model.to_ldr(radiance, 3) * 255 + 0.5).to(torch.uint8).numpy())
    assert "view 3" in response_choices(model) and "filmic" in response_choices(model)
    for mode in ("tone-mapped", "linear HDR", "false colour"):
        for response in ("reference", "view 1", *STANDARD_RESPONSES):
            picture = display_image(model, radiance, ViewState(response=response, mode=mode))
            assert picture.shape == (*radiance.shape[:2], 3) and picture.dtype == np.uint8


def test_depth_and_opacity_displays(model):
    """Opacity is grey from the march's transmittance; depth is coloured only where something is hit."""
    from hdrplenoxels.viewer.display import depth_opacity_view, geometry_image

    i = model.test_ids[0]
    cams = model.cameras
    depth, opacity = depth_opacity_view(model, cams.c2w[i], cams.intrinsics[i], cams.size(i))
    assert depth.shape == opacity.shape == (cams.size(i)[1], cams.size(i)[0])
    assert opacity.min() >= 0 and opacity.max() <= 1 and (opacity > 0.5).any() and (opacity < 0.5).any()
    grey = geometry_image(depth, opacity, "opacity")
    assert np.array_equal(grey[..., 0], (opacity * 255 + 0.5).to(torch.uint8).numpy())
    coloured = geometry_image(depth, opacity, "depth")
    assert (coloured[(opacity <= 0.5).numpy()] == 0).all() and coloured[(opacity > 0.5).numpy()].any()


def test_standard_responses_are_monotone_curves_into_the_unit_range():
    x = torch.linspace(0.0, 20.0, 2001)
    for name, curve in STANDARD_RESPONSES.items():
        y = curve(x)
        assert y.min() >= 0 and y.max() <= 1 and (y[1:] >= y[:-1] - 1e-7).all(), name
    assert STANDARD_RESPONSES["filmic"](torch.tensor(4.0)) < 1.0  # a shoulder, not a clip


def test_false_colour_and_histogram_place_luminance_in_stops():
    stops = (-8.0, 4.0)
    linear = torch.full((2, 2, 3), 2.0**-2)  # log2 luminance -2: half-way along (-8, 4)
    assert np.array_equal(false_colour(linear, stops)[0, 0], turbo(np.array([0.5]))[0])
    bar = legend(stops, width=100)
    assert np.array_equal(bar[0, 0], turbo(np.array([0.0]))[0]) and np.array_equal(
        bar[0, -1], turbo(np.array([1.0]))[0]
    )
    picture = histogram(linear, stops=(-16.0, 8.0), bins=96)
    filled = (picture[-1] != 24).any(-1).nonzero()[0]  # the one bar reaches the bottom row
    assert filled.min() // 2 == filled.max() // 2 == int((-2 + 16) / 24 * 96)


def test_view_refuses_a_folder_without_a_model_and_a_port_in_use(tmp_path, run):
    proc = subprocess.run(
        [sys.executable, "-m", "hdrplenoxels", "view", str(tmp_path)], capture_output=True, text=True
    )
    assert proc.returncode == 2 and "no trained model" in proc.stderr and "Traceback" not in proc.stderr
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = subprocess.run(
            [sys.executable, "-m", "hdrplenoxels", "view", str(run), "--port", str(port)],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert proc.returncode == 2 and f"--port {port}" in proc.stderr and "Traceback" not in proc.stderr


def _browser():
    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    webdriver = pytest.importorskip("selenium.webdriver")
    if chromium is None or driver is None:
        pytest.skip("needs Debian's chromium and chromium-driver (make test installs them as root)")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--window-size=1000,700"):  # fmt: skip
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(driver), options=options)


def _canvas_crop(browser) -> np.ndarray:
    """The 3D canvas's pixels in a screenshot (the viewer's picture is its background)."""
    box = browser.execute_script(
        "const r = document.querySelector('canvas').getBoundingClientRect();"
        "return [r.left, r.top, r.width, r.height, window.devicePixelRatio];"
    )
    shot = np.asarray(Image.open(io.BytesIO(browser.get_screenshot_as_png())).convert("RGB"))
    x, y, w, h, ratio = (float(v) for v in box)
    return shot[int(y * ratio) : int((y + h) * ratio), int(x * ratio) : int((x + w) * ratio)]


CLEAR = (slice(0.3, 0.95), slice(0.05, 0.6))  # of the canvas: below the notice, left of the control panel


def _clear_part(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    rows, cols = CLEAR
    return image[int(rows.start * h) : int(rows.stop * h), int(cols.start * w) : int(cols.stop * w)]


def _wait(condition, seconds: float = 60.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.2)


def test_viewer_in_a_real_browser_shows_the_render_and_follows_the_ev_control(model, run, tmp_path):
    browser = _browser()
    # Training-camera frustums off: in this tiny scene the neighbours' thumbnails would cover the picture.
    viewer = Viewer(
        model, run, ViewerConfig(port=0, full_long_side=256, rest_seconds=0.2, show_cameras=False)
    )
    try:
        port = viewer.start()
        browser.get(f"http://127.0.0.1:{port}/")
        _wait(lambda: len(viewer.clients) == 1)
        (view,) = viewer.clients.values()

        def settled(ev: float):
            """The last picture at full size for a camera that has not moved for a second, at `ev`."""
            shown = view.shown
            full = view.full_version == view.pose_version and time.monotonic() - view.moved_at > 1.0
            ok = shown is not None and full and shown.state.ev == ev and shown.at > view.moved_at
            return shown if ok and shown.radiance.shape[1] == viewer.cfg.full_long_side else None

        _wait(lambda: settled(0.0))
        first = settled(0.0)
        # It opens at the first training view, through its learned tone: the picture looks like the photo.
        assert first.state.adopted == model.train_ids[0]
        assert np.allclose(first.c2w, model.cameras.c2w[model.train_ids[0]], atol=1e-3)
        h, w = first.picture.shape[:2]
        assert math.isclose(w / h, view.camera[2], rel_tol=0.02)
        # The picture sent is the package's own render of the browser's camera, through the controls.
        direct = model.render_view(first.c2w, intrinsics_for(first.fov, w, h), (w, h))
        assert torch.equal(direct, first.radiance)
        assert np.array_equal(first.picture, display_image(model, direct, first.state))
        assert first.picture.std() > 10  # not blank

        def shown_matches(expected: np.ndarray) -> bool:
            """`expected` (scaled) is on the canvas where no control covers it, up to JPEG loss."""
            crop = _canvas_crop(browser)
            scaled = np.asarray(Image.fromarray(expected).resize((crop.shape[1], crop.shape[0])))
            shown, wanted = _clear_part(crop).astype(float), _clear_part(scaled).astype(float)
            return float(np.abs(shown - wanted).mean()) < 15.0  # a wrong or blank picture: 50+

        _wait(lambda: shown_matches(view.last_picture))  # the client fades the first frame in
        before = _clear_part(_canvas_crop(browser)).mean()
        viewer.set_ev(2.0)
        _wait(lambda: settled(2.0))
        brighter = settled(2.0)
        assert np.array_equal(brighter.picture, display_image(model, brighter.radiance, brighter.state))
        if np.allclose(brighter.c2w, first.c2w):
            assert torch.equal(brighter.radiance, first.radiance)  # no new render for a control change
        assert brighter.picture.mean() > first.picture.mean() + 10
        _wait(lambda: shown_matches(view.last_picture))
        assert _clear_part(_canvas_crop(browser)).mean() > before + 10
        assert len(viewer.frustums) == len(model.names) and not any(f.visible for f in viewer.frustums)
        viewer.adopt_view(view.client, 3)  # as a click on frustum 3 does: its learned tone is shown
        _wait(lambda: viewer.state.adopted == 3 and view.full_version == view.pose_version)
        _wait(lambda: (s := view.shown) is not None and s.state.adopted == 3)
        assert np.array_equal(view.shown.picture, display_image(model, view.shown.radiance, view.shown.state))
        stem = viewer.save_view(view.client)
        for suffix in (".png", ".exr", ".json"):
            assert stem.with_suffix(suffix).exists()
    finally:
        browser.quit()
        viewer.stop()


def test_keyframes_become_nerfstudios_camera_path(model, run):
    from hdrplenoxels.data.camera_path import PathFrame, read_camera_path

    viewer = Viewer(model, run)
    cams = model.cameras
    viewer.keyframes = [PathFrame(cams.c2w[i], 40.0, ev, (1.0, 1.0, 1.0)) for i, ev in ((1, -1.0), (5, 1.0))]
    path = viewer.camera_path(frames=5)
    assert [f.ev for f in path.frames] == [-1.0, -0.5, 0.0, 0.5, 1.0] and len(path.keyframes) == 2
    assert np.allclose(model.geometry.poses_to_world(path.frames[-1].c2w), cams.c2w[5])
    from hdrplenoxels.data.camera_path import write_camera_path

    write_camera_path(run / "camera_path.json", path)
    assert len(read_camera_path(run / "camera_path.json").frames) == 5
