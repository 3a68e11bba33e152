"""The MSI background saved with a native grid file: exact round trip, absent when not saved, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.io import load_background, load_grid, save_grid
from hdrplenoxels.grid.sparse_grid import SparseGrid


def make_pair(seed: int = 0) -> tuple[SparseGrid, MSIBackground]:
    g = torch.Generator().manual_seed(seed)
    grid = SparseGrid.create((4, 4, 4), center=(0.1, -0.2, 0.3), radius=(1.0, 2.0, 0.5), basis_dim=4)
    bg = MSIBackground.create(grid, layers=3, height=4, width=8, samples_per_layer=3)
    bg.density = torch.randn(bg.density.shape, generator=g)
    bg.color = torch.rand(bg.color.shape, generator=g) * 1e4  # HDR values survive exactly
    return grid, bg


def test_background_round_trip_is_exact(tmp_path):
    grid, bg = make_pair()
    save_grid(tmp_path / "g.npz", grid, meta={"step": 3}, background=bg)
    loaded = load_background(tmp_path / "g.npz")
    assert torch.equal(loaded.density, bg.density) and torch.equal(loaded.color, bg.color)
    assert (loaded.center, loaded.radius, loaded.samples_per_layer) == (bg.center, bg.radius, 3)
    grid2, meta, extra = load_grid(tmp_path / "g.npz")  # the grid reads as before, the background is no extra
    assert meta == {"step": 3} and extra == {} and torch.equal(grid2.links, grid.links)


def test_a_grid_saved_without_background_has_none(tmp_path):
    grid, _ = make_pair()
    save_grid(tmp_path / "g.npz", grid)
    assert load_background(tmp_path / "g.npz") is None


def test_a_damaged_background_is_an_input_error_naming_the_problem(tmp_path):
    grid, bg = make_pair()
    path = save_grid(tmp_path / "g.npz", grid, background=bg)
    z = dict(np.load(path))
    del z["bg/color"]
    np.savez(tmp_path / "no_color.npz", **z)
    with pytest.raises(InputError, match="bg/color"):
        load_background(tmp_path / "no_color.npz")
    z = dict(np.load(path))
    z["bg/color"] = z["bg/color"][:, :, :5]
    np.savez(tmp_path / "bad_shape.npz", **z)
    with pytest.raises(InputError, match="colour"):
        load_background(tmp_path / "bad_shape.npz")
