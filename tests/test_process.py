"""`process`: photos -> COLMAP -> transforms.json -> train, EXIF exposure, COLMAP models, and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, TiffImagePlugin

from hdrplenoxels.cli.main import main
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.colmap import load_colmap, write_colmap
from hdrplenoxels.data.exif import read_exif_exposure
from hdrplenoxels.eval.evaluate import evaluate
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.process import process_photos, sfm
from hdrplenoxels.synth.generate import SynthOptions, synthesize
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.train.config import preset
from hdrplenoxels.train.trainer import Trainer

EXIF_IFD, EXPOSURE_TIME, F_NUMBER, ISO, FOCAL_35MM = 0x8769, 0x829A, 0x829D, 0x8827, 0xA405


def _save_jpeg_with_exif(src: Path, dst: Path, exposure_time: float, focal_35mm: int | None = None) -> None:
    exif = Image.Exif()
    ifd = exif.get_ifd(EXIF_IFD)
    ifd[EXPOSURE_TIME] = TiffImagePlugin.IFDRational(exposure_time)
    ifd[F_NUMBER] = TiffImagePlugin.IFDRational(4)
    ifd[ISO] = 100
    if focal_35mm:
        ifd[FOCAL_35MM] = focal_35mm
    with Image.open(src) as img:
        img.convert("RGB").save(dst, quality=95, exif=exif)


def _rotation_errors_deg(found: Cameras, truth: Cameras) -> np.ndarray:
    """Per-camera rotation error after the best global rotation (SfM fixes the frame only up to a
    similarity; the rotation part is the chordal mean of truth @ found^T)."""
    m = sum(t[:3, :3] @ f[:3, :3].T for f, t in zip(found.c2w, truth.c2w))
    u, _, vt = np.linalg.svd(m)
    align = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    errors = []
    for f, t in zip(found.c2w, truth.c2w):
        cos = (np.trace((align @ f[:3, :3]).T @ t[:3, :3]) - 1.0) / 2.0
        errors.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.asarray(errors)


@pytest.fixture(scope="module")
def gallery(tmp_path_factory) -> Path:
    """20 renders of the SfM scene: static captures and -3/0/+3 EV captures (as JPEGs with EXIF)."""
    out = tmp_path_factory.mktemp("gallery")
    synthesize("gallery", out, SynthOptions(n_views=20))
    photos = out / "varying_jpeg"
    photos.mkdir()
    truth = json.loads((out / "varying" / "camera_truth.json").read_text())
    for view in truth["views"]:
        src = out / "varying" / view["file"]
        # A 30 mm (35 mm-equivalent) lens: the synthetic camera's 60 degree field of view.
        _save_jpeg_with_exif(src, photos / f"{src.stem}.jpg", 2.0 ** view["ev"] / 100, focal_35mm=30)
    return out


def test_process_varying_exposure_photos_registers_all_with_accurate_poses_and_exif(gallery, tmp_path):
    out = tmp_path / "processed"
    result = process_photos(gallery / "varying_jpeg", out, log=lambda s: None)
    assert len(result.registered) == 20 and not result.unregistered
    scene = load_scene(out)
    truth = load_scene(gallery / "varying")
    order = [truth.names.index(f"images/{Path(n).stem}.png") for n in scene.names]
    truth_cams = Cameras(
        truth.cameras.c2w[order], truth.cameras.intrinsics[order], truth.cameras.sizes[order]
    )
    errors = _rotation_errors_deg(scene.cameras, truth_cams)
    assert errors.max() < 1.0, errors
    # EXIF exposure is recorded and offered as the initial exposure: differences equal the true EVs.
    true_ev = np.array(
        [v["ev"] for v in json.loads((gallery / "varying" / "camera_truth.json").read_text())["views"]]
    )[order]
    init = scene.extras["exposure_init_ev"]
    np.testing.assert_allclose(init - init[0], true_ev - true_ev[0], atol=1e-6)
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["frames"][0]["exif"] == {
        "exposure_time": pytest.approx(2.0 ** true_ev[0] / 100),
        "f_number": 4.0,
        "iso": 100.0,
    }
    assert meta["process"]["registered"] == 20 and meta["forward_facing"] is False
    # train's scene line says which sparse points the box was fitted to
    assert "sparse points seen by >= 2 views" in meta["process"]["box_from"]
    assert scene.bounds_notes["box"] == f"'aabb' that `process` derived from {meta['process']['box_from']}"
    assert not list(tmp_path.glob(".processed.partial-*"))  # the work folder is gone


def test_sift_features_are_affine_adapted_unless_turned_off(tmp_path):
    """Affine-adapted SIFT is what registers an exposure bracket (docs/performance.md, "Affine-adapted
    SIFT"). COLMAP stores each keypoint's shape as a 2x2 matrix: a similarity (rotation and scale) for
    plain SIFT, a general affine map when the shape is estimated."""
    import pycolmap

    (tmp_path / "img").mkdir()
    blocks = np.kron(np.random.default_rng(0).random((24, 32)), np.ones((8, 8)))
    Image.fromarray(np.repeat((blocks * 255).astype(np.uint8)[..., None], 3, axis=2)).save(
        tmp_path / "img" / "a.png"
    )
    off_similarity = {}
    for affine in (False, True):
        database = tmp_path / f"features_{affine}.db"
        sfm.extract(database, tmp_path / "img", ["a.png"], True, sfm.SfmConfig(affine_shape=affine))
        with pycolmap.Database.open(str(database)) as db:
            a11, a12, a21, a22 = db.read_keypoints(1)[:, 2:6].T
        assert len(a11) > 50
        off_similarity[affine] = float(np.max(np.abs(a11 - a22) + np.abs(a12 + a21)))
    assert sfm.SfmConfig().affine_shape
    assert off_similarity[False] < 1e-4 and off_similarity[True] > 0.5


def test_process_then_train_fits_held_out_right_halves(gallery, tmp_path):
    """Issue 5 asks for >= 25 dB on held-out right halves. Measured: 32.7 dB (34.4 with the true poses);
    before scenes were normalised to a unit box it was 24.0-27.4 (SfM units are 2.1x the true ones)."""
    process_photos(gallery / "static" / "images", tmp_path / "data", log=lambda s: None)
    scene = load_scene(tmp_path / "data")
    model = Trainer(scene, preset("fast"), tmp_path / "run").run(progress=False)
    result = evaluate(model, scene, lpips=False)
    assert result["holdout"] == "right-half"
    assert result["psnr"] >= 25.0, result


def test_exposure_init_from_metadata_starts_each_view_at_its_exif_exposure():
    tm = ToneMapper(3, np.array([[8, 8]] * 3), ToneMapConfig(exposure_init_from_metadata=True))
    tm.init_from_images(torch.tensor([[0.2, 0.2, 0.2], [0.1, 0.12, 0.1], [0.5, 0.4, 0.6]]))
    ref = int(tm.reference)
    before = tm.log_wb.detach().clone()
    tm.init_exposures(np.array([0.0, -3.0, 3.0]))
    wb = tm.log_wb.detach()
    means = wb.mean(1).numpy()
    np.testing.assert_allclose(
        (means - means[ref]) / np.log(2.0), np.array([0, -3, 3]) - [0, -3, 3][ref], atol=1e-5
    )
    chroma = (wb - wb.mean(1, keepdim=True)).numpy()
    np.testing.assert_allclose(chroma, (before - before.mean(1, keepdim=True)).numpy(), atol=1e-6)
    assert np.allclose(wb[ref].numpy(), tm.reference_log_wb.numpy())


def test_exif_exposure_is_read_from_jpeg_and_absent_otherwise(tmp_path):
    src = tmp_path / "a.png"
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(src)
    _save_jpeg_with_exif(src, tmp_path / "a.jpg", 1 / 125)
    exif = read_exif_exposure(tmp_path / "a.jpg")
    assert exif is not None and exif.exposure_time == pytest.approx(0.008) and exif.f_number == 4.0
    assert exif.stops == pytest.approx(np.log2(0.008 / 16))
    assert read_exif_exposure(src) is None
    (tmp_path / "junk.jpg").write_bytes(b"not a jpeg")
    assert read_exif_exposure(tmp_path / "junk.jpg") is None


@pytest.mark.parametrize("text", [False, True])
def test_colmap_model_round_trip_gives_the_same_cameras(tmp_path, text):
    rng = np.random.default_rng(3)
    n = 5
    c2w = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        c2w[i, :3, :3] = q * np.sign(np.linalg.det(q))
        c2w[i, :3, 3] = rng.normal(size=3)
    sizes = np.array([[8 + i, 6 + i] for i in range(n)])
    k = np.array([[10.0 + i, 11.0 + i, 4.0 + 0.1 * i, 3.0 - 0.1 * i] for i in range(n)])
    cams = Cameras(c2w, k, sizes)
    names = [f"im{i}.png" for i in range(n)]
    (tmp_path / "images").mkdir()
    for i, name in enumerate(names):
        w, h = sizes[i]
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(tmp_path / "images" / name)
    write_colmap(tmp_path / "sparse" / "0", cams, names, text=text)
    scene = load_scene(tmp_path)
    assert scene.names == names and scene.extras["layout"] == "colmap"
    np.testing.assert_allclose(scene.cameras.c2w, cams.c2w, atol=1e-5)
    np.testing.assert_allclose(scene.cameras.intrinsics, cams.intrinsics, atol=1e-5)
    np.testing.assert_array_equal(scene.cameras.sizes, cams.sizes)


def test_write_colmap_never_leaves_a_half_written_model(tmp_path, monkeypatch):
    import pycolmap

    cams = Cameras(
        np.tile(np.eye(4), (3, 1, 1)), np.tile([10.0, 10.0, 4.0, 3.0], (3, 1)), np.tile([8, 6], (3, 1))
    )
    names = ["a.png", "b.png", "c.png"]
    model = write_colmap(tmp_path / "sparse" / "0", cams, names)
    before = {f.name: f.read_bytes() for f in model.iterdir()}
    assert set(before) >= {"cameras.bin", "images.bin"}

    def fail_half_way(self, folder):
        (Path(folder) / "cameras.bin").write_bytes(b"trunc")
        raise OSError("disk full")

    monkeypatch.setattr(pycolmap.Reconstruction, "write_binary", fail_half_way)
    with pytest.raises(OSError, match="disk full"):
        write_colmap(model, cams, names)
    assert {f.name: f.read_bytes() for f in model.iterdir()} == before
    assert [f.name for f in model.parent.iterdir()] == ["0"]  # no partial folder left behind


def test_colmap_distorted_camera_is_undistorted_at_load(tmp_path):
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(
            model="SIMPLE_RADIAL", width=40, height=30, params=[40.0, 20.0, 15.0, 0.1], camera_id=1
        )
    )
    (tmp_path / "images").mkdir()
    for i in range(3):
        w2c = np.eye(4)[:3]
        w2c[0, 3] = 0.1 * i
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"v{i}.png", camera_id=1, image_id=i + 1), pycolmap.Rigid3d(w2c)
        )
        Image.fromarray(np.full((30, 40, 3), 100 + i, np.uint8)).save(tmp_path / "images" / f"v{i}.png")
    (tmp_path / "sparse").mkdir()
    rec.write_binary(tmp_path / "sparse")
    scene = load_colmap(tmp_path)
    w, h = scene.cameras.size(0)
    assert (w, h) != (40, 30) and scene.images[0].shape == (h, w, 3)  # resampled and cropped
    assert scene.cameras.intrinsics[0, 0] == pytest.approx(40.0)


def _cli_error(args: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as info:
        main(args)
    assert info.value.code == 2
    err = capsys.readouterr().err
    last = err.replace("\r", "\n").strip().splitlines()[-1]  # after any progress bar
    assert last.startswith("error: ") and "Traceback" not in err
    return last


def test_process_bad_input_gives_one_line_errors_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "out"
    assert "no such folder" in _cli_error(["process", str(tmp_path / "missing"), str(out)], capsys)
    (tmp_path / "empty").mkdir()
    assert "no photos found" in _cli_error(["process", str(tmp_path / "empty"), str(out)], capsys)
    bad = tmp_path / "bad"
    bad.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        Image.fromarray(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)).save(bad / f"p{i}.jpg")
    data = (bad / "p1.jpg").read_bytes()
    (bad / "p1.jpg").write_bytes(data[: len(data) // 2])
    assert "p1.jpg" in _cli_error(["process", str(bad), str(out)], capsys)
    (bad / "p1.jpg").write_bytes(data)
    # Pure noise has no consistent geometry: registration fails with a clear message.
    assert "could be registered" in _cli_error(["process", str(bad), str(out)], capsys)
    assert not out.exists() and not list(tmp_path.glob(".out.partial-*"))
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert "not empty" in _cli_error(["process", str(bad), str(out)], capsys)
    assert (out / "keep.txt").read_text() == "mine"


def test_colmap_reader_refuses_corrupt_model_files(tmp_path):
    (tmp_path / "images").mkdir()
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (sparse / name).write_bytes(b"\x05\x00garbage")
    with pytest.raises(InputError) as info:
        load_colmap(tmp_path)
    assert "sparse/0" in str(info.value) and "\n" not in str(info.value)
    (sparse / "points3D.bin").unlink()
    with pytest.raises(InputError, match="points3D"):
        load_colmap(tmp_path)
