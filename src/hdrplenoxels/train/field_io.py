"""Every kind of radiance field behind one save and load (docs/design.md, "Engine interface").

A saved field records its kind in the file's `format` entry, so a model file loads to the right
renderer: the sparse grid's native format (grid/io.py), or a NeRF's network weights
(`hdrplenoxels-nerf`, the same `.npz` conventions: no pickle, atomic writes, `meta_json`, `x/` extras).
A NeRF file holds its `NerfConfig` (network and sampling), never the Adam settings it trained with.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import numpy as np
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.grid import io as grid_io
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import SparseGrid
from hdrplenoxels.render.fields import Field
from hdrplenoxels.render.nerf import NerfConfig, NerfField

NERF_FORMAT = "hdrplenoxels-nerf"
NERF_VERSION = 1
WEIGHT_PREFIX = "w/"


def save_field(
    path,
    field: Field,
    meta: dict[str, Any] | None = None,
    extra_arrays: dict[str, np.ndarray] | None = None,
    background: MSIBackground | None = None,
) -> None:
    """Write `field` (+ JSON `meta`, `extra_arrays` and the grid's MSI `background`) atomically, in its
    kind's format."""
    grid_io.write_npz(path, field_arrays(field, meta, extra_arrays, background))


def field_arrays(
    field: Field,
    meta: dict[str, Any] | None = None,
    extra_arrays: dict[str, np.ndarray] | None = None,
    background: MSIBackground | None = None,
) -> dict[str, np.ndarray]:
    """The entries `save_field` writes, as host arrays (`grid_io.grid_arrays`: views of a CPU field's
    tensors, valid while it is unchanged)."""
    if isinstance(field, SparseGrid):
        return grid_io.grid_arrays(field, meta=meta, extra_arrays=extra_arrays, background=background)
    if background is not None:
        raise ValueError("only a voxel grid is saved with an MSI background")
    header = {"config": dataclasses.asdict(field.cfg), "n_images": field.n_images}
    arrays = {
        "format": np.array(NERF_FORMAT),
        "version": np.array(NERF_VERSION, dtype=np.int64),
        "meta_json": np.array(json.dumps(meta or {})),
        "nerf_json": np.array(json.dumps(header)),
    }
    for name, value in field.state_dict().items():
        arrays[WEIGHT_PREFIX + name] = value.detach().cpu().numpy()
    for name, value in (extra_arrays or {}).items():
        arrays[grid_io.EXTRA_PREFIX + name] = np.asarray(value)
    return arrays


def load_field(
    path, device: torch.device | str = "cpu"
) -> tuple[Field, dict[str, Any], dict[str, np.ndarray]]:
    """Read a file written by `save_field` -> (field, meta, extra arrays); defects are `InputError`s."""
    field, _, meta, extra = load_field_with_background(path, device)
    return field, meta, extra


def load_field_with_background(
    path, device: torch.device | str = "cpu"
) -> tuple[Field, MSIBackground | None, dict[str, Any], dict[str, np.ndarray]]:
    """`load_field`, and the MSI background saved with a grid (None when there is none)."""
    z = grid_io.read_npz(path)
    if "format" not in z or grid_io.scalar_str(path, z, "format") != NERF_FORMAT:
        grid, meta, extra = grid_io.grid_from_arrays(path, z, device)
        return grid, grid_io.background_from_arrays(path, z, device), meta, extra
    meta = grid_io.checked_meta(path, z, NERF_VERSION, "NeRF file")
    try:
        header = json.loads(grid_io.scalar_str(path, z, "nerf_json"))
        # Files before the Adam settings moved to training's `NerfSettings` also hold lr, lr_final and
        # lr_decay_steps: not the network's, so not read.
        cfg = NerfConfig.among(header["config"])
        weights = {
            k.removeprefix(WEIGHT_PREFIX): torch.from_numpy(v)
            for k, v in z.items()
            if k.startswith(WEIGHT_PREFIX)
        }
        field = NerfField(cfg, [0.0] * 3, [1.0] * 3, int(header["n_images"]))
        field.load_state_dict(weights)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise InputError(path, f"the NeRF's description or weights don't fit together ({e})") from e
    return field.to(device), None, meta, grid_io.extra_arrays(z)
