"""Property-based fuzzing of every input kind the package reads (Hypothesis).

Each kind writes a valid input with the package's own writers, then Hypothesis mutates it: JSON values
replaced, keys dropped, arrays of other dtypes and shapes, .npy headers declaring absurd shapes, Python
object arrays, forged PNG headers (huge sizes, 16-bit colour), images in every Pillow mode and format,
truncated, zero-size and bit-flipped files; camera paths; video files (mutated H.264 clips, some with a
display rotation) and photos whose EXIF orientation holds any value, as `process` reads them; and
`train --resume` on a run whose newest checkpoint, config or log was mutated. Every case must end in
success or one `InputError` line (what the CLI prints as `error: ...` with exit 2), within a time limit,
without writing anything (a CLI command writes only under its own output folder, and nothing there when
it fails).

`tests/test_fuzz_inputs.py` runs a fixed-seed subset; `make fuzz` runs this file as a script with many more
cases per kind and prints a table of outcomes:

    python tests/fuzz_inputs.py --examples 1000
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import functools
import io
import json
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
import zipfile
import zlib
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from hdrplenoxels.cli.common import load_model, load_tones
from hdrplenoxels.cli.main import main
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.run_lock import LOCK_FILE
from hdrplenoxels.data import load_scene
from hdrplenoxels.data.camera_path import CameraPath, PathFrame, read_camera_path, write_camera_path
from hdrplenoxels.data.colmap import write_colmap
from hdrplenoxels.data.exposures import load_exposures
from hdrplenoxels.data.image_io import read_image_with_alpha, write_png
from hdrplenoxels.data.llff import write_hdrnerf, write_llff
from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.data.poses import read_poses
from hdrplenoxels.data.sight_lines import POINTS_FILE, POINTS_KEY, SightLines, write_sight_lines
from hdrplenoxels.data.video import VIDEO_EXTENSIONS, video_info
from hdrplenoxels.data.writers import write_blender, write_nerfstudio
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.grid.io import save_grid
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.process.photos import stage_photos
from hdrplenoxels.process.video import stage_video
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.controller import ToneController
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.run_folder import CHECKPOINT_DIR, LOG_FILE
from hdrplenoxels.train.trainer import Trainer

TIME_LIMIT_S = 20.0
OUTCOMES = ("ok", "error", "crash", "timeout")
N_VIEWS = 3
NAMES = [f"v{i}.png" for i in range(N_VIEWS)]
OUTPUT_DIR = "output"  # where a kind that runs a CLI command lets it write (checked by that kind)


# ---------------------------------------------------------------------------- valid inputs
def cameras() -> Cameras:
    c2w = np.tile(np.eye(4), (N_VIEWS, 1, 1))
    c2w[:, 0, 3] = np.arange(N_VIEWS) * 0.5
    c2w[:, 2, 3] = -3.0
    return Cameras(c2w, np.tile([8.0, 8.0, 4.0, 4.0], (N_VIEWS, 1)), np.tile([8, 8], (N_VIEWS, 1)))


def images() -> list[np.ndarray]:
    return [np.random.default_rng(i).integers(0, 256, (8, 8, 3), dtype=np.uint8) for i in range(N_VIEWS)]


def model(levels: int = 1) -> Model:
    """A tiny model: one box, or a cascade of `levels` boxes (4-D links, levels in the geometry), with a
    tone mapper and a tone controller."""
    geometry = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4), levels=levels)
    grid = SparseGrid.create((4, 4, 4), basis_dim=4, levels=levels)
    tm = ToneMapper(N_VIEWS, cameras().sizes, ToneMapConfig(enabled=True))
    ctl = ToneController("centre-average@1+grey", (0.5, -0.9), (0.1, 0.0, -0.1, -0.6))
    opt, cams = RenderOptions(), cameras()
    return Model(grid, geometry, opt, cams, NAMES, [0, 1], [2], "x", tonemapper=tm, controller=ctl)


# ---------------------------------------------------------------------------- mutations
json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


def mutate_bytes(data: st.DataObject, raw: bytes) -> bytes:
    op = data.draw(st.sampled_from(["truncate", "empty", "flip", "insert", "garbage"]))
    n = len(raw)
    if op == "empty" or n == 0:
        return b""
    if op == "truncate":
        return raw[: data.draw(st.integers(0, n - 1))]
    if op == "garbage":
        return data.draw(st.binary(max_size=64))
    at = data.draw(st.integers(0, n - 1))
    if op == "insert":
        return raw[:at] + data.draw(st.binary(min_size=1, max_size=16)) + raw[at:]
    out = bytearray(raw)
    for _ in range(data.draw(st.integers(1, 8))):
        out[data.draw(st.integers(0, n - 1))] = data.draw(st.integers(0, 255))
    return bytes(out)


def mutate_json(data: st.DataObject, obj):
    """Replace one node (found by a random walk from the root), delete a key, or break the text."""
    op = data.draw(st.sampled_from(["replace", "replace", "delete", "bytes"]))
    if op == "bytes":
        return mutate_bytes(data, json.dumps(obj).encode())
    obj = json.loads(json.dumps(obj))
    parent, key, node = None, None, obj
    while isinstance(node, (dict, list)) and node and data.draw(st.booleans()):
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        parent, key = node, data.draw(st.sampled_from(keys))
        node = node[key]
    if parent is None:
        return data.draw(json_values) if op == "replace" else {}
    if op == "delete":
        del parent[key]
    else:
        parent[key] = data.draw(json_values)
    return obj


def write_json(path: Path, value) -> None:
    if isinstance(value, bytes):
        path.write_bytes(value)
    else:
        path.write_text(json.dumps(value))  # NaN and Infinity as Python writes them


DTYPES = [
    "float16",
    "float32",
    "float64",
    "int8",
    "int32",
    "int64",
    "uint8",
    "bool",
    "complex64",
    "<U3",
    "S2",
]


def mutate_array(data: st.DataObject, arr: np.ndarray) -> np.ndarray:
    op = data.draw(st.sampled_from(["dtype", "shape", "values", "empty", "scalar"]))
    if op == "dtype":
        try:
            return arr.astype(data.draw(st.sampled_from(DTYPES)))
        except (ValueError, TypeError, OverflowError):  # text that is no number: another text
            return np.asarray(data.draw(st.text(max_size=20)))
    if op == "shape":
        shape = data.draw(st.lists(st.integers(0, 6), max_size=4))
        return np.resize(arr, shape)
    if op == "empty":
        return arr.reshape(-1)[:0]
    if op == "scalar":
        return np.asarray(data.draw(st.floats() | st.integers(-(2**40), 2**40)))
    if arr.dtype.kind not in "biuf":  # a string entry (format, meta_json): another string
        return np.asarray(data.draw(st.text(max_size=20)))
    out = arr.astype(np.float64).copy()
    if out.size:
        flat = out.reshape(-1)
        for _ in range(data.draw(st.integers(1, 4))):
            flat[data.draw(st.integers(0, flat.size - 1))] = data.draw(st.floats(width=64))
    return out.astype(arr.dtype) if arr.dtype.kind == "f" else out


def npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def forged_npy(data: st.DataObject) -> bytes:
    """A .npy header declaring a huge shape (or Python objects) followed by a few bytes."""
    big = data.draw(st.integers(2**20, 2**62))
    shape = data.draw(st.sampled_from([(big,), (big, 17), (3, big), (big, big)]))
    descr = data.draw(st.sampled_from(["<f4", "<f8", "<i4", "|O", "<U9"]))
    header = {"descr": descr, "fortran_order": data.draw(st.booleans()), "shape": shape}
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue() + data.draw(st.binary(max_size=32))


def mutate_npy_file(data: st.DataObject, path: Path) -> None:
    arr = np.load(path)
    op = data.draw(st.sampled_from(["array", "array", "forged", "object", "bytes"]))
    if op == "array":
        path.write_bytes(npy_bytes(mutate_array(data, arr)))
    elif op == "forged":
        path.write_bytes(forged_npy(data))
    elif op == "object":
        path.write_bytes(npy_bytes(np.array([arr, "x"], dtype=object)))
    else:
        path.write_bytes(mutate_bytes(data, path.read_bytes()))


def mutate_npz_file(data: st.DataObject, path: Path) -> None:
    with zipfile.ZipFile(path) as zf:
        entries = {info.filename: zf.read(info) for info in zf.infolist()}
    op = data.draw(st.sampled_from(["array", "array", "meta", "delete", "forged", "object", "bytes"]))
    if op == "bytes":
        path.write_bytes(mutate_bytes(data, path.read_bytes()))
        return
    name = data.draw(st.sampled_from(sorted(entries)))
    if op == "meta" and "meta_json.npy" not in entries:  # an archive without our metadata entry
        op = "array"
    if op == "meta":
        meta = json.loads(np.load(io.BytesIO(entries["meta_json.npy"])).item())
        entries["meta_json.npy"] = npy_bytes(np.array(json.dumps(mutate_json(data, meta), default=repr)))
    elif op == "delete":
        del entries[name]
    elif op == "forged":
        entries[name] = forged_npy(data)
    elif op == "object":
        entries[name] = npy_bytes(np.array([1, "x", None], dtype=object))
    else:
        entries[name] = npy_bytes(mutate_array(data, np.load(io.BytesIO(entries[name]))))
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in entries.items():
            zf.writestr(key, value)


def png_bytes(width: int, height: int, bit_depth: int, colour_type: int, pixels: bytes) -> bytes:
    """A PNG written by hand, so that its header can state anything (16-bit colour, huge sizes)."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(pixels))
        + chunk(b"IEND", b"")
    )


IMAGE_MODES = ["1", "L", "P", "RGB", "RGBA", "LA", "PA", "I;16", "I", "F", "CMYK", "YCbCr", "LAB", "HSV"]
IMAGE_FORMATS = ["PNG", "JPEG", "TIFF", "BMP", "GIF", "WEBP", "PPM"]


def draw_image_file(data: st.DataObject, path: Path) -> None:
    op = data.draw(st.sampled_from(["pillow", "pillow", "png", "huge", "zero"]))
    if op == "zero":
        path.write_bytes(b"")
        return
    if op in ("png", "huge"):
        w, h = (data.draw(st.integers(1, 12)), data.draw(st.integers(1, 12)))
        if op == "huge":
            w, h = data.draw(
                st.sampled_from([(2**31 - 1, 1), (1, 2**31 - 1), (100_000, 100_000), (2**16, 2**15)])
            )
        depth, colour = data.draw(
            st.sampled_from([(8, 2), (16, 2), (16, 6), (16, 0), (8, 4), (16, 4), (1, 0)])
        )
        channels = {0: 1, 2: 3, 4: 2, 6: 4}[colour]
        row = 1 + (w * channels * depth + 7) // 8
        pixels = data.draw(st.binary(max_size=64)) if op == "huge" else bytes(row * h)
        path.write_bytes(png_bytes(w, h, depth, colour, pixels))
    else:
        mode = data.draw(st.sampled_from(IMAGE_MODES))
        size = (data.draw(st.integers(1, 16)), data.draw(st.integers(1, 16)))
        img = Image.new(mode, size)
        try:
            img.save(path, format=data.draw(st.sampled_from(IMAGE_FORMATS)))
        except (OSError, ValueError, KeyError):
            img.convert("RGB").save(path, format="PNG")
    if data.draw(st.booleans()):
        path.write_bytes(mutate_bytes(data, path.read_bytes()))


# ---------------------------------------------------------------------------- the input kinds
@dataclass
class Kind:
    build: Callable[[st.DataObject, Path], Callable[[], object]]  # writes a (mutated) input; returns the read


def _scene(write_valid: Callable[[Path], Path], mutate: Callable[[st.DataObject, Path], None]):
    def build(data: st.DataObject, folder: Path):
        target = write_valid(folder)
        if data.draw(st.integers(0, 9)) > 0:  # one case in ten is the valid input itself
            mutate(data, target)
        return lambda: load_scene(folder)

    return build


def _json_file(data: st.DataObject, path: Path) -> None:
    write_json(path, mutate_json(data, json.loads(path.read_text())))


def _nerfstudio(folder: Path) -> Path:
    return write_nerfstudio(folder, cameras(), images(), NAMES)


def _sparse_points(folder: Path) -> Path:
    """A nerfstudio scene whose 'sparse_points' key names its SfM points file (as `process` writes it)."""
    path = write_nerfstudio(folder, cameras(), images(), NAMES)
    lines = SightLines(np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 2.0]]), np.array([0, 1, 2]), np.array([0, 0, 1]))
    write_sight_lines(folder / POINTS_FILE, lines, NAMES)
    write_json(path, json.loads(path.read_text()) | {POINTS_KEY: POINTS_FILE})
    return folder / POINTS_FILE


def _blender_one_file(folder: Path) -> Path:
    """instant-ngp's form of the Blender convention: one transforms.json with camera_angle_x."""
    train, test = write_blender(folder, cameras(), [0, 1, 2], [], images())
    train.rename(folder / "transforms.json")
    test.unlink()
    return folder / "transforms.json"


def _blender_splits(folder: Path) -> Path:
    write_blender(folder, cameras(), [0, 1], [2], images())
    return folder / "transforms_train.json"


def _blender_split_mutation(data: st.DataObject, path: Path) -> None:
    _json_file(
        data, path.with_name(data.draw(st.sampled_from(["transforms_train.json", "transforms_test.json"])))
    )


def _llff(folder: Path) -> Path:
    return write_llff(folder, cameras(), [[1.0, 9.0]] * N_VIEWS, images(), NAMES)


def _hdrnerf(folder: Path) -> Path:
    return write_hdrnerf(folder, cameras(), [[1.0, 9.0]] * N_VIEWS, [0.125, 0.5, 2.0], images(), NAMES)


def _hdrnerf_mutation(data: st.DataObject, path: Path) -> None:
    if data.draw(st.booleans()):  # the exposure column only
        arr = np.load(path)
        arr[:, -1] = data.draw(st.lists(st.floats(width=64), min_size=N_VIEWS, max_size=N_VIEWS))
        np.save(path, arr)
    else:
        mutate_npy_file(data, path)


def _colmap(text: bool) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        for name, img in zip(NAMES, images()):
            write_png(folder / "images" / name, img)
        return write_colmap(folder / "sparse" / "0", cameras(), NAMES, text=text)

    return write


def _colmap_mutation(data: st.DataObject, model_dir: Path) -> None:
    path = data.draw(st.sampled_from(sorted(model_dir.iterdir())))
    raw = path.read_bytes()
    if path.suffix == ".txt" and data.draw(st.booleans()):
        lines = raw.decode().splitlines()
        i = data.draw(st.integers(0, max(len(lines) - 1, 0)))
        tokens = lines[i].split() if lines else []
        if tokens and data.draw(st.booleans()):
            tokens[data.draw(st.integers(0, len(tokens) - 1))] = data.draw(
                st.sampled_from(["nan", "-1", "1e308", "0", "x", "99999999999"]) | st.text(max_size=4)
            )
            lines[i] = " ".join(tokens)
        elif lines:
            del lines[i]
        path.write_text("\n".join(lines) + "\n")
    else:
        path.write_bytes(mutate_bytes(data, raw))


def _image(data: st.DataObject, folder: Path):
    path = folder / f"photo.{data.draw(st.sampled_from(['png', 'jpg', 'tif', 'bmp']))}"
    draw_image_file(data, path)
    return lambda: read_image_with_alpha(path)


def _model_cli(data: st.DataObject, folder: Path, levels: int = 1):
    """Through the CLI: `export` reads the model and writes a file, which must exist only on success."""
    path = folder / "model.npz"
    model(levels).save(path)
    mutate_npz_file(data, path)
    out = folder / OUTPUT_DIR / "ckpt.npz"

    def run() -> None:
        code, stderr = run_cli(["export", str(path), str(out)])
        if code == 0:
            assert out.is_file(), "export succeeded without writing its file"
            return
        assert not any((folder / OUTPUT_DIR).glob("*")), "a failed export left a file"
        raise_cli_error(path, code, stderr)

    return run


def raise_cli_error(path: Path, code: int, stderr: str) -> None:
    """A failed CLI command must have printed one `error:` line and exited 2: re-raised as InputError."""
    if code != 2 or stderr.count("\n") != 1 or not stderr.startswith("error: "):
        raise AssertionError(f"exit {code}, stderr {stderr!r}")
    raise InputError(path, stderr.strip().removeprefix("error: "))


def run_cli(argv: list[str]) -> tuple[int, str]:
    """(exit code, stderr) of one in-process CLI command."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            main(argv)
            code = 0
        except SystemExit as e:
            code = e.code or 0
    return code, err.getvalue()


def _checkpoint(data: st.DataObject, folder: Path):
    path = folder / "checkpoints" / "step_0000010.npz"
    m = model()
    extra = m.extra_arrays() | {
        "optim/sigma_rms": np.ones(64, np.float32),
        "rng/state": np.arange(16, dtype=np.uint8),
    }
    save_grid(path, m.grid, m.meta() | {"level": 0}, extra)
    mutate_npz_file(data, path)
    return lambda: load_model(str(path))


def _tone_params(data: st.DataObject, folder: Path):
    path = folder / "tone_params.json"
    write_json(path, mutate_json(data, model().tonemapper.parameters_dict()))
    return lambda: load_tones(str(path))


def _camera_path(data: st.DataObject, folder: Path):
    """nerfstudio's camera_path.json as the viewer and `render --save-camera-path` write it."""
    path = folder / "camera_path.json"
    frames = [PathFrame(c2w, 50.0, ev=float(i), wb=(1.0, 0.9, 1.1)) for i, c2w in enumerate(cameras().c2w)]
    write_camera_path(path, CameraPath(frames, 16, 12, 24.0, keyframes=frames[:2]))
    write_json(path, mutate_json(data, json.loads(path.read_text())))
    return lambda: read_camera_path(path)


_RESUME_TEMPLATE: dict[str, Path] = {}
RESUME_ITERS = 5


def resume_template() -> Path:
    """A tiny run killed after its checkpoint at step 5 (model removed), the same run finished (`finished`),
    and their data (made once)."""
    if "root" not in _RESUME_TEMPLATE:
        root = Path(tempfile.mkdtemp(prefix="hdrplenoxels-fuzz-resume-"))
        atexit.register(shutil.rmtree, root, ignore_errors=True)
        write_nerfstudio(root / "data", cameras(), images(), NAMES)
        cfg = preset("fast")
        cfg.grid.reso_schedule = [(6, 6, 6)]
        cfg.optim.n_iters = cfg.checkpoint_every = RESUME_ITERS
        cfg.optim.batch_size = 64
        cfg.checkpoint_seconds = cfg.checkpoint_gap_seconds = 0.0  # a whole checkpoint at step 5
        cfg.tonemap.enabled = True
        cfg.device = "cpu"
        cfg.scene_mode = "bbox"  # the fuzzing cameras all look one way and state no bounds
        Trainer(load_scene(root / "data"), cfg, root / "run").run(progress=False)
        (root / "run" / MODEL_FILE).unlink()
        cfg.checkpoint_every = 0  # finished: its last checkpoint is the state beside the model
        Trainer(load_scene(root / "data"), cfg, root / "finished").run(progress=False)
        _RESUME_TEMPLATE["root"] = root
    return _RESUME_TEMPLATE["root"]


def _resume(data: st.DataObject, folder: Path):
    """`train --resume` on a run whose newest checkpoint (a whole one, or a finished run's state beside
    its model), config.json or log was mutated: it continues, or refuses with one error line and leaves
    the run folder as it was."""
    template = resume_template()
    run = folder / OUTPUT_DIR / "run"
    target = data.draw(st.sampled_from(["checkpoint", "checkpoint", "finished", "config", "log"]))
    shutil.copytree(template / ("finished" if target == "finished" else "run"), run)
    if target in ("checkpoint", "finished"):
        path = sorted((run / CHECKPOINT_DIR).glob("step_*.npz"))[-1]
        mutate_npz_file(data, path)
    elif target == "config":
        path = run / "config.json"
        _json_file(data, path)
    else:
        path = run / LOG_FILE
        path.write_bytes(mutate_bytes(data, path.read_bytes()))
    before = snapshot(run)

    def resume() -> None:
        argv = ["train", str(template / "data"), "--out", str(run), "--resume", "--quiet"]
        code, stderr = run_cli([*argv, "--iters", str(RESUME_ITERS + 2)])
        if code == 0:
            assert (run / MODEL_FILE).is_file(), "a resume succeeded without writing the model"
            return
        after = {k: v for k, v in snapshot(run).items() if k != LOCK_FILE}
        assert after == {k: v for k, v in before.items() if k != LOCK_FILE}, "a refused resume wrote files"
        raise_cli_error(path, code, stderr)

    return resume


def _poses(data: st.DataObject, folder: Path):
    suffix = data.draw(st.sampled_from([".npy", ".json", ".txt"]))
    path = folder / f"poses{suffix}"
    c2w = cameras().c2w
    if suffix == ".npy":
        np.save(path, c2w)
        mutate_npy_file(data, path)
    elif suffix == ".json":
        write_json(path, mutate_json(data, c2w.tolist()))
    else:
        np.savetxt(path, c2w.reshape(-1, 4))
        path.write_bytes(mutate_bytes(data, path.read_bytes()))
    convention = data.draw(st.sampled_from(["opengl", "opencv"]))
    return lambda: read_poses(path, convention)


def _exposures(data: st.DataObject, folder: Path):
    path = folder / "exposures.json"
    valid = data.draw(
        st.sampled_from(
            [
                {"v0": -1.0, "v1": 0.0, "v2": 1.0},
                {"views": [{"file": n, "ev": float(i)} for i, n in enumerate(NAMES)]},
            ]
        )
    )
    write_json(path, mutate_json(data, valid))
    return lambda: load_exposures(path, NAMES)


def write_video(path: Path, n_frames: int, rotation: int) -> None:
    """A tiny H.264 clip of noise; `rotation` in its display matrix (where this PyAV can write one)."""
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = 16, 12, "yuv420p"
        if rotation and hasattr(stream, "set_display_rotation"):
            stream.set_display_rotation(rotation)
        for i in range(n_frames):
            pixels = np.random.default_rng(i).integers(0, 256, (12, 16, 3), dtype=np.uint8)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(pixels, format="rgb24")))
        container.mux(stream.encode())


def _video(data: st.DataObject, folder: Path):
    """A video as `process` reads one: probed, every frame scored, the chosen ones written as photos
    (under the output folder)."""
    path = folder / f"clip{data.draw(st.sampled_from(VIDEO_EXTENSIONS))}"
    write_video(path, data.draw(st.integers(1, 6)), data.draw(st.sampled_from([0, 90, -90, 180])))
    if data.draw(st.integers(0, 9)) > 0:
        path.write_bytes(mutate_bytes(data, path.read_bytes()))
    return lambda: stage_video(path, video_info(path), folder / OUTPUT_DIR / "frames", 3)


def _exif_orientation(data: st.DataObject, folder: Path):
    """A photo whose EXIF orientation tag holds any value, staged as `process` stages it (turned upright
    into the output folder)."""
    path = folder / f"photo.{data.draw(st.sampled_from(['jpg', 'png', 'tif']))}"
    exif = Image.Exif()
    exif[0x0112] = data.draw(
        st.integers(0, 9) | st.integers(0, 65535) | st.text(max_size=4) | st.tuples(st.integers(0, 9))
    )
    size = (data.draw(st.integers(1, 12)), data.draw(st.integers(1, 12)))
    try:
        Image.new(data.draw(st.sampled_from(["RGB", "L", "RGBA"])), size, 128).save(path, exif=exif)
    except (OSError, ValueError, TypeError, struct.error):  # a value Pillow cannot write: no tag at all
        Image.new("RGB", size, 128).save(path)
    if data.draw(st.integers(0, 3)) == 0:
        path.write_bytes(mutate_bytes(data, path.read_bytes()))
    return lambda: stage_photos([path], folder / OUTPUT_DIR / "staged")


KINDS: dict[str, Kind] = {
    "transforms.json (nerfstudio)": Kind(_scene(_nerfstudio, _json_file)),
    "transforms.json (Blender / instant-ngp)": Kind(_scene(_blender_one_file, _json_file)),
    "sparse_points.npz": Kind(_scene(_sparse_points, mutate_npz_file)),
    "Blender splits": Kind(_scene(_blender_splits, _blender_split_mutation)),
    "LLFF poses_bounds.npy": Kind(_scene(_llff, mutate_npy_file)),
    "HDR-NeRF exposures": Kind(_scene(_hdrnerf, _hdrnerf_mutation)),
    "COLMAP binary": Kind(_scene(_colmap(text=False), _colmap_mutation)),
    "COLMAP text": Kind(_scene(_colmap(text=True), _colmap_mutation)),
    "images": Kind(_image),
    "model.npz (CLI export)": Kind(_model_cli),
    "model.npz of a cascade (CLI export)": Kind(functools.partial(_model_cli, levels=3)),
    "checkpoint": Kind(_checkpoint),
    "tone_params.json": Kind(_tone_params),
    "camera_path.json": Kind(_camera_path),
    "train --resume": Kind(_resume),
    "pose files": Kind(_poses),
    "exposure file": Kind(_exposures),
    "video files": Kind(_video),
    "EXIF orientation": Kind(_exif_orientation),
}


# ---------------------------------------------------------------------------- running one case
class _Timeout(BaseException):
    pass


def _alarm(signum, frame):
    raise _Timeout


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def outcome(read: Callable[[], object], folder: Path, limit_s: float = TIME_LIMIT_S) -> tuple[str, str]:
    """("ok" | "error" | "crash" | "timeout", detail). A read must not write: any new or changed file
    under `folder` (other than the CLI's own output, checked by that kind) is a crash."""
    before = snapshot(folder)
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, limit_s)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            read()
        result = ("ok", "")
    except InputError as e:
        line = f"error: {e}"
        one_line = "\n" not in line and e.path is not None
        result = ("error", line) if one_line else ("crash", f"not one line naming a file: {line!r}")
    except _Timeout:
        result = ("timeout", f"over {limit_s:.0f} s")
    except Exception:  # everything else is what fuzzing looks for
        result = ("crash", traceback.format_exc(limit=-4))
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    outside = f"{OUTPUT_DIR}/"
    after = {k: v for k, v in snapshot(folder).items() if not k.startswith(outside)}
    if result[0] != "crash" and after != {k: v for k, v in before.items() if not k.startswith(outside)}:
        result = ("crash", "reading the input wrote files")
    return result


def run_kind(name: str, examples: int, derandomize: bool, record: Callable[[str, str, str], None]) -> None:
    """Run `examples` Hypothesis cases of one kind, calling `record(kind, outcome, detail)` for each."""

    @settings(
        max_examples=examples,
        derandomize=derandomize,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
        phases=[p for p in settings.default.phases if p.name != "shrink"],
    )
    @given(st.data())
    def case(data):
        with tempfile.TemporaryDirectory(prefix="hdrplenoxels-fuzz-") as tmp:
            folder = Path(tmp)
            read = KINDS[name].build(data, folder)
            record(name, *outcome(read, folder))

    case()


def _one_kind(kind: str, examples: int) -> None:
    """Child process of `main_fuzz`: one kind's tally as a JSON line, then its crashes."""
    tally: Counter = Counter()
    crashes: list[str] = []

    def record(_: str, result: str, detail: str) -> None:
        tally[result] += 1
        if result in ("crash", "timeout") and len(crashes) < 10:
            crashes.append(f"--- {kind}: {result}\n{detail}")

    run_kind(kind, examples, derandomize=False, record=record)
    print(json.dumps(tally))
    print("\n".join(crashes))


def main_fuzz(argv: list[str] | None = None) -> int:
    """Each kind in its own process, so that a hang inside C++ code (which no Python timer interrupts)
    or a crash of the interpreter is counted instead of stopping the run."""
    parser = argparse.ArgumentParser(description="Fuzz every input kind; print outcomes per kind.")
    parser.add_argument("--examples", type=int, default=1000, help="cases per input kind")
    parser.add_argument("--kinds", nargs="*", default=sorted(KINDS), help="input kinds (default: all)")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        _one_kind(args.one, args.examples)
        return 0
    tally: dict[str, Counter] = {}
    t0 = time.perf_counter()
    for kind in args.kinds:
        cmd = [sys.executable, __file__, "--one", kind, "--examples", str(args.examples)]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=TIME_LIMIT_S * args.examples)
            first, _, rest = done.stdout.partition("\n")
            tally[kind] = Counter(json.loads(first)) if done.returncode == 0 else Counter(crash=1)
            report = rest.strip() if done.returncode == 0 else done.stdout[-2000:] + done.stderr[-2000:]
        except subprocess.TimeoutExpired:
            tally[kind], report = Counter(timeout=1), "the kind's process did not finish"
        print(f"{kind}: {dict(tally[kind])}", file=sys.stderr, flush=True)
        if report:
            print(report, file=sys.stderr)
    print(f"\n| input kind | cases | {' | '.join(OUTCOMES)} |\n|---|---:|" + "---:|" * len(OUTCOMES))
    for kind, counts in tally.items():
        print(f"| {kind} | {sum(counts.values())} | " + " | ".join(str(counts[o]) for o in OUTCOMES) + " |")
    total = sum(tally.values(), Counter())
    print(f"| **all** | {sum(total.values())} | " + " | ".join(str(total[o]) for o in OUTCOMES) + " |")
    print(f"\n{time.perf_counter() - t0:.0f} s")
    return 1 if total["crash"] or total["timeout"] else 0


if __name__ == "__main__":
    sys.exit(main_fuzz())
