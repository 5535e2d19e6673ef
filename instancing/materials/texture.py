"""Textures: spatially varying parameter values of materials, as Mitsuba's ``bitmap``,
``checkerboard``, ``mesh_attribute`` and ``volume`` plugins define them, looked up at a hit's
surface coordinates ``uv`` (the first two), on its triangle (the third) or at its point in
space (the last).

A texture maps ``uv`` by its ``to_uv`` (a 2D affine map) and then:

* ``checkerboard``: ``color0`` where the fractional parts of u and v lie on the same side
  of 1/2, else ``color1`` (the other way round for a number parameter, as Mitsuba);
* ``bitmap``: the image's texels with their centres at ``(i + 1/2) / width``, row 0 at
  v = 0, interpolated bilinearly (``filter_type`` ``bilinear``) or taken nearest, indices
  outside the image wrapped (``wrap_mode`` ``repeat``, ``mirror`` or ``clamp``). 8-bit
  images are sRGB-encoded and decoded to linear values unless ``raw``, as Mitsuba reads
  them; a one-channel image is grey;
* ``mesh_attribute``: the hit mesh's attribute ``name`` (read from its file, see
  :func:`~instancing.io.mesh_file.read_ply`) times ``scale``: a ``vertex_`` attribute
  interpolated with the hit's barycentrics, a ``face_`` one constant over each face; a
  one-value attribute is grey. Looked up at a :class:`LookupPoint`, which the scene builds
  where some material reads one; the scene checks that every instance with such a material
  is a mesh that has the attribute (``instancing.scene.scene``);
* ``volume``: a ``gridvolume``'s values (a ``.vol`` file's grid, 1 or 3 channels, read by
  :mod:`instancing.io.volume_grid`) at the hit's point mapped by the inverse of the volume's
  ``to_world`` into the unit cube (the grid's own bounding box first, with
  ``use_grid_bbox``), cell centres at ``(i + 1/2) / res``, interpolated trilinearly or taken
  nearest, indices outside wrapped (``clamp`` by default, ``repeat``, ``mirror``); or a
  ``constvolume``'s ``value`` (a number or colour), held as a grid of one cell, whose unit
  cube under ``to_world`` bounds a medium as a grid's does.

All textures of a scene are one :class:`TextureSet`: their texels one flat array, their
parameters one array per field over textures, so that a lane looks up its own texture
with gathers and any number of textures cost one kernel per texture type present.
A number parameter reads a colour texture's luminance (Mitsuba's ``eval_1``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..core.backend import Array2f, Array3f, Bool, Float, Int32, UInt32, device_array, dr
from ..core.errors import SceneError
from ..core.transform_spec import parse_transform
from .parameter import check_keys

#: Texture types, and the keys each takes besides ``type``.
TEXTURE_KEYS = {
    "bitmap": {"filename", "filter_type", "wrap_mode", "raw", "to_uv"},
    "checkerboard": {"color0", "color1", "to_uv"},
    "mesh_attribute": {"name", "scale"},
    "volume": {"volume"},
}
#: A volume texture's volume types and the keys of each (Mitsuba's plugins'), and the
#: filters of a grid.
VOLUME_KEYS = {
    "gridvolume": {"type", "filename", "filter_type", "wrap_mode", "raw", "to_world", "use_grid_bbox"},
    "constvolume": {"type", "value", "to_world"}}
VOLUME_FILTERS = ("trilinear", "nearest")
#: How a mesh attribute's name starts: a value per vertex, or per face.
ATTRIBUTE_KINDS = ("vertex_", "face_")
FILTERS = ("bilinear", "nearest")
WRAPS = ("repeat", "mirror", "clamp")
#: Linear sRGB (Rec. 709 primaries, D65 white) to CIE XYZ, the rows of X, Y and Z, as
#: Mitsuba's ``srgb_to_xyz``.
SRGB_TO_XYZ = ((0.412453, 0.357580, 0.180423),
               (0.212671, 0.715160, 0.072169),
               (0.019334, 0.119193, 0.950227))
#: Mitsuba's luminance weights of linear RGB (``luminance()``): the Y row.
LUMINANCE = SRGB_TO_XYZ[1]


@dataclass(frozen=True, eq=False)
class Texture:
    """A validated texture: its ``type``, ``to_uv`` (3x3, a 2D affine map in homogeneous
    coordinates), and for a bitmap its linear texels (H, W, 3) float32, filter and wrap
    mode, the resolved path of its file (empty once its texels changed) and ``raw``; for a
    checkerboard its two colours; for
    a mesh attribute the attribute's name and the scale; for a volume its grid (Z, Y, X, 3)
    float32 as ``texels`` and ``to_local``, the 4x4 map from world space to the grid's unit
    cube."""

    type: str
    to_uv: np.ndarray
    texels: np.ndarray | None = None
    filter: str = "bilinear"
    wrap: str = "repeat"
    filename: str = ""
    raw: bool = False
    color0: tuple[float, float, float] = (0.4, 0.4, 0.4)
    color1: tuple[float, float, float] = (0.2, 0.2, 0.2)
    attribute: str = ""
    scale: float = 1.0
    to_local: np.ndarray | None = None

    def with_texels(self, texels: np.ndarray) -> "Texture":
        """This bitmap with other texels ((H, W, 3) float32, linear), which no file holds: its
        ``filename`` is then empty."""
        return dataclasses.replace(self, texels=np.asarray(texels, np.float32), filename="")

    @property
    def mean(self) -> float:
        """The mean value over the texture (Mitsuba's ``Texture::mean``: a bitmap's mean
        luminance; a checkerboard's two colours' means, half each). A mesh attribute has
        none (it depends on the mesh): SceneError, as Mitsuba's plugin refuses."""
        if self.type in ("mesh_attribute", "volume"):
            raise SceneError(f"a {self.type} texture has no mean value (it depends on where "
                             "it is read); Mitsuba's plugin has none either")
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
                  read_image: Callable[..., tuple[Any, str]] | None) -> Texture:
    """Validate a texture dict given for a parameter.

    Args:
        where: the parameter, for errors ("material 'floor': 'reflectance'").
        value_of: validates a checkerboard colour by the parameter's own rule (a number
            for a number parameter, stored as grey).
        read_image: given a bitmap's file name and ``raw``, its linear (H, W, 3) float32
            texels and the file's resolved path; with ``volume=True``, a grid's values
            (Z, Y, X, C) and bounding box (lo, hi) instead (None where the caller reads no
            files).
    """
    kind = spec.get("type")
    if not isinstance(kind, str) or kind not in TEXTURE_KEYS:
        raise SceneError(f"{where}: unknown texture type {kind!r}; supported types are "
                         f"{list(TEXTURE_KEYS)}")
    check_keys(where, kind, spec, {"type", *TEXTURE_KEYS[kind]}, what="texture")
    to_uv = _to_uv(where, spec.get("to_uv"))
    if kind == "mesh_attribute":
        name = spec.get("name")
        if not isinstance(name, str) or not name.startswith(ATTRIBUTE_KINDS):
            raise SceneError(f"{where}: a mesh_attribute texture needs a 'name' starting with "
                             f"'vertex_' or 'face_', got {name!r}")
        scale = spec.get("scale", 1.0)
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale):
            raise SceneError(f"{where}.scale must be a finite number, got {scale!r}")
        return Texture(kind, to_uv, attribute=name, scale=float(scale))
    if kind == "volume":
        return _parse_volume(where, spec.get("volume"), value_of, read_image)
    if kind == "checkerboard":
        colors = [tuple(float(c) for c in np.broadcast_to(value_of(spec.get(key, default),
                                                                   f"{where}.{key}"), 3))
                  for key, default in (("color0", 0.4), ("color1", 0.2))]
        return Texture(kind, to_uv, color0=colors[0], color1=colors[1])
    filename, picked = _file_and_modes(where, "a bitmap texture", spec, FILTERS, "repeat")
    raw = spec.get("raw", False)
    if not isinstance(raw, bool):
        raise SceneError(f"{where}.raw must be true or false, got {raw!r}")
    if read_image is None:
        raise SceneError(f"{where}: a bitmap texture needs a scene that reads files")
    texels, path = read_image(filename, raw)
    return Texture(kind, to_uv, texels, picked["filter_type"], picked["wrap_mode"], path, raw)


def _file_and_modes(where: str, what: str, spec: dict, filters: tuple[str, ...],
                    wrap: str) -> tuple[str, dict[str, str]]:
    """A bitmap's or grid's file name and its ``filter_type`` (one of ``filters``, the first
    by default) and ``wrap_mode`` (``wrap`` by default), lower case."""
    filename = spec.get("filename")
    if not isinstance(filename, str) or not filename:
        raise SceneError(f"{where}: {what} needs a 'filename'")
    picked = {}
    for key, (allowed, default) in {"filter_type": (filters, filters[0]),
                                    "wrap_mode": (WRAPS, wrap)}.items():
        value = spec.get(key, default)
        if not isinstance(value, str) or value.lower() not in allowed:
            raise SceneError(f"{where}.{key} must be one of {list(allowed)}, got {value!r}")
        picked[key] = value.lower()
    return filename, picked


def _parse_volume(where: str, spec: Any, value_of: Callable[[Any, str], Any], read_image) -> Texture:
    """A ``volume`` texture's ``gridvolume`` or ``constvolume`` (module docstring): a grid
    read by ``read_image(filename, raw, volume=True)`` as (values (Z, Y, X, C), (lo, hi)),
    path; a constant's ``value`` checked by ``value_of``, as a texture's colours are."""
    where = f"{where}.volume"
    kind = spec.get("type") if isinstance(spec, dict) else None
    if kind not in VOLUME_KEYS:
        raise SceneError(f"{where}: a volume texture holds a 'gridvolume' (a dict with its "
                         f"'filename') or a 'constvolume' (with its 'value'), got "
                         f"{kind if isinstance(spec, dict) else spec!r}")
    check_keys(where, kind, spec, VOLUME_KEYS[kind], what="volume")
    to_world = np.asarray(spec.get("to_world", np.eye(4)), np.float64) if _is_matrix(
        spec.get("to_world", np.eye(4))) else None
    if to_world is None or to_world.shape != (4, 4) or not np.isfinite(to_world).all() or \
            np.any(to_world[3] != (0, 0, 0, 1)) or abs(np.linalg.det(to_world[:3, :3])) == 0:
        raise SceneError(f"{where}.to_world must be an invertible 4x4 affine matrix, got "
                         f"{spec.get('to_world')!r}")
    to_local = np.linalg.inv(to_world)
    if kind == "constvolume":
        value = np.broadcast_to(np.asarray(value_of(spec.get("value", 1.0), f"{where}.value"),
                                           np.float32), 3)
        return Texture("volume", np.eye(3), value.reshape(1, 1, 1, 3).copy(), "nearest", "clamp",
                       to_local=to_local)
    filename, picked = _file_and_modes(where, "a gridvolume", spec, VOLUME_FILTERS, "clamp")
    flags = {}
    for key in ("raw", "use_grid_bbox"):
        flags[key] = spec.get(key, False)
        if not isinstance(flags[key], bool):
            raise SceneError(f"{where}.{key} must be true or false, got {flags[key]!r}")
    if read_image is None:
        raise SceneError(f"{where}: a gridvolume needs a scene that reads files")
    (values, (lo, hi)), path = read_image(filename, flags["raw"], volume=True)
    if flags["use_grid_bbox"]:
        if np.any(hi <= lo):
            raise SceneError(f"{where}: use_grid_bbox with an empty bounding box {lo.tolist()} - "
                             f"{hi.tolist()} in its file")
        to_local = np.diag([*(1.0 / (hi - lo)), 1.0]) @ np.vstack(
            [np.hstack([np.eye(3), -lo[:, None]]), [0, 0, 0, 1]]) @ to_local
    grid = np.repeat(values, 3, axis=3) if values.shape[3] == 1 else values
    return Texture("volume", np.eye(3), grid.astype(np.float32), picked["filter_type"],
                   picked["wrap_mode"], path, flags["raw"], to_local=to_local)


def _to_uv(where: str, value: Any) -> np.ndarray:
    """``to_uv`` as a 3x3 homogeneous 2D map: absent (identity), a 3x3 matrix, or the 4x4
    transform Mitsuba takes, as a matrix or a list of operations like ``to_world``'s (its x
    and y rows and columns and translation)."""
    if value is None:
        return np.eye(3)
    if isinstance(value, (list, tuple)) and value and all(isinstance(op, dict) for op in value):
        value = parse_transform(value, f"{where}.to_uv").to_numpy()[0]
    m = np.asarray(value, np.float64) if _is_matrix(value) else None
    if m is not None and m.shape == (4, 4):
        m = m[np.ix_([0, 1, 3], [0, 1, 3])]
    if m is None or m.shape != (3, 3) or not np.isfinite(m).all() or np.any(m[2] != (0, 0, 1)):
        raise SceneError(f"{where}.to_uv must be a 3x3 affine matrix (last row 0 0 1), a "
                         f"4x4 transform or a list of operations, got {value!r}")
    return m


def _is_matrix(value: Any) -> bool:
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        return False
    return array.ndim == 2


@dataclass(frozen=True)
class LookupPoint:
    """Where a texture is looked up in a scene whose materials read mesh attributes or
    volumes: the hit's surface coordinates, its triangle (the position in the scene's mesh
    library) and its barycentrics (b1, b2) on that triangle, and its point (rendering
    space)."""

    uv: Array2f
    triangle: UInt32
    prim_uv: Array2f
    p: Array3f


#: What textures are looked up at: the surface coordinates, or a :class:`LookupPoint`.
Coordinates = Array2f | LookupPoint


def surface_uv(point: Coordinates) -> Array2f:
    """The surface coordinates of a lookup point."""
    return point.uv if isinstance(point, LookupPoint) else point


class TextureSet:
    """The scene's textures as device arrays, looked up per lane (module docstring).

    Args:
        textures: the scene's textures.
        attributes: given an attribute name, its values at the corners of every triangle of
            the scene's meshes, (T, 3, 3) float32 (:meth:`MeshLibrary.attribute_corners`);
            needed where some texture is a mesh attribute.
        origin: the world point at the origin of rendering space (volumes are looked up at
            rendering-space points).
    """

    def __init__(self, textures: list[Texture],
                 attributes: Callable[[str], np.ndarray] | None = None,
                 origin: np.ndarray | None = None):
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
        # (depth, height, width) of each texture's texels: a bitmap's one layer, a volume's
        # grid, one texel of 0 for the others.
        shapes = [t.texels.shape[:3] if t.type == "volume" else (1, *t.texels.shape[:2])
                  if t.type == "bitmap" else (1, 1, 1) for t in textures]
        sizes = [s[1:] for s in shapes]
        offsets = np.cumsum([0] + [int(np.prod(s)) for s in shapes])[:-1]
        self.sizes, self.offsets = sizes, offsets
        self.height = device_array(UInt32, np.array([s[0] for s in sizes], np.uint32))
        self.width = device_array(UInt32, np.array([s[1] for s in sizes], np.uint32))
        self.offset = device_array(UInt32, offsets.astype(np.uint32))
        self.wrap = device_array(UInt32, np.array([WRAPS.index(t.wrap) for t in textures], np.uint32))
        self.nearest = device_array(UInt32, np.array([t.filter == "nearest" for t in textures],
                                                     np.uint32))
        #: Every bitmap's and volume's texels, one after another (other textures hold one
        #: texel of 0).
        self.host_texels = np.concatenate([t.texels.reshape(-1, 3) if t.type in ("bitmap", "volume")
                                           else np.zeros((1, 3), np.float32)
                                           for t in textures]).astype(np.float32)
        self.texels = device_array(Float, self.host_texels.ravel())
        self.has_bitmaps = bool(bitmaps)
        self.has_checkerboards = any(t.type == "checkerboard" for t in textures)
        #: The attribute names that mesh_attribute textures read, and per texture its
        #: attribute's start in :attr:`attributes` (in corner values), its scale and
        #: whether it is a face attribute.
        self.attribute_names = sorted({t.attribute for t in textures if t.type == "mesh_attribute"})
        self.has_attributes = bool(self.attribute_names)
        if self.has_attributes:
            if attributes is None:
                raise SceneError("a mesh_attribute texture needs a scene with meshes")
            self.set_attributes(attributes)
            named = [self.attribute_names.index(t.attribute) if t.type == "mesh_attribute" else 0
                     for t in textures]
            self.attribute_start = device_array(UInt32, np.array(named, np.uint32) * self.corner_count)
            self.is_attribute = device_array(UInt32, np.array(
                [t.type == "mesh_attribute" for t in textures], np.uint32))
            self.is_face = device_array(UInt32, np.array(
                [t.attribute.startswith("face_") for t in textures], np.uint32))
            self.attribute_scale = device_array(Float, np.array([t.scale for t in textures], np.float32))
        #: Volumes: per texture whether it is one, its grid's depth, and the rows of its map
        #: from rendering space to the grid's unit cube (12 arrays, row-major 3x4).
        self.has_volumes = any(t.type == "volume" for t in textures)
        if self.has_volumes:
            shift = np.eye(4)
            shift[:3, 3] = np.zeros(3) if origin is None else origin
            maps = [(t.to_local @ shift)[:3] if t.type == "volume" else np.zeros((3, 4)) for t in textures]
            self.to_local = [device_array(Float, np.array([m[r, c] for m in maps], np.float32))
                             for r in range(3) for c in range(4)]
            self.depth = device_array(UInt32, np.array([s[0] for s in shapes], np.uint32))
            self.is_volume = device_array(UInt32, np.array([t.type == "volume" for t in textures],
                                                           np.uint32))

    def set_attributes(self, attributes: Callable[[str], np.ndarray]) -> None:
        """Upload the attributes the textures read: per name, its values at every triangle's
        corners (``attributes(name)``, (T, 3, 3)), one name's table after another."""
        tables = [attributes(name) for name in self.attribute_names]
        #: Corner values per attribute name (3 per triangle of the scene's meshes).
        self.corner_count = tables[0].shape[0] * 3
        self.attributes = device_array(Float, np.concatenate(tables).ravel())

    def attribute_offset(self, name: str) -> int:
        """Where attribute ``name``'s table starts in :attr:`attributes`, in floats."""
        return 3 * self.attribute_names.index(name) * self.corner_count

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

    def eval(self, texture: UInt32, point: Coordinates, active: Bool, number: bool = False) -> Array3f:
        """Each active lane's texture at its lookup point (0 elsewhere), for a colour
        parameter or a ``number`` one (see the checkerboard's parity below)."""
        u, v = self._mapped(texture, surface_uv(point), active)
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
        if self.has_attributes:
            value = self._attribute(texture, point, active, value)
        if self.has_volumes:
            value = self._volume(texture, point, active, value)
        return value

    def _volume(self, texture: UInt32, point: Coordinates, active: Bool, value: Array3f) -> Array3f:
        """``value``, but on the lanes whose texture is a volume its grid's value at the
        hit's point, interpolated trilinearly between the eight cells around it (or the cell
        holding it, for nearest lookups), indices wrapped by the texture's mode."""
        if not isinstance(point, LookupPoint):
            raise ValueError("a volume texture is looked up without the hit's point")
        mine = active & (dr.gather(UInt32, self.is_volume, texture, active) != 0)
        m = [dr.gather(Float, a, texture, mine) for a in self.to_local]
        p = point.p
        unit = [dr.fma(m[4 * r], p.x, dr.fma(m[4 * r + 1], p.y, dr.fma(m[4 * r + 2], p.z, m[4 * r + 3])))
                for r in range(3)]
        sizes = [dr.gather(UInt32, a, texture, mine) for a in (self.width, self.height, self.depth)]
        offset = dr.gather(UInt32, self.offset, texture, mine)
        wrap = dr.gather(UInt32, self.wrap, texture, mine)
        nearest = dr.gather(UInt32, self.nearest, texture, mine) != 0
        axes = [_along(u, n, nearest, wrap) for u, n in zip(unit, sizes)]
        index = [a[0] for a in axes]
        weights = [a[1] for a in axes]

        def cell(i, j, k):
            flat = (UInt32(index[2][k]) * sizes[1] + UInt32(index[1][j])) * sizes[0] + UInt32(index[0][i])
            return dr.gather(Array3f, self.texels, offset + flat, mine)

        wx, wy, wz = weights
        layers = []
        for k in (0, 1):
            rows = [dr.fma(cell(1, j, k) - cell(0, j, k), wx, cell(0, j, k)) for j in (0, 1)]
            layers.append(dr.fma(rows[1] - rows[0], wy, rows[0]))
        return dr.select(mine, dr.fma(layers[1] - layers[0], wz, layers[0]), value)

    def _attribute(self, texture: UInt32, point: Coordinates, active: Bool, value: Array3f) -> Array3f:
        """``value``, but on the lanes whose texture is a mesh attribute its value on the
        hit triangle: a vertex attribute interpolated at the barycentrics (Mitsuba's order of
        operations), a face attribute its triangle's own, times the texture's scale."""
        if not isinstance(point, LookupPoint):
            raise ValueError("a mesh_attribute texture is looked up without the hit's triangle")
        mine = active & (dr.gather(UInt32, self.is_attribute, texture, active) != 0)
        start = dr.gather(UInt32, self.attribute_start, texture, mine) + point.triangle * 3
        c0, c1, c2 = (dr.gather(Array3f, self.attributes, start + k, mine) for k in range(3))
        face = dr.gather(UInt32, self.is_face, texture, mine) != 0
        b1 = dr.select(face, 0.0, point.prim_uv.x)
        b2 = dr.select(face, 0.0, point.prim_uv.y)
        interpolated = dr.fma(c0, 1.0 - b1 - b2, dr.fma(c1, b1, c2 * b2))
        scale = dr.gather(Float, self.attribute_scale, texture, mine)
        return dr.select(mine, interpolated * scale, value)

    def gradient(self, texture: UInt32, point: Coordinates, active: Bool) -> Array2f:
        """Each active lane's bitmap's derivatives of its luminance by (u, v), as Mitsuba's
        ``eval_1_grad``: of the bilinear interpolation in texel coordinates, mapped by the
        transpose of ``to_uv``'s linear part and then scaled by the bitmap's width and
        height (in that order, as Mitsuba's); 0 for nearest lookups and checkerboards."""
        u, v = self._mapped(texture, surface_uv(point), active)
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
        columns, fx = _along(u, width, nearest, wrap)
        rows, fy = _along(v, height, nearest, wrap)

        def texel(i, j):
            return dr.gather(Array3f, self.texels, offset + UInt32(j) * width + UInt32(i), active)

        return ((texel(columns[0], rows[0]), texel(columns[1], rows[0]), texel(columns[0], rows[1]),
                 texel(columns[1], rows[1])), fx, fy, nearest)


def _along(u: Float, size: UInt32, nearest: Bool, wrap: UInt32) -> tuple[list[Int32], Float]:
    """Along one axis of ``size`` texels (or cells), centres at half-integers: the two
    indices a lookup at ``u`` in [0, 1] reads, wrapped by the mode, and the weight of the
    second (0 for nearest lookups, which read the texel holding u)."""
    x = dr.select(nearest, u * Float(size), dr.fma(u, Float(size), -0.5))
    first = dr.floor(x)
    return ([_wrapped(Int32(first) + k, Int32(size), wrap) for k in (0, 1)],
            dr.select(nearest, 0.0, x - first))


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
