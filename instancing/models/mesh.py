"""Triangle-mesh models: object-space geometry and BVH, shared by all instances.

All mesh models of a scene live in one :class:`MeshLibrary`: their triangles
and BVH nodes are concatenated, and each mesh is entered through its own root
reference, so one traversal kernel serves every mesh (the bottom level of the
two-level acceleration). A tree's items are a mesh's triangles or, where the surface area
heuristic prefers, their references (a slender triangle split into several;
:mod:`~instancing.accel.triangle_references`). Triangles are stored in BVH leaf order, once per
item (a triangle's ``position`` is its leaf position, its first where it has several), as
their three corners ``(v0, v1, v2)``, rounded to float32 once, 12 floats per triangle: the
first eight coordinates are read as two float4 packet loads, the ninth by one
scalar gather (the last three floats are padding; see
:func:`~instancing.core.backend.device_array`); ``prim`` reported to the user is the
triangle's index in its file.

Ray/triangle tests:

* traversal (float32): Woop, Benthin & Wald, "Watertight Ray/Triangle
  Intersection", JCGT 2(1), 2013, as in pbrt-v4's ``IntersectTriangle``. The
  corners are moved into a frame where the ray starts at the origin and runs
  along +z; whether the ray passes inside is then decided by the signs of three
  2D edge functions, each a function of one edge's two corners only. Neighbours
  share exact float32 corners and the signs are computed exactly, so both take
  the same side of their shared edge and a ray can never slip between them
  (Moller-Trumbore's barycentrics are formed per triangle and can: a leak
  through a crack was measured in the stress suite's shear + reflection case);
* re-intersection (the ray's precision, float64 in phase 2): Moller & Trumbore,
  "Fast, Minimum Storage Ray/Triangle Intersection" (1997), on the known
  triangle only.

The geometric normal is ``cross(v1 - v0, v2 - v0)`` as in Mitsuba (never
flipped toward the ray).
"""

from __future__ import annotations

from typing import Mapping, NamedTuple

import numpy as np

from ..accel.bvh import BVHKernel
from ..accel.triangle_references import mesh_forest
from ..core.backend import (Array3f, Array4f, Bool, Float, Float64, UInt32, device_array,
                            device_arrays, dr)
from ..core.error_bounds import gamma
from ..core.errors import SceneError
from .curves import NORMAL_STORED, EdgeTopology, SectionParts


class MeshData(NamedTuple):
    """A triangle mesh as NumPy arrays."""

    vertices: np.ndarray
    """(V, 3) float64 vertex positions."""

    faces: np.ndarray
    """(F, 3) int64 triangles, as indices into ``vertices``."""

    normals: np.ndarray | None = None
    """(F, 3 corners, 3) float64 shading normals at each triangle's corners (not
    necessarily unit: they are interpolated, then normalized), or None: flat shading
    by the geometric normal."""

    uvs: np.ndarray | None = None
    """(F, 3 corners, 2) float64 surface coordinates at each triangle's corners, or None:
    a hit's ``uv`` is then its barycentrics (b1, b2), as in Mitsuba."""

    attributes: Mapping[str, np.ndarray] | None = None
    """Mitsuba's mesh attributes by name: a ``vertex_<name>`` one a (V, dim) float32 array of
    each vertex's values, a ``face_<name>`` one an (F, dim) array of each triangle's; or
    None: the mesh has none."""

    weld: np.ndarray | None = None
    """(F, 3 corners) int64 keys that, with the vertex, decide which corners share a
    computed smooth normal (:func:`vertex_normals`): an OBJ corner's texture-coordinate
    index, since Mitsuba welds an OBJ's vertices by their position, texture and normal
    indices, so that the normals it computes break along texture seams; or None: corners
    of a vertex share one."""

    def attribute_corners(self, name: str) -> np.ndarray:
        """Attribute ``name``'s values at each triangle's corners, (F, 3, dim) float32 (a face
        attribute's value at all three)."""
        values = self.attributes[name]
        if name.startswith("vertex_"):
            return values[self.faces]
        return np.repeat(values[:, None], 3, axis=1)

    def with_normals(self, normals: np.ndarray | None) -> "MeshData":
        """The same geometry with other corner normals (None: flat shading)."""
        return self._replace(normals=normals)

    def flipped(self) -> "MeshData":
        """The mesh turned inside out, as Mitsuba's ``flip_normals``: every triangle's
        winding reversed (so its geometric normal), its corner normals negated."""
        normals = None if self.normals is None else -self.normals[:, ::-1]
        uvs = None if self.uvs is None else self.uvs[:, ::-1].copy()
        weld = None if self.weld is None else self.weld[:, ::-1].copy()
        return MeshData(self.vertices, self.faces[:, ::-1].copy(), normals, uvs, self.attributes, weld)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, weld: np.ndarray | None = None) -> np.ndarray:
    """Smooth shading normals as Mitsuba computes them for a mesh file without any:
    at each vertex the unit normals of its triangles, weighted by the triangles' angles
    there (Thurmer & Wuthrich 1998), summed and normalized. Returned per corner,
    (F, 3, 3); a vertex whose sum vanishes (only degenerate triangles) takes each
    triangle's own normal there. With ``weld`` (:attr:`MeshData.weld`), the corners of a
    vertex sum only with those of the same key."""
    v = vertices[faces]
    face_normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    length = np.linalg.norm(face_normal, axis=1, keepdims=True)
    unit = face_normal / np.where(length > 0, length, 1.0)
    # Each corner's welded vertex: the vertex, or its (vertex, key) pair.
    slot = faces if weld is None else np.unique(faces * (int(weld.max()) + 2) + (weld + 1),
                                                return_inverse=True)[1].reshape(faces.shape)
    total = np.zeros((int(slot.max()) + 1, 3))
    for c in range(3):
        a, b = v[:, (c + 1) % 3] - v[:, c], v[:, (c + 2) % 3] - v[:, c]
        angle = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
        np.add.at(total, slot[:, c], angle[:, None] * unit)
    corner = total[slot]
    size = np.linalg.norm(corner, axis=2, keepdims=True)
    return np.where(size > 0, corner / np.where(size > 0, size, 1.0), unit[:, None, :])


#: Plane-triangle distances computed at once by MeshLibrary.plane_sections (memory bound).
SECTION_BLOCK = 1 << 22
#: Triangles per BVH leaf at most (the SAH makes smaller leaves where a split is cheaper):
#: 2 costs more loop iterations per ray, 8 no fewer (docs/how-it-works.md).
MESH_LEAF_SIZE = 4


def difference_of_products(a: Float, b: Float, c: Float, d: Float) -> Float:
    """``a b - c d`` within 2 ulp (Kahan's algorithm with two FMAs, as pbrt-v4's
    ``DifferenceOfProducts``; Jeannerod, Louvet & Muller, Math. Comp. 82, 2013).

    Its sign is therefore exact unless the products underflow. A plain ``a * b - c * d``
    has the exact sign (or 0) only while the compiler does not contract it into an FMA,
    which Dr.Jit's CUDA backend allows (``mul.ftz`` without ``.rn``).
    """
    cd = c * d
    return dr.fma(a, b, -cd) + dr.fma(-c, d, cd)


def permuted(v, k: UInt32) -> Float:
    """Component ``k`` (0, 1, 2: x, y, z; per lane) of the vector ``v``."""
    return dr.select(k == 0, v.x, dr.select(k == 1, v.y, v.z))


#: Edges drawn per silhouette sample of a mesh (see SilhouetteEdges.sample).
EDGE_DRAWS = 16
GOLDEN_FRACTION = 0.6180339887498949


class SilhouetteEdges(NamedTuple):
    """Edges that can be silhouettes (device arrays), for sampling visibility boundaries
    seen from points: start, start-to-end vector, the two faces' unit normals (the second
    0 for boundary and non-manifold edges), whether shading jumps across it (1.0 or 0.0),
    and per mesh its first edge and count (host)."""

    start: Array3f
    direction: Array3f
    normal0: Array3f
    normal1: Array3f
    jump: Float
    first: np.ndarray
    count: np.ndarray

    def sample(self, first: UInt32, count: UInt32, view: Array3f, u: Float, u_choice: Float,
               creases: bool = False) -> tuple[Array3f, Array3f, Bool]:
        """As :meth:`~instancing.models.analytic.AnalyticModel.sample_silhouette` for the
        mesh whose edges are ``first .. first + count - 1``. An edge counts where it is a rim
        or exactly one of its faces is seen from ``view`` (with ``creases``: also where
        shading jumps across it and either face is seen).

        Few of a mesh's edges count from any one point, so EDGE_DRAWS edges are drawn at
        the points ``u + i phi`` (mod 1; phi the golden ratio's fraction, so that the draws
        do not stride in step with a mesh's regular edge order; each uniform), the
        counting ones are counted, and one of them, picked with ``u_choice``, is returned
        with its measure scaled by (counting draws) / EDGE_DRAWS: the estimate is the mean
        over the draws, as unbiased as one uniform draw, with fewer empty samples."""
        def draw(i: int):
            shifted = u + i * GOLDEN_FRACTION
            shifted = shifted - dr.floor(shifted)
            scaled = shifted * Float(count)
            k = dr.minimum(UInt32(scaled), count - 1)
            edge = first + k
            start = dr.gather(Array3f, self.start, edge)
            n0, n1 = (dr.gather(Array3f, a, edge) for a in (self.normal0, self.normal1))
            seen0, seen1 = dr.dot(view - start, n0) > 0.0, dr.dot(view - start, n1) > 0.0
            shows = seen0 != seen1
            if creases:
                shows |= (dr.gather(Float, self.jump, edge) != 0) & (seen0 | seen1)
            return dr.all(n1 == 0.0) | shows, edge, scaled - Float(k)

        found = UInt32(0)
        for i in range(EDGE_DRAWS):
            found += UInt32(draw(i)[0])
        # The pick-th counting draw.
        pick = dr.minimum(UInt32(u_choice * Float(found)), dr.maximum(found, 1) - 1)
        seen, edge, s = UInt32(0), UInt32(0), Float(0.0)
        for i in range(EDGE_DRAWS):
            counts, edge_i, s_i = draw(i)
            mine = counts & (seen == pick)
            edge, s = dr.select(mine, edge_i, edge), dr.select(mine, s_i, s)
            seen += UInt32(counts)
        start, direction = (dr.gather(Array3f, a, edge) for a in (self.start, self.direction))
        measure = Float(count) * Float(found) / EDGE_DRAWS
        return dr.fma(direction, s, start), direction * measure, found > 0


def _root_in_unit_interval(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Per row, a root of ``a t^2 + b t + c`` in [0, 1] (clipped), where the polynomial
    changes sign over [0, 1] (so that exactly one root lies there)."""
    root = np.sqrt(np.maximum(b * b - 4.0 * a * c, 0.0))
    # Both roots without cancellation; the linear case where a vanishes.
    q = -0.5 * (b + np.where(b >= 0, root, -root))
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = np.where(q != 0, c / q, 0.0)
        t2 = np.where(a != 0, q / np.where(a != 0, a, 1.0), t1)
    pick = np.where((t1 >= 0) & (t1 <= 1), t1, t2)
    return np.clip(np.nan_to_num(pick), 0.0, 1.0)


#: How far (relative to its extent) a mesh's vertices may lie off its plane for the mesh to
#: count as flat (float32 rounding of its coordinates).
FLAT_TOLERANCE = 1e-6


class MeshLibrary:
    """The scene's mesh models, concatenated for one shared traversal kernel.

    Args:
        meshes: the mesh models' data, in the order the scene numbers them.
        names: how errors name each mesh (its model and file; default ``mesh k``).

    Raises:
        SceneError: a mesh's total area is no normal float32 number (it is stored so).
    """

    def __init__(self, meshes: list[MeshData], names: list[str] | None = None):
        names = names if names is not None else [f"mesh {k}" for k in range(len(meshes))]
        #: Per mesh, its plane where it is flat (see :meth:`plane`), once asked for.
        self._planes: dict[int, tuple[np.ndarray, float] | None] = {}
        tri_packets, normal_packets, uv_packets, areas = [], [], [], []
        originals = []
        #: Per mesh, whether it is shaded smoothly (has corner normals).
        self.smooth = [mesh.normals is not None for mesh in meshes]
        #: Whether some mesh has surface coordinates of its own (else uv is barycentric).
        self.has_uvs = any(mesh.uvs is not None for mesh in meshes)
        #: Per mesh, the leaf-order position of each of its triangles (file order).
        self._leaf_position: list[np.ndarray] = []
        self.object_bounds: list[tuple[np.ndarray, np.ndarray]] = []
        # One BVH per mesh, all built at once over the triangles or, where the surface area
        # heuristic prefers, their references (several for a slender or slanted triangle).
        corners = [mesh.vertices[mesh.faces] for mesh in meshes]  # (F, 3 corners, 3) each
        trees, self.root_refs, leaf_triangles = mesh_forest([v.astype(np.float32) for v in corners],
                                                            MESH_LEAF_SIZE)
        item_offset = 0
        for mesh, v, order in zip(meshes, corners, leaf_triangles):
            corner_rows = v.reshape(-1, 3)
            self.object_bounds.append((corner_rows.min(axis=0), corner_rows.max(axis=0)))
            # The mesh's triangles in leaf order, a triangle once per reference.
            v = v[order]
            # The three corners rounded to float32 once: neighbours share exact corners, and
            # the edges are formed in the precision of each test (exact in float64).
            packets = np.zeros((len(v), 12), np.float32)
            packets[:, :9] = v.reshape(-1, 9)
            tri_packets.append(packets)
            # Area sampling: the triangles' object-space areas (leaf order), in float64 from
            # the float32 corners (in float32, their squares overflow from coordinates of
            # about 1e10 and underflow below about 1e-11), counted at a triangle's first
            # position only.
            corner = packets[:, :3].astype(np.float64)
            area = 0.5 * np.linalg.norm(np.cross(packets[:, 3:6] - corner, packets[:, 6:9] - corner), axis=1)
            if len(order) > len(mesh.faces):
                # (Each triangle once: a triangle of several references at its first.)
                first = np.zeros(len(order), bool)
                first[np.unique(order, return_index=True)[1]] = True
                area = np.where(first, area, 0.0)
            areas.append(area)
            if any(self.smooth):
                # Corner normals in the same order and layout; a flat mesh among smooth ones
                # stores its face normal at each corner (which interpolates to itself).
                normals = (mesh.normals[order] if mesh.normals is not None else
                           np.repeat(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])[:, None], 3, 1))
                corner = np.zeros((len(v), 12), np.float32)
                corner[:, :9] = normals.reshape(-1, 9)
                normal_packets.append(corner)
            if self.has_uvs:
                # Corner uvs, 6 per triangle; (0, 0), (1, 0), (0, 1) interpolate to the
                # barycentrics where a mesh has none.
                uvs = mesh.uvs[order] if mesh.uvs is not None else np.broadcast_to(
                    np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), (len(v), 3, 2))
                uv_packets.append(np.asarray(uvs, np.float32).reshape(-1, 6))
            originals.append(order)
            position = np.empty(len(mesh.faces), order.dtype)
            # (A triangle's first position, where it has several.)
            position[order[::-1]] = np.arange(item_offset, item_offset + len(order))[::-1]
            self._leaf_position.append(position)
            item_offset += len(v)
        self.kernel = BVHKernel(trees, frontier=0, nested=True)
        self.triangles = device_array(Float, np.concatenate(tri_packets).ravel())
        self.corner_normals = (device_array(Float, np.concatenate(normal_packets).ravel())
                               if normal_packets else None)
        self.corner_uvs = (device_array(Float, np.concatenate(uv_packets).ravel())
                           if uv_packets else None)
        self.original_index = UInt32(np.concatenate(originals).astype(np.uint32))
        self.object_areas = [float(a.sum()) for a in areas]
        self.triangle_offsets = np.cumsum([0] + [len(a) for a in areas])[:-1]
        self.triangle_counts = np.array([len(a) for a in areas])
        self.triangle_total = int(self.triangle_counts.sum())
        # The total area is stored in float32 (area lights' densities): it must be normal there.
        tiny, largest = float(np.finfo(np.float32).tiny), float(np.finfo(np.float32).max)
        for name, total in zip(names, self.object_areas):
            if not tiny <= total <= largest:
                problem = ("vanish in float32 (coordinates below about 1e-19): scale it up"
                           if total < tiny else "overflow float32: scale it down")
                raise SceneError(f"{name}: the triangle areas (total {total:.3g}) {problem}")
        self.area_cdf = Float(np.concatenate([np.cumsum(a) / a.sum() for a in areas]).astype(np.float32))
        self._meshes = meshes
        self._orders = originals
        self._edges: dict[int, EdgeTopology] = {}

    def attribute_sources(self, mesh: int, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Where mesh ``mesh``'s attribute ``name`` goes in :meth:`attribute_corners`: the
        corners (global, in leaf order: 3 per triangle) and, per corner, the row of the
        attribute's values it takes (a vertex's, or for a face attribute its face's)."""
        order = self._orders[mesh]
        first = 3 * int(self.triangle_offsets[mesh])
        corners = first + np.arange(3 * len(order))
        if name.startswith("vertex_"):
            return corners, self._meshes[mesh].faces[order].ravel()
        return corners, np.repeat(order, 3)

    def set_attribute(self, mesh: int, name: str, values: np.ndarray) -> MeshData:
        """Give mesh ``mesh`` new values (same shape) of its attribute ``name``; returns the
        mesh with them."""
        data = self._meshes[mesh]
        self._meshes[mesh] = data._replace(attributes={**data.attributes, name: values})
        return self._meshes[mesh]

    def attribute_corners(self, name: str) -> np.ndarray:
        """Mesh attribute ``name`` at every triangle's corners in leaf order, (T, 3 corners, 3)
        float32: a one-value attribute as grey, 0 on the meshes without it."""
        parts = []
        for mesh, order in zip(self._meshes, self._orders):
            part = np.zeros((len(order), 3, 3), np.float32)
            if name in (mesh.attributes or {}):
                part[:] = mesh.attribute_corners(name)[order]
            parts.append(part)
        return np.concatenate(parts)

    def plane_sections(self, mesh: int, normal: np.ndarray, offset: np.ndarray) -> SectionParts:
        """Where mesh ``mesh`` meets the object-space planes ``normal . x = offset`` (M unit
        normals (M, 3), offsets (M,)): per crossed triangle, the segment between its two
        crossed edges, with the triangle's unit normal (:data:`SectionParts`)."""
        v = self.triangle_corners(mesh)  # (F, 3 corners, 3)
        face_normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        face_normal /= np.maximum(np.linalg.norm(face_normal, axis=1, keepdims=True), 1e-300)
        # The crossed triangles, a block of planes at a time (M x F distances at most
        # SECTION_BLOCK at once: a mesh resting on a finely tessellated one meets many planes).
        rows, faces, ds = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros((0, 3))]
        step = max(1, SECTION_BLOCK // max(len(v), 1))
        for first in range(0, len(normal), step):
            distance = (np.einsum("fcj,mj->mfc", v, normal[first:first + step])
                        - offset[first:first + step, None, None])  # (m, F, 3)
            above = distance > 0
            row, face = np.nonzero(above.any(axis=2) & ~above.all(axis=2))
            rows.append(row + first)
            faces.append(face)
            ds.append(distance[row, face])
        row, face, d = np.concatenate(rows), np.concatenate(faces), np.concatenate(ds)
        corners = v[face]
        # The two edges whose ends lie on opposite sides, each cut where the distance is 0.
        points = []
        for a, b in ((0, 1), (1, 2), (2, 0)):
            cut = (d[:, a] > 0) != (d[:, b] > 0)
            share = d[:, a] / np.where(cut, d[:, a] - d[:, b], 1.0)
            points.append((cut, corners[:, a] + (corners[:, b] - corners[:, a]) * share[:, None]))
        first = np.where(points[0][0][:, None], points[0][1], points[1][1])
        second = np.where(points[2][0][:, None], points[2][1], points[1][1])
        return (row, np.zeros(len(row), bool), first, second - first, np.zeros_like(first),
                np.full(len(row), NORMAL_STORED), face_normal[face])

    def terminator_arcs(self, mesh: int, viewpoints: np.ndarray) -> tuple[np.ndarray, ...]:
        """Where the smooth shading of mesh ``mesh`` turns away from the object-space
        points ``viewpoints`` (M, 3), or homogeneous ones (M, 4) (w = 0: a viewer at infinity
        in direction c): inside each triangle, the curve on which the
        interpolated normal is perpendicular to the line of sight,
        ``g(x) = sn(x) . (c - w x) = 0`` (a conic in the barycentrics; Mitsuba's one-sided
        BSDFs go black where g < 0, so the reflected light jumps there). Per triangle whose
        corners' g change sign, the arc between its two crossed edges: returns (row (K,),
        leaf-order triangle position (K,), start A (K, 3), chord B - A (K, 3), unit
        in-plane normal of the chord (K, 3)); the arc is ``A + s (B - A) + h(s) normal``
        (:meth:`terminator_point`). An arc that enters and leaves by one edge is not found.
        """
        data = self._meshes[mesh]
        if data.normals is None:
            empty = np.zeros((0, 3))
            return np.zeros(0, np.int64), np.zeros(0, np.int64), empty, empty, empty
        v, n = data.vertices[data.faces], data.normals  # (F, 3 corners, 3)
        viewpoints = np.asarray(viewpoints, np.float64)
        if viewpoints.shape[1] == 3:
            viewpoints = np.concatenate([viewpoints, np.ones((len(viewpoints), 1))], axis=1)
        face_normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        rows, faces, starts, chords = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [], []
        step = max(1, SECTION_BLOCK // max(len(v), 1))
        for first in range(0, len(viewpoints), step):
            c = viewpoints[first:first + step, None, None, :3]  # (m, 1, 1, 3)
            w = viewpoints[first:first + step, None, None, 3:]  # (m, 1, 1, 1)
            g = np.einsum("fcj,mfcj->mfc", n, c - w * v[None])
            positive = g > 0
            row, face = np.nonzero(positive.any(axis=2) & ~positive.all(axis=2))
            points = []
            for a, b in ((0, 1), (1, 2), (2, 0)):
                # g on the edge a -> b, quadratic in t; its one root in [0, 1] where the
                # corners' signs differ.
                dv, dn = v[face, b] - v[face, a], n[face, b] - n[face, a]
                w_k = w[row, 0, 0, 0]
                q = c[row, 0, 0] - w_k[:, None] * v[face, a]
                c0 = g[row, face, a]
                c1 = np.einsum("kj,kj->k", dn, q) - w_k * np.einsum("kj,kj->k", n[face, a], dv)
                c2 = -w_k * np.einsum("kj,kj->k", dn, dv)
                t = _root_in_unit_interval(c2, c1, c0)
                points.append((positive[row, face, a] != positive[row, face, b],
                               v[face, a] + t[:, None] * dv))
            (cut0, p0), (cut1, p1), (_, p2) = points
            a_point = np.where(cut0[:, None], p0, p1)
            b_point = np.where(cut0[:, None] & cut1[:, None], p1, p2)
            rows.append(row + first)
            faces.append(face)
            starts.append(a_point)
            chords.append(b_point - a_point)
        row, face = np.concatenate(rows), np.concatenate(faces)
        start = np.concatenate(starts) if starts else np.zeros((0, 3))
        chord = np.concatenate(chords) if chords else np.zeros((0, 3))
        normal = np.cross(face_normal[face], chord)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        return row, self._leaf_position[mesh][face], start, chord, normal

    def terminator_point(self, position: UInt32, start: Array3f, chord: Array3f,
                         normal: Array3f, s: Float, c: Array3f, w: float = 1.0
                         ) -> tuple[Array3f, Array3f, Bool]:
        """The point of a terminator arc (:meth:`terminator_arcs`) at parameter s seen from
        the homogeneous object-space point (c, w) (w = 0: a viewer at infinity in direction
        c; AD attached: the arc slides over the triangle as c moves,
        and the point with it), its tangent d x / ds (detached) and whether it lies in the
        triangle. The point is ``P + h normal`` with ``P = start + s chord`` and h the root
        of ``g(P + h normal) = 0`` nearest 0 (a quadratic: along a line in the triangle,
        sn and x are linear)."""
        v0, e1, e2 = self._triangle(position)
        n0, n1, n2 = self._corners(position, self.corner_normals)
        a11, a12, a22 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
        det = a11 * a22 - a12 * a12

        def barycentric(w):
            # (u, v) of an in-plane vector w = u e1 + v e2.
            b1, b2 = dr.dot(w, e1), dr.dot(w, e2)
            return (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det

        def shading(w, u_v):
            return (n1 - n0) * u_v[0] + (n2 - n0) * u_v[1] + w

        point = dr.fma(chord, s, start)
        sn_p = shading(n0, barycentric(point - v0))
        sn_h = shading(Array3f(0.0), barycentric(normal))
        q = c - w * point
        a = -w * dr.dot(sn_h, normal)
        b = dr.dot(sn_h, q) - w * dr.dot(sn_p, normal)
        c0 = dr.dot(sn_p, q)
        disc = dr.fma(b, b, -4.0 * a * c0)
        # The root nearest 0, in the form without cancellation.
        root = dr.sqrt(dr.maximum(disc, 0.0))
        h = -2.0 * c0 / (b + dr.select(b >= 0, root, -root))
        x = point + normal * h
        with dr.suspend_grad():
            # d x / ds by implicit differentiation: g(P(s) + h(s) normal) = 0.
            x0, c_0 = dr.detach(x), dr.detach(c)
            sn_x = shading(n0, barycentric(x0 - v0))

            def slope(step):
                return dr.dot(shading(Array3f(0.0), barycentric(step)), c_0 - w * x0) - w * dr.dot(sn_x, step)

            tangent = chord - normal * (slope(chord) / slope(normal))
            u, v = barycentric(x0 - v0)
            slack = 1e-5
            inside = (disc >= 0) & (u >= -slack) & (v >= -slack) & (u + v <= 1.0 + slack)
        return x, tangent, inside & dr.isfinite(h)

    def triangle_corners(self, mesh: int) -> np.ndarray:
        """The triangles of mesh ``mesh`` as (F, 3 corners, 3) float64 object-space points."""
        data = self._meshes[mesh]
        return data.vertices[data.faces]

    def plane(self, mesh: int) -> tuple[np.ndarray, float] | None:
        """The object-space plane (unit normal n, offset c: n . x = c) that every triangle of
        mesh ``mesh`` lies in (a flat floor or panel, within float32 rounding of its extent),
        or None; computed once per mesh."""
        if mesh not in self._planes:
            corners = self.triangle_corners(mesh)
            normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            largest = np.argmax(np.linalg.norm(normals, axis=1))
            normal = normals[largest] / np.linalg.norm(normals[largest])
            offset = float(corners[largest, 0] @ normal)
            extent = float(np.ptp(corners.reshape(-1, 3), axis=0).max())
            flat = np.abs(corners.reshape(-1, 3) @ normal - offset).max() <= FLAT_TOLERANCE * extent
            self._planes[mesh] = (normal, offset) if flat else None
        return self._planes[mesh]

    def edges(self, mesh: int) -> EdgeTopology:
        """The edge topology of mesh ``mesh`` (for its discontinuity curves), built on first use."""
        if mesh not in self._edges:
            data = self._meshes[mesh]
            self._edges[mesh] = EdgeTopology.of_mesh(data.vertices, data.faces, data.normals)
        return self._edges[mesh]

    def silhouette_edges(self, meshes: list[int]) -> "SilhouetteEdges":
        """The edges of meshes ``meshes`` that can be silhouettes, rims or shading jumps
        (:meth:`~instancing.models.curves.EdgeTopology.possible_silhouettes`), as device
        arrays, with each mesh's (first, count) into them."""
        fields, jumps, first, count = [], [], [], []
        for mesh in meshes:
            topology = self.edges(mesh)
            keep = topology.possible_silhouettes()
            manifold = topology.face1 >= 0
            normal1 = np.where(manifold[:, None],
                               topology.face_normal[np.where(manifold, topology.face1, 0)], 0.0)
            # In a fixed random order: neighbouring edges share their fate (silhouette loops),
            # and the draws along u should not.
            order = np.flatnonzero(keep)
            order = order[np.random.default_rng(mesh).permutation(len(order))]
            fields.append([a[order] for a in (topology.start, topology.direction,
                                              topology.face_normal[topology.face0], normal1)])
            jumps.append(topology.shading_jump[order])
            first.append(sum(count))
            count.append(int(keep.sum()))
        arrays = [np.concatenate(parts) for parts in zip(*fields)]
        floats = device_arrays(Float, *[a[:, k] for a in arrays for k in range(3)],
                               np.concatenate(jumps).astype(np.float32))
        return SilhouetteEdges(*[Array3f(*floats[3 * f:3 * f + 3]) for f in range(4)], floats[12],
                               np.array(first, np.int64), np.array(count, np.int64))

    def _triangle(self, position: UInt32, vector=Array3f) -> tuple[Array3f, Array3f, Array3f]:
        """(v0, e1 = v1 - v0, e2 = v2 - v0) of the triangle at ``position`` in the precision of
        ``vector`` (Array3f or Array3f64; the float32 corners' edges are exact in float64)."""
        v0, v1, v2 = (vector(c) for c in self._corners(position))
        return v0, v1 - v0, v2 - v0

    def _corners(self, position: UInt32, packed: Float | None = None
                 ) -> tuple[Array3f, Array3f, Array3f]:
        """The float32 corners (v0, v1, v2) of the triangle at ``position`` (of ``packed``:
        its corner normals): two packet loads and one gather."""
        packed = self.triangles if packed is None else packed
        a = dr.gather(Array4f, packed, position * 3)
        b = dr.gather(Array4f, packed, position * 3 + 1)
        z2 = dr.gather(Float, packed, position * 12 + 8)
        return Array3f(a.x, a.y, a.z), Array3f(a.w, b.x, b.y), Array3f(b.z, b.w, z2)

    @staticmethod
    def _moller_trumbore(o: Array3f, d: Array3f, triangle: tuple):
        """(t, u, v, inside) of the ray and the plane of ``triangle`` (v0, e1, e2):
        barycentrics u, v of the crossing and whether it lies in the triangle (in the
        precision of the ray; not watertight, used for the known triangle of phase 2)."""
        v0, e1, e2 = triangle
        pvec = dr.cross(d, e2)
        det = dr.dot(e1, pvec)
        inv_det = dr.rcp(det)
        tvec = o - v0
        u = dr.dot(tvec, pvec) * inv_det
        qvec = dr.cross(tvec, e1)
        v = dr.dot(d, qvec) * inv_det
        t = dr.dot(e2, qvec) * inv_det
        return t, u, v, (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1)

    @staticmethod
    def ray_frame(o: Array3f, d: Array3f) -> tuple:
        """Per-ray constants of the watertight test (Woop et al. 2013, section 3).

        Args:
            o, d: object-space float32 rays (Array3f, width N; d need not be unit).

        Returns ``(k, o_perm, shear)``: ``k = (kx, ky, kz)`` (UInt32) with ``kz`` the
        axis of the largest ``|d|`` component and ``kx, ky`` the next two cyclically
        (which keeps the winding, so the sign of det is the orientation); the origin's
        components in that order; and the shear ``(-d_kx / d_kz, -d_ky / d_kz, 1 / d_kz)``
        that maps the ray onto +z. Computed once per (ray, instance), before traversal.
        """
        ax, ay, az = dr.abs(d.x), dr.abs(d.y), dr.abs(d.z)
        kz = dr.select(ax > ay, dr.select(ax > az, UInt32(0), UInt32(2)),
                       dr.select(ay > az, UInt32(1), UInt32(2)))
        kx = dr.select(kz == 2, UInt32(0), kz + 1)
        ky = dr.select(kx == 2, UInt32(0), kx + 1)

        dz = permuted(d, kz)
        shear = (-permuted(d, kx) / dz, -permuted(d, ky) / dz, dr.rcp(dz))
        return (kx, ky, kz), (permuted(o, kx), permuted(o, ky), permuted(o, kz)), shear

    def intersect_triangle(self, frame: tuple, position: UInt32, t_max: Float) -> Float:
        """Watertight test of the triangle at leaf-order ``position``: t in (0, t_max) or inf.

        Woop, Benthin & Wald (JCGT 2013) and pbrt-v4's ``IntersectTriangle``, in float32,
        on the ray given by its :meth:`ray_frame`. Every edge function has its exact sign
        (:func:`difference_of_products`; an exact 0 is recomputed in float64 in case its
        products underflowed). Triangles sharing an edge compute its edge function from
        the same transformed corners, so they decide the same way which side of it a ray
        passes, and a ray through their edge (or shared vertex) hits all of them: no ray
        slips through a closed mesh (watertight). Both windings count. t is in units of
        the ray's direction. Unlike pbrt-v4, no conservative margin is added to the t > 0
        test: spawned rays are offset instead (:mod:`instancing.core.ray_offset`).
        """
        (kx, ky, kz), (ox, oy, oz), (sx, sy, sz) = frame
        # Translate the corners by the ray origin, permute the axes per lane, and shear so
        # that the ray runs along +z from the origin. (Gathering the permuted components
        # one by one, nine scalar gathers, measured slower than the packet loads and selects.)
        corners = []
        for v in self._corners(position):
            px = permuted(v, kx) - ox
            py = permuted(v, ky) - oy
            pz = permuted(v, kz) - oz
            corners.append((dr.fma(sx, pz, px), dr.fma(sy, pz, py), pz))
        (x0, y0, z0), (x1, y1, z1), (x2, y2, z2) = corners
        # Edge functions: twice the signed areas of the triangles (0, p1, p2), (0, p2, p0),
        # (0, p0, p1) in the xy plane, each formed from one edge's corners only, with the
        # error-compensated difference of products: within 2 ulp, so of the exact sign.
        e0 = difference_of_products(x1, y2, y1, x2)
        e1 = difference_of_products(x2, y0, y2, x0)
        e2 = difference_of_products(x0, y1, y0, x1)
        # An exact 0 can still be a tiny product flushed or underflowed in float32: redo
        # it in float64, where the products of float32 numbers are exact (pbrt-v4). On all
        # lanes with a select: measured no slower than a symbolic if (within 5 % noise).
        edge = (e0 == 0) | (e1 == 0) | (e2 == 0)
        e0 = dr.select(edge, Float(Float64(x1) * Float64(y2) - Float64(y1) * Float64(x2)), e0)
        e1 = dr.select(edge, Float(Float64(x2) * Float64(y0) - Float64(y2) * Float64(x0)), e1)
        e2 = dr.select(edge, Float(Float64(x0) * Float64(y1) - Float64(y0) * Float64(x1)), e2)
        # Inside when no edge function has a sign opposite to another's (either winding).
        outside = ((e0 < 0) | (e1 < 0) | (e2 < 0)) & ((e0 > 0) | (e1 > 0) | (e2 > 0))
        det = e0 + e1 + e2
        # Scaled distance sum(e_i z_i) / det, z in units of the ray direction.
        t_scaled = dr.fma(e0, z0 * sz, dr.fma(e1, z1 * sz, e2 * (z2 * sz)))
        t = t_scaled / det
        return dr.select(~outside & (det != 0) & (t > 0) & (t < t_max), t, dr.inf)

    def surface_point(self, o: Array3f, d: Array3f, position: UInt32
                      ) -> tuple[Float, Array3f, Array3f, tuple]:
        """(t, object-space hit point, object-space shading normal, barycentrics (b1, b2))
        on the known triangle at ``position``, t = inf if missed.

        The point is interpolated from the barycentrics, ``v0 + u e1 + v e2``
        (pbrt-v4): it lies in the triangle's plane up to a few roundings of the
        vertices' magnitude, whereas ``o + t d`` carries the error of a far origin.
        Computed in the precision of the ray (float64 in phase 2) by Moller-Trumbore,
        which is not watertight: a ray through an edge may miss here, and the caller
        then keeps phase 1's t (see :func:`instancing.scene.intersection.reintersect`).
        The shading normal is the corner normals interpolated with the same
        barycentrics (not normalized; the geometric normal where the library has no
        corner normals).
        """
        v0, e1, e2 = triangle = self._triangle(position, type(o))
        t, u, v, inside = self._moller_trumbore(o, d, triangle)
        if self.corner_normals is None:
            shading = dr.cross(e1, e2)
        else:
            n0, n1, n2 = (type(o)(c) for c in self._corners(position, self.corner_normals))
            shading = dr.fma(n2 - n0, v, dr.fma(n1 - n0, u, n0))
        return (dr.select(inside & (t > 0), t, dr.inf), dr.fma(e2, v, dr.fma(e1, u, v0)), shading,
                (u, v))

    def uv(self, position: UInt32, b1, b2):
        """The surface coordinates at barycentrics (b1, b2) of the triangle at ``position``:
        its corner uvs interpolated, or (b1, b2) where the library has none (Mitsuba's
        rule for a mesh without texture coordinates); in the precision of b1."""
        vector = type(b1)
        if self.corner_uvs is None:
            return b1, b2
        base = position * 6
        c = [vector(dr.gather(Float, self.corner_uvs, base + k)) for k in range(6)]
        b0 = 1.0 - b1 - b2
        return (dr.fma(c[0], b0, dr.fma(c[2], b1, c[4] * b2)),
                dr.fma(c[1], b0, dr.fma(c[3], b1, c[5] * b2)))

    def derivatives(self, position: UInt32, vector=Array3f) -> tuple[Array3f, Array3f]:
        """The object-space derivatives (dp/du, dp/dv) of the point on the triangle at
        ``position`` (Mitsuba's, from its corner uvs; where its mesh has none, u and v are the
        barycentrics b1, b2 and the derivatives the edges v1 - v0, v2 - v0), as ``vector``; 0
        where the uvs do not span the triangle (Mitsuba then orients by the normal)."""
        _, e1, e2 = self._triangle(position, vector)
        if self.corner_uvs is None:
            return e1, e2
        c = [dr.value_t(vector)(dr.gather(Float, self.corner_uvs, position * 6 + k)) for k in range(6)]
        du1, dv1, du2, dv2 = c[2] - c[0], c[3] - c[1], c[4] - c[0], c[5] - c[1]
        det = dr.fma(du1, dv2, -dv1 * du2)
        spans = det != 0
        return (dr.select(spans, (e1 * dv2 - e2 * dv1) / det, vector(0.0)),
                dr.select(spans, (e2 * du1 - e1 * du2) / det, vector(0.0)))

    def point_error(self, position: UInt32) -> Array3f:
        """Componentwise object-space error bound of a point interpolated in the triangle
        (hit or sample): gamma(7) (|v0| + |e1| + |e2|), pbrt-v4's bound with weights <= 1."""
        v0, e1, e2 = self._triangle(position)
        return gamma(7) * (dr.abs(v0) + dr.abs(e1) + dr.abs(e2))

    def intersect(self, o: Array3f, d: Array3f, t_max: Float, active: Bool,
                  root_ref: UInt32, any_hit: bool = False) -> tuple[Float, UInt32]:
        """Nearest triangle hit of object-space rays through the mesh whose root is ``root_ref``.

        Returns ``(t, position)`` with t = inf where nothing is hit in (0, t_max);
        ``position`` is the leaf-order triangle index (see :meth:`prim_index`).
        With ``any_hit`` (shadow rays), traversal stops at the first triangle hit,
        whose t is returned.
        """

        frame = self.ray_frame(o, d)
        return self.kernel.nearest(o, d, t_max, active, root_ref, any_hit,
                                   lambda position, t_best: self.intersect_triangle(frame, position, t_best))

    def sample_area(self, first: UInt32, count: UInt32, u1: Float, u2: Float
                    ) -> tuple[Array3f, UInt32, tuple[Float, Float]]:
        """A point uniform by object-space area on the mesh whose triangles are
        ``first .. first + count - 1`` (leaf order), its triangle position and its
        barycentrics (b1, b2) there."""
        # Pick a triangle by the area CDF, then a uniform point in it.
        # The predicate is monotone over the whole concatenated CDF: true before this
        # mesh's segment, then while the segment's CDF stays <= u1.
        last = first + count - 1
        position = dr.binary_search(
            0, self.triangle_total - 1,
            lambda i: (i < first) | ((i <= last) & (dr.gather(Float, self.area_cdf, i) <= u1)))
        position = dr.minimum(position, last)
        # What is left of u1 within the triangle's stretch of the CDF, stretched back to
        # [0, 1), places the point with u2 (as Mitsuba reuses the sample that picks the
        # triangle): the points of a stratified pair stay stratified on each triangle.
        end = dr.gather(Float, self.area_cdf, position)
        later = position > first
        start = dr.select(later, dr.gather(Float, self.area_cdf, position - 1, later), 0.0)
        u1 = dr.clip((u1 - start) / dr.maximum(end - start, 1e-30), 0.0, 1.0)
        v0, e1, e2 = self._triangle(position)
        root = dr.sqrt(u1)
        b1, b2 = 1.0 - root, u2 * root
        return dr.fma(e2, b2, dr.fma(e1, b1, v0)), position, (b1, b2)

    def prim_index(self, position: UInt32) -> UInt32:
        """The triangle's index in its mesh file, from its leaf-order position."""
        return dr.gather(UInt32, self.original_index, position)

    def normal(self, position: UInt32, vector=Array3f) -> Array3f:
        """Geometric object-space normal cross(e1, e2) (not normalized), as ``vector``."""
        _, e1, e2 = self._triangle(position, vector)
        return dr.cross(e1, e2)

