"""Loading in two steps: every layout's parser describes a scene without reading a pixel, and the one
image loader turns that description into the same `SceneData` as `load_scene`, naming the file it fails on."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from helpers import raises_naming
from PIL import Image

from hdrplenoxels.data import image_io, load_scene
from hdrplenoxels.data.colmap import describe_colmap
from hdrplenoxels.data.description import CameraDescription, SceneDescription, ViewDescription
from hdrplenoxels.data.image_io import write_png
from hdrplenoxels.data.images import load_images
from hdrplenoxels.data.llff import describe_llff, write_hdrnerf, write_llff, write_llff_hwf_cxcy
from hdrplenoxels.data.transforms_json import describe_transforms
from hdrplenoxels.data.writers import write_blender, write_nerfstudio
from hdrplenoxels.geometry.cameras import Cameras

N, W, H = 5, 8, 6


def _cameras() -> Cameras:
    c2w = np.tile(np.eye(4), (N, 1, 1))
    c2w[:, 0, 3] = np.arange(N) * 0.5
    return Cameras(c2w, [[10.0, 10.0, W / 2, H / 2]] * N, [[W, H]] * N)


def _images(alpha: bool = False) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, size=(H, W, 4 if alpha else 3), dtype=np.uint8) for _ in range(N)]


def _colmap(root: Path) -> None:
    """A COLMAP folder with a distorted camera (undistorted by the loader) and three photos."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="SIMPLE_RADIAL", width=40, height=30, params=[40.0, 20.0, 15.0, 0.1], camera_id=1
    )
    rec.add_camera_with_trivial_rig(cam)
    (root / "images").mkdir(parents=True)
    for i in range(3):
        w2c = np.eye(4)[:3]
        w2c[0, 3] = 0.1 * i
        image = pycolmap.Image(name=f"v{i}.png", camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c))
        Image.fromarray(np.full((30, 40, 3), 100 + i, np.uint8)).save(root / "images" / f"v{i}.png")
    (root / "sparse").mkdir()
    rec.write_binary(root / "sparse")


LAYOUTS = {
    "nerfstudio": (lambda p: write_nerfstudio(p, _cameras(), _images(alpha=True)), describe_transforms),
    "blender": (lambda p: write_blender(p, _cameras(), [1, 2, 3, 4], [0], _images()), describe_transforms),
    "llff": (lambda p: write_llff(p, _cameras(), [(1.0, 5.0)] * N, _images()), describe_llff),
    "llff_hwf_cxcy": (
        lambda p: write_llff_hwf_cxcy(p, _cameras(), [(1.0, 5.0)] * N, _images()),
        describe_llff,
    ),
    "hdrnerf": (
        lambda p: write_hdrnerf(p, _cameras(), [(1.0, 5.0)] * N, [0.01] * N, _images()),
        describe_llff,
    ),
    "colmap": (_colmap, describe_colmap),
}


def _no_pixels(path, *args, **kwargs):
    raise AssertionError(f"the parser decoded {path}")


@pytest.mark.parametrize("layout", LAYOUTS)
def test_parsers_describe_without_reading_pixels(tmp_path, monkeypatch, layout):
    write, describe = LAYOUTS[layout]
    write(tmp_path)
    with monkeypatch.context() as m:
        m.setattr(image_io, "_open_decoded", _no_pixels)  # every image read goes through it
        description = describe(tmp_path)
    assert description.layout == layout
    assert all(p.is_file() for p in description.image_paths)
    assert len(description.names) == len(description.views) == (3 if layout == "colmap" else N)
    scene = load_images(description)
    expected = load_scene(tmp_path)
    assert (scene.names, scene.train_ids, scene.test_ids) == (
        expected.names,
        expected.train_ids,
        expected.test_ids,
    )
    for got, want in zip(scene.images, expected.images, strict=True):
        np.testing.assert_array_equal(got, want)
    for field in ("c2w", "intrinsics", "sizes"):
        np.testing.assert_array_equal(getattr(scene.cameras, field), getattr(expected.cameras, field))
    assert scene.extras.keys() == expected.extras.keys()
    assert (scene.scene_box, scene.near_far, scene.forward_facing) == (
        expected.scene_box,
        expected.near_far,
        expected.forward_facing,
    )


def test_description_fields_carry_what_the_layout_states(tmp_path):
    write_nerfstudio(tmp_path / "ns", _cameras(), _images(alpha=True), extra={"background": 0.25})
    ns = describe_transforms(tmp_path / "ns")
    assert ns.alpha == "white" and ns.background_brightness == 0.25 and not ns.white_background
    assert ns.views[0].camera.fx == 10.0 and ns.views[0].camera.shared
    write_blender(tmp_path / "bl", _cameras(), [1, 2, 3, 4], [0], _images())
    bl = describe_transforms(tmp_path / "bl")
    assert bl.white_background and bl.forward_facing is False and bl.views[0].camera.fov_x is not None
    write_hdrnerf(tmp_path / "hdr", _cameras(), [(1.0, 5.0)] * N, [0.5] * N, _images())
    hdr = describe_llff(tmp_path / "hdr")
    np.testing.assert_array_equal(hdr.exposure_init_ev, [-1.0] * N)
    assert hdr.near_far == (1.0, 5.0) and hdr.views[0].camera.resized_copies and hdr.alpha == "drop"
    _colmap(tmp_path / "col")
    assert describe_colmap(tmp_path / "col").views[0].camera.distortion.model == "SIMPLE_RADIAL"


def _one_view_scene(image: Path, camera: CameraDescription) -> SceneDescription:
    view = ViewDescription(
        "a.png", image, np.eye(4), camera, image.parent / "scene.json", "scene.json frame 0"
    )
    return SceneDescription(layout="test", source=image.parent, views=[view], train_ids=[0], test_ids=[])


def test_loader_errors_name_the_image_file(tmp_path):
    image = tmp_path / "a.png"
    write_png(image, np.zeros((H, W, 3), np.uint8))
    scene = load_images(_one_view_scene(image, CameraDescription(fx=10.0, fy=10.0)))
    assert scene.cameras.intrinsics.tolist() == [[10.0, 10.0, W / 2, H / 2]]
    stated = CameraDescription(fx=10.0, fy=10.0, width=W + 1, height=H)
    raises_naming(
        "a.png", load_images, _one_view_scene(image, stated), contains=(f"{W}x{H}", "scene.json frame 0")
    )
    resized = dataclasses.replace(stated, width=2 * W, height=3 * H, resized_copies=True)
    raises_naming("a.png", load_images, _one_view_scene(image, resized), contains=("resized copy",))
    image.write_bytes(b"not a png")
    raises_naming("a.png", load_images, _one_view_scene(image, CameraDescription(fx=10.0)))
    image.unlink()
    raises_naming(
        "a.png", load_images, _one_view_scene(image, CameraDescription(fx=10.0)), contains=("not found",)
    )
