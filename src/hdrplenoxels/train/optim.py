"""Learning-rate schedules and the grid optimiser of Plenoxels / HDR-Plenoxels (docs/method.md,
"Training").

The grid is not optimised with `torch.optim.RMSprop`: svox2's kernel initialises the running mean-square
with the first squared gradient (no bias towards 0 at the start) and floors parameters at -1e9, and
HDR-Plenoxels applies it densely to every voxel every step. `Svox2RMSProp` reproduces exactly that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from hdrplenoxels.kernels.dispatch import use_kernel
from hdrplenoxels.kernels.rmsprop import MEAN_SQUARE_FLOOR, RMSPropStep
from hdrplenoxels.kernels.rmsprop_reference import rmsprop_reference_
from hdrplenoxels.kernels.torch_rmsprop import TorchRMSPropStep
from hdrplenoxels.kernels.torch_rmsprop_kernel import torch_rmsprop_
from hdrplenoxels.kernels.torch_rmsprop_reference import torch_rmsprop_reference_
from hdrplenoxels.tonemap.module import ToneMapper

PARAM_FLOOR = -1e9
CATCH_UP_ROWS = 1 << 18
OWED_RATES = 128
"""Steps of SH rates an optimiser owing the view prior's pull keeps (a ring): no row may owe more, so
whoever owes settles at least every `OWED_RATES - 1` steps (the Warp grid: `OWED_SETTLE_EVERY`)."""


@dataclass
class ExpSchedule:
    """Log-linear decay from `lr_init` to `lr_final` over `max_steps`, with an optional sine warm-up.

    `lr(s) = D(s) * exp((1 - t) ln lr_init + t ln lr_final)`, `t = clip(s / max_steps, 0, 1)`,
    `D(s) = m + (1 - m) sin(pi/2 * clip(s / S, 0, 1))` for `S = delay_steps > 0` (else 1), `m = delay_mult`;
    0 for `s < 0` or when both rates are 0. Steps past `max_steps` keep `lr_final` (as svox2 does).
    """

    lr_init: float
    lr_final: float
    max_steps: int
    delay_steps: int = 0
    delay_mult: float = 1.0

    def __post_init__(self) -> None:
        if self.lr_init < 0 or self.lr_final < 0:
            raise ValueError(f"learning rates must be >= 0, got {self.lr_init} -> {self.lr_final}")
        if (self.lr_init == 0) != (self.lr_final == 0):
            raise ValueError("a log-linear schedule needs both rates > 0 (or both 0 to switch it off)")
        if self.max_steps <= 0:
            raise ValueError(f"max_steps must be > 0, got {self.max_steps}")
        if self.delay_steps < 0:
            raise ValueError(f"delay_steps must be >= 0, got {self.delay_steps}")

    def __call__(self, step: int | float) -> float:
        if step < 0 or (self.lr_init == 0 and self.lr_final == 0):
            return 0.0
        if self.delay_steps > 0:
            u = min(max(step / self.delay_steps, 0.0), 1.0)
            delay = self.delay_mult + (1.0 - self.delay_mult) * math.sin(0.5 * math.pi * u)
        else:
            delay = 1.0
        t = min(max(step / self.max_steps, 0.0), 1.0)
        return delay * math.exp((1.0 - t) * math.log(self.lr_init) + t * math.log(self.lr_final))


@dataclass(frozen=True)
class StepClock:
    """The number of the step being taken, twice: `step` for code that runs on the host at every step,
    and `count`, the same number as a (1,) int64 tensor on the training device, for work a CUDA graph
    replays. A replay runs no Python, so there only `count` is the step's own: the replayed region
    advances it itself (`Trainer._step_region`)."""

    step: int
    count: torch.Tensor

    @classmethod
    def at(cls, step: int, device: torch.device | str) -> StepClock:
        return cls(step, torch.full((1,), step, dtype=torch.int64, device=device))


class StepRates:
    """Several `ExpSchedule`s' learning rates at a step given as a device count (`StepClock.count`), as
    one float32 tensor on that device: an optimiser's kernels read their rate from it, so a step replayed
    from a CUDA graph uses its own step's rates, where host floats would stay those of the step that was
    recorded.

    The rates of every step up to `last_step` are computed once, in float64 and rounded to float32 (the
    kernels' precision; tests/test_optim.py holds them to the host schedules), into a table on the
    device: a step then reads its row with one gather instead of evaluating the schedules in a few dozen
    tiny operators, each a kernel of a replayed step on a GPU. The table stops where every schedule has
    settled (its decay and warm-up over) or at `last_step`; a count past its end reads its last row."""

    def __init__(self, schedules: list[ExpSchedule], device: torch.device | str, last_step: int) -> None:
        settled = max([max(s.max_steps, s.delay_steps) for s in schedules], default=0)
        steps = torch.arange(-1, min(settled, max(last_step, 0)) + 1, dtype=torch.float64)
        self.table = _schedule_rates(schedules, steps).to(device)  # row k: step k - 1

    def __call__(self, count: torch.Tensor) -> torch.Tensor:
        """(S,) float32: each schedule's rate at step `count` ((1,) integer tensor), as `ExpSchedule`."""
        row = torch.clamp(count + 1, 0, self.table.shape[0] - 1)
        return self.table.index_select(0, row).reshape(-1)


def _schedule_rates(schedules: list[ExpSchedule], steps: torch.Tensor) -> torch.Tensor:
    """(K, S) float32: `ExpSchedule`'s formula at K float64 `steps` for each of S schedules, evaluated
    in float64 (0 for a negative step or a schedule switched off)."""

    def column(values) -> torch.Tensor:
        return torch.tensor(values, dtype=torch.float64)

    on = torch.tensor([s.lr_init > 0 for s in schedules])
    log_init = column([math.log(s.lr_init) if s.lr_init > 0 else 0.0 for s in schedules])
    log_final = column([math.log(s.lr_final) if s.lr_init > 0 else 0.0 for s in schedules])
    delayed = torch.tensor([s.delay_steps > 0 for s in schedules])
    delay_steps = column([max(s.delay_steps, 1) for s in schedules])
    delay_mult = column([s.delay_mult for s in schedules])
    max_steps = column([s.max_steps for s in schedules])
    k = steps[:, None]
    u = torch.clamp(k / delay_steps, 0.0, 1.0)
    delay = delay_mult + (1.0 - delay_mult) * torch.sin((0.5 * math.pi) * u)
    t = torch.clamp(k / max_steps, 0.0, 1.0)
    decayed = torch.exp((1.0 - t) * log_init + t * log_final)
    rate = torch.where(delayed, delay, 1.0) * decayed
    return torch.where(on & (k >= 0), rate, 0.0).to(torch.float32)


@dataclass(frozen=True)
class OwedPull:
    """What rows owing the view prior's pull owe it under: the grid's (density, SH) it pulls, the pull's
    weights over the SH columns (C,), and the SH rate of each step s at `rates[s % OWED_RATES]`."""

    params: tuple[torch.Tensor, torch.Tensor]
    pull: torch.Tensor
    rates: torch.Tensor


class Svox2RMSProp:
    """svox2's RMSProp for voxel arrays (the grid's density and SH, the MSI's), updated densely.

    Per scalar: `v <- g^2` where `v == 0`, else `v <- beta v + (1 - beta) g^2`;
    `theta <- max(theta - lr g / (sqrt(v) + eps), -1e9)`. State is one `v` per parameter, created at the
    first step; call `reset()` whenever the grid is resampled (the arrays change shape and meaning).

    The fused path may visit only the grid rows a step touched (`step_accumulated(touched=...)`): the
    result is still the dense update, because the decay an untouched row's `v` owes is paid when it is
    next touched, and by `catch_up()` (which `state_dict` and the dense steps call) for the rest.

    Learning rates may be floats or a tensor on the parameters' device (`StepRates`), and the count of
    steps taken lives on that device too: a step replayed from a CUDA graph then updates with its own
    rates and count (`train/step_graph.py`).

    With a pull (the view prior) the update is dense, unless it is owed (`step_accumulated(owe_pull=
    True)`): then an untouched row's pulled steps are owed, and paid in the dense update's arithmetic
    when it is next touched, by `pay_owed` before a step reads it, and by `settle` for every row; the
    result is the dense update's (JOURNAL.md, "The view prior's pull, owed").
    """

    def __init__(self, beta: float = 0.95, eps: float = 1e-8) -> None:
        if not 0.0 <= beta < 1.0:
            raise ValueError(f"beta must be in [0, 1), got {beta}")
        if eps <= 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        self.beta = float(beta)
        self.eps = float(eps)
        self.state: list[torch.Tensor] = []
        # Steps taken since the state was created (or reset, or loaded): (1,) int32 on the state's device.
        self.count: torch.Tensor | None = None
        # After steps over touched rows only: the last step each grid row's state is up to date with.
        self.last_step: torch.Tensor | None = None
        # While the view prior's pull is owed: what the owed steps were (`OwedPull`).
        self.owed: OwedPull | None = None

    @property
    def owing_pull(self) -> bool:
        """Whether rows may owe pulled steps: a step must then `pay_owed` the rows it reads first."""
        return self.owed is not None

    @property
    def steps(self) -> int:
        """Steps taken since the state was created (a read of the device count: not for every step)."""
        return 0 if self.count is None else int(self.count[0])

    def reset(self) -> None:
        """Forget the running mean-squares (done at every grid resample, docs/method.md "Grid")."""
        self.state = []
        self.count = None
        self.last_step = None
        self.owed = None

    @torch.no_grad()
    def catch_up(self) -> None:
        """Pay every row's owed decay (or pulled steps), so the state is what dense steps would have left."""
        if self.owed is not None:
            self.settle()
            self.owed = None
        last = self.last_step
        if last is None:
            return
        for state in self.state:
            rows = state.view(last.shape[0], -1)
            for start in range(0, rows.shape[0], CATCH_UP_ROWS):  # chunks: no grid-sized temporaries
                v = rows[start : start + CATCH_UP_ROWS]
                gap = (self.count - 1 - last[start : start + CATCH_UP_ROWS]).to(v.dtype)[:, None]
                decayed = (v * torch.pow(self.beta, gap)).clamp_(min=MEAN_SQUARE_FLOOR)
                torch.where((v > 0) & (gap > 0), decayed, v, out=v)
        self.last_step = None  # every row is up to date

    @torch.no_grad()
    def pay_owed(self, rows: torch.Tensor | None = None, listed: bool | None = None) -> None:
        """While owing the pull: bring the grid rows marked in `rows` (uint8 over the rows; None: every
        row) up to date with the last step taken, before the next step reads them. The same update
        whenever it is paid (the dense update's own arithmetic, step by step), so paying early changes
        nothing. `listed`: `pay_owed_rows_`'s (the rows that owe listed first)."""
        from hdrplenoxels.kernels.rmsprop_kernel import pay_owed_rows_

        owed = self.owed
        if owed is None or self.last_step is None:
            return
        rule = (self.beta, self.eps, PARAM_FLOOR)
        pay_owed_rows_(
            owed.params,
            (self.state[0], self.state[1]),
            self.last_step,
            self.count,
            owed.pull,
            owed.rates,
            rule,
            rows,
            listed=listed,
        )

    def settle(self) -> None:
        """While owing the pull: pay every row's owed steps, staying in that regime (nothing the
        recorded step depends on changes; JOURNAL.md, "The view prior's pull, owed")."""
        self.pay_owed(None)

    @torch.no_grad()
    def step(
        self,
        params: list[torch.Tensor],
        grads: list[torch.Tensor | None],
        lrs: list[float] | torch.Tensor,
        pulls: list[torch.Tensor | None] | None = None,
    ) -> None:
        """Update every element of every parameter in place; a `None` gradient counts as zero. A param's
        `pulls` entry (C,), weights over its last axis, adds `pull * param` to its gradient: the
        gradient of an L2 prior that holds every row, touched by the step's rays or not
        (`rmsprop_reference_`, the oracle of kernels/rmsprop_kernel.py)."""
        states = self._states(params, grads, lrs)
        self.catch_up()
        self.count.add_(1)
        rates = _rates_for(lrs)
        for p, v, g, lr, pull in zip(params, states, grads, rates, _pulls_for(params, pulls), strict=True):
            g = torch.zeros_like(p) if g is None else g
            rmsprop_reference_(RMSPropStep(p, v, g[None], lr, self.beta, self.eps, PARAM_FLOOR, pull))

    @torch.no_grad()
    def step_accumulated(
        self,
        params: list[torch.Tensor],
        grads: list[torch.Tensor],
        lrs: list[float] | torch.Tensor,
        *,
        fused: bool = True,
        occupancy=None,
        touched: torch.Tensor | None = None,
        pulls: list[torch.Tensor | None] | None = None,
        owe_pull: bool = False,
        listed: bool | None = None,
    ) -> None:
        """`step` (with its `pulls`) from gradient buffers stacked in parts (P, *param.shape), which are
        left zeroed.

        `fused` runs the one-pass Warp kernel (`kernels/rmsprop_kernel.py`), which also rebuilds
        `occupancy` (of the grid whose density is `params[0]`) when given; otherwise this reference: sum
        the parts, `step`, clear. `touched` (params: a grid's density and SH): a uint8 mask over the
        grid's rows that holds every row with a non-zero gradient, left cleared. Without a pull the fused
        update visits only those rows (and adds to the occupancy rather than rebuilding it); a pull acts
        on every row, so with one the update is dense, reading the gradient parts of those rows only,
        unless `owe_pull` (a pull on the SH alone): then the untouched rows owe their pulled steps
        (`owing_pull`), and every later step must `pay_owed` the rows it reads before it reads them.
        `listed`: `fused_grid_rmsprop_touched_`'s (the touched rows listed first).
        """
        pulls = _pulls_for(params, pulls)
        if not fused:
            self.step(params, [g.sum(0) for g in grads], lrs, pulls)
            for g in grads:
                g.zero_()
            if touched is not None:
                touched.zero_()
            return
        from hdrplenoxels.kernels.rmsprop_kernel import fused_rmsprop_

        states = self._states(params, grads, lrs)
        rates = _rates_for(lrs)
        pulled = any(pull is not None for pull in pulls)
        if touched is not None and pulled and owe_pull:
            self._owe_pull(params, states, grads, rates, touched, occupancy, pulls, listed)
        elif touched is None or pulled:
            self.catch_up()
            for i, (p, v, g, lr, pull) in enumerate(zip(params, states, grads, rates, pulls, strict=True)):
                step = RMSPropStep(p, v, g, lr, self.beta, self.eps, PARAM_FLOOR, pull)
                fused_rmsprop_(step, occupancy if i == 0 else None, touched=touched)
            if touched is not None:
                touched.zero_()
        else:
            if len(params) != 2:
                raise ValueError(f"touched rows are for a grid's (density, SH), got {len(params)} params")
            if self.owed is not None:  # the pull has ended: its owed steps are paid first
                self.catch_up()
            self._touched_update(params, states, grads, rates, touched, occupancy, listed=listed)
        self.count.add_(1)

    def _owe_pull(self, params, states, grads, rates, touched, occupancy, pulls, listed) -> None:
        """The touched rows' update with the pull, the others owing it (`step_accumulated`)."""
        if len(params) != 2 or pulls[0] is not None:
            raise ValueError("an owed pull is on a grid's SH: params (density, SH), no pull on the density")
        pull, owed = pulls[1], self.owed
        # Entering the regime, or another pull (a new tensor: `view_prior_pull` keeps one per weight;
        # comparing values would wait for the GPU) or grid: what rows owe (decay, or pulled steps under
        # the old pull) is paid first, so a row owes under one rule at a time.
        if owed is None or owed.pull is not pull or owed.params[1] is not params[1]:
            self.catch_up()
            ring = torch.zeros(OWED_RATES, dtype=torch.float32, device=params[0].device)
            self.owed = OwedPull((params[0], params[1]), pull, ring)
        self._touched_update(params, states, grads, rates, touched, occupancy, self.owed, listed)

    def _touched_update(
        self, params, states, grads, rates, touched, occupancy, owed=None, listed=None
    ) -> None:
        """`fused_grid_rmsprop_touched_` of the grid's (density, SH), with `owed`'s pull when given."""
        from hdrplenoxels.kernels.rmsprop_kernel import fused_grid_rmsprop_touched_

        if self.last_step is None:  # every row is up to date with the previous step
            self.last_step = (self.count - 1).expand(params[0].shape[0]).contiguous()
        fused_grid_rmsprop_touched_(
            (params[0], params[1]),
            (states[0], states[1]),
            (grads[0], grads[1]),
            (rates[0], rates[1]),
            touched,
            self.last_step,
            self.count,
            self.beta,
            self.eps,
            PARAM_FLOOR,
            occupancy,
            pull=None if owed is None else owed.pull,
            rates=None if owed is None else owed.rates,
            listed=listed,
        )

    def _states(
        self, params: list[torch.Tensor], grads: list, lrs: list[float] | torch.Tensor
    ) -> list[torch.Tensor]:
        """The mean-square state of each param (and the count), created at the first step, on the
        param's device."""
        if not len(params) == len(grads) == len(lrs):
            raise ValueError(f"got {len(params)} params, {len(grads)} grads and {len(lrs)} learning rates")
        if not self.state:
            self.state = [torch.zeros_like(p) for p in params]
            self.count = torch.zeros(1, dtype=torch.int32, device=params[0].device)
            self.last_step = None
            self.owed = None
        if len(self.state) != len(params):
            raise ValueError(f"optimiser holds state for {len(self.state)} params, got {len(params)}")
        for i, p in enumerate(params):
            v = self.state[i]
            if v.shape != p.shape:
                raise ValueError(
                    f"param {i} has shape {tuple(p.shape)} but its state {tuple(v.shape)}; "
                    "call reset() after resampling the grid"
                )
            if v.device != p.device or v.dtype != p.dtype:
                self.state[i] = v.to(device=p.device, dtype=p.dtype)
        if self.count.device != params[0].device:
            self.count = self.count.to(params[0].device)
        return self.state

    def state_dict(self) -> dict[str, np.ndarray]:
        """Plain arrays `v0`, `v1`, ... for `save_grid(extra_arrays=...)`; empty before the first step."""
        self.catch_up()
        return {f"v{i}": v.detach().cpu().numpy().copy() for i, v in enumerate(self.state)}

    def load_state_dict(self, state: dict[str, np.ndarray], device: torch.device | str = "cpu") -> None:
        """Restore what `state_dict` returned (shapes are checked against the params at the next step). A
        positive mean square below `MEAN_SQUARE_FLOOR` (a subnormal stall, as states were saved before the
        floor) is raised to it: a CPU kernel reads a subnormal as 0, a fresh state."""
        n = len(state)
        keys = [f"v{i}" for i in range(n)]
        if sorted(state) != sorted(keys):
            raise ValueError(f"optimiser state must have keys {keys}, got {sorted(state)}")
        self.state = [torch.tensor(np.asarray(state[k]), dtype=torch.float32, device=device) for k in keys]
        for v in self.state:
            v.masked_fill_((v > 0) & (v < MEAN_SQUARE_FLOOR), MEAN_SQUARE_FLOOR)
        self.count = torch.zeros(1, dtype=torch.int32, device=device) if self.state else None
        self.last_step = None
        self.owed = None

    def checkpoint_arrays(self) -> dict[str, np.ndarray]:
        """The state exactly as it is, owed decay unpaid: taking a checkpoint then changes nothing, and a
        run resumed from it continues bit for bit (`state_dict` pays the decay, which rounds differently
        from paying it later). An owed pull is paid first (it rounds alike whenever paid), so the arrays
        and the grid beside them hold no owed pulled steps. A CPU optimiser's arrays are views of its
        state, valid until its next step."""
        self.settle()
        arrays = {f"v{i}": v.detach().cpu().numpy() for i, v in enumerate(self.state)}
        if self.state:
            arrays["steps"] = np.array(self.steps)
        if self.last_step is not None:
            arrays["last_step"] = self.last_step.cpu().numpy().copy()
        return arrays

    def load_checkpoint_arrays(
        self,
        arrays: dict[str, np.ndarray],
        device: torch.device | str = "cpu",
        params: list[torch.Tensor] | None = None,
    ) -> None:
        """Restore `checkpoint_arrays()` (or a `state_dict()`, as older checkpoints hold); with `params`,
        a ValueError unless the state fits them (a damaged checkpoint fails here, not steps later)."""
        arrays = dict(arrays)
        steps, last_step = arrays.pop("steps", None), arrays.pop("last_step", None)
        self.load_state_dict(arrays, device)
        if steps is not None:
            steps = np.asarray(steps)
            count = float(steps.reshape(-1)[0]) if steps.size == 1 and steps.dtype.kind in "iuf" else -1.0
            if not 0 <= count < 2**31:
                raise ValueError(f"optimiser steps must be one count, got {steps!r}")
            if self.count is not None:
                self.count.fill_(int(count))
        if last_step is not None:
            self.last_step = torch.as_tensor(np.asarray(last_step), dtype=torch.int32, device=device)
        if params is not None and self.state:
            shapes = [tuple(p.shape) for p in params]
            if [tuple(v.shape) for v in self.state] != shapes:
                raise ValueError(f"optimiser state must have shapes {shapes}")
            if self.last_step is not None and tuple(self.last_step.shape) != shapes[0][:1]:
                raise ValueError(f"optimiser last_step must have shape {shapes[0][:1]}")


def _rates_for(lrs: list[float] | torch.Tensor) -> list[float] | list[torch.Tensor]:
    """One rate per param: the floats as given, or each entry of a rates tensor as a one-element view
    (read by the kernels where they run)."""
    if isinstance(lrs, torch.Tensor):
        return [lrs[i : i + 1] for i in range(lrs.shape[0])]
    return [float(lr) for lr in lrs]


def _pulls_for(params: list[torch.Tensor], pulls: list[torch.Tensor | None] | None) -> list:
    """One pull (or None) per param, each (C,) over its param's last axis."""
    if pulls is None:
        return [None] * len(params)
    if len(pulls) != len(params):
        raise ValueError(f"got {len(pulls)} pulls for {len(params)} params")
    for p, pull in zip(params, pulls):
        if pull is not None and (pull.dim() != 1 or p.dim() < 2 or pull.shape[0] != p.shape[-1]):
            columns, got = tuple(p.shape[-1:]), tuple(pull.shape)
            raise ValueError(f"a pull must be one weight per column {columns}, got {got}")
    return list(pulls)


class TorchRMSProp:
    """torch.optim.RMSprop's update (no momentum, not centred) for a few small tensors.

    Written out because constructing torch's optimiser imports torch._dynamo, 0.8 s of every training
    run's start-up. `state_arrays` uses torch's state names, so older checkpoints still resume. As
    `Svox2RMSProp`, it takes its rate as a float or a one-element tensor, and counts its steps on the
    parameters' device, so that it can step inside a replayed CUDA graph.
    """

    def __init__(self, params, alpha: float = 0.99, eps: float = 1e-8) -> None:
        self.params = list(params)
        self.alpha = float(alpha)
        self.eps = float(eps)
        self.square_avg = [torch.zeros_like(p) for p in self.params]
        device = self.params[0].device if self.params else "cpu"
        self.count = torch.zeros(1, dtype=torch.int64, device=device)  # steps taken

    @property
    def steps(self) -> int:
        """Steps taken (a read of the device count: not for every step)."""
        return int(self.count[0])

    @torch.no_grad()
    def step(self, grads: list[torch.Tensor], lr: float | torch.Tensor) -> None:
        self.count.add_(1)
        for p, g, v in zip(self.params, grads, self.square_avg, strict=True):
            run = torch_rmsprop_ if use_kernel(p) else torch_rmsprop_reference_
            run(TorchRMSPropStep(p, v, g, lr, self.alpha, self.eps))

    def state_arrays(self) -> dict[str, np.ndarray]:
        if not self.steps:
            return {}
        out = {}
        for i, v in enumerate(self.square_avg):
            out[f"{i}/square_avg"] = v.detach().cpu().numpy().copy()
            out[f"{i}/step"] = np.asarray(float(self.steps), dtype=np.float32)
        return out

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore from `state_arrays()`; a ValueError (nothing changed) when the arrays do not fit the
        parameters."""
        square_avg, steps = {}, self.steps
        for name, value in arrays.items():
            i, _, key = name.partition("/")
            if not i.isdigit() or int(i) >= len(self.params) or key not in ("square_avg", "step"):
                raise ValueError(f"unknown optimiser state {name!r} for {len(self.params)} parameters")
            value = np.asarray(value)
            if value.dtype.kind not in "biuf":
                raise ValueError(f"optimiser state {name!r} must be numbers, got {value.dtype}")
            if key == "step":
                if value.size != 1 or not np.isfinite(value).all() or value.reshape(-1)[0] < 0:
                    raise ValueError(f"optimiser state {name!r} must be one step count, got {value!r}")
                steps = int(value.reshape(-1)[0])
                continue
            param = self.params[int(i)]
            if tuple(value.shape) != tuple(param.shape):
                raise ValueError(f"optimiser state {name!r} must have shape {tuple(param.shape)}")
            state = np.ascontiguousarray(value, dtype=np.float32)  # the kernel's layout, whatever the file's
            square_avg[int(i)] = torch.as_tensor(state).to(param.device, param.dtype)
        for i, v in square_avg.items():
            self.square_avg[i] = v
        self.count.fill_(steps)


def make_tone_optimiser(tonemapper: ToneMapper) -> TorchRMSProp:
    """RMSprop (alpha 0.95, as HDR-Plenoxels) over the trainable tone parameters; lr given per step."""
    return TorchRMSProp([p for p in tonemapper.parameters() if p.requires_grad], alpha=0.95, eps=1e-8)
