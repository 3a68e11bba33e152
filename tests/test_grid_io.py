"""Grid files: native round trip, atomic saves, clear errors on bad input, svox2 import/export."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.grid import io as grid_io
from hdrplenoxels.grid.io import export_svox2, import_svox2, load_grid, save_grid
from hdrplenoxels.grid.sparse_grid import SparseGrid


def make_grid(seed: int = 0, reso=(4, 5, 3), basis_dim: int = 9) -> SparseGrid:
    g = torch.Generator().manual_seed(seed)
    keep = torch.rand(reso, generator=g) > 0.3
    density = torch.randn(reso, generator=g) * 10
    sh = torch.randn((*reso, 3 * basis_dim), generator=g)
    return SparseGrid.from_dense(density, sh, (0.1, -0.2, 0.3), (1.0 + 1 / 3, 2.0, 0.7), keep)


def assert_grid_equal(a: SparseGrid, b: SparseGrid) -> None:
    assert torch.equal(a.links, b.links)
    assert a.links.dtype == b.links.dtype == torch.int32
    assert torch.equal(a.density, b.density)
    assert torch.equal(a.sh, b.sh)
    assert a.center == b.center
    assert a.radius == b.radius


def test_native_round_trip_is_exact(tmp_path):
    grid = make_grid()
    meta = {"step": 1234, "reso_list": [[128, 128, 128]], "name": "fern", "lr": 0.5}
    extra = {
        "rms/v0": np.random.default_rng(0).random(grid.num_voxels).astype(np.float32),
        "epoch": np.array(3),
    }
    out = save_grid(tmp_path / "grid.npz", grid, meta=meta, extra_arrays=extra)
    assert out == tmp_path / "grid.npz"
    loaded, meta2, extra2 = load_grid(tmp_path / "grid.npz")
    assert_grid_equal(grid, loaded)
    assert meta2 == meta
    assert set(extra2) == set(extra)
    for k, v in extra.items():
        assert np.array_equal(extra2[k], v) and extra2[k].dtype == v.dtype
    assert list(tmp_path.iterdir()) == [tmp_path / "grid.npz"]  # no temp files left over


def test_native_file_holds_no_pickle_and_any_suffix_works(tmp_path):
    grid = make_grid(basis_dim=1)
    save_grid(tmp_path / "grid.ckpt", grid)  # numpy must not append ".npz"
    assert (tmp_path / "grid.ckpt").exists()
    with np.load(tmp_path / "grid.ckpt", allow_pickle=False) as z:
        assert str(z["format"]) == "hdrplenoxels-grid" and int(z["version"]) == 2
    loaded, meta, extra = load_grid(tmp_path / "grid.ckpt")
    assert_grid_equal(grid, loaded)
    assert meta == {} and extra == {}


def test_failed_save_keeps_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "grid.npz"
    save_grid(path, make_grid(seed=1))
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(grid_io.np.lib.format, "write_array", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        save_grid(path, make_grid(seed=2))
    assert path.read_bytes() == before
    assert list(tmp_path.iterdir()) == [path]
    with pytest.raises(ValueError, match="JSON"):
        save_grid(path, make_grid(seed=2), meta={"bad": object()})
    assert path.read_bytes() == before


def _expect_input_error(fn, path, *fragments):
    with pytest.raises(InputError) as info:
        fn(path)
    msg = str(info.value)
    assert path.name in msg
    for frag in fragments:
        assert frag in msg, msg
    assert "\n" not in msg


@pytest.mark.parametrize("loader", [load_grid, import_svox2])
def test_unreadable_files_raise_input_error(tmp_path, loader):
    _expect_input_error(loader, tmp_path / "missing.npz", "not found")
    _expect_input_error(loader, tmp_path, "folder")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(np.random.default_rng(0).bytes(4096))
    _expect_input_error(loader, junk, "not a readable .npz")
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    _expect_input_error(loader, empty, "not a readable .npz")
    good = tmp_path / "good.npz"
    save_grid(good, make_grid())
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    _expect_input_error(loader, truncated)
    npy = tmp_path / "single.npz"
    with open(npy, "wb") as f:
        np.save(f, np.zeros(3))
    _expect_input_error(loader, npy, ".npy")
    pickled = tmp_path / "pickled.npz"
    with open(pickled, "wb") as f:
        np.savez(f, links=np.array([{"a": 1}], dtype=object))
    _expect_input_error(loader, pickled, "links")


def test_damaged_member_raises_input_error(tmp_path):
    good = tmp_path / "good.npz"
    save_grid(good, make_grid())
    data = bytearray(good.read_bytes())
    mid = len(data) // 3
    data[mid : mid + 64] = bytes(
        64
    )  # damage the stored data (its CRC no longer matches), keep the zip directory
    bad = tmp_path / "bad.npz"
    bad.write_bytes(bytes(data))
    _expect_input_error(load_grid, bad)


def test_load_grid_refuses_svox2_and_foreign_files(tmp_path):
    ckpt = tmp_path / "ckpt.npz"
    export_svox2(ckpt, make_grid())
    _expect_input_error(load_grid, ckpt, "svox2", "import_svox2")
    other = tmp_path / "other.npz"
    np.savez(other, weights=np.zeros(3))
    _expect_input_error(load_grid, other, "format")
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, format=np.array("something-else"), version=np.array(1))
    _expect_input_error(load_grid, wrong, "something-else")


def _rewrite(src, dst, **changes):
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    with open(dst, "wb") as f:
        np.savez(f, **arrays)
    return dst


def test_load_grid_checks_keys_version_and_shapes(tmp_path):
    good = tmp_path / "good.npz"
    grid = make_grid()
    save_grid(good, grid)
    m = grid.num_voxels
    _expect_input_error(load_grid, _rewrite(good, tmp_path / "nokey.npz", sh=None), "missing", "sh")
    _expect_input_error(load_grid, _rewrite(good, tmp_path / "newer.npz", version=np.array(3)), "newer")
    rows = np.arange(m, dtype=np.int32)
    rows[0] = m
    _expect_input_error(
        load_grid, _rewrite(good, tmp_path / "links.npz", **{"links/rows": rows}), "links", str(m)
    )
    sh5 = np.zeros((m, 15), np.float32)
    _expect_input_error(load_grid, _rewrite(good, tmp_path / "sh.npz", sh=sh5), "15 columns")
    short = np.zeros(m - 1, np.float32)
    _expect_input_error(load_grid, _rewrite(good, tmp_path / "rows.npz", density=short), "rows")
    flat = np.array([4, 5], np.int64)
    _expect_input_error(
        load_grid, _rewrite(good, tmp_path / "flat.npz", **{"links/shape": flat}), "links/shape"
    )
    bad_r = np.array([1.0, 0.0, 1.0])
    _expect_input_error(load_grid, _rewrite(good, tmp_path / "radius.npz", radius=bad_r), "radius")
    bad_meta = np.array("{not json")
    _expect_input_error(load_grid, _rewrite(good, tmp_path / "meta.npz", meta_json=bad_meta), "JSON")


def test_the_link_grid_is_stored_as_its_occupied_cells(tmp_path):
    """No dense `links` entry: its shape, the occupied cells in order and their rows, which rebuild it."""
    grid = make_grid(seed=5)
    path = save_grid(tmp_path / "grid.npz", grid)
    dense = grid.links[0].numpy()
    with np.load(path, allow_pickle=False) as z:
        assert "links" not in z.files
        assert z["links/shape"].tolist() == list(dense.shape)
        assert np.array_equal(z["links/cells"], np.flatnonzero(dense >= 0))
        assert np.array_equal(z["links/rows"], dense[dense >= 0]) and z["links/rows"].dtype == np.int32


def test_a_link_grid_larger_than_free_memory_is_refused_before_it_is_made(tmp_path, monkeypatch):
    from hdrplenoxels.core import npy_files

    keep = torch.zeros((20, 20, 20), dtype=torch.bool)
    keep[:2, :2, :2] = True  # 8 voxels: every stored array is small, the dense grid 32 000 bytes
    grid = SparseGrid.from_dense(
        torch.ones(keep.shape), torch.ones((*keep.shape, 3)), (0, 0, 0), (1, 1, 1), keep
    )
    good = save_grid(tmp_path / "good.npz", grid)
    monkeypatch.setattr(npy_files, "available_memory_bytes", lambda: 20_000)
    _expect_input_error(load_grid, good, "link grid [20, 20, 20] needs 31.2 KiB of memory")


def test_a_version_1_file_with_a_dense_link_grid_still_loads(tmp_path):
    grid = make_grid(seed=6)
    good = save_grid(tmp_path / "good.npz", grid)
    v1 = dict.fromkeys(("links/shape", "links/cells", "links/rows"))
    old = _rewrite(good, tmp_path / "v1.npz", version=np.array(1), links=grid.links[0].numpy(), **v1)
    assert_grid_equal(grid, load_grid(old)[0])


def test_damaged_sparse_links_raise_input_errors(tmp_path):
    good = save_grid(tmp_path / "good.npz", make_grid(seed=7))
    with np.load(good) as z:
        cells, rows = z["links/cells"], z["links/rows"]
    cases = {
        "missing": ({"links/cells": None}, "missing"),
        "unsorted": ({"links/cells": cells[::-1].copy()}, "increasing"),
        "outside": ({"links/cells": cells + 1000}, "below 60"),
        "floats": ({"links/cells": cells.astype(np.float32)}, "integer"),
        "lengths": ({"links/rows": rows[:-1]}, "entries"),
        "negative": ({"links/rows": -rows - 1}, "negative"),
        "huge": ({"links/shape": np.array([8, 4096, 4096, 4096])}, "not the size"),
        "levels": ({"links/shape": np.array([9, 4, 5, 3])}, "not the size"),
        "thin": ({"links/shape": np.array([60, 1, 1])}, "not the size"),
        "wrapping": (
            {"links/cells": np.array([0, 2**62, -(2**62) - 1, 5]), "links/rows": rows[:4]},
            "increasing",
        ),
        "zero": ({"links/shape": np.array([4, 0, 3])}, "not the size"),
    }
    for name, (changes, words) in cases.items():
        _expect_input_error(load_grid, _rewrite(good, tmp_path / f"{name}.npz", **changes), "links", words)


def test_svox2_round_trip_rounds_sh_to_float16(tmp_path):
    grid = make_grid(seed=3)
    path = tmp_path / "ckpt.npz"
    export_svox2(path, grid)
    with np.load(path, allow_pickle=False) as z:
        assert z["radius"].dtype == np.float32 and z["radius"].shape == (3,)
        assert z["center"].dtype == np.float32
        assert z["links"].dtype == np.int32 and z["links"].shape == grid.reso
        assert z["density_data"].dtype == np.float32 and z["density_data"].shape == (grid.num_voxels, 1)
        assert z["sh_data"].dtype == np.float16 and z["sh_data"].shape == (grid.num_voxels, 27)
        assert int(z["basis_type"]) == 1
    back = import_svox2(path)
    assert torch.equal(back.links, grid.links)
    assert torch.equal(back.density, grid.density)
    assert back.sh.dtype == torch.float32
    assert torch.equal(back.sh, grid.sh.half().float())
    assert back.center == pytest.approx(grid.center, rel=1e-6)
    assert back.radius == pytest.approx(grid.radius, rel=1e-6)


def test_svox2_import_normalises_negative_links_and_warns_on_extras(tmp_path):
    grid = make_grid(seed=4, basis_dim=4)
    links = grid.links[0].numpy().copy()  # svox2's links: one box
    empty = links < 0
    links[empty] = -2 - np.arange(int(empty.sum()))  # accel_dist_prop writes values <= -2
    path = tmp_path / "ckpt.npz"
    np.savez(
        path,
        radius=np.array(grid.radius, np.float32),
        center=np.array(grid.center, np.float32),
        links=links,
        density_data=grid.density.numpy()[:, None],
        sh_data=grid.sh.numpy().astype(np.float16),
        basis_type=np.array(1),
        background_data=np.zeros((2, 3, 4), np.float32),
        background_links=np.zeros((2, 3), np.int32),
    )
    with pytest.warns(UserWarning, match="background_data"):
        back = import_svox2(path)
    assert torch.equal(back.links, grid.links)
    assert int(back.links.min()) == -1
    assert back.basis_dim == 4


def test_svox2_import_refuses_ours_and_other_bases(tmp_path):
    ours = tmp_path / "grid.npz"
    save_grid(ours, make_grid())
    _expect_input_error(import_svox2, ours, "hdrplenoxels grid", "load_grid")
    ckpt = tmp_path / "ckpt.npz"
    export_svox2(ckpt, make_grid())
    mlp = _rewrite(ckpt, tmp_path / "mlp.npz", basis_type=np.array(255))
    _expect_input_error(import_svox2, mlp, "basis_type 255", "MLP")
    tex = _rewrite(ckpt, tmp_path / "tex.npz", basis_type=None, basis_data=np.zeros((4, 4, 4, 9), np.float32))
    _expect_input_error(import_svox2, tex, "basis_type 4")
    nosh = _rewrite(ckpt, tmp_path / "nosh.npz", sh_data=None)
    _expect_input_error(import_svox2, nosh, "missing", "sh_data")
    legacy = _rewrite(
        ckpt, tmp_path / "legacy.npz", sh_data=None, density_data=None, data=np.zeros((3, 28), np.float32)
    )
    _expect_input_error(import_svox2, legacy, "links")  # links point past the 3 rows


def test_svox2_import_legacy_data_layout_and_defaults(tmp_path):
    grid = make_grid(seed=5)
    data = np.concatenate([grid.density.numpy()[:, None], grid.sh.numpy()], axis=1)
    path = tmp_path / "old.npz"
    np.savez(path, links=grid.links[0].numpy(), data=data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = import_svox2(path)
    assert torch.equal(back.density, grid.density) and torch.equal(back.sh, grid.sh)
    assert back.center == (0.0, 0.0, 0.0) and back.radius == (1.0, 1.0, 1.0)


def test_export_warns_on_float16_overflow(tmp_path):
    grid = make_grid()
    grid.sh[0, 0] = 1e6
    with pytest.warns(UserWarning, match="float16"):
        export_svox2(tmp_path / "ckpt.npz", grid)


def test_npz_entries_are_stored_as_they_are_and_numpy_reads_them(tmp_path):
    """No entry is deflated (with sparse links nothing left repays it), and the file is a plain `.npz`."""
    import zipfile

    cells = np.arange(0, 3000, 3, dtype=np.int32)
    values = np.random.default_rng(0).random(1000).astype(np.float32)
    path = tmp_path / "grid.npz"
    grid_io.write_npz(path, {"links/cells": cells, "values": values})
    with zipfile.ZipFile(path) as zf:
        assert {info.compress_type for info in zf.infolist()} == {zipfile.ZIP_STORED}
    with np.load(path, allow_pickle=False) as z:
        assert np.array_equal(z["links/cells"], cells) and np.array_equal(z["values"], values)
