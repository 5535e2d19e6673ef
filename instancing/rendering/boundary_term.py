"""Boundary terms of image derivatives: edge sampling of moving instances' silhouettes and
of the shadows they cast.

A pixel value is an integral over the film, ``I = int f(x; theta) k(x) dx``
(k: the pixel filter, x in pixels). Where f jumps across a curve that moves
with theta (a silhouette, a crease of a flat-shaded mesh, the rim of an open
shape), the derivative gains a line integral (Li et al., "Differentiable
Monte Carlo Ray Tracing through Edge Sampling", 2018)::

    dI/dtheta = int df/dtheta k dx  +  oint (f(x - eps n) - f(x + eps n)) (n . dx/dtheta) k dl

The first term is the interior term (AD through the re-attached
intersection and shading); this module estimates the second.

**Curves in object space.** Affine maps send tangent rays to tangent rays,
so a silhouette seen from the camera at world position c is the image of the
silhouette seen from ``c_obj = M^-1 c`` on the untransformed model (c homogeneous,
:meth:`~instancing.scene.camera.Camera.viewpoint`: an orthographic camera's is the
direction back along its view, w = 0). Each
model's discontinuity curves are computed in closed form in object space
(float64, once per frame) and mapped through the instance's differentiable
``world_from_object``; this holds for any invertible affine map, shear and
reflection included:

* sphere: the circle of tangency ``x . c_obj = 1`` (none from inside);
* cylinder: the two tangent lines ``q . c_xy = 1`` (from outside its
  infinite extension) and the rims at z = 0 and z = 1 (open ends);
* disk: its rim; rectangle: its four sides;
* cube and meshes: edges whose two faces are not coplanar (flat shading
  jumps there; smooth shading too where the geometric normal's turn changes
  what the surface blocks) or whose corner normals differ, unless both faces
  look away from the camera (one-sided materials are black there on both
  sides), and every boundary or non-manifold edge.

Curves hidden behind other surfaces are sampled too; there both side rays
see the occluder and the term vanishes. Curves of instances that do not move
are skipped (their velocity is zero).

**Estimator.** A curve is picked with probability proportional to its
approximate film length times its jump scale (a floor keeps every curve possible): 1
where a surface ends in front of another, and for a crease between two faces that both
face the camera on a plain diffuse mesh, how far the normals turn there, from 0.1 to 1
(:attr:`~instancing.models.curves.EdgeTopology.jump_scale`: a faceted terrain's many
shallow creases jump far less than its horizon), then a point on it
uniformly in its parameter; the density per unit film length follows from
the film speed of the parameterisation. f is evaluated by the integrator on
both sides of the point, ``EDGE_OFFSET`` pixels away, with the same random
numbers (near the smooth silhouette of a sphere or cylinder the shading varies
as the square root of that distance, so there the jump is extrapolated from two
offsets); the velocity ``n . dx/dtheta`` comes from AD through the projection
of the moving point ``M(theta) x_obj`` (tangential sliding of a smooth
silhouette along the surface does not change the normal velocity, so
x_obj is kept fixed). The contribution has value 0 and derivative equal to
the boundary term, and is splatted into the pixels through the filter.

**Terminator arcs** (with the silhouettes, ``sppp``). On a smooth mesh the shading
normal can turn away from the camera inside a triangle, where one-sided materials go
black: the arcs ``sn(x) . (c - x) = 0`` per triangle
(:meth:`~instancing.models.mesh.MeshLibrary.terminator_arcs`), solved again in the kernel
with the camera's object-space position attached, so that they slide as the instance
moves (:func:`_terminator_points`).

**Contact curves** (with the silhouettes, ``sppp``). Where a moving instance
meets a plane of another (a rectangle, a disk, a cube face, a mesh triangle) the
camera sees one surface end at the other: the model's closed-form section with
that plane, in its own object space
(:meth:`~instancing.models.analytic.AnalyticModel.plane_sections`; a mesh's
per-triangle segments), sampled where it lies on both surfaces (the plane's
extent: a square, the unit disk, the triangle), moving as the intersection of
two moving surfaces (:func:`_contact_points`). A curved instance meeting a flat
one is the curved one cut by the flat one's planes. Two curved surfaces (spheres and
cylinders under any affine maps: quadrics) meet along a curve with no closed form: it is
traced on a grid over the first one's surface as segments whose ends lie on both
(:func:`~instancing.models.curves.quadric_intersection`), and each sampled point is moved
onto the curve by Newton's method, with the exact density (:func:`_onto_intersection`).

**Curves seen in flat mirrors** (with the silhouettes, ``sppp``). A static flat face
that may reflect by a delta lobe (a rectangle's, a disk's, a cube face's or a flat mesh's
plane under a mirror, a smooth glass or a plastic's coating) shows the moving instances' silhouettes as
seen from the camera's mirror image in its plane (the same closed forms, from that
viewpoint); a curve point p is seen where the camera sees its reflection p - 2 h n (h its
height over the plane, n the plane's normal), if p lies on the camera's side
(:func:`mirror_sampler`). The jump is evaluated, as for the camera's own curves, by the
integrator on both sides of that film point, through the mirror.

**Shadow curves** (``sppi``). A point or directional light casts the moving
instances' silhouettes *seen from the light* (the same closed forms, from the
homogeneous viewpoint ``M^-1 (L, 1)`` or ``M^-1 (-direction, 0)``; only
silhouette and boundary edges, no creases) onto the next surface along its
rays: there the direct light jumps, and the camera sees the jump as a film
curve. A curve point p is mapped to that surface point z by phase 2 on the
ray from the light through p (AD attached, so z moves with the occluder, the
receiver and the light), its tangent carried along the ray onto the
receiver's tangent plane; then z is edge-sampled like a silhouette. Samples
count only where the camera sees the receiver on both sides of the curve
(``SHADOW_VISIBILITY_TOLERANCE``): a shadow hidden behind its caster, as when
the light sits at the camera, adds nothing.

Casters: the moving instances, and the static ones whose boxes meet the span between a
moving instance's box and the light (their shadows may fall on it; every instance for a
moving light).

Limitations: the curves here are seen from the camera; the visibility changes seen from
the surfaces it sees (area lights' and the environment's penumbrae, indirect light) are
the term of :mod:`instancing.rendering.secondary_boundary`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.backend import (Array3f, Bool, Float, Matrix3f, UInt32, device_arrays, device_vectors,
                            dr, vectors_from_rows)
from ..core.box import overlapping_pairs, swept_overlap
from ..core.rng import sample_streams
from ..core.transform import object_point, transposed_vector, world_normal, world_point, world_vector
from ..models.analytic import ANALYTIC_MODELS
from ..models.curves import (NORMAL_CYLINDER, NORMAL_SPHERE, QUADRIC_DIAGONALS, Curves,
                             quadric_intersection)
from ..scene.camera import BatchLanes, Camera, CameraBatch, CameraLanes
from ..scene.description import DirectionalLight, PointLight
from ..scene.instance_table import MESH_KIND
from ..scene.intersection import MISS, PreliminaryHit, reintersect
from .pixel_filter import PixelFilter

#: Distance (pixels) of the two side samples from the curve.
EDGE_OFFSET = 1e-3
#: Points per curve for the film-length estimate that drives curve selection.
POLYLINE_POINTS = 9
#: Every curve gets at least this fraction of the mean selection weight, so a
#: curve whose polyline estimate misses its visible part is still sampled.
WEIGHT_FLOOR = 0.01
#: Seed offsets that separate the boundary samples' streams (curve and point choice, and
#: the integrator's numbers on both sides of the curve) from the interior ones, for the
#: silhouettes and for the shadow curves.
BOUNDARY_STREAM_SEED = 0x2545F491
SIDE_STREAM_SEED = 0x68E31DA4
SHADOW_STREAM_SEED = 0x1B873593
SHADOW_SIDE_STREAM_SEED = 0x4CF5AD43
CONTACT_STREAM_SEED = 0x6B43A9B5
CONTACT_SIDE_STREAM_SEED = 0x3C6EF372
TERMINATOR_STREAM_SEED = 0x7F4A7C15
TERMINATOR_SIDE_STREAM_SEED = 0x2C1B3C6D
MIRROR_STREAM_SEED = 0x5BD1E995
MIRROR_SIDE_STREAM_SEED = 0x1F83D9AB
#: Where the search for the surface a shadow curve falls on starts past the curve point,
#: as a fraction of the occluder's size: a ray tangent to a float32 surface can graze it
#: over a chord of about 1e-3 of its radius.
RECEIVER_SEARCH_OFFSET = 1e-2
#: A shadow curve counts where the camera sees the surface it falls on on both sides of it:
#: the side rays' first hits lie within this fraction of the distance to that surface.
#: (Where an occluder's silhouette hides the curve, as when the light sits at the camera
#: and every shadow hides behind its caster, the side rays straddle the silhouette.)
SHADOW_VISIBILITY_TOLERANCE = 1e-2
#: Moving receivers whose swept boxes are tested one by one for casters; beyond, one box
#: around them all (see _casters_onto).
MAX_RECEIVER_SPANS = 64
#: Sine of the angle below which the camera looks along a shadow ray (see shadow_samplers).
COLINEAR_TOLERANCE = 1e-5


def selection_weights(curves: Curves, to_world: np.ndarray, camera: Camera) -> np.ndarray:
    """Approximate film length (pixels) of each curve, by a polyline of POLYLINE_POINTS,
    times its jump scale (:attr:`~instancing.models.curves.Curves.scale`), floored: the
    curve-selection weights. ``to_world``: (K, 4, 4) world_from_object matrix
    of each curve's instance. (Contact and shadow curves count only where the polyline's
    points lie on both surfaces or where the shadow falls in view: :func:`_film_lengths`.)"""
    world = _world_polylines(curves, to_world)
    return _floored(_film_lengths(world, np.ones(world.shape[:2], bool), camera) * curves.scales)


def _film_lengths(world: np.ndarray, found: np.ndarray, camera: Camera) -> np.ndarray:
    """Film length (pixels) of polylines through the world points (K, S, 3), counting the
    steps between points that are ``found`` (K, S) and in front of the camera."""
    k, points = world.shape[:2]
    x, y, in_front = camera.project(vectors_from_rows(world.reshape(-1, 3)))
    film = np.stack([np.asarray(x), np.asarray(y)], axis=-1).reshape(k, points, 2)
    front = np.asarray(in_front).reshape(k, points) & found
    step = np.linalg.norm(np.diff(film, axis=1), axis=-1)
    both = front[:, 1:] & front[:, :-1]
    return np.where(both, np.minimum(step, 4.0 * (camera.width + camera.height)), 0.0).sum(axis=1)


def world_length_weights(curves: Curves, to_world: np.ndarray) -> np.ndarray:
    """Approximate world length of each curve, by a polyline of POLYLINE_POINTS, floored:
    curve-selection weights for viewers anywhere (the shading points of the secondary
    term). ``to_world`` as for :func:`selection_weights`."""
    world = _world_polylines(curves, to_world)
    return _floored(np.linalg.norm(np.diff(world, axis=1), axis=-1).sum(axis=1))


def _world_polylines(curves: Curves, to_world: np.ndarray) -> np.ndarray:
    """World points (K, POLYLINE_POINTS, 3) evenly spaced in each curve's parameter."""
    pts = curves.points(np.linspace(0.0, 1.0, POLYLINE_POINTS))
    return np.einsum("kij,ksj->ksi", to_world[:, :3, :3], pts) + to_world[:, None, :3, 3]


def _floored(length: np.ndarray) -> np.ndarray:
    """Selection weights from lengths: each at least WEIGHT_FLOOR of the mean."""
    return np.maximum(length, WEIGHT_FLOOR * max(length.mean(), 1e-3))


#: The smallest curve table (padded): the curve counts of a few moving instances, which
#: change as they move, stay within one table size.
MIN_CURVE_CAPACITY = 64


def _padded(values: np.ndarray, capacity: int, mode: str = "zeros") -> np.ndarray:
    """``values`` (K,) or (K, 3) extended to ``capacity`` rows with zeros, or with copies of
    the last row (``mode="edge"``)."""
    pad = [(0, capacity - len(values))] + [(0, 0)] * (values.ndim - 1)
    return np.pad(values, pad, mode="edge") if mode == "edge" else np.pad(values, pad)


def _uploaded(columns: dict[str, np.ndarray]) -> dict:
    """Dr.Jit arrays of host columns: a (N, 3) float array an Array3f, (N,) floats a Float,
    (N,) integers a UInt32; in Dr.Jit's own storage (backend.device_arrays: an array wrapping
    a NumPy buffer makes a recorded optimisation step record anew whenever the buffer's
    alignment differs), one upload per type."""
    floats = [n for n, v in columns.items() if v.dtype.kind == "f"]
    ints = [n for n, v in columns.items() if v.dtype.kind != "f"]
    flat = [columns[n][:, k] if columns[n].ndim > 1 else columns[n]
            for n in floats for k in range(columns[n].shape[1] if columns[n].ndim > 1 else 1)]
    uploaded = iter(device_arrays(Float, *flat))
    out = {n: Array3f(*[next(uploaded) for _ in range(3)]) if columns[n].ndim > 1
           else next(uploaded) for n in floats}
    out.update(zip(ints, device_arrays(UInt32, *[columns[n] for n in ints])))
    return out


@dataclass
class BoundarySampler:
    """Dr.Jit form of a frame's curves with their selection distribution."""

    count: int  # padded capacity (a power of four)
    instance: UInt32
    circle: UInt32  # 1 for circles, 0 for segments
    c: Array3f
    u: Array3f
    v: Array3f
    cdf: Float
    probability: Float
    #: Shadow curves only: per curve, the delta light casting it (index into the light
    #: set's delta lights) and the receiver search offset (RECEIVER_SEARCH_OFFSET).
    light: UInt32 | None = None
    offset: Float | None = None
    #: Contact curves only: the flat instance each curve lies on, and more.
    contact: "ContactData | None" = None
    #: Terminator arcs only: each arc's triangle and chord normal.
    terminator: "TerminatorData | None" = None
    #: Curves seen in flat mirrors only: each curve's mirror plane.
    mirror: "MirrorData | None" = None
    #: Whether some curve is the smooth silhouette of a curved surface (see boundary_term).
    curved: bool = False
    #: Several views' curves (:meth:`joined`): per view, 1 if it has curves; view k's
    #: table fills entries [k * count, (k + 1) * count). None: one view's table.
    views: UInt32 | None = None
    #: The uploaded columns as host arrays (:func:`_uploaded`), which :meth:`joined` reads.
    host: dict = dataclasses.field(default_factory=dict, repr=False)

    @staticmethod
    def build(curves: Curves, weights: np.ndarray, light: np.ndarray | None = None,
              offset: np.ndarray | None = None) -> "BoundarySampler":
        """Upload the curves, padded to a power of four of at least MIN_CURVE_CAPACITY
        (padding is never picked), so that the sampling kernel, and a recorded step, change
        only when the curve count crosses one of those sizes. Shadow curves also carry their
        ``light`` and receiver search ``offset`` (K,)."""
        capacity = MIN_CURVE_CAPACITY
        while capacity < len(curves):
            capacity *= 4
        pad = capacity - len(curves)
        total = weights.sum()
        cdf = np.concatenate([np.cumsum(weights) / total, np.full(pad, 2.0)])
        cdf[len(curves) - 1] = 1.0
        columns = {"instance": curves.instance, "circle": curves.circle.astype(np.int64),
                   "c": curves.c, "u": curves.u, "v": curves.v}
        if light is not None:
            columns.update(light=light, offset=offset)
        columns = {name: _padded(values, capacity) for name, values in columns.items()}
        columns.update(cdf=cdf, probability=np.concatenate([weights / total, np.ones(pad)]))
        return BoundarySampler(capacity, **_uploaded(columns), host=columns)

    @staticmethod
    def joined(samplers: list["BoundarySampler | None"]) -> "BoundarySampler | None":
        """One table for the views of a camera batch: each view's curves with their own
        selection distribution (None: a view without curves) in a slot of the largest
        view's capacity, padded with the view's last entry (never picked: its cumulative
        weight is at least 1); host work, one upload per array type. None when no view
        has curves."""
        present = [s for s in samplers if s is not None]
        if len(samplers) == 1 or not present:
            return samplers[0] if len(samplers) == 1 else None
        capacity = max(s.count for s in present)

        def joined_columns(tables: list[dict | None], empty: dict) -> dict:
            # Each view's columns padded to the capacity with their last entry, or for a
            # view without curves, entries that are never picked.
            like = next(t for t in tables if t is not None)
            return {name: np.concatenate([
                np.full((capacity,) + like[name].shape[1:], empty.get(name, 0))
                if t is None else _padded(t[name], capacity, "edge") for t in tables])
                for name in like}

        columns = joined_columns([None if s is None else s.host for s in samplers],
                                 {"cdf": 2.0, "probability": 1.0})
        sampler = BoundarySampler(capacity, **_uploaded(columns), host=columns,
                                  curved=any(s.curved for s in present),
                                  views=device_arrays(UInt32, np.array(
                                      [0 if s is None else 1 for s in samplers]))[0])
        for name in ("contact", "terminator", "mirror"):
            parts = [None if s is None else getattr(s, name) for s in samplers]
            if any(p is not None for p in parts):
                part = joined_columns([None if p is None else p.host for p in parts], {})
                setattr(sampler, name, type(next(p for p in parts if p is not None))(
                    **_uploaded(part), host=part))
        return sampler

    def sample(self, u_pick: Float, u_param: Float, view: UInt32 | None = None
               ) -> tuple[UInt32, UInt32, Array3f, Array3f, Float, Bool]:
        """Pick curves and points on them: (curve, instance, object point, d point / ds,
        probability, whether the lane's view has a curve). ``view``: each lane's view in a
        :meth:`joined` table (None for one view's table)."""
        # First curve whose cumulative weight exceeds u_pick (u_pick < 1 <= the last real
        # entry), within the lane's view's slot.
        base = UInt32(0) if view is None else view * self.count
        k = base + dr.binary_search(0, self.count - 1,
                                    lambda i: dr.gather(Float, self.cdf, base + i) <= u_pick)
        circle = dr.gather(UInt32, self.circle, k) != 0
        c, u, v = (dr.gather(Array3f, a, k) for a in (self.c, self.u, self.v))
        sin, cos = dr.sincos(2.0 * math.pi * u_param)
        a = dr.select(circle, cos, u_param)
        b = dr.select(circle, sin, 0.0)
        point = c + u * a + v * b
        tangent = dr.select(circle, (v * cos - u * sin) * (2.0 * math.pi), u)
        present = Bool(True) if view is None else dr.gather(UInt32, self.views, view) != 0
        return (k, dr.gather(UInt32, self.instance, k), point, tangent,
                dr.gather(Float, self.probability, k), present)


@dataclass
class ContactData:
    """Per contact curve (padded like the curves): the instance whose plane or quadric it
    lies on (``other``), that plane's extent on it (:data:`EXTENT_SQUARE` ...; for a
    triangle, its ``corner`` and edges ``edge1``, ``edge2``, else zeros) or the quadric's
    (:data:`EXTENT_SPHERE`, :data:`EXTENT_CYLINDER`), the plane's object-space normal there
    (``plane``; zeros for a quadric), how the curve's own model gives its normal
    (:data:`~instancing.models.curves.NORMAL_STORED` ...) and the stored object-space normal."""

    other: UInt32
    extent: UInt32
    plane: Array3f
    corner: Array3f
    edge1: Array3f
    edge2: Array3f
    code: UInt32
    normal: Array3f
    #: The uploaded columns as host arrays (see :meth:`BoundarySampler.joined`).
    host: dict = dataclasses.field(default_factory=dict, repr=False)
    #: Whether some curve is where two curved surfaces meet (see :func:`_onto_intersection`):
    #: a plain attribute, so that a recorded step's key (recording.python_state) holds it.
    quadrics: bool = dataclasses.field(init=False, default=False)

    def __post_init__(self):
        self.quadrics = bool(np.any(self.host.get("extent", np.zeros(0)) >= EXTENT_SPHERE))

    @staticmethod
    def build(other: np.ndarray, extent: np.ndarray, plane: np.ndarray, triangle: np.ndarray,
              code: np.ndarray, normal: np.ndarray, capacity: int) -> "ContactData":
        columns = {name: _padded(np.asarray(values), capacity) for name, values in (
            ("other", other), ("extent", extent), ("plane", plane), ("corner", triangle[:, 0]),
            ("edge1", triangle[:, 1]), ("edge2", triangle[:, 2]), ("code", code),
            ("normal", normal))}
        return ContactData(**_uploaded(columns), host=columns)


#: Model kinds whose planes other instances may rest on or sink into (contact curves), with
#: their planes in object space as (unit normal, offset): a rectangle's and a disk's z = 0,
#: a cube's six faces (one per plane; the section is clipped to the face's square). Every
#: triangle of a mesh is a receiving plane too (see _receiving_planes).
RECEIVER_PLANES = {"rectangle": [((0.0, 0.0, 1.0), 0.0)], "disk": [((0.0, 0.0, 1.0), 0.0)],
                   "cube": [(tuple(side * np.eye(3)[k]), 1.0) for k in range(3) for side in (-1.0, 1.0)]}
#: The extent of a receiving plane on its instance: the square [-1, 1]^2 of a rectangle or
#: a cube face, the unit disk, or one mesh triangle; or of a curved receiver (its quadric,
#: see QUADRIC_DIAGONALS): the whole sphere, or the cylinder's tube 0 <= z <= 1.
EXTENT_SQUARE, EXTENT_DISK, EXTENT_TRIANGLE, EXTENT_SPHERE, EXTENT_CYLINDER = 0, 1, 2, 3, 4
#: The extent code of each curved receiver kind.
QUADRIC_EXTENTS = {"sphere": EXTENT_SPHERE, "cylinder": EXTENT_CYLINDER}
#: Relative slack of the extent test of a contact point on its plane (float32 object space).
PLANE_EXTENT_SLACK = 1e-5


def _within_extent(local, extent, corner, edge1, edge2):
    """Whether receiver-space points ``local`` (x, y, z components) on a receiving plane lie
    within its extent (``extent`` codes; a triangle's ``corner`` and edges as components).
    Arithmetic and comparisons only: the same test on NumPy arrays and on Dr.Jit arrays."""
    x, y, z = local
    limit = 1.0 + PLANE_EXTENT_SLACK
    square = (abs(x) <= limit) & (abs(y) <= limit) & (abs(z) <= limit)
    disk = x * x + y * y <= limit * limit

    def dot(a, b):
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    # Barycentric coordinates (s, t) / det of the point in the triangle's plane.
    d = [p - q for p, q in zip(local, corner)]
    a11, a12, a22 = dot(edge1, edge1), dot(edge1, edge2), dot(edge2, edge2)
    b1, b2 = dot(d, edge1), dot(d, edge2)
    det = a11 * a22 - a12 * a12
    s, t = a22 * b1 - a12 * b2, a11 * b2 - a12 * b1
    slack = PLANE_EXTENT_SLACK * det
    triangle = (s >= -slack) & (t >= -slack) & (s + t <= det + slack)
    tube = (z >= 0.0) & (z <= 1.0)
    return (((extent == EXTENT_SQUARE) & square) | ((extent == EXTENT_DISK) & disk)
            | ((extent == EXTENT_TRIANGLE) & triangle) | (extent == EXTENT_SPHERE)
            | ((extent == EXTENT_CYLINDER) & tube))


def _receiving_planes(scene, kind: np.ndarray, a: np.ndarray, b: np.ndarray,
                      box_a: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, ...]:
    """The planes of receivers ``b`` met by instances ``a`` (pairs; ``box_a``: a's world
    boxes, lo and hi): per plane, its pair, its unit normal and offset in b's object space,
    its extent code and its triangle (corner, edge 1, edge 2; zeros unless a mesh
    triangle). A mesh receiver gives each of its (non-degenerate) triangles whose world box
    meets a's."""
    pair, normal, offset, extent, triangle = [], [], [], [], []
    analytic = np.flatnonzero(kind[b] != MESH_KIND)
    for k in analytic:
        for n, c in RECEIVER_PLANES[kind[b[k]]]:
            pair.append([k])
            normal.append([n])
            offset.append([c])
            extent.append([EXTENT_DISK if kind[b[k]] == "disk" else EXTENT_SQUARE])
            triangle.append(np.zeros((1, 3, 3)))
    meshes = np.flatnonzero(kind[b] == MESH_KIND)
    if len(meshes):
        model = np.asarray(scene.description.instance_model)
        for k, lo, hi in zip(meshes, box_a[0][meshes], box_a[1][meshes]):
            corners = scene.instances.meshes.triangle_corners(scene.mesh_index(int(model[b[k]])))
            to_b = scene.instances.to_world_of(b[k:k + 1])[0]
            world = corners @ to_b[:3, :3].T + to_b[:3, 3]
            cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            area = np.linalg.norm(cross, axis=1)
            meet = (np.all(world.min(axis=1) <= hi, axis=1) & np.all(lo <= world.max(axis=1), axis=1)
                    & (area > 0))
            n = cross[meet] / area[meet, None]
            pair.append(np.full(len(n), k))
            normal.append(n)
            offset.append(np.einsum("fj,fj->f", n, corners[meet, 0]))
            extent.append(np.full(len(n), EXTENT_TRIANGLE))
            v = corners[meet]
            triangle.append(np.stack([v[:, 0], v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]], axis=1))
    if not pair:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), \
            np.zeros((0, 3, 3))
    return (np.concatenate(pair).astype(np.int64), np.concatenate(normal, axis=0).reshape(-1, 3),
            np.concatenate(offset).astype(np.float64), np.concatenate(extent).astype(np.int64),
            np.concatenate(triangle, axis=0))


def contact_samplers(scene, cameras: list[Camera]) -> list[BoundarySampler | None]:
    """Per camera, the frame's contact curves: where a moving instance meets a plane of
    another instance (a rectangle, a disk, a cube face or a mesh triangle: a floor, a wall,
    a card, a box), or a moving such instance meets any other, the curve along which the
    camera sees one surface end at the other; in the object space of the first instance of
    the pair, weighted by film length (host work: the curves found once, their film lengths
    per camera); None when no pair's boxes overlap. (Two receivers touch along one curve:
    the pair is taken once, sectioning the one with more planes, a mesh, by the other's.)"""
    curves = _contact_curves(scene)
    if curves is None:
        return [None] * len(cameras)
    curves, fields, world, found = curves
    samplers = [BoundarySampler.build(curves, _floored(_film_lengths(world, found, camera)))
                for camera in cameras]
    # (One curve table: every camera's sampler shares its contact data.)
    contact = ContactData.build(*fields, samplers[0].count)
    for sampler in samplers:
        sampler.contact = contact
    return samplers


def _contact_curves(scene) -> tuple[Curves, tuple, np.ndarray, np.ndarray] | None:
    """The contact curves of :func:`contact_samplers` with their :class:`ContactData` fields
    (other, extent, plane, triangle, code, normal), their world polylines (K, POLYLINE_POINTS,
    3) and where those points lie on both surfaces (K, POLYLINE_POINTS); None when there
    are none."""
    moving = set(scene.moving_instances.tolist())
    if not moving:
        return None
    desc = scene.description
    kind = np.array([m.kind for m in desc.models])[np.asarray(desc.instance_model)]
    parts = [part for part in (_plane_contacts(scene, kind, moving), _quadric_contacts(scene, kind, moving))
             if part is not None]
    if not parts:
        return None
    curves = Curves.joined([part[0] for part in parts])
    fields = tuple(np.concatenate(field) for field in zip(*[part[1] for part in parts]))
    other, extent, _, triangle, code, _ = fields
    from_other = scene.instances.from_world_of(other)
    # The polyline points on both surfaces: within the other's extent, and on the
    # cylinder's height.
    world = _world_polylines(curves, scene.instances.to_world_of(curves.instance))
    local = np.einsum("kij,ksj->ksi", from_other[:, :3, :3], world) + from_other[:, None, :3, 3]
    inside = _within_extent(np.moveaxis(local, -1, 0), extent[:, None],
                            *(triangle[:, k].T[:, :, None] for k in range(3)))
    z = curves.points(np.linspace(0.0, 1.0, POLYLINE_POINTS))[..., 2]
    on_tube = (code[:, None] != NORMAL_CYLINDER) | ((z >= 0.0) & (z <= 1.0))
    return curves, fields, world, inside & on_tube


def _plane_contacts(scene, kind: np.ndarray, moving: set) -> tuple[Curves, tuple] | None:
    """Where instances meet the receiving planes of others (:data:`RECEIVER_PLANES`, mesh
    triangles): the curves, each its model's closed-form section with the plane, and their
    :class:`ContactData` fields."""
    desc = scene.description
    receivers = np.flatnonzero(np.isin(kind, list(RECEIVER_PLANES) + [MESH_KIND]))
    if not len(receivers):
        return None
    everything = np.arange(len(kind))
    candidates = everything if moving & set(receivers.tolist()) else np.array(sorted(moving))
    lo_a, hi_a = scene.instance_bounds(candidates)
    lo_b, hi_b = scene.instance_bounds(receivers)
    ia, ib = overlapping_pairs(lo_a, hi_a, lo_b, hi_b)
    a, b = candidates[ia], receivers[ib]
    both = np.isin(a, receivers)
    rank_a, rank_b = kind[a] == MESH_KIND, kind[b] == MESH_KIND
    once = (rank_b < rank_a) | ((rank_b == rank_a) & (a < b))
    keep = (a != b) & (np.isin(a, list(moving)) | np.isin(b, list(moving))) & (~both | once)
    a, b, box_a = a[keep], b[keep], (lo_a[ia[keep]], hi_a[ia[keep]])
    if not len(a):
        return None
    # One entry per receiving plane of each b: its object-space plane, then the plane in
    # world space and in a's object space: n_a . x = c_a.
    entry, plane, plane_offset, extent, triangle = _receiving_planes(scene, kind, a, b, box_a)
    a, b = a[entry], b[entry]
    n_b, on_b = _world_planes(scene, b, plane, plane_offset)
    to_a = scene.instances.to_world_of(a)
    n_a = np.einsum("kji,kj->ki", to_a[:, :3, :3], n_b)
    c_a = np.einsum("kj,kj->k", n_b, on_b - to_a[:, :3, 3])
    length = np.linalg.norm(n_a, axis=1)
    n_a, c_a = n_a / length[:, None], c_a / length
    parts = []
    for model_index, model in enumerate(desc.models):
        mine = np.flatnonzero(np.asarray(desc.instance_model)[a] == model_index)
        if not len(mine):
            continue
        source = (ANALYTIC_MODELS[model.kind].plane_sections(n_a[mine], c_a[mine])
                  if model.kind in ANALYTIC_MODELS else scene.instances.meshes.plane_sections(
                      scene.mesh_index(model_index), n_a[mine], c_a[mine]))
        rows, circle, c, u, v, code, normal = source
        parts.append((mine[rows], circle, c, u, v, code, normal))
    if not parts:
        return None
    pair, circle, c, u, v, code, normal = (np.concatenate(p) for p in zip(*parts))
    if not len(pair):
        return None
    return (Curves(a[pair], circle, c, u, v),
            (b[pair], extent[pair], plane[pair], triangle[pair], code, normal))


def _quadric_contacts(scene, kind: np.ndarray, moving: set) -> tuple[Curves, tuple] | None:
    """Where two curved instances (spheres, cylinders) meet, one of them moving: the curve
    of intersection of their quadrics, traced in the first one's object space as segments
    whose ends lie on it (:func:`~instancing.models.curves.quadric_intersection`; the kernel
    moves the sampled points onto it, :func:`_onto_intersection`), and their
    :class:`ContactData` fields."""
    curved = np.flatnonzero(np.isin(kind, list(QUADRIC_DIAGONALS)))
    mover = curved[np.isin(curved, list(moving))]
    if len(curved) < 2 or not len(mover):
        return None
    # Each moving curved instance against every curved one; two moving ones paired once.
    ia, ib = overlapping_pairs(*scene.instance_bounds(mover), *scene.instance_bounds(curved))
    a, b = mover[ia], curved[ib]
    keep = (a != b) & ((a < b) | ~np.isin(b, mover))
    a, b = a[keep], b[keep]
    if not len(a):
        return None
    to_a, from_b = scene.instances.to_world_of(a), scene.instances.from_world_of(b)
    pieces = []
    for k in range(len(a)):
        # a's object space to b's.
        linear = from_b[k, :3, :3] @ to_a[k, :3, :3]
        offset = from_b[k, :3, :3] @ to_a[k, :3, 3] + from_b[k, :3, 3]
        start, step = quadric_intersection(kind[a[k]], kind[b[k]], linear, offset)
        if len(start):
            pieces.append((k, start, step))
    if not pieces:
        return None
    pair = np.concatenate([np.full(len(start), k) for k, start, _ in pieces])
    start = np.concatenate([start for _, start, _ in pieces])
    step = np.concatenate([step for _, _, step in pieces])
    count = len(pair)
    zeros = np.zeros((count, 3))
    code = np.where(kind[a[pair]] == "cylinder", NORMAL_CYLINDER, NORMAL_SPHERE)
    extent = np.array([QUADRIC_EXTENTS[k] for k in kind[b[pair]]], np.int64)
    return (Curves(a[pair], np.zeros(count, bool), start, step, zeros),
            (b[pair], extent, zeros, np.zeros((count, 3, 3)), code, zeros))


def _contact_points(scene, sampler_data: BoundarySampler, curve: UInt32, instance: UInt32,
                    x_obj: Array3f, p: Array3f) -> tuple[Array3f, Bool]:
    """Contact curve points with the curve's velocity: where instance a's surface (p, moving
    with a) meets the flat instance b's, the point moves in the plane of the two normals so
    as to stay on both: w = alpha n_a + beta n_b with n_a . w = v_a and n_b . w = v_b (the
    surfaces' normal speeds). Returns the point (value p, derivative w) and whether it lies
    on both surfaces."""
    data, table = sampler_data.contact, scene.instances
    other = dr.gather(UInt32, data.other, curve)
    code = dr.gather(UInt32, data.code, curve)
    with dr.suspend_grad():
        p0 = dr.detach(p)
        n_obj = dr.select(code == NORMAL_SPHERE, x_obj,
                          dr.select(code == NORMAL_CYLINDER, Array3f(x_obj.x, x_obj.y, 0.0),
                                    dr.gather(Array3f, data.normal, curve)))
        n_a = world_normal(table.inverse(instance), n_obj)
        inverse_b = table.inverse(other)
        local = object_point(inverse_b, p0)
        extent = dr.gather(UInt32, data.extent, curve)
        # b's object-space normal: its plane's, or its quadric's gradient at the point.
        n_b = world_normal(inverse_b, dr.select(
            extent == EXTENT_SPHERE, local, dr.select(extent == EXTENT_CYLINDER,
                                                      Array3f(local.x, local.y, 0.0),
                                                      dr.gather(Array3f, data.plane, curve))))
        corner, edge1, edge2 = (dr.gather(Array3f, v, curve)
                                for v in (data.corner, data.edge1, data.edge2))
        inside = _within_extent((local.x, local.y, local.z), extent, corner, edge1, edge2)
        on_tube = (code != NORMAL_CYLINDER) | ((x_obj.z >= 0.0) & (x_obj.z <= 1.0))
        k = dr.dot(n_a, n_b)
        apart = 1.0 - k * k
    # The surfaces' normal speeds at p (AD): a's material point, b's material point.
    v_a = dr.dot(n_a, p - p0)
    v_b = dr.dot(n_b, world_point(table.forward(other), local) - p0)
    alpha = (v_a - k * v_b) / apart
    beta = (v_b - k * v_a) / apart
    return p0 + n_a * alpha + n_b * beta, inside & on_tube & (apart > 1e-8)


#: Newton steps that move a point of a traced segment onto the curve where two quadrics meet
#: (from about 1e-4 of the model's size away: the error squares at each step).
INTERSECTION_NEWTON_STEPS = 4
#: A point counts as on both quadrics when each equation (``x^T D x - 1``, halved) is
#: within this after the steps.
INTERSECTION_TOLERANCE = 1e-4


def _onto_intersection(scene, sampler_data: BoundarySampler, curve: UInt32, instance: UInt32,
                       x_obj: Array3f, tangent: Array3f) -> tuple[Array3f, Array3f, Bool]:
    """The contact curves of two curved surfaces come as segments whose ends lie on the
    curve (:func:`_quadric_contacts`). Their point x(s) is mapped to the curve's point in the
    plane through x(s) perpendicular to the segment (Newton's method on the two quadrics and
    that plane, in a's object space), and the segment's dx/ds = u to the curve's
    dy/ds = (u . u) t / (t . u), t the curve's tangent (from (y - x(s)) . u = 0): the planes
    of consecutive segments meet the curve at their shared end, so the segments map onto the
    curve once, and s stays an exact parameter of it. Other curves pass unchanged. Returns
    (object point, its d / ds, whether it lies on both quadrics); detached."""
    data, table = sampler_data.contact, scene.instances
    with dr.suspend_grad():
        extent = dr.gather(UInt32, data.extent, curve)
        quadric = (extent == EXTENT_SPHERE) | (extent == EXTENT_CYLINDER)
        code = dr.gather(UInt32, data.code, curve)
        d_a = Array3f(1.0, 1.0, dr.select(code == NORMAL_CYLINDER, 0.0, 1.0))
        d_b = Array3f(1.0, 1.0, dr.select(extent == EXTENT_CYLINDER, 0.0, 1.0))
        forward_a = table.forward(instance)
        inverse_b = table.inverse(dr.gather(UInt32, data.other, curve))
        along = tangent / dr.norm(tangent)

        def equations(y):
            # Both quadrics' halved equations at y and their gradients in a's object space.
            y_b = object_point(inverse_b, world_point(forward_a, y))
            g_b = transposed_vector(forward_a, transposed_vector(inverse_b, d_b * y_b))
            return (0.5 * (dr.dot(d_a * y, y) - 1.0), 0.5 * (dr.dot(d_b * y_b, y_b) - 1.0),
                    d_a * y, g_b)

        y = Array3f(x_obj)
        for _ in range(INTERSECTION_NEWTON_STEPS):
            f_a, f_b, g_a, g_b = equations(y)
            jacobian = Matrix3f([[g_a.x, g_a.y, g_a.z], [g_b.x, g_b.y, g_b.z],
                                 [along.x, along.y, along.z]])
            y -= dr.rcp(jacobian) @ Array3f(f_a, f_b, dr.dot(y - x_obj, along))
        f_a, f_b, g_a, g_b = equations(y)
        t = dr.cross(g_a, g_b)
        t_dot_u = dr.dot(t, tangent)
        dy = t * (dr.squared_norm(tangent) / t_dot_u)
        # (A curve nearly perpendicular to its segment would mean a grid too coarse for it.)
        on_both = ((dr.abs(f_a) <= INTERSECTION_TOLERANCE) & (dr.abs(f_b) <= INTERSECTION_TOLERANCE)
                   & (dr.abs(t_dot_u) > 0.1 * dr.norm(t) * dr.norm(tangent)) & dr.isfinite(dy.x)
                   & dr.isfinite(y.x))
    return (dr.select(quadric, y, x_obj), dr.select(quadric, dy, tangent), ~quadric | on_both)


@dataclass
class TerminatorData:
    """Per terminator arc (padded like the curves): its triangle's leaf-order position in
    the mesh library and the unit in-plane normal of its chord (see
    :meth:`~instancing.models.mesh.MeshLibrary.terminator_arcs`)."""

    position: UInt32
    normal: Array3f
    #: The uploaded columns as host arrays (see :meth:`BoundarySampler.joined`).
    host: dict = dataclasses.field(default_factory=dict, repr=False)

    @staticmethod
    def build(position: np.ndarray, normal: np.ndarray, capacity: int) -> "TerminatorData":
        columns = {"position": _padded(np.asarray(position), capacity),
                   "normal": _padded(normal, capacity)}
        return TerminatorData(**_uploaded(columns), host=columns)


def terminator_sampler(scene, camera: Camera) -> BoundarySampler | None:
    """The frame's terminator arcs: on the moving smooth meshes, where the interpolated
    normal turns away from the camera inside a triangle (one-sided materials go black
    there; :meth:`~instancing.models.mesh.MeshLibrary.terminator_arcs`), in object space,
    weighted by film length (host work); None when there are none."""
    moving = scene.moving_instances
    meshes = scene.instances.meshes
    if not len(moving) or meshes is None or not any(meshes.smooth):
        return None
    desc = scene.description
    eye = camera.viewpoint()
    parts = []
    for model_index, model in enumerate(desc.models):
        if model.kind != MESH_KIND or model.mesh.normals is None:
            continue
        mine = moving[np.asarray(desc.instance_model)[moving] == model_index]
        if not len(mine):
            continue
        viewpoints = np.einsum("mij,j->mi", scene.instances.from_world_of(mine), eye)
        row, position, start, chord, normal = meshes.terminator_arcs(scene.mesh_index(model_index),
                                                                     viewpoints)
        parts.append((mine[row], position, start, chord, normal))
    if not parts:
        return None
    instance, position, start, chord, normal = (np.concatenate(p) for p in zip(*parts))
    if not len(instance):
        return None
    curves = Curves(instance, np.zeros(len(instance), bool), start, chord, np.zeros_like(start))
    sampler = BoundarySampler.build(curves, selection_weights(
        curves, scene.instances.to_world_of(instance), camera))
    sampler.terminator = TerminatorData.build(position, normal, sampler.count)
    return sampler


def _terminator_points(scene, sampler_data: BoundarySampler, camera: Camera,
                       lanes: CameraLanes | BatchLanes, curve: UInt32, instance: UInt32, x_obj: Array3f,
                       u_param: Float) -> tuple[Array3f, Array3f, Bool]:
    """Terminator arc points: the arc's point at ``u_param`` as seen from each lane's camera
    (``lanes``) in the instance's object space (AD attached: the arc slides as the instance
    moves relative to the camera), mapped to world space; its world tangent (detached);
    whether it lies in its triangle."""
    data, table = sampler_data.terminator, scene.instances
    rows = table.forward(instance)
    eye, w = camera.lane_viewpoint(lanes)
    # The camera's (homogeneous) viewpoint in object space, A^-1 (c - w b), from the
    # (differentiable) forward rows.
    linear = dr.rcp(Matrix3f([[r.x, r.y, r.z] for r in rows]))
    offset = eye - w * Array3f(rows[0].w, rows[1].w, rows[2].w)
    c_obj = linear @ offset
    start = dr.detach(x_obj) - dr.gather(Array3f, sampler_data.u, curve) * u_param
    x, tangent, inside = table.meshes.terminator_point(
        dr.gather(UInt32, data.position, curve), start, dr.gather(Array3f, sampler_data.u, curve),
        dr.gather(Array3f, data.normal, curve), u_param, c_obj, w)
    with dr.suspend_grad():
        world_tangent = world_vector(rows, tangent)
    return world_point(rows, x), world_tangent, inside


@dataclass
class MirrorData:
    """Per curve seen in a flat mirror (padded like the curves): the mirror's world plane
    ``normal . x = offset`` (unit normal)."""

    normal: Array3f
    offset: Float
    #: The uploaded columns as host arrays (see :meth:`BoundarySampler.joined`).
    host: dict = dataclasses.field(default_factory=dict, repr=False)

    @staticmethod
    def build(normal: np.ndarray, offset: np.ndarray, capacity: int) -> "MirrorData":
        columns = {"normal": _padded(normal, capacity), "offset": _padded(offset, capacity)}
        return MirrorData(**_uploaded(columns), host=columns)


def mirror_sampler(scene, camera: Camera) -> BoundarySampler | None:
    """The moving instances' silhouettes as the camera sees them in static flat mirrors
    (:func:`_mirror_faces`): a plane's reflection maps the camera to a virtual viewpoint,
    whose silhouettes, reflected back, are what the camera sees of them in that plane
    (host work, from the detached transforms); weighted by their reflections' film
    lengths. None when no moving instance has a curve there."""
    eye = camera.viewpoint()
    parts, lengths, planes = [], [], []
    for normal, offset, instances in _mirror_faces(scene, camera):
        # The camera's side of the plane, and its mirror image (a homogeneous point).
        side = _plane_side(normal, offset, eye)
        curves = scene.discontinuity_curves(np.append(eye[:3] - 2.0 * side * normal, eye[3]), instances)
        if not len(curves):
            continue
        world = _world_polylines(curves, scene.instances.to_world_of(curves.instance))
        height = world @ normal - offset
        # Only points on the camera's side of the plane show in it.
        lengths.append(_film_lengths(world - 2.0 * height[..., None] * normal,
                                     height * side > 0, camera) * curves.scales)
        parts.append(curves)
        planes.append((np.repeat(normal[None], len(curves), axis=0), np.full(len(curves), offset)))
    if not parts:
        return None
    curves = Curves.joined(parts)
    sampler = BoundarySampler.build(curves, _floored(np.concatenate(lengths)))
    sampler.mirror = MirrorData.build(np.concatenate([n for n, _ in planes]),
                                      np.concatenate([o for _, o in planes]), sampler.count)
    sampler.curved = _any_curved(scene, scene.moving_instances)
    return sampler


#: Corners (4, 3) of each receiving plane's face (RECEIVER_PLANES order) in object space:
#: the square [-1, 1]^2 at z = 0 (a disk's bounding square), a cube's six faces (a flat
#: mesh's face is its object box).
_FACE_CORNERS = {
    "rectangle": [np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)],
    "disk": [np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)],
    "cube": [np.array([np.insert([a, b], k, side) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))],
                      np.float64) for k in range(3) for side in (-1.0, 1.0)]}


def _mirror_faces(scene, camera: Camera) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """The static flat faces (rectangles, disks, cube faces, flat meshes) whose material may
    reflect by a delta lobe (a mirror, a smooth glass, a plastic's coating) and in which the
    camera may see moving instances: per face, its world plane (unit normal, offset) and the
    moving instances whose reflected boxes overlap the face on the film, on the camera's
    side."""
    moving = scene.moving_instances
    desc = scene.description
    kinds = np.array([m.kind for m in desc.models])[np.asarray(desc.instance_model)]
    delta = np.array([scene.materials[name].may_sample_delta for name in scene.material_names], bool)
    mirror = np.isin(kinds, list(RECEIVER_PLANES) + [MESH_KIND]) & delta[np.asarray(desc.instance_material_index)]
    mirror[moving] = False
    mirrors = np.flatnonzero(mirror)
    if not len(moving) or not len(mirrors):
        return []
    faces = [(index, *face) for index in mirrors for face in _object_faces(scene, index, kinds[index])]
    if not faces:
        return []
    index, plane, plane_offset, corners = (np.array(x) for x in zip(*faces))
    normal, point = _world_planes(scene, index, plane, plane_offset)
    offset = np.einsum("kj,kj->k", normal, point)
    to_world = scene.instances.to_world_of(index)
    corners = np.einsum("kij,kpj->kpi", to_world[:, :3, :3], corners) + to_world[:, None, :3, 3]
    side = _plane_side(normal, offset, camera.viewpoint())
    normal, offset, side, corners = normal[side != 0], offset[side != 0], side[side != 0], corners[side != 0]
    faces = range(len(side))
    box = _box_corners(*scene.instance_bounds(moving))
    height = np.einsum("ikj,fj->fik", box, normal) - offset[:, None, None]  # (F, I, 8)
    mirrored = box[None] - 2.0 * height[..., None] * normal[:, None, None, :]
    face_box = _film_box(corners, camera)[:, 0]  # (F, 4)
    image_box = _film_box(mirrored.reshape(len(faces), -1, 3), camera, groups=len(moving))  # (F, I, 4)
    overlap = ((image_box[..., 0] <= face_box[:, None, 2]) & (face_box[:, None, 0] <= image_box[..., 2])
               & (image_box[..., 1] <= face_box[:, None, 3]) & (face_box[:, None, 1] <= image_box[..., 3]))
    seen = overlap & np.any(height * side[:, None, None] > 0, axis=2)
    return [(normal[f], float(offset[f]), moving[seen[f]]) for f in faces if seen[f].any()]


def _plane_side(normal: np.ndarray, offset: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """``normal . x - w offset`` of a homogeneous viewpoint (x, w) and planes ``normal . y =
    offset``: its signed height over them (a viewer at infinity: the sign of the side)."""
    return normal @ viewpoint[:3] - viewpoint[3] * offset


def _world_planes(scene, instances: np.ndarray, plane: np.ndarray, plane_offset: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """World unit normals and points (K, 3) of the object-space planes ``plane . x =
    plane_offset`` (unit normals (K, 3)) of ``instances`` (K): normals by the inverse
    transpose."""
    to_world, from_world = scene.instances.to_world_of(instances), scene.instances.from_world_of(instances)
    normal = np.einsum("kji,kj->ki", from_world[:, :3, :3], plane)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    point = np.einsum("kij,kj->ki", to_world[:, :3, :3], plane * plane_offset[:, None]) + to_world[:, :3, 3]
    return normal, point


def _object_faces(scene, instance: int, kind: str) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """The flat faces of an instance's model in object space: per face its plane (normal,
    offset) and 8 points whose film box holds the face (a receiving plane's corners twice, a
    flat mesh's object box); none for a mesh that is not flat."""
    if kind != MESH_KIND:
        return [(np.asarray(plane), offset, np.concatenate([corners, corners]))
                for (plane, offset), corners in zip(RECEIVER_PLANES[kind], _FACE_CORNERS[kind])]
    mesh = scene.mesh_index(int(scene.description.instance_model[instance]))
    plane = scene.instances.meshes.plane(mesh)
    return [] if plane is None else [(plane[0], plane[1], _box_corners(
        *(bound[None] for bound in scene.instances.meshes.object_bounds[mesh]))[0])]


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 8 corners (K, 8, 3) of boxes (K, 3)."""
    return np.stack([np.where(np.array([i & 1, i & 2, i & 4], bool), hi, lo) for i in range(8)], axis=1)


def _film_box(points: np.ndarray, camera: Camera, groups: int = 1) -> np.ndarray:
    """Film bounding boxes (x0, y0, x1, y1), clipped to the film, of world points (F, P, 3)
    taken in ``groups`` equal runs along P: (F, groups, 4). A group with some points at or
    behind the camera plane gets the whole film; one with all there, an empty box."""
    f, p = points.shape[:2]
    x, y, in_front = camera.project(vectors_from_rows(points.reshape(-1, 3)))
    shape = (f, groups, p // groups)
    x, y = np.asarray(x, np.float64).reshape(shape), np.asarray(y, np.float64).reshape(shape)
    in_front = np.asarray(in_front).reshape(shape)
    front, behind = in_front.all(axis=2), ~in_front.any(axis=2)
    w, h = camera.width, camera.height
    corners = [(x.min(axis=2), w, 0, np.inf), (y.min(axis=2), h, 0, np.inf), (x.max(axis=2), w, w, -np.inf),
               (y.max(axis=2), h, h, -np.inf)]
    return np.stack([np.where(front, np.clip(value, 0, size), np.where(behind, empty, whole))
                     for value, size, whole, empty in corners], axis=-1)


def _any_curved(scene, instances: np.ndarray) -> bool:
    """Whether some of ``instances`` is of a curved analytic model (smooth silhouettes)."""
    models = scene.description.models
    return any(ANALYTIC_MODELS[models[m].kind].curved
               for m in set(np.asarray(scene.description.instance_model)[instances].tolist())
               if models[m].kind in ANALYTIC_MODELS)


def boundary_sampler(scene, camera: Camera) -> BoundarySampler | None:
    """The frame's curve-selection distribution: the moving instances' discontinuity
    curves seen from the camera, with their weights (host work, from the detached
    transforms); None when no moving instance has a curve."""
    moving = scene.moving_instances
    if not len(moving):
        return None
    curves = scene.discontinuity_curves(camera.viewpoint(), moving)
    if not len(curves):
        return None
    sampler = BoundarySampler.build(curves, selection_weights(
        curves, scene.instances.to_world_of(curves.instance), camera))
    sampler.curved = _any_curved(scene, moving)
    return sampler


def shadow_samplers(scene, cameras: list[Camera]) -> list[BoundarySampler | None]:
    """Per camera, the frame's shadow curves: the discontinuity curves seen from each point
    and directional light (their shadow boundaries fall where rays from the light graze
    them) of the moving instances, and of every instance for a moving light, weighted by
    the film length of the shadows they cast (host work, rays cast with
    :meth:`~instancing.scene.scene.Scene.intersect`: the curves and the surfaces their
    shadows fall on found once, their visibility and film lengths per camera); None for a
    camera that sees none (:func:`shadow_lights`)."""
    lit_by = [shadow_lights(scene, camera) for camera in cameras]
    lit = sorted({i: light for each in lit_by for i, light in each}.items(), key=lambda x: x[0])
    if not lit or not (len(scene.moving_instances) or len(scene.moving_lights)):
        return [None] * len(cameras)
    curves, light_of, offset = shadow_curves(scene, lit, [shadow_casters(scene, i, light)
                                                          for i, light in lit])
    if not len(curves):
        return [None] * len(cameras)
    slot = scene.light_set().delta_slot
    world = _world_polylines(curves, scene.instances.to_world_of(curves.instance))
    # Rays from each light through the curve points, continued to the next surface.
    direction = np.empty_like(world)
    for i, light in lit:
        mine = light_of == slot[i]
        if isinstance(light, PointLight):
            away = world[mine] - np.asarray(light.position)
            direction[mine] = away / np.linalg.norm(away, axis=-1, keepdims=True)
        else:
            direction[mine] = np.asarray(light.direction)
    origin = world + direction * offset[:, None, None]
    t, instance = _first_hits(scene, origin.reshape(-1, 3), direction.reshape(-1, 3))
    found = (instance != MISS).reshape(world.shape[:2])
    # (Where nothing was found, z stays at the curve point: it counts nowhere.)
    z = origin + direction * np.where(found, t.reshape(found.shape), 0.0)[..., None]
    # Per camera the curves of the lights it sees, and the camera's rays to where their
    # shadows fall (traced together: one kernel for every camera).
    mine = [np.isin(light_of, [slot[i] for i, _ in seen]) for seen in lit_by]
    origins, to_z = zip(*(_sight(camera, z[m]) for camera, m in zip(cameras, mine)))
    distance = [np.linalg.norm(v, axis=-1) for v in to_z]
    sight, _ = _first_hits(scene, np.concatenate([o.reshape(-1, 3) for o in origins]),
                           np.concatenate([(v / np.maximum(r, 1e-300)[..., None]).reshape(-1, 3)
                                           for v, r in zip(to_z, distance)]))
    sight = np.split(sight, np.cumsum([r.size for r in distance])[:-1])
    samplers = []
    for camera, m, origin, v, r, t_sight in zip(cameras, mine, origins, to_z, distance, sight):
        if not m.any():
            samplers.append(None)
            continue
        # Seen by the camera: nothing in front of z, and z not straight behind its caster
        # (the camera looking along the shadow ray: a light at the camera hides every
        # shadow behind what casts it, and rounding alone would decide the grazing test).
        to_p = world[m] - origin
        clear = t_sight.reshape(r.shape) >= r * (1.0 - SHADOW_VISIBILITY_TOLERANCE)
        behind = (np.linalg.norm(np.cross(v, to_p), axis=-1)
                  <= COLINEAR_TOLERANCE * r * np.linalg.norm(to_p, axis=-1))
        # (Curves whose shadows the polyline finds nowhere in view keep the floor weight: a
        # sampler that came and went with visibility would change a recorded step's key.)
        lengths = _film_lengths(z[m], found[m] & clear & ~behind, camera)
        samplers.append(BoundarySampler.build(curves.subset(m), _floored(lengths),
                                              light_of[m], offset[m]))
    return samplers


def _sight(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera's rays to world points (..., 3): their origins, and the vectors from there
    to the points (a viewer at infinity: from the camera's plane, along its view)."""
    eye = camera.viewpoint()
    if eye[3]:
        return np.broadcast_to(eye[:3], points.shape), points - eye[:3]
    forward = -eye[:3]
    depth = (points - np.asarray(camera.world_from_camera.matrix, np.float64)[:3, 3]) @ forward
    return points - depth[..., None] * forward, depth[..., None] * forward


def shadow_casters(scene, index: int, light: PointLight | DirectionalLight) -> np.ndarray:
    """The instances whose shadows from scene light ``index`` move: every instance when
    the light moves, else the moving instances and those that may cast its shadow onto a
    moving one (:func:`_casters_onto`)."""
    if index in scene.moving_lights:
        return np.arange(len(scene.instance_ids))
    moving = scene.moving_instances
    return np.union1d(moving, _casters_onto(scene, light, moving)).astype(np.int64)


def shadow_curves(scene, lit: list[tuple[int, PointLight | DirectionalLight]],
                  casters: list[np.ndarray]) -> tuple[Curves, np.ndarray, np.ndarray]:
    """The silhouettes that the ``casters`` of each light of ``lit`` (scene light index,
    light) show it (no creases: only curves that cast shadows), with per curve its light
    (index into the light set's delta lights) and receiver search offset
    (RECEIVER_SEARCH_OFFSET of the caster's size: its largest axis); host work."""
    slot = scene.light_set().delta_slot
    parts, light_of = [], []
    for (i, light), who in zip(lit, casters):
        # The light as a homogeneous viewpoint: its position, or the direction it comes from.
        viewpoint = (np.append(light.position, 1.0) if isinstance(light, PointLight)
                     else np.append(-np.asarray(light.direction), 0.0))
        curves = scene.discontinuity_curves(viewpoint, np.asarray(who, np.int64), creases=False)
        parts.append(curves)
        light_of.append(np.full(len(curves), slot[i]))
    curves = Curves.joined(parts)
    if not len(curves):
        return curves, np.zeros(0, np.int64), np.zeros(0)
    size = np.linalg.norm(scene.instances.to_world_of(curves.instance)[:, :3, :3], axis=1).max(axis=1)
    return curves, np.concatenate(light_of).astype(np.int64), RECEIVER_SEARCH_OFFSET * size


def _casters_onto(scene, light: PointLight | DirectionalLight, receivers: np.ndarray) -> np.ndarray:
    """The instances that may cast ``light``'s shadow onto the ``receivers``: their boxes meet
    a receiver's box swept towards the light (to the light's position, which covers the
    hull of the box and the light, or across the scene towards a directional light); pairs
    found by the swept boxes' bounds, then tested exactly (conservative, from world boxes;
    host work)."""
    if not len(receivers):
        return np.zeros(0, np.int64)
    lo, hi = scene.instance_bounds(np.arange(len(scene.instance_ids)))
    r_lo, r_hi = scene.instance_bounds(receivers)
    if len(r_lo) > MAX_RECEIVER_SPANS:
        # Many moving receivers: one box around them all (still conservative).
        r_lo, r_hi = r_lo.min(axis=0, keepdims=True), r_hi.max(axis=0, keepdims=True)
    if isinstance(light, PointLight):
        sweep = np.asarray(light.position, np.float64) - 0.5 * (r_lo + r_hi)
    else:
        extent = np.linalg.norm(hi.max(axis=0) - lo.min(axis=0))
        towards = -np.asarray(light.direction, np.float64) / np.linalg.norm(light.direction)
        sweep = np.broadcast_to(extent * towards, r_lo.shape)
    i, j = overlapping_pairs(lo, hi, np.minimum(r_lo, r_lo + sweep), np.maximum(r_hi, r_hi + sweep))
    meets = swept_overlap(lo[i], hi[i], r_lo[j], r_hi[j], sweep[j])
    return np.unique(i[meets])


def shadow_lights(scene, camera: Camera) -> list[tuple[int, PointLight | DirectionalLight]]:
    """The point and directional lights (with their indices into ``scene.lights``) whose
    shadows the camera can see: all but point lights at the camera, which hide every
    shadow behind what casts it (a lens: at its centre)."""
    eye = camera.viewpoint()
    if eye is None:
        eye = np.append(np.asarray(camera.world_from_camera.matrix, np.float64)[:3, 3], 1.0)
    return [(i, light) for i, light in enumerate(scene.rendering_lights)
            if isinstance(light, DirectionalLight)
            or isinstance(light, PointLight)
            and not (eye[3] and np.allclose(light.position, eye[:3], rtol=0,
                                            atol=1e-6 * (1 + np.abs(eye).max())))]


def _first_hits(scene, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Phase 1 only for (N, 3) NumPy rays: (t (N,) float64, instance (N,), MISS where none).
    The rays go to Dr.Jit's own storage (:func:`~instancing.core.backend.device_vectors`): a
    kernel reading NumPy buffers is compiled anew for their alignment, every step."""
    hit = scene.intersect_preliminary(device_vectors(origins), device_vectors(directions))
    dr.eval(hit.t, hit.instance)
    return np.asarray(hit.t, np.float64), np.asarray(hit.instance)


def shadow_receivers(scene, lights, light: UInt32, offset: Float, p: Array3f, tangent: Array3f,
                     active: Bool) -> tuple[Array3f, Array3f, Bool]:
    """Where shadow curves fall: for curve points ``p`` (moving with the occluder) and their
    tangents, cast by delta light ``light`` (index into ``lights.delta``), the point on the
    next surface along the ray from the light through p, searched from ``offset`` past p,
    with derivatives from the occluder, the receiver and the light (phase 2 on the ray
    from the light, AD attached), its tangent along the curve (detached) and whether a
    surface was found."""
    z, dz, found = Array3f(0.0), Array3f(0.0), Bool(False)
    for j, delta in enumerate(lights.delta):
        kind = delta.kind
        mine = active & (light == j)
        # The ray from the light through p, d = p - L (or the light's direction), from a
        # point past p: phase 2 finds the receiver's nearest hit from its origin, and the
        # occluder itself may be the receiver (its rim's shadow falls inside it).
        d = p - delta.vector if kind == "point" else delta.vector
        with dr.suspend_grad():
            length = dr.norm(dr.detach(d))
            unit = dr.detach(d) / length
            first = scene.intersect_preliminary(dr.detach(p) + unit * offset, unit, mine)
        o = p + d * (offset / length)
        hit = reintersect(scene.instances, o, d,
                          PreliminaryHit(first.t / length, first.instance, first.position))
        with dr.suspend_grad():
            # The curve's tangent carried along the ray onto the receiver's tangent plane
            # (z = L + s (p - L), s = |z - L| / |p - L|, for a point light).
            n = dr.detach(hit.n)
            along = dr.dot(n, tangent) / dr.dot(n, dr.detach(d))
            stretch = 1.0 + dr.detach(hit.t) + offset / length if kind == "point" else 1.0
            dz_j = stretch * (tangent - dr.detach(d) * along)
        z = dr.select(mine, hit.p, z)
        dz = dr.select(mine, dz_j, dz)
        found |= mine & hit.valid
    return z, dz, found


def boundary_term(sampler_data: BoundarySampler | None, scene, batch: CameraBatch,
                  radiance: Callable, channels: int, sppp: int, seed: UInt32, max_lanes: int,
                  pixel_filter: PixelFilter,
                  lights=None) -> list[Float] | None:
    """Per-pixel boundary contribution (value 0, derivative = the boundary term) in every
    view of a camera batch, sampled as one wavefront.

    Args:
        sampler_data: the frame's curves (:func:`boundary_sampler`, or the shadow curves
            of :func:`shadow_samplers`; for several views, their
            :meth:`BoundarySampler.joined` table); the Dr.Jit work here reads only
            arrays, so an optimisation step can be recorded.
        scene: the scene; only ``scene.moving_instances`` contribute.
        batch: the pinhole cameras the images are rendered from.
        radiance: ``radiance(o, d, sampler) -> list[Float]`` of ``channels``
            values per ray (the integrator, evaluated detached here).
        sppp: boundary samples per pixel (the total is sppp * W * H per view; view k's
            samples are lanes k * sppp * W * H onwards of the batch's streams).
        seed: render seed (an opaque UInt32).
        max_lanes: samples traced at once at most.
        pixel_filter: the camera's reconstruction filter.
        lights: the scene's light set (:class:`~instancing.scene.lights.LightSet`), for
            shadow curves.

    Returns:
        one Float of W * H pixels per view per channel (view-major, then row-major), or
        None when there are no curves or no samples.
    """
    if sampler_data is None or sppp <= 0:
        return None
    camera = batch.camera
    w, h = camera.width, camera.height
    per_view = sppp * w * h
    total = per_view * len(batch)
    image = [dr.zeros(Float, w * h * len(batch)) for _ in range(channels)]
    table = scene.instances
    shadows = sampler_data.light is not None
    stream, side_stream = ((SHADOW_STREAM_SEED, SHADOW_SIDE_STREAM_SEED) if shadows
                           else (CONTACT_STREAM_SEED, CONTACT_SIDE_STREAM_SEED)
                           if sampler_data.contact is not None
                           else (TERMINATOR_STREAM_SEED, TERMINATOR_SIDE_STREAM_SEED)
                           if sampler_data.terminator is not None
                           else (MIRROR_STREAM_SEED, MIRROR_SIDE_STREAM_SEED)
                           if sampler_data.mirror is not None
                           else (BOUNDARY_STREAM_SEED, SIDE_STREAM_SEED))
    for first in range(0, total, max_lanes):
        lanes = min(max_lanes, total - first)
        index = dr.arange(UInt32, lanes) + dr.opaque(UInt32, first)
        rng = sample_streams(index, seed + stream)
        view = index // dr.opaque(UInt32, per_view) if len(batch) > 1 else None
        lanes = batch.lanes(view)
        u_pick, u_param = rng.next_float32(), rng.next_float32()
        curve, instance, x_obj, tangent, probability, found = sampler_data.sample(
            u_pick, u_param, view)
        if sampler_data.contact is not None and sampler_data.contact.quadrics:
            x_obj, tangent, on_curve = _onto_intersection(scene, sampler_data, curve, instance,
                                                          x_obj, tangent)
            found &= on_curve
        # Map the curve point through the instance's differentiable transform.
        rows = table.forward(instance)
        p = world_point(rows, x_obj)
        with dr.suspend_grad():
            p_tangent = world_vector(rows, tangent)
        if sampler_data.terminator is not None:
            p, p_tangent, on_arc = _terminator_points(scene, sampler_data, camera, lanes, curve, instance,
                                                      x_obj, u_param)
            found &= on_arc
        if sampler_data.contact is not None:
            p, on_both = _contact_points(scene, sampler_data, curve, instance, x_obj, p)
            found &= on_both
        if sampler_data.mirror is not None:
            # A curve seen in a flat mirror: where the camera sees its mirror image, if it
            # lies on the camera's side of the mirror.
            normal = dr.gather(Array3f, sampler_data.mirror.normal, curve)
            offset = dr.gather(Float, sampler_data.mirror.offset, curve)
            height = dr.dot(normal, p) - offset
            eye, eye_w = camera.lane_viewpoint(lanes)
            found &= dr.detach(height) * (dr.dot(normal, eye) - eye_w * offset) > 0
            p = p - 2.0 * height * normal
            p_tangent = p_tangent - 2.0 * dr.dot(normal, p_tangent) * normal
        if shadows:
            # A shadow curve is seen where it falls: on the next surface from its light.
            p, p_tangent, received = shadow_receivers(
                scene, lights, dr.gather(UInt32, sampler_data.light, curve),
                dr.gather(Float, sampler_data.offset, curve), p, p_tangent, found)
            found &= received
        fx, fy, in_front = camera.project(p, lanes)
        # Film-space tangent and unit normal of the curve at the sample (detached).
        with dr.suspend_grad():
            tx, ty = camera.film_velocity(dr.detach(p), p_tangent, lanes)
            speed = dr.sqrt(dr.fma(tx, tx, ty * ty))
            nx, ny = ty / speed, -tx / speed
            x0, y0 = dr.detach(fx), dr.detach(fy)
            # Where film samples are drawn: the film, or its border within the filter's reach
            # when the film samples that (a curve beyond the film's edge changes no sample
            # restricted to the film, even where the filter around an edge pixel reaches it).
            margin = 0.0 if pixel_filter.film_only else pixel_filter.radius or 0.0
            valid = found & in_front & (speed > 0) & (x0 >= -margin) & (x0 < w + margin) \
                & (y0 >= -margin) & (y0 < h + margin)
            # Step 1: the jump of f across the curve, from both sides with the same random
            # numbers. At the smooth silhouette of a curved surface the normal, and so the
            # shading, varies as the square root of the distance e to the curve:
            # J(e) = J + a sqrt(e) + O(e), and 2 J(e) - J(4 e) cancels the root term.
            jump = [Float(0.0) for _ in range(channels)]
            steps = (((EDGE_OFFSET, 2.0), (4.0 * EDGE_OFFSET, -1.0)) if sampler_data.curved
                     else ((EDGE_OFFSET, 1.0),))
            for offset, coefficient in steps:
                sides = []
                for sign in (-1.0, 1.0):
                    o, d = camera.rays((x0 + sign * offset * nx) / w,
                                       (y0 + sign * offset * ny) / h, None, lanes)
                    if shadows:
                        # The shadow curve must be in view on this side (see
                        # SHADOW_VISIBILITY_TOLERANCE).
                        distance = dr.norm(dr.detach(p) - o)
                        seen = scene.intersect_preliminary(o, d, valid).t
                        valid &= dr.abs(seen - distance) <= SHADOW_VISIBILITY_TOLERANCE * distance
                    side_rng = sample_streams(index, seed + side_stream)
                    sides.append(radiance(o, d, side_rng))
                jump = [j + coefficient * (a - b) for j, a, b in zip(jump, *sides)]
            # Step 2: Monte Carlo weight 1 / (pdf per film length * the view's sample count).
            weight = dr.select(valid, speed / (probability * per_view), 0.0)
        # Step 3: normal velocity of the moving point (AD), value 0.
        velocity = nx * (fx - x0) + ny * (fy - y0)
        # (Each view's pixels follow the previous view's.)
        first_pixel = UInt32(0) if view is None else view * (w * h)
        for ch in range(channels):
            contribution = jump[ch] * weight * velocity
            _splat(image[ch], contribution, x0, y0, valid, w, h, pixel_filter, first_pixel)
    return image


def _splat(target: Float, value: Float, x: Float, y: Float, valid: Bool, w: int, h: int,
           pixel_filter: PixelFilter, first_pixel: UInt32) -> None:
    """Add film-space contributions to the pixels whose filter covers (x, y), of the film
    that starts at ``first_pixel`` of ``target``."""
    if pixel_filter.radius is None:
        px, py = UInt32(dr.floor(x)), UInt32(dr.floor(y))
        dr.scatter_reduce(dr.ReduceOp.Add, target, value, first_pixel + py * w + px, valid)
        return
    reach = int(math.ceil(pixel_filter.radius))
    bx, by = dr.floor(x), dr.floor(y)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            px, py = bx + dx, by + dy
            inside = valid & (px >= 0) & (px < w) & (py >= 0) & (py < h)
            # The filter's density, restricted to the film (as the film samples are).
            k = (pixel_filter.weight(px + 0.5 - x) * pixel_filter.weight(py + 0.5 - y)
                 / (pixel_filter.film_share(px + 0.5, w) * pixel_filter.film_share(py + 0.5, h)))
            dr.scatter_reduce(dr.ReduceOp.Add, target, value * k,
                              first_pixel + UInt32(py) * w + UInt32(px), inside & (k > 0))
