"""Image I/O: exact round trips, mode conversions, atomic writes and one-line errors for bad files."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from PIL import Image, ImageFile

from hdrplenoxels.core.errors import InputError, WriteError
from hdrplenoxels.data import image_io
from hdrplenoxels.data.image_io import read_exr, read_image, read_image_with_alpha, write_exr, write_png

RNG = np.random.default_rng(0)


def _raises_naming(path: Path, fn, *args) -> InputError:
    """Call fn and check it raises a one-line InputError that names `path`'s file."""
    with pytest.raises(InputError) as info:
        fn(*args)
    msg = str(info.value)
    assert path.name in msg and "\n" not in msg
    return info.value


def _png16(path: Path, arr: np.ndarray) -> None:
    """Minimal 16-bit PNG writer (Pillow cannot write 16-bit colour PNGs)."""
    arr = np.asarray(arr, dtype=">u2")
    h, w = arr.shape[:2]
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[1 if arr.ndim == 2 else arr.shape[2]]
    raw = b"".join(b"\x00" + arr[y].tobytes() for y in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    ihdr = struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    )


# ---- PNG / Pillow ---------------------------------------------------------------------------------


def test_png_uint8_round_trip_exact(tmp_path):
    img = RNG.integers(0, 256, size=(6, 8, 3), dtype=np.uint8)
    p = write_png(tmp_path / "a.png", img)
    out = read_image(p)
    assert out.dtype == np.uint8 and out.shape == (6, 8, 3)
    np.testing.assert_array_equal(out, img)
    rgb, alpha = read_image_with_alpha(p)
    assert alpha is None
    np.testing.assert_array_equal(rgb, img)


def test_png_float_is_clipped_and_rounded(tmp_path):
    f = np.array([[[-0.5, 0.0, 1.0], [2.0, 0.5, 0.2]]], dtype=np.float32)  # (1,2,3)
    out = read_image(write_png(tmp_path / "f.png", f))
    np.testing.assert_array_equal(out, [[[0, 0, 255], [255, 128, 51]]])


def test_png_write_rejects_bad_shapes_and_dtypes(tmp_path):
    with pytest.raises(ValueError):
        write_png(tmp_path / "x.png", np.zeros((6, 8, 2), np.uint8))
    with pytest.raises(TypeError):
        write_png(tmp_path / "x.png", np.zeros((6, 8, 3), np.int32))
    assert not list(tmp_path.iterdir())


def test_greyscale_and_palette_become_rgb(tmp_path):
    g = RNG.integers(0, 256, size=(6, 8), dtype=np.uint8)
    Image.fromarray(g, mode="L").save(tmp_path / "g.png")
    np.testing.assert_array_equal(read_image(tmp_path / "g.png"), np.repeat(g[:, :, None], 3, axis=2))

    rgb = RNG.integers(0, 256, size=(6, 8, 3), dtype=np.uint8)
    pal = Image.fromarray(rgb).quantize(colors=16)
    pal.save(tmp_path / "p.png")
    out, alpha = read_image_with_alpha(tmp_path / "p.png")
    assert alpha is None
    np.testing.assert_array_equal(out, np.asarray(pal.convert("RGB")))


def test_rgba_and_la_give_alpha_separately(tmp_path):
    rgba = RNG.integers(0, 256, size=(6, 8, 4), dtype=np.uint8)
    write_png(tmp_path / "a.png", rgba)
    rgb, alpha = read_image_with_alpha(tmp_path / "a.png")
    np.testing.assert_array_equal(rgb, rgba[:, :, :3])
    assert alpha is not None and alpha.dtype == np.float32
    np.testing.assert_allclose(alpha, rgba[:, :, 3] / 255.0, atol=1e-7)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), rgba[:, :, :3])

    la = RNG.integers(0, 256, size=(6, 8, 2), dtype=np.uint8)
    Image.fromarray(la, mode="LA").save(tmp_path / "la.png")
    rgb, alpha = read_image_with_alpha(tmp_path / "la.png")
    np.testing.assert_array_equal(rgb, np.repeat(la[:, :, :1], 3, axis=2))
    np.testing.assert_allclose(alpha, la[:, :, 1] / 255.0, atol=1e-7)


def test_16bit_greyscale_scaled_by_257_rounded(tmp_path):
    v = np.array([[0, 128, 129, 257, 65535, 32896, 386, 385]], dtype=np.uint16)
    _png16(tmp_path / "g16.png", v)
    out = read_image(tmp_path / "g16.png")
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out[0, :, 0], [0, 0, 1, 1, 255, 128, 2, 1])
    np.testing.assert_array_equal(out[..., 0], out[..., 2])


@pytest.mark.parametrize("channels", [2, 3, 4])
def test_16bit_colour_png_is_refused_with_advice(tmp_path, channels):
    p = tmp_path / f"c16_{channels}.png"
    _png16(p, RNG.integers(0, 65536, size=(6, 8, channels)))
    err = _raises_naming(p, read_image, p)
    assert "16-bit" in err.problem and "8-bit" in err.problem


def test_missing_garbage_and_truncated_images(tmp_path):
    _raises_naming(tmp_path / "nope.png", read_image, tmp_path / "nope.png")
    (tmp_path / "junk.png").write_bytes(b"this is not an image")
    _raises_naming(tmp_path / "junk.png", read_image, tmp_path / "junk.png")

    big = RNG.integers(0, 256, size=(64, 64, 3), dtype=np.uint8)
    write_png(tmp_path / "full.png", big)
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    _raises_naming(tmp_path / "cut.png", read_image, tmp_path / "cut.png")
    Image.fromarray(big).save(tmp_path / "full.jpg", quality=90)
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 2])
    _raises_naming(tmp_path / "cut.jpg", read_image, tmp_path / "cut.jpg")
    assert ImageFile.LOAD_TRUNCATED_IMAGES is False


def test_unsupported_mode(tmp_path):
    Image.new("CMYK", (8, 6)).save(tmp_path / "cmyk.jpg")
    err = _raises_naming(tmp_path / "cmyk.jpg", read_image, tmp_path / "cmyk.jpg")
    assert "CMYK" in err.problem
    Image.new("F", (8, 6)).save(tmp_path / "f.tiff")
    _raises_naming(tmp_path / "f.tiff", read_image, tmp_path / "f.tiff")


def test_png_atomic_write_keeps_old_file(tmp_path, monkeypatch):
    good = RNG.integers(0, 256, size=(6, 8, 3), dtype=np.uint8)
    p = write_png(tmp_path / "a.png", good)
    before = p.read_bytes()

    def broken_save(self, fp, *args, **kwargs):
        Path(fp).write_bytes(b"half a png")
        raise OSError("disk full")

    monkeypatch.setattr(Image.Image, "save", broken_save)
    with pytest.raises(OSError):
        write_png(p, np.zeros((6, 8, 3), np.uint8))
    assert p.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir()] == ["a.png"]


# ---- EXR -----------------------------------------------------------------------------------------


def test_exr_round_trip_exact(tmp_path):
    img = (RNG.standard_normal((6, 8, 3)) * 100).astype(np.float32)
    img[0, 0] = [0.0, 1e-30, 65504.0 * 10]
    out = read_exr(write_exr(tmp_path / "a.exr", img))
    assert out.dtype == np.float32 and out.shape == (6, 8, 3)
    np.testing.assert_array_equal(out, img)


def test_exr_write_non_contiguous_view(tmp_path):
    img = RNG.random((8, 6, 3)).astype(np.float32)
    view = img.transpose(1, 0, 2)[:, ::-1]
    np.testing.assert_array_equal(read_exr(write_exr(tmp_path / "v.exr", view)), view)


def test_exr_write_without_exr_suffix_still_exr(tmp_path):
    img = RNG.random((6, 8, 3)).astype(np.float32)
    p = write_exr(tmp_path / "radiance.bin", img)
    np.testing.assert_array_equal(read_exr(p), img)


def _write_channels(path: Path, channels: dict) -> None:
    """Write with OpenEXR directly, as another tool would (it ignores numpy strides: copy first)."""
    channels = {k: np.ascontiguousarray(v) for k, v in channels.items()}
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))


def test_exr_separate_half_channels_with_alpha(tmp_path):
    rgb = RNG.random((6, 8, 3)).astype(np.float16)
    _write_channels(
        tmp_path / "h.exr",
        {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": np.ones((6, 8), np.float16)},
    )
    out = read_exr(tmp_path / "h.exr")
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, rgb.astype(np.float32))


def test_exr_layer_and_luminance_channels(tmp_path):
    rgb = RNG.random((6, 8, 3)).astype(np.float32)
    _write_channels(tmp_path / "l.exr", {f"beauty.{c}": rgb[..., i] for i, c in enumerate("RGB")})
    np.testing.assert_array_equal(read_exr(tmp_path / "l.exr"), rgb)
    _write_channels(tmp_path / "y.exr", {"Y": rgb[..., 0]})
    np.testing.assert_array_equal(read_exr(tmp_path / "y.exr"), np.repeat(rgb[..., :1], 3, axis=2))
    _write_channels(tmp_path / "z.exr", {"Z": rgb[..., 0]})
    err = _raises_naming(tmp_path / "z.exr", read_exr, tmp_path / "z.exr")
    assert "Z" in err.problem


def test_exr_bad_files(tmp_path):
    _raises_naming(tmp_path / "missing.exr", read_exr, tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    _raises_naming(tmp_path / "junk.exr", read_exr, tmp_path / "junk.exr")
    write_exr(tmp_path / "full.exr", RNG.random((32, 32, 3)).astype(np.float32))
    data = (tmp_path / "full.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    _raises_naming(tmp_path / "cut.exr", read_exr, tmp_path / "cut.exr")


def test_exr_write_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError):
        write_exr(tmp_path / "x.exr", np.zeros((6, 8), np.float32))
    with pytest.raises(TypeError):
        write_exr(tmp_path / "x.exr", np.zeros((6, 8, 3), np.uint8))


def test_exr_atomic_write_keeps_old_file_and_uses_exr_suffix(tmp_path, monkeypatch):
    good = RNG.random((6, 8, 3)).astype(np.float32)
    p = write_exr(tmp_path / "a.exr", good)
    before = p.read_bytes()
    seen: list[Path] = []

    def broken(tmp: Path, rgb: np.ndarray) -> None:
        seen.append(tmp)
        tmp.write_bytes(b"half an exr")
        raise RuntimeError("writer crashed")

    monkeypatch.setattr(image_io, "_write_exr_file", broken)
    with pytest.raises(WriteError, match="a.exr: can't write \\(writer crashed\\)"):  # OpenEXR's RuntimeError
        write_exr(p, np.zeros((6, 8, 3), np.float32))
    assert seen and seen[0].suffix == ".exr" and seen[0].parent == tmp_path
    assert p.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir()] == ["a.exr"]
    np.testing.assert_array_equal(read_exr(p), good)
