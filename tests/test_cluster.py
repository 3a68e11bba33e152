"""`batch` and the executors: the local executor, and a real local Ray instance (2 CPUs) for batch, an
experiment, a worker killed mid-training, and paths the workers cannot see."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from test_train import TINY

from hdrplenoxels.cli.main import main
from hdrplenoxels.cluster.batch import capture_jobs, run_batch
from hdrplenoxels.cluster.executors import ExecutorConfig, _resources, check_paths_visible, start_ray
from hdrplenoxels.cluster.experiment import plan_of
from hdrplenoxels.cluster.jobs import LOG_FILE
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.parallel import cpu_workers
from hdrplenoxels.experiments import EXPERIMENTS
from hdrplenoxels.experiments.table_s1 import TABLE_METHODS
from hdrplenoxels.synth.procedural import write_procedural_scene
from hdrplenoxels.train.config import apply_overrides, parse_overrides
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.run_folder import checkpoints
from hdrplenoxels.train.trainer import Trainer, TrainingStopped

SMALL = [
    "--no-lpips",
    "--set",
    "grid.reso_schedule=[[12,12,12],[20,20,20]]",
    "--set",
    "grid.upsample_every=20",
    "--set",
    "optim.batch_size=512",
]
BATCH = ["--iters", "60", *SMALL]
EXPERIMENT = ["--scenes", "demo", "--views", "8", "--resolution", "64x32", "--spp", "2", "--iters", "40"]


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> Path:
    """Two tiny procedural captures (transforms.json datasets), different scenes."""
    root = tmp_path_factory.mktemp("captures")
    for name, background in (("a", TINY.background_brightness), ("b", 0.2)):
        write_procedural_scene(root / name, replace(TINY, background_brightness=background))
    return root


@pytest.fixture(scope="module")
def local_batch(captures, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("local") / "out"
    main(["batch", str(captures), str(out), *BATCH])
    return out


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    start_ray(None)
    yield ray
    ray.shutdown()


def attempts(log: Path) -> list[str]:
    return [line for line in log.read_text().splitlines() if line.startswith("== ") and "attempt" in line]


# ----------------------------------------------------------------------------- without Ray
def test_every_experiment_lists_its_runs():
    """The ray executor trains an experiment's `plan`: every registered experiment has one."""
    assert [name for name in EXPERIMENTS if plan_of(name) is None] == []


def test_without_ray_the_ray_executor_is_one_error_line(captures, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    for args in (
        ["batch", str(captures), str(tmp_path / "out"), "--executor", "ray"],
        ["experiment", "table-s1", str(tmp_path / "out"), "--executor", "ray"],
    ):
        with pytest.raises(SystemExit) as e:
            main(args)
        assert e.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert (
            len(err) == 1 and err[0].startswith("error: ") and "pip install hdrplenoxels[cluster]" in err[0]
        )
    assert not (tmp_path / "out").exists()


def test_a_ray_address_nobody_answers_at_is_one_error_line(captures, tmp_path, capsys):
    pytest.importorskip("ray")
    with pytest.raises(SystemExit) as e:
        main(
            [
                "batch",
                str(captures),
                str(tmp_path / "out"),
                "--executor",
                "ray",
                "--ray-address",
                "127.0.0.1:1",
            ]
        )
    assert e.value.code == 2
    assert "error: --ray-address 127.0.0.1:1: no Ray cluster answers there" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["batch", str(captures), str(tmp_path / "out"), "--ray-address", "auto"])
    assert e.value.code == 2 and "--ray-address needs --executor ray" in capsys.readouterr().err


def test_bad_captures_folders_are_refused(captures, tmp_path, capsys):
    (tmp_path / "file").write_text("")
    (tmp_path / "empty").mkdir()
    (tmp_path / "mixed" / "notes").mkdir(parents=True)
    cases = {
        tmp_path / "missing": "no such folder",
        tmp_path / "file": "is not a folder",
        tmp_path / "empty": "holds no capture folders",
        captures / "a": "is itself a dataset",
        tmp_path / "mixed": "no photos found",
    }
    for folder, problem in cases.items():
        with pytest.raises(SystemExit) as e:
            main(["batch", str(folder), str(tmp_path / "out")])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert problem in err and err.startswith("error: ")
    with pytest.raises(SystemExit):
        main(["batch", str(captures), str(captures / "out")])
    assert "inside CAPTURES" in capsys.readouterr().err


def test_batch_scores_every_capture_and_skips_finished_ones(captures, local_batch, tmp_path, capsys):
    summary = json.loads((local_batch / "summary.json").read_text())
    assert sorted(summary["captures"]) == ["a", "b"] and summary["failed"] == {}
    assert "right half" in summary["protocol"] and "right half" in (local_batch / "summary.md").read_text()
    for name in ("a", "b"):
        folder = local_batch / name
        result = summary["captures"][name]
        # the same numbers as `eval` on the run
        main(["eval", str(folder / "run"), "--no-lpips", "--json", str(tmp_path / f"{name}.json")])
        scored = json.loads((tmp_path / f"{name}.json").read_text())
        assert result["psnr"] == scored["psnr"] and result["ssim"] == scored["ssim"]
        assert len(list((folder / "renders").glob("*.png"))) == scored["num_test_views"] > 0
        assert len(attempts(folder / LOG_FILE)) == 1
    assert summary["captures"]["a"]["psnr"] != summary["captures"]["b"]["psnr"]  # two different scenes

    stamp = (local_batch / "a" / "result.json").stat().st_mtime_ns
    capsys.readouterr()
    main(["batch", str(captures), str(local_batch), *BATCH])
    assert "2 of 2 captures already finished" in capsys.readouterr().out
    assert (local_batch / "a" / "result.json").stat().st_mtime_ns == stamp


def test_a_folder_of_photos_is_processed_into_out_first_and_only_once(captures, tmp_path, monkeypatch):
    """COLMAP itself is tested in test_process.py; here a stand-in writes the dataset it would."""
    photos = tmp_path / "captures" / "shoot"
    photos.mkdir(parents=True)
    for i in range(3):
        (photos / f"IMG_{i}.jpg").write_bytes(b"")
    (tmp_path / "captures" / "a").symlink_to(captures / "a")
    processed = []

    def fake_process(source, out, cfg, overwrite, log):
        processed.append((source, out))
        shutil.copytree(captures / "a", out)

    monkeypatch.setattr("hdrplenoxels.cluster.batch.process_photos", fake_process)
    out = tmp_path / "out"
    for _ in range(2):
        main(["batch", str(tmp_path / "captures"), str(out), *BATCH])
    assert processed == [(photos.resolve(), out.resolve() / "shoot" / "data")]
    summary = json.loads((out / "summary.json").read_text())["captures"]
    assert summary["shoot"]["processed"] and not summary["a"]["processed"]
    assert summary["shoot"]["data"] == str(out.resolve() / "shoot" / "data")


def test_ctrl_c_stops_a_local_batch_and_says_how_to_continue(captures, tmp_path, monkeypatch, capsys):
    started = []

    def stopped(spec, resume):
        started.append(spec.data.name)
        raise TrainingStopped("SIGINT", 7, spec.run / "checkpoints" / "step_0000007.npz")

    monkeypatch.setattr("hdrplenoxels.cluster.batch.train_spec", stopped)
    with pytest.raises(SystemExit) as e:
        main(["batch", str(captures), str(tmp_path / "out"), *BATCH])
    assert e.value.code == 130 and started == ["a"]  # the second capture never starts
    assert "continue with the same command" in capsys.readouterr().err


def test_a_task_reserves_a_gpu_where_its_config_asks_for_cuda():
    class Job:
        def __init__(self, device):
            self.device = device

    def ray_with(gpus):
        nodes = [{"Alive": True, "Resources": {"CPU": 8.0, **({"GPU": gpus} if gpus else {})}}]
        return SimpleNamespace(nodes=lambda: nodes)

    assert _resources(ray_with(0), Job("cpu"), 2) == {"num_cpus": 2, "num_gpus": 0}
    assert _resources(ray_with(0), Job("auto"), 16) == {"num_cpus": 8, "num_gpus": 0}
    assert _resources(ray_with(1), Job("auto"), 2)["num_gpus"] == 1
    assert _resources(ray_with(1), Job("cuda:0"), 2)["num_gpus"] == 1
    assert _resources(ray_with(1), Job("cpu"), 2)["num_gpus"] == 0


# ----------------------------------------------------------------------------- a real local Ray
def test_ray_batch_equals_local_and_reports_a_failed_capture(
    ray_instance, captures, local_batch, tmp_path, capsys
):
    """Each capture a Ray task with the driver's thread counts, so the numbers equal the local run's;
    a broken capture fails on its own (its error and log come back) while the others finish."""
    mixed = tmp_path / "captures"
    mixed.mkdir()
    for name in ("a", "b"):
        (mixed / name).symlink_to(captures / name)
    (mixed / "broken").mkdir()
    (mixed / "broken" / "transforms.json").write_text("{")
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        main(["batch", str(mixed), str(out), *BATCH, "--executor", "ray"])
    assert e.value.code == 1
    err = capsys.readouterr().err
    assert "failed: broken: " in err and "transforms.json" in err
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["failed"]) == ["broken"] and "transforms.json" in summary["failed"]["broken"]["error"]
    assert "Traceback" in Path(summary["failed"]["broken"]["log"]).read_text()
    local = json.loads((local_batch / "summary.json").read_text())["captures"]
    for name in ("a", "b"):
        ray_result = summary["captures"][name]
        assert (ray_result["psnr"], ray_result["ssim"]) == (local[name]["psnr"], local[name]["ssim"])
        line = attempts(out / name / LOG_FILE)[0]
        assert f"pid {os.getpid()}," not in line  # trained in a worker, not here
        assert f"{torch.get_num_threads()} torch threads, {cpu_workers()} kernel threads" in line
        assert "GOMP_SPINCOUNT=10000 THP_MEM_ALLOC_ENABLE=1" in line  # process settings, before torch loaded


def test_a_killed_worker_is_retried_and_resumes_from_its_checkpoint(ray_instance, captures, tmp_path):
    one = tmp_path / "captures"
    one.mkdir()
    (one / "a").symlink_to(captures / "a")
    overrides = parse_overrides(
        [*SMALL[2::2], "optim.n_iters=200", "checkpoint_every=10", "checkpoint_gap_seconds=0"]
    )
    config = apply_overrides(preset("fast"), overrides)
    out = tmp_path / "ray"
    jobs = capture_jobs(one, out, config, lpips=False)
    done: list = []
    batch = threading.Thread(target=lambda: done.append(run_batch(jobs, out, ExecutorConfig("ray"))))
    batch.start()
    run, deadline = out / "a" / "run", time.monotonic() + 120
    while not checkpoints(run) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert checkpoints(run) and not (run / "model.npz").exists()
    pid = int(attempts(out / "a" / LOG_FILE)[0].split(", pid ")[1].split(",")[0])
    os.kill(pid, signal.SIGKILL)
    batch.join(timeout=180)
    (_, outcomes) = done[0]
    assert [o.error for o in outcomes] == [None]
    log = (out / "a" / LOG_FILE).read_text()
    assert len(attempts(out / "a" / LOG_FILE)) == 2 and "resuming" in log

    unbroken = tmp_path / "local"
    run_batch(capture_jobs(one, unbroken, config, lpips=False), unbroken, ExecutorConfig("local"))
    with np.load(run / "model.npz") as resumed, np.load(unbroken / "a" / "run" / "model.npz") as straight:
        assert sorted(resumed.files) == sorted(straight.files)
        for key in straight.files:
            if key != "meta_json":  # names the run folder
                assert np.array_equal(resumed[key], straight[key]), key


def test_an_experiment_on_ray_equals_local_and_its_report_trains_nothing(ray_instance, tmp_path, monkeypatch):
    data = ["--data", str(tmp_path / "data"), "--no-lpips"]
    main(["experiment", "table-s1", str(tmp_path / "local"), *EXPERIMENT, *data])

    def no_training(self, progress=True):
        raise AssertionError("the report phase trained a run")

    monkeypatch.setattr(Trainer, "run", no_training)  # this process only: Ray workers train
    main(["experiment", "table-s1", str(tmp_path / "ray"), *EXPERIMENT, *data, "--executor", "ray"])
    local, ray = (json.loads((tmp_path / k / "report.json").read_text()) for k in ("local", "ray"))
    assert local.pop("settings") == ray.pop("settings")
    assert ray == local
    assert len(list((tmp_path / "ray" / "runs" / "demo").glob(f"*/{LOG_FILE}"))) == len(TABLE_METHODS)


def test_a_path_the_workers_cannot_see_is_refused_before_any_run(ray_instance, tmp_path):
    with pytest.raises(InputError) as e:
        check_paths_visible(ray_instance, tmp_path / "out", [tmp_path / "not_there"])
    assert "not_there" in str(e.value) and "every node sees" in str(e.value)
    assert list((tmp_path / "out").iterdir()) == []  # the probe file is gone
