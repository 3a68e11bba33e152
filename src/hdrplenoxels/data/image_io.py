"""Reading and writing images: 8-bit photos with Pillow, linear HDR with OpenEXR.

Every problem with a user's file becomes an `InputError(path, problem)` so the CLI can print one line.
Writes go through `atomic_path`, so a failure never leaves a half-written file where a good one was.
EXIF orientation is deliberately NOT applied: camera poses and intrinsics in NeRF layouts describe the
stored pixel grid.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import pillow_heif
from PIL import Image, UnidentifiedImageError

from hdrplenoxels.core.atomic import atomic_path
from hdrplenoxels.core.errors import InputError, WriteError

# Modes Pillow decodes with full fidelity into something we can turn into 8-bit RGB (+ alpha).
_RGB_MODES = {"1", "L", "P", "RGB", "RGBX"}
_ALPHA_MODES = {"LA", "PA", "RGBA"}
_INT_MODES = {"I;16", "I;16B", "I;16L", "I;16N", "I"}  # 16-bit greyscale (or 32-bit int holding it)


# An iPhone's photos are HEIC by default: Pillow reads them once pillow-heif has registered its opener,
# which also turns them upright by their own rotation and mirror (their EXIF orientation then reads 1).
pillow_heif.register_heif_opener()


def _is_16bit_colour(img: Image.Image) -> bool:
    """True for 16-bit-per-sample colour / grey+alpha PNGs, which Pillow silently truncates to 8 bits.

    Must be asked before `load()`: the decoder's raw mode (e.g. 'RGB;16B') is only known until then.
    """
    if img.mode in _INT_MODES:
        return False
    rawmode = getattr(getattr(img, "png", None), "im_rawmode", None)
    if rawmode is None and img.tile:
        args = img.tile[0].args
        rawmode = args if isinstance(args, str) else (args[0] if args else None)
    return isinstance(rawmode, str) and ";16" in rawmode


def _open_decoded(path: Path) -> tuple[Image.Image, bool]:
    """Open and fully decode `path` (so truncated files fail here, not later as garbage pixels).

    Returns the image and whether it is a 16-bit colour image that Pillow truncated to 8 bits.
    """
    if not path.exists():
        raise InputError(path, "image file not found")
    if not path.is_file():
        raise InputError(path, "is not a file")
    try:
        img = Image.open(path)
        sixteen = _is_16bit_colour(img)
        img.load()
    except UnidentifiedImageError:
        raise InputError(path, "not a readable image (unknown or corrupt format)") from None
    except Image.DecompressionBombError as e:
        raise InputError(path, f"image too large to decode safely ({e})") from None
    except (OSError, SyntaxError, ValueError) as e:  # truncated data, bad chunks, broken headers
        raise InputError(path, f"cannot decode image: {e}") from None
    return img, sixteen


def _int_to_uint8(path: Path, img: Image.Image) -> np.ndarray:
    """16-bit greyscale to 8-bit RGB by value/257, rounded (maps 0..65535 exactly onto 0..255)."""
    a = np.asarray(img).astype(np.int64)
    if a.size and (a.min() < 0 or a.max() > 65535):
        raise InputError(
            path, f"integer image (mode {img.mode}) has values outside 0..65535; convert it to 8-bit RGB"
        )
    g = np.floor(a / 257.0 + 0.5).astype(np.uint8)
    return np.repeat(g[:, :, None], 3, axis=2)


def read_image_with_alpha(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """RGB uint8 (H,W,3) and, for images with transparency, straight alpha float32 (H,W) in [0,1].

    Greyscale, palette and 16-bit greyscale are converted to RGB. 16-bit colour PNGs are refused because
    Pillow reads only their high byte (not a faithful rounding); other modes (CMYK, float, ...) too.
    """
    path = Path(path)
    img, sixteen = _open_decoded(path)
    mode = img.mode
    if sixteen:
        raise InputError(
            path,
            "16-bit PNG with colour or alpha channels: Pillow reads only the high byte of each sample, "
            "not a faithful 8-bit image; convert it to 8-bit RGB(A) first "
            "(e.g. `magick in.png -depth 8 out.png`)",
        )
    if mode in _INT_MODES:
        return _int_to_uint8(path, img), None
    if mode in _ALPHA_MODES or (mode == "P" and "transparency" in img.info):
        rgba = np.asarray(img.convert("RGBA"))
        return np.ascontiguousarray(rgba[:, :, :3]), rgba[:, :, 3].astype(np.float32) / 255.0
    if mode in _RGB_MODES:
        return np.ascontiguousarray(np.asarray(img.convert("RGB"))), None
    raise InputError(path, f"unsupported image mode {mode!r}; save it as 8-bit RGB, RGBA or greyscale")


def composite_on_white(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """rgb*a + (1-a) on a white background, back to uint8 with rounding."""
    a = alpha[:, :, None]
    out = rgb.astype(np.float32) / 255.0 * a + (1.0 - a)
    return np.round(out * 255.0).clip(0, 255).astype(np.uint8)


def read_image(path: str | Path) -> np.ndarray:
    """RGB uint8 (H,W,3); any alpha channel is dropped (use `read_image_with_alpha` to composite)."""
    return read_image_with_alpha(path)[0]


def _to_uint8(img: np.ndarray) -> np.ndarray:
    """uint8 as is; floats are taken as [0,1], clipped and rounded (NaN -> 0)."""
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    if np.issubdtype(img.dtype, np.floating):
        f = np.nan_to_num(img.astype(np.float64), nan=0.0)
        return np.round(np.clip(f, 0.0, 1.0) * 255.0).astype(np.uint8)
    raise TypeError(f"write_png expects uint8 or float in [0,1], got {img.dtype}")


def write_png(path: str | Path, img: np.ndarray) -> Path:
    """Write (H,W), (H,W,3) or (H,W,4) uint8 / float-in-[0,1] as PNG, atomically."""
    a = _to_uint8(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        raise ValueError(f"write_png expects (H,W), (H,W,3) or (H,W,4), got shape {a.shape}")
    pil = Image.fromarray(np.ascontiguousarray(a))
    with atomic_path(path, suffix=".png") as tmp:
        pil.save(tmp, format="PNG")
    return Path(path)


def _write_exr_file(tmp: Path, rgb: np.ndarray) -> None:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": rgb}) as f:
        f.write(str(tmp))


def write_exr(path: str | Path, img: np.ndarray) -> Path:
    """Write linear float RGB (H,W,3) as a float32 ZIP-compressed scanline EXR, atomically."""
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"write_exr expects (H,W,3), got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise TypeError(f"write_exr expects a float array, got {a.dtype}")
    rgb = np.ascontiguousarray(a, dtype=np.float32)
    with atomic_path(path, suffix=".exr") as tmp:
        try:
            _write_exr_file(tmp, rgb)
        except RuntimeError as e:  # OpenEXR's report of a failed write: '... "<tmp file>". <cause>.'
            raise WriteError(path, str(e).rsplit('". ', 1)[-1].rstrip(".")) from None
    return Path(path)


def _exr_rgb(path: Path, channels: dict) -> np.ndarray:
    """Pick R, G, B from separately read channels: bare names, a single layer ('beauty.R'), or Y (grey)."""
    names = sorted(channels)
    group = next((g for g in ("RGB", "RGBA") if g in channels), None)
    if group is not None:  # grouped read (not what we ask for, but some versions group anyway)
        px = np.asarray(channels[group].pixels)
        if not np.issubdtype(px.dtype, np.floating):
            raise InputError(path, f"EXR colour channels are {px.dtype}, expected HALF or FLOAT")
        return np.ascontiguousarray(px[..., :3], dtype=np.float32)
    if all(c in channels for c in "RGB"):
        planes = [channels[c] for c in "RGB"]
    else:
        layers = {n.rsplit(".", 1)[0] for n in names if "." in n and n.rsplit(".", 1)[1] in ("R", "G", "B")}
        full = [lay for lay in sorted(layers) if all(f"{lay}.{c}" in channels for c in "RGB")]
        if len(full) == 1:
            planes = [channels[f"{full[0]}.{c}"] for c in "RGB"]
        elif "Y" in channels:
            planes = [channels["Y"]] * 3
        else:
            raise InputError(path, f"EXR has no R, G, B channels (found {', '.join(names) or 'none'})")
    arrays = [np.asarray(p.pixels) for p in planes]
    for a in arrays:
        if not np.issubdtype(a.dtype, np.floating):
            raise InputError(path, f"EXR colour channels are {a.dtype}, expected HALF or FLOAT")
        if a.shape != arrays[0].shape or a.ndim != 2:
            raise InputError(path, "EXR colour channels differ in size (subsampled channels are unsupported)")
    return np.stack(arrays, axis=-1).astype(np.float32)


def read_exr(path: str | Path) -> np.ndarray:
    """Linear float32 RGB (H,W,3) from an EXR with an RGB(A) group or separate R, G, B channels."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "EXR file not found" if not path.exists() else "is not a file")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = dict(f.channels())
            rgb = _exr_rgb(path, channels)
    except InputError:
        raise
    except Exception as e:  # OpenEXR raises RuntimeError / ValueError for corrupt or truncated files
        raise InputError(path, f"cannot read EXR: {e}") from None
    return rgb
