"""Grid files: our native `.npz` format and the Plenoxels (svox2) `ckpt.npz` layout.

Native format (version 2), written atomically by `write_npz` and read with `allow_pickle=False` (a grid
file can never execute code):

- `format` = "hdrplenoxels-grid" and `version` = 2 (0-d arrays),
- the link grid, (Rx,Ry,Rz) or (levels,Rx,Ry,Rz) for a cascade of more than one level, stored sparsely:
  `links/shape` int64 (its 3 or 4 sizes), `links/cells` (K,) int32 or int64, the flat (C-order) indices of
  its occupied cells, strictly increasing, and `links/rows` (K,) int32, the row each of them holds; every
  other cell is empty (-1). Version 1 stored the dense `links` array instead (still read): at a cascade's
  size deflating it cost seconds a save (JOURNAL.md, "Checkpoint writes").
- `density` (M,) float32, `sh` (M, 3*basis_dim) float32,
- `center`, `radius` (3,) float64 (exact round trip of the grid's Python floats),
- `meta_json`: a JSON string as a 0-d unicode array,
- `x/<name>`: caller arrays (optimiser state and the like),
- optionally the MSI background (`grid/background.py`): `bg/density` (L,H,W) float32, `bg/color` (L,H,W,3)
  float32, `bg/center` (3,) and `bg/radius` () float64, `bg/samples_per_layer` () int64. Readers that
  predate it ignore these entries (and render the constant background instead).

svox2 layout (checked against `svox2.SparseGrid.save/load`): `radius`, `center` (3,)
float32, `links` int32, `density_data` (M,1) float32, `sh_data` (M, 3*basis_dim) float16, `basis_type`
(1 = spherical harmonics). Old svox2 files may hold a single `data` array (density first, then SH).
"""

from __future__ import annotations

import json
import os
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hdrplenoxels.core.atomic import atomic_path, ensure_space
from hdrplenoxels.core.errors import InputError
from hdrplenoxels.core.npy_files import memory_shortfall, read_npz
from hdrplenoxels.geometry.sh import VALID_BASIS_DIMS
from hdrplenoxels.grid.background import MSIBackground
from hdrplenoxels.grid.sparse_grid import MAX_LEVELS, SparseGrid

FORMAT = "hdrplenoxels-grid"
VERSION = 2
LINKS_PREFIX = "links/"
# Cells of a link grid a file may ask for: far beyond any grid trained here, yet a damaged size is refused
# before a dense array of it is allocated.
MAX_LINK_CELLS = 2**33
EXTRA_PREFIX = "x/"
SVOX2_BASIS_SH = 1
SVOX2_BASIS_NAMES = {1: "spherical harmonics", 4: "learned 3-D texture basis", 255: "MLP basis"}
FLOAT16_MAX = 65504.0
BACKGROUND_PREFIX = "bg/"
_BACKGROUND_KEYS = ("density", "color", "center", "radius", "samples_per_layer")
_NATIVE_KEYS = ("format", "version", "density", "sh", "center", "radius", "meta_json")
_SPARSE_LINK_KEYS = tuple(LINKS_PREFIX + k for k in ("shape", "cells", "rows"))

PathLike = str | os.PathLike


# ----------------------------------------------------------------------------- native format
def save_grid(
    path: PathLike,
    grid: SparseGrid,
    meta: dict[str, Any] | None = None,
    extra_arrays: dict[str, np.ndarray] | None = None,
    background: MSIBackground | None = None,
) -> Path:
    """Write `grid` (+ JSON `meta`, `extra_arrays` and the MSI `background`) atomically: a failed save
    keeps the old file."""
    write_npz(path, grid_arrays(grid, meta, extra_arrays, background))
    return Path(path)


def grid_arrays(
    grid: SparseGrid,
    meta: dict[str, Any] | None = None,
    extra_arrays: dict[str, np.ndarray] | None = None,
    background: MSIBackground | None = None,
) -> dict[str, np.ndarray]:
    """The entries `save_grid` writes, as host arrays: a GPU grid's are copies, a CPU grid's views of
    its tensors (valid while the grid is unchanged), so a file can be written later, on another thread."""
    try:
        meta_json = json.dumps(meta or {})
    except (TypeError, ValueError) as e:
        raise ValueError(f"grid meta must be JSON-serialisable: {e}") from e
    arrays: dict[str, np.ndarray] = {
        "format": np.array(FORMAT),
        "version": np.array(VERSION, dtype=np.int64),
        **sparse_links(grid.links if grid.levels > 1 else grid.links[0]),
        "density": _np(grid.density).astype(np.float32, copy=False),
        "sh": _np(grid.sh).astype(np.float32, copy=False),
        "center": np.asarray(grid.center, dtype=np.float64),
        "radius": np.asarray(grid.radius, dtype=np.float64),
        "meta_json": np.array(meta_json),
    }
    for name, value in (extra_arrays or {}).items():
        arr = _np(value) if isinstance(value, torch.Tensor) else np.asarray(value)
        if not name or not isinstance(name, str):
            raise ValueError(f"extra array names must be non-empty strings, got {name!r}")
        if arr.dtype.hasobject:
            raise ValueError(f"extra array {name!r} has dtype object; only numeric/string arrays are stored")
        arrays[EXTRA_PREFIX + name] = arr
    if background is not None:
        arrays.update(_background_arrays(background))
    return arrays


def load_grid(
    path: PathLike, device: torch.device | str = "cpu"
) -> tuple[SparseGrid, dict[str, Any], dict[str, np.ndarray]]:
    """Read a native grid file -> (grid, meta, extra arrays); any defect is an `InputError` naming it."""
    return grid_from_arrays(path, read_npz(path), device)


def grid_from_arrays(
    path: PathLike, z: dict[str, np.ndarray], device: torch.device | str = "cpu"
) -> tuple[SparseGrid, dict[str, Any], dict[str, np.ndarray]]:
    """`load_grid` of arrays already read from `path` (named in errors)."""
    if "format" not in z:
        if _looks_like_svox2(z):
            raise InputError(
                path, "this is a Plenoxels (svox2) checkpoint, not an hdrplenoxels grid; use `import_svox2`"
            )
        raise InputError(path, "not an hdrplenoxels grid file (no 'format' entry)")
    fmt = scalar_str(path, z, "format")
    if fmt != FORMAT:
        raise InputError(path, f"not an hdrplenoxels grid file (format {fmt!r}, expected {FORMAT!r})")
    link_keys = ("links",) if "links" in z else _SPARSE_LINK_KEYS
    missing = [k for k in (*_NATIVE_KEYS, *link_keys) if k not in z]
    if missing:
        raise InputError(path, f"grid file is missing entries: {', '.join(missing)}")
    meta = checked_meta(path, z, VERSION, "grid file")
    density = z["density"]
    if density.ndim == 2 and density.shape[1] == 1:
        density = density[:, 0]
    links = z["links"] if "links" in z else dense_links(path, z)
    names = ("density", "sh")
    grid = _build_grid(path, links, density, z["sh"], z["center"], z["radius"], names, device, cascade=True)
    return grid, meta, extra_arrays(z)


def sparse_links(links: torch.Tensor) -> dict[str, np.ndarray]:
    """The link grid as the `links/` entries: found on the grid's device, so a GPU grid sends the host
    only its occupied cells."""
    flat = links.reshape(-1)
    cells = torch.nonzero(flat >= 0).squeeze(1)
    rows = flat[cells]
    small = flat.numel() <= np.iinfo(np.int32).max
    return {
        LINKS_PREFIX + "shape": np.array(links.shape, dtype=np.int64),
        LINKS_PREFIX + "cells": _np(cells.to(torch.int32) if small else cells),
        LINKS_PREFIX + "rows": _np(rows).astype(np.int32, copy=False),
    }


def dense_links(path: PathLike, z: dict[str, np.ndarray]) -> np.ndarray:
    """The dense link grid of the `links/` entries, each checked first (named in the error)."""
    shape, cells, rows = (z[k] for k in _SPARSE_LINK_KEYS)
    if shape.ndim != 1 or shape.size not in (3, 4) or shape.dtype.kind not in "iu":
        raise InputError(
            path,
            f"'{LINKS_PREFIX}shape' must be 3 or 4 integers, got dtype {shape.dtype} shape {shape.shape}",
        )
    sizes = [int(s) for s in shape]
    levels_ok = len(sizes) == 3 or 1 <= sizes[0] <= MAX_LEVELS
    if not levels_ok or min(sizes[-3:]) < 2 or np.prod(sizes, dtype=np.float64) > MAX_LINK_CELLS:
        raise InputError(path, f"'{LINKS_PREFIX}shape' {sizes} is not the size of a link grid")
    n = int(np.prod(sizes))
    shortfall = memory_shortfall(4 * n)  # the dense int32 grid
    if shortfall:
        raise InputError(path, f"the link grid {sizes} {shortfall}")
    for key, a in ((f"{LINKS_PREFIX}cells", cells), (f"{LINKS_PREFIX}rows", rows)):
        if a.ndim != 1 or a.dtype.kind not in "iu":
            raise InputError(
                path, f"'{key}' must be a 1-D integer array, got dtype {a.dtype} shape {a.shape}"
            )
    if cells.shape != rows.shape:
        raise InputError(
            path, f"'{LINKS_PREFIX}cells' has {cells.size} entries but '{LINKS_PREFIX}rows' has {rows.size}"
        )
    # Neighbours compared, not subtracted: a difference can wrap (unsigned, or int64 far apart).
    if cells.size and (int(cells[0]) < 0 or int(cells[-1]) >= n or not np.all(cells[1:] > cells[:-1])):
        raise InputError(path, f"'{LINKS_PREFIX}cells' must be increasing cell indices below {n}")
    if rows.size and int(rows.min()) < 0:
        raise InputError(path, f"'{LINKS_PREFIX}rows' holds a negative row {int(rows.min())}")
    if rows.size and int(rows.max()) > np.iinfo(np.int32).max:
        raise InputError(path, f"'{LINKS_PREFIX}rows' holds row {int(rows.max())}, past any grid's")
    links = np.full(sizes, -1, dtype=np.int32)
    links.reshape(-1)[cells] = rows
    return links


def extra_arrays(z: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The `x/` entries of a native file (a grid's or a NeRF's), by their names without the prefix."""
    return {k.removeprefix(EXTRA_PREFIX): v for k, v in z.items() if k.startswith(EXTRA_PREFIX)}


def load_background(path: PathLike, device: torch.device | str = "cpu") -> MSIBackground | None:
    """The MSI background saved with a native grid file, or None when it has none."""
    return background_from_arrays(path, read_npz(path), device)


def background_from_arrays(
    path: PathLike, z: dict[str, np.ndarray], device: torch.device | str = "cpu"
) -> MSIBackground | None:
    """`load_background` of arrays already read from `path` (named in errors)."""
    present = [k for k in _BACKGROUND_KEYS if BACKGROUND_PREFIX + k in z]
    if not present:
        return None
    if len(present) != len(_BACKGROUND_KEYS):
        missing = sorted(set(_BACKGROUND_KEYS) - set(present))
        raise InputError(
            path, f"the background is missing entries: {', '.join(BACKGROUND_PREFIX + k for k in missing)}"
        )
    b = {k: z[BACKGROUND_PREFIX + k] for k in _BACKGROUND_KEYS}
    for key in ("density", "color"):
        if b[key].dtype.kind != "f":
            raise InputError(path, f"'{BACKGROUND_PREFIX}{key}' must hold floats, got dtype {b[key].dtype}")
    radius = b["radius"]
    if radius.size != 1 or radius.dtype.kind not in "iuf":
        raise InputError(
            path, f"'{BACKGROUND_PREFIX}radius' must be a single number, got shape {radius.shape}"
        )
    try:
        return MSIBackground(
            torch.from_numpy(b["density"].astype(np.float32)).to(device),
            torch.from_numpy(b["color"].astype(np.float32)).to(device),
            _vec3(path, b["center"], BACKGROUND_PREFIX + "center", positive=False),
            float(radius.reshape(())),
            _scalar_int(path, z, BACKGROUND_PREFIX + "samples_per_layer"),
        )
    except ValueError as e:  # shapes or values MSIBackground rejects
        raise InputError(path, f"invalid background: {e}") from e


def _background_arrays(bg: MSIBackground) -> dict[str, np.ndarray]:
    return {
        BACKGROUND_PREFIX + "density": _np(bg.density).astype(np.float32, copy=False),
        BACKGROUND_PREFIX + "color": _np(bg.color).astype(np.float32, copy=False),
        BACKGROUND_PREFIX + "center": np.asarray(bg.center, dtype=np.float64),
        BACKGROUND_PREFIX + "radius": np.array(bg.radius, dtype=np.float64),
        BACKGROUND_PREFIX + "samples_per_layer": np.array(bg.samples_per_layer, dtype=np.int64),
    }


# ----------------------------------------------------------------------------- svox2
def import_svox2(path: PathLike, device: torch.device | str = "cpu") -> SparseGrid:
    """Read a Plenoxels (svox2) `ckpt.npz`; SH stored as float16 become float32, links < 0 become -1."""
    z = read_npz(path)
    if "format" in z:
        raise InputError(
            path, "this is an hdrplenoxels grid file, not a Plenoxels (svox2) checkpoint; use `load_grid`"
        )
    if "basis_type" in z:
        basis_type = _scalar_int(path, z, "basis_type")
    elif "basis_data" in z:  # svox2 files from before `basis_type` was stored: basis_data => learned basis
        basis_type = 4
    else:
        basis_type = SVOX2_BASIS_SH
    if basis_type != SVOX2_BASIS_SH:
        name = SVOX2_BASIS_NAMES.get(basis_type, "unknown basis")
        raise InputError(
            path, f"svox2 basis_type {basis_type} ({name}) is not supported; only spherical harmonics (1) is"
        )
    ignored = sorted(k for k in z if k.startswith(("background_", "basis_data", "basis_mlp")))
    if ignored:
        warnings.warn(f"{path}: ignoring svox2 entries {', '.join(ignored)}", UserWarning, stacklevel=2)

    if "density_data" in z or "sh_data" in z:
        missing = [k for k in ("links", "density_data", "sh_data") if k not in z]
        if missing:
            raise InputError(path, f"svox2 checkpoint is missing entries: {', '.join(missing)}")
        density, sh, names = z["density_data"], z["sh_data"], ("density_data", "sh_data")
    elif "data" in z and "links" in z:  # oldest svox2 layout: data = [density | sh]
        data = z["data"]
        if data.ndim != 2 or data.shape[1] < 2:
            raise InputError(path, f"svox2 'data' must be 2-D (M, 1 + 3*basis_dim), got {data.shape}")
        density, sh, names = data[:, :1], data[:, 1:], ("data[:, :1]", "data[:, 1:]")
    else:
        raise InputError(path, "not a Plenoxels (svox2) checkpoint (needs links, density_data and sh_data)")
    if density.ndim == 2 and density.shape[1] == 1:
        density = density[:, 0]
    center = z["center"] if "center" in z else np.zeros(3)
    radius = z["radius"] if "radius" in z else np.ones(3)
    return _build_grid(path, z["links"], density, sh, center, radius, names, device)


def export_svox2(path: PathLike, grid: SparseGrid) -> Path:
    """Write `grid` as a svox2 `ckpt.npz` (SH rounded to float16 as svox2 does), atomically. svox2 has
    one box: a cascade's finest level is written (its voxels' rows renumbered), the coarser levels are
    not."""
    if grid.levels > 1:
        grid = finest_level(grid)
    sh = _np(grid.sh).astype(np.float32, copy=False)
    if sh.size and np.abs(sh).max() > FLOAT16_MAX:
        warnings.warn(
            f"{path}: SH values beyond ±{FLOAT16_MAX:g} become inf in the float16 svox2 format",
            UserWarning,
            stacklevel=2,
        )
    with np.errstate(over="ignore"):  # already warned above
        sh16 = sh.astype(np.float16)
    arrays = {
        "radius": np.asarray(grid.radius, dtype=np.float32),
        "center": np.asarray(grid.center, dtype=np.float32),
        "links": _np(grid.links[0]).astype(np.int32, copy=False),
        "density_data": _np(grid.density).astype(np.float32, copy=False).reshape(-1, 1),
        "sh_data": sh16,
        "basis_type": np.array(SVOX2_BASIS_SH, dtype=np.int64),
    }
    write_npz(path, arrays)  # uncompressed, as svox2's own `save` writes by default
    return Path(path)


def finest_level(grid: SparseGrid) -> SparseGrid:
    """Level 0 of a cascade alone, as a one-box grid."""
    level0 = torch.zeros(grid.num_voxels, dtype=torch.bool, device=grid.device)
    rows = grid.links[0][grid.links[0] >= 0].long()
    level0[rows] = True
    pruned = grid.prune(level0)
    return SparseGrid(pruned.links[:1].clone(), pruned.density, pruned.sh, grid.center, grid.radius)


# ----------------------------------------------------------------------------- helpers
def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def write_npz(path: PathLike, arrays: dict[str, np.ndarray]) -> None:
    """An `.npz` of the arrays stored as they are, written to a temp file beside `path`, synced, then
    renamed into place; a file that can't fit is refused before the old one's folder is touched.

    Nothing is deflated: with the link grid stored sparsely, what is left (floats, increasing indices)
    shrinks little, and deflating it took longer than writing it (JOURNAL.md, "Checkpoint
    writes").
    """
    arrays = {name: np.asanyarray(value) for name, value in arrays.items()}
    ensure_space(path, sum(a.nbytes for a in arrays.values()))
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, value in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                with zf.open(info, "w", force_zip64=True) as entry:
                    np.lib.format.write_array(entry, value, allow_pickle=False)
        f.flush()
        os.fsync(f.fileno())


def checked_meta(path: PathLike, z: dict[str, np.ndarray], supported: int, what: str) -> dict[str, Any]:
    """The JSON `meta_json` of a native file whose `version` entry this code reads (<= `supported`)."""
    version = _scalar_int(path, z, "version")
    if version > supported:
        raise InputError(
            path, f"{what} format version {version} is newer than this hdrplenoxels supports ({supported})"
        )
    if version < 1:
        raise InputError(path, f"invalid {what} format version {version}")
    try:
        meta = json.loads(scalar_str(path, z, "meta_json"))
    except json.JSONDecodeError as e:
        raise InputError(path, f"'meta_json' is not valid JSON ({e})") from e
    if not isinstance(meta, dict):
        raise InputError(path, "'meta_json' must hold a JSON object")
    return meta


def _looks_like_svox2(z: dict[str, np.ndarray]) -> bool:
    return "links" in z and ("density_data" in z or "sh_data" in z or "data" in z)


def scalar_str(path: PathLike, z: dict[str, np.ndarray], key: str) -> str:
    a = z[key]
    if a.shape != () or a.dtype.kind not in "US":
        raise InputError(path, f"entry {key!r} must be a single string")
    v = a.item()
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _scalar_int(path: PathLike, z: dict[str, np.ndarray], key: str) -> int:
    a = z[key]
    if a.size != 1 or a.dtype.kind not in "iu":
        raise InputError(path, f"entry {key!r} must be a single integer, got dtype {a.dtype} shape {a.shape}")
    return int(a.reshape(()))


def _vec3(path: PathLike, a: np.ndarray, key: str, positive: bool) -> tuple[float, float, float]:
    a = np.asarray(a)
    if a.size == 1 and a.dtype.kind in "iuf":  # svox2 accepts a scalar radius
        a = np.full(3, a.reshape(()))
    if a.shape != (3,) or a.dtype.kind not in "iuf" or not np.all(np.isfinite(a)):
        raise InputError(path, f"entry {key!r} must be 3 finite numbers, got dtype {a.dtype} shape {a.shape}")
    if positive and not np.all(a > 0):
        raise InputError(path, f"entry {key!r} must be positive, got {a.tolist()}")
    return tuple(float(v) for v in a)  # type: ignore[return-value]


def _build_grid(
    path: PathLike,
    links: np.ndarray,
    density: np.ndarray,
    sh: np.ndarray,
    center: np.ndarray,
    radius: np.ndarray,
    names: tuple[str, str],
    device: torch.device | str,
    cascade: bool = False,
) -> SparseGrid:
    """Check shapes and index ranges, then build the grid (negative links normalised to -1); `cascade`:
    4-D links (levels first) are allowed."""
    dname, sname = names
    dims = "a 3-D (or, for a cascade, 4-D)" if cascade else "a 3-D"
    if links.ndim not in ((3, 4) if cascade else (3,)) or links.dtype.kind not in "iu":
        raise InputError(
            path, f"'links' must be {dims} integer array, got dtype {links.dtype} shape {links.shape}"
        )
    if min(links.shape[-3:]) < 2:
        raise InputError(path, f"'links' must have at least 2 voxels per axis, got shape {links.shape}")
    if links.ndim == 4 and not 1 <= links.shape[0] <= MAX_LEVELS:
        raise InputError(path, f"'links' has {links.shape[0]} levels; a grid has 1 to {MAX_LEVELS}")
    if density.ndim != 1 or density.dtype.kind != "f":
        raise InputError(
            path, f"{dname!r} must be (M,) or (M, 1) floats, got dtype {density.dtype} shape {density.shape}"
        )
    if sh.ndim != 2 or sh.dtype.kind != "f":
        raise InputError(path, f"{sname!r} must be a 2-D float array, got dtype {sh.dtype} shape {sh.shape}")
    if sh.shape[1] % 3 or sh.shape[1] // 3 not in VALID_BASIS_DIMS:
        dims = ", ".join(str(3 * d) for d in VALID_BASIS_DIMS)
        raise InputError(path, f"{sname!r} has {sh.shape[1]} columns; expected one of {dims} (3 x basis_dim)")
    m = density.shape[0]
    if sh.shape[0] != m:
        raise InputError(path, f"{dname!r} has {m} rows but {sname!r} has {sh.shape[0]}")
    lmax = int(links.max())
    if lmax >= m:
        raise InputError(path, f"'links' points at row {lmax} but there are only {m} voxels")
    if links.dtype != np.int32 or int(links.min()) < -1:  # a version 2 file's are as they stay: no copy
        links = np.where(links < 0, -1, links).astype(np.int32)
    grid_center = _vec3(path, center, "center", positive=False)
    grid_radius = _vec3(path, radius, "radius", positive=True)
    try:
        return SparseGrid(
            torch.from_numpy(links).to(device),
            torch.from_numpy(density.astype(np.float32)).to(device),
            torch.from_numpy(sh.astype(np.float32)).to(device),
            grid_center,
            grid_radius,
        )
    except ValueError as e:  # anything SparseGrid rejects that the checks above missed
        raise InputError(path, str(e)) from e
