"""Fuzzing every input kind, a fixed-seed subset (tests/fuzz_inputs.py; `make fuzz` runs many more cases),
and the crashes fuzzing found, each pinned by a plain test."""

from __future__ import annotations

import io
import json
import shutil
import struct
import zipfile

import numpy as np
import pytest
from fuzz_inputs import KINDS, cameras, forged_npy, model, npy_bytes, resume_template, run_cli, run_kind
from helpers import raises_naming
from hypothesis import strategies as st

from hdrplenoxels.cli.common import load_model, load_tones
from hdrplenoxels.core.run_lock import LOCK_FILE
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.camera_path import CameraPath, PathFrame, read_camera_path, write_camera_path
from hdrplenoxels.data.colmap import write_colmap
from hdrplenoxels.data.image_io import write_png
from hdrplenoxels.data.llff import load_llff, write_llff
from hdrplenoxels.data.poses import read_poses
from hdrplenoxels.train.config import read_config
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.run_folder import CHECKPOINT_DIR, LOG_FILE

EXAMPLES = 10  # per kind: about 130 cases in all, well under a minute


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_fuzzed_inputs_end_in_success_or_one_error_line(kind):
    found: list[str] = []
    outcomes: set[str] = set()

    def record(_: str, result: str, detail: str) -> None:
        outcomes.add(result)
        if result not in ("ok", "error"):
            found.append(f"{result}: {detail}")

    run_kind(kind, EXAMPLES, derandomize=True, record=record)
    assert not found, "\n".join(found[:3])
    assert "error" in outcomes, "no case was refused: the mutations never reached the reader"


# ---------------------------------------------------------------------------- what fuzzing found
def _replace_npz_entry(path, name: str, raw: bytes) -> None:
    with zipfile.ZipFile(path) as zf:
        entries = {i.filename: zf.read(i) for i in zf.infolist()}
    entries[name] = raw
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in entries.items():
            zf.writestr(key, value)


class _Draws:
    """Stands in for Hypothesis's `data` with fixed answers, to build one forged header."""

    def __init__(self, *answers):
        self.answers = list(answers)

    def draw(self, _strategy: st.SearchStrategy):
        return self.answers.pop(0)


@pytest.mark.parametrize(
    ("raw", "needle"),
    [
        (
            lambda: forged_npy(_Draws(2**40, (2**40,), "<f4", False, b"")),
            "header declares shape (1099511627776,)",
        ),
        (lambda: forged_npy(_Draws(2**31, (2**31, 2**31), "<f8", False, b"x")), "header declares shape"),
        (lambda: npy_bytes(np.array([1, "x", None], dtype=object)), "holds Python objects"),
    ],
)
def test_model_entries_that_would_allocate_terabytes_or_hold_objects_are_refused(tmp_path, raw, needle):
    path = tmp_path / "model.npz"
    model().save(path)
    _replace_npz_entry(path, "density.npy", raw())
    e = raises_naming("model.npz", load_model, str(path), contains=(needle,))
    assert "'density'" in str(e)


def test_damaged_model_metadata_is_one_error(tmp_path):
    path = tmp_path / "model.npz"
    m = model()
    m.cameras.intrinsics = m.cameras.intrinsics[:1].copy()
    m.save(path)
    raises_naming("model.npz", load_model, str(path), contains=("damaged model file",))


def test_npy_with_a_huge_declared_shape_is_refused(tmp_path):
    write_llff(tmp_path, cameras(), [[1.0, 9.0]] * 3)
    (tmp_path / "poses_bounds.npy").write_bytes(forged_npy(_Draws(2**50, (2**50, 17), "<f8", False, b"")))
    raises_naming("poses_bounds.npy", load_llff, tmp_path, contains=("header declares shape",))
    pose = tmp_path / "pose.npy"
    pose.write_bytes(forged_npy(_Draws(2**40, (2**40,), "<f4", False, b"")))
    raises_naming("pose.npy", read_poses, pose, "opengl", contains=("header declares shape",))


@pytest.mark.parametrize(
    ("name", "edit"),
    [
        ("points3D.bin", lambda raw: struct.pack("<Q", 1) + bytes(43) + struct.pack("<Q", 2**62)),
        ("frames.bin", lambda raw: raw[:72] + struct.pack("<I", 2**31) + raw[76:]),
        ("images.bin", lambda raw: struct.pack("<Q", 2**40) + raw[8:]),
        ("rigs.bin", lambda raw: raw[:12] + struct.pack("<I", 2**30) + raw[16:]),
    ],
)
def test_colmap_counts_beyond_the_file_are_refused_before_pycolmap_reads(tmp_path, name, edit):
    """COLMAP reads as many records as a count says, past the file's end: this one hung, allocating."""
    for i, img in enumerate(np.zeros((3, 8, 8, 3), np.uint8)):
        write_png(tmp_path / "images" / f"v{i}.png", img)
    model_dir = write_colmap(tmp_path / "sparse" / "0", cameras(), ["v0.png", "v1.png", "v2.png"])
    path = model_dir / name
    path.write_bytes(edit(path.read_bytes()))
    raises_naming(name, load_scene, tmp_path, contains=("damaged COLMAP file",))


def test_fuzz_seeds_are_valid(tmp_path):
    """The inputs the mutations start from load: a refusal in the fuzz run is the mutation's doing."""
    for i, img in enumerate(np.zeros((3, 8, 8, 3), np.uint8)):
        write_png(tmp_path / "images" / f"v{i}.png", img)
    write_colmap(tmp_path / "sparse" / "0", cameras(), ["v0.png", "v1.png", "v2.png"])
    assert len(load_scene(tmp_path).names) == 3
    path = tmp_path / "model.npz"
    model().save(path)
    assert load_model(str(path)).tonemapper is not None


def test_colmap_text_image_observing_a_missing_point_is_one_error(tmp_path):
    for i, img in enumerate(np.zeros((3, 8, 8, 3), np.uint8)):
        write_png(tmp_path / "images" / f"v{i}.png", img)
    model_dir = write_colmap(tmp_path / "sparse" / "0", cameras(), ["v0.png", "v1.png", "v2.png"], text=True)
    path = model_dir / "images.txt"
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.endswith("v0.png"))
    lines[first + 1] = "1.0 1.0 7"  # its 2-D point observes 3-D point 7; points3D.txt holds none
    path.write_text("\n".join(lines) + "\n")
    raises_naming(tmp_path.name, load_scene, tmp_path, contains=("observes 3-D point 7,",))


def test_npy_header_the_tokenizer_chokes_on_is_one_error(tmp_path):
    header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (3, 17), }  \xe3{b".ljust(118) + b"\n"
    path = tmp_path / "poses_bounds.npy"
    path.write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(408))
    raises_naming("poses_bounds.npy", load_llff, tmp_path, contains=("broken .npy header",))


def test_tone_params_with_a_malformed_vignetting_is_one_error(tmp_path):
    params = model().tonemapper.parameters_dict()
    for bad in ({"k1": 1.0}, [[0.0] * 3] * 3):
        path = tmp_path / "tone_params.json"
        path.write_text(json.dumps(params | {"vignetting": bad}))
        raises_naming("tone_params.json", load_tones, str(path))


@pytest.mark.parametrize(
    "edit",
    [{"image_size": {"w": 8}}, {"knot_power": 0.0}, {"white_balance": 1.0}, {"image_size": [[8, 8]]}],
    ids=["image_size-dict", "knot_power-0", "white_balance-scalar", "image_size-one-row"],
)
def test_tone_params_fields_of_the_wrong_kind_are_one_error(tmp_path, edit):
    path = tmp_path / "tone_params.json"
    path.write_text(json.dumps(model().tonemapper.parameters_dict() | edit))
    raises_naming("tone_params.json", load_tones, str(path))


def test_model_geometry_of_the_wrong_shape_is_one_error(tmp_path):
    """Found through `export`, which reads the geometry to move the grid into the dataset's frame."""
    m = model()
    m.geometry.world_from_data = np.eye(4)[0]
    path = tmp_path / "model.npz"
    m.save(path)
    raises_naming("model.npz", load_model, str(path), contains=("world_from_data",))


def test_colmap_text_image_name_that_is_not_utf8_is_one_error(tmp_path):
    for i, img in enumerate(np.zeros((3, 8, 8, 3), np.uint8)):
        write_png(tmp_path / "images" / f"v{i}.png", img)
    model_dir = write_colmap(tmp_path / "sparse" / "0", cameras(), ["v0.png", "v1.png", "v2.png"], text=True)
    path = model_dir / "images.txt"
    path.write_bytes(path.read_bytes().replace(b"v0.png", b"v\xfa.png"))
    raises_naming("0", load_scene, tmp_path, contains=("not UTF-8",))


# ---------------------------------------------------------------------------- what fuzzing `--resume` found
def _killed_run(tmp_path):
    """A copy of the fuzzer's tiny run killed after its checkpoint, and that run's data."""
    template = resume_template()
    run = tmp_path / "run"
    shutil.copytree(template / "run", run)
    return template / "data", run


def _resume_cli(data, run) -> tuple[int, str]:
    return run_cli(["train", str(data), "--out", str(run), "--resume", "--quiet", "--iters", "7"])


def test_resume_survives_a_log_line_cut_inside_a_character(tmp_path):
    data, run = _killed_run(tmp_path)
    log = run / LOG_FILE
    log.write_bytes(log.read_bytes() + b'{"step": 6, "loss": \xe2\x82')  # a kill inside a UTF-8 character
    code, stderr = _resume_cli(data, run)
    assert code == 0, stderr
    assert all(json.loads(line)["step"] != 6 or "psnr" in line for line in log.read_text().splitlines())


@pytest.mark.parametrize(
    "entry, value",
    [
        ("tonemap/crf_interior", np.zeros(5, np.float32)),  # was: a crash while plotting the curves
        ("tonemap/crf_group", np.full(3, 9, np.int64)),  # a group that does not exist
        ("tonemap_optim/1/square_avg", np.zeros((2, 2), np.float32)),  # the wrong parameter's shape
        ("tonemap_optim/0/step", np.array(np.inf, np.float32)),  # was: OverflowError
        ("optim/v1", np.zeros((5, 2), np.float32)),  # was: a crash at the first step after resuming
        ("optim/steps", np.array([1, 2])),
    ],
)
def test_a_damaged_training_state_is_refused_and_nothing_is_written(tmp_path, entry, value):
    data, run = _killed_run(tmp_path)
    ckpt = sorted((run / CHECKPOINT_DIR).glob("step_*.npz"))[-1]
    _replace_npz_entry(ckpt, f"x/{entry}.npy", npy_bytes(value))  # extra arrays are stored under x/
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != LOCK_FILE}
    code, stderr = _resume_cli(data, run)
    assert code == 2 and stderr.startswith("error: ") and stderr.count("\n") == 1, stderr
    assert ckpt.name in stderr and "does not fit this run" in stderr
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != LOCK_FILE} == before


@pytest.mark.parametrize(
    "setting", ["grid.sh_degree=7", "optim.batch_size=0", "grid.reso_schedule=[[0,0,0]]", "optim.lr_sh=nan"]
)
def test_settings_no_run_can_use_are_one_error_before_anything_is_written(tmp_path, setting):
    data, _ = _killed_run(tmp_path)
    out = tmp_path / "new"
    code, stderr = run_cli(["train", str(data), "--out", str(out), "--quiet", "--set", setting])
    assert code == 2 and stderr.startswith("error: --set: ") and setting.partition("=")[0] in stderr, stderr
    assert not out.exists()


def test_a_saved_configuration_is_typed_like_an_override(tmp_path):
    cfg = preset("fast").to_dict()
    cfg["optim"]["batch_size"] = "many"
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    raises_naming("config.json", read_config, tmp_path / "config.json", contains=("optim.batch_size",))


@pytest.mark.parametrize(
    "change",
    [
        lambda d: d["camera_path"].__setitem__(0, [1, 2]),  # was: AttributeError
        lambda d: d["keyframes"][0].__setitem__("hdrplenoxels", "bright"),  # was: AttributeError
        lambda d: d.__setitem__("keyframes", 5),  # was: TypeError
    ],
)
def test_camera_path_entries_of_the_wrong_kind_are_one_error(tmp_path, change):
    path = tmp_path / "camera_path.json"
    frames = [PathFrame(c2w, 50.0) for c2w in cameras().c2w]
    write_camera_path(path, CameraPath(frames, 16, 12, 24.0, keyframes=frames[:2]))
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    raises_naming("camera_path.json", read_camera_path, path)


def test_a_model_of_an_unknown_scene_mode_is_one_error(tmp_path):
    """Was: `export` of a model whose geometry said neither bbox nor ndc died in grid_in_data_frame."""
    path = tmp_path / "model.npz"
    model().save(path)
    with zipfile.ZipFile(path) as zf:
        meta = json.loads(np.load(io.BytesIO(zf.read("meta_json.npy"))).item())
    meta["geometry"]["mode"] = "sphere"
    _replace_npz_entry(path, "meta_json.npy", npy_bytes(np.array(json.dumps(meta))))
    raises_naming("model.npz", load_model, str(path), contains=("geometry mode",))
