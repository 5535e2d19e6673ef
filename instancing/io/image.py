"""Image files: lossless float32 OpenEXR (read and write) and tone-mapped PNG previews.

This is the last step of the data path (film -> EXR / PNG / tensor). EXR files
go through the OpenEXR Python package (its ``OpenEXR.File`` API, 3.x): every
channel is stored as 32-bit float with ZIP compression, which is lossless, so a
render written and read back is the same bits, NaN payloads and -0.0 included.

EXR keeps channels sorted by name inside the file, so the order a caller gave
(``depth, nx, ny, nz, instance`` for an AOV image) would be lost. We store it
in the string-list header attribute :data:`CHANNEL_ORDER_ATTRIBUTE` and restore
it on read. Files from other tools come back with R, G, B, A first (those that
exist, in that order) and then the remaining channels sorted by name.

PNG previews are encoded by Mitsuba's ``Bitmap`` writer (libpng; it also tags
the file as sRGB), so the package needs neither Pillow nor matplotlib.

Facts about OpenEXR 3.5 measured while writing this module (they shape the code):

- ``OpenEXR.File(header, {name: array})`` ignores NumPy strides: a
  non-contiguous view is written as if it were contiguous (wrong pixels, no
  error). Every channel is therefore copied with ``np.ascontiguousarray``.
- ``OpenEXR.File(header, channels)`` replaces the arrays in the ``channels``
  dict it is given by ``OpenEXR.Channel`` objects (the caller's dict changes).
- The default read (``separate_channels=False``) merges ``R, G, B(, A)`` into
  one ``"RGB"``/``"RGBA"`` array and ``a.R, a.G, a.B`` into ``"a"``;
  ``separate_channels=True`` gives one 2-D array per channel under its file name.
- Channel names longer than 255 bytes are silently truncated on write and a
  name containing NUL fails with an unrelated cast error, so names are checked
  here first. float64 arrays are refused by the writer (converted here first).
- Errors come as plain ``RuntimeError``/``ValueError`` (missing, corrupt or
  truncated file, unwritable path) and the C library also prints a line on
  stderr; they are re-raised as :class:`ImageFileError` naming the path.
- ZIP and PIZ round-trip float32 bits exactly (NaN payloads, denormals, -0.0).
  Of the other codecs only ``PXR24`` altered FLOAT channels (it keeps 24 bits);
  B44(A) and DWAA/DWAB are lossy for HALF channels only.
- A mip-mapped tiled file written by the package itself could not be read back
  ("corrupt chunk table"); single-level tiled files read like scanline ones.
- Chunk data carries no checksum: a corrupted (not truncated) compressed chunk
  can decode to wrong pixels without any error.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import OpenEXR

from ..core.errors import InstancingError
from .output_file import replaced

#: Header attribute (a string list) that records the intended channel order.
CHANNEL_ORDER_ATTRIBUTE = "channel_order"

#: Channel names used when ``write_exr`` is given none, by channel count.
DEFAULT_CHANNELS = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}

#: The largest exposure (stops) of a PNG preview: 2^1000 is near float64's largest number.
MAX_EXPOSURE = 1000.0

#: File name suffixes of other image formats, which write_exr refuses (a name without a
#: suffix, or any other, is taken as meant).
OTHER_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".hdr", ".tif", ".tiff", ".bmp", ".pfm")

# Lossless for float32 data (measured bit-exact). ZIP is OpenEXR's default;
# Mitsuba writes PIZ, which is equally lossless.
_EXR_COMPRESSION = OpenEXR.ZIP_COMPRESSION

# Longest channel name (in UTF-8 bytes) an EXR file can hold; OpenEXR
# truncates longer ones silently.
_MAX_CHANNEL_NAME_BYTES = 255

# Channels of a colour image, in the order they come back from files that do
# not record their own order.
_COLOR_CHANNELS = ("R", "G", "B", "A")


class ImageFileError(InstancingError, OSError):
    """An image file is missing, unreadable, corrupt, unsupported or unwritable."""


class ImageNotFoundError(ImageFileError, FileNotFoundError):
    """An image file to be read does not exist (also a :class:`FileNotFoundError`)."""


class ImageDataError(InstancingError, ValueError):
    """Pixels or channel names given to a writer do not form a valid image."""


def write_exr(path: str | os.PathLike[str], image: Any,
              channels: Sequence[str] | None = None) -> None:
    """Write an image as a lossless float32 OpenEXR file.

    Args:
        path: destination file; replaced whole once written (never left half-written).
        image: anything ``numpy.asarray`` turns into a real array of shape
            (H, W, C) or (H, W) (read as C = 1): a NumPy array, a Dr.Jit
            ``TensorXf`` (see :mod:`instancing.core.backend`), a Mitsuba ``Bitmap``.
            Bool, integer and float data are converted to float32.
        channels: C distinct channel names, in the order of the last axis.
            Defaults to ``["Y"]``, ``["R", "G", "B"]`` or ``["R", "G", "B", "A"]``
            for C = 1, 3, 4 and is required for any other C.

    Every channel is stored as 32-bit float with ZIP compression, and the given
    channel order is recorded in the header attribute ``"channel_order"`` so
    that :func:`read_exr` returns the channels in this order.

    Limitations: float64 (and integers above 2**24) are rounded to float32;
    single-part scanline images only; no other header metadata is written.

    Raises:
        ImageDataError: the array is not 2-D or 3-D, is empty, is not real
            numeric data, or ``channels`` is missing, of the wrong length, not
            distinct, or holds a name EXR cannot store.
        ImageFileError: the file cannot be written, or its name ends in another image
            format's suffix (OTHER_IMAGE_SUFFIXES).
    """
    path = _fspath(path)
    if Path(path).suffix.lower() in OTHER_IMAGE_SUFFIXES:
        raise ImageFileError(f"cannot write EXR image {path!r}: its name says "
                             f"{Path(path).suffix} (write_png writes PNG previews)")
    pixels = _as_float32_image(image, path)
    names = _channel_names(channels, pixels.shape[2], path)

    # One contiguous 2-D plane per channel: OpenEXR ignores strides, so a view
    # such as pixels[..., k] would be written with the wrong pixels.
    planes = {name: np.ascontiguousarray(pixels[:, :, k]) for k, name in enumerate(names)}
    header = {
        "compression": _EXR_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        CHANNEL_ORDER_ATTRIBUTE: list(names),
    }
    try:
        with replaced(path) as partial:
            OpenEXR.File(header, planes).write(partial)
    except (RuntimeError, ValueError, TypeError, OSError) as exc:
        raise ImageFileError(f"cannot write EXR image {path!r}: {exc}") from exc


def read_exr(path: str | os.PathLike[str]) -> tuple[np.ndarray, list[str]]:
    """Read every channel of a single-part OpenEXR image as float32.

    Args:
        path: an OpenEXR file, written by :func:`write_exr` or any other tool.

    Returns:
        ``(pixels, names)``: a C-contiguous float32 NumPy array of shape
        (H, W, C) (C = 1 for a one-channel image) and its C channel names.
        Files from :func:`write_exr` keep the order they were written in;
        other files list R, G, B, A first (those present, in that order), then
        the other channels sorted by name. Half and 32-bit unsigned integer
        channels are converted to float32 (exact for half and for integers up
        to 2**24); float32 data is returned bit for bit.

    Limitations: multi-part, deep and subsampled images are refused, and
    mip-mapped files fail in OpenEXR itself (single-level tiled files work). OpenEXR
    checks the structure of a file, not its pixel data: a corrupted (rather
    than truncated) compressed block may go undetected.

    Raises:
        ImageNotFoundError: the file does not exist.
        ImageFileError: the file is not a readable OpenEXR image, or uses one
            of the unsupported features above.
    """
    path = _fspath(path)
    if not os.path.exists(path):
        raise ImageNotFoundError(f"EXR image {path!r} does not exist")
    if os.path.isdir(path):
        raise ImageFileError(f"EXR image {path!r} is a directory, not a file")
    try:
        exr = OpenEXR.File(path, separate_channels=True)
        parts = exr.parts
        if len(parts) != 1:
            raise ImageFileError(
                f"EXR image {path!r} has {len(parts)} parts; only single-part images are "
                "supported")
        header = exr.header()
        planes = {name: channel.pixels for name, channel in exr.channels().items()}
    except ImageFileError:
        raise
    except (RuntimeError, ValueError, TypeError, OSError, IndexError) as exc:
        raise ImageFileError(f"cannot read EXR image {path!r}: {exc}") from exc

    if not planes:
        raise ImageFileError(f"EXR image {path!r} has no channels")
    names = _stored_channel_order(header, list(planes))

    # Stack the channels into one (H, W, C) array, converting exact types.
    shape = None
    for name in names:
        plane = planes[name]
        if not isinstance(plane, np.ndarray) or plane.dtype.kind not in "fu" or plane.ndim != 2:
            raise ImageFileError(
                f"EXR image {path!r}: channel {name!r} is not a flat image plane (deep images "
                "are not supported)")
        if shape is None:
            shape = plane.shape
        elif plane.shape != shape:
            raise ImageFileError(
                f"EXR image {path!r}: channel {name!r} has size {plane.shape}, other channels "
                f"{shape} (subsampled channels are not supported)")
    pixels = np.empty(shape + (len(names),), dtype=np.float32)
    for k, name in enumerate(names):
        pixels[:, :, k] = planes[name]
    return pixels, names


def read_texture(path: str | os.PathLike[str], raw: bool = False) -> np.ndarray:
    """Read a texture image (PNG, JPEG, OpenEXR, ... : what Mitsuba's ``Bitmap`` reads) as
    linear RGB texels, as Mitsuba's ``bitmap`` texture holds them.

    Args:
        path: the image file.
        raw: keep the stored values (no sRGB decoding of 8-bit images).

    Returns:
        (H, W, 3) float32, row 0 the top row of the image: 8-bit sRGB-encoded images
        decoded to linear values unless ``raw``; float images as stored; a grey image
        repeated in the three channels; alpha dropped.

    Raises:
        ImageNotFoundError: the file does not exist.
        ImageFileError: the file cannot be read as an image, or has other than 1-4 channels.
    """
    path = _fspath(path)
    if not os.path.isfile(path):
        raise ImageNotFoundError(f"texture image {path!r} does not exist")
    import mitsuba as mi

    try:
        bitmap = mi.Bitmap(path)
        if bitmap.channel_count() not in (1, 2, 3, 4):
            raise ImageFileError(f"texture image {path!r} has {bitmap.channel_count()} channels; "
                                 "expected grey, grey + alpha, RGB or RGBA")
        if raw:
            bitmap.set_srgb_gamma(False)
        linear = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
    except ImageFileError:
        raise
    except (RuntimeError, ValueError, TypeError, OSError) as exc:
        raise ImageFileError(f"cannot read texture image {path!r}: {exc}") from exc
    texels = np.array(linear, dtype=np.float32, copy=True)
    if texels.ndim == 2:
        texels = texels[:, :, None]
    texels = np.ascontiguousarray(np.broadcast_to(texels, texels.shape[:2] + (3,)))
    if not np.isfinite(texels).all():
        raise ImageFileError(f"texture image {path!r} holds non-finite values")
    return texels


def write_png(path: str | os.PathLike[str], image: Any, exposure: float = 0.0,
              premultiplied: bool = False) -> None:
    """Write an 8-bit sRGB PNG preview of a linear image.

    Args:
        path: destination file; replaced whole once written (never left half-written).
        image: anything ``numpy.asarray`` turns into a real array of shape
            (H, W), (H, W, 1) (grayscale), (H, W, 3) (RGB) or (H, W, 4) (RGBA),
            holding linear radiance.
        exposure: in stops; colour channels are multiplied by ``2**exposure``.
        premultiplied: whether an RGBA image's colour is premultiplied by its alpha, as a
            render's is (its pixels average the light of all their samples, 0 where they
            miss): then divided by it (0 where the alpha is 0).

    Colour channels are exposed, clamped to [0, 1] (NaN -> 0), encoded with the
    sRGB transfer function (IEC 61966-2-1) and rounded to the nearest of the 256
    levels. Alpha is coverage, not light: it is clamped and quantized linearly,
    without exposure or sRGB encoding, and stored as straight (not
    premultiplied) alpha, as PNG defines it. The file is tagged as sRGB.

    Limitations: a lossy preview (8 bits, clamped); use :func:`write_exr` to
    keep the data.

    Raises:
        ImageDataError: bad array shape or type, channel count not 1, 3 or 4,
            or an ``exposure`` that is not finite or beyond MAX_EXPOSURE stops.
        ImageFileError: the file cannot be written, or its name ends in another image
            format's suffix (.exr, OTHER_IMAGE_SUFFIXES).
    """
    path = _fspath(path)
    suffix = Path(path).suffix.lower()
    if suffix == ".exr" or (suffix in OTHER_IMAGE_SUFFIXES and suffix != ".png"):
        raise ImageFileError(f"cannot write PNG image {path!r}: its name says {Path(path).suffix} "
                             + ("(write_exr writes EXR files)" if suffix == ".exr" else ""))
    pixels = _as_float32_image(image, path)
    count = pixels.shape[2]
    if count not in (1, 3, 4):
        raise ImageDataError(
            f"PNG image {path!r}: cannot show {count} channels; give 1 (gray), 3 (RGB) or "
            "4 (RGBA)")
    try:
        exposure = float(exposure)
    except (TypeError, ValueError) as exc:
        raise ImageDataError(f"PNG image {path!r}: exposure {exposure!r} is not a number") from exc
    if not math.isfinite(exposure) or abs(exposure) > MAX_EXPOSURE:
        raise ImageDataError(f"PNG image {path!r}: exposure {exposure!r} must be a finite number of "
                             f"stops within +-{MAX_EXPOSURE}")

    # Tone map in float64: expose, clamp, sRGB-encode the colour channels.
    linear = pixels.astype(np.float64)
    color = slice(0, 3) if count == 4 else slice(0, count)
    if premultiplied and count == 4:
        alpha = linear[..., 3:]
        with np.errstate(divide="ignore", invalid="ignore"):
            linear[..., color] = np.where(alpha > 0, linear[..., color] / alpha, 0.0)
    levels = np.empty_like(linear)
    levels[..., color] = srgb_encode(np.clip(linear[..., color] * 2.0 ** exposure, 0.0, 1.0))
    if count == 4:
        levels[..., 3] = np.clip(linear[..., 3], 0.0, 1.0)
    levels = np.nan_to_num(levels, nan=0.0)
    codes = np.floor(levels * 255.0 + 0.5).astype(np.uint8)

    # Mitsuba's Bitmap marks uint8 data as sRGB and writes it through libpng.
    # Imported here: Mitsuba is heavy and must follow `import instancing`.
    import mitsuba as mi

    formats = {1: mi.Bitmap.PixelFormat.Y, 3: mi.Bitmap.PixelFormat.RGB,
               4: mi.Bitmap.PixelFormat.RGBA}
    try:
        with replaced(path) as partial:
            mi.Bitmap(codes, formats[count]).write(partial, mi.Bitmap.FileFormat.PNG)
    except (RuntimeError, ValueError, OSError) as exc:
        raise ImageFileError(f"cannot write PNG image {path!r}: {exc}") from exc


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Apply the sRGB opto-electronic transfer function (IEC 61966-2-1).

    Args:
        linear: values in [0, 1], any shape.

    Returns:
        Encoded values in [0, 1], same shape: ``12.92 x`` for x <= 0.0031308,
        else ``1.055 x**(1/2.4) - 0.055``.
    """
    linear = np.asarray(linear, dtype=np.float64)
    return np.where(linear <= 0.0031308, 12.92 * linear,
                    1.055 * np.power(np.maximum(linear, 0.0031308), 1.0 / 2.4) - 0.055)


def _fspath(path: str | os.PathLike[str]) -> str:
    """Return a path argument as a str (OpenEXR accepts only str)."""
    try:
        return os.fsdecode(os.fspath(path))
    except TypeError as exc:
        raise ImageDataError(f"image path {path!r} is not a str or os.PathLike") from exc


def _as_float32_image(image: Any, path: str) -> np.ndarray:
    """Convert writer input to a float32 (H, W, C) array, checking its type and shape."""
    try:
        array = np.asarray(image)
    except Exception as exc:  # any failure of a foreign __array__ means "not an image"
        raise ImageDataError(
            f"image for {path!r}: cannot convert {type(image).__name__} to an array: {exc}"
        ) from exc
    if array.dtype.kind not in "biuf":
        raise ImageDataError(
            f"image for {path!r}: pixel type {array.dtype} is not real numeric data")
    if array.ndim == 2:
        array = array[:, :, np.newaxis]
    if array.ndim != 3:
        raise ImageDataError(
            f"image for {path!r}: shape {array.shape} is not (H, W) or (H, W, C)")
    if 0 in array.shape:
        raise ImageDataError(f"image for {path!r}: shape {array.shape} is empty")
    return array.astype(np.float32, copy=False)


def _channel_names(channels: Sequence[str] | None, count: int, path: str) -> list[str]:
    """Return the channel names for a C-channel image, checking what EXR can store."""
    if channels is None:
        if count not in DEFAULT_CHANNELS:
            raise ImageDataError(
                f"image for {path!r} has {count} channels; name them with `channels` "
                "(defaults exist only for 1, 3 and 4 channels)")
        return list(DEFAULT_CHANNELS[count])
    if isinstance(channels, (str, bytes)):
        raise ImageDataError(
            f"image for {path!r}: channels must be a list of names, not the string {channels!r}")
    names = list(channels)
    if len(names) != count:
        raise ImageDataError(
            f"image for {path!r} has {count} channels but {len(names)} names were given: "
            f"{names!r}")
    for name in names:
        if not isinstance(name, str) or not name or "\0" in name:
            raise ImageDataError(
                f"image for {path!r}: channel name {name!r} is not a non-empty string "
                "without NUL")
        if len(name.encode("utf-8")) > _MAX_CHANNEL_NAME_BYTES:
            raise ImageDataError(
                f"image for {path!r}: channel name {name[:40]!r}... is longer than "
                f"{_MAX_CHANNEL_NAME_BYTES} bytes")
    if len(set(names)) != len(names):
        raise ImageDataError(f"image for {path!r}: channel names {names!r} are not distinct")
    return names


def _stored_channel_order(header: dict, names: list[str]) -> list[str]:
    """Return the channel order recorded in the header, or R, G, B, A then sorted."""
    recorded = header.get(CHANNEL_ORDER_ATTRIBUTE)
    if (isinstance(recorded, list) and all(isinstance(n, str) for n in recorded)
            and len(recorded) == len(names) and set(recorded) == set(names)):
        return list(recorded)
    color = [n for n in _COLOR_CHANNELS if n in names]
    return color + sorted(n for n in names if n not in _COLOR_CHANNELS)
