"""Image decoding and encoding (worker/engine/images.py): formats, depths, channel order, limits."""

from __future__ import annotations

import io
import struct
import zlib

import cv2
import numpy as np
import pytest
import tifffile
from PIL import Image

from worker.engine.exceptions import ImageDecodeError, ImageSizeMismatchError, ImageTooLargeError
from worker.engine.images import (
    check_size,
    decode_image,
    encode_png,
    srgb_decode,
    srgb_encode,
    to_grey,
)

H, W = 12, 20


def _pixels(bits: int, channels: int, seed: int = 0) -> np.ndarray:
    """Random pixels (alpha too), each channel's range distinct so that a swapped R/B shows."""
    rng = np.random.default_rng(seed)
    top = 255 if bits == 8 else 65535
    a = rng.integers(0, top + 1, size=(H, W, channels))
    if channels >= 3:
        a[..., 0] = a[..., 0] // 4  # red dark
        a[..., 2] = top - a[..., 2] // 4  # blue bright
    a = a.astype(np.uint8 if bits == 8 else np.uint16)
    return a[..., 0] if channels == 1 else a


def _png(a: np.ndarray) -> bytes:
    if a.dtype == np.uint16:  # PIL cannot write 16-bit colour PNGs: OpenCV, in BGR(A) order
        order = [2, 1, 0, 3][: a.shape[2]] if a.ndim == 3 else slice(None)
        ok, enc = cv2.imencode(".png", np.ascontiguousarray(a[..., order]))
        assert ok
        return enc.tobytes()
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


def _tiff(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    tifffile.imwrite(buf, a, photometric="minisblack" if a.ndim == 2 else "rgb")
    return buf.getvalue()


def _expected(a: np.ndarray) -> np.ndarray:
    top = 255.0 if a.dtype == np.uint8 else 65535.0
    f = a.astype(np.float64) / top
    return f[..., :3] if f.ndim == 3 else f


LOSSLESS_CASES = [
    pytest.param(enc, bits, ch, id=f"{name}-{bits}bit-{ {1: 'grey', 3: 'rgb', 4: 'rgba'}[ch] }")
    for name, enc in (("png", _png), ("tiff", _tiff))
    for bits in (8, 16)
    for ch in (1, 3, 4)
]


@pytest.mark.parametrize(("encoder", "bits", "channels"), LOSSLESS_CASES)
def test_lossless_formats_decode_exactly(encoder, bits: int, channels: int) -> None:  # noqa: ANN001
    a = _pixels(bits, channels)
    img = decode_image(encoder(a))
    assert img.dtype == np.float32
    assert img.shape == ((H, W) if channels == 1 else (H, W, 3))
    np.testing.assert_allclose(img, _expected(a), atol=1e-7)
    if channels > 1:  # R and B not swapped (OpenCV decodes BGR)
        assert img[..., 0].mean() < 0.3 < 0.7 < img[..., 2].mean()


@pytest.mark.parametrize("compression", ["raw", "tiff_lzw", "tiff_adobe_deflate"])
def test_rgba_tiff_keeps_straight_colours(compression: str) -> None:
    """Alpha is dropped, not multiplied in (libtiff's RGBA reader would premultiply), also for
    the compressions cameras and PIL write."""
    a = _pixels(8, 4, seed=3)
    buf = io.BytesIO()
    Image.fromarray(a, mode="RGBA").save(buf, format="TIFF", compression=compression)
    np.testing.assert_allclose(decode_image(buf.getvalue()), _expected(a), atol=1e-7)


@pytest.mark.parametrize("mode", ["L", "RGB"])
def test_jpeg_decodes_to_its_colours(mode: str) -> None:
    """Flat patches survive JPEG to within a couple of levels; the channel order is RGB."""
    colours = [(200, 30, 60), (20, 180, 90), (40, 50, 220), (128, 128, 128)]
    a = np.zeros((64, 64, 3), np.uint8)
    for k, c in enumerate(colours):
        a[(k // 2) * 32 : (k // 2 + 1) * 32, (k % 2) * 32 : (k % 2 + 1) * 32] = c
    pil = Image.fromarray(a).convert(mode)
    buf = io.BytesIO()
    pil.save(buf, format="JPEG", quality=95)
    img = decode_image(buf.getvalue())
    want = np.asarray(pil, dtype=np.float64) / 255.0
    assert img.shape == want.shape
    for k in range(4):
        y, x = (k // 2) * 32 + 16, (k % 2) * 32 + 16
        np.testing.assert_allclose(
            img[y - 8 : y + 8, x - 8 : x + 8].mean(axis=(0, 1)), want[y, x], atol=3 / 255
        )


def _gif() -> bytes:
    buf = io.BytesIO()
    Image.new("L", (8, 8)).save(buf, format="GIF")
    return buf.getvalue()


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"this is not an image at all" * 10,
        np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes(),
        _png(_pixels(8, 3))[:60],  # header intact, pixel data truncated
        b"\x89PNG\r\n\x1a\n" + b"\x00" * 100,  # signature, then junk
        _gif(),  # a real image, but not an accepted format
    ],
    ids=["empty", "text", "random", "truncated-png", "bad-chunks", "gif"],
)
def test_unreadable_data_raises_image_decode_error(data: bytes) -> None:
    with pytest.raises(ImageDecodeError):
        decode_image(data)


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG whose IHDR claims ``width`` × ``height`` (8-bit RGB) but whose pixel data is a few
    bytes: any decoder that runs fails (or tries to allocate the claimed size)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", zlib.compress(b"\x00" * 16))
        + _chunk(b"IEND", b"")
    )


@pytest.mark.filterwarnings("ignore::PIL.Image.DecompressionBombWarning")
@pytest.mark.parametrize("side", [5_000, 10_000, 20_000, 100_000])
def test_pixel_limit_is_checked_before_decoding(side: int) -> None:
    """A header claiming more than 4096² px raises ImageTooLargeError although it holds almost
    no pixel data: a decoder run first would have failed differently (or allocated the size).
    The larger sides are also past PIL's own decompression-bomb limits."""
    with pytest.raises(ImageTooLargeError, match="pixels"):
        decode_image(_png_header_only(side, side))
    with pytest.raises(ImageDecodeError) as exc:  # the same file at a small size: only corrupt
        decode_image(_png_header_only(10, 10))
    assert not isinstance(exc.value, ImageTooLargeError)


def test_pixel_limit_boundary() -> None:
    data = _png(_pixels(8, 1))
    assert decode_image(data, max_pixels=H * W).shape == (H, W)
    with pytest.raises(ImageTooLargeError):
        decode_image(data, max_pixels=H * W - 1)


def test_check_size() -> None:
    img = np.zeros((H, W, 3), np.float32)
    check_size(img, W, H)
    check_size(img[..., 0], W, H)
    with pytest.raises(ImageSizeMismatchError, match=f"{W}×{H} px but the camera is {H}×{W}"):
        check_size(img, H, W)
    with pytest.raises(ImageSizeMismatchError):
        check_size(img, W, H + 1)


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("channels", [1, 3])
def test_encode_png_round_trip(bits: int, channels: int) -> None:
    rng = np.random.default_rng(1)
    shape = (H, W) if channels == 1 else (H, W, 3)
    img = rng.uniform(0, 1, shape).astype(np.float32)
    img[0, 0] = 0.0 if channels == 1 else (1.0, 0.0, 0.25)  # a known, asymmetric pixel
    back = decode_image(encode_png(img, bits=bits))
    assert back.shape == shape
    np.testing.assert_allclose(back, img, atol=0.5 / (255 if bits == 8 else 65535) + 1e-7)


def test_srgb_curves() -> None:
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=2e-6)
    # Known points of the standard curve: linear 0.5 encodes to 0.7354, 0.2140 to 0.5.
    assert float(srgb_encode(np.float32(0.5))) == pytest.approx(0.7354, abs=1e-4)
    assert float(srgb_decode(np.float32(0.5))) == pytest.approx(0.2140, abs=1e-4)
    assert float(srgb_encode(np.float32(0.002))) == pytest.approx(0.002 * 12.92, rel=1e-6)


def test_to_grey_is_the_channel_mean() -> None:
    img = np.zeros((2, 2, 3), np.float32)
    img[..., 2] = 0.9  # pure blue stays visible (luma would give 0.07)
    np.testing.assert_allclose(to_grey(img), 0.3, atol=1e-7)
    grey = np.full((2, 2), 0.4, np.float32)
    assert to_grey(grey) is grey or np.array_equal(to_grey(grey), grey)
