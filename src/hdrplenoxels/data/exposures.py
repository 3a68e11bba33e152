"""Known exposure values per view, read from a JSON side file (optional input of the tone mapper).

Two forms are accepted:
- a `camera_truth.json` written by `hdrplenoxels synth` (`{"views": [{"file": ..., "ev": ...}, ...]}`);
- a mapping from image name (file stem) to exposure value in stops: `{"IMG_0001": -1.0, ...}`.
Only differences between views matter: a constant offset is absorbed by the reference image.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hdrplenoxels.core.errors import InputError
from hdrplenoxels.data.validate import read_json


def _by_name(path: Path, data: object) -> dict[str, float]:
    if isinstance(data, dict) and isinstance(data.get("views"), list):
        pairs = []
        for i, v in enumerate(data["views"]):
            if not isinstance(v, dict) or "ev" not in v or "file" not in v:
                raise InputError(path, f"views[{i}] needs 'file' and 'ev'")
            pairs.append((Path(str(v["file"])).stem, v["ev"]))
    elif isinstance(data, dict):
        pairs = list(data.items())
    else:
        raise InputError(path, "expected a JSON object: {name: EV} or a synth camera_truth.json")
    out = {}
    for name, ev in pairs:
        if isinstance(ev, bool) or not isinstance(ev, (int, float)) or not math.isfinite(ev):
            raise InputError(path, f"exposure of {name!r} is not a finite number: {ev!r}")
        out[Path(str(name)).stem] = float(ev)
    return out


def load_exposures(path: str | Path, names: list[str]) -> np.ndarray:
    """EV per view (N,) in the order of `names` (image names of the scene; matched by file stem)."""
    path = Path(path)
    table = _by_name(path, read_json(path, "cannot read the exposure file"))
    stems = [Path(n).stem for n in names]
    missing = [s for s in stems if s not in table]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise InputError(path, f"no exposure for {len(missing)} of the scene's {len(stems)} images: {shown}")
    return np.array([table[s] for s in stems], dtype=np.float64)
