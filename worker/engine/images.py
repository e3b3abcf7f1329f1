"""Image input and output: decoding references, encoding renders, tone mapping.

References arrive as PNG, JPEG or TIFF, 8- or 16-bit, grey, RGB or RGBA. Internally an image is a
float32 array in [0, 1], shape (H, W) for grey or (H, W, 3) for colour. Renders are linear
radiance; :func:`to_display` maps them to the sRGB-encoded [0, 1] range a camera file would hold.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from schemas.names import DEFAULT_MAX_IMAGE_PIXELS, IMAGE_FORMATS
from worker.engine.exceptions import ImageDecodeError, ImageSizeMismatchError, ImageTooLargeError

FloatImage = NDArray[np.float32]


def decode_image(data: bytes, max_pixels: int = DEFAULT_MAX_IMAGE_PIXELS) -> FloatImage:
    """Decode PNG/JPEG/TIFF bytes to float32 in [0, 1], (H, W) or (H, W, 3); alpha is dropped.

    The header is read first (PIL, formats whitelisted) so that ImageTooLargeError is raised
    before any pixel is decoded; the pixels are then decoded by OpenCV, which keeps 16-bit depth
    for every format. Raises ImageDecodeError for anything unreadable.
    """
    if not data:
        raise ImageDecodeError("image is empty")
    try:
        with Image.open(io.BytesIO(data), formats=IMAGE_FORMATS) as img:
            w, h = img.size
            fmt = img.format
    except Image.DecompressionBombError as exc:  # PIL's own guard (> 179 Mpx) fired first
        raise ImageTooLargeError(f"image has more than {max_pixels} pixels ({exc})") from exc
    except Exception as exc:  # PIL raises many types for unknown or corrupt data
        raise ImageDecodeError(f"not a readable PNG, JPEG or TIFF image ({exc})") from exc
    if w * h > max_pixels:
        raise ImageTooLargeError(f"image has {w}×{h} pixels, more than {max_pixels}")
    import cv2

    a = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if a is None or a.size == 0 or a.shape[:2] != (h, w):
        raise ImageDecodeError("image data is corrupt or truncated")
    if fmt == "TIFF" and a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 4:
        # OpenCV reads 8-bit TIFFs with alpha through libtiff's RGBA reader, which premultiplies
        # unassociated alpha; PIL returns the stored (straight) colours, as for PNG.
        try:
            with Image.open(io.BytesIO(data), formats=("TIFF",)) as img:
                a = np.asarray(img.convert("RGBA"))[..., [2, 1, 0, 3]]
        except Exception as exc:
            raise ImageDecodeError(f"image data is corrupt or truncated ({exc})") from exc
    return _to_float(a)


def _to_float(a: NDArray[np.generic]) -> FloatImage:
    """OpenCV's decoded array (grey, BGR or BGRA; 8/16-bit or float) to float [0, 1] RGB/grey."""
    if a.dtype == np.uint8:
        f = a.astype(np.float32) / 255.0
    elif a.dtype == np.uint16:
        f = a.astype(np.float32) / 65535.0
    else:
        f = a.astype(np.float32)
        f = f / max(float(f.max()), 1e-12) if f.max() > 1.0 else np.clip(f, 0.0, 1.0)
    if f.ndim == 3:
        f = f[..., :3][..., ::-1] if f.shape[2] >= 3 else f[..., 0]
    return np.ascontiguousarray(f, dtype=np.float32)


def check_size(image: FloatImage, width: int, height: int) -> None:
    """Raise ImageSizeMismatchError unless the image is ``width`` × ``height``."""
    h, w = image.shape[:2]
    if (w, h) != (width, height):
        raise ImageSizeMismatchError(f"image is {w}×{h} px but the camera is {width}×{height} px")


def to_grey(image: FloatImage) -> FloatImage:
    """Grey image for feature work: the mean of R, G and B (a grey image is returned as is).

    Not luma: Rec. 709 weights blue at 7 %, which turns blue solar arrays black and hides the
    largest structures of many spacecraft from the feature tracker.
    """
    if image.ndim == 2:
        return image.astype(np.float32, copy=False)
    import cv2

    rgb = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    grey = cv2.transform(rgb, np.full((1, 3), 1.0 / 3.0, dtype=np.float32))  # ~10× np.mean
    return grey.reshape(image.shape[:2])


def _pow(x: NDArray[np.float32], exponent: float) -> NDArray[np.float32]:
    """x ** exponent: OpenCV's (several times faster) for images, numpy's for the rest."""
    if x.ndim == 2 or (x.ndim == 3 and x.shape[2] <= 4):
        import cv2

        return cv2.pow(np.ascontiguousarray(x), exponent)
    return np.power(x, np.float32(exponent))


def srgb_encode(linear: NDArray[np.floating]) -> FloatImage:
    """sRGB transfer function of linear values clipped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0).astype(np.float32)
    y = 1.055 * _pow(x, 1.0 / 2.4) - 0.055
    y = np.where(x <= 0.0031308, 12.92 * x, y)
    return y.astype(np.float32, copy=False)


def srgb_decode(encoded: NDArray[np.floating]) -> FloatImage:
    """Inverse sRGB transfer function, [0, 1] → linear [0, 1]."""
    x = np.clip(encoded, 0.0, 1.0).astype(np.float32)
    y = _pow((x + 0.055) / 1.055, 2.4)
    y = np.where(x <= 0.04045, x / 12.92, y)
    return y.astype(np.float32, copy=False)


def to_display(linear: FloatImage) -> FloatImage:
    """A linear render as an sRGB-encoded image in [0, 1], as a camera would store it."""
    return srgb_encode(linear)


def to_uint8(image: NDArray[np.floating]) -> NDArray[np.uint8]:
    """[0, 1] floats to 8-bit with rounding."""
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def encode_png(
    image: NDArray[np.floating] | NDArray[np.uint8], bits: int = 8, compress_level: int = 6
) -> bytes:
    """PNG bytes of a [0, 1] float (or uint8) image, grey or RGB; ``bits`` 8 or 16;
    ``compress_level`` zlib's, 1 (fastest) to 9 (smallest)."""
    if image.dtype == np.uint8:
        arr: NDArray[np.generic] = image
    elif bits == 16:
        arr = (np.clip(image, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
    else:
        arr = to_uint8(image)
    buf = io.BytesIO()
    if arr.dtype == np.uint16 and arr.ndim == 3:
        import cv2

        params = [cv2.IMWRITE_PNG_COMPRESSION, compress_level]
        ok, enc = cv2.imencode(".png", np.ascontiguousarray(arr[..., ::-1]), params)
        if not ok:
            raise ImageDecodeError("PNG encoding failed")
        return enc.tobytes()
    Image.fromarray(arr).save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


def on_sky(image: FloatImage, origin: tuple[int, int], size: tuple[int, int]) -> FloatImage:
    """A window's ``image`` at ``origin`` of a black image of ``size`` (w, h)."""
    box = Box.at(origin, (image.shape[1], image.shape[0]))
    return box.paste(image, (size[1], size[0]))


@dataclass(frozen=True)
class Box:
    """A rectangle of an image, columns [x0, x1) and rows [y0, y1), px."""

    x0: int
    y0: int
    x1: int
    y1: int

    @classmethod
    def at(cls, origin: tuple[int, int], size: tuple[int, int]) -> Box:
        """The box of ``size`` (w, h) whose top-left pixel is ``origin``."""
        (x, y), (w, h) = origin, size
        return cls(x, y, x + w, y + h)

    @property
    def slices(self) -> tuple[slice, slice]:
        return slice(self.y0, self.y1), slice(self.x0, self.x1)

    @property
    def pixels(self) -> int:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    def grown(self, margin: int, shape: tuple[int, ...]) -> Box:
        """This box ``margin`` px larger on every side, within an image of ``shape``."""
        h, w = shape[:2]
        return Box(
            max(self.x0 - margin, 0),
            max(self.y0 - margin, 0),
            min(self.x1 + margin, w),
            min(self.y1 + margin, h),
        )

    def of(self, image: NDArray[np.generic]) -> NDArray[np.generic]:
        """The box's part of ``image`` (a view)."""
        return image[self.slices]

    def paste(
        self, part: NDArray[np.generic], shape: tuple[int, ...], fill: float = 0.0
    ) -> NDArray[np.generic]:
        """``part`` (the box's size) in an image of ``shape``'s rows and columns, ``fill``
        elsewhere."""
        out = np.full((*shape[:2], *part.shape[2:]), fill, dtype=part.dtype)
        out[self.slices] = part
        return out
