"""The step's repeating part replayed from a CUDA graph (`train/step_graph.py`, JOURNAL.md
"CUDA graph"): when it is captured, replayed and captured again, and that a failed capture leaves the run
stepping without it. A stand-in capture runs here; the CUDA tests replay real graphs. That the part
replays faithfully (the same launches, scalars and addresses each step) is held on any machine by
`test_sync_free_step.py`."""

from __future__ import annotations

import pytest
import torch

from hdrplenoxels.train.config import TrainConfig
from hdrplenoxels.train.step_graph import StepGraph, uses_step_graph


class Recorder:
    """A capture that counts: `record` returns a replay that runs the region again into the same tensor
    (as a graph's replay overwrites the recording's own outputs)."""

    def __init__(self, fail: bool = False):
        self.fail = fail
        self.eager_runs = 0
        self.records = 0
        self.replays = 0

    def eager(self, region):
        self.eager_runs += 1
        return region()

    def record(self, region):
        if self.fail:
            raise RuntimeError("operation not permitted when stream is capturing")
        self.records += 1
        outputs = torch.empty(0)

        def replay():
            self.replays += 1
            result = region()
            outputs.resize_(result.shape).copy_(result)

        return replay, outputs


def test_a_key_runs_eagerly_for_its_warmup_then_replays_one_capture():
    capture, runs = Recorder(), []
    graph = StepGraph(capture, warmup=2)

    def region():  # counts its runs
        runs.append(1)
        return torch.tensor(len(runs) - 1)

    for _ in range(5):
        graph("grid A", region)
    assert (capture.eager_runs, capture.records, capture.replays) == (2, 1, 3)
    assert len(runs) == 5 and graph.captures == 1
    assert int(graph("grid A", region)) == 5  # a replay returns the recording's outputs, refreshed
    for _ in range(4):  # a resample: new tensors, a new key
        graph("grid B", region)
    assert (capture.eager_runs, capture.records, capture.replays) == (4, 2, 6)
    assert graph.captures == 2 and graph.failure is None


def test_a_failed_capture_runs_that_step_and_every_later_one_eagerly():
    capture, runs = Recorder(fail=True), []
    graph = StepGraph(capture, warmup=1)
    for _ in range(4):
        graph("grid A", lambda: torch.tensor(runs.append(1) or len(runs)))
    assert len(runs) == 4  # no step lost or run twice
    assert capture.eager_runs == 4 and capture.replays == 0
    assert graph.failure == "RuntimeError: operation not permitted when stream is capturing"
    assert graph.captures == 0


def test_warmup_must_be_at_least_one_step():
    with pytest.raises(ValueError, match="warmup"):
        StepGraph(Recorder(), warmup=0)


def test_cuda_graphs_are_on_by_default_for_the_warp_grid_on_cuda_only():
    assert uses_step_graph(TrainConfig(), "cuda")
    assert not uses_step_graph(TrainConfig(), "cpu")
    assert not uses_step_graph(TrainConfig(cuda_graph=False), "cuda")
    for settings in ({"model": "nerf"}, {"backend": "torch"}):  # they launch eagerly, and say nothing
        cfg = TrainConfig(**settings)
        assert not uses_step_graph(cfg, "cuda") and cfg.check("bbox") == []


def test_a_cpu_run_ignores_the_setting(tiny_scene, tmp_path):
    """On a CPU there is no graph: the same run, the same grid, to the bit."""
    from hdrplenoxels.train.trainer import Trainer

    grids = []
    for graph in (False, True):
        cfg = _tiny_config(tiny_scene, "cpu", graph)
        trainer = Trainer(tiny_scene, cfg, tmp_path / str(graph))
        assert trainer.step_graph is None
        for _ in range(4):
            trainer.train_step()
        grids.append(trainer.engine.field.density.clone())
    assert torch.equal(*grids)


def test_the_trainer_steps_through_a_capture_and_captures_once_per_grid(tiny_scene, tmp_path):
    """The trainer's side, with a stand-in capture that runs the region again at each replay: the same
    run to the bit, a new capture after the resample (the grid's tensors are the key) and after the view
    prior ends (its weight is a constant of the recorded step)."""
    from hdrplenoxels.train.trainer import Trainer

    runs = []
    for graph in (False, True):
        trainer = Trainer(tiny_scene, _tiny_config(tiny_scene, "cpu", False), tmp_path / str(graph))
        if graph:
            trainer.step_graph = StepGraph(Recorder())
        losses = []
        while trainer.step < trainer.cfg.optim.n_iters:
            losses.append(trainer.train_step())
            trainer.upsample()
        runs.append((torch.stack(losses), trainer.engine.field.density.detach()))
    assert trainer.cfg.tonemap.sh_view_until * trainer.cfg.optim.n_iters == 8
    # 16³: steps 0-2 eager, 3-5 replayed; 24³ from step 6 with the view prior (6, 7 eager), without it
    # from step 8 (8-10 eager, 11 replayed). (Owing the view prior's pull, a CUDA run's default, adds an
    # eager step after each grid's first: `GridEngine.graph_key`.)
    assert trainer.step_graph.captures == 2
    assert (trainer.step_graph.capture.eager_runs, trainer.step_graph.capture.replays) == (8, 4)
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])


def test_a_replaced_tone_buffer_is_a_new_key(tiny_scene, tmp_path):
    """A graph reads the tone mapper's buffers (the reference, the image sizes, the curve groups) by
    address, as it reads the parameters: a buffer replaced (as `load_state_arrays` does) must be
    recorded anew, not replayed from the old address."""
    from hdrplenoxels.train.trainer import Trainer

    trainer = Trainer(tiny_scene, _tiny_config(tiny_scene, "cpu", False), tmp_path)
    key = trainer._graph_key()
    assert trainer._graph_key() == key
    for name, _ in trainer.tonemapper.named_buffers():
        before = getattr(trainer.tonemapper, name)
        setattr(trainer.tonemapper, name, before.clone())
        assert trainer._graph_key() != key, name
        setattr(trainer.tonemapper, name, before)
    assert trainer._graph_key() == key


def _tiny_config(scene, device: str, graph: bool) -> TrainConfig:
    from hdrplenoxels.train.config import apply_overrides
    from hdrplenoxels.train.presets import preset

    overrides = {
        "device": device,
        "cuda_graph": graph,
        "grid.reso_schedule": [(16, 16, 16), (24, 24, 24)],
        "grid.upsample_every": 6,
        "optim.n_iters": 12,
        "optim.batch_size": 256,
        "checkpoint_every": 0,
        "tonemap.enabled": True,
    }
    return apply_overrides(preset("fast"), overrides)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_cuda_run_replays_its_graph_and_trains_as_without_it(tiny_scene, tmp_path):
    """Through a resample (a second capture): the replayed steps see the batches and train the grid as the
    launched ones do, and a replayed step never makes the host wait. CUDA's atomics add in any order, so
    two runs part even without a graph (benchmarks/RESULTS.md, "GPU, 2026-11-27"): a voxel whose gradient
    sums to about 0 steps either way under RMSProp, so a few percent of the voxels end apart; the losses
    agree step by step until the resample, whose pruning such voxels change, and only on average after it.
    A replay after the resample must train the new grid, not the freed one. The view prior ends at step 5
    (a new key: step 5 eager), so the last steps, 9 to 11, are the second grid's recording and replays."""
    from hdrplenoxels.train.trainer import Trainer

    losses, grids = [], []
    for graph in (False, True):
        cfg = _tiny_config(tiny_scene, "cuda", graph)
        cfg.tonemap.sh_view_until = 0.4  # 4.8 of 12 steps: off from step 5, before the resample
        trainer = Trainer(tiny_scene, cfg, tmp_path / str(graph))
        mse = []
        while trainer.step < trainer.cfg.optim.n_iters - 1:
            mse.append(trainer.train_step())
            if trainer.step == trainer.cfg.grid.upsample_every:  # before the resample prunes on density
                grids.append(trainer.engine.field.density.detach().cpu())
            trainer.upsample()
        before = trainer.engine.field.density.detach().clone()
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            mse.append(trainer.train_step())
        finally:
            torch.cuda.set_sync_debug_mode("default")
        assert not torch.equal(trainer.engine.field.density, before)  # the last (replayed) step trained
        if graph:
            assert trainer.step_graph.failure is None
            assert trainer.step_graph.captures == 2
        losses.append(torch.stack(mse).cpu())
    first = trainer.cfg.grid.upsample_every  # the first step on the resampled grid
    # the same batches, step by step on the first grid; on the second, apart by a few pruned voxels
    torch.testing.assert_close(losses[1][:first], losses[0][:first], rtol=1e-2, atol=1e-6)
    torch.testing.assert_close(losses[1][first:].mean(), losses[0][first:].mean(), rtol=0.1, atol=0.0)
    apart = (grids[1] - grids[0]).abs() > 1e-3 * (1 + grids[0].abs())
    assert apart.float().mean() < 0.15  # a graph that skipped or repeated an update would part most voxels
