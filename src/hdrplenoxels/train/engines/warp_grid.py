"""The grid on the Warp kernels: forward and hand-written backward, fused touched-row RMSProp.

The engine owns what makes the kernels fast: per-thread gradient buffers, the forward's sample record
(CPU), the Morton ray order, and the renderer's block occupancy, which the fused update keeps current.
With a background model (the MSI) the forward first marches it, then composites it behind the grid with
the transmittance the grid's march leaves, which the background's backward scales its gradient by
(docs/design.md, "Kernels").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hdrplenoxels.core.warp_runtime import warp_device
from hdrplenoxels.kernels.background_kernel import msi_accumulate_backward, msi_forward, msi_gradient_parts
from hdrplenoxels.kernels.grad_buffers import GridGradients, gradient_parts
from hdrplenoxels.kernels.march_kernel import (
    accumulate_backward,
    mark_read_rows,
    records_samples,
    render_forward,
)
from hdrplenoxels.kernels.occupancy_kernel import TIGHTEN_EVERY, occupancy_for
from hdrplenoxels.kernels.sample_record import SampleRecord
from hdrplenoxels.kernels.tv import TVTerm
from hdrplenoxels.kernels.tv_kernel import tv_grad_
from hdrplenoxels.render.ray_order import training_order
from hdrplenoxels.train.engines.grid_engine import GridEngine
from hdrplenoxels.train.optim import OWED_RATES
from hdrplenoxels.train.ray_pool import RayBatch

OWED_SETTLE_EVERY = OWED_RATES // 2
"""Steps between payments of every voxel's owed view-prior pull (`Svox2RMSProp.settle`): a dense pass
once per this many steps instead of every step, and no voxel owes more than the ring of rates holds."""
TV_LAYOUTS = {"auto": None, "cell": False, "channel": True}  # `TrainConfig.tv_layout` as `tv_grad_` takes it
# `TrainConfig.owed_pay` and `touched_update` as the optimiser takes them (None: the device's default)
ROW_PASSES = {"auto": None, "every-row": False, "listed": True}


@dataclass
class PendingBackward:
    """What a forward leaves for its backward: the (reordered) batch, its radiance and sample record, and
    with a background model the radiance behind the grid, the transmittance the grid left in front of it,
    and the distortion sums."""

    batch: RayBatch
    rgb: torch.Tensor
    record: SampleRecord | None
    behind: torch.Tensor | None
    transmittance: torch.Tensor | None
    distortion_stats: torch.Tensor | None


class WarpGridEngine(GridEngine):
    render_backend = "warp"
    fused_optimiser = True

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._record: SampleRecord | None = None
        self._pending: PendingBackward | None = None

    def _gradient_parts(self) -> int:
        return gradient_parts(self.field)

    def _background_parts(self) -> int:
        return msi_gradient_parts(self.background)

    def _record_for(self, rays: int) -> SampleRecord | None:
        """The forward's record of a batch's samples, for the backward (reused from step to step);
        None where the kernels keep none (CUDA)."""
        if not records_samples(warp_device(self.field.density)):
            return None
        if self._record is None or self._record.rays != rays:
            self._record = SampleRecord.empty(rays, self.device)
        return self._record

    def forward(self, batch: RayBatch) -> tuple[torch.Tensor, RayBatch]:
        grads = self.gradients()  # sized (after a resample) before the record and the forward take memory
        if self.optimiser.owing_pull:  # the rows it reads pay the view prior's pull they owe first
            mark_read_rows(self.field, batch.origins, batch.dirs, self.render_opt, grads.touched)
            self.optimiser.pay_owed(grads.touched, ROW_PASSES[self.cfg.owed_pay])
        order = training_order(self.field, batch.origins, batch.dirs)
        if order is not None:  # CPU threads march rays in turn: neighbours should share voxels
            batch = batch.reordered(order)
        record = self._record_for(len(batch.origins))
        behind = transmittance = None
        if self.background is not None:
            behind = self._background_forward(batch)
            transmittance = batch.origins.new_empty(batch.origins.shape[0])
        n = batch.origins.shape[0]
        stats = batch.origins.new_empty((n, 3)) if self.distortion_weight > 0 else None
        rgb = render_forward(
            self.field,
            batch.origins,
            batch.dirs,
            self.render_opt,
            record=record,
            behind=behind,
            transmittance=transmittance,
            distortion=stats,
        )
        self._pending = PendingBackward(batch, rgb, record, behind, transmittance, stats)
        return rgb.requires_grad_(True), batch

    def _background_forward(self, batch: RayBatch) -> torch.Tensor:
        """The background's radiance behind each ray (N, 3)."""
        return msi_forward(self.background, batch.origins, batch.dirs, self.render_opt)

    def _background_backward(self, batch: RayBatch, behind: torch.Tensor, grad_behind: torch.Tensor) -> None:
        """d loss / d C_bg (N, 3) into the background's gradient buffers."""
        msi_accumulate_backward(
            self.background,
            batch.origins,
            batch.dirs,
            behind,
            grad_behind,
            self.render_opt,
            self.background_gradients(),
        )

    def backward(self, grad_rgb: torch.Tensor) -> None:
        """The backward kernels add straight into the gradient buffers (replaying the record on CPU);
        the background's sees d loss / d C_bg = T_fg d loss / d C (docs/method.md, "Background"); the
        distortion loss (the batch mean times `distortion_weight`) adds its gradient in the same pass."""
        pending, self._pending = self._pending, None
        batch, stats = pending.batch, pending.distortion_stats
        if self.background is not None:
            self._background_backward(batch, pending.behind, pending.transmittance[:, None] * grad_rgb)
        distortion = None
        if stats is not None:
            per_ray = self.distortion_weight / stats.shape[0]
            distortion = (stats, torch.full_like(stats[:, 0], per_ray))
        accumulate_backward(
            self.field,
            batch.origins,
            batch.dirs,
            pending.rgb.detach(),
            grad_rgb,
            self.render_opt,
            self.gradients(),
            record=pending.record,
            distortion=distortion,
        )

    def _add_tv(self, term: TVTerm, grad_parts: torch.Tensor, grads: GridGradients) -> None:
        per_channel = TV_LAYOUTS[self.cfg.tv_layout]
        if self.optimiser.owing_pull and term.values.dim() == 2:  # the SH's: its rows pay what they owe
            tv_grad_(term, grad_parts, touched=grads.touched, marks_only=True, per_channel=per_channel)
            self.optimiser.pay_owed(grads.touched, ROW_PASSES[self.cfg.owed_pay])
        tv_grad_(term, grad_parts, touched=grads.touched, per_channel=per_channel)

    def after_step(self, step: int) -> None:
        """Every `TIGHTEN_EVERY` steps the occupancy is rebuilt exactly, whatever the steps did: the
        touched update inside a step only adds marks to it, and a replayed step leaves the host nothing
        to tell whether it did (it runs no Python). What voxels owe of the view prior's pull is paid
        every `OWED_SETTLE_EVERY` steps (no voxel may owe `OWED_RATES` steps) and once it ends."""
        if step % TIGHTEN_EVERY == 0:
            occupancy_for(self.field).rebuild(self.field.density)
        if self.optimiser.owing_pull:
            if step >= self.cfg.view_prior_end():
                self.optimiser.catch_up()  # the next steps owe no pull: settled, out of that regime
            elif step % OWED_SETTLE_EVERY == 0:
                self.settle()

    def _update_scope(self, grads: GridGradients) -> dict:
        """The fused update visits only the rows this step's gradients touched (the result of a dense
        update), or with the view prior's pull every row unless the others owe it
        (`TrainConfig.view_prior_update`); it marks the renderer's occupancy for the new density in the
        same pass."""
        update = self.cfg.view_prior_update
        owe = update == "owed" or (update == "auto" and self.device.type == "cuda")
        listed = ROW_PASSES[self.cfg.touched_update]
        return {
            "occupancy": occupancy_for(self.field),
            "touched": grads.touched,
            "owe_pull": owe,
            "listed": listed,
        }
