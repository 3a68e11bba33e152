"""Fitting a trained model's tone controller (`tonemap/controller.py`) to its training views' learned
tones, the field frozen: each training view is rendered small and metered, and the form with the
smallest leave-one-out error is kept. Test views never take part (their tones were learned from
their left halves only)."""

from __future__ import annotations

import math

import numpy as np
import torch

from hdrplenoxels.render import Backend
from hdrplenoxels.tonemap.controller import Readings, ToneController, choose_form, fit, meter
from hdrplenoxels.train.model import Model

METER_LONG_SIDE = 96  # training views are rendered this large to meter them (a camera's meter is coarse)


def view_readings(model: Model, ids: list[int], backend: Backend = "warp") -> list[Readings]:
    """The meter readings of views `ids`, rendered with their long side METER_LONG_SIDE."""
    cams, out = model.cameras, []
    for i in ids:
        w, h = cams.size(i)
        s = min(1.0, METER_LONG_SIDE / max(w, h))
        size = (max(1, round(w * s)), max(1, round(h * s)))
        radiance = model.render_view(
            cams.c2w[i], cams.intrinsics_at(i, size), size, backend, model.default_appearance(i)
        )
        out.append(meter(model.hdr(radiance)))
    return out


def learned_stops(model: Model, ids: list[int]) -> np.ndarray:
    """The learned tones of views `ids` as log white balance in stops (N, 3), on linear radiance."""
    return (model.tonemapper.linear_log_wb()[ids] / math.log(2.0)).cpu().numpy()


@torch.no_grad()
def fit_controller(model: Model, backend: Backend = "warp") -> tuple[ToneController, dict[str, float]]:
    """The controller for `model` (which must have a tone mapper) and every form's leave-one-out error
    in stops (empty with fewer than 4 training views, which get the mean tone)."""
    if model.tonemapper is None:
        raise ValueError("a tone controller needs a model trained with tone mapping")
    ids = list(model.train_ids)
    readings = view_readings(model, ids, backend)
    stops = learned_stops(model, ids)
    form, errors = choose_form(readings, stops)
    return fit(form, readings, stops), errors


def controller_note(controller: ToneController, errors: dict[str, float]) -> str:
    """One line for the command line: the form chosen and its leave-one-out error beside the mean tone's."""
    if not errors:
        return f"tone controller: {controller.form} (too few training views to fit a meter)"
    return (
        f"tone controller: {controller.form}, leave-one-out error {errors[controller.form]:.2f} stops "
        f"over the training views (mean tone: {errors['mean']:.2f})"
    )
