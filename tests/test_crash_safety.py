"""Crash safety of training: killed anywhere it resumes to the very same model, a signal stops it with a
checkpoint, one run folder has one writer, and checkpoints do not change what is trained."""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_train import tiny_config as train_config

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.run_lock import RunLock
from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.model import MODEL_FILE
from hdrplenoxels.train.run_folder import CHECKPOINT_DIR
from hdrplenoxels.train.run_state import is_run_state, resumable
from hdrplenoxels.train.trainer import Trainer, TrainingStopped

N_ITERS = 45


def tiny_config() -> TrainConfig:
    cfg = train_config(N_ITERS)
    cfg.tonemap.enabled = True
    cfg.checkpoint_every = 7  # checkpoints fall between touched-row optimiser steps, decay owed
    cfg.checkpoint_seconds = 0.0
    cfg.device = "cpu"  # bit-reproducible (CUDA's float atomics add in a varying order)
    return cfg


@pytest.fixture(scope="module")
def unbroken(tiny_scene, tmp_path_factory) -> dict[str, np.ndarray]:
    run = tmp_path_factory.mktemp("unbroken")
    Trainer(tiny_scene, tiny_config(), run).run(progress=False)
    return dict(np.load(run / MODEL_FILE))


def assert_same_model(path: Path, reference: dict[str, np.ndarray]) -> None:
    """Every array equal (the metadata holds the config, whose checkpoint settings may differ)."""
    model = dict(np.load(path))
    assert model.keys() == reference.keys()
    for key, value in reference.items():
        if key != "meta_json":
            assert np.array_equal(model[key], value), key


def test_checkpoints_at_every_step_leave_the_run_bit_identical(tiny_scene, tmp_path, unbroken):
    """Saving reads the optimiser state as it is (no owed decay paid), so checkpointing cannot change
    the result: a run that also checkpoints by time after every step ends with the same model."""
    cfg = tiny_config()
    cfg.checkpoint_seconds = 1e-9
    Trainer(tiny_scene, cfg, tmp_path).run(progress=False)
    kept = sorted(p.name for p in (tmp_path / CHECKPOINT_DIR).glob("step_*.npz"))
    assert kept == [f"step_{s:07d}.npz" for s in (N_ITERS - 2, N_ITERS - 1, N_ITERS)]  # the newest 3
    assert_same_model(tmp_path / MODEL_FILE, unbroken)


@pytest.mark.parametrize("gap", [0.0, 1e9])
def test_a_step_count_checkpoint_sooner_than_the_gap_is_skipped(tiny_scene, tmp_path, gap, unbroken):
    """`checkpoint_gap_seconds` drops the every-N-steps checkpoints that come too soon (the final one
    stays), and the model is the same either way."""
    cfg = tiny_config()
    cfg.checkpoint_gap_seconds, cfg.keep_checkpoints = gap, 0
    Trainer(tiny_scene, cfg, tmp_path).run(progress=False)
    kept = sorted(p.name for p in (tmp_path / CHECKPOINT_DIR).glob("step_*.npz"))
    steps = [*range(7, N_ITERS, 7), N_ITERS] if gap == 0 else [N_ITERS]
    assert kept == [f"step_{s:07d}.npz" for s in steps]
    assert_same_model(tmp_path / MODEL_FILE, unbroken)


class Killed(Exception):
    pass


def test_resume_from_any_checkpoint_equals_the_unbroken_run(tiny_scene, tmp_path, unbroken):
    first = Trainer(tiny_scene, tiny_config(), tmp_path)
    step = first.train_step

    def step_then_die():
        if first.step == 23:  # two steps past the checkpoint of step 21, after the resample at 20
            raise Killed
        return step()

    first.train_step = step_then_die
    with pytest.raises(Killed):
        first.run(progress=False)
    resumed = Trainer(tiny_scene, tiny_config(), tmp_path, resume=True)
    assert resumed.step == 21
    resumed.run(progress=False)
    assert_same_model(tmp_path / MODEL_FILE, unbroken)
    steps = [int(line.split('"step": ')[1].split(",")[0]) for line in (tmp_path / "train_log.jsonl").open()]
    assert steps == sorted(set(steps))  # the log holds each logged step once, not the lost ones again


def test_resume_on_a_run_without_a_checkpoint_starts_it(tiny_scene, tmp_path, unbroken):
    (tmp_path / "train_log.jsonl").write_text('{"step": 5, "mse": 0.1}\n{"step": 10, "ms')  # killed early
    trainer = Trainer(tiny_scene, tiny_config(), tmp_path, resume=True)
    assert trainer.step == 0 and not trainer.resumed
    trainer.run(progress=False)
    assert_same_model(tmp_path / MODEL_FILE, unbroken)


TRAIN_SCRIPT = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    sys.path.insert(0, {tests!r})
    from test_crash_safety import tiny_config
    from hdrplenoxels.data import load_scene
    from hdrplenoxels.train.trainer import Trainer
    Trainer(load_scene(Path(sys.argv[1])), tiny_config(), Path(sys.argv[2]), resume=True).run(progress=False)
    """
).format(tests=str(Path(__file__).parent))


def _start(scene_path: Path, run: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", TRAIN_SCRIPT, str(scene_path), str(run)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_killed_at_random_moments_it_resumes_to_the_unbroken_model(tiny_scene_path, tmp_path, unbroken):
    """SIGKILL at random times (before training, mid-step, mid-checkpoint, at a resample), then resume,
    until the run finishes: the model is bit-identical to an unbroken run's, and no partial file is
    ever picked up (a resume that read one would fail or differ)."""
    rng = random.Random(7)
    run = tmp_path / "run"
    kills = 0
    started = time.monotonic()
    while True:
        proc = _start(tiny_scene_path, run)
        if kills < 6:
            time.sleep(rng.uniform(0.5, 4.0))
        if proc.poll() is None and kills < 6:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            kills += 1
            continue
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-2000:]
        break
    assert time.monotonic() - started < 600  # bounded: a hang would show here, not as a CI time-out
    assert kills > 0
    assert_same_model(run / MODEL_FILE, unbroken)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "hdrplenoxels", *args]


def test_sigterm_stops_train_with_a_checkpoint_and_says_how_to_resume(tiny_scene_path, tmp_path):
    run = tmp_path / "run"
    train = ["train", str(tiny_scene_path.parent), "--preset", "fast", "--out", str(run), "--quiet"]
    proc = subprocess.Popen(
        _cli(*train, "--iters", "100000", "--device", "cpu"), stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 120
    while not (run / "config.json").exists() and time.monotonic() < deadline:
        time.sleep(0.05)  # the run has started
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "Traceback" not in err and "stopped by SIGTERM at step" in err and "--resume" in err
    step = int(err.split("stopped by SIGTERM at step ")[1].split(";")[0])
    assert (run / CHECKPOINT_DIR / f"step_{step:07d}.npz").exists() and not (run / MODEL_FILE).exists()
    done = subprocess.run(_cli(*train, "--resume", "--iters", str(step + 3)), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"trained {step + 3} steps" in done.stdout


def test_trainer_turns_a_signal_into_a_checkpoint_and_training_stopped(tiny_scene, tmp_path):
    trainer = Trainer(tiny_scene, tiny_config(), tmp_path)
    step = trainer.train_step
    before = signal.getsignal(signal.SIGINT)  # ignored, not Python's handler, in a background job

    def step_then_signal():
        loss = step()
        if trainer.step == 3:
            os.kill(os.getpid(), signal.SIGINT)
        return loss

    trainer.train_step = step_then_signal
    with pytest.raises(TrainingStopped) as stopped:
        trainer.run(progress=False)
    assert (stopped.value.signal_name, stopped.value.step) == ("SIGINT", 3)
    assert stopped.value.checkpoint.exists() and stopped.value.checkpoint.name == "step_0000003.npz"
    assert signal.getsignal(signal.SIGINT) is before  # handlers restored
    assert not trainer.lock.held


def test_one_run_folder_has_one_writer(tiny_scene, tmp_path):
    first = Trainer(tiny_scene, tiny_config(), tmp_path)
    with pytest.raises(InputError, match=f"in use by process {os.getpid()}"):
        Trainer(tiny_scene, tiny_config(), tmp_path, overwrite=True)
    first.lock.release()
    Trainer(tiny_scene, tiny_config(), tmp_path, overwrite=True).lock.release()


def test_a_lock_left_by_a_killed_process_is_taken_over(tmp_path):
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pathlib import Path; from hdrplenoxels.core.run_lock import RunLock; "
            "lock = RunLock(Path(sys.argv[1])).acquire(); print('held', flush=True); time.sleep(60)",
            str(tmp_path),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(InputError, match=f"in use by process {holder.pid}"):
        RunLock(tmp_path).acquire()
    holder.kill()
    holder.wait()
    lock = RunLock(tmp_path).acquire()  # the kernel dropped the dead holder's lock
    assert f"process {os.getpid()}" in (tmp_path / ".lock").read_text()
    lock.release()


def test_checkpoint_state_round_trips_the_owed_decay():
    from hdrplenoxels.train.optim import Svox2RMSProp

    g = torch.Generator().manual_seed(3)
    params = [torch.randn(50, generator=g), torch.randn(50, 4, generator=g)]
    opt = Svox2RMSProp()
    for _ in range(3):
        hit = torch.rand(50, generator=g) < 0.3
        grads = [torch.randn(1, 50, generator=g) * hit, torch.randn(1, 50, 4, generator=g) * hit[:, None]]
        opt.step_accumulated(params, grads, [0.1, 0.1], touched=hit.to(torch.uint8))
    assert opt.last_step is not None
    arrays = opt.checkpoint_arrays()
    assert opt.last_step is not None  # reading the state paid nothing
    restored = Svox2RMSProp()
    restored.load_checkpoint_arrays(arrays)
    assert restored.steps == opt.steps and torch.equal(restored.last_step, opt.last_step)
    assert all(torch.equal(a, b) for a, b in zip(restored.state, opt.state))


def test_a_background_run_resumes_bit_identical(tiny_scene, tmp_path):
    """The MSI (in the checkpoint beside the grid) and its RMSProp state (`optim/bg/...`) come back
    exactly: killed after a checkpoint, the resumed run ends with the unbroken run's model."""
    cfg = tiny_config()
    cfg.background.enabled = True  # forced on: the tiny scene's own mode is a plain box
    cfg.background.layers, cfg.background.height, cfg.background.width = 3, 6, 12
    Trainer(tiny_scene, cfg, tmp_path / "unbroken").run(progress=False)
    reference = dict(np.load(tmp_path / "unbroken" / MODEL_FILE))
    assert {"bg/density", "bg/color"} <= reference.keys()
    first = Trainer(tiny_scene, cfg, tmp_path / "resumed")
    step = first.train_step

    def step_then_die():
        if first.step == 16:  # two steps past the checkpoint of step 14
            raise Killed
        return step()

    first.train_step = step_then_die
    with pytest.raises(Killed):
        first.run(progress=False)
    resumed = Trainer(tiny_scene, cfg, tmp_path / "resumed", resume=True)
    assert resumed.step == 14 and resumed.engine.background is not None
    assert any(k.startswith("bg/") for k in resumed.engine.state_arrays())
    resumed.run(progress=False)
    assert_same_model(tmp_path / "resumed" / MODEL_FILE, reference)


def _held_until(condition, write):
    """`write`, called only once `condition()` holds: a background write made late on purpose."""

    def late(*args):
        deadline = time.monotonic() + 60
        while not condition() and time.monotonic() < deadline:
            time.sleep(0.001)
        return write(*args)

    return late


def test_checkpoints_written_behind_the_steps_hold_the_step_they_were_taken_at(tiny_scene, tmp_path):
    """A GPU run writes its periodic checkpoints on the writer thread, from host copies. Forced on here
    (a CPU, whose arrays are views), each write held back until 3 more steps have run: every checkpoint
    still equals the foreground run's, file for file, and so does the model."""
    cfg = tiny_config()
    cfg.keep_checkpoints = 0
    Trainer(tiny_scene, cfg, tmp_path / "foreground").run(progress=False)
    trainer = Trainer(tiny_scene, cfg, tmp_path / "background")
    assert not trainer.background_checkpoints  # a CPU's default
    trainer.background_checkpoints = True
    write = trainer.folder.write_checkpoint
    trainer.folder.write_checkpoint = lambda path, *args: _held_until(
        lambda: trainer.step >= min(int(path.stem.split("_")[1]) + 3, N_ITERS), write
    )(path, *args)
    trainer.run(progress=False)
    written = sorted((tmp_path / "background" / CHECKPOINT_DIR).glob("step_*.npz"))
    assert [p.name for p in written] == [f"step_{s:07d}.npz" for s in [*range(7, N_ITERS, 7), N_ITERS]]
    for path in written:
        assert_same_model(path, dict(np.load(tmp_path / "foreground" / CHECKPOINT_DIR / path.name)))
    foreground_model = dict(np.load(tmp_path / "foreground" / MODEL_FILE))
    assert_same_model(tmp_path / "background" / MODEL_FILE, foreground_model)


def test_the_final_checkpoint_keeps_the_tones_as_trained(tiny_scene, tmp_path, monkeypatch):
    """The final checkpoint is written on the writer thread while the gauge is fitted: it holds the tone
    mapper as training left it (exponent 1), the model the fitted exponent. The write is held until the
    controller's fit has begun, after the gauge's, so a checkpoint made from views would show it."""
    import hdrplenoxels.train.run_end as run_end

    gauge_fitted = []
    fit = run_end.fit_controller
    monkeypatch.setattr(run_end, "fit_controller", lambda *a: (gauge_fitted.append(1), fit(*a))[1])
    cfg = tiny_config()
    cfg.checkpoint_every = 0
    trainer = Trainer(tiny_scene, cfg, tmp_path)
    folder = trainer.folder
    folder.write_checkpoint = _held_until(lambda: bool(gauge_fitted), folder.write_checkpoint)
    trainer.run(progress=False)
    final = dict(np.load(tmp_path / CHECKPOINT_DIR / f"step_{N_ITERS:07d}.npz"))
    model = dict(np.load(tmp_path / MODEL_FILE))
    assert float(final["x/tonemap/exponent"]) == 1.0
    assert float(model["x/tonemap/exponent"]) != 1.0  # the response prior's gauge (output_prior_gamma)
    assert (tmp_path / "tone_params.png").stat().st_size > 0


def test_a_finished_runs_last_checkpoint_is_its_state_beside_the_model(tiny_scene, tmp_path):
    """The last checkpoint holds no field (the model holds it): a finished run extended with `--resume`
    and more steps from it ends as one extended from a whole checkpoint of that step."""
    whole = tiny_config()
    whole.checkpoint_every = 15  # step 45's checkpoint is a periodic one: a whole checkpoint
    Trainer(tiny_scene, whole, tmp_path / "whole").run(progress=False)
    run = tmp_path / "state"
    Trainer(tiny_scene, tiny_config(), run).run(progress=False)
    name = f"step_{N_ITERS:07d}.npz"
    assert not is_run_state(tmp_path / "whole" / CHECKPOINT_DIR / name)
    last = run / CHECKPOINT_DIR / name
    assert is_run_state(last) and resumable(last)
    assert {"density", "sh"}.isdisjoint(np.load(last).files) and "x/optim/v1" in np.load(last).files
    again = tiny_config()
    again.log_every = 3  # resumed, finished already, with a setting a resume may change
    Trainer(tiny_scene, again, run, resume=True).run(progress=False)
    assert is_run_state(last) and resumable(
        last
    )  # the model was written again, with the new setting; not the state
    longer = tiny_config()
    longer.optim.n_iters = N_ITERS + 10
    for folder in (run, tmp_path / "whole"):
        resumed = Trainer(tiny_scene, longer, folder, resume=True)
        assert resumed.step == N_ITERS
        resumed.run(progress=False)
    assert_same_model(run / MODEL_FILE, dict(np.load(tmp_path / "whole" / MODEL_FILE)))


def test_killed_between_the_last_state_and_the_model_it_resumes_from_the_checkpoint_before(
    tiny_scene, tmp_path, unbroken
):
    """The state is written first: killed before the model, the state is no checkpoint to resume from
    (its model is missing), and the run goes on from step 42, to the same model."""
    Trainer(tiny_scene, tiny_config(), tmp_path).run(progress=False)
    (tmp_path / MODEL_FILE).unlink()
    last = tmp_path / CHECKPOINT_DIR / f"step_{N_ITERS:07d}.npz"
    left = last.stat().st_ino
    resumed = Trainer(tiny_scene, tiny_config(), tmp_path, resume=True)
    assert resumed.step == 42
    resumed.run(progress=False)
    assert_same_model(tmp_path / MODEL_FILE, unbroken)
    # The state the killed run left is written again, this run's, beside this run's model.
    assert last.stat().st_ino != left and is_run_state(last) and resumable(last)


def test_a_last_state_that_does_not_go_with_the_model_is_refused_and_nothing_is_lost(tiny_scene, tmp_path):
    """Only the state left, beside a model of another configuration: `--resume` refuses, naming the
    checkpoint, and deletes nothing (starting over would throw a finished model away)."""
    cfg = tiny_config()
    cfg.keep_checkpoints = 1
    Trainer(tiny_scene, cfg, tmp_path / "run").run(progress=False)
    other = tiny_config()
    other.seed = 7
    Trainer(tiny_scene, other, tmp_path / "other").run(progress=False)
    shutil.copy(tmp_path / "other" / MODEL_FILE, tmp_path / "run" / MODEL_FILE)
    before = sorted(p.name for p in (tmp_path / "run").rglob("*"))
    with pytest.raises(InputError, match=f"step_{N_ITERS:07d}.npz.*does not go with"):
        Trainer(tiny_scene, cfg, tmp_path / "run", resume=True)
    assert sorted(p.name for p in (tmp_path / "run").rglob("*")) == before
