"""The view prior's pull owed by untouched rows (`Svox2RMSProp.step_accumulated(owe_pull=True)`) leaves
what the dense update leaves, paid early or late (JOURNAL.md, "The view prior's pull, owed").

The optimiser's tests run on the fast device (to the bit on the CPU; on CUDA within rounding, the dense
update there being a thread per element, whose sums the compiler may contract otherwise); the trained
runs on the CPU, where two runs are equal to the bit (CUDA's atomics are not)."""

import pytest
import torch
from cuda_kernels import use_cuda_kernels
from devices import FAST_DEVICE

from hdrplenoxels.train.optim import OWED_RATES, Svox2RMSProp

ROWS, COLUMNS = 300, 12


def _grid(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    density = torch.randn(ROWS, generator=g)
    sh = torch.randn(ROWS, COLUMNS, generator=g)
    return density.to(FAST_DEVICE), sh.to(FAST_DEVICE)


def _pull(weight: float) -> torch.Tensor:
    pull = torch.full((3, COLUMNS // 3), 2.0 * weight)
    pull[:, 0] = 0.0
    return pull.reshape(-1).to(FAST_DEVICE)


def _equal(got: torch.Tensor, want: torch.Tensor) -> None:
    exact = FAST_DEVICE.type == "cpu"
    torch.testing.assert_close(got, want, rtol=0 if exact else 1e-5, atol=0 if exact else 1e-6)


def _close(got: torch.Tensor, want: torch.Tensor) -> None:
    """Equal but for the rounding of a power against repeated products (and on CUDA `_equal`'s)."""
    cpu = FAST_DEVICE.type == "cpu"
    torch.testing.assert_close(got, want, rtol=1e-6 if cpu else 1e-5, atol=1e-7 if cpu else 1e-6)


def _train(owe: bool, steps: int, seed: int = 0, reads: bool = False, pull_until: int | None = None):
    """`steps` steps of random sparse gradients (touched rows only) with the pull, densely or owed; with
    `reads`, random rows are paid before each step as a forward's reads would be."""
    density, sh = _grid(seed)
    opt = Svox2RMSProp(beta=0.95)
    g = torch.Generator().manual_seed(seed + 1)
    pull = _pull(0.3)
    for step in range(steps):
        touched = (torch.rand(ROWS, generator=g) < 0.1).to(torch.uint8)
        mask = touched.bool()
        gd = torch.zeros(2, ROWS)
        gs = torch.zeros(2, ROWS, COLUMNS)
        gd[:, mask] = torch.randn(2, int(mask.sum()), generator=g)
        gs[:, mask] = torch.randn(2, int(mask.sum()), COLUMNS, generator=g)
        read = (torch.rand(ROWS, generator=g) < 0.2).to(torch.uint8)
        touched, gd, gs, read = (t.to(FAST_DEVICE) for t in (touched, gd, gs, read))
        if reads and opt.owing_pull:
            opt.pay_owed(read)
        lrs = torch.tensor([0.5 / (1 + step), 0.05 / (1 + 0.1 * step)], device=FAST_DEVICE)
        pulls = [None, pull if pull_until is None or step < pull_until else None]
        opt.step_accumulated([density, sh], [gd, gs], lrs, touched=touched, pulls=pulls, owe_pull=owe)
    opt.catch_up()
    return density, sh, opt.state


@pytest.mark.parametrize("reads", [False, True])
def test_owed_pull_is_the_dense_update(reads):
    dense = _train(False, 40)
    owed = _train(True, 40, reads=reads)
    for a, b in zip((*dense[:2], *dense[2]), (*owed[:2], *owed[2]), strict=True):
        _equal(b, a)


def test_owed_pull_then_none_is_the_dense_update():
    """The pull ends inside the run: what is owed is paid under it, then owed decay takes over."""
    dense = _train(False, 30, pull_until=17)
    owed = _train(True, 30, pull_until=17, reads=True)
    for a, b in zip((*dense[:2], *dense[2]), (*owed[:2], *owed[2]), strict=True):
        _close(b, a)  # the decay after it is paid as beta^gap


def test_rows_owe_steps_until_paid():
    """An owing row's values are stale (else the test above would show nothing) until paid."""
    density, sh = _grid(3)
    opt = Svox2RMSProp(beta=0.95)
    touched = torch.zeros(ROWS, dtype=torch.uint8, device=FAST_DEVICE)
    touched[:5] = 1
    grads = [torch.zeros(1, ROWS, device=FAST_DEVICE), torch.zeros(1, ROWS, COLUMNS, device=FAST_DEVICE)]
    before, pull = sh.clone(), _pull(0.3)  # one tensor: a new one is another pull (what is owed is paid)
    for _ in range(3):
        opt.step_accumulated(
            [density, sh], grads, [0.1, 0.05], touched=touched.clone(), pulls=[None, pull], owe_pull=True
        )
    assert opt.owing_pull
    assert torch.equal(sh[5:], before[5:])  # untouched: owed
    assert not torch.equal(sh[:5, 1:], before[:5, 1:])  # touched: pulled
    opt.settle()
    assert not torch.equal(sh[5:, 1:], before[5:, 1:])
    assert torch.equal(sh[5:, 0], before[5:, 0])  # no pull on the DC term
    assert opt.owing_pull  # settling stays owing: the recorded step does not change


@pytest.mark.parametrize("pulled", [True, False])
def test_paying_a_thread_per_value_is_paying_a_thread_per_row(pulled):
    """CUDA's paying passes (`pay_owed_values`, then the rows' stamp; and the variant that lists the rows
    that owe first, `pay_listed_values`) against the CPU's (a thread per row): rows owing 0 to 9 steps,
    some marked, the same values, mean squares and last steps."""
    from hdrplenoxels.kernels.rmsprop_kernel import pay_owed_rows_

    g = torch.Generator().manual_seed(7)
    density, sh = _grid(5)
    start = [torch.rand(ROWS, generator=g).to(FAST_DEVICE), (torch.rand(ROWS, COLUMNS, generator=g) * 1e-3)]
    start[1] = start[1].to(FAST_DEVICE)
    start[0][:7] = 0.0  # fresh states
    owes = torch.randint(0, 10, (ROWS,), generator=g, dtype=torch.int32).to(FAST_DEVICE)
    step = torch.tensor([20], dtype=torch.int32, device=FAST_DEVICE)
    rates = (torch.rand(128, generator=g) * 0.1).to(FAST_DEVICE)
    marked = (torch.rand(ROWS, generator=g) < 0.5).to(torch.uint8).to(FAST_DEVICE)
    pull = _pull(0.3) if pulled else None
    paid = []
    for per_element, listed in ((False, False), (True, False), (True, True)):
        sh_now, states, last = sh.clone(), [s.clone() for s in start], step - 1 - owes
        pay_owed_rows_(
            (density, sh_now),
            states,
            last,
            step,
            pull,
            rates,
            (0.95, 1e-8, -1e9),
            marked,
            per_element,
            listed,
        )
        paid.append((sh_now, *states, last))
    rows, values, listed_values = paid
    for a, b, c in zip(rows, values, listed_values, strict=True):
        _equal(b, a)
        _equal(c, a)
    unmarked = (marked == 0) & (owes > 0)
    assert torch.equal(rows[3][marked.bool()], step.expand(int(marked.sum())) - 1)  # stamped
    assert torch.equal(rows[3][unmarked], (step - 1 - owes)[unmarked])  # still owing
    assert not torch.equal(rows[1], start[0]) and torch.equal(rows[1][unmarked], start[0][unmarked])
    moved = marked.bool() & (owes > 0)
    assert torch.equal(rows[0][moved, 1:], sh[moved, 1:]) != pulled  # paid: pulled, or with no pull at rate 0


def test_the_tv_layouts_train_alike(tiny_scene, tmp_path):
    """`tv_layout`: a thread per (cell, channel) trains as a thread per cell, to the bit on the CPU, with
    the owed pull's marks (`marks_only`) and the TV's own marks in play."""
    cell, _ = _trained(tiny_scene, tmp_path / "cell", owe=True, tv_layout="cell")
    channel, _ = _trained(tiny_scene, tmp_path / "channel", owe=True, tv_layout="channel")
    a, b = cell.model().field, channel.model().field
    assert torch.equal(a.density, b.density) and torch.equal(a.sh, b.sh)


def test_the_listed_row_passes_train_as_the_passes_over_every_row(tiny_scene, tmp_path, monkeypatch):
    """`owed_pay` and `touched_update` "listed" (the rows that owe, and the touched rows, listed first)
    train as the passes over every row, to the bit on the CPU, with the forward's marks, the SH TV's and
    the occupancy's in play (a launch recorder sees the listed kernels run in place of the others)."""
    from hdrplenoxels.core import warp_runtime
    from hdrplenoxels.kernels import rmsprop_listed

    every, _ = _trained(tiny_scene, tmp_path / "every", owe=True, row_passes="every-row")
    launched, launch = [], warp_runtime.launch_kernel
    for module in (warp_runtime, rmsprop_listed):  # `launch_split` launches through warp_runtime's
        monkeypatch.setattr(
            module, "launch_kernel", lambda k, **kw: (launched.append(k.func.__name__), launch(k, **kw))
        )
    listed, _ = _trained(tiny_scene, tmp_path / "listed", owe=True, row_passes="listed")
    assert {"pay_listed_values", "rmsprop_listed_values"} <= set(launched)
    assert not {"pay_owed_values", "rmsprop_touched_rows"} & set(launched)  # (settling pays every row)
    a, b = every.model().field, listed.model().field
    assert torch.equal(a.density, b.density) and torch.equal(a.sh, b.sh)


def test_ring_bounds_the_owed_steps():
    assert OWED_RATES >= 64


def _trained(
    tiny_scene,
    folder,
    owe: bool,
    steps: int = 30,
    schedule: int = 30,
    tv_layout: str = "auto",
    row_passes: str = "auto",
):
    from test_train import tiny_config

    from hdrplenoxels.train.trainer import Trainer

    cfg = tiny_config(schedule)
    cfg.device = "cpu"
    cfg.tonemap.enabled = True
    cfg.view_prior_update = "owed" if owe else "dense"
    cfg.optim.lambda_tv_sh = 1e-3  # the SH's TV reads rows that may owe the pull
    cfg.tv_layout, cfg.owed_pay, cfg.touched_update = tv_layout, row_passes, row_passes
    trainer = Trainer(tiny_scene, cfg, folder)
    owing = []
    for _ in range(steps):
        trainer.train_step()
        owing.append(trainer.engine.optimiser.owing_pull)
    return trainer, owing


@pytest.mark.parametrize("cuda_kernels", [False, True])
def test_owed_view_prior_trains_as_the_dense_one(tiny_scene, tmp_path, monkeypatch, cuda_kernels):
    """The tiny scene tone-mapped (the view prior on for two thirds of it, a resample at step 20):
    every voxel's density and SH, and the tone parameters, as the dense update leaves them, to the bit.
    Also with CUDA's kernels on the CPU (`cuda_kernels.use_cuda_kernels`: the lanes' backward re-marches,
    so the rows it reads are the marking march's), where "auto" owes the pull."""
    if cuda_kernels:
        use_cuda_kernels(monkeypatch)
    dense, dense_owing = _trained(tiny_scene, tmp_path / "dense", owe=False)
    owed, owed_owing = _trained(tiny_scene, tmp_path / "owed", owe=True)
    assert not any(dense_owing)
    assert owed_owing[:19] == [True] * 19 and owed_owing[-1] is False  # the prior ends at step 20
    a, b = dense.model().field, owed.model().field
    assert torch.equal(a.density, b.density) and torch.equal(a.sh, b.sh)
    tones = dense.tonemapper.state_dict(), owed.tonemapper.state_dict()
    assert all(torch.equal(value, tones[1][key]) for key, value in tones[0].items())


def test_a_model_taken_while_owing_is_settled(tiny_scene, tmp_path):
    """`Trainer.model` (what saving, evaluation and the viewer read) pays what is owed first."""
    dense, _ = _trained(tiny_scene, tmp_path / "dense", owe=False, steps=6)
    owed, owing = _trained(tiny_scene, tmp_path / "owed", owe=True, steps=6)
    assert owing[-1]
    stale = owed.engine.field.sh.detach().clone()
    assert not torch.equal(stale, dense.engine.field.sh)  # rows owe the pull
    assert torch.equal(owed.model().field.sh, dense.model().field.sh)
    # a recorded CUDA step that pays what rows owe is not the one recorded before they owed
    assert owed.engine.graph_key() == (0, True) and dense.engine.graph_key() == (0, False)


def test_settling_often_with_a_small_ring_trains_the_same(tiny_scene, tmp_path, monkeypatch):
    """Every voxel's owed steps are paid every `OWED_SETTLE_EVERY` steps, so a ring of rates only that
    long (here 4, settled every 2 steps) never wraps onto a step still owed."""
    from hdrplenoxels.train import optim
    from hdrplenoxels.train.engines import warp_grid

    dense, _ = _trained(tiny_scene, tmp_path / "dense", owe=False)
    monkeypatch.setattr(optim, "OWED_RATES", 4)
    monkeypatch.setattr(warp_grid, "OWED_SETTLE_EVERY", 2)
    owed, _ = _trained(tiny_scene, tmp_path / "owed", owe=True)
    assert owed.engine.optimiser.owed is None or owed.engine.optimiser.owed.rates.shape == (4,)
    assert torch.equal(dense.model().field.sh, owed.model().field.sh)
