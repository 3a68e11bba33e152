"""A training step that never makes the host wait for the GPU (JOURNAL.md, "A step without
host synchronisation"): its random numbers are drawn on the training device, its per-grid constants are
made once per grid, and nothing in it reads a tensor back. On CUDA torch's sync debug mode checks the
step itself; on any machine `host_reads` finds the reads that would wait there."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from cuda_kernels import use_cuda_kernels
from devices import FAST_DEVICE
from host_reads import host_reads
from launch_log import in_launch_order, launch_log
from wall_points import with_wall_points

from hdrplenoxels.kernels import dispatch, march_kernel
from hdrplenoxels.kernels.occupancy_kernel import TIGHTEN_EVERY
from hdrplenoxels.kernels.tv import check_cells
from hdrplenoxels.train.config import apply_overrides
from hdrplenoxels.train.presets import preset
from hdrplenoxels.train.run_state import GENERATOR_STATE_BYTES, restore_generator
from hdrplenoxels.train.trainer import Trainer

# Functions that read on the host only where that waits for nothing: the TV cells' range check reads
# CPU tensors only (`tv.check_cells`), and the row-per-thread RMSProp, which takes its pull as kernel
# constants, is the CPU's update (CUDA's is per element).
CPU_ONLY_READS = ("check_cells", "fused_rmsprop_")


@pytest.fixture(scope="module")
def walled_scene(walled):
    """The walled room with sparse points on its walls, seen by every training view: a real capture's
    ingredients (a cascade, lines of sight) at a test's size."""
    return with_wall_points(walled, per_view=10, reach=0.98)


# Every part of a step a real capture's run has (a cascade with its MSI background, the distortion
# loss, the free-space and surface priors, the sparsity prior a GPU preset may use, the tone mapper with
# its view prior), and the one box of a synthetic scene.
STEPS = {
    "cascade": {
        "scene_mode": "cascade",
        "optim.lambda_distortion": 0.01,
        "optim.lambda_free_space": 1.0,
        "optim.lambda_surface": 1.0,
        "optim.lambda_sparsity": 1e-8,
    },
    "box": {"scene_mode": "bbox", "optim.lambda_distortion": 0.0},
}


def _trainer(scene, settings: dict, folder, device) -> Trainer:
    overrides = {
        "device": str(device),
        "grid.reso_schedule": [(16, 16, 16)],
        "optim.n_iters": 50,
        "optim.batch_size": 256,
        "optim.free_space_lines": 64,
        "checkpoint_every": 0,
        "tonemap.enabled": True,
    }
    return Trainer(scene, apply_overrides(preset("fast"), overrides | settings), folder)


@pytest.mark.parametrize(
    "kind, fused, update",
    [
        ("cascade", False, "auto"),
        ("box", False, "auto"),
        ("cascade", True, "auto"),
        ("cascade", True, "owed"),
    ],
)
def test_a_steady_state_step_reads_nothing_back_on_the_host(
    walled_scene, tmp_path, monkeypatch, kind, fused, update
):
    """Also on CUDA's path of the fused kernels (the tone loss, the ray draw, the tone optimiser), and
    with the view prior's pull owed (CUDA's "auto"), which marks and pays the rows a step reads."""
    monkeypatch.setattr(dispatch, "KERNELS_ON_CPU", fused)
    trainer = _trainer(walled_scene, STEPS[kind] | {"view_prior_update": update}, tmp_path, FAST_DEVICE)
    assert trainer._view_prior_weight() > 0
    assert (trainer.engine.field.levels > 1) == (kind == "cascade")
    assert (trainer.engine.background is not None) == (kind == "cascade")
    assert "lines of sight" in trainer.sight_priors_note
    for _ in range(3):  # the first steps build what is kept per grid (views, constants, optimiser state)
        trainer.train_step()
    before = trainer.engine.field.density.clone()
    with host_reads(exempt=CPU_ONLY_READS) as reads:
        trainer.train_step()
    assert not reads, "\n".join(map(str, reads))
    assert not torch.equal(trainer.engine.field.density, before)  # the step did train
    assert trainer.engine.optimiser.owing_pull == (update == "owed" or FAST_DEVICE.type == "cuda")


def test_the_host_read_finder_finds_a_read():
    """The finder must see a read where there is one: the TV range check reads its cells' bounds."""
    links = torch.zeros((2, 2, 2), dtype=torch.int32)
    with host_reads() as reads:
        check_cells(links, torch.arange(3))
    assert [r.function for r in reads] == ["check_cells", "check_cells"]
    assert all(r.what == "__int__" and r.where.startswith("kernels/tv.py:") for r in reads)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("kind", list(STEPS))
def test_a_steady_state_cuda_step_never_synchronises(walled_scene, tmp_path, kind):
    trainer = _trainer(walled_scene, STEPS[kind], tmp_path, torch.device("cuda"))
    for _ in range(3):
        trainer.train_step()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        trainer.train_step()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()


def test_a_generator_continues_from_its_state_and_is_reseeded_from_another_device_kind():
    g = torch.Generator().manual_seed(3)
    torch.rand(5, generator=g)
    state = g.get_state().numpy().copy()
    expected = torch.rand(4, generator=g)
    resumed = torch.Generator()
    restore_generator(resumed, state, reseed=99)
    assert torch.equal(torch.rand(4, generator=resumed), expected)  # a resumed run equals an unbroken one
    restore_generator(resumed, np.zeros(GENERATOR_STATE_BYTES["cuda"], np.uint8), reseed=99)
    assert torch.equal(
        torch.rand(4, generator=resumed), torch.rand(4, generator=torch.Generator().manual_seed(99))
    )
    with pytest.raises(RuntimeError):  # neither kind's state: the checkpoint is refused upstream
        restore_generator(resumed, np.zeros(7, np.uint8), reseed=99)
    assert torch.Generator().get_state().numel() == GENERATOR_STATE_BYTES["cpu"]


@pytest.mark.parametrize(
    "kind, lanes, view_prior, update",
    [
        ("cascade", None, True, "auto"),
        ("cascade", None, True, "owed"),
        ("cascade", None, False, "auto"),
        ("box", None, False, "auto"),
        ("cascade", march_kernel.CUDA_LANES, False, "auto"),
        ("cascade", march_kernel.CUDA_LANES, True, "owed"),
    ],
)
def test_the_repeating_part_of_a_step_launches_the_same_every_step(
    walled_scene, tmp_path, monkeypatch, kind, lanes, view_prior, update
):
    """What a CUDA graph replays (`Trainer._step_region`: the whole step, its optimisers included,
    JOURNAL.md "CUDA graph") must launch the same kernels with the same scalars and the same
    outside addresses at every step, or a replay would run a stale copy of it; and it must leave the
    host's state as it found it, since a replay runs no Python. The two steps logged have the engine's
    exact occupancy rebuild between them (every `TIGHTEN_EVERY` steps, outside the region), with the view
    prior on (its pull owed by the rows no step touches, paid by those a step reads before it reads
    them) or over (the update of touched rows, which reads the optimiser's count).
    Also with CUDA's kernels (`cuda_kernels.use_cuda_kernels`) on the CPU,
    and with the pull owed on a CPU (`view_prior_update` "owed", CUDA's "auto"). The steps launch one by
    one (`cuda_graph` off) so that the log sees them on CUDA too: a replay runs no Python."""
    if lanes is not None:
        use_cuda_kernels(monkeypatch, lanes)
    until = {"tonemap.sh_view_until": 1.0 if view_prior else 0.5}  # of 50 steps; steps 31 and 32 are logged
    launched = {"view_prior_update": update, "cuda_graph": False}
    trainer = _trainer(walled_scene, STEPS[kind] | until | launched, tmp_path, FAST_DEVICE)
    assert (trainer._view_prior_weight() > 0) and trainer.tonemapper is not None
    region, logs, host = trainer._step_region, [], []

    def logged():
        before = host_state(trainer)
        with launch_log() as log:
            out = region()
        logs.append(log)
        host.append((before, host_state(trainer)))
        return out

    while trainer.step < TIGHTEN_EVERY - 1:  # more than the 3 steps a graph's warm-up takes
        trainer.train_step()
    trainer._step_region = logged
    before = trainer.engine.field.density.clone()
    tone_before = [p.clone() for p in trainer.tone_optimiser.params]
    count = int(trainer.step_count[0])
    trainer.train_step()
    trainer.train_step()
    assert not torch.equal(trainer.engine.field.density, before)  # the steps did train
    assert not any(torch.equal(a, b) for a, b in zip(tone_before, trainer.tone_optimiser.params))
    assert int(trainer.step_count[0]) == count + 2 == trainer.step  # the region advanced the device's count
    for i, (entering, leaving) in enumerate(host):
        assert entering == leaving, f"step {i}: the region changed the host's state"
    kernels = {entry[1] for entry in logs[0] if entry[0] == "warp"}
    marches = {k for k in kernels if "forward" in k or "backward" in k}
    assert len(marches) >= 2 and any("tv" in k for k in kernels)  # the log saw the kernels
    assert any("rmsprop" in k for k in kernels)  # and the optimiser's: dense, or of touched rows
    owing = view_prior and (update == "owed" or FAST_DEVICE.type == "cuda")  # "auto": owed on CUDA
    assert trainer.engine.optimiser.owing_pull == owing
    assert any("touched" in k for k in kernels) == (not view_prior or owing)
    for owed in ("read_rows", "pay_owed"):  # the rows a step reads pay what they owe first
        assert any(owed in k for k in kernels) == owing
    # a warp per ray where asked, and by default on CUDA
    assert any("lane" in k for k in marches) == (march_kernel.lanes_for(FAST_DEVICE.type, lanes) > 0)
    fused = {"_tone_loss", "_curve_smoothness", "_draw_rays", "_torch_rmsprop"}
    fused |= {"_msi_tv_grad"} if trainer.engine.background is not None else set()
    assert fused <= kernels if dispatch.use_kernel(trainer.step_count) else not fused & kernels
    first, second = logs
    assert len(first) == len(second)
    for i, (a, b) in enumerate(zip(first, second)):
        assert a == b, f"launch {i} differs between steps:\n{a}\n{b}"


def host_state(trainer: Trainer) -> dict:
    """What a step's Python may change and a later step read: the plain values (numbers, flags, None,
    which tensor) held by the trainer, its engine, optimisers, tone mapper and the grid's occupancy."""

    def plain(obj) -> dict:
        out = {}
        for name, value in vars(obj).items():
            if value is None or isinstance(value, (bool, int, float, str)):
                out[name] = value
            elif isinstance(value, torch.Tensor):
                out[name] = ("tensor", value.data_ptr(), tuple(value.shape))
        return out

    engine = trainer.engine
    held = {"trainer": trainer, "engine": engine, "optimiser": engine.optimiser}
    held |= {"background optimiser": engine.bg_optimiser, "tone optimiser": trainer.tone_optimiser}
    held |= {"occupancy": engine.field.__dict__.get("_occupancy"), "pool": trainer.pool}
    return {name: plain(obj) for name, obj in held.items() if obj is not None}


def test_the_host_state_check_sees_a_changed_count():
    """The check above must see host state a region changes: a Python step counter."""

    class Holder:
        pass

    trainer = Holder()
    trainer.engine = Holder()
    trainer.engine.optimiser = trainer.engine.bg_optimiser = Holder()
    trainer.engine.field = Holder()
    trainer.tone_optimiser, trainer.pool, trainer.steps = None, None, 3
    before = host_state(trainer)
    trainer.steps += 1
    assert host_state(trainer) != before


def test_the_launch_log_sees_a_changed_scalar_and_a_new_outside_tensor():
    """The log must show what a graph would freeze: a scalar that changes, an outside tensor replaced."""

    def region(scale, outside):
        return (outside * scale).sum()

    a, b = torch.ones(4), torch.ones(4)
    logs = []
    for scale, outside in ((2.0, a), (2.0, a), (3.0, a), (2.0, b)):
        with launch_log() as log:
            region(scale, outside)
        logs.append(log)
    assert logs[0] == logs[1]
    assert logs[0] != logs[2]  # the scalar
    assert logs[0] != logs[3]  # the outside tensor's address


def test_the_launch_log_orders_the_parts_of_one_launch_but_nothing_else():
    """A CPU launch's parts reach the log in the order the threads take them; the log sorts them, and
    only them: different kernels, and a part whose scalar changed, stay apart."""

    def part(start: int) -> tuple:
        return ("warp", "k", (8,), (("start", repr(start)),))

    op = ("aten.add", (), ())
    assert in_launch_order([part(8), part(0), op, part(4)]) == [part(0), part(8), op, part(4)]
    assert in_launch_order([part(8), part(0)]) == in_launch_order([part(0), part(8)])
    assert in_launch_order([part(0), part(9)]) != in_launch_order([part(0), part(8)])
    other = ("warp", "j", (8,), ())
    assert in_launch_order([part(0), other, part(4)]) == [part(0), other, part(4)]
