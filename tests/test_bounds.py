"""Scene bounds from every source the data has (instant-ngp's aabb / aabb_scale, sdfstudio's scene_box,
COLMAP's sparse points), the box / NDC choice, and the one line saying what was chosen and why."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import raises_naming
from PIL import Image

from hdrplenoxels.data.bounds import point_box
from hdrplenoxels.data.colmap import describe_reconstruction
from hdrplenoxels.data.llff import describe_llff, write_llff
from hdrplenoxels.data.placement import choose_mode, placement_summary, setup_scene
from hdrplenoxels.data.scene import SceneData
from hdrplenoxels.data.transforms_json import describe_transforms
from hdrplenoxels.geometry.cameras import Cameras

N = 4


def _transforms(folder: Path, forward: bool = False, **meta) -> Path:
    """A transforms.json of N views (no images needed to describe it): a ring around the origin, or, with
    `forward`, a sideways sweep all looking the same way."""
    folder.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(N):
        Image.new("RGB", (8, 6)).save(folder / f"v{i}.png")
        pose = np.eye(4)  # OpenGL: looking along -z
        if forward:
            pose[:3, 3] = [0.2 * i, 0.0, 4.0]
        else:
            a = 2 * np.pi * i / N
            pose[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
            pose[:3, 3] = 4.0 * np.array([np.sin(a), 0.0, np.cos(a)])
        frames.append({"file_path": f"v{i}.png", "transform_matrix": pose.tolist()})
    path = folder / "transforms.json"
    path.write_text(json.dumps({"fl_x": 8.0, **meta, "frames": frames}))
    return path


def _scene(path: Path) -> SceneData:
    """The description as a scene (blank images: bounds never depend on pixels)."""
    d = describe_transforms(path)
    cams = Cameras(np.stack([v.c2w for v in d.views]), [[8.0, 8.0, 4.0, 3.0]] * N, [[8, 6]] * N)
    images = [np.zeros((6, 8, 3), np.uint8)] * N
    return SceneData(
        images, cams, d.names, d.train_ids, d.test_ids, d.source, d.scene_box, d.forward_facing,
        d.near_far, bounds_notes=d.bounds_notes, box_source=d.box_source, aabb_scale=d.aabb_scale,
    )  # fmt: skip


def test_aabb_is_the_box_and_the_line_says_so(tmp_path):
    scene = _scene(_transforms(tmp_path, aabb=[[-1, -2, -3], [1, 2, 3]]))
    assert scene.scene_box == ((-1.0, -2.0, -3.0), (1.0, 2.0, 3.0))
    line = placement_summary(scene)
    assert line.startswith("scene: bounding box from 'aabb' in transforms.json, 2 x 4 x 6 units;"), line
    assert "forward-facing: no (views face every way)" in line and "beyond" not in line and "\n" not in line
    assert setup_scene(scene)[1].mode == "bbox"


@pytest.mark.parametrize("box", [[[0, 0, 0], [2, 1, 4]], {"aabb": [[0, 0, 0], [2, 1, 4]], "near": 0.1}])
def test_scene_box_of_sdfstudio_and_nerfstudio(tmp_path, box):
    scene = _scene(_transforms(tmp_path, scene_box=box))
    assert scene.scene_box == ((0.0, 0.0, 0.0), (2.0, 1.0, 4.0))
    assert "from 'scene_box' in transforms.json, 2 x 1 x 4 units" in placement_summary(scene)


def test_aabb_scale_gives_a_cascade_around_instant_ngps_unit_cube(tmp_path):
    scene = _scene(_transforms(tmp_path, aabb_scale=16))
    np.testing.assert_allclose(scene.scene_box, [[-0.5 / 0.33] * 3, [0.5 / 0.33] * 3])
    line = placement_summary(scene)
    assert line.startswith("scene: cascade of 5 boxes (content beyond the box (aabb_scale 16"), line
    assert "3.03 x 3.03 x 3.03 units around instant-ngp's unit cube" in line and "\n" not in line
    assert "multi-sphere background" in line
    assert choose_mode(scene) == "cascade"
    _, geometry = setup_scene(scene)
    assert geometry.mode == "bbox" and geometry.wants_background and geometry.levels == 5  # 16 = 2^4 beyond
    # Asked for a plain box, the line says what is lost and how to get it.
    line = placement_summary(scene, "bbox")
    assert "renders as the background colour (--scene-mode bbox+background would model it)" in line
    assert not setup_scene(scene, "bbox")[1].wants_background and setup_scene(scene, "bbox")[1].levels == 1
    # NGP's own scale and offset move the cube: p * scale + offset = 0.5 at its centre.
    scene = _scene(_transforms(tmp_path, aabb_scale=1, scale=0.5, offset=[0.0, 0.5, 1.0]))
    np.testing.assert_allclose(scene.scene_box, [[0.0, -1.0, -2.0], [2.0, 1.0, 0.0]])
    assert "beyond" not in placement_summary(scene) and choose_mode(scene) == "bbox"
    # An explicit aabb wins over the cube; aabb_scale still says the content reaches beyond it.
    scene = _scene(_transforms(tmp_path, aabb_scale=4, aabb=[[-1, -1, -1], [1, 1, 1]]))
    assert scene.scene_box == ((-1.0,) * 3, (1.0,) * 3)
    assert "aabb_scale 4" in placement_summary(scene) and choose_mode(scene) == "cascade"
    # The cameras (4 from the centre) need 2^2 x the box with the margin: more than aabb_scale 4 gives.
    assert setup_scene(scene)[1].levels == 4
    # A box drawn around the cameras keeps one box, with the background beyond it.
    scene = _scene(_transforms(tmp_path, aabb_scale=4, aabb=[[-5, -5, -5], [5, 5, 5]]))
    assert choose_mode(scene) == "bbox+background" and setup_scene(scene)[1].levels == 1


@pytest.mark.parametrize(
    "meta", [{"aabb_scale": 0.5}, {"aabb_scale": "16"}, {"scene_box": [[1, 0, 0], [0, 1, 1]]}]
)
def test_bad_bounds_name_the_key(tmp_path, meta):
    path = _transforms(tmp_path, **meta)
    raises_naming("transforms.json", describe_transforms, path, contains=(next(iter(meta)),))


def test_forward_facing_views_take_ndc_with_near_far_or_say_what_to_add(tmp_path):
    scene = _scene(_transforms(tmp_path, forward=True, near_far=[1.0, 20.0]))
    assert choose_mode(scene) == "ndc"
    line = placement_summary(scene)
    assert line.startswith("scene: NDC, near/far 1-20 from 'near_far' in transforms.json;"), line
    assert "forward-facing: yes (views within 0 deg of their mean, 40 the limit)" in line
    bare = _scene(_transforms(tmp_path / "bare", forward=True))
    raises_naming("transforms.json", setup_scene, bare, contains=('"near_far"', "--scene-mode bbox"))
    raises_naming("transforms.json", placement_summary, bare, contains=("forward-facing",))
    assert setup_scene(bare, "bbox")[1].mode == "bbox"  # asked for explicitly
    assert "bounding box (--scene-mode) from a box around the cameras' focus point" in placement_summary(
        bare, "bbox"
    )
    boxed = _scene(_transforms(tmp_path / "boxed", forward=True, aabb=[[-1, -1, -2], [1, 1, 0]]))
    assert choose_mode(boxed) == "bbox"
    assert "forward-facing: yes" in placement_summary(boxed) and "no near/far for NDC" in placement_summary(
        boxed
    )


def test_a_far_bound_beyond_the_box_is_reported(tmp_path):
    scene = _scene(_transforms(tmp_path, aabb=[[-1, -1, -1], [1, 1, 1]], near_far=[0.5, 40.0]))
    line = placement_summary(scene)
    assert "content beyond the box (far depth 40 > 5.73" in line and "multi-sphere background" in line
    assert choose_mode(scene) == "cascade"  # seen from cameras outside the box
    scene.near_far = (0.5, 5.0)
    assert "beyond" not in placement_summary(scene) and choose_mode(scene) == "bbox"


def _reconstruction(images: Path):
    """A COLMAP model of 3 views: 300 inliers seen twice, one far mismatch seen twice, and 19 points seen
    once; returns it and the points seen twice."""
    import pycolmap

    rng = np.random.default_rng(0)
    inliers = rng.uniform([-1.0, -0.5, 4.0], [1.0, 0.5, 6.0], size=(300, 3))
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=40, height=30, params=[40.0, 40.0, 20.0, 15.0], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    images.mkdir(parents=True)
    for i in range(3):
        w2c = np.eye(4)[:3]
        w2c[0, 3] = 0.1 * i
        points2d = [pycolmap.Point2D(np.array([1.0, 1.0])) for _ in range(320)]
        image = pycolmap.Image(name=f"v{i}.png", camera_id=1, image_id=i + 1, points2D=points2d)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c))
        Image.new("RGB", (40, 30)).save(images / f"v{i}.png")

    def add(xyz, image_ids, k):
        track = pycolmap.Track()
        for image_id in image_ids:
            track.add_element(image_id, k)
        rec.add_point3D(np.asarray(xyz, float), track, np.zeros(3, np.uint8))

    for k, p in enumerate(inliers):
        add(p, (1, 2), k)
    add([-50.0, 0.0, 5.0], (1, 3), 300)  # a mismatch seen twice: the percentile drops it
    for k in range(301, 320):
        add([100.0, 0.0, 5.0], (3,), k)  # seen once: no triangulated point
    return rec, np.vstack([inliers, [[-50.0, 0.0, 5.0]]])


def test_colmap_box_is_robust_and_uses_points_seen_twice(tmp_path):
    """1-99th percentile of the points seen by >= 2 views: a single far outlier seen twice and a cloud of
    points seen once move the box by no more than the percentile allows."""
    rec, tracked = _reconstruction(tmp_path / "images")
    d = describe_reconstruction(rec, tmp_path / "images", tmp_path)
    np.testing.assert_allclose(d.scene_box, point_box(tracked))
    lo, hi = np.asarray(d.scene_box)
    assert -1.3 < lo[0] < -0.9 and 0.9 < hi[0] < 1.3
    assert d.bounds_notes["box"] == "301 sparse points seen by >= 2 views (1-99th percentile, padded 10 %)"
    assert "depths" in d.bounds_notes["near_far"]
    # the lines of sight of the free-space prior: the same points, each with the views that saw it
    lines = d.sight_lines
    order = lambda p: p[np.lexsort(p.T)]  # noqa: E731  (the model's point order is its own)
    np.testing.assert_allclose(order(lines.points), order(tracked))
    outlier = int(np.argmin(lines.points[:, 0]))
    assert len(lines) == 2 * 301 and sorted(lines.view[lines.point == outlier].tolist()) == [0, 2]


def test_llff_folders_take_the_box_from_the_colmap_model_they_keep(tmp_path):
    rec, tracked = _reconstruction(tmp_path / "colmap_images")
    cams = Cameras(np.tile(np.eye(4), (3, 1, 1)), [[40.0, 40.0, 20.0, 15.0]] * 3, [[40, 30]] * 3)
    cams.c2w[:, 0, 3] = [0.0, 0.1, 0.2]
    write_llff(tmp_path / "llff", cams, [(1.0, 5.0)] * 3, [np.zeros((30, 40, 3), np.uint8)] * 3)
    assert describe_llff(tmp_path / "llff").scene_box is None  # no model kept: no box
    (tmp_path / "llff" / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(tmp_path / "llff" / "sparse" / "0")
    d = describe_llff(tmp_path / "llff")
    np.testing.assert_allclose(d.scene_box, point_box(tracked))
    assert d.bounds_notes["box"].endswith("of sparse/0/")
    assert d.bounds_notes["near_far"] == "the near/far columns of poses_bounds.npy"


def test_a_box_from_process_names_the_points_it_fits_or_says_so_for_older_outputs(tmp_path):
    box = [[-1, -1, -1], [1, 1, 1]]
    older = describe_transforms(_transforms(tmp_path / "old", aabb=box, process={"registered": N}))
    assert older.bounds_notes["box"] == (
        "'aabb' that `process` derived from its sparse points (1-99th percentile, padded 10 %)"
    )
    note = "1,204 sparse points seen by >= 2 views (1-99th percentile, padded 10 %)"
    new = describe_transforms(_transforms(tmp_path / "new", aabb=box, process={"box_from": note}))
    assert new.bounds_notes["box"] == f"'aabb' that `process` derived from {note}"


def test_box_and_background_asked_for_says_so(tmp_path):
    scene = _scene(_transforms(tmp_path, aabb=[[-1, -1, -1], [1, 1, 1]]))
    line = placement_summary(scene, "bbox+background")
    assert line.startswith("scene: bounding box + background (--scene-mode) from 'aabb'"), line
    assert line.endswith("; what lies beyond the box: a multi-sphere background behind the box models it")
    assert setup_scene(scene, "bbox+background")[1].wants_background


def test_a_capture_whose_box_is_its_points_gets_a_cascade_reaching_every_camera(tmp_path):
    """`process` output: the box is the sparse points' extent (the room around the cameras); the finest
    box is a cube around what the cameras look at, and the outermost holds every camera and the points."""
    meta = {"aabb": [[-9, -3, -9], [9, 5, 9]], "process": {"box_from": "points"}, "near_far": [1.0, 20.0]}
    scene = _scene(_transforms(tmp_path, **meta))
    assert scene.box_source == "points" and choose_mode(scene) == "cascade"
    line = placement_summary(scene)
    assert line.startswith("scene: cascade of ") and "around the point the cameras look at" in line
    cams, geometry = setup_scene(scene)
    assert geometry.wants_background and geometry.radius == (1.0, 1.0, 1.0)  # the finest box: a unit cube
    outer = 2.0 ** (geometry.levels - 1)
    positions = cams.c2w[:, :3, 3]
    assert (np.abs(positions) < outer / 1.1 + 1e-6).all()  # every camera inside, with the margin
    corners = np.array(meta["aabb"]) * geometry.scale() + geometry.world_from_data[:3, 3]
    assert (np.abs(corners) <= outer + 1e-6).all()  # and the points' extent
    assert (np.abs(corners) > outer / 2).any()  # one level fewer would not do
    # Asked for one box, it keeps the old placement: the points' box itself.
    assert setup_scene(scene, "bbox")[1].levels == 1


def test_a_walk_is_never_ndc(tmp_path):
    """Forward-facing views with near/far whose camera travels farther than the near depth (a walk along a
    street): a cascade, not NDC; the same views from near one pose stay NDC."""
    walk = _scene(
        _transforms(tmp_path / "walk", forward=True, near_far=[0.2, 20.0], aabb=[[-1, -1, -5], [3, 1, 0]])
    )
    walk.box_source = "points"
    assert choose_mode(walk) == "cascade"
    line = placement_summary(walk)
    assert "forward-facing: yes" in line and "travel" in line and "not NDC" in line
    assert "around the middle of the sparse points" in line  # the views converge nowhere
    still = _scene(_transforms(tmp_path / "still", forward=True, near_far=[2.0, 20.0]))
    assert choose_mode(still) == "ndc"
