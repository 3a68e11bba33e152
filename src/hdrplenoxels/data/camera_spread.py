"""How much a capture's camera settings vary between its photos, measured from the photos themselves: the
spread of their EXIF exposures, and the exposure and white balance by which overlapping views disagree on
the same surface. It decides whether `train` learns a tone per photo by default (`train.tone_choice`).

The pixels are compared where SIFT finds the same point in two views (brightness-invariant features, so
a point matches across exposures): each pair of neighbouring views gives the median log2 ratio of their
colours over the matched points, per channel, and a least-squares fit of one gain per view and channel to
those ratios gives each view's exposure (the channels' mean) and white balance (each channel less the
mean). One fixed camera leaves the gains equal up to noise and view-dependent shading; varying settings
spread them by what the settings changed. Only the views given (a run's training views) are read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdrplenoxels.data.scene import SceneData

MAX_VIEWS = 60  # at most this many views are compared (spread evenly): enough to see a spread
NEIGHBOURS = 4  # each view is compared with this many others, the nearest in position and direction
MAX_SIDE = 640  # views are compared at most this large on their long side
MIN_MATCHES = 10  # a pair with fewer matched points in range says nothing
CODE_RANGE = (12, 243)  # 8-bit codes compared: neither near black nor near clipping, in every channel
RATIO = 0.8  # Lowe's ratio test on the descriptors' distances
SPREAD_PERCENTILES = (10, 90)  # a spread is the range between these percentiles of the views' gains


@dataclass
class CameraSpread:
    """Stops by which the photos' settings vary (None: not measured)."""

    exif_stops: float | None  # the range of the views' EXIF exposures (None: not every view has one)
    exposure_stops: float | None  # the spread of the views' exposure from their pixels (None: too few pairs)
    white_balance_stops: float | None  # the largest spread of one channel's gain over the exposure's
    pairs: int  # pairs of views whose matched points measured the pixels' spread
    compared: int = 0  # pairs of neighbouring views compared

    def to_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def camera_spread(scene: SceneData, views: list[int], pixels: bool = True) -> CameraSpread:
    """The spread of `views`' settings (module docstring); `pixels`: also from the pixels (False: EXIF
    only, as when EXIF alone already decides)."""
    exif = _exif_stops(scene, views)
    if not pixels:
        return CameraSpread(exif, None, None, 0)
    gains, pairs, compared = _view_gains(scene, _spread_evenly(views, MAX_VIEWS))
    if gains is None:
        return CameraSpread(exif, None, None, pairs, compared)
    lo, hi = SPREAD_PERCENTILES
    luminance = gains.mean(1)
    exposure = float(np.percentile(luminance, hi) - np.percentile(luminance, lo))
    chroma = gains - luminance[:, None]
    balance = float((np.percentile(chroma, hi, axis=0) - np.percentile(chroma, lo, axis=0)).max())
    return CameraSpread(exif, exposure, balance, pairs, compared)


def exif_evs(scene: SceneData) -> np.ndarray | None:
    """Every view's EXIF exposure in stops (`process` records them), None unless every view has one."""
    evs = scene.extras.get("exposure_init_ev")
    if evs is None or any(v is None or not np.isfinite(v) for v in evs):
        return None
    return np.asarray(evs, dtype=np.float64)


def _exif_stops(scene: SceneData, views: list[int]) -> float | None:
    """max - min of the views' EXIF exposures in stops, None unless every view has one."""
    evs = exif_evs(scene)
    return None if evs is None else float(evs[views].max() - evs[views].min())


def _spread_evenly(views: list[int], n: int) -> list[int]:
    if len(views) <= n:
        return list(views)
    return [views[int(k)] for k in np.linspace(0, len(views) - 1, n).round()]


def _neighbour_pairs(scene: SceneData, views: list[int]) -> list[tuple[int, int]]:
    """Each view with its `NEIGHBOURS` nearest others (positions over the typical spacing, plus how far
    their directions turn), as (a, b) index pairs into `views`, each pair once."""
    c2w = scene.cameras.c2w[views]
    centres, ahead = c2w[:, :3, 3], c2w[:, :3, 2]
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(distance, np.inf)
    spacing = max(float(np.median(distance.min(1))), 1e-9)
    score = distance / spacing + 4.0 * (1.0 - ahead @ ahead.T)
    pairs = set()
    for a in range(len(views)):
        for b in np.argsort(score[a])[:NEIGHBOURS]:
            if np.isfinite(score[a, b]):
                pairs.add((min(a, int(b)), max(a, int(b))))
    return sorted(pairs)


def _features(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SIFT of one view at most `MAX_SIDE` large: (keypoints (N, 2) x, y; descriptors (N, 128) unit
    length; the view's colours (H, W, 3) at that size, float)."""
    from PIL import Image

    img = Image.fromarray(image)
    factor = int(np.ceil(max(img.size) / MAX_SIDE))
    if factor > 1:
        img = img.reduce(factor)
    rgb = np.asarray(img, dtype=np.float32)
    grey = np.ascontiguousarray(
        (rgb @ np.float32([0.299, 0.587, 0.114])).round().clip(0, 255).astype(np.uint8)
    )
    keypoints, descriptors = _extractor().extract_from_uint8_array(grey)
    xy = np.array([(k.x, k.y) for k in keypoints], dtype=np.float32).reshape(-1, 2)
    d = descriptors.data.astype(np.float32)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    return xy, d, rgb


_EXTRACTOR = None


def _extractor():
    """One CPU SIFT extractor for the process (making one loads its options and logs a line)."""
    global _EXTRACTOR
    if _EXTRACTOR is None:
        import pycolmap

        pycolmap.logging.minloglevel = 2
        _EXTRACTOR = pycolmap.FeatureExtractor.create(
            pycolmap.FeatureExtractionOptions(), pycolmap.Device.cpu
        )
    return _EXTRACTOR


def _matches(da: np.ndarray, db: np.ndarray) -> np.ndarray:
    """(M, 2) indices of mutual nearest neighbours that pass the ratio test."""
    if len(da) < 2 or len(db) < 2:
        return np.zeros((0, 2), dtype=int)
    distance = np.sqrt(np.maximum(2.0 - 2.0 * da @ db.T, 0.0))
    nearest = np.argmin(distance, 1)
    two = np.partition(distance, 1, axis=1)[:, :2]
    passes = two[:, 0] < RATIO * two[:, 1]
    back = np.argmin(distance, 0)
    a = np.nonzero(passes & (back[nearest] == np.arange(len(da))))[0]
    return np.stack([a, nearest[a]], 1)


def _largest_linked(pairs: list[tuple[int, int]]) -> set[int]:
    """The largest set of views that `pairs` link into one (a connected component)."""
    parent: dict[int, int] = {}

    def root(v: int) -> int:
        while parent.setdefault(v, v) != v:
            v = parent[v]
        return v

    for a, b in pairs:
        parent[root(a)] = root(b)
    groups: dict[int, set[int]] = {}
    for v in list(parent):
        groups.setdefault(root(v), set()).add(v)
    return max(groups.values(), key=len, default=set())


def _colours(rgb: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The mean colour of the 3 x 3 pixels around each point (N, 3)."""
    h, w = rgb.shape[:2]
    x = np.clip(np.round(xy[:, 0]).astype(int), 1, w - 2)
    y = np.clip(np.round(xy[:, 1]).astype(int), 1, h - 2)
    patches = [rgb[y + dy, x + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    return np.mean(patches, axis=0)


def _view_gains(scene: SceneData, views: list[int]) -> tuple[np.ndarray | None, int, int]:
    """Each view's log2 gain per channel (V, 3), mean zero over the views, from its neighbours' matched
    points, over the largest set of views the measured pairs link (views in two unlinked sets have no
    common scale); None when that set holds fewer than half the views: too few to stand for the capture.
    And the number of pairs that measured anything, of those compared."""
    pairs = _neighbour_pairs(scene, views)
    features = {}
    rows, ratios = [], []
    lo, hi = CODE_RANGE
    for a, b in pairs:
        for v in (a, b):
            if v not in features:
                features[v] = _features(scene.images[views[v]])
        (xa, da, ra), (xb, db, rb) = features[a], features[b]
        m = _matches(da, db)
        if len(m) == 0:
            continue
        ca, cb = _colours(ra, xa[m[:, 0]]), _colours(rb, xb[m[:, 1]])
        usable = ((ca > lo) & (ca < hi) & (cb > lo) & (cb < hi)).all(1)
        if usable.sum() < MIN_MATCHES:
            continue
        rows.append((a, b))
        ratios.append(np.median(np.log2(ca[usable]) - np.log2(cb[usable]), axis=0))
    linked = _largest_linked(rows)
    if len(linked) < len(views) / 2:
        return None, len(rows), len(pairs)
    kept = [r for r, (a, b) in enumerate(rows) if a in linked]
    index = {v: k for k, v in enumerate(sorted(linked))}
    system = np.zeros((len(kept) + 1, len(index)))
    for r, k in enumerate(kept):
        a, b = rows[k]
        system[r, index[a]], system[r, index[b]] = 1.0, -1.0
    system[-1] = 1.0  # the gauge: gains of mean zero
    target = np.vstack([np.array([ratios[k] for k in kept]), np.zeros((1, 3))])
    gains = np.linalg.lstsq(system, target, rcond=None)[0]
    return gains, len(rows), len(pairs)
