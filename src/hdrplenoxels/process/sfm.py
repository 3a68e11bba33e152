"""Structure from motion with pycolmap on CPU: SIFT features, matching, incremental mapping, undistortion.

Matching is exhaustive up to `exhaustive_limit` images (every pair: most robust for photos in any order)
and sequential beyond (neighbours in file-name order with quadratic overlap: what video frames and walks
need). COLMAP's loop detection needs a vocabulary tree, which would have to be downloaded at run time, so
sequential matching closes loops itself: every pair among `loop_images` images spread evenly over the
sequence is matched as well. Measurements: docs/performance.md, "Registration of real captures".
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
FEATURES = ("auto", "as-taken", "equalised")


@dataclass
class SfmConfig:
    camera_model: str = "SIMPLE_RADIAL"  # COLMAP's default for photos: one focal, one radial term
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    exhaustive_limit: int = 100
    sequential_overlap: int = 10
    loop_images: int = 30  # sequential matching also matches every pair among this many spread images
    single_camera: bool | None = None  # None: one camera per photo size; False: a camera per photo
    max_image_size: int = 3200  # SIFT works on images downscaled to this longest side
    # ... and on a video's frames to this one: as many frames registered in less time
    # (docs/performance.md, "Video input").
    video_image_size: int = 1280
    num_threads: int = -1  # all cores
    # Which copies features come from: "auto" tries the photos as taken and, when they register fewer than
    # `retry_below` of the photos, histogram-equalised copies too, keeping the better model
    # (process.registration).
    features: Literal["auto", "as-taken", "equalised"] = "auto"
    retry_below: float = 0.95
    # Affine-adapted SIFT: matches across wide baselines and slanted surfaces, which bridge the views a
    # bracket's clipped +3 EV frames leave weakly linked (docs/performance.md, "Registration of real
    # captures").
    affine_shape: bool = True
    seed: int = 0  # seeds the matches' geometric verification (RANSAC), the mapper and triangulation


def quiet_colmap() -> None:
    """Keep COLMAP's log lines out of the user's terminal, errors excepted: its per-step INFO lines, and
    its warnings, hundreds of solver lines when a video's frames start small models that are dropped."""
    import pycolmap

    pycolmap.logging.minloglevel = 2


def choose_matcher(cfg: SfmConfig, n_images: int, sequence: bool) -> str:
    """`sequence`: the images are frames in time order (a video), whose neighbours are what to match."""
    if cfg.matcher != "auto":
        return cfg.matcher
    return "exhaustive" if n_images <= cfg.exhaustive_limit and not sequence else "sequential"


def extract(database: Path, images: Path, groups: Sequence[Sequence[str]], cfg: SfmConfig) -> None:
    """SIFT features of every named image; the images of each group share one camera (unless
    `cfg.single_camera` is False: then every image has its own)."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = cfg.num_threads
    options.max_image_size = cfg.max_image_size
    options.sift.estimate_affine_shape = cfg.affine_shape
    shared = cfg.single_camera is not False
    for names in groups:  # each call makes the group's camera (COLMAP's single-camera mode is per call)
        pycolmap.extract_features(
            database,
            images,
            image_names=list(names),
            camera_mode=pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.PER_IMAGE,
            reader_options=reader,
            extraction_options=options,
            device=pycolmap.Device.cpu,
        )


def loop_pairs(names: Sequence[str], n_spread: int) -> list[tuple[str, str]]:
    """Every pair among `n_spread` images spread evenly over the sequence (in file-name order)."""
    ordered = sorted(names)
    step = max(1, -(-len(ordered) // max(n_spread, 1)))
    spread = ordered[::step]
    return [(a, b) for i, a in enumerate(spread) for b in spread[i + 1 :]]


def match(database: Path, matcher: str, cfg: SfmConfig, names: Sequence[str]) -> None:
    """Match and verify image pairs; the same features and seed give the same verified pairs."""
    import pycolmap

    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = cfg.num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = cfg.seed
    common = {
        "matching_options": options,
        "verification_options": verification,
        "device": pycolmap.Device.cpu,
    }
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, **common)
        return
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = cfg.sequential_overlap
    pairing.quadratic_overlap = True
    pycolmap.match_sequential(database, pairing_options=pairing, **common)
    pairs = loop_pairs(names, cfg.loop_images)
    if pairs:  # pairs the sequential pass matched already are skipped
        pair_file = database.with_name("loop_pairs.txt")
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        imported = pycolmap.ImportedPairingOptions()
        imported.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(database, pairing_options=imported, **common)


def reconstruct(database: Path, images: Path, out: Path, cfg: SfmConfig, on_image: Callable[[], None]):
    """The largest model incremental mapping finds (by registered images), and its folder."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = cfg.num_threads
    options.random_seed = cfg.seed
    options.mapper.random_seed = cfg.seed
    options.triangulation.random_seed = cfg.seed
    out.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(database, images, out, options, next_image_callback=on_image)
    if not models:
        return None, None
    index, rec = max(models.items(), key=lambda kv: kv[1].num_reg_images())
    return rec, out / str(index)


def undistort(model_dir: Path, images: Path, out: Path, cfg: SfmConfig) -> None:
    """COLMAP's image undistorter: pinhole images in `out/images`, the pinhole model in `out/sparse`."""
    import pycolmap

    pycolmap.undistort_images(out, model_dir, images, num_threads=cfg.num_threads)
