"""svox2's RMSProp fused into one Warp pass over the grid, reading and clearing the gradient buffers.

The same update as `rmsprop_reference.rmsprop_reference_` (held to it by tests), but one read and
one write of each array instead of a dozen torch passes and temporaries, split over the CPU's
cores by rows, and the gradient parts are summed and zeroed in the same pass.

`fused_grid_rmsprop_touched_` is the same dense update of a grid's density and SH, visiting only the
rows (voxels) a step's gradients touched: an untouched row's values do not move (its gradient is 0)
and its mean squares only decay by beta per step, so that decay is owed, and paid as beta^gap when the
row is next touched (`Svox2RMSProp.catch_up` pays the rest before anything reads the state).

With the view prior's pull an untouched row's SH do move, by the pull alone: those steps are owed too,
and paid step by step, in the dense update's own arithmetic (`pay_owed`, the rates of the owed steps
kept in a ring), by `pay_owed_rows_` before a step reads the row and by the touched update before it
updates it (JOURNAL.md, "The view prior's pull, owed").

The arithmetic of a value's step lives in `kernels/rmsprop_funcs.py`; the touched update and the
paying pass over listed rows, variants for CUDA, in `kernels/rmsprop_listed.py`.

Oracle: `hdrplenoxels.kernels.rmsprop_reference.rmsprop_reference_`; parity: tests/test_optim.py.
"""

# No `from __future__ import annotations` here: Warp evaluates the kernels' annotations, and those that
# name a row type see it only as a closure variable when they are real objects.
import functools

import torch
import warp as wp

from hdrplenoxels.core.parallel import cpu_workers, split
from hdrplenoxels.core.warp_runtime import KERNEL, launch_split, to_warp, warp_device, warp_struct
from hdrplenoxels.kernels.grad_buffers import check_row_array
from hdrplenoxels.kernels.occupancy_kernel import BlockOccupancy, OccupancyMarks, mark_voxel, no_marks
from hdrplenoxels.kernels.rmsprop import RMSPropStep
from hdrplenoxels.kernels.rmsprop_funcs import (
    OwedSteps,
    OwedValues,
    RMSPropRule,
    RowsTouched,
    TouchedUpdate,
    decay_steps,
    flat_pull,
    gradient_in,
    mean_square,
    no_pull,
    owed_decay,
    owed_steps,
    owed_values,
    pay_owed_value,
    pulled_steps,
    rmsprop_rule,
    rmsprop_scalar,
    rmsprop_value,
    rows_touched,
    scalar_array,
    take_element,
    take_entry,
)
from hdrplenoxels.kernels.rmsprop_listed import (
    CUDA_OWED_LISTED,
    CUDA_TOUCHED_LISTED,
    pay_listed,
    touched_listed,
)


@functools.cache
def _row_rules(columns: int, parts: int):
    """(row type, take_row, rmsprop_row) for rows of `columns` values and `parts` gradient buffers
    (unrolled): both kernels that update whole rows share them."""
    row_t = wp.types.vector(length=columns, dtype=wp.float32)

    @wp.func
    def take_row(grads: wp.array2d(dtype=row_t), row: int):
        """Sum a row's gradient parts and clear them."""
        g = grads[0, row]
        grads[0, row] = row_t()
        for p in range(1, parts):
            g = g + grads[p, row]
            grads[p, row] = row_t()
        return g

    @wp.func
    def rmsprop_row(x: row_t, v: row_t, g: row_t, lr: float, rule: RMSPropRule):
        """A row's new values and mean squares."""
        for c in range(columns):
            v[c] = mean_square(v[c], g[c], rule.beta)
            x[c] = rmsprop_value(x[c], g[c], v[c], lr, rule)
        return x, v

    return row_t, take_row, rmsprop_row


@functools.cache
def _owed_rules(columns: int):
    """`pay_owed` for rows of `columns` SH values: the owed steps of a row that the view prior's pull
    moved while no gradient touched it."""
    row_t, _, rmsprop_row = _row_rules(columns, 1)

    @wp.func
    def pay_owed(
        x: row_t,
        v: row_t,
        pull: row_t,
        first: int,
        last: int,
        rates: wp.array(dtype=wp.float32),
        rule: RMSPropRule,
    ):
        """A row's SH and their mean squares after the dense update's steps `first` to `last` with no
        gradient: pulled at each step's rate (`rates[s % len]`), in the arithmetic of `_rmsprop_kernel`
        and `_flat_kernel`, so the result is the dense update's (the density's part: `decay_steps`)."""
        for s in range(first, last + 1):
            x, v = rmsprop_row(x, v, wp.cw_mul(pull, x), rates[s % rates.shape[0]], rule)
        return x, v

    return row_t, pay_owed


@functools.cache
def _owed_kernel(columns: int):
    """Pay the owed pulled steps of every row in `rows` (`RowsTouched`: marked ones, or all), bringing
    it up to the step before `steps[0]`."""
    row_t, pay_owed = _owed_rules(columns)

    @KERNEL
    def pay_owed_rows(
        density_state: wp.array(dtype=wp.float32),
        sh: wp.array(dtype=row_t),
        sh_state: wp.array(dtype=row_t),
        rows: RowsTouched,
        owed: OwedSteps,
        first_row: int,
        pull: wp.array(dtype=row_t),
        rule: RMSPropRule,
    ):
        row = wp.tid() + first_row
        if not gradient_in(rows, row):
            return
        step = owed.steps[0]
        if step - owed.last_step[row] <= 1:
            return
        first = owed.last_step[row] + 1
        density_state[row] = decay_steps(density_state[row], step - first, rule.beta)
        x, v = pay_owed(sh[row], sh_state[row], pull[0], first, step - 1, owed.rates, rule)
        sh[row] = x
        sh_state[row] = v
        owed.last_step[row] = step - 1

    return pay_owed_rows


@KERNEL
def pay_owed_values(
    values: OwedValues,
    rows: RowsTouched,
    owed: OwedSteps,
    first_row: int,
    pull: wp.array(dtype=wp.float32),
    rule: RMSPropRule,
):
    """`pay_owed_rows` a thread per value, launched over (rows, columns): on CUDA the lanes of a warp
    then share one or two rows and so the number of steps they loop over, where a thread per row waits
    for the row of its warp that owes the most. The rows are stamped after (`stamp_paid_rows`)."""
    row, column = wp.tid()
    row += first_row
    if gradient_in(rows, row):
        pay_owed_value(values, owed, pull, rule, row, column)


@KERNEL
def stamp_paid_rows(rows: RowsTouched, owed: OwedSteps, first_row: int):
    """The rows `pay_owed_values` paid are up to the step before `owed.steps[0]`."""
    row = wp.tid() + first_row
    if gradient_in(rows, row) and owed.last_step[row] + 1 < owed.steps[0]:
        owed.last_step[row] = owed.steps[0] - 1


@functools.cache
def _rmsprop_kernel(columns: int, parts: int):
    """The update specialised for `columns` values per row and `parts` gradient buffers (unrolled).

    Rows are loaded and stored as whole vectors, so the arithmetic runs on local values the compiler
    can vectorise (element-wise array access would have to assume the arrays alias)."""
    row_t, take_row, rmsprop_row = _row_rules(columns, parts)

    @KERNEL
    def rmsprop_rows(
        param: wp.array(dtype=row_t),
        state: wp.array(dtype=row_t),
        grads: wp.array2d(dtype=row_t),
        first_row: int,
        lr: wp.array(dtype=wp.float32),
        rule: RMSPropRule,
        pull: row_t,
        touched: RowsTouched,
    ):
        row = wp.tid() + first_row
        x = param[row]
        g = wp.cw_mul(pull, x)
        if gradient_in(touched, row):
            g = take_row(grads, row) + g
        x, v = rmsprop_row(x, state[row], g, lr[0], rule)
        state[row] = v
        param[row] = x

    return rmsprop_rows


@functools.cache
def _touched_kernel(columns: int, parts: int, pulled: bool = False):
    """The update of a grid's density and SH (`columns` values per row), for touched rows only, each
    first paying its owed decay. `mark` adds the rows left with density > 0 to the occupancy, which
    is not cleared first: it stays a superset of the exact one, and skipping stays exact.

    `pulled`: the view prior's `pull` acts (on every row, touched or not): a touched row first pays its
    owed pulled steps a value at a time (`pay_owed_values`' arithmetic, through the float views
    `sh_values`, `sh_state_values` and `pull_values` of the same arrays), then takes the pull with its
    gradient; the step's SH rate is kept in `rates` at `step % len(rates)` for the rows that owe it."""
    row_t, take_row, rmsprop_row = _row_rules(columns, parts)

    @KERNEL
    def rmsprop_touched_rows(
        density: wp.array(dtype=wp.float32),
        density_state: wp.array(dtype=wp.float32),
        density_grads: wp.array2d(dtype=wp.float32),
        sh: wp.array(dtype=row_t),
        sh_state: wp.array(dtype=row_t),
        sh_grads: wp.array2d(dtype=row_t),
        touched: wp.array(dtype=wp.uint8),
        first_row: int,
        update: TouchedUpdate,
        pull: wp.array(dtype=row_t),
        sh_values: wp.array2d(dtype=wp.float32),
        sh_state_values: wp.array2d(dtype=wp.float32),
        pull_values: wp.array(dtype=wp.float32),
    ):
        row = wp.tid() + first_row
        step = update.owed.steps[0]
        # `wp.static`: decided when the kernel is built, so each variant holds only its own code
        if wp.static(pulled) and row == 0:
            update.owed.rates[step % update.owed.rates.shape[0]] = update.lr_sh[0]
        if touched[row] == wp.uint8(0):
            return
        touched[row] = wp.uint8(0)
        gap = step - update.owed.last_step[row] - 1
        update.owed.last_step[row] = step
        vd = density_state[row]
        if wp.static(pulled):
            vd = decay_steps(vd, gap, update.rule.beta)
        else:
            decay = wp.float32(1.0)
            if gap > 0:
                decay = wp.pow(update.rule.beta, float(gap))
                vd = owed_decay(vd, decay)
        gd = take_element(density_grads, parts, row)
        xd, vd = rmsprop_scalar(density[row], vd, gd, update.lr_density[0], update.rule)
        density_state[row] = vd
        density[row] = xd
        if update.mark != 0 and xd > 0.0:
            mark_voxel(update.marks, row)
        # SH: a row vector, read only now, so that it is not held in registers through the density's update
        if wp.static(pulled):
            if gap > 0:  # a value at a time, as `pay_owed_values`: a row's 27 need not be live at once
                for c in range(columns):
                    xc = sh_values[row, c]
                    vc = sh_state_values[row, c]
                    xc, vc = pulled_steps(xc, vc, pull_values[c], step - gap, step, update.owed, update.rule)
                    sh_values[row, c] = xc
                    sh_state_values[row, c] = vc
            x = sh[row]
            v = sh_state[row]
            g = take_row(sh_grads, row) + wp.cw_mul(pull[0], x)
        else:
            g = take_row(sh_grads, row)
            v = sh_state[row]
            if gap > 0:  # its own loop: the usual gap-free row then vectorises like the dense update
                for c in range(columns):
                    v[c] = owed_decay(v[c], decay)
            x = sh[row]  # after the loop: read before it, the row stays in registers across it
        x, v = rmsprop_row(x, v, g, update.lr_sh[0], update.rule)
        sh_state[row] = v
        sh[row] = x

    return rmsprop_touched_rows


@functools.cache
def _flat_kernel(parts: int):
    """The update one element per thread, launched over (rows, columns): on CUDA neighbouring threads
    then touch neighbouring floats (whole-row threads would stride by a row and waste most of every
    memory transaction). With `mark` (the values are a grid's density), it also rebuilds the
    renderer's occupancy in the same pass."""

    @KERNEL
    def rmsprop_flat(
        param: wp.array2d(dtype=wp.float32),
        state: wp.array2d(dtype=wp.float32),
        grads: wp.array3d(dtype=wp.float32),
        first_row: int,
        lr: wp.array(dtype=wp.float32),
        rule: RMSPropRule,
        pull: wp.array(dtype=wp.float32),
        mark: int,
        marks: OccupancyMarks,
        touched: RowsTouched,
    ):
        row, column = wp.tid()
        row += first_row
        x = param[row, column]
        g = pull[column % pull.shape[0]] * x
        if gradient_in(touched, row):
            g = take_entry(grads, parts, row, column) + g
        x, v = rmsprop_scalar(x, state[row, column], g, lr[0], rule)
        state[row, column] = v
        param[row, column] = x
        if mark != 0 and x > 0.0:
            mark_voxel(marks, row)

    return rmsprop_flat


def fused_rmsprop_(
    s: RMSPropStep,
    occupancy: BlockOccupancy | None = None,
    per_element: bool | None = None,
    touched: torch.Tensor | None = None,
) -> None:
    """`s`'s step (`RMSPropStep`) in place, for a param (M,) or (M, C), or of more axes (the MSI's: rows
    over its last axes); its gradient parts are left zeroed. With `occupancy` (the param is its grid's
    density), the occupancy is rebuilt for the new density in the same pass. `per_element`: a thread per
    element (default on CUDA) or per row (default on the CPU, where whole rows vectorise). `touched` (M,)
    uint8, for a param of M rows: the rows whose gradient parts hold anything (any other row's must all
    be 0); only theirs are read and cleared, the rest take the pull alone (the same result: a zero
    gradient adds nothing)."""
    param, state, grads, lr, pull = s.param, s.state, s.grads, s.lr, s.pull
    n = param.shape[0] * (param.shape[1] if param.dim() > 2 else 1)  # more axes: rows of the others
    if n == 0:
        return
    device = warp_device(param)
    columns = param.numel() // n
    # One value a row is an element: the row kernel's vector view would need the parts' rows contiguous.
    flat = occupancy is not None or columns == 1 or (device != "cpu" if per_element is None else per_element)
    if pull is not None and (param.dim() != 2 or pull.shape != param.shape[1:]):
        raise ValueError(f"a pull is one weight per column of a (M, C) param, got {tuple(pull.shape)}")
    if touched is not None:
        check_row_array("touched", touched, n, torch.uint8)
    scope = rows_touched(touched, device)
    # Views, never copies (`view` raises where `reshape` would copy): the kernels write in place.
    param_rows, state_rows = param.detach().view(n, columns), state.view(n, columns)
    grad_rows = grads.view(grads.shape[0], n, columns)
    if flat:  # one thread per element: dims (rows, columns)
        kernel = _flat_kernel(grads.shape[0])
        marking = [0, no_marks(device)] if occupancy is None else [1, occupancy.marks()]
        inputs = [
            to_warp(param_rows, "the parameters"),
            to_warp(state_rows, "the mean squares"),
            to_warp(grad_rows, "the gradient parts"),
        ]
        constants = [
            scalar_array(lr, torch.float32, "rate", param),
            rmsprop_rule(s.beta, s.eps, s.floor),
            flat_pull(pull, device),
            *marking,
            scope,
        ]
    else:
        kernel = _rmsprop_kernel(columns, grads.shape[0])
        row_t = wp.types.vector(length=columns, dtype=wp.float32)
        inputs = [
            to_warp(param_rows, "the parameters", dtype=row_t),
            to_warp(state_rows, "the mean squares", dtype=row_t),
            to_warp(grad_rows, "the gradient parts", dtype=row_t),
        ]
        weights = [0.0] * columns if pull is None else pull.float().tolist()
        constants = [
            scalar_array(lr, torch.float32, "rate", param),
            rmsprop_rule(s.beta, s.eps, s.floor),
            row_t(*weights),
            scope,
        ]
    # every row costs the same: launch_parts' default split
    launch_split(kernel, n, inputs, constants, device, columns=columns if flat else None)
    # Warp wrote behind torch's back: bump the version counters so caches keyed on them (the
    # renderer's block occupancy) see the change, and autograd refuses stale saved tensors.
    torch.autograd.graph.increment_version([param, state, grads])
    if occupancy is not None:
        occupancy.rebuilt_for(param)


# Touched rows cluster (where the batch's rays cross the scene), so large grids are cut into more
# parts than threads (each thread takes the next part when done, which evens out the work); small
# ones are not, as every launch costs tens of microseconds.
PARTS_PER_WORKER = 8


ROWS_PER_PART = 1 << 16


def _row_parts(n: int) -> list[tuple[int, int]]:
    """The CPU parts of a pass over some of a grid's `n` rows (`PARTS_PER_WORKER`)."""
    workers = cpu_workers()
    return split(n, min(PARTS_PER_WORKER * workers, max(workers, n // ROWS_PER_PART)))


def fused_grid_rmsprop_touched_(
    params: tuple[torch.Tensor, torch.Tensor],
    states: tuple[torch.Tensor, torch.Tensor],
    grads: tuple[torch.Tensor, torch.Tensor],
    lrs: tuple[float | torch.Tensor, float | torch.Tensor],
    touched: torch.Tensor,
    last_step: torch.Tensor,
    step: int | torch.Tensor,
    beta: float,
    eps: float,
    floor: float,
    occupancy: BlockOccupancy | None = None,
    pull: torch.Tensor | None = None,
    rates: torch.Tensor | None = None,
    listed: bool | None = None,
) -> None:
    """`fused_rmsprop_` of a grid's (density (M,), SH (M, C)) for the rows i with `touched[i] != 0`
    (uint8, (M,)): each first pays the decay owed for the steps since `last_step[i]` (int32, (M,)),
    then takes step `step`. Every other row must have zero gradient in all parts. `touched` is left
    cleared and `last_step[i]` = `step` where updated. With `occupancy` (of this grid), the rows left
    with density > 0 are marked in it, without clearing it first (see `_touched_kernel`). `lrs` and
    `step` may be tensors on the grid's device ((1,) float32, (1,) int32), read where the kernel runs,
    as `fused_rmsprop_`'s rate.

    `pull` (C,), `fused_rmsprop_`'s pull on the SH, with `rates` (R,) float32: the steps a row owes
    are pulled ones, paid as the dense update would have taken them at the SH rates kept in `rates`
    (this step's written at `step % R`), so no row may owe R steps or more (`pay_owed_rows_`).

    `listed`: the touched rows listed first, then a fixed number of threads update their values
    (`_listed_touched_kernel`); None: `CUDA_TOUCHED_LISTED` on CUDA, never on a CPU. The same numbers."""
    density, sh = params
    n = density.shape[0]
    if n == 0:
        return
    if sh.shape[0] != n or density.dim() != 1:
        shapes = f"{tuple(density.shape)}, {tuple(sh.shape)}"
        raise ValueError(f"expected a grid's density (M,) and SH (M, C), got {shapes}")
    check_row_array("touched", touched, n, torch.uint8)
    check_row_array("last_step", last_step, n, torch.int32)
    columns = sh.numel() // n
    device = warp_device(density)
    if occupancy is None:  # nothing is marked; the kernel still needs arrays of the right types
        marks = no_marks(device)
    else:
        if occupancy.density_stamp is None or not occupancy.density_stamp.matches(density):
            occupancy.rebuild(density)  # marks are only added below: they must hold for it now
        marks = occupancy.marks(clear=False)
    pull_row, ring = _owed_inputs(pull, rates, columns, device)
    update = warp_struct(
        TouchedUpdate,
        owed=owed_steps(last_step, step, ring, density),
        lr_density=scalar_array(lrs[0], torch.float32, "rate", density),
        lr_sh=scalar_array(lrs[1], torch.float32, "rate", density),
        rule=rmsprop_rule(beta, eps, floor),
        mark=int(occupancy is not None),
        marks=marks,
    )
    if CUDA_TOUCHED_LISTED and device != "cpu" if listed is None else listed:
        touched_listed(params, states, grads, touched, update, pull is not None, flat_pull(pull, device))
    else:
        _touched_rows(params, states, grads, touched, update, pull, pull_row)
    torch.autograd.graph.increment_version([density, sh, *states, *grads, touched, last_step])
    if occupancy is not None:
        occupancy.rebuilt_for(density)


def _touched_rows(params, states, grads, touched, update: TouchedUpdate, pull, pull_row) -> None:
    """`fused_grid_rmsprop_touched_` a thread per row (`_touched_kernel`), over every row."""
    density, sh = params
    n, buffers = density.shape[0], grads[0].shape[0]
    columns = sh.numel() // n
    row_t = wp.types.vector(length=columns, dtype=wp.float32)
    device = warp_device(density)
    kernel = _touched_kernel(columns, buffers, pull is not None)
    inputs = [
        to_warp(density.detach(), "the grid density"),
        to_warp(states[0], "the density mean squares"),
        to_warp(grads[0], "the density gradient parts"),
        to_warp(sh.detach().view(n, -1), "the grid SH", dtype=row_t),
        to_warp(states[1].view(n, -1), "the SH mean squares", dtype=row_t),
        to_warp(grads[1].view(buffers, n, -1), "the SH gradient parts", dtype=row_t),
        to_warp(touched, "the touched rows"),
    ]
    constants = [update, pull_row]
    values = [
        to_warp(sh.detach().view(n, -1), "the grid SH"),
        to_warp(states[1].view(n, -1), "the SH mean squares"),
        flat_pull(pull, device),
    ]
    launch_split(kernel, n, inputs, constants + values, device, _row_parts(n))


def _owed_inputs(
    pull: torch.Tensor | None, rates: torch.Tensor | None, columns: int, device: str
) -> tuple[wp.array, wp.array]:
    """The kernels' (pull, rates ring) arguments: the pull's `columns` weights as one row (an array, read
    where the kernel runs: no copy to the host) with its ring, or without a pull a zero row and a
    one-slot ring that nothing reads."""
    if pull is None:
        return _zero_row(columns, device), no_pull(device)
    if pull.shape != (columns,) or rates is None or rates.dim() != 1 or rates.dtype != torch.float32:
        raise ValueError(f"an owed pull is ({columns},) weights with a 1-D float32 ring of rates")
    row_t = wp.types.vector(length=columns, dtype=wp.float32)
    weights = pull.float().contiguous().view(1, columns)
    return to_warp(weights, "the pull", dtype=row_t), to_warp(rates, "the owed steps' rates")


@functools.cache
def _zero_row(columns: int, device: str) -> wp.array:
    return wp.zeros(1, dtype=wp.types.vector(length=columns, dtype=wp.float32), device=device)


def pay_owed_rows_(
    params: tuple[torch.Tensor, torch.Tensor],
    states: tuple[torch.Tensor, torch.Tensor],
    last_step: torch.Tensor,
    step: torch.Tensor,
    pull: torch.Tensor,
    rates: torch.Tensor,
    rule: tuple[float, float, float],
    rows: torch.Tensor | None = None,
    per_element: bool | None = None,
    listed: bool | None = None,
) -> None:
    """Bring the rows in `rows` (uint8 (M,), nonzero: marked; None: every row) of a grid's (density (M,),
    SH (M, C)) and their mean squares up to the step before `step` ((1,) int32, the step about to be
    taken): each pays the pulled steps it owes since `last_step` (`fused_grid_rmsprop_touched_` with
    `pull`), and `last_step` becomes `step - 1` there. A step's reads of those rows then see what the
    dense update would have left. `rule`: (beta, eps, floor). `per_element`: a thread per value
    (`pay_owed_values`, default on CUDA) or per row (default on the CPU, where whole rows vectorise);
    `listed` (with marked `rows`): the rows that owe listed first, then their values paid by a fixed
    number of threads (`pay_listed_values`; None: `CUDA_OWED_LISTED` on CUDA, never on a CPU). The same
    numbers every way."""
    density, sh = params
    n = density.shape[0]
    if n == 0:
        return
    check_row_array("last_step", last_step, n, torch.int32)
    columns = sh.numel() // n
    device = warp_device(density)
    per_value = device != "cpu" if per_element is None else per_element
    listed = rows is not None and (CUDA_OWED_LISTED and device != "cpu" if listed is None else listed)
    if not (per_value or listed):  # a thread per row: the pull as one row vector
        weights, ring = _owed_inputs(pull, rates, columns, device)
    else:  # without a pull, a zero pull at a zero rate, as `_owed_inputs`
        ring = no_pull(device) if pull is None else to_warp(rates, "the owed steps' rates")
        weights = flat_pull(pull, device)
    owed, terms = owed_steps(last_step, step, ring, density), rmsprop_rule(*rule)
    if listed:
        pay_listed(owed_values(states[0], sh, states[1]), rows, owed, weights, terms)
    elif per_value:
        values = owed_values(states[0], sh, states[1])
        scope = rows_touched(rows, device)
        # two passes, so no thread reads a row's last step after another of its threads stamped it
        parts = _row_parts(n)
        launch_split(pay_owed_values, n, [values, scope, owed], [weights, terms], device, parts, columns)
        launch_split(stamp_paid_rows, n, [scope, owed], [], device, parts)
    else:
        row_t = wp.types.vector(length=columns, dtype=wp.float32)
        values = [
            to_warp(states[0], "the density mean squares"),  # the density does not move: no gradient
            to_warp(sh.detach().view(n, -1), "the grid SH", dtype=row_t),
            to_warp(states[1].view(n, -1), "the SH mean squares", dtype=row_t),
        ]
        head = [*values, rows_touched(rows, device), owed]
        launch_split(_owed_kernel(columns), n, head, [weights, terms], device, _row_parts(n))
    torch.autograd.graph.increment_version([sh, *states, last_step])
