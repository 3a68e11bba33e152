"""The `hdrplenoxels` command end to end: one fast training run, then eval, render, poses, export/import,
resume; malformed input as real subprocesses (one `error:` line, exit code 2); `--help` of every command.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hdrplenoxels.cli.main import EXIT_INPUT_ERROR, main
from hdrplenoxels.core.devices import pick_device
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.image_io import read_exr, read_image, write_png
from hdrplenoxels.data.placement import SceneGeometry
from hdrplenoxels.geometry.cameras import Cameras
from hdrplenoxels.grid.io import export_svox2
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render import RenderOptions
from hdrplenoxels.synth.procedural import ProceduralSceneSpec, write_procedural_scene
from hdrplenoxels.tonemap.config import SPARSE_BRACKET
from hdrplenoxels.train.model import MODEL_FILE, Model

PSNR_TARGET = 30.0
SPEC = ProceduralSceneSpec()
TEST_IDS = list(range(0, SPEC.num_views, 8))
SUBCOMMANDS = ("train", "render", "eval", "export", "import-svox2", "demo")


def run_cli(argv: list[str]) -> None:
    """`main(argv)` in-process; a non-zero exit fails the test with its code."""
    try:
        main(argv)
    except SystemExit as e:  # pragma: no cover - only on failure
        if e.code not in (0, None):
            pytest.fail(f"hdrplenoxels {' '.join(argv)} exited with {e.code}")


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return -10.0 * math.log10(max(mse, 1e-20))


# ============================================================================ one trained run
@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> SimpleNamespace:
    root = tmp_path_factory.mktemp("cli")
    scene_json = write_procedural_scene(root / "scene", SPEC)
    run = root / "run"
    t0 = time.perf_counter()
    run_cli(
        ["train", str(scene_json.parent), "--preset", "fast", "--no-tonemap", "--out", str(run), "--quiet"]
    )
    seconds = time.perf_counter() - t0
    return SimpleNamespace(
        root=root, scene=scene_json.parent, scene_json=scene_json, run=run, seconds=seconds
    )


@pytest.fixture(scope="module")
def test_renders(trained) -> Path:
    """`render RUN --out D` of the test views (shared by the render, pose and svox2 tests)."""
    out = trained.root / "renders"
    run_cli(["render", str(trained.run), "--out", str(out)])
    return out


def frame_name(i: int) -> str:
    return f"frame_{i:03d}"


def test_fast_preset_acceptance(trained):
    j = trained.root / "metrics.json"
    run_cli(["eval", str(trained.run), "--json", str(j)])
    result = json.loads(j.read_text())
    for key in ("psnr", "ssim", "lpips_vgg", "lpips_alex"):
        assert isinstance(result[key], float), key
        assert math.isfinite(result[key]), key
    assert len(result["views"]) == result["num_test_views"] == len(TEST_IDS) == 5
    assert [v["index"] for v in result["views"]] == TEST_IDS
    assert result["holdout"] == "right-half"
    assert "right half" in result["protocol"]
    assert result["psnr"] >= PSNR_TARGET, result["psnr"]
    # Training time is reported, not asserted (a shared 2-core machine's wall time is no test).
    print(f"fast preset: {result['psnr']:.2f} dB PSNR, training {trained.seconds:.1f} s")


def test_eval_prints_table(trained, capsys):
    capsys.readouterr()
    run_cli(["eval", str(trained.run), "--no-lpips"])
    out = capsys.readouterr().out
    assert "mean" in out
    assert "psnr" in out and "ssim" in out
    for i in TEST_IDS:
        assert f"images/{frame_name(i)}.png" in out
    assert "protocol:" in out


def test_render_writes_png_and_exr_per_test_view(test_renders):
    pngs = sorted(p.stem for p in test_renders.glob("*.png"))
    exrs = sorted(p.stem for p in test_renders.glob("*.exr"))
    assert pngs == exrs == [frame_name(i) for i in TEST_IDS]
    for name in pngs:
        hdr = read_exr(test_renders / f"{name}.exr")
        assert hdr.dtype == np.float32
        assert hdr.shape == (SPEC.height, SPEC.width, 3)
        assert np.isfinite(hdr).all()
        ldr = read_image(test_renders / f"{name}.png")
        expected = np.round(np.clip(hdr, 0.0, 1.0) * 255.0).astype(np.int16)
        assert np.abs(expected - ldr.astype(np.int16)).max() <= 1, name


def test_render_pose_file_matches_test_view(trained, test_renders):
    """A transforms.json (OpenGL) pose rendered via --pose equals the render of that test view."""
    frames = json.loads(trained.scene_json.read_text())["frames"]
    i, k = TEST_IDS[1], TEST_IDS[2]
    pose_json = trained.root / "pose.json"
    pose_json.write_text(json.dumps(frames[i]["transform_matrix"]))
    out = trained.root / "pose_render"
    run_cli(["render", str(trained.run), "--pose", str(pose_json), "--out", str(out)])
    assert sorted(p.name for p in out.iterdir()) == ["pose_000.exr", "pose_000.png"]
    ref = read_exr(test_renders / f"{frame_name(i)}.exr")
    assert np.abs(read_exr(out / "pose_000.exr") - ref).max() <= 1e-4

    # Two stacked poses in an .npy render two images, in order.
    pose_npy = trained.root / "poses.npy"
    np.save(pose_npy, np.array([frames[i]["transform_matrix"], frames[k]["transform_matrix"]]))
    out2 = trained.root / "pose_render_npy"
    run_cli(["render", str(trained.run), "--pose", str(pose_npy), "--out", str(out2)])
    assert sorted(p.stem for p in out2.glob("*.exr")) == ["pose_000", "pose_001"]
    assert len(list(out2.glob("*.png"))) == 2
    assert np.abs(read_exr(out2 / "pose_000.exr") - ref).max() <= 1e-4
    ref_k = read_exr(test_renders / f"{frame_name(k)}.exr")
    assert np.abs(read_exr(out2 / "pose_001.exr") - ref_k).max() <= 1e-4

    # OpenCV convention: the same camera with y and z flipped.
    cv = np.asarray(frames[i]["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0])
    pose_txt = trained.root / "pose_cv.txt"
    np.savetxt(pose_txt, cv)
    out3 = trained.root / "pose_render_cv"
    argv = ["render", str(trained.run), "--pose", str(pose_txt), "--pose-convention", "opencv"]
    run_cli([*argv, "--out", str(out3)])
    assert np.abs(read_exr(out3 / "pose_000.exr") - ref).max() <= 1e-4


def test_export_import_svox2_round_trip(trained, test_renders):
    ckpt = trained.root / "export" / "ckpt.npz"
    ckpt.parent.mkdir()
    run_cli(["export", str(trained.run), str(ckpt)])
    with np.load(ckpt, allow_pickle=False) as z:
        assert {"links", "density_data", "sh_data", "radius", "center", "basis_type"} <= set(z.files)
        assert z["sh_data"].dtype == np.float16
    run2 = trained.root / "run_svox2"
    run_cli(["import-svox2", str(ckpt), str(trained.scene), "--out", str(run2)])
    assert (run2 / MODEL_FILE).is_file()
    out = trained.root / "renders_svox2"
    run_cli(["render", str(run2), "--out", str(out)])
    for i in TEST_IDS:
        a = read_exr(test_renders / f"{frame_name(i)}.exr")
        b = read_exr(out / f"{frame_name(i)}.exr")
        assert a.shape == b.shape
        # Only the float16 rounding of the SH differs (measured: ~7e-5 max, > 100 dB); 30x margin.
        assert np.abs(a - b).max() <= 2e-3, i
        assert psnr(a, b) > 60.0, i


def test_train_resume_continues_from_last_checkpoint(trained):
    run = trained.root / "run_resume"  # a copy, so the other tests keep the 600-step run
    shutil.copytree(trained.run, run)
    log = run / "train_log.jsonl"
    before = [json.loads(line)["step"] for line in log.read_text().splitlines()]
    assert before[-1] == 600
    argv = ["train", str(trained.scene), "--preset", "fast", "--out", str(run), "--quiet"]
    run_cli([*argv, "--iters", "620", "--resume"])
    after = [json.loads(line)["step"] for line in log.read_text().splitlines()]
    assert after[: len(before)] == before
    new = after[len(before) :]
    assert new and all(s > 600 for s in new), new
    assert new[-1] == 620
    assert (run / "checkpoints" / "step_0000620.npz").is_file()
    assert Model.load(run / MODEL_FILE).step == 620


# ============================================================================ malformed input
def _run_subprocess(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "COLUMNS": "200"}
    return subprocess.run(
        [sys.executable, "-m", "hdrplenoxels", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _tiny_dataset(folder: Path, n: int = 3, size: int = 8, **meta) -> Path:
    """A hand-made nerfstudio scene: `n` solid-colour `size`x`size` PNGs and a transforms.json."""
    frames = []
    for i in range(n):
        name = f"images/img_{i}.png"
        write_png(folder / name, np.full((size, size, 3), 40 * i + 20, dtype=np.uint8))
        pose = np.eye(4)
        pose[:3, 3] = [0.0, 0.0, 3.0 + i]
        frames.append({"file_path": name, "transform_matrix": pose.tolist()})
    base = {"fl_x": 10.0, "fl_y": 10.0, "cx": size / 2, "cy": size / 2, "w": size, "h": size}
    base["aabb"] = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]  # the views all look one way: say where the scene is
    path = folder / "transforms.json"
    path.write_text(json.dumps({**base, **meta, "frames": frames}))
    return path


def _tiny_model(path: Path) -> Path:
    """A valid (untrained) model file with one camera, for the --pose case."""
    grid = SparseGrid.create((4, 4, 4), basis_dim=1)
    geometry = SceneGeometry("bbox", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), np.eye(4))
    pose = np.eye(4)
    pose[2, 3] = -3.0
    cams = Cameras(pose[None], np.array([[10.0, 10.0, 4.0, 4.0]]), np.array([[8, 8]]))
    Model(grid, geometry, RenderOptions(), cams, ["a.png"], [], [0], "nowhere").save(path)
    return path


def _case_missing_data(tmp: Path) -> tuple[list[str], Path, str]:
    missing = tmp / "no_such_scene"
    return ["train", str(missing), "--out", str(tmp / "run")], missing, "does not exist"


def _case_bad_json(tmp: Path) -> tuple[list[str], Path, str]:
    path = _tiny_dataset(tmp / "scene")
    path.write_text(path.read_text()[:-5] + ",,}")
    return ["train", str(path.parent), "--out", str(tmp / "run")], path, "invalid JSON"


def _case_missing_image(tmp: Path) -> tuple[list[str], Path, str]:
    path = _tiny_dataset(tmp / "scene")
    image = path.parent / "images" / "img_1.png"
    image.unlink()
    return ["train", str(path), "--out", str(tmp / "run")], image, "not found"


def _case_wrong_size(tmp: Path) -> tuple[list[str], Path, str]:
    path = _tiny_dataset(tmp / "scene", w=16, h=12)
    return ["train", str(path), "--out", str(tmp / "run")], path.parent / "images" / "img_0.png", "8x8"


def _case_render_random_npz(tmp: Path) -> tuple[list[str], Path, str]:
    path = tmp / "model.npz"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    return ["render", str(path), "--out", str(tmp / "out")], path, "not a readable .npz"


def _case_eval_svox2(tmp: Path) -> tuple[list[str], Path, str]:
    path = export_svox2(tmp / "ckpt.npz", SparseGrid.create((4, 4, 4)))
    return ["eval", str(path)], path, "Plenoxels (svox2) checkpoint"


def _case_non_rigid_pose(tmp: Path) -> tuple[list[str], Path, str]:
    model = _tiny_model(tmp / "model.npz")
    pose = tmp / "pose.json"
    pose.write_text(json.dumps((np.diag([2.0, 1.0, 1.0, 1.0])).tolist()))
    return ["render", str(model), "--pose", str(pose), "--out", str(tmp / "out")], pose, "not a rigid"


MALFORMED = {
    "missing-data-path": _case_missing_data,
    "invalid-json": _case_bad_json,
    "missing-image": _case_missing_image,
    "image-size-mismatch": _case_wrong_size,
    "render-random-bytes-npz": _case_render_random_npz,
    "eval-svox2-ckpt": _case_eval_svox2,
    "non-rigid-pose": _case_non_rigid_pose,
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_input_gives_one_error_line(case, tmp_path):
    args, offender, problem = MALFORMED[case](tmp_path)
    proc = _run_subprocess(args, tmp_path)
    assert proc.returncode == EXIT_INPUT_ERROR, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error:"), lines[0]
    assert str(offender) in lines[0], lines[0]
    assert problem in lines[0], lines[0]


def test_a_missing_gpu_is_one_error_line_before_anything_is_written(tmp_path):
    scene = _tiny_dataset(tmp_path / "scene")
    args = ["train", str(scene), "--device", "cuda:99", "--out", str(tmp_path / "run")]
    proc = _run_subprocess(args, tmp_path)
    assert proc.returncode == EXIT_INPUT_ERROR, (proc.returncode, proc.stderr)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: --device cuda:99"), proc.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name", ["gpu", "mps", "cuda:99"])
def test_device_names_are_checked(name, tmp_path, capsys):
    with pytest.raises(InputError, match=f"--device {name}"):
        pick_device(name)
    out = tmp_path / "experiment"
    with pytest.raises(SystemExit) as e:  # refused before the experiment renders its scenes
        main(["experiment", "crf-transfer", str(out), "--iters", "1", "--device", name])
    assert e.value.code == EXIT_INPUT_ERROR and f"--device {name}" in capsys.readouterr().err
    assert not out.exists()
    assert pick_device("cpu") == torch.device("cpu")
    assert pick_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.parametrize("command", ["render", "eval"])
@pytest.mark.parametrize("kind", ["random-bytes", "svox2"])
def test_render_eval_refuse_non_model_files_in_process(command, kind, tmp_path, capsys):
    """The other render/eval x bad-file combinations, in-process (same `main`, no interpreter start)."""
    if kind == "svox2":
        path, problem = export_svox2(tmp_path / "ckpt.npz", SparseGrid.create((4, 4, 4))), "svox2"
    else:
        path, problem = tmp_path / "m.npz", "not a readable .npz"
        path.write_bytes(np.random.default_rng(1).bytes(1000))
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main([command, str(path)])
    assert exc.value.code == EXIT_INPUT_ERROR
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("error:") and str(path) in err[0]
    assert problem in err[0]
    if kind == "svox2":
        assert "Plenoxels" in err[0]


def _pose_json_object(tmp: Path) -> Path:
    path = tmp / "frame.json"
    path.write_text(json.dumps({"transform_matrix": np.eye(4).tolist()}))
    return path


def _pose_mirror(tmp: Path) -> Path:
    path = tmp / "mirror.json"
    path.write_text(json.dumps(np.diag([-1.0, 1.0, 1.0, 1.0]).tolist()))
    return path


def _pose_strings_npy(tmp: Path) -> Path:
    path = tmp / "strings.npy"
    np.save(path, np.array(["1"] * 16))
    return path


def _pose_3x4(tmp: Path) -> Path:
    path = tmp / "pose.txt"
    np.savetxt(path, np.eye(4)[:3])
    return path


@pytest.mark.parametrize(
    "make, problem",
    [
        (_pose_json_object, "got dict"),
        (_pose_mirror, "reflection"),
        (_pose_strings_npy, "dtype"),
        (_pose_3x4, "4x4"),
    ],
    ids=["json-object", "mirror", "string-npy", "3x4-text"],
)
def test_bad_pose_files_in_process(make, problem, tmp_path, capsys):
    model = _tiny_model(tmp_path / "model.npz")
    pose = make(tmp_path)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["render", str(model), "--pose", str(pose), "--out", str(tmp_path / "out")])
    assert exc.value.code == EXIT_INPUT_ERROR
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith(f"error: {pose}:") and problem in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("option", ["--iters", "--batch-size"])
def test_train_refuses_non_positive_counts(option, tmp_path, capsys):
    scene = _tiny_dataset(tmp_path / "scene")
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["train", str(scene), "--out", str(tmp_path / "run"), option, "0"])
    assert exc.value.code == 2
    assert option in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


# ============================================================================ help
@pytest.mark.parametrize("command", SUBCOMMANDS)
def test_subcommand_help(command, capsys):
    capsys.readouterr()
    try:
        main([command, "--help"])
    except SystemExit as e:  # pragma: no cover - click versions differ in how --help exits
        assert e.code in (0, None)
    out = capsys.readouterr().out
    assert f"Usage: hdrplenoxels {command}" in out
    assert "--help" in out
    lines = [line.strip() for line in out.splitlines() if line.strip()]
    description = lines[1]  # the line after "Usage: ..."
    assert len(description) > 20 and not description.startswith("-"), out


def test_version_prints_the_installed_packages_version(capsys):
    from importlib.metadata import version

    main(["--version"])
    assert capsys.readouterr().out.strip() == f"hdrplenoxels, version {version('hdrplenoxels')}"


def test_group_help_lists_every_subcommand(capsys):
    capsys.readouterr()
    try:
        main(["--help"])
    except SystemExit as e:  # pragma: no cover
        assert e.code in (0, None)
    out = capsys.readouterr().out
    for command in SUBCOMMANDS:
        assert command in out


def test_tiny_model_renders(tmp_path):
    """The hand-built model used for the --pose case is itself valid (so the case tests the pose)."""
    model = _tiny_model(tmp_path / "model.npz")
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps(np.eye(4).tolist()))
    run_cli(["render", str(model), "--pose", str(pose), "--out", str(tmp_path / "out"), "--backend", "torch"])
    img = read_exr(tmp_path / "out" / "pose_000.exr")
    assert img.shape == (8, 8, 3) and torch.isfinite(torch.from_numpy(img)).all()


def test_train_response_prior_sets_the_tone_config_and_needs_the_tone_mapper(tmp_path, capsys):
    scene = _tiny_dataset(tmp_path / "scene")
    main(
        ["train", str(scene), "--out", str(tmp_path / "run"), "--iters", "1", "--tonemap"]
        + ["--response-prior", "0.01", "--quiet"]
    )
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["tonemap"]["lambda_crf_loglog"] == 0.01
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(
            [
                "train",
                str(scene),
                "--out",
                str(tmp_path / "plain"),
                "--no-tonemap",
                "--response-prior",
                "0.01",
            ]
        )
    assert exc.value.code == 2
    assert "--response-prior" in capsys.readouterr().err
    assert not (tmp_path / "plain").exists()


def test_train_sparse_bracket_turns_on_the_response_prior_and_saturation_weighting(tmp_path, capsys):
    scene = _tiny_dataset(tmp_path / "scene")
    base = ["train", str(scene), "--iters", "1", "--tonemap", "--quiet"]
    main(base + ["--out", str(tmp_path / "plain")])
    main(base + ["--out", str(tmp_path / "sparse"), "--sparse-bracket"])
    main(base + ["--out", str(tmp_path / "own"), "--sparse-bracket", "--response-prior", "0.5"])
    main(base + ["--out", str(tmp_path / "weighted"), "--saturation-weighting"])
    main(base + ["--out", str(tmp_path / "unweighted"), "--no-saturation-weighting"])

    def tone(run: str) -> dict:
        return json.loads((tmp_path / run / "config.json").read_text())["tonemap"]

    # The CPU presets weight the tone loss (`presets.CPU_TONE_LOSS`); the flag turns it either way.
    assert (tone("plain")["lambda_crf_loglog"], tone("plain")["saturation_weighting"]) == (0.0, True)
    assert not tone("unweighted")["saturation_weighting"]
    assert tone("sparse") == tone("plain") | SPARSE_BRACKET and SPARSE_BRACKET["saturation_weighting"]
    assert SPARSE_BRACKET["lambda_crf_loglog"] > 0
    assert tone("own")["lambda_crf_loglog"] == 0.5 and tone("own")["saturation_weighting"]
    assert tone("weighted")["saturation_weighting"] and tone("weighted")["lambda_crf_loglog"] == 0.0
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["train", str(scene), "--out", str(tmp_path / "none"), "--no-tonemap", "--sparse-bracket"])
    assert exc.value.code == 2
    assert "--sparse-bracket" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_train_preset_auto_is_the_default_and_says_what_it_chose(tmp_path, capsys, monkeypatch):
    """On this CPU `auto` trains `fast` and says so in one line; the saved run names the preset it ran,
    so a resumed run keeps it whatever `auto` would choose then."""
    scene = _tiny_dataset(tmp_path / "scene")
    run = tmp_path / "run"
    main(["train", str(scene), "--out", str(run), "--iters", "2", "--device", "cpu", "--quiet"])
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("preset: ")]
    assert lines == ["preset: fast (no CUDA device; --preset balanced trains longer for more quality; "
                     "--preset names another)"]  # fmt: skip
    assert json.loads((run / "config.json").read_text())["preset"] == "fast"
    monkeypatch.setattr("hdrplenoxels.cli.train.auto_preset", lambda *a: pytest.fail("chose again"))
    main(["train", str(scene), "--out", str(run), "--iters", "3", "--resume", "--quiet"])
    assert json.loads((run / "config.json").read_text())["preset"] == "fast"


@pytest.mark.parametrize(
    ("device", "mode", "chosen"),
    [
        ("cpu", "bbox", "fast"),
        ("cpu", "cascade", "fast"),
        ("cuda", "bbox", "paper-synthetic"),
        ("cuda", "cascade", "paper-real"),
        ("cuda", "ndc", "paper-real"),
        ("cuda", "bbox+background", "paper-real"),
    ],
)
def test_preset_auto_picks_the_cpu_preset_or_the_papers_schedule_for_the_capture(device, mode, chosen):
    from hdrplenoxels.train.presets import PRESETS, auto_preset

    name, why = auto_preset(device, mode)
    assert name == chosen and name in PRESETS and why
