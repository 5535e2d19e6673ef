"""The instance table (lecture: "Instancing").

An instance is a reference to one shared base model, its inverse
transformation (with the forward one) and a material. The table stores these
as flat per-instance arrays, gathered by instance index inside kernels: no
Python object and no virtual call per instance.

Kernels only contain code for the model kinds present in the scene: the
per-kind tests below are unrolled over ``kinds`` (a Python loop over model
*types*), so a sphere-only scene traces sphere code and nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .backend import Array3f, Array3f64, Array4f, Bool, Float, Float64, UInt32, dr
from .error_bounds import remap_error
from .models.analytic import ANALYTIC_MODELS
from .models.mesh import MeshLibrary
from .transform import Transform

#: Kind name of triangle meshes in the table (obj and ply models).
MESH_KIND = "mesh"


@dataclass
class InstanceTable:
    """Per-instance arrays of a scene.

    Attributes:
        to_world: (N, 4, 4) float64 world_from_object matrices.
        from_world: (N, 4, 4) float64 object_from_world matrices (their inverses).
        kind_names: the model kinds present, in code order (e.g. ``["sphere", "mesh"]``).
        kind_code: (N,) int index into ``kind_names`` per instance.
        mesh_root: (N,) int BVH root reference of mesh instances (0 otherwise).
        meshes: the scene's mesh library, or None when no instance is a mesh.

    Derived Dr.Jit arrays (float32, gathered in kernels): ``inverse_rows`` and
    ``forward_rows`` (per instance three float4 packets, A^-1 row i or A row i
    with b_i), ``remap_error`` (per instance, :func:`~instancing.error_bounds.remap_error`).
    """

    to_world: np.ndarray
    from_world: np.ndarray
    kind_names: list[str]
    kind_code: np.ndarray
    mesh_root: np.ndarray
    meshes: MeshLibrary | None

    def __post_init__(self):
        self.count = len(self.to_world)
        # Per instance 12 floats, gathered as three float4 packets: row i holds
        # row i of the inverse linear part A^-1 and, in w, the forward
        # translation b_i (see object_ray for why not -A^-1 b); the forward
        # rows hold row i of A and b_i, to map hit points back (world_point).
        translation = self.to_world[:, :3, 3]
        self.inverse_rows = _pack_rows(self.from_world[:, :3, :3], translation)
        self.forward_rows = _pack_rows(self.to_world[:, :3, :3], translation)
        self._update_remap_error()
        self._kind_code = UInt32(self.kind_code.astype(np.uint32)) if len(self.kind_names) > 1 else None
        self._mesh_root = (UInt32(self.mesh_root.astype(np.uint32))
                           if MESH_KIND in self.kind_names else None)

    def set_transforms(self, world_from_object: Transform) -> None:
        """Replace every instance's transform by a per-lane one (one lane per instance).

        Keeps the AD graph: the inverse and forward linear parts and the
        translation come from the transform's own matrices, so gradients of
        anything computed from the table reach the parameters they were built from.
        """
        inverse, forward = world_from_object.inverse_matrix, world_from_object.matrix
        # One packed entry per lane of 12 * count: a select over the 12 (row, column)
        # slots of gathered matrix entries. Side-effect free and evaluated at once, so
        # every call compiles to the same kernel (scatters fused unpredictably with
        # later work and re-compiled on most optimisation steps).
        lane = dr.arange(UInt32, 12 * self.count)
        instance, slot = lane // 12, lane % 12
        flats = []
        for linear in (inverse, forward):
            flat = Float(0.0)
            for r in range(3):
                for c in range(4):
                    entry = linear[r][c] if c < 3 else forward[r][3]
                    value = entry if dr.width(entry) == 1 else dr.gather(Float, entry, instance)
                    flat = dr.select(slot == 4 * r + c, value, flat)
            flats.append(flat)
        dr.eval(flats)
        self.inverse_rows, self.forward_rows = flats
        self._update_remap_error()

    def _update_remap_error(self) -> None:
        """Per-instance remap bound of the stored float32 matrices (error_bounds.remap_error)."""
        def linear(flat):
            return np.asarray(dr.detach(flat), np.float64).reshape(self.count, 3, 4)[:, :, :3]

        self.remap_error = Float(remap_error(linear(self.forward_rows), linear(self.inverse_rows)))

    # -- lecture: "Intersecting Transformed Objects" -------------------------------------------

    def inverse(self, instance: UInt32) -> tuple[Array4f, Array4f, Array4f]:
        """Per-lane rows (A^-1 row i, b_i) of each lane's instance."""
        return _gather_rows(self.inverse_rows, instance)

    def forward(self, instance: UInt32) -> tuple[Array4f, Array4f, Array4f]:
        """Per-lane rows (A row i, b_i) of each lane's instance."""
        return _gather_rows(self.forward_rows, instance)

    @staticmethod
    def world_point(rows, p_obj: Array3f) -> Array3f:
        """Map an object-space point to world space: ``A p + b``, the translation added last.

        Adding b last keeps the full relative precision of the small term
        ``A p`` until the one rounding that the world coordinate needs anyway
        (pbrt-v4 transforms points this way).
        """
        return type(p_obj)(*[dr.fma(r.z, p_obj.z, dr.fma(r.y, p_obj.y, r.x * p_obj.x)) + r.w
                             for r in rows])

    @staticmethod
    def world_vector(rows, v_obj: Array3f) -> Array3f:
        """Map an object-space vector to world space: ``A v`` (no translation)."""
        return type(v_obj)(*[dr.fma(r.z, v_obj.z, dr.fma(r.y, v_obj.y, r.x * v_obj.x))
                             for r in rows])

    @staticmethod
    def object_ray(rows, o: Array3f, d: Array3f) -> tuple[Array3f, Array3f]:
        """Transform the ray into object space: origin with w=1, direction with w=0.

        The origin is mapped as ``A^-1 (o - b)`` rather than ``A^-1 o - A^-1 b``:
        the same affine map, but the subtraction is exact when the ray starts
        near the instance (Sterbenz), so secondary rays and instances far from
        the world origin keep full relative precision. The direction is not
        renormalized, so t is the same number in both spaces.
        """
        vector = type(o)
        rel = vector(o.x - rows[0].w, o.y - rows[1].w, o.z - rows[2].w)

        def linear(r, v):
            return dr.fma(r.z, v.z, dr.fma(r.y, v.y, r.x * v.x))

        return (vector(linear(rows[0], rel), linear(rows[1], rel), linear(rows[2], rel)),
                vector(linear(rows[0], d), linear(rows[1], d), linear(rows[2], d)))

    @staticmethod
    def world_normal(rows, n_obj: Array3f) -> Array3f:
        """Transform an object-space normal by the inverse transpose, then normalize."""
        r0, r1, r2 = rows
        vector = type(n_obj)
        n = vector(r0.x, r0.y, r0.z) * n_obj.x
        n = dr.fma(vector(r1.x, r1.y, r1.z), n_obj.y, n)
        n = dr.fma(vector(r2.x, r2.y, r2.z), n_obj.z, n)
        # Correctly rounded sqrt and division (dr.normalize's rsqrt approximation costs ~1 ulp).
        return n / dr.sqrt(dr.squared_norm(n))

    def _kind_mask(self, instance: UInt32, code: int) -> Bool | bool:
        """Lanes whose instance has model kind ``code`` (True when one kind only)."""
        if self._kind_code is None:
            return True
        return dr.gather(UInt32, self._kind_code, instance) == code

    def intersect_object(self, instance: UInt32, o: Array3f, d: Array3f,
                         t_max: Float) -> tuple[Float, UInt32]:
        """Intersect object-space rays with each lane's untransformed model.

        Returns ``(t, position)``: t in (0, t_max) or inf; position is the
        leaf-order triangle for meshes and 0 otherwise.
        """
        t = Float(dr.inf)
        position = UInt32(0)
        for code, name in enumerate(self.kind_names):
            mask = self._kind_mask(instance, code)
            if name == MESH_KIND:
                root = dr.gather(UInt32, self._mesh_root, instance)
                t_k, pos_k = self.meshes.intersect(o, d, t_max, Bool(mask), root)
                position = dr.select(mask, pos_k, position)
            else:
                t_k = ANALYTIC_MODELS[name].intersect(o, d, t_max)
            t = dr.select(mask, t_k, t)
        return t, position

    def reintersect_object(self, instance: UInt32, o: Array3f64, d: Array3f64,
                           position: UInt32) -> tuple[Float64, Array3f64, Array3f64, Array3f64]:
        """Differentiable t, object-space hit point, its error bound and object-space normal
        for a known instance and triangle, in float64.

        No traversal: the winning model (and triangle) is tested once more
        with AD attached, in float64 (see :func:`instancing.intersection.reintersect`).
        The hit point is the model's own, re-projected onto its surface
        (barycentric for triangles), with the model's error bound.
        """
        t = Float64(dr.inf)
        p = Array3f64(0.0)
        error = Array3f64(0.0)
        n = Array3f64(0.0)
        for code, name in enumerate(self.kind_names):
            mask = self._kind_mask(instance, code)
            if name == MESH_KIND:
                t_k, p_k = self.meshes.surface_point(o, d, position)
                e_k = Array3f64(self.meshes.point_error(position))
                n_k = self.meshes.normal(position, Array3f64)
            else:
                model = ANALYTIC_MODELS[name]
                t_k = model.intersect(o, d, dr.inf)
                p_k = model.surface_point(o, d, t_k)
                e_k = model.point_error(p_k)
                n_k = model.normal(p_k, position)
            t = dr.select(mask, t_k, t)
            p = dr.select(mask, p_k, p)
            error = dr.select(mask, e_k, error)
            n = dr.select(mask, n_k, n)
        return t, p, error, n

    def prim_index(self, instance: UInt32, position: UInt32) -> UInt32:
        """User-facing primitive index: the triangle's file index for meshes, else 0."""
        if self.meshes is None:
            return UInt32(0)
        mesh_code = self.kind_names.index(MESH_KIND)
        return dr.select(self._kind_mask(instance, mesh_code),
                         self.meshes.prim_index(position), 0)


def _pack_rows(linear: np.ndarray, translation: np.ndarray) -> Float:
    """(N, 3, 3) linear parts and (N, 3) translations as flat float32 (A row i, b_i) packets."""
    rows = np.concatenate([linear, translation[:, :, None]], axis=2)
    return Float(np.ascontiguousarray(rows.astype(np.float32)).ravel())


def _gather_rows(flat: Float, instance: UInt32) -> tuple[Array4f, Array4f, Array4f]:
    """The three float4 row packets of each lane's instance."""
    return tuple(dr.gather(Array4f, flat, instance * 3 + r) for r in range(3))
