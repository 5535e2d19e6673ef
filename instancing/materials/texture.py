"""Textures: spatially varying parameter values of materials, as Mitsuba's ``bitmap`` and
``checkerboard`` plugins define them, looked up at a hit's surface coordinates ``uv``.

A texture maps ``uv`` by its ``to_uv`` (a 2D affine map) and then:

* ``checkerboard``: ``color0`` where the fractional parts of u and v lie on the same side
  of 1/2, else ``color1`` (the other way round for a number parameter, as Mitsuba);
* ``bitmap``: the image's texels with their centres at ``(i + 1/2) / width``, row 0 at
  v = 0, interpolated bilinearly (``filter_type`` ``bilinear``) or taken nearest, indices
  outside the image wrapped (``wrap_mode`` ``repeat``, ``mirror`` or ``clamp``). 8-bit
  images are sRGB-encoded and decoded to linear values unless ``raw``, as Mitsuba reads
  them; a one-channel image is grey.

All textures of a scene are one :class:`TextureSet`: their texels one flat array, their
parameters one array per field over textures, so that a lane looks up its own texture
with gathers and any number of textures cost one kernel per texture type present.
A number parameter reads a colour texture's luminance (Mitsuba's ``eval_1``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..core.backend import Array2f, Array3f, Bool, Float, Int32, UInt32, device_array, dr
from ..core.errors import SceneError
from .parameter import check_keys

#: Texture types, and the keys each takes besides ``type``.
TEXTURE_KEYS = {
    "bitmap": {"filename", "filter_type", "wrap_mode", "raw", "to_uv"},
    "checkerboard": {"color0", "color1", "to_uv"},
}
FILTERS = ("bilinear", "nearest")
WRAPS = ("repeat", "mirror", "clamp")
#: Mitsuba's luminance weights of linear RGB (``luminance()``).
LUMINANCE = (0.212671, 0.715160, 0.072169)


@dataclass(frozen=True, eq=False)
class Texture:
    """A validated texture: its ``type``, ``to_uv`` (3x3, a 2D affine map in homogeneous
    coordinates), and for a bitmap its linear texels (H, W, 3) float32, filter and wrap
    mode, the resolved path of its file and ``raw``; for a checkerboard its two colours."""

    type: str
    to_uv: np.ndarray
    texels: np.ndarray | None = None
    filter: str = "bilinear"
    wrap: str = "repeat"
    filename: str = ""
    raw: bool = False
    color0: tuple[float, float, float] = (0.4, 0.4, 0.4)
    color1: tuple[float, float, float] = (0.2, 0.2, 0.2)

    @property
    def mean(self) -> float:
        """The mean value over the texture (Mitsuba's ``Texture::mean``: a bitmap's mean
        luminance; a checkerboard's two colours' means, half each)."""
        if self.type == "checkerboard":
            return 0.5 * (float(np.mean(self.color0)) + float(np.mean(self.color1)))
        return float(np.mean(self.texels.astype(np.float64) @ LUMINANCE))


def mean_value(value: Any) -> float:
    """The mean of a parameter value: a texture's, or a colour's or number's own."""
    return value.mean if isinstance(value, Texture) else float(np.mean(value))


def is_texture(value: Any) -> bool:
    """Whether a parameter value is a texture dict (``{"type": "bitmap", ...}``)."""
    return isinstance(value, dict)


def parse_texture(where: str, spec: dict, value_of: Callable[[Any, str], Any],
                  read_image: Callable[[str, bool], tuple[np.ndarray, str]] | None) -> Texture:
    """Validate a texture dict given for a parameter.

    Args:
        where: the parameter, for errors ("material 'floor': 'reflectance'").
        value_of: validates a checkerboard colour by the parameter's own rule (a number
            for a number parameter, stored as grey).
        read_image: given a bitmap's file name and ``raw``, its linear (H, W, 3) float32
            texels and the file's resolved path (None where the caller reads no files).
    """
    kind = spec.get("type")
    if not isinstance(kind, str) or kind not in TEXTURE_KEYS:
        raise SceneError(f"{where}: unknown texture type {kind!r}; supported types are "
                         f"{list(TEXTURE_KEYS)}")
    check_keys(where, kind, spec, {"type", *TEXTURE_KEYS[kind]}, what="texture")
    to_uv = _to_uv(where, spec.get("to_uv"))
    if kind == "checkerboard":
        colors = [tuple(float(c) for c in np.broadcast_to(value_of(spec.get(key, default),
                                                                   f"{where}.{key}"), 3))
                  for key, default in (("color0", 0.4), ("color1", 0.2))]
        return Texture(kind, to_uv, color0=colors[0], color1=colors[1])
    filename = spec.get("filename")
    if not isinstance(filename, str) or not filename:
        raise SceneError(f"{where}: a bitmap texture needs a 'filename'")
    choice = {"filter_type": (FILTERS, "bilinear"), "wrap_mode": (WRAPS, "repeat")}
    picked = {}
    for key, (allowed, default) in choice.items():
        value = spec.get(key, default)
        if not isinstance(value, str) or value.lower() not in allowed:
            raise SceneError(f"{where}.{key} must be one of {list(allowed)}, got {value!r}")
        picked[key] = value.lower()
    raw = spec.get("raw", False)
    if not isinstance(raw, bool):
        raise SceneError(f"{where}.raw must be true or false, got {raw!r}")
    if read_image is None:
        raise SceneError(f"{where}: a bitmap texture needs a scene that reads files")
    texels, path = read_image(filename, raw)
    return Texture(kind, to_uv, texels, picked["filter_type"], picked["wrap_mode"], path, raw)


def _to_uv(where: str, value: Any) -> np.ndarray:
    """``to_uv`` as a 3x3 homogeneous 2D map: absent (identity), a 3x3 matrix, or the 4x4
    transform Mitsuba takes (its x and y rows and columns and translation)."""
    if value is None:
        return np.eye(3)
    m = np.asarray(value, np.float64) if _is_matrix(value) else None
    if m is not None and m.shape == (4, 4):
        m = m[np.ix_([0, 1, 3], [0, 1, 3])]
    if m is None or m.shape != (3, 3) or not np.isfinite(m).all() or np.any(m[2] != (0, 0, 1)):
        raise SceneError(f"{where}.to_uv must be a 3x3 affine matrix (last row 0 0 1) or a "
                         f"4x4 transform, got {value!r}")
    return m


def _is_matrix(value: Any) -> bool:
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        return False
    return array.ndim == 2


class TextureSet:
    """The scene's textures as device arrays, looked up per lane (module docstring)."""

    def __init__(self, textures: list[Texture]):
        self.textures = textures
        self.kinds = sorted({t.type for t in textures})
        rows = [t.to_uv[:2].ravel() for t in textures]
        self.to_uv = [device_array(Float, np.array([r[k] for r in rows], np.float32))
                      for k in range(6)]
        self.is_bitmap = device_array(UInt32, np.array([t.type == "bitmap" for t in textures],
                                                       np.uint32))
        #: Each texture's two checkerboard colours, (T, 2, 3) on the host, and as color0, color1.
        self.host_colors = np.array([[t.color0, t.color1] for t in textures], np.float32)
        self._upload_colors()
        bitmaps = [t for t in textures if t.type == "bitmap"]
        sizes = [t.texels.shape[:2] if t.type == "bitmap" else (1, 1) for t in textures]
        offsets = np.cumsum([0] + [h * w for h, w in sizes])[:-1]
        self.sizes, self.offsets = sizes, offsets
        self.height = device_array(UInt32, np.array([s[0] for s in sizes], np.uint32))
        self.width = device_array(UInt32, np.array([s[1] for s in sizes], np.uint32))
        self.offset = device_array(UInt32, offsets.astype(np.uint32))
        self.wrap = device_array(UInt32, np.array([WRAPS.index(t.wrap) for t in textures], np.uint32))
        self.nearest = device_array(UInt32, np.array([t.filter == "nearest" for t in textures],
                                                     np.uint32))
        #: Every bitmap's texels, one after another (a checkerboard holds one texel of 0).
        self.host_texels = np.concatenate([t.texels.reshape(-1, 3) if t.type == "bitmap"
                                           else np.zeros((1, 3), np.float32)
                                           for t in textures]).astype(np.float32)
        self.texels = device_array(Float, self.host_texels.ravel())
        self.has_bitmaps = bool(bitmaps)
        self.has_checkerboards = any(t.type == "checkerboard" for t in textures)

    def texel_range(self, texture: int) -> tuple[int, tuple[int, int]]:
        """Where bitmap ``texture``'s texels start in :attr:`texels` (in floats) and its
        (height, width)."""
        return 3 * int(self.offsets[texture]), self.sizes[texture]

    def texels_of(self, texture: int) -> np.ndarray:
        """The (H, W, 3) float32 texels of bitmap ``texture`` as stored."""
        start, (h, w) = self.texel_range(texture)
        return self.host_texels[start // 3:start // 3 + h * w].reshape(h, w, 3).copy()

    def set_texels(self, texture: int, texels: np.ndarray) -> None:
        """Replace the texels of bitmap ``texture`` ((H, W, 3), the same size)."""
        start, (h, w) = self.texel_range(texture)
        self.host_texels[start // 3:start // 3 + h * w] = np.reshape(texels, (h * w, 3))
        self.texels = device_array(Float, self.host_texels.ravel())

    def _upload_colors(self) -> None:
        self.color0, self.color1 = (Array3f(*(device_array(Float, self.host_colors[:, k, c])
                                              for c in range(3))) for k in range(2))

    def set_color(self, texture: int, field: str, rgb) -> None:
        """Replace checkerboard ``texture``'s ``field`` ("color0" or "color1")."""
        self.host_colors[texture, ("color0", "color1").index(field)] = rgb
        self._upload_colors()

    def eval(self, texture: UInt32, uv: Array2f, active: Bool, number: bool = False) -> Array3f:
        """Each active lane's texture at its surface coordinates (0 elsewhere), for a colour
        parameter or a ``number`` one (see the checkerboard's parity below)."""
        u, v = self._mapped(texture, uv, active)
        value = Array3f(0.0)
        if self.has_checkerboards:
            # Mitsuba's checkerboard gives a number parameter color0 on the squares where
            # it gives a colour parameter color1 (its eval_1 tests the opposite parity of
            # its eval); renders follow Mitsuba.
            same = (u - dr.floor(u) > 0.5) == (v - dr.floor(v) > 0.5)
            if number:
                same = ~same
            value = dr.select(same, dr.gather(Array3f, self.color0, texture, active),
                              dr.gather(Array3f, self.color1, texture, active))
        if self.has_bitmaps:
            bitmap = dr.gather(UInt32, self.is_bitmap, texture, active) != 0
            (c00, c10, c01, c11), fx, fy, _ = self._footprint(texture, u, v, active & bitmap)
            top, bottom = dr.fma(c10 - c00, fx, c00), dr.fma(c11 - c01, fx, c01)
            value = dr.select(bitmap, dr.fma(bottom - top, fy, top), value)
        return value

    def gradient(self, texture: UInt32, uv: Array2f, active: Bool) -> Array2f:
        """Each active lane's bitmap's derivatives of its luminance by (u, v), as Mitsuba's
        ``eval_1_grad``: of the bilinear interpolation in texel coordinates, mapped by the
        transpose of ``to_uv``'s linear part and then scaled by the bitmap's width and
        height (in that order, as Mitsuba's); 0 for nearest lookups and checkerboards."""
        u, v = self._mapped(texture, uv, active)
        bitmap = active & (dr.gather(UInt32, self.is_bitmap, texture, active) != 0)
        corners, fx, fy, nearest = self._footprint(texture, u, v, bitmap)
        f00, f10, f01, f11 = (luminance(c) for c in corners)
        dx = dr.fma(1.0 - fy, f10 - f00, fy * (f11 - f01))
        dy = dr.fma(1.0 - fx, f01 - f00, fx * (f11 - f10))
        m = [dr.gather(Float, a, texture, bitmap) for a in self.to_uv]
        size = [Float(dr.gather(UInt32, a, texture, bitmap)) for a in (self.width, self.height)]
        du = size[0] * dr.fma(m[0], dx, m[3] * dy)
        dv = size[1] * dr.fma(m[1], dx, m[4] * dy)
        smooth = bitmap & ~nearest
        return Array2f(dr.select(smooth, du, 0.0), dr.select(smooth, dv, 0.0))

    def _mapped(self, texture: UInt32, uv: Array2f, active: Bool) -> tuple[Float, Float]:
        """The surface coordinates mapped by each lane's texture's ``to_uv``."""
        m = [dr.gather(Float, a, texture, active) for a in self.to_uv]
        return (dr.fma(m[0], uv.x, dr.fma(m[1], uv.y, m[2])),
                dr.fma(m[3], uv.x, dr.fma(m[4], uv.y, m[5])))

    def _footprint(self, texture: UInt32, u: Float, v: Float, active: Bool):
        """The four texels a bilinear (or nearest) lookup at (u, v) reads, texel centres at
        ((i + 1/2) / width, ...), indices wrapped by the texture's mode: ((c00, c10, c01,
        c11), fx, fy, nearest), c_ij the texel i columns right and j rows down of the first,
        fx and fy the interpolation weights (0 for nearest lookups)."""
        width = dr.gather(UInt32, self.width, texture, active)
        height = dr.gather(UInt32, self.height, texture, active)
        offset = dr.gather(UInt32, self.offset, texture, active)
        wrap = dr.gather(UInt32, self.wrap, texture, active)
        nearest = dr.gather(UInt32, self.nearest, texture, active) != 0
        # Texel coordinates, texel centres at half-integers (shifted for bilinear weights).
        x = dr.select(nearest, u * Float(width), dr.fma(u, Float(width), -0.5))
        y = dr.select(nearest, v * Float(height), dr.fma(v, Float(height), -0.5))
        x0, y0 = dr.floor(x), dr.floor(y)
        fx = dr.select(nearest, 0.0, x - x0)
        fy = dr.select(nearest, 0.0, y - y0)
        i0, j0 = Int32(x0), Int32(y0)
        columns = [_wrapped(i, Int32(width), wrap) for i in (i0, i0 + 1)]
        rows = [_wrapped(j, Int32(height), wrap) for j in (j0, j0 + 1)]

        def texel(i, j):
            return dr.gather(Array3f, self.texels, offset + UInt32(j) * width + UInt32(i), active)

        return ((texel(columns[0], rows[0]), texel(columns[1], rows[0]), texel(columns[0], rows[1]),
                 texel(columns[1], rows[1])), fx, fy, nearest)


def _wrapped(i: Int32, size: Int32, wrap: UInt32) -> Int32:
    """Texel index i folded into [0, size) by the wrap mode (``WRAPS`` order)."""
    size = dr.maximum(size, 1)  # inactive lanes read size 0: no integer division by it
    period = dr.select(wrap == WRAPS.index("mirror"), 2 * size, size)
    m = i % period
    m = dr.select(m < 0, m + period, m)
    mirrored = dr.select(m >= size, period - 1 - m, m)
    clamped = dr.clip(i, 0, size - 1)
    return dr.select(wrap == WRAPS.index("clamp"), clamped,
                     dr.select(wrap == WRAPS.index("mirror"), mirrored, m))


def luminance(rgb: Array3f) -> Float:
    """Mitsuba's luminance of linear RGB (a number parameter's value of a colour texture)."""
    return dr.fma(rgb.x, LUMINANCE[0], dr.fma(rgb.y, LUMINANCE[1], rgb.z * LUMINANCE[2]))
