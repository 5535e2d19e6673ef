"""Mitsuba's binary volume grid files (``.vol``, read by its ``gridvolume`` plugin).

Layout (little-endian): the bytes ``VOL`` and the version 3; the encoding (int32, 1: float32);
the cell counts along x, y and z and the channel count (int32 each); the grid's bounding box
(6 float32: x, y, z min, then max); then the values, x fastest, then y, then z, channels
innermost: ``data[((z * yres + y) * xres + x) * channels + c]``.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass

import numpy as np

from .image import ImageFileError

_HEADER = struct.Struct("<3sBiiiii6f")
#: Channel counts a grid read as a texture may hold (one: grey, three: a colour).
TEXTURE_CHANNELS = (1, 3)


@dataclass(frozen=True)
class VolumeGrid:
    """A grid's values (z, y, x, channels) float32 and its bounding box (lo, hi)."""

    values: np.ndarray
    bounds: tuple[np.ndarray, np.ndarray]


def read_volume_grid(path: str | os.PathLike[str]) -> VolumeGrid:
    """Read a ``.vol`` file (module docstring).

    Raises:
        ImageFileError: the file is missing or unreadable, not a version-3 float32 grid, of
            another channel count than 1 or 3, truncated or longer than its header says, or
            holds a value or bound that is not finite.
    """
    where = f"volume grid file '{os.fspath(path)}'"
    try:
        with open(path, "rb") as stream:
            data = stream.read()
    except FileNotFoundError:
        raise ImageFileError(f"{where} not found") from None
    except OSError as exc:
        raise ImageFileError(f"{where} cannot be read ({exc.strerror or exc})") from None
    if len(data) < _HEADER.size:
        raise ImageFileError(f"{where} is too short for a volume grid header")
    magic, version, encoding, xres, yres, zres, channels, *box = _HEADER.unpack_from(data)
    if magic != b"VOL" or version != 3:
        raise ImageFileError(f"{where} is not a version-3 Mitsuba volume grid (starts with "
                             f"{data[:4]!r})")
    if encoding != 1:
        raise ImageFileError(f"{where}: encoding {encoding} is not supported (1: float32 is)")
    if min(xres, yres, zres) <= 0:
        raise ImageFileError(f"{where}: the cell counts {[xres, yres, zres]} must be positive")
    if channels not in TEXTURE_CHANNELS:
        raise ImageFileError(f"{where}: {channels} channels; a volume texture reads 1 or 3")
    count = xres * yres * zres * channels
    if len(data) != _HEADER.size + 4 * count:
        raise ImageFileError(f"{where}: holds {len(data) - _HEADER.size} bytes of values, its "
                             f"header says {4 * count} ({xres} x {yres} x {zres} x {channels} "
                             "float32)")
    values = np.frombuffer(data, "<f4", count, _HEADER.size).reshape(zres, yres, xres, channels)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise ImageFileError(f"{where}: {bad.size} values are not finite (the first at flat "
                             f"index {bad[0]})")
    lo, hi = np.array(box[:3], np.float64), np.array(box[3:], np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ImageFileError(f"{where}: the bounding box {box} is not finite")
    return VolumeGrid(values.astype(np.float32), (lo, hi))
