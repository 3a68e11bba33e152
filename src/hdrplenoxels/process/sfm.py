"""Structure from motion with pycolmap on CPU: SIFT features, matching, global or incremental mapping,
undistortion.

Matching is exhaustive up to `exhaustive_limit` images (every pair: most robust for photos in any order)
and sequential beyond (neighbours in file-name order with quadratic overlap: what video frames and walks
need). COLMAP's loop detection needs a vocabulary tree, which would have to be downloaded at run time, so
sequential matching closes loops itself: every pair among `loop_images` images spread evenly over the
sequence is matched as well.

Mapping is global (GLOMAP: rotations and positions of all photos at once) or incremental (COLMAP: photo
by photo from an initial pair); `process.registration` decides which per capture. The EXIF focal
length (COLMAP reads it: the 35 mm equivalent over the frame's diagonal, or the focal length and the
sensor's size) starts the fit, or is held fixed (`SfmConfig.focal`; where a fitted focal is kept is
decided in process.registration). The distortion term is always fitted (a phone's lens has one).
Measurements: JOURNAL.md, "Registration of real captures".
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Sequence
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
FEATURES = ("auto", "as-taken", "equalised")
MAPPERS = ("auto", "global", "incremental")
CAMERA = 0  # COLMAP's sensor type of a camera, in its database's frame_data and pose_priors
MAX_REPROJECTION_ERROR_PX = 4.0  # COLMAP's mapper drops observations past this
FOCAL_STEP = 0.1  # `adjusted_both_ways` moves a focal by at most this fraction between two adjustments
STEP_ITERATIONS = 10  # ... and adjusts the steps on the way with at most this many iterations


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
    # (JOURNAL.md, "Video input").
    video_image_size: int = 1280
    num_threads: int = -1  # all cores
    # Which copies features come from: "auto" tries the photos as taken and, when they register fewer than
    # `retry_below` of the photos, histogram-equalised copies too, keeping the better model
    # (process.registration).
    features: Literal["auto", "as-taken", "equalised"] = "auto"
    retry_below: float = 0.95
    # Affine-adapted SIFT: matches across wide baselines and slanted surfaces, which bridge the views a
    # bracket's clipped +3 EV frames leave weakly linked (JOURNAL.md, "Registration of real
    # captures").
    affine_shape: bool = True
    seed: int = 0  # seeds the matches' geometric verification (RANSAC), the mapper and triangulation
    # "auto": global and incremental mapping, compared, and a third mapping where they disagree
    # (process.registration); the other two force one.
    mapper: Literal["auto", "global", "incremental"] = "auto"
    # Where every camera has an EXIF focal: "auto" fits the focal, then adjusts the kept model again with
    # the EXIF focal held and keeps the fitted one only where it explains the photos clearly better
    # (`min_focal_gain`, process.registration); "exif" always holds it (distortion is still fitted),
    # "fit" always fits it.
    focal: Literal["auto", "exif", "fit"] = "auto"
    # `auto` keeps a fitted focal over the EXIF one only when, on the same observations, it lowers the
    # mean reprojection error by more than this fraction (JOURNAL.md, "The EXIF focal or a
    # fitted one").
    min_focal_gain: float = 0.03
    # `auto` maps each capture both ways and compares the cameras: a camera turned by more than this many
    # degrees between the two models, or moved by more than this fraction of the model's extent, means
    # one of them is wrong, and a third mapping decides (process.registration).
    max_disagreement_deg: float = 5.0
    max_disagreement_position: float = 0.3
    # The third mapping is global, from the image pairs with at least this many verified matches (COLMAP
    # takes 15): weak pairs, such as those a repeated floor pattern makes, can turn a global model.
    strict_min_matches: int = 30


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
    number_images_by_name(database)


def number_images_by_name(database: Path) -> None:
    """Renumber a database's images (and their one-image frames) in name order. COLMAP numbers images in
    the order its extraction threads finish them, and mapping visits them by id, so without this the
    same photos could map differently from run to run. Frames of several images (a rig) are left."""
    with closing(sqlite3.connect(database)) as db, db:
        rows = db.execute("SELECT image_id, name FROM images").fetchall()
        new_id = {old: new for new, (old, _) in enumerate(sorted(rows, key=lambda r: r[1]), start=1)}
        frame_of = dict(db.execute(f"SELECT data_id, frame_id FROM frame_data WHERE sensor_type = {CAMERA}"))
        frames = db.execute("SELECT COUNT(*) FROM frames").fetchone()[0]
        one_image_frames = len(frame_of) == len(set(frame_of.values())) == frames == len(rows)
        if all(o == n for o, n in new_id.items()) or not one_image_frames:
            return
        new_frame = {frame_of[old]: new for old, new in new_id.items()}
        renumbered = [  # (table, column, condition, mapping)
            ("images", "image_id", "", new_id),
            ("keypoints", "image_id", "", new_id),
            ("descriptors", "image_id", "", new_id),
            ("frame_data", "data_id", f"sensor_type = {CAMERA}", new_id),
            ("pose_priors", "corr_data_id", f"corr_sensor_type = {CAMERA}", new_id),
            ("frames", "frame_id", "", new_frame),
            ("frame_data", "frame_id", "", new_frame),
        ]
        offset = max(max(new_id), max(new_frame)) + len(rows) + 1  # moved clear of every id first
        for table, column, condition, _ in renumbered:
            where = f" WHERE {condition}" if condition else ""
            db.execute(f"UPDATE {table} SET {column} = {column} + {offset}{where}")
        for table, column, condition, mapping in renumbered:
            extra = f" AND {condition}" if condition else ""
            db.executemany(
                f"UPDATE {table} SET {column} = ? WHERE {column} = ?{extra}",
                [(new, old + offset) for old, new in mapping.items()],
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


def focal_priors(database: Path) -> list[float | None]:
    """Each camera's focal length in pixels as COLMAP read it from the photos' EXIF (None: no EXIF
    focal, so COLMAP guessed 1.2 x the longest side)."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        cams = sorted(db.read_all_cameras(), key=lambda c: c.camera_id)
        return [float(c.mean_focal_length()) if c.has_prior_focal_length else None for c in cams]
    finally:
        db.close()


def camera_poses(rec) -> dict[str, np.ndarray]:
    """Camera-to-world 4x4 of each registered image of a model, by image name (OpenCV axes)."""
    poses = {}
    for image in rec.images.values():
        if image.has_pose:
            w2c = np.eye(4)
            w2c[:3] = image.cam_from_world().matrix()
            poses[image.name] = np.linalg.inv(w2c)
    return poses


def model_focals(rec) -> list[float]:
    """The focal lengths (pixels) of a model's cameras, by camera id."""
    return [float(rec.cameras[i].mean_focal_length()) for i in sorted(rec.cameras)]


def adjusted_both_ways(rec, focals: Sequence[float], loss: str = "TRIVIAL") -> tuple[float, object, float]:
    """A model bundle-adjusted with each camera's focal free and, a copy, with it held at `focals` (by
    camera id), on the same observations: (the mean reprojection error free, the held model, its mean
    reprojection error), each observation's error capped at 4 px (`capped_error`). The held copy gets
    there in steps of at most `FOCAL_STEP`, adjusted at every step: moved tens of percent at once, some
    of its points land behind the cameras and the adjustment runs off (JOURNAL.md, "The EXIF
    focal or a fitted one"). `loss`: the adjustments' `pycolmap.LossFunctionType` (squared errors; the
    benchmark compares others). Observations the held model then puts past 4 px, as COLMAP's mapper
    filters them, are dropped from it afterwards."""
    import pycolmap

    free, held = pycolmap.Reconstruction(rec), pycolmap.Reconstruction(rec)
    for model in (free, held):
        pycolmap.ObservationManager(model).filter_observations_with_negative_depth()
    start = np.array(model_focals(held))
    ratio = np.asarray(focals, float) / start
    steps = max(1, int(np.ceil(np.abs(np.log(ratio)).max() / np.log1p(FOCAL_STEP))))
    bundle_adjust(free, False, loss)
    for k in range(1, steps + 1):  # the steps on the way only need to follow: a few iterations each
        set_focals(held, start * ratio ** (k / steps))
        bundle_adjust(held, True, loss, None if k == steps else STEP_ITERATIONS)
    errors = [capped_error(model) for model in (free, held)]
    pycolmap.ObservationManager(held).filter_all_points3D(MAX_REPROJECTION_ERROR_PX, 0.0)
    held.update_point_3d_errors()
    return errors[0], held, errors[1]


def capped_error(model, cap: float = MAX_REPROJECTION_ERROR_PX) -> float:
    """The mean over every observation of a model of its reprojection error in pixels, capped at `cap` (a
    point behind its camera counts `cap`): a point an adjustment sends astray counts as one outlier, not
    as the millions of pixels its projection lands away."""
    total, count = 0.0, 0
    for image in model.images.values():
        if not image.has_pose:
            continue
        seen = [(p.xy, p.point3D_id) for p in image.points2D if p.has_point3D()]
        if not seen:
            continue
        xy = np.array([a for a, _ in seen])
        world = np.array([model.points3D[i].xyz for _, i in seen])
        pose = image.cam_from_world().matrix()
        projected = model.cameras[image.camera_id].img_from_cam(world @ pose[:, :3].T + pose[:, 3])
        error = np.linalg.norm(np.asarray(projected) - xy, axis=1)
        total += float(np.minimum(np.nan_to_num(error, nan=cap, posinf=cap), cap).sum())
        count += len(seen)
    return total / max(count, 1)


def set_focals(model, focals: Sequence[float]) -> None:
    """Set each camera's focal length (by camera id) of `model` in place."""
    for camera_id, focal in zip(sorted(model.cameras), focals):
        camera = model.cameras[camera_id]
        params = np.array(camera.params)
        params[list(camera.focal_length_idxs())] = focal
        camera.params = params
        model.cameras[camera_id] = camera


def bundle_adjust(model, hold_focal: bool, loss: str, iterations: int | None = None) -> None:
    """Adjust every registered image's pose, the points and the cameras' distortion (and focal, unless
    `hold_focal`) of `model` in place, the gauge fixed by three points; `iterations`: at most this many
    (None: Ceres's default, 100)."""
    import pycolmap

    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length, options.refine_extra_params = not hold_focal, True
    options.print_summary = False
    options.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss)
    if iterations is not None:
        options.ceres.solver_options.max_num_iterations = iterations
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in model.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    pycolmap.create_default_ceres_bundle_adjuster(options, config, model).solve()


def _seeded(options, cfg: SfmConfig):
    """A pipeline's options with its threads and every random seed it has set from `cfg`, so that both
    mappers give the same model on every run."""
    options.num_threads = cfg.num_threads
    options.random_seed = options.mapper.random_seed = cfg.seed
    return options


def _incremental_options(cfg: SfmConfig, hold_focal: bool):
    import pycolmap

    options = _seeded(pycolmap.IncrementalPipelineOptions(), cfg)
    options.triangulation.random_seed = cfg.seed
    options.ba_refine_focal_length = options.mapper.abs_pose_refine_focal_length = not hold_focal
    return options


def _global_options(cfg: SfmConfig, hold_focal: bool):
    import pycolmap

    options = _seeded(pycolmap.GlobalPipelineOptions(), cfg)
    options.mapper.num_threads = cfg.num_threads
    options.mapper.bundle_adjustment.refine_focal_length = not hold_focal
    return options


def reconstruct(
    database: Path,
    images: Path,
    out: Path,
    cfg: SfmConfig,
    on_image: Callable[[], None],
    mapper: str = "incremental",
    hold_focal: bool = False,
    min_matches: int | None = None,
):
    """The largest model `mapper` ("global" or "incremental") finds (by registered images), and its
    folder; `hold_focal`: the cameras' focal lengths stay as in the database (distortion is fitted);
    `min_matches`: the global mapper uses only image pairs with this many verified matches (None:
    COLMAP's default)."""
    import pycolmap

    out.mkdir(parents=True, exist_ok=True)
    if mapper == "global":
        options = _global_options(cfg, hold_focal)
        if min_matches is not None:
            options.min_num_matches = min_matches
        models = pycolmap.global_mapping(database, images, out, options)
    elif mapper == "incremental":
        options = _incremental_options(cfg, hold_focal)
        models = pycolmap.incremental_mapping(database, images, out, options, next_image_callback=on_image)
    else:
        raise ValueError(f"mapper must be 'global' or 'incremental', got {mapper!r}")
    if not models:
        return None, None
    index, rec = max(models.items(), key=lambda kv: kv[1].num_reg_images())
    if mapper == "global":  # it registers all at once: the progress display catches up at the end
        for _ in range(rec.num_reg_images()):
            on_image()
    return rec, out / str(index)


def undistort(model_dir: Path, images: Path, out: Path, cfg: SfmConfig) -> None:
    """COLMAP's image undistorter: pinhole images in `out/images`, the pinhole model in `out/sparse`."""
    import pycolmap

    pycolmap.undistort_images(out, model_dir, images, num_threads=cfg.num_threads)
