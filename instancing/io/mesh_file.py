"""Triangle mesh readers for Wavefront OBJ, Stanford PLY and Mitsuba serialized files.

The readers return plain NumPy arrays (:class:`MeshData`).  Vertices are
kept as they are in the file (never deduplicated), and every polygon
``(v0, v1, ..., v[n-1])`` is fan-triangulated into ``(v0, v[i], v[i+1])`` for
``i = 1 .. n-2``, polygons in file order. Vertex normals in the file (OBJ ``vn``
referenced by faces, PLY ``nx ny nz``) become the triangles' corner normals, as
Mitsuba reads them; a file without them gives ``normals=None`` (the scene then
computes smooth ones, or shades flat with ``face_normals``).

OBJ has its own small parser because triangle indices must agree with
Mitsuba's ``obj`` plugin (same fan order, faces never reordered or merged),
which a general-purpose loader does not promise.
"""

from __future__ import annotations

import io
import math
import os
import re
import struct
import tempfile
import warnings
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import plyfile

from ..core.arguments import FLOAT32_MAX, integer
from ..core.errors import MeshFileError
from ..models.mesh import MeshData, vertex_normals


# OBJ statements that carry no triangle geometry and are skipped.
_OBJ_IGNORED = frozenset(
    {"vp", "o", "g", "s", "usemtl", "mtllib", "l", "p"})

# One vertex of an OBJ face: 'i', 'i/j', 'i//k' or 'i/j/k' (position, texture, normal).
_OBJ_FACE_VERTEX = re.compile(r"([+-]?\d+)(?:/([+-]?\d*)(?:/([+-]?\d*))?)?", re.ASCII)

# PLY list properties that may hold a face's vertex indices.
_PLY_FACE_PROPERTIES = ("vertex_indices", "vertex_index")
# plyfile reads a binary element with list properties in one piece (memory-mapped) only
# where each list's length is given: faces are first read as triangles.
_PLY_TRIANGLE_FACES = {"face": {name: 3 for name in _PLY_FACE_PROPERTIES}}
# What plyfile raises on a malformed file: besides its own errors, builtin ones for some
# malformed headers (negative or absurd counts, duplicate properties).
_PLY_PARSE_ERRORS = (plyfile.PlyParseError, ValueError, TypeError, IndexError, OverflowError,
                     MemoryError)
# Pairs of vertex properties read as texture coordinates, the first present.
_PLY_TEXCOORDS = (("u", "v"), ("texture_u", "texture_v"), ("s", "t"))
# Postfix series of a PLY mesh attribute's properties (``<prefix>_<c>``), as Mitsuba's.
_ATTRIBUTE_POSTFIXES = ("xyzw", "rgba", "0123", "1234")

# Mitsuba's serialized format: its identifier and the flags of a mesh record.
_SERIALIZED_MAGIC = 0x041C
_HAS_NORMALS, _HAS_TEXCOORDS, _HAS_COLORS, _DOUBLE_PRECISION = 0x0001, 0x0002, 0x0008, 0x2000


def read_mesh(path: str | os.PathLike[str], shape_index: int = 0) -> MeshData:
    """Read a triangle mesh, choosing the reader by the file extension.

    Args:
        path: an ``.obj``, ``.ply`` or ``.serialized`` file (extension case-insensitive).
        shape_index: which mesh of a serialized file (0 for the others).

    Returns:
        The mesh, polygons fan-triangulated (see :func:`read_obj`,
        :func:`read_ply` and :func:`read_serialized`).

    Raises:
        MeshFileError: the extension is none of those, a shape_index is given for an OBJ
            or PLY file, or the chosen reader rejects the file.
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".serialized":
        return read_serialized(path, shape_index)
    reader = _READERS.get(suffix)
    if reader is None:
        raise _error(path, f"unknown extension {suffix!r} "
                           "(expected '.obj', '.ply' or '.serialized')")
    if shape_index != 0:
        raise _error(path, f"shape_index {shape_index!r} applies to serialized files only")
    return reader(path)


def read_obj(path: str | os.PathLike[str]) -> MeshData:
    """Read the polygons of a Wavefront OBJ file as triangles.

    Args:
        path: the OBJ file.

    Returns:
        The ``v`` positions in file order and the ``f`` polygons,
        fan-triangulated in file order as Mitsuba's ``obj`` plugin does; where
        faces refer to ``vn`` normals, the corner normals (corners without a
        normal index then take the smooth normal :func:`vertex_normals` gives);
        where they refer to ``vt`` texture coordinates, the corner uvs as stored
        (corners without one take (0, 0); the scene flips v as Mitsuba's
        ``flip_tex_coords``) and, without normals, their indices as the corners'
        :attr:`~instancing.models.mesh.MeshData.weld` (Mitsuba's computed normals break
        along texture seams).

    Raises:
        MeshFileError: the file is missing or unreadable, a line cannot be
            parsed, a face has fewer than 3 vertices or an index out of
            range, a coordinate or normal is not finite or beyond float32's
            range, a normal that a face uses has zero length, or there are no
            vertices or no faces.

    Limitations:
        Only ``v``, ``vt``, ``vn`` and ``f`` are read: a ``w`` (or vertex colour) after
        ``x y z`` is ignored, as is a third texture coordinate;
        ``vp o g s usemtl mtllib l p`` statements are skipped, and any
        other statement (free-form geometry, for one) is rejected.  A face
        may only refer to vertices defined above it, and line continuations
        (a trailing backslash) are not supported.  Stricter than Mitsuba,
        which skips unknown statements and faces of fewer than 3 vertices;
        Mitsuba in turn rejects negative indices, which are read here.
    """
    text = _read_bytes(path).decode("utf-8", errors="replace")
    positions: list[tuple[float, float, float]] = []
    normals: list[tuple[float, float, float]] = []
    texcoords: list[tuple[float, float]] = []
    corners: list[int] = []
    corner_normals: list[int] = []
    corner_uvs: list[int] = []
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split("#", 1)[0].split()
        if not tokens or tokens[0] in _OBJ_IGNORED:
            continue
        keyword, arguments = tokens[0], tokens[1:]
        if keyword == "v":
            positions.append(
                _obj_vertex(path, number, line, arguments))
        elif keyword == "vn":
            normals.append(_obj_vertex(path, number, line, arguments, "normal 'vn x y z'"))
        elif keyword == "vt":
            texcoords.append(_obj_texcoord(path, number, line, arguments))
        elif keyword == "f":
            polygon = _obj_polygon(path, number, line, arguments,
                                   len(positions), len(normals), len(texcoords))
            # Fan-triangulate: (v0, v[i], v[i+1]) for i = 1 .. n-2.
            for i in range(1, len(polygon) - 1):
                for vertex, normal, uv in (polygon[0], polygon[i], polygon[i + 1]):
                    corners.append(vertex)
                    corner_normals.append(normal)
                    corner_uvs.append(uv)
        else:
            raise _line_error(path, number, line,
                              f"unsupported statement {keyword!r}")
    mesh = _mesh_data(path, np.array(positions, dtype=np.float64),
                      np.array(corners, dtype=np.int64))
    uv_index = np.array(corner_uvs, dtype=np.int64).reshape(-1, 3)
    if (uv_index >= 0).any():
        table = np.concatenate([np.array(texcoords, dtype=np.float64), np.zeros((1, 2))])
        mesh = mesh._replace(uvs=table[uv_index])  # index -1: the (0, 0) row
    index = np.array(corner_normals, dtype=np.int64).reshape(-1, 3)
    if not (index >= 0).any():
        # No normals: those computed for it break where the texture coordinates do.
        return mesh._replace(weld=uv_index) if (uv_index >= 0).any() else mesh
    # Corners without a normal index take the smooth normal there.
    corner = vertex_normals(mesh.vertices, mesh.faces)
    given = index >= 0
    corner[given] = _corner_normals(path, np.array(normals, dtype=np.float64), index[given])
    return mesh.with_normals(corner)


def read_ply(path: str | os.PathLike[str]) -> MeshData:
    """Read the polygons of an ASCII or binary Stanford PLY file as triangles.

    Args:
        path: the PLY file.

    Returns:
        The ``x y z`` properties of the ``vertex`` element and the polygons
        of the ``face`` element, fan-triangulated in file order.

    Raises:
        MeshFileError: the file is missing, unreadable or corrupt, lacks the
            ``vertex`` element with ``x y z`` or the ``face`` element with a
            ``vertex_indices`` (or ``vertex_index``) list, a face has fewer
            than 3 vertices or an index out of range, a coordinate or normal
            is not finite or beyond float32's range, a normal that a face uses
            has zero length, or there are no vertices or no faces.

    Returns also the corner normals where the ``vertex`` element has ``nx ny nz``, the
    corner uvs where it has ``u v`` (or ``s t``, ``texture_u texture_v``), as stored, and the
    ``vertex`` and ``face`` elements' other properties as mesh attributes, as Mitsuba names
    and groups them (:func:`_ply_attributes`; a polygon's at each of its triangles).

    Limitations:
        Every other element is ignored, and so are the properties that are no mesh attributes
        by Mitsuba's rules (:func:`_ply_attributes`).  Mitsuba's own ``ply`` plugin accepts
        triangles only, so only triangle-only files load in both.
    """
    ply = _parse_ply(path)
    vertices = _ply_vertices(path, ply)
    polygons, sizes = _ply_polygons(path, ply, len(vertices))
    # Fan-triangulate: triangle j of the polygon whose indices start at flat
    # offset s is (s, s + j + 1, s + j + 2), for j = 0 .. size - 3.
    triangle_counts = sizes - 2
    first = np.repeat(np.cumsum(sizes) - sizes, triangle_counts)
    j = np.arange(triangle_counts.sum()) - np.repeat(
        np.cumsum(triangle_counts) - triangle_counts, triangle_counts)
    corners = polygons[np.stack([first, first + j + 1, first + j + 2], axis=1)]
    mesh = _mesh_data(path, vertices, corners.reshape(-1))
    normals = _ply_normals(path, ply)
    texcoords = _ply_texcoords(path, ply)
    if texcoords is not None:
        mesh = mesh._replace(uvs=texcoords[mesh.faces])
    # Attributes: a vertex's values as read, a polygon's on each of its fan triangles.
    attributes = _ply_attributes(path, ply, "vertex", {"x", "y", "z", "nx", "ny", "nz",
                                                        *_ply_texcoord_names(ply)})
    polygon_of_triangle = np.repeat(np.arange(len(sizes)), triangle_counts)
    for name, values in _ply_attributes(path, ply, "face", set(_PLY_FACE_PROPERTIES)).items():
        if name in attributes:
            raise _error(path, f"two mesh attributes are named {name!r}")
        attributes[name] = values[polygon_of_triangle]
    if attributes:
        mesh = mesh._replace(attributes=attributes)
    return mesh if normals is None else mesh.with_normals(_corner_normals(path, normals, mesh.faces))


def _parse_ply(path: str | os.PathLike[str]) -> plyfile.PlyData:
    """The PLY file as plyfile parses it: a binary file whose faces are all triangles in
    one piece (about 100x faster than element by element), any other file element by
    element, which also reports what is wrong with a malformed one."""
    data = _read_bytes(path)
    if b"format binary_" in data[:data.find(b"end_header")]:
        # plyfile reads in one piece only from a memory-mapped file. It maps a private copy:
        # a mapping of the user's file would crash the process if the file shrank meanwhile.
        with tempfile.TemporaryFile() as copy:
            copy.write(data)
            copy.seek(0)
            try:
                return plyfile.PlyData.read(copy, known_list_len=_PLY_TRIANGLE_FACES)
            except _PLY_PARSE_ERRORS:
                pass  # other polygons than triangles, or a problem the reader below reports
    try:
        return plyfile.PlyData.read(io.BytesIO(data))
    except _PLY_PARSE_ERRORS as exc:
        raise _error(path, f"corrupt PLY file ({exc})") from None


def read_serialized(path: str | os.PathLike[str], shape_index: int = 0) -> MeshData:
    """Read one mesh of a Mitsuba ``.serialized`` file (format versions 3 and 4).

    Args:
        path: the file: one or more meshes, each a 4-byte header (format 0x041C,
            version) and a zlib stream; with several, a table of their offsets at the end.
        shape_index: which mesh (Mitsuba's ``shape_index``).

    Returns:
        Positions and triangles, the vertex normals as corner normals where the file has
        them (else None), and the texture coordinates as corner uvs where it has them.
        Vertex colours are skipped, as by Mitsuba's RGB variants.

    Raises:
        MeshFileError: the file is missing or unreadable, not in the format, of another
            version, truncated or corrupt, ``shape_index`` out of range, an index out of
            range, a coordinate or normal not finite or beyond float32's range, a normal
            that a face uses of zero length, or no vertices or faces.
    """
    data = _read_bytes(path)
    shape_index = integer("shape_index", shape_index, 0, where=f"mesh file '{os.fspath(path)}'",
                          error=MeshFileError)
    if len(data) < 4:
        raise _error(path, "too short for a serialized mesh")
    magic, version = struct.unpack_from("<HH", data, 0)
    if magic != _SERIALIZED_MAGIC:
        raise _error(path, f"not a Mitsuba serialized mesh (format {magic:#06x}, expected "
                           f"{_SERIALIZED_MAGIC:#06x})")
    if version not in (3, 4):
        raise _error(path, f"serialized format version {version} is not supported (3 and 4 are)")
    start = 0
    if shape_index:
        # The offsets of the meshes are stored at the end: uint64 (version 4) or uint32
        # (version 3) each, then their uint32 count.
        count, = struct.unpack_from("<I", data, len(data) - 4)
        if shape_index >= count:
            raise _error(path, f"shape_index {shape_index} is out of range for {count} meshes")
        size = 8 if version == 4 else 4
        table = len(data) - 4 - size * count
        if table < 0:
            raise _error(path, "corrupt mesh offset table")
        start, = struct.unpack_from("<Q" if version == 4 else "<I", data, table + size * shape_index)
        if not 0 <= start <= len(data) - 4 or struct.unpack_from("<HH", data, start) != (magic, version):
            raise _error(path, f"corrupt offset {start} of mesh {shape_index}")
    try:
        body = zlib.decompressobj().decompress(data[start + 4:])
    except zlib.error as exc:
        raise _error(path, f"corrupt compressed mesh data ({exc})") from None
    return _serialized_mesh(path, body, version)


def _serialized_mesh(path, body: bytes, version: int) -> MeshData:
    """The mesh in a decompressed serialized stream (module ``read_serialized``)."""
    reader = _Bytes(path, body)
    flags = reader.unpack("<I")[0]
    if version == 4:
        reader.cstring()
    vertex_count, face_count = reader.unpack("<QQ")
    real = np.float64 if flags & _DOUBLE_PRECISION else np.float32
    vertices = reader.array(real, vertex_count * 3).reshape(-1, 3).astype(np.float64)
    normals = reader.array(real, vertex_count * 3).reshape(-1, 3) if flags & _HAS_NORMALS else None
    uvs = reader.array(real, vertex_count * 2).reshape(-1, 2) if flags & _HAS_TEXCOORDS else None
    if flags & _HAS_COLORS:
        reader.array(real, vertex_count * 3)
    faces = reader.array(np.uint32, face_count * 3).astype(np.int64)
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if bad.size:
        raise _error(path, f"vertex {bad[0]} has a non-finite coordinate {vertices[bad[0]].tolist()}")
    out_of_range = np.flatnonzero(faces >= vertex_count)
    if out_of_range.size:
        raise _error(path, f"face {out_of_range[0] // 3} has vertex index {faces[out_of_range[0]]}, "
                           f"out of range for {vertex_count} vertices")
    mesh = _mesh_data(path, vertices, faces)
    if uvs is not None:
        mesh = mesh._replace(uvs=uvs.astype(np.float64)[mesh.faces])
    if normals is not None:
        if not np.isfinite(normals).all():
            raise _error(path, "non-finite vertex normals")
        mesh = mesh.with_normals(_corner_normals(path, normals.astype(np.float64), mesh.faces))
    return mesh


class _Bytes:
    """Little-endian reads from a decompressed stream; running past its end is an error
    naming the file."""

    def __init__(self, path, data: bytes):
        self.path, self.data, self.at = path, data, 0

    def take(self, size: int) -> bytes:
        if size < 0 or self.at + size > len(self.data):
            raise _error(self.path, "truncated serialized mesh data")
        chunk = self.data[self.at:self.at + size]
        self.at += size
        return chunk

    def unpack(self, fmt: str) -> tuple:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))

    def array(self, dtype, count: int) -> np.ndarray:
        item = np.dtype(dtype).newbyteorder("<")
        return np.frombuffer(self.take(int(count) * item.itemsize), dtype=item)

    def cstring(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise _error(self.path, "truncated serialized mesh name")
        name = self.data[self.at:end].decode("utf-8", errors="replace")
        self.at = end + 1
        return name


def _read_bytes(path: str | os.PathLike[str]) -> bytes:
    """Return the contents of ``path``, raising MeshFileError on failure."""
    try:
        with open(path, "rb") as stream:
            return stream.read()
    except FileNotFoundError:
        raise _error(path, "not found") from None
    except OSError as exc:
        raise _error(path, f"cannot be read ({exc.strerror or exc})") from None


def _obj_vertex(path: str | os.PathLike[str], number: int, line: str,
                arguments: list[str], what: str = "vertex 'v x y z [w]'"
                ) -> tuple[float, float, float]:
    """Parse the arguments of an OBJ ``v`` (or ``vn``) statement into (x, y, z)."""
    try:
        values = [float(argument) for argument in arguments]
    except ValueError:
        values = []
    if len(values) < 3:
        raise _line_error(path, number, line, f"expected a {what}")
    if not all(math.isfinite(value) for value in values[:3]):
        raise _line_error(path, number, line, f"non-finite {what.split()[0]} coordinate")
    return values[0], values[1], values[2]


def _obj_texcoord(path: str | os.PathLike[str], number: int, line: str,
                  arguments: list[str]) -> tuple[float, float]:
    """Parse the arguments of an OBJ ``vt u [v [w]]`` statement into (u, v); v defaults
    to 0 as the format says."""
    try:
        values = [float(argument) for argument in arguments]
    except ValueError:
        values = []
    if not values:
        raise _line_error(path, number, line, "expected a texture coordinate 'vt u [v [w]]'")
    if not all(math.isfinite(value) for value in values[:2]):
        raise _line_error(path, number, line, "non-finite texture coordinate")
    return values[0], values[1] if len(values) > 1 else 0.0


def _obj_polygon(path: str | os.PathLike[str], number: int, line: str,
                 arguments: list[str], vertex_count: int,
                 normal_count: int, texcoord_count: int) -> list[tuple[int, int, int]]:
    """Parse the arguments of an OBJ ``f`` statement into 0-based (vertex, normal, uv)
    indices, normal and uv -1 where the corner names none.

    ``vertex_count`` (``normal_count``, ``texcoord_count``) is the number of ``v``
    (``vn``, ``vt``) statements above the face: a negative index counts back from it,
    and no index may reach past it.
    """
    if len(arguments) < 3:
        raise _line_error(path, number, line,
                          f"face has {len(arguments)} vertices, at least 3 "
                          "are needed")
    polygon = []
    for argument in arguments:
        # Read i, j and k from 'i', 'i/j', 'i//k' or 'i/j/k'.
        match = _OBJ_FACE_VERTEX.fullmatch(argument)
        if match is None:
            raise _line_error(path, number, line,
                              f"cannot parse face vertex {argument!r}")
        vertex = _obj_index(path, number, line, match.group(1), vertex_count, "vertices")
        normal = (_obj_index(path, number, line, match.group(3), normal_count, "normals")
                  if match.group(3) else -1)
        uv = (_obj_index(path, number, line, match.group(2), texcoord_count, "texture coordinates")
              if match.group(2) else -1)
        polygon.append((vertex, normal, uv))
    return polygon


def _obj_index(path: str | os.PathLike[str], number: int, line: str, text: str,
               count: int, what: str) -> int:
    """Resolve a 1-based (positive) or relative (negative) OBJ index into 0-based."""
    index = int(text)
    resolved = index - 1 if index > 0 else count + index
    if index == 0 or not 0 <= resolved < count:
        raise _line_error(path, number, line,
                          f"face index {index} is out of range for "
                          f"{count} {what} defined so far")
    return resolved


def _ply_vertices(path: str | os.PathLike[str],
                  ply: plyfile.PlyData) -> np.ndarray:
    """Return the x, y, z properties of the PLY ``vertex`` element."""
    element = _ply_element(path, ply, "vertex")
    columns = []
    for name in "xyz":
        property_ = _ply_property(element, (name,))
        if property_ is None or isinstance(property_, plyfile.PlyListProperty):
            raise _error(path, f"PLY element 'vertex' has no scalar "
                               f"property {name!r}")
        columns.append(element.data[name].astype(np.float64))
    vertices = np.stack(columns, axis=1).reshape(-1, 3)
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if bad.size:
        raise _error(path, f"vertex {bad[0]} has a non-finite coordinate "
                           f"{vertices[bad[0]].tolist()}")
    return vertices


def _ply_normals(path: str | os.PathLike[str], ply: plyfile.PlyData) -> np.ndarray | None:
    """The per-vertex normals ``nx ny nz`` of the PLY ``vertex`` element, or None."""
    element = _ply_element(path, ply, "vertex")
    found = [_ply_property(element, (name,)) for name in ("nx", "ny", "nz")]
    if all(p is None for p in found):
        return None
    if any(p is None or isinstance(p, plyfile.PlyListProperty) for p in found):
        raise _error(path, "PLY element 'vertex' has some but not all of the scalar "
                           "normal properties 'nx', 'ny', 'nz'")
    normals = np.stack([element.data[n].astype(np.float64) for n in ("nx", "ny", "nz")], axis=1)
    bad = np.flatnonzero(~np.isfinite(normals).all(axis=1))
    if bad.size:
        raise _error(path, f"vertex {bad[0]} has a non-finite normal {normals[bad[0]].tolist()}")
    return normals


def _ply_texcoords(path: str | os.PathLike[str], ply: plyfile.PlyData) -> np.ndarray | None:
    """The per-vertex texture coordinates of the PLY ``vertex`` element (``u v``, ``s t``
    or ``texture_u texture_v``, as Mitsuba's ``ply`` plugin reads them), or None."""
    element = _ply_element(path, ply, "vertex")
    for names in _PLY_TEXCOORDS:
        found = [_ply_property(element, (name,)) for name in names]
        if any(p is None or isinstance(p, plyfile.PlyListProperty) for p in found):
            continue
        uvs = np.stack([element.data[n].astype(np.float64) for n in names], axis=1)
        bad = np.flatnonzero(~np.isfinite(uvs).all(axis=1))
        if bad.size:
            raise _error(path, f"vertex {bad[0]} has non-finite texture coordinates "
                               f"{uvs[bad[0]].tolist()}")
        return uvs
    return None


def _ply_texcoord_names(ply: plyfile.PlyData) -> tuple[str, ...]:
    """The names of the ``vertex`` element's properties that are read as texture
    coordinates (the first pair of :func:`_ply_texcoords` present), or ()."""
    vertex = next((e for e in ply.elements if e.name == "vertex"), None)
    present = set() if vertex is None else {p.name for p in vertex.properties}
    return next((names for names in _PLY_TEXCOORDS if present.issuperset(names)), ())


def _ply_attributes(path: str | os.PathLike[str], ply: plyfile.PlyData, kind: str,
                    reserved: set[str]) -> dict[str, np.ndarray]:
    """Mitsuba's mesh attributes of the PLY element ``kind`` (``vertex`` or ``face``): name
    (``<kind>_<name>``) to a (count, dim) float32 array, grouped as Mitsuba's ``ply``
    plugin groups the element's other scalar properties:

    * ``r g b`` (or ``red green blue``), with ``a`` (``alpha``) where present: ``<kind>_color``;
    * consecutive properties ``<prefix>_<c>`` whose one-letter postfixes run along one of
      ``x y z w``, ``r g b a``, ``0 1 2 3`` or ``1 2 3 4`` from its start, 1 or 3 of them:
      ``<kind>_<prefix>`` (``<kind>_<prefix>_color`` for ``r g b``).

    Other properties (no ``_<c>`` postfix, a broken or 2- or 4-long run, a prefix seen
    before) are skipped with a warning, as Mitsuba skips them; integer values are taken as
    they are (Mitsuba does not scale a colour of 0 - 255 to 0 - 1 either: warned)."""
    element = next((e for e in ply.elements if e.name == kind), None)
    if element is None:
        return {}
    columns = {p.name: p for p in element.properties
               if not isinstance(p, plyfile.PlyListProperty) and p.name not in reserved}
    groups: list[tuple[str, list[str]]] = []
    for names in (("r", "g", "b", "a"), ("red", "green", "blue", "alpha")):
        if all(name in columns for name in names[:3]):
            groups.append(("color", [n for n in names if n in columns]))
            for name in names:
                columns.pop(name, None)
            break
    for name in ("r", "g", "b", "a"):
        columns.pop(name, None)
    skipped: list[str] = []
    runs: list[list[str]] = []
    open_run = False
    for name in columns:
        prefix, underscore, postfix = name.rpartition("_")
        if not underscore or len(postfix) != 1:
            skipped.append(name)
            open_run = False
        elif open_run and runs[-1][0].rpartition("_")[0] == prefix:
            runs[-1].append(name)
        else:
            runs.append([name])
            open_run = True
    seen = set()
    for run in runs:
        prefix = run[0].rpartition("_")[0]
        postfixes = "".join(name[-1] for name in run)
        series = next((s for s in _ATTRIBUTE_POSTFIXES if s.startswith(postfixes)), None)
        if prefix in seen or series is None or len(run) not in (1, 3):
            skipped.extend(run)
            continue
        seen.add(prefix)
        groups.append((prefix + ("_color" if series == "rgba" else ""), run))
    if skipped:
        warnings.warn(f"mesh file '{os.fspath(path)}': PLY {kind} properties {skipped} are not "
                      "read as mesh attributes (Mitsuba's naming rules: <prefix>_x/y/z, _r/g/b, "
                      "_0/1/2 or _1/2/3, one or three of them)", stacklevel=3)
    attributes = {}
    for name, run in groups:
        values = np.stack([element.data[n].astype(np.float32) for n in run], axis=1)
        if len(run) >= 3 and any(element.data[n].dtype.kind != "f" for n in run):
            warnings.warn(f"mesh file '{os.fspath(path)}': mesh attribute '{kind}_{name}' has "
                          "integer values, taken as they are (colours are expected in [0, 1], "
                          "as Mitsuba expects them)", stacklevel=3)
        full = f"{kind}_{name}"
        if full in attributes:
            raise _error(path, f"two mesh attributes are named {full!r}")
        attributes[full] = values
    return attributes


def _ply_polygons(path: str | os.PathLike[str], ply: plyfile.PlyData,
                  vertex_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the PLY faces' vertex indices, flattened, and their counts."""
    element = _ply_element(path, ply, "face")
    property_ = _ply_property(element, _PLY_FACE_PROPERTIES)
    if not isinstance(property_, plyfile.PlyListProperty):
        raise _error(path, "PLY element 'face' has no list property "
                           "'vertex_indices' or 'vertex_index'")
    lists = element.data[property_.name]
    if lists.dtype != object:
        # Read in one piece (see _parse_ply): a row of indices per triangle.
        return _ply_indices(path, lists.reshape(-1), np.full(len(lists), lists.shape[1]),
                            vertex_count)
    sizes = np.fromiter((len(polygon) for polygon in lists), dtype=np.int64,
                        count=len(lists))
    short = np.flatnonzero(sizes < 3)
    if short.size:
        raise _error(path, f"face {short[0]} has {sizes[short[0]]} "
                           "vertices, at least 3 are needed")
    polygons = (np.concatenate(lists) if len(lists)
                else np.empty(0, dtype=np.int64))
    return _ply_indices(path, polygons, sizes, vertex_count)


def _ply_indices(path: str | os.PathLike[str], polygons: np.ndarray, sizes: np.ndarray,
                 vertex_count: int) -> tuple[np.ndarray, np.ndarray]:
    """The faces' flattened vertex indices as int64 and their counts, checked."""
    if polygons.dtype.kind not in "iu":
        raise _error(path, f"PLY face indices have non-integer type "
                           f"{polygons.dtype}")
    polygons = polygons.astype(np.int64)
    out_of_range = np.flatnonzero((polygons < 0) | (polygons >= vertex_count))
    if out_of_range.size:
        # The polygon holding flat position k is the first whose end exceeds k.
        k = out_of_range[0]
        face = np.searchsorted(np.cumsum(sizes), k, side="right")
        raise _error(path, f"face {face} has vertex index {polygons[k]}, out "
                           f"of range for {vertex_count} vertices")
    return polygons, sizes


def _ply_element(path: str | os.PathLike[str], ply: plyfile.PlyData,
                 name: str) -> plyfile.PlyElement:
    """Return the PLY element called ``name``, raising if it is missing."""
    for element in ply.elements:
        if element.name == name:
            return element
    raise _error(path, f"PLY file has no {name!r} element")


def _ply_property(element: plyfile.PlyElement,
                  names: tuple[str, ...]) -> plyfile.PlyProperty | None:
    """Return the first property of ``element`` named in ``names``."""
    for name in names:
        for property_ in element.properties:
            if property_.name == name:
                return property_
    return None


#: Triangles per run of the zero-area check in :func:`_mesh_data`.
_AREA_CHECK_RUN = 1 << 16


def _mesh_data(path: str | os.PathLike[str], vertices: np.ndarray,
               corners: np.ndarray) -> MeshData:
    """Build MeshData from flat triangle corners, rejecting an empty mesh and one whose
    triangles all have zero area (nothing a ray could hit or a lamp could emit from)."""
    if len(vertices) == 0:
        raise _error(path, "no vertices")
    if len(corners) == 0:
        raise _error(path, "no faces")
    _check_float32_range(path, vertices, "vertex")
    faces = corners.reshape(-1, 3)
    vertices64 = np.asarray(vertices, np.float64)
    # Checked a run of triangles at a time: a mesh's first run nearly always has area.
    for run in range(0, len(faces), _AREA_CHECK_RUN):
        p = vertices64[faces[run:run + _AREA_CHECK_RUN]]
        if np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).any():
            break
    else:
        raise _error(path, f"all {len(faces)} triangles have zero area (collinear or repeated "
                           "corners): the mesh has no surface")
    return MeshData(vertices=vertices, faces=faces)


def _corner_normals(path: str | os.PathLike[str], normals: np.ndarray,
                    index: np.ndarray) -> np.ndarray:
    """The file's vertex normals ``normals`` (N, 3) at the corners ``index`` (any shape),
    refusing normals beyond float32's range and, among those the corners use, normals of
    zero length in float32 (where they are stored): shading would normalize them to NaN."""
    _check_float32_range(path, normals, "normal")
    used = np.zeros(len(normals), bool)
    used[index] = True
    zero = np.flatnonzero(used & ~normals.astype(np.float32).any(axis=1))
    if zero.size:
        raise _error(path, f"{zero.size} of the {used.sum()} vertex normals that faces use have "
                           f"zero length (the first: normal {zero[0]}, counting from 0), so they "
                           "give no shading direction; remove the file's normals to shade by "
                           "computed ones")
    return normals[index]


def _check_float32_range(path: str | os.PathLike[str], values: np.ndarray, what: str) -> None:
    """Refuse rows of ``values`` (vertices or normals, (N, 3)) with an entry beyond
    float32's range, in which meshes are stored."""
    bad = np.flatnonzero((np.abs(values) > FLOAT32_MAX).any(axis=1))
    if bad.size:
        raise _error(path, f"{what} {bad[0]} (counting from 0) {values[bad[0]].tolist()} lies "
                           f"beyond float32's range |x| <= {FLOAT32_MAX:.4g}, in which meshes "
                           f"are stored ({bad.size} in all)")


def _error(path: str | os.PathLike[str], problem: str) -> MeshFileError:
    """Build the error for ``problem`` in the mesh file ``path``."""
    return MeshFileError(f"mesh file '{os.fspath(path)}': {problem}")


def _line_error(path: str | os.PathLike[str], number: int, line: str,
                problem: str) -> MeshFileError:
    """Build the error for ``problem`` on line ``number`` of ``path``."""
    return _error(path, f"line {number} ({line.strip()!r}): {problem}")


_READERS: dict[str, Callable[[str | os.PathLike[str]], MeshData]] = {
    ".obj": read_obj,
    ".ply": read_ply,
}
