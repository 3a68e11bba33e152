"""The grid's touched update and the owed pull's paying pass over listed rows, variants for CUDA
(`TrainConfig.touched_update`, `owed_pay` = "listed"): a thread per row lists the rows that need the
pass (the touched rows, or the marked rows that owe), then a fixed number of threads stride over the
listed rows' values. The passes over values do not grow with the grid and a warp's threads read and
write neighbouring floats, where the passes of `kernels/rmsprop_kernel.py` launch a thread per row (or
per value) of the whole grid. Each value in the same arithmetic (`kernels/rmsprop_funcs.py`), so the same
numbers (JOURNAL.md, "The touched update and the owed pull over listed rows").

Oracle: `hdrplenoxels.kernels.rmsprop_reference.rmsprop_reference_`; parity: tests/test_optim.py.
"""

# No `from __future__ import annotations` here: Warp evaluates the kernels' annotations.
import functools

import torch
import warp as wp

from hdrplenoxels.core.warp_runtime import KERNEL, launch_kernel, to_warp, warp_device
from hdrplenoxels.kernels import rmsprop_funcs as rf
from hdrplenoxels.kernels.grad_buffers import check_row_array
from hdrplenoxels.kernels.occupancy_kernel import mark_voxel


@KERNEL
def list_owing_rows(
    rows: rf.RowsTouched,
    owed: rf.OwedSteps,
    listed: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """Append each marked row that owes a step to `listed`, counting them in `count[0]` (in the order
    the atomic adds fall: each row is paid on its own, so the order changes no number)."""
    row = wp.tid()
    if rf.gradient_in(rows, row) and owed.last_step[row] + 1 < owed.steps[0]:
        listed[wp.atomic_add(count, 0, 1)] = row


@KERNEL
def pay_listed_values(
    values: rf.OwedValues,
    listed: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    owed: rf.OwedSteps,
    pull: wp.array(dtype=wp.float32),
    rule: rf.RMSPropRule,
    threads: int,
):
    """`pay_owed_values` over the listed rows only: `threads` threads stride over their values, so the
    launch is the same size whatever the grid and however many rows owe (a CUDA graph replays it)."""
    columns = wp.int64(values.sh.shape[1])
    total = wp.int64(count[0]) * columns  # 64 bits: a large grid's listed values pass 2^31
    k = wp.int64(wp.tid())
    while k < total:
        entry = k // columns
        column = int(k - entry * columns)
        rf.pay_owed_value(values, owed, pull, rule, listed[int(entry)], column)
        k += wp.int64(threads)


@KERNEL
def stamp_listed_rows(
    listed: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), owed: rf.OwedSteps, threads: int
):
    """The rows `pay_listed_values` paid are up to the step before `owed.steps[0]`."""
    k = wp.tid()
    while k < count[0]:
        owed.last_step[listed[k]] = owed.steps[0] - 1
        k += threads


@KERNEL
def list_touched_rows(
    touched: wp.array(dtype=wp.uint8),
    update: rf.TouchedUpdate,
    pulled: int,
    listed: wp.array(dtype=wp.int32),
    gaps: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """The touched update's rows, listed (`_touched_kernel`'s bookkeeping, a thread per row): each
    touched row is cleared, appended to `listed` with the steps it missed (`gaps`) and stamped with this
    step; with `pulled`, this step's SH rate is kept in the ring."""
    row = wp.tid()
    owed = update.owed
    step = owed.steps[0]
    if pulled != 0 and row == 0:
        owed.rates[step % owed.rates.shape[0]] = update.lr_sh[0]
    if touched[row] != wp.uint8(0):
        touched[row] = wp.uint8(0)
        k = wp.atomic_add(count, 0, 1)
        listed[k] = row
        gaps[k] = step - owed.last_step[row] - 1
        owed.last_step[row] = step


@functools.cache
def _listed_touched_kernel(pulled: bool):
    """`_touched_kernel`'s update of the listed rows, a thread per value (the SH's C, then the density):
    `threads` threads stride over them, so on CUDA a warp's threads read and write neighbouring floats
    of one or two rows, where a thread per row strides a row apart. Each value in `_touched_kernel`'s
    arithmetic (a row's vector operations are its values' own), so the same numbers."""

    @KERNEL
    def rmsprop_listed_values(
        density: wp.array(dtype=wp.float32),
        density_state: wp.array(dtype=wp.float32),
        density_grads: wp.array2d(dtype=wp.float32),
        sh: wp.array2d(dtype=wp.float32),
        sh_state: wp.array2d(dtype=wp.float32),
        sh_grads: wp.array3d(dtype=wp.float32),
        listed: wp.array(dtype=wp.int32),
        gaps: wp.array(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        update: rf.TouchedUpdate,
        pull: wp.array(dtype=wp.float32),
        threads: int,
    ):
        columns = sh.shape[1]
        width = wp.int64(columns + 1)
        total = wp.int64(count[0]) * width  # 64 bits: a large grid's listed values pass 2^31
        step = update.owed.steps[0]
        k = wp.int64(wp.tid())
        while k < total:
            entry = int(k // width)
            column = int(k - wp.int64(entry) * width)
            row = listed[entry]
            gap = gaps[entry]
            if column == columns:  # the density
                vd = density_state[row]
                if wp.static(pulled):
                    vd = rf.decay_steps(vd, gap, update.rule.beta)
                elif gap > 0:
                    vd = rf.owed_decay(vd, wp.pow(update.rule.beta, float(gap)))
                gd = rf.take_element(density_grads, density_grads.shape[0], row)
                xd, vd = rf.rmsprop_scalar(density[row], vd, gd, update.lr_density[0], update.rule)
                density_state[row] = vd
                density[row] = xd
                if update.mark != 0 and xd > 0.0:
                    mark_voxel(update.marks, row)
            else:
                x = sh[row, column]
                v = sh_state[row, column]
                g = wp.float32(0.0)
                if wp.static(pulled):
                    w = pull[column]
                    x, v = rf.pulled_steps(x, v, w, step - gap, step, update.owed, update.rule)
                    g = rf.take_entry(sh_grads, sh_grads.shape[0], row, column) + w * x
                else:
                    if gap > 0:
                        v = rf.owed_decay(v, wp.pow(update.rule.beta, float(gap)))
                    g = rf.take_entry(sh_grads, sh_grads.shape[0], row, column)
                x, v = rf.rmsprop_scalar(x, v, g, update.lr_sh[0], update.rule)
                sh_state[row, column] = v
                sh[row, column] = x
            k += wp.int64(threads)

    return rmsprop_listed_values


# On CUDA the touched update lists the touched rows, then strides over their values
# (`_listed_touched_kernel`): off until a GPU's timing chooses (`make gpu-check`'s levels run it).
CUDA_TOUCHED_LISTED = False


def touched_listed(params, states, grads, touched, update: rf.TouchedUpdate, pulled: bool, pull) -> None:
    """`fused_grid_rmsprop_touched_(listed=True)`: list the touched rows, then update their values (one
    launch each: the list's atomic counter is shared by the whole launch)."""
    density, sh = params
    n, buffers = density.shape[0], grads[0].shape[0]
    device = warp_device(density)
    listed = torch.empty(n, dtype=torch.int32, device=density.device)
    gaps = torch.empty(n, dtype=torch.int32, device=density.device)
    count = torch.zeros(1, dtype=torch.int32, device=density.device)
    lists = [to_warp(t, "the listed rows") for t in (listed, gaps, count)]
    launch_kernel(
        list_touched_rows,
        dim=n,
        inputs=[to_warp(touched, "the touched rows"), update, int(pulled), *lists],
        device=device,
    )
    threads = listed_threads(device)
    inputs = [
        to_warp(density.detach(), "the grid density"),
        to_warp(states[0], "the density mean squares"),
        to_warp(grads[0], "the density gradient parts"),
        to_warp(sh.detach().view(n, -1), "the grid SH"),
        to_warp(states[1].view(n, -1), "the SH mean squares"),
        to_warp(grads[1].view(buffers, n, -1), "the SH gradient parts"),
        *lists,
        update,
        pull,
        threads,
    ]
    launch_kernel(_listed_touched_kernel(pulled), dim=threads, inputs=inputs, device=device)


# On CUDA the paying pass lists the rows that owe, then strides over their values (`pay_listed_values`):
# off until a GPU's timing chooses (`make gpu-check`'s levels run it beside the default).
CUDA_OWED_LISTED = False


LISTED_THREADS_PER_SM = 1024  # `pay_listed_values`' threads on CUDA: this many a multiprocessor


def listed_threads(device: str) -> int:
    """How many threads stride over the listed values: the GPU's resident threads, or one CPU thread."""
    if device == "cpu":
        return 1
    return torch.cuda.get_device_properties(device).multi_processor_count * LISTED_THREADS_PER_SM


def pay_listed(
    values: rf.OwedValues,
    rows: torch.Tensor,
    owed: rf.OwedSteps,
    weights: wp.array,
    rule: rf.RMSPropRule,
) -> None:
    """`pay_owed_rows_(listed=True)`: list the marked rows that owe, pay their values, stamp them; one
    launch each (the list's atomic counter is shared by the whole launch)."""
    device = warp_device(rows)
    n = values.sh.shape[0]
    check_row_array("rows", rows, n, torch.uint8)
    listed = torch.empty(n, dtype=torch.int32, device=rows.device)
    count = torch.zeros(1, dtype=torch.int32, device=rows.device)
    listed_w, count_w = to_warp(listed, "the listed rows"), to_warp(count, "the listed rows' count")
    launch_kernel(
        list_owing_rows, dim=n, inputs=[rf.rows_touched(rows, device), owed, listed_w, count_w], device=device
    )
    threads = listed_threads(device)
    pay = [values, listed_w, count_w, owed, weights, rule, threads]
    launch_kernel(pay_listed_values, dim=threads, inputs=pay, device=device)
    launch_kernel(stamp_listed_rows, dim=threads, inputs=[listed_w, count_w, owed, threads], device=device)
