"""The Warp functions and structs the grid's RMSProp kernels share (`kernels/rmsprop_kernel.py`, the
dense and touched updates and the owed pull's pass; `kernels/rmsprop_listed.py`, their variants over
listed rows): one arithmetic for a value's step, its owed decay and its owed pulled steps, so that every
form of the update leaves the same numbers.
"""

# No `from __future__ import annotations` here: Warp evaluates the structs' annotations.
import functools

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import to_warp, warp_struct
from hdrplenoxels.kernels.occupancy_kernel import OccupancyMarks
from hdrplenoxels.kernels.rmsprop import MEAN_SQUARE_FLOOR


@wp.func
def mean_square(v: float, g: float, beta: float) -> float:
    """svox2's running mean square: a fresh state (0) starts at g^2; a positive one stays at or above
    `MEAN_SQUARE_FLOOR`."""
    g2 = g * g
    return wp.where(v == 0.0, g2, wp.max(v * beta + g2 * (1.0 - beta), wp.float32(MEAN_SQUARE_FLOOR)))


@wp.struct
class RMSPropRule:
    """The constants of one svox2 RMSProp step, shared by every array it updates (each has its own lr)."""

    beta: float
    eps: float
    floor: float
    """No value drops below it."""


def rmsprop_rule(beta: float, eps: float, floor: float) -> RMSPropRule:
    return warp_struct(RMSPropRule, beta=float(beta), eps=float(eps), floor=float(floor))


@wp.func
def rmsprop_value(x: float, g: float, v: float, lr: float, rule: RMSPropRule) -> float:
    return wp.max(x - lr * (g / (wp.sqrt(v) + rule.eps)), rule.floor)


@wp.func
def owed_decay(v: float, decay: float) -> float:
    """A mean square after the decays its row missed (`decay` = beta^gap, gap > 0), floored as the dense
    decay is (`MEAN_SQUARE_FLOOR`)."""
    return wp.where(v > 0.0, wp.max(v * decay, wp.float32(MEAN_SQUARE_FLOOR)), v)


@wp.func
def take_element(grads: wp.array2d(dtype=wp.float32), parts: int, i: int) -> float:
    """Sum element i's gradient parts and clear them."""
    g = wp.float32(0.0)
    for p in range(parts):
        g += grads[p, i]
        grads[p, i] = 0.0
    return g


@wp.struct
class RowsTouched:
    """The rows whose gradient parts a dense update reads (`fused_rmsprop_`'s `touched`): with `known`
    0 every row's; else those with `rows[row] != 0`, every other row's gradient being 0 (the view
    prior's dense steps: most rows then take only the pull, and reading and clearing their zero
    gradients would be most of the pass's memory traffic)."""

    known: int
    rows: wp.array(dtype=wp.uint8)


@wp.func
def gradient_in(touched: RowsTouched, row: int) -> bool:
    return touched.known == 0 or touched.rows[row] != wp.uint8(0)


@wp.struct
class OwedSteps:
    """What the touched update and the owed pull's passes keep of the steps: each row's last step taken
    (`last_step` (M,) int32), the step about to be taken (`steps` (1,) int32, read where the kernel
    runs) and the ring of recent steps' SH rates (`rates` (R,) float32, a step's at `step % R`; one
    unread slot without a pull)."""

    last_step: wp.array(dtype=wp.int32)
    steps: wp.array(dtype=wp.int32)
    rates: wp.array(dtype=wp.float32)


def owed_steps(
    last_step: torch.Tensor, step: int | torch.Tensor, rates: wp.array, like: torch.Tensor
) -> OwedSteps:
    """`OwedSteps` over a grid's last steps, the step (`scalar_array`'s forms) and a ring of rates."""
    return warp_struct(
        OwedSteps,
        last_step=to_warp(last_step, "the last steps"),
        steps=scalar_array(step, torch.int32, "step", like),
        rates=rates,
    )


@wp.func
def rmsprop_scalar(x: float, v: float, g: float, lr: float, rule: RMSPropRule):
    """An element's new value and mean square (`v` after any owed decay)."""
    v = mean_square(v, g, rule.beta)
    return rmsprop_value(x, g, v, lr, rule), v


@wp.func
def decay_steps(v: float, steps: int, beta: float) -> float:
    """A mean square after `steps` steps with no gradient, step by step as the dense update takes them
    (not `beta^steps`: the owed pull's rows must end where the dense update's do, to the bit)."""
    for _s in range(steps):
        v = mean_square(v, 0.0, beta)
    return v


@wp.func
def pulled_steps(x: float, v: float, w: float, first: int, stop: int, owed: OwedSteps, rule: RMSPropRule):
    """A value and its mean square after the steps `first` to `stop - 1` with no gradient but the pull
    (`w` times the value), each at its own rate from `owed.rates`: the dense update's arithmetic."""
    for s in range(first, stop):
        x, v = rmsprop_scalar(x, v, w * x, owed.rates[s % owed.rates.shape[0]], rule)
    return x, v


@wp.struct
class OwedValues:
    """What paying owed steps a value at a time moves (`pay_owed_value`): the SH values and their mean
    squares, a row per voxel, and the density's mean square (the density has no pull, only its decay)."""

    density_state: wp.array(dtype=wp.float32)
    sh: wp.array2d(dtype=wp.float32)
    sh_state: wp.array2d(dtype=wp.float32)


def owed_values(density_state: torch.Tensor, sh: torch.Tensor, sh_state: torch.Tensor) -> OwedValues:
    """`OwedValues` over a grid's tensors: the SH (M, ...) and its mean squares as rows of M."""
    n = density_state.shape[0]
    return warp_struct(
        OwedValues,
        density_state=to_warp(density_state, "the density mean squares"),
        sh=to_warp(sh.detach().view(n, -1), "the grid SH"),
        sh_state=to_warp(sh_state.view(n, -1), "the SH mean squares"),
    )


@wp.func
def pay_owed_value(
    values: OwedValues,
    owed: OwedSteps,
    pull: wp.array(dtype=wp.float32),
    rule: RMSPropRule,
    row: int,
    column: int,
):
    """One SH value of `row` and its mean square brought up to the step before `owed.steps[0]`, pulled
    at each owed step's rate; column 0's call also decays the density's mean square. `last_step` is
    read, not stamped: the row's other values read it too."""
    step = owed.steps[0]
    first = owed.last_step[row] + 1
    if first < step:
        x = values.sh[row, column]
        v = values.sh_state[row, column]
        w = pull[column % pull.shape[0]]  # one 0 for every column without a pull (`no_pull`)
        x, v = pulled_steps(x, v, w, first, step, owed, rule)
        values.sh[row, column] = x
        values.sh_state[row, column] = v
        if column == 0:
            values.density_state[row] = decay_steps(values.density_state[row], step - first, rule.beta)


@wp.func
def take_entry(grads: wp.array3d(dtype=wp.float32), parts: int, row: int, column: int) -> float:
    """Sum an entry's gradient parts (parts, rows, columns) and clear them."""
    g = wp.float32(0.0)
    for p in range(parts):
        g += grads[p, row, column]
        grads[p, row, column] = 0.0
    return g


def rows_touched(touched: torch.Tensor | None, device: str) -> RowsTouched:
    """`RowsTouched` of a mask, or (None) every row read."""
    if touched is None:
        return every_row(device)
    return warp_struct(RowsTouched, known=1, rows=to_warp(touched, "the touched rows"))


@functools.cache
def every_row(device: str) -> RowsTouched:
    return warp_struct(RowsTouched, known=0, rows=wp.zeros(1, dtype=wp.uint8, device=device))


@functools.cache
def no_pull(device: str) -> wp.array:
    """The element kernel's pull when there is none: one 0 that every column reads (made once, not
    every step)."""
    return wp.zeros(1, dtype=wp.float32, device=device)


def flat_pull(pull: torch.Tensor | None, device: str) -> wp.array:
    """A pull as the kernels that take a value at a time read it: its weights (C,), or `no_pull`."""
    return no_pull(device) if pull is None else to_warp(pull.float().contiguous(), "the pull")


def scalar_array(
    value: float | int | torch.Tensor, dtype: torch.dtype, what: str, like: torch.Tensor
) -> wp.array:
    """A kernel's learning rate or step as a one-element Warp array on `like`'s device: a tensor's own
    memory (a view of a `StepRates` result, an optimiser's count), which the kernel reads where it runs
    (a replayed CUDA graph's own value), or a number filled into a new one (no copy from the host)."""
    if not isinstance(value, torch.Tensor):
        value = torch.full((1,), value, dtype=dtype, device=like.device)
    if value.shape != (1,) or value.dtype != dtype or value.device != like.device:
        got = f"{tuple(value.shape)} {value.dtype} on {value.device}"
        raise ValueError(f"a {what} tensor is (1,) {dtype} on {like.device}, got {got}")
    return to_warp(value.contiguous(), f"the {what}")


@wp.struct
class TouchedUpdate:
    """What both forms of the touched update (a thread per row, or the rows listed) take besides the
    grid's arrays."""

    owed: OwedSteps
    lr_density: wp.array(dtype=wp.float32)
    """The density's rate (one element, read where the kernel runs)."""
    lr_sh: wp.array(dtype=wp.float32)
    rule: RMSPropRule
    mark: int
    """1: mark the rows left with density > 0 in `marks`."""
    marks: OccupancyMarks
