"""Structure from motion with pycolmap on CPU: SIFT features, matching, incremental mapping, undistortion.

Matching is exhaustive up to `exhaustive_limit` images (every pair: most robust for small captures) and
sequential beyond (neighbours in file-name order, with quadratic overlap: what video frames and walk-
around captures need). Loop detection would need a vocabulary tree downloaded at run time, so it is off.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE")


@dataclass
class SfmConfig:
    camera_model: str = "SIMPLE_RADIAL"  # COLMAP's default for photos: one focal, one radial term
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    exhaustive_limit: int = 100
    sequential_overlap: int = 10
    single_camera: bool | None = None  # None: one shared camera when all photos have the same size
    max_image_size: int = 3200  # SIFT works on images downscaled to this longest side
    num_threads: int = -1  # all cores
    equalise: bool = True  # extract features from histogram-equalised copies (see process.photos)
    # Affine-adapted SIFT: matches across wide baselines and slanted surfaces, which bridge the views a
    # bracket's clipped +3 EV frames leave weakly linked (docs/performance.md, "Affine-adapted SIFT").
    affine_shape: bool = True
    seed: int = 0  # seeds the mapper and triangulation (matching stays multithreaded and unseeded)


def quiet_colmap() -> None:
    """Keep COLMAP's per-step log lines (glog INFO) out of the user's terminal: warnings still show."""
    import pycolmap

    pycolmap.logging.minloglevel = 1


def choose_matcher(cfg: SfmConfig, n_images: int) -> str:
    if cfg.matcher != "auto":
        return cfg.matcher
    return "exhaustive" if n_images <= cfg.exhaustive_limit else "sequential"


def extract(database: Path, images: Path, names: list[str], same_size: bool, cfg: SfmConfig) -> None:
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = cfg.num_threads
    options.max_image_size = cfg.max_image_size
    options.sift.estimate_affine_shape = cfg.affine_shape
    single = same_size if cfg.single_camera is None else cfg.single_camera
    pycolmap.extract_features(
        database,
        images,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE if single else pycolmap.CameraMode.PER_IMAGE,
        reader_options=reader,
        extraction_options=options,
        device=pycolmap.Device.cpu,
    )


def match(database: Path, matcher: str, cfg: SfmConfig) -> None:
    import pycolmap

    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = cfg.num_threads
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=options, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.sequential_overlap
        pairing.quadratic_overlap = True
        pycolmap.match_sequential(
            database,
            matching_options=options,
            pairing_options=pairing,
            device=pycolmap.Device.cpu,
        )


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
