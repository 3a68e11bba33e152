"""Every writer under a failing file system (disk full part-way through a write, a read-only or forbidden
folder, a failing fsync or rename): the previous file is intact, no temporary file is left, the error is one
`WriteError` line naming the file and the cause, and through the CLI one `error:` line with exit code 74.
A file known not to fit is refused before anything is written."""

from __future__ import annotations

import errno
import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from faults import FAULTS, inject, snapshot, tmpfs

from hdrplenoxels.cli.main import EXIT_WRITE_ERROR, main
from hdrplenoxels.core import atomic
from hdrplenoxels.core.atomic import atomic_write_text
from hdrplenoxels.core.errors import WriteError
from hdrplenoxels.data import image_io
from hdrplenoxels.data.colmap import write_colmap
from hdrplenoxels.data.image_io import write_exr, write_png
from hdrplenoxels.data.llff import write_llff
from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.data.writers import write_blender, write_nerfstudio
from hdrplenoxels.experiments.report import write_report
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.grid.io import export_svox2, load_grid, save_grid
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.synth.procedural import ProceduralSceneSpec, write_procedural_scene
from hdrplenoxels.tonemap.config import ToneMapConfig
from hdrplenoxels.tonemap.module import ToneMapper
from hdrplenoxels.tonemap.plots import plot_tone_params
from hdrplenoxels.train.model import MODEL_FILE, Model
from hdrplenoxels.train.run_state import is_run_state, load_run_state


# ---------------------------------------------------------------------------- small things to write
def grid(version: int) -> SparseGrid:
    g = SparseGrid.create((4, 4, 4), basis_dim=4, init_sigma=0.1 + version)
    g.sh.add_(float(version))
    return g


def cameras(version: int, n: int = 3) -> Cameras:
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 2, 3] = -3.0 - np.arange(n) - version
    return Cameras(c2w, np.tile([10.0, 10.0, 4.0, 4.0], (n, 1)), np.tile([8, 8], (n, 1)))


def model(version: int) -> Model:
    geometry = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4))
    return Model(grid(version), geometry, RenderOptions(), cameras(version, 1), ["a.png"], [], [0], "x")


def image(version: int) -> np.ndarray:
    return np.random.default_rng(version).random((24, 32, 3))


def tone_params(version: int) -> dict:
    tm = ToneMapper(3, np.tile([8, 8], (3, 1)), ToneMapConfig(enabled=True))
    tm.log_wb.data += version
    return tm.parameters_dict() | {"names": ["a", "b", "c"]}


@dataclass
class Writer:
    target: str  # relative to the test folder: the file (or folder) the fault hits
    write: Callable[[Path, int], object]  # (folder, version)
    skip: tuple[str, ...] = ()  # faults this writer can't be reached by (a C++ writer's own writes)


WRITERS = {
    "model.npz / checkpoint": Writer(
        "model.npz",
        lambda d, v: save_grid(d / "model.npz", grid(v), {"v": v}, {"optim/x": np.arange(99) + v}),
    ),
    "model (Model.save)": Writer("run/model.npz", lambda d, v: model(v).save(d / "run" / MODEL_FILE)),
    "svox2 export": Writer("ckpt.npz", lambda d, v: export_svox2(d / "ckpt.npz", grid(v))),
    "render PNG": Writer("renders/r_0.png", lambda d, v: write_png(d / "renders/r_0.png", image(v))),
    "render EXR": Writer("renders/r_0.exr", lambda d, v: write_exr(d / "renders/r_0.exr", image(v))),
    "report (report.md after report.json)": Writer(
        "exp/report.md",
        lambda d, v: write_report(d / "exp", {"experiment": "x", "v": v}, f"# v{v}\n" + "| a | b |\n" * 9),
    ),
    "config.json": Writer(
        "config.json", lambda d, v: atomic_write_text(d / "config.json", json.dumps({"v": [v] * 99}))
    ),
    "tone_params.png": Writer(
        "tone_params.png", lambda d, v: plot_tone_params(tone_params(v), d / "tone_params.png")
    ),
    "transforms.json (process, synth)": Writer(
        "ds/transforms.json",
        lambda d, v: write_nerfstudio(d / "ds", cameras(v), [image(v)] * 3, ["a.png", "b.png", "c.png"]),
    ),
    "Blender splits": Writer(
        "bl/transforms_test.json", lambda d, v: write_blender(d / "bl", cameras(v), [0, 1], [2])
    ),
    "poses_bounds.npy": Writer(
        "llff/poses_bounds.npy", lambda d, v: write_llff(d / "llff", cameras(v), [[1.0, 9.0 + v]] * 3)
    ),
    "COLMAP model": Writer(
        "sparse/0",
        lambda d, v: write_colmap(d / "sparse/0", cameras(v), ["a.png", "b.png", "c.png"]),
        skip=("enospc-mid-write", "enospc-fsync"),  # pycolmap writes the files itself, without fsync
    ),
    "synth procedural scene": Writer(
        "proc/transforms.json",
        lambda d, v: write_procedural_scene(
            d / "proc", ProceduralSceneSpec(grid_reso=8, num_views=2, width=8, height=8, seed=v)
        ),
    ),
}


def _exr_fails_mid_write(monkeypatch, inj) -> None:
    """OpenEXR writes its file from C++, past Python's `open`: write half of it, then report as OpenEXR
    does on a full disk (a RuntimeError; measured on a full tmpfs, see test_real_full_disk)."""
    real = image_io._write_exr_file

    def failing(tmp: Path, rgb: np.ndarray) -> None:
        real(tmp, rgb)
        with open(tmp, "r+b") as f:
            f.truncate(os.path.getsize(tmp) // 2)
        inj.hits.append(str(tmp))
        raise RuntimeError(f'Failed to write pixel data to image file "{tmp}". No space left on device.')

    monkeypatch.setattr(image_io, "_write_exr_file", failing)


@pytest.mark.parametrize("fault", sorted(FAULTS))
@pytest.mark.parametrize("name", sorted(WRITERS))
def test_writer_keeps_the_previous_file(tmp_path, monkeypatch, name, fault):
    writer = WRITERS[name]
    if fault in writer.skip:
        pytest.skip(f"{name} writes its files itself")
    target = tmp_path / writer.target
    writer.write(tmp_path, 0)
    before = snapshot(tmp_path)
    with inject(monkeypatch, fault, target) as inj:
        if name == "render EXR" and fault == "enospc-mid-write":
            _exr_fails_mid_write(monkeypatch, inj)
        with pytest.raises(WriteError) as caught:
            writer.write(tmp_path, 1)
    assert inj.hits, "the fault never struck: the writer went around the injected file system"
    cause = os.strerror(FAULTS[fault][1])
    assert str(caught.value) == f"{target}: can't write ({cause})"
    after = snapshot(tmp_path)
    assert after.keys() == before.keys(), "a temporary file was left behind (or a file vanished)"
    old = {k: v for k, v in before.items() if (tmp_path / k).is_relative_to(target)}
    assert old and all(after[k] == v for k, v in old.items()), "the previous file was damaged"
    monkeypatch.undo()
    writer.write(tmp_path, 1)  # the disk is fine again: the same call now succeeds and changes the file
    assert snapshot(tmp_path).keys() == before.keys()
    assert any(snapshot(tmp_path)[k] != v for k, v in old.items())


def test_a_checkpoint_that_cannot_fit_is_refused_before_writing(tmp_path, monkeypatch):
    path = tmp_path / "checkpoints" / "step_0000010.npz"
    save_grid(path, grid(0))
    before = snapshot(tmp_path)
    g = grid(1)
    stored = g.density.numel() * 4 + g.sh.numel() * 4  # float arrays are stored as they are
    free = stored // 2
    monkeypatch.setattr(atomic.shutil, "disk_usage", lambda _: shutil._ntuple_diskusage(10**9, 10**9, free))
    monkeypatch.setattr(atomic.tempfile, "mkstemp", lambda **_: pytest.fail("a file was created"))
    with pytest.raises(WriteError) as caught:
        save_grid(path, g)
    assert caught.value.errno == errno.ENOSPC
    assert str(caught.value).startswith(f"{path}: can't write (No space left on device: needs at least")
    assert snapshot(tmp_path) == before


def test_real_full_disk(tmp_path):
    """A real 1.5 MiB file system with old files on it: the C++ writers (OpenEXR) and Pillow fail
    part-way for real, the grid writer refuses up front, and the old files survive."""
    try:
        disk_cm = tmpfs(tmp_path / "disk", 1536)
        disk = disk_cm.__enter__()
    except PermissionError as e:
        pytest.skip(f"can't mount a small file system here: {e}")
    try:
        small = np.random.default_rng(0).random((8, 8, 3))
        big = np.random.default_rng(1).random((768, 1024, 3))  # ~9 MiB as EXR, ~2.3 MiB as PNG
        write_exr(disk / "r.exr", small)
        write_png(disk / "r.png", small)
        save_grid(disk / "model.npz", grid(0))
        before = snapshot(disk)
        for write, name in (
            (lambda: write_exr(disk / "r.exr", big), "r.exr"),
            (lambda: write_png(disk / "r.png", big), "r.png"),
            (
                lambda: save_grid(disk / "model.npz", SparseGrid.create((24, 24, 24), basis_dim=4)),
                "model.npz",
            ),
        ):
            with pytest.raises(WriteError) as caught:
                write()
            assert str(caught.value).startswith(f"{disk / name}: can't write (No space left on device")
            assert snapshot(disk) == before
        np.testing.assert_allclose(image_io.read_exr(disk / "r.exr"), small, atol=1e-6)
    finally:
        disk_cm.__exit__(None, None, None)


# ---------------------------------------------------------------------------- through the CLI
def run_cli(argv: list[str], capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as done:
        main(argv)
    return done.value.code, capsys.readouterr().err


def test_cli_export_to_a_full_disk(tmp_path, monkeypatch, capsys):
    model(0).save(tmp_path / MODEL_FILE)
    out = tmp_path / "ckpt.npz"
    export_svox2(out, grid(5))
    old = out.read_bytes()
    with inject(monkeypatch, "enospc-mid-write", out):
        code, err = run_cli(["export", str(tmp_path / MODEL_FILE), str(out)], capsys)
    assert code == EXIT_WRITE_ERROR
    assert err == f"error: {out}: can't write (No space left on device)\n"
    assert out.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.npz", MODEL_FILE]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    spec = ProceduralSceneSpec(grid_reso=16, num_views=8, width=16, height=16)
    return write_procedural_scene(tmp_path_factory.mktemp("scene"), spec)


TRAIN = [
    "--iters", "12", "--batch-size", "256", "--tonemap", "--quiet", "--device", "cpu",
    "--set", "grid.reso_schedule=[[8,8,8]]", "--set", "checkpoint_every=6", "--set", "log_every=3",
]  # fmt: skip


@pytest.mark.parametrize(
    ("target", "fault"),
    [
        ("checkpoints/step_0000012.npz", "enospc-mid-write"),
        ("model.npz", "erofs-rename"),
        ("tone_params.json", "enospc-fsync"),
        ("train_log.jsonl", "enospc-mid-write"),  # the log is appended to, not replaced
    ],
)
def test_cli_train_on_a_failing_disk(tmp_path, monkeypatch, capsys, scene, target, fault):
    """A resumed run that fails to write `target`: one line naming it, exit 74, the files of the first
    part intact, the lock released (a later --resume finishes the run)."""
    run = tmp_path / "run"
    assert main_ok(["train", str(scene), "--out", str(run), *TRAIN[:1], "6", *TRAIN[2:]])
    before = snapshot(run)
    with inject(monkeypatch, fault, run / target) as inj:
        if target == "train_log.jsonl":  # the append itself, not the resume's rewrite of the log
            inj.matches = lambda p: not isinstance(p, int) and Path(os.fsdecode(p)) == run / target
        code, err = run_cli(["train", str(scene), "--out", str(run), "--resume", *TRAIN], capsys)
    assert inj.hits
    assert code == EXIT_WRITE_ERROR
    cause = os.strerror(FAULTS[fault][1])
    assert err.count("\n") == 1 and err.startswith("error: ") and "Traceback" not in err
    assert f"{run / target}: " in err and cause in err
    after = snapshot(run)
    if target in before and target != "train_log.jsonl":
        assert after[target] == before[target], "the previous file was damaged"
    assert all(after[k] == v for k, v in before.items() if k.startswith("checkpoints/"))
    assert after["train_log.jsonl"].startswith(before["train_log.jsonl"])
    for name in after:  # whatever the run did write before the fault is complete
        if name.endswith(".npz"):  # a grid, or a finished run's last checkpoint without its field
            load_run_state(run / name) if is_run_state(run / name) else load_grid(run / name)
    assert not [k for k in after if Path(k).name.startswith(".") and k != ".lock"], "temporary file left"
    monkeypatch.undo()
    assert main_ok(["train", str(scene), "--out", str(run), "--resume", *TRAIN])
    assert load_grid(run / MODEL_FILE)[1]["step"] == 12


def main_ok(argv: list[str]) -> bool:
    try:
        main(argv)
    except SystemExit as e:
        return e.code in (0, None)
    return True


def test_cli_train_into_a_read_only_folder(tmp_path, monkeypatch, capsys, scene):
    run = tmp_path / "run"
    run.mkdir()
    with inject(monkeypatch, "erofs-create", run / ".lock"):
        code, err = run_cli(["train", str(scene), "--out", str(run), *TRAIN], capsys)
    assert code == EXIT_WRITE_ERROR
    assert err == f"error: {run / '.lock'}: Read-only file system\n"
    assert list(run.iterdir()) == []


@pytest.mark.skipif(
    os.geteuid() == 0, reason="root writes into read-only folders (faults are injected above)"
)
def test_cli_train_into_a_chmod_read_only_folder(tmp_path, capsys, scene):
    run = tmp_path / "run"
    run.mkdir()
    run.chmod(0o555)
    try:
        code, err = run_cli(["train", str(scene), "--out", str(run), *TRAIN], capsys)
    finally:
        run.chmod(0o755)
    assert code == EXIT_WRITE_ERROR
    assert err.startswith(f"error: {run}") and "Permission denied" in err and err.count("\n") == 1


def test_cli_process_on_a_full_disk_keeps_the_old_dataset(tmp_path, monkeypatch, capsys):
    """`process` fails while staging (a greyscale photo is converted to PNG): OUT keeps its old content
    and no partial folder is left beside it."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        write_png(photos / f"p{i}.png", np.random.default_rng(i).random((16, 16)))
    out = tmp_path / "out"
    out.mkdir()
    (out / "transforms.json").write_text("{}")
    with inject(monkeypatch, "enospc-mid-write", Path("p0.png")) as inj:
        inj.matches = lambda p: not isinstance(p, int) and Path(os.fsdecode(p)).name.startswith(".p0.png.")
        code, err = run_cli(["process", str(photos), str(out), "--overwrite"], capsys)
    assert code == EXIT_WRITE_ERROR
    lines = err.strip().splitlines()
    assert lines[-1].startswith("error: ") and lines[-1].endswith(
        "p0.png: can't write (No space left on device)"
    )
    assert "Traceback" not in err
    assert snapshot(out) == {"transforms.json": b"{}"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "photos"]


@pytest.mark.parametrize("name", sorted(WRITERS))
def test_every_writer_leaves_files_as_the_umask_says(tmp_path, name):
    """Temporary files are owner-only; what lands must read like any new file (0644 under umask 022)."""
    old = os.umask(0o022)
    try:
        WRITERS[name].write(tmp_path, 0)
    finally:
        os.umask(old)
    modes = {str(p.relative_to(tmp_path)): oct(p.stat().st_mode & 0o777) for p in tmp_path.rglob("*")}
    expected = {n: oct(0o755 if (tmp_path / n).is_dir() else 0o644) for n in modes}
    assert modes and modes == expected
