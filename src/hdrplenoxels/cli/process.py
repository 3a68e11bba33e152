"""`process`: photos or a video -> dataset."""

from __future__ import annotations

import time

import click

from hdrplenoxels.cli.common import choice_option
from hdrplenoxels.process.sfm import CAMERA_MODELS, MAPPERS
from hdrplenoxels.process.video import DEFAULT_FRAMES


@click.command()
@click.argument("source")
@click.argument("out", type=click.Path(file_okay=False))
@choice_option(
    "--camera-model",
    choices=CAMERA_MODELS,
    default="SIMPLE_RADIAL",
    help="Lens model COLMAP fits (images are undistorted to pinhole afterwards).",
)
@choice_option(
    "--matcher",
    choices=["auto", "exhaustive", "sequential"],
    default="auto",
    help="auto: exhaustive up to 100 photos; sequential (file-name order, loops closed by matching "
    "every pair of 30 spread images) beyond, and for a video.",
)
@choice_option(
    "--mapper",
    choices=MAPPERS,
    default="auto",
    help="auto: global (GLOMAP) and incremental (COLMAP) mapping, compared camera by camera; where they "
    "disagree, a global mapping of the strongly matched pairs decides.",
)
@click.option(
    "--exif-focal",
    "focal",
    flag_value="exif",
    help="Hold the focal length the photos' EXIF gives fixed. Default: also fit it, and keep the fit only "
    "where it explains the photos clearly better (a walk straight ahead cannot fix its focal; a phone's EXIF "
    "can be wrong for a cropped frame). Photos without an EXIF focal are always self-calibrated.",
)
@click.option(
    "--fit-focal",
    "--free-focal",
    "focal",
    flag_value="fit",
    help="Fit the focal length, starting from the EXIF one, and keep the fit whatever it explains.",
)
@click.option(
    "--equalise/--no-equalise",
    default=None,
    help="Extract features from histogram-equalised copies, or from the photos as taken. Default: the "
    "photos as taken, and equalised copies as well if that leaves over 5 % out (the better model is kept).",
)
@click.option(
    "--frames",
    type=click.IntRange(min=3),
    default=DEFAULT_FRAMES,
    show_default=True,
    help="For a video: how many frames to keep, the sharpest of each stretch of the clip.",
)
@click.option("--threads", type=int, default=-1, show_default=True, help="CPU threads (-1: all cores).")
@click.option("--overwrite", is_flag=True, help="Replace OUT once the new result is complete.")
def process(source, out, camera_model, matcher, mapper, focal, equalise, frames, threads, overwrite):
    """Calibrate SOURCE, a folder of photos or a video (.mp4, .mov, .m4v), with COLMAP (pycolmap, CPU)
    into a dataset in OUT for `train`."""
    from hdrplenoxels.process import process_photos
    from hdrplenoxels.process.sfm import SfmConfig

    features = "auto" if equalise is None else ("equalised" if equalise else "as-taken")
    cfg = SfmConfig(
        camera_model=camera_model,
        matcher=matcher,
        features=features,
        num_threads=threads,
        mapper=mapper,
        focal=focal or "auto",
    )
    t0 = time.perf_counter()
    result = process_photos(source, out, cfg, overwrite=overwrite, log=click.echo, frames=frames)
    click.echo(
        f"registered {len(result.registered)} of {result.n_photos} photos "
        f"(features from the photos {result.features.replace('-', ' ')}, {result.mapper} mapping), "
        f"{result.n_points} points, reprojection error {result.reprojection_error_px:.2f} px, focal "
        f"{', '.join(f'{f:.0f}' for f in result.focal_px)} px ({result.focal_source}), "
        f"{time.perf_counter() - t0:.1f} s"
    )
