"""`process VIDEO` on a clip made for it (JOURNAL.md, "Video input").

No phone video is shared with the project, so the clip is made, in one of two ways:
- `--synth SCENE`: `--views` views of a synthetic scene rendered along its camera path with Mitsuba (1 spp
  by default: the `gallery` scene's self-lit textures render without noise), each held for an equal share
  of the clip: a walk with real parallax between views;
- `PHOTOS`: a real capture's photos in file-name order, each resized to slightly more than the clip's
  height and held for an equal share of the clip while a crop window pans across it (frames of one photo
  share its viewpoint, so SfM gets no parallax from them).
It is encoded as H.264 with PyAV. A fifth of the frames, drawn with a fixed seed, get a horizontal motion
blur of `--blur` pixels, as from a shaking hand. Then `process CLIP OUT --frames N` runs in this process
and the script prints its wall time, how many of the chosen frames are blurred against as many evenly
spaced ones, and the median sharpness of both.

A clip already in OUT (from an earlier run with the same options) is reused.

Usage: python benchmarks/studies/video_input/video_input.py OUT
       (--synth gallery [--views 180] [--spp 1] | --photos PHOTOS)
       [--seconds 30] [--fps 30] [--size 1920x1080] [--blur 25] [--frames 150] [--sift-size PIXELS]
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterator
from pathlib import Path

import av
import numpy as np
from PIL import Image

from hdrplenoxels.process import process_photos
from hdrplenoxels.process.photos import find_photos
from hdrplenoxels.process.sfm import SfmConfig

PAN = 0.1  # photos are resized to (1 + PAN) x the clip's height; the crop pans over the extra width


def motion_blur(rgb: np.ndarray, length: int) -> np.ndarray:
    """A horizontal box blur of `length` pixels (a camera moving sideways during the exposure)."""
    padded = np.pad(rgb.astype(np.float32), ((0, 0), (length // 2, length - 1 - length // 2), (0, 0)), "edge")
    c = np.cumsum(padded, axis=1)
    c = np.concatenate([np.zeros_like(c[:, :1]), c], axis=1)
    return np.round((c[:, length:] - c[:, :-length]) / length).astype(np.uint8)


def photo_frames(photos: list[Path], n: int, size: tuple[int, int]) -> Iterator[np.ndarray]:
    """`n` frames: each photo held for an equal share while a crop window pans across it."""
    w, h = size
    current, resized = -1, None
    for j in range(n):
        p = j * len(photos) // n
        if p != current:
            with Image.open(photos[p]) as img:
                scale = h * (1 + PAN) / img.height
                new_size = (round(img.width * scale), round(h * (1 + PAN)))
                resized = np.asarray(img.convert("RGB").resize(new_size, Image.LANCZOS))
            current = p
        first = p * n // len(photos)
        share = max(1, (p + 1) * n // len(photos) - first)
        x = round((resized.shape[1] - w) * (j - first) / share)
        y = (resized.shape[0] - h) // 2
        yield resized[y : y + h, x : x + w]


def synth_frames(scene: str, views: int, n: int, size: tuple[int, int], spp: int) -> Iterator[np.ndarray]:
    """`n` frames: `views` renders along the scene's camera path, each held for an equal share."""
    from hdrplenoxels.synth.mitsuba_render import load_scene_dict, render_view
    from hdrplenoxels.synth.pipeline import CameraSettings, capture
    from hdrplenoxels.synth.scenes import SCENES

    rig = SCENES[scene].build(views, *size)
    loaded = load_scene_dict(rig.scene)
    current, frame = -1, None
    for j in range(n):
        v = j * views // n
        if v != current:
            frame = capture(render_view(loaded, rig.cameras, v, spp, seed=v), CameraSettings())
            current = v
        yield frame


def blurred_frames(n: int) -> set[int]:
    """The fifth of the clip's frames that get a motion blur (a fixed draw)."""
    return set(np.random.default_rng(0).choice(n, n // 5, replace=False).tolist())


def write_clip(
    frames: Iterator[np.ndarray], out: Path, blurred: set[int], fps: int, size: tuple[int, int], blur: int
) -> None:
    """Encode the frames, with a motion blur on those in `blurred`."""
    with av.open(str(out), "w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height = size
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "18", "preset": "veryfast"}
        for j, frame in enumerate(frames):
            if j in blurred:
                frame = motion_blur(frame, blur)
            pixels = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            container.mux(stream.encode(pixels))
        container.mux(stream.encode())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--synth", help="a synthetic scene (e.g. gallery)")
    source.add_argument("--photos", type=Path, help="a folder of real photos")
    parser.add_argument("--views", type=int, default=180)
    parser.add_argument("--spp", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--fps", type=int, default=30)
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--blur", type=int, default=25)
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--sift-size", type=int, help="SfmConfig.max_image_size (default: process's)")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    clip = args.out / "clip.mp4"
    n = int(round(args.seconds * args.fps))
    blurred = blurred_frames(n)
    if clip.exists():  # made by an earlier run with the same options
        print(f"clip: {clip} (reused)")
    else:
        if args.synth:
            frames = synth_frames(args.synth, args.views, n, size, args.spp)
        else:
            frames = photo_frames(find_photos(args.photos), n, size)
        t0 = time.perf_counter()
        write_clip(frames, clip, blurred, args.fps, size, args.blur)
        print(
            f"clip: {clip} ({clip.stat().st_size / 1e6:.1f} MB) written in {time.perf_counter() - t0:.0f} s"
        )
    cfg = SfmConfig() if args.sift_size is None else SfmConfig(max_image_size=args.sift_size)
    t0 = time.perf_counter()
    result = process_photos(clip, args.out / "data", cfg, overwrite=True, frames=args.frames)
    wall = time.perf_counter() - t0
    meta = json.loads((args.out / "data" / "transforms.json").read_text())["process"]
    chosen = sorted(int(Path(n).stem.split("_")[1]) for n in [*result.registered, *result.unregistered])
    total = meta["frames_decoded"]
    even = np.unique(np.linspace(0, total - 1, len(chosen)).round().astype(int))
    summary = {
        "process_seconds": round(wall, 1),
        "stage_seconds": {k: round(v, 1) for k, v in result.stage_seconds.items()},
        "registered": len(result.registered),
        "chosen": len(chosen),
        "blurred_chosen": len(blurred & set(chosen)),
        "blurred_even": len(blurred & set(even.tolist())),
        "sharpness_chosen_median": round(meta["sharpness_chosen_median"], 1),
        "sharpness_even_median": round(meta["sharpness_even_median"], 1),
        "tried": result.tried,
    }
    name = "summary.json" if args.sift_size is None else f"summary_sift{args.sift_size}.json"
    (args.out / name).write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
