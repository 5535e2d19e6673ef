"""Discontinuity curves of models in object space, and the edge topology of polyhedra.

Where an image (or the light arriving at a point) jumps across a curve that moves with
a parameter, its derivative gains a line integral over that curve (Li et al.,
"Differentiable Monte Carlo Ray Tracing through Edge Sampling", 2018). Affine maps send
rays tangent to a model to rays tangent to its instance, so the curves an instance
shows from a world point x are the images of the curves its model shows from
``M^-1 x``: each model computes them in object space, in closed form, for many
viewpoints at once (as Mitsuba's ``Shape::sample_silhouette`` serves its shapes).

A model's curves from viewpoints (M, 3) come as :data:`CurveParts`: for K curves, the
row of the viewpoint each belongs to (K,), whether it is a circle (K,), and its
``c``, ``u``, ``v`` (K, 3) in the parameterisation of :class:`Curves`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Two faces are coplanar (no shading jump) when their unit normals differ by less.
COPLANAR_TOLERANCE = 1e-6

#: The smallest jump scale of a mesh crease (:attr:`EdgeTopology.jump_scale`): shading can
#: jump across a shallow crease by more than its normals' turn (a glossy highlight), so no
#: crease is drawn less than a tenth as often per unit of film length as a silhouette.
CREASE_SCALE_FLOOR = 0.1

#: (viewpoint row, circle flag, c, u, v) of K curves; see the module docstring.
CurveParts = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class Curves:
    """Discontinuity curves in object space: ``x(s) = c + u a(s) + v b(s)``, s in [0, 1).

    Segments: ``a = s, b = 0`` (from c to c + u). Circles: ``a = cos 2 pi s,
    b = sin 2 pi s``. All arrays float64 (K, 3), ``instance`` and ``circle`` (K,).
    ``scale`` (K,): how large the jump across each curve is expected to be against an
    occluding silhouette's (1), which scales how often it is drawn (None: 1 for all).
    """

    instance: np.ndarray
    circle: np.ndarray
    c: np.ndarray
    u: np.ndarray
    v: np.ndarray
    scale: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.instance)

    @property
    def scales(self) -> np.ndarray:
        """(K,) the curves' jump scales (see the class docstring)."""
        return np.ones(len(self)) if self.scale is None else self.scale

    @staticmethod
    def joined(parts: "list[Curves]") -> "Curves":
        """The curves of ``parts`` (at least one), in order."""
        scale = (None if all(c.scale is None for c in parts)
                 else np.concatenate([c.scales for c in parts]))
        return Curves(*[np.concatenate([getattr(c, f) for c in parts])
                        for f in ("instance", "circle", "c", "u", "v")], scale=scale)

    def subset(self, keep: np.ndarray) -> "Curves":
        """The curves where the boolean mask ``keep`` (K,) is set, in order."""
        if keep.all():
            return self
        return Curves(*[getattr(self, f)[keep] for f in ("instance", "circle", "c", "u", "v")],
                      scale=None if self.scale is None else self.scale[keep])

    def points(self, s: np.ndarray) -> np.ndarray:
        """Object-space points (K, S, 3) at parameters s (S,)."""
        a = np.where(self.circle[:, None], np.cos(2 * np.pi * s)[None], s[None])
        b = np.where(self.circle[:, None], np.sin(2 * np.pi * s)[None], 0.0)
        return self.c[:, None] + self.u[:, None] * a[..., None] + self.v[:, None] * b[..., None]


#: How a contact curve knows the model's object-space normal at its points: stored per curve
#: (flat pieces), the point itself (sphere), or (x, y, 0) (cylinder, whose sections are
#: also clipped to 0 <= z <= 1).
NORMAL_STORED, NORMAL_SPHERE, NORMAL_CYLINDER = 0, 1, 2

#: (row of the plane, circle flag, c, u, v, normal code, stored normal (K, 3)) of K curves
#: where a model meets planes.
SectionParts = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                     np.ndarray]


def sections_of(pieces: list[tuple]) -> SectionParts:
    """:data:`SectionParts` from per-plane pieces ``(keep (M,), circle, c, u, v (M, 3),
    normal code, stored normal (M, 3))``."""
    rows, circle, c, u, v, code, normal = [], [], [], [], [], [], []
    for keep, is_circle, c_k, u_k, v_k, code_k, n_k in pieces:
        which = np.flatnonzero(keep)
        rows.append(which)
        circle.append(np.full(len(which), is_circle))
        code.append(np.full(len(which), code_k))
        for out, a in ((c, c_k), (u, u_k), (v, v_k), (normal, n_k)):
            out.append(a[which])
    return tuple(np.concatenate(a) for a in (rows, circle, c, u, v, code, normal))


def square_chord(normal: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the lines ``normal . (x, y) = offset`` (M lines, normal (M, 2)) cross the square
    [-1, 1]^2: (keep (M,), start (M, 2), start-to-end vector (M, 2)); Liang-Barsky clipping."""
    length2 = np.einsum("ij,ij->i", normal, normal)
    safe = np.maximum(length2, 1e-300)
    point = normal * (offset / safe)[:, None]
    direction = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
    lo, hi = np.full(len(normal), -np.inf), np.full(len(normal), np.inf)
    for k in range(2):
        d, p = direction[:, k], point[:, k]
        moving = np.abs(d) > 1e-300
        a = np.where(moving, (-1.0 - p) / np.where(moving, d, 1.0), -np.inf)
        b = np.where(moving, (1.0 - p) / np.where(moving, d, 1.0), np.inf)
        lo = np.maximum(lo, np.minimum(a, b))
        hi = np.minimum(hi, np.maximum(a, b))
        # A line parallel to this axis crosses the square only if it lies within it.
        lo = np.where(~moving & (np.abs(p) > 1.0), np.inf, lo)
    keep = (length2 > 1e-24) & (lo < hi)
    lo, hi = np.where(keep, lo, 0.0), np.where(keep, hi, 0.0)
    return keep, point + direction * lo[:, None], direction * (hi - lo)[:, None]


def parts_of(pieces: list[tuple]) -> CurveParts:
    """:data:`CurveParts` from per-viewpoint pieces ``(keep (M,), circle, c, u, v (M, 3))``:
    the curves of the viewpoints where ``keep`` holds."""
    rows, circle, c, u, v = [], [], [], [], []
    for keep, is_circle, c_k, u_k, v_k in pieces:
        which = np.flatnonzero(keep)
        rows.append(which)
        circle.append(np.full(len(which), is_circle))
        c.append(c_k[which])
        u.append(u_k[which])
        v.append(v_k[which])
    return (np.concatenate(rows), np.concatenate(circle), np.concatenate(c), np.concatenate(u),
            np.concatenate(v))


def orthonormal_pair(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (M, 3) perpendicular to the unit vectors n and to each other."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    a = np.cross(n, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return a, np.cross(n, a)


def _apart(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(E,) whether the unit normals a, b (E, 3) differ: not parallel within
    COPLANAR_TOLERANCE, or opposite."""
    return ((np.linalg.norm(np.cross(a, b), axis=1) > COPLANAR_TOLERANCE)
            | (np.einsum("ij,ij->i", a, b) < 0))


@dataclass(frozen=True)
class EdgeTopology:
    """Edges of a triangle mesh with their (up to two) faces, for crease/silhouette tests."""

    start: np.ndarray     # (E, 3) first vertex
    direction: np.ndarray  # (E, 3) second vertex minus first
    face0: np.ndarray     # (E,) a face on the edge
    face1: np.ndarray     # (E,) the other face, or -1 for boundary / non-manifold edges
    face_point: np.ndarray   # (F, 3) a vertex of each face
    face_normal: np.ndarray  # (F, 3) unit normals (cross(e1, e2) orientation)
    shading_jump: np.ndarray  # (E,) whether light reflected there can jump across the edge
    jump_scale: np.ndarray  # (E,) how far the normals turn there, against a silhouette's 1

    @staticmethod
    def of_mesh(vertices: np.ndarray, faces: np.ndarray,
                normals: np.ndarray | None = None) -> "EdgeTopology":
        """The edges of the triangles ``faces`` (F, 3) of ``vertices`` (V, 3). Reflected light
        can jump across an edge where its faces are not coplanar, even under smooth shading:
        the geometric normal turns there, and it decides which directions the surface
        itself blocks (a point light just past the mesh's silhouette seen from it lights
        one face and not the other); and, with corner ``normals`` (F, 3, 3), where the two
        faces' normals at either end differ. How much it jumps there scales with how far the
        normals turn (a diffuse surface's shading by at most the normals' difference): the
        edge's jump scale is the length of the difference of its faces' unit normals (or of
        their corner normals at an end, the larger), between CREASE_SCALE_FLOOR and 1; 1 for
        an edge of fewer or more than two faces."""
        v = vertices[faces]
        normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        owner = np.tile(np.arange(len(faces)), 3)
        key = np.sort(pairs, axis=1)
        order = np.lexsort((key[:, 1], key[:, 0]))
        key, owner = key[order], owner[order]
        first = np.ones(len(key), bool)
        first[1:] = np.any(key[1:] != key[:-1], axis=1)
        starts = np.flatnonzero(first)
        counts = np.diff(np.append(starts, len(key)))
        face0 = owner[starts]
        # Manifold edges have exactly two faces; others are always discontinuities.
        face1 = np.where(counts == 2, owner[np.minimum(starts + 1, len(key) - 1)], -1)
        edge = key[starts]
        manifold = face1 >= 0
        other = np.where(manifold, face1, face0)
        jump = _apart(normal[face0], normal[other])
        turn = np.linalg.norm(normal[face0] - normal[other], axis=1)
        if normals is not None:
            unit = normals / np.maximum(np.linalg.norm(normals, axis=2, keepdims=True), 1e-300)
            for end in (0, 1):
                # Each face's corner normal at this end of the edge.
                at = [unit[f, np.argmax(faces[f] == edge[:, end][:, None], axis=1)]
                      for f in (face0, other)]
                jump |= _apart(*at)
                turn = np.maximum(turn, np.linalg.norm(at[0] - at[1], axis=1))
        scale = np.where(manifold, np.clip(turn, CREASE_SCALE_FLOOR, 1.0), 1.0)
        return EdgeTopology(vertices[edge[:, 0]], vertices[edge[:, 1]] - vertices[edge[:, 0]],
                            face0, face1, v[:, 0], normal, jump | ~manifold, scale)

    def _creases(self) -> tuple[np.ndarray, np.ndarray]:
        """(manifold (E,), crease (E,)): edges with two faces, and those whose two faces are
        not coplanar (or face opposite ways)."""
        manifold = self.face1 >= 0
        f1 = np.where(manifold, self.face1, self.face0)
        return manifold, _apart(self.face_normal[self.face0], self.face_normal[f1])

    def possible_silhouettes(self) -> np.ndarray:
        """(E,) the edges that are a silhouette, rim or shading jump from some viewpoint:
        all but the edges between coplanar faces with the same normals on both."""
        manifold, crease = self._creases()
        return ~manifold | crease | self.shading_jump

    def discontinuity_curves(self, viewpoints: np.ndarray, creases: bool = True) -> CurveParts:
        """The edges that can show a jump seen from the homogeneous viewpoints (M, 4), as
        segments (a face is seen from (c, w) where (c - w f) . n > 0, f on the face):
        silhouette and boundary edges, and with ``creases`` the edges where shading
        jumps (:attr:`shading_jump`) between faces of which one is seen (not needed for
        shadows, which only silhouettes cast)."""
        return self.scaled_discontinuity_curves(viewpoints, creases)[0]

    def scaled_discontinuity_curves(self, viewpoints: np.ndarray, creases: bool = True
                                    ) -> tuple[CurveParts, np.ndarray]:
        """:meth:`discontinuity_curves` and their jump scales (:attr:`Curves.scale`): 1 for
        silhouette and boundary edges, where a surface ends in front of another;
        :attr:`jump_scale` for a crease between two faces that both face the viewer."""
        cam, w = viewpoints[:, None, :3], viewpoints[:, None, 3:]
        facing = np.einsum("mfj,fj->mf", cam - w * self.face_point[None], self.face_normal) > 0
        manifold = self.face1 >= 0
        f1 = np.where(manifold, self.face1, self.face0)
        ends = ~manifold[None] | (facing[:, self.face0] != facing[:, f1])
        keep = ends
        if creases:
            keep = ends | (self.shading_jump[None] & (facing[:, self.face0] | facing[:, f1]))
        which, edge = np.nonzero(keep)
        parts = (which, np.zeros(len(edge), bool), self.start[edge], self.direction[edge],
                 np.zeros((len(edge), 3)))
        return parts, np.where(ends[which, edge], 1.0, self.jump_scale[edge])


#: The curved analytic models as quadrics in object space: ``sum_k D_k x_k^2 = 1`` with these
#: diagonals D (the cylinder's tube is the part with 0 <= z <= 1).
QUADRIC_DIAGONALS = {"sphere": (1.0, 1.0, 1.0), "cylinder": (1.0, 1.0, 0.0)}
#: Rows and columns of the grid over a curved model's surface on which the curve where it
#: meets another quadric is traced: a loop narrower than about a cell may be missed.
INTERSECTION_GRID = (96, 192)
#: Regula falsi steps per grid edge that the curve crosses (to float64 roundoff from a cell).
CROSSING_STEPS = 16
#: How far the grid over a cylinder's tube reaches past its ends (in z), so that a curve
#: leaving the tube is traced up to its rim (points past it are not on the surface).
TUBE_MARGIN = 0.05


def quadric_intersection(kind_a: str, kind_b: str, linear: np.ndarray,
                         offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The curve where the surface of curved model ``kind_a`` meets the quadric of
    ``kind_b``, as segments in a's object space: (start (S, 3), start-to-end (S, 3)).

    ``linear`` (3, 3) and ``offset`` (3,) map a's object space to b's. The quadric of b is
    traced on a grid over a's surface (marching squares); every vertex is the root of b's
    equation along a grid edge, found by bisection in float64, so it lies on both surfaces
    and neighbouring segments share it exactly. A cylinder's tube is traced a little past
    its ends, and b's cylinder is taken as infinite: the caller keeps the points within
    both surfaces' extents.
    """
    rows, cols = INTERSECTION_GRID
    d_b = np.asarray(QUADRIC_DIAGONALS[kind_b])
    phi = 2.0 * np.pi * np.arange(cols + 1) / cols  # the last column is the first again
    if kind_a == "sphere":
        # Poles perpendicular to the direction of b's centre, so that a loop around it
        # keeps away from them.
        centre = -np.linalg.solve(linear, offset) if abs(np.linalg.det(linear)) > 0 else offset
        size = np.linalg.norm(centre)
        toward = centre / size if size > 1e-12 else np.array([1.0, 0.0, 0.0])
        pole, e1 = orthonormal_pair(toward[None])
        pole, e1 = pole[0], e1[0]
        e2 = np.cross(pole, e1)
        ring = np.linspace(0.0, np.pi, rows + 1)

        def surface(r, p):
            return (np.sin(r)[..., None] * (np.cos(p)[..., None] * e1 + np.sin(p)[..., None] * e2)
                    + np.cos(r)[..., None] * pole)
    else:
        ring = np.linspace(-TUBE_MARGIN, 1.0 + TUBE_MARGIN, rows + 1)

        def surface(r, p):
            return np.stack(np.broadcast_arrays(np.cos(p), np.sin(p), r), axis=-1)

    def quadric(x):
        y = x @ linear.T + offset
        return np.einsum("...k,k->...", y * y, d_b) - 1.0

    negative = quadric(surface(ring[:, None], phi[None, :])) < 0.0  # (rows + 1, cols + 1)
    if negative.all() or not negative.any():
        return np.zeros((0, 3)), np.zeros((0, 3))

    def crossings(r0, r1, p0, p1):
        # The root of b's equation along the grid edges from (r0, p0) to (r1, p1), which
        # bracket one: regula falsi with the Illinois rule (the end kept twice in a row has
        # its value halved), superlinear and never leaving the bracket.
        def value(t):
            return quadric(surface(r0 + (r1 - r0) * t, p0 + (p1 - p0) * t))
        lo, hi = np.zeros(len(r0)), np.ones(len(r0))
        f_lo, f_hi = value(lo), value(hi)
        side = np.zeros(len(r0))
        for _ in range(CROSSING_STEPS):
            t = np.clip((lo * f_hi - hi * f_lo) / np.where(f_hi != f_lo, f_hi - f_lo, 1.0), lo, hi)
            f = value(t)
            low = np.sign(f) == np.sign(f_lo)
            lo, f_lo = np.where(low, t, lo), np.where(low, f, f_lo)
            hi, f_hi = np.where(low, hi, t), np.where(low, f_hi, f)
            f_hi = np.where(low & (side > 0), 0.5 * f_hi, f_hi)
            f_lo = np.where(~low & (side < 0), 0.5 * f_lo, f_lo)
            side = np.where(low, 1.0, -1.0)
        t = np.where(np.abs(f_lo) <= np.abs(f_hi), lo, hi)
        return surface(r0 + (r1 - r0) * t, p0 + (p1 - p0) * t)

    # Edge crossings: along the rings (r fixed, between columns j and j + 1) and along the
    # columns (p fixed, between rows i and i + 1).
    along_ring = negative[:, :-1] != negative[:, 1:]    # (rows + 1, cols)
    along_column = negative[:-1, :] != negative[1:, :]  # (rows, cols + 1)
    ring_point = np.zeros(along_ring.shape + (3,))
    i, j = np.nonzero(along_ring)
    ring_point[i, j] = crossings(ring[i], ring[i], phi[j], phi[j + 1])
    column_point = np.zeros(along_column.shape + (3,))
    i, j = np.nonzero(along_column)
    column_point[i, j] = crossings(ring[i], ring[i + 1], phi[j], phi[j])
    # Marching squares: per cell, the crossings on its bottom, right, top and left edges.
    edges = [(along_ring[:-1], ring_point[:-1]), (along_column[:, 1:], column_point[:, 1:]),
             (along_ring[1:], ring_point[1:]), (along_column[:, :-1], column_point[:, :-1])]
    cut = np.stack([e[0] for e in edges])      # (4, rows, cols)
    point = np.stack([e[1] for e in edges])    # (4, rows, cols, 3)
    count = cut.sum(axis=0)
    starts, ends = [], []
    two = count == 2
    first = np.argmax(cut, axis=0)
    second = 3 - np.argmax(cut[::-1], axis=0)
    ci, cj = np.nonzero(two)
    starts.append(point[first[ci, cj], ci, cj])
    ends.append(point[second[ci, cj], ci, cj])
    # Saddles (four crossings): the centre's side decides which corners the curve cuts off.
    ci, cj = np.nonzero(count == 4)
    if len(ci):
        centre_negative = quadric(surface(0.5 * (ring[ci] + ring[ci + 1]),
                                          0.5 * (phi[cj] + phi[cj + 1]))) < 0.0
        joined = centre_negative == negative[ci, cj]  # the bottom-left corner's side
        # Joined: cut off the bottom-right (bottom, right) and top-left (top, left) corners;
        # else the bottom-left (bottom, left) and top-right (top, right) ones.
        for a, b_joined, b_apart in ((0, 1, 3), (2, 3, 1)):
            other = np.where(joined, b_joined, b_apart)
            starts.append(point[a, ci, cj])
            ends.append(point[other, ci, cj])
    start, end = np.concatenate(starts), np.concatenate(ends)
    keep = np.linalg.norm(end - start, axis=1) > 1e-12
    return start[keep], (end - start)[keep]
