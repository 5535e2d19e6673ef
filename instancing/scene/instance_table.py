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

import functools
from typing import Any

import numpy as np

from ..core.backend import Array3f, Array4f, Bool, Float, UInt32, device_array, dr
from ..core.error_bounds import remap_error
from ..core.transform import Transform
from ..models.analytic import wide_scales
from ..models.bspline_curve import BSplineCurveLibrary
from ..models.linear_curve import LinearCurveLibrary
from ..models.mesh import MeshLibrary
from ..models.sdf_grid import SDFGridLibrary

#: Kind name of triangle meshes in the table (obj and ply models).
MESH_KIND = "mesh"
#: Kind name of signed distance grids (Mitsuba's ``sdfgrid``).
GRID_KIND = "sdfgrid"
#: Kind name of linear curves (Mitsuba's ``linearcurve``).
CURVE_KIND = "linearcurve"
#: Kind name of cubic B-spline curves (Mitsuba's ``bsplinecurve``).
BSPLINE_KIND = "bsplinecurve"


class InstanceTable:
    """Per-instance arrays of a scene.

    Built from the user's float64 matrices and their float64 inverses, which
    are rounded to float32 once and not kept: from then on the stored float32
    matrices are the scene's transforms (as in Mitsuba, whose transforms are
    float32), and :attr:`to_world` / :attr:`from_world` read them back as
    float64 on demand.

    Args:
        to_world: (N, 4, 4) float64 world_from_object matrices.
        from_world: (N, 4, 4) float64 object_from_world matrices (their inverses,
            computed in float64 from the user's input, never from the rounded matrix).
        kind_names: the model kinds present, in code order (e.g. ``["sphere", "mesh"]``).
        kind_code: (N,) index into ``kind_names`` per instance (not stored for one kind).
        mesh_root: (N,) BVH root reference of mesh and grid instances (into their
            library's forest), anything for the others (not stored when all such instances
            share one root).
        meshes: the scene's mesh library, or None when no instance is a mesh.
        grids: the scene's SDF grid library, or None when no instance is a grid.
        curves: the scene's linear curve library, or None when no instance is a curve.
        bsplines: the scene's B-spline curve library, or None when no instance is one.
        inward: (N,) bool per instance, True where its analytic model is turned inside out
            (``flip_normals``; stored only where some is), or None.

    Dr.Jit arrays (float32, gathered in kernels): ``inverse_rows`` (per instance
    three float4 packets: A^-1 row i with the forward translation b_i in w),
    ``forward_linear`` (per instance the 9 entries of A, row by row; b is read
    from ``inverse_rows``, not stored twice) and ``remap_error`` (per instance,
    :func:`~instancing.core.error_bounds.remap_error`; computing it in the kernel
    from the gathered rows instead was measured 15-20 % slower on rendering):
    88 bytes per instance.
    """

    def __init__(self, to_world: np.ndarray, from_world: np.ndarray, kind_names: list[str],
                 kind_code: np.ndarray, mesh_root: np.ndarray, meshes: MeshLibrary | None,
                 grids: SDFGridLibrary | None = None, curves: LinearCurveLibrary | None = None,
                 bsplines: BSplineCurveLibrary | None = None, inward: np.ndarray | None = None):
        self.count = len(to_world)
        self.kind_names = kind_names
        self.meshes = meshes
        self.grids = grids
        self.curves = curves
        self.bsplines = bsplines
        #: The libraries of the kinds that walk a BVH of their own, by kind name.
        self.libraries = {kind: library for kind, library in
                          ((MESH_KIND, meshes), (GRID_KIND, grids), (CURVE_KIND, curves),
                           (BSPLINE_KIND, bsplines)) if library is not None}
        #: Whether surface records carry surface coordinates (set by a scene whose
        #: materials read textures; else uv is 0 and not computed).
        self.surface_uv = False
        #: Whether hits compute the shading tangent from dp/du (some material is anisotropic).
        self.surface_tangents = False
        #: Whether surface records carry dp/du and dp/dv (some material is bump-mapped).
        self.surface_derivatives = False
        #: Whether surface records carry the hit triangle and its barycentrics (some
        #: material reads mesh attributes).
        self.surface_attributes = False
        #: Whether some instance's scale needs the quadrics' unit-exponent test
        #: (:func:`~instancing.models.analytic.wide_scales`; set by the scene, never unset).
        self.wide_scales = wide_scales(to_world)
        # Per instance 12 floats for phase 1, gathered as three float4 packets: row i
        # holds row i of the inverse linear part A^-1 and, in w, the forward
        # translation b_i (see object_ray for why not -A^-1 b). The forward linear
        # part A maps hit points back (world_point) with the same b_i.
        self.inverse_rows = _pack_rows(from_world[:, :3, :3], to_world[:, :3, 3])
        self.forward_linear = device_array(Float, to_world[:, :3, :3].astype(np.float32).ravel())
        self._update_remap_error()
        # Per-instance indices only where they vary: one kind needs no kind code, one
        # walked model (a mesh or a grid) no per-instance root.
        self.kind_code = (device_array(UInt32, np.asarray(kind_code, np.uint32))
                           if len(kind_names) > 1 else None)
        #: Per instance whether its analytic model's normals point inward (``Bool``), or
        #: None where every normal points outward as the model defines it.
        self.inward = (device_array(Bool, np.asarray(inward, bool))
                       if inward is not None and np.any(inward) else None)
        roots = [r for library in self.libraries.values() for r in library.root_refs]
        self.mesh_root = None
        if roots:
            self.mesh_root = (device_array(UInt32, np.asarray(mesh_root, np.uint32))
                               if len(roots) > 1 else roots[0])

    # -- the stored matrices as float64 ------------------------------------------------------

    @property
    def to_world(self) -> np.ndarray:
        """(N, 4, 4) float64 world_from_object matrices: the stored float32 values, exactly."""
        return self.to_world_of(slice(None))

    @property
    def from_world(self) -> np.ndarray:
        """(N, 4, 4) float64 object_from_world matrices: the stored float32 A^-1 and
        -A^-1 b from the stored A^-1 and b, in float64."""
        return self.from_world_of(slice(None))

    def to_world_of(self, instances: Any) -> np.ndarray:
        """float64 world_from_object matrices of ``instances`` (an index, slice or index array)."""
        inverse, linear = self._rows_of(instances)
        out = np.zeros(linear.shape[:-2] + (4, 4))
        out[..., :3, :3] = linear
        out[..., :3, 3] = inverse[..., :, 3]
        out[..., 3, 3] = 1.0
        return out

    def from_world_of(self, instances: Any) -> np.ndarray:
        """float64 object_from_world matrices of ``instances`` (an index, slice or index array)."""
        inverse = self._rows_of(instances)[0]
        out = np.zeros(inverse.shape[:-2] + (4, 4))
        out[..., :3, :3] = inverse[..., :3]
        out[..., :3, 3] = -np.einsum("...ij,...j->...i", inverse[..., :3], inverse[..., :, 3])
        out[..., 3, 3] = 1.0
        return out

    def _rows_of(self, instances: Any) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_host_rows` of an index, slice or index array; only the indexed
        instances are read back (a step's few moving instances out of a million)."""
        if isinstance(instances, slice):
            inverse, linear = self._host_rows()
            return inverse[instances], linear[instances]
        index = np.asarray(instances, np.int64)
        inverse, linear = self._host_rows(index.ravel() % max(self.count, 1))
        return inverse.reshape(index.shape + (3, 4)), linear.reshape(index.shape + (3, 3))

    def _host_rows(self, instances: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Detached float32 NumPy copies of the inverse rows (N, 3, 4) and the forward
        linear parts (N, 3, 3), of every instance or of the index array ``instances``
        (K,) (gathered before the read-back)."""
        inverse, linear = dr.detach(self.inverse_rows), dr.detach(self.forward_linear)
        if instances is None:
            return (np.asarray(inverse).reshape(self.count, 3, 4),
                    np.asarray(linear).reshape(self.count, 3, 3))
        k = len(instances)
        index = device_array(UInt32, np.asarray(instances, np.uint32))

        def picked(flat: Float, width: int) -> np.ndarray:
            # The ``width`` entries of each listed instance, gathered in one kernel.
            entry = dr.arange(UInt32, width * k)
            return np.asarray(dr.gather(Float, flat, dr.gather(UInt32, index, entry // width) * width
                                        + entry % width))

        return picked(inverse, 12).reshape(k, 3, 4), picked(linear, 9).reshape(k, 3, 3)

    # -- installing new transforms -------------------------------------------------------------

    def set_transforms(self, world_from_object: Transform, changed: np.ndarray | UInt32 | None = None,
                       derivatives_only: bool = False) -> None:
        """Replace instances' transforms by per-lane ones.

        Args:
            world_from_object: without ``changed``, one lane per instance (or one
                for all): every row is packed anew. With ``changed``, lane k is
                instance ``changed[k]``: those rows are written into a copy of the
                stored ones (O(K) work besides the copy; at 1e6 instances the full
                packing cost a step 0.3 s).
            changed: the instances whose transforms differ from the stored ones
                (NumPy or ``UInt32`` indices); only their remap bounds are computed again.
            derivatives_only: the stored values stay; the ``changed`` instances' rows
                gain the derivatives of their lanes (attaching parameters). No host work.

        Keeps the AD graph: the inverse and forward linear parts and the
        translation come from the transform's own matrices, so gradients of
        anything computed from the table reach the parameters they were built from.
        """
        inverse, forward = world_from_object.inverse_matrix, world_from_object.matrix
        # Evaluate the matrices first: a gather from a pending entry would evaluate
        # that entry as its own kernel, whose code depends on the alignment of the
        # NumPy buffers it was made from, and so re-compile on most optimisation steps.
        dr.eval(inverse, forward)
        inverse_slots = [inverse[r][c] if c < 3 else forward[r][3] for r in range(3) for c in range(4)]
        forward_slots = [forward[r][c] for r in range(3) for c in range(3)]
        if changed is None:
            self.inverse_rows = self._packed(inverse_slots, 12)
            self.forward_linear = self._packed(forward_slots, 9)
        else:
            index = changed if isinstance(changed, UInt32) else \
                device_array(UInt32, np.asarray(changed, np.uint32))
            self.inverse_rows = _written(self.inverse_rows, inverse_slots, index, 12, derivatives_only)
            self.forward_linear = _written(self.forward_linear, forward_slots, index, 9,
                                           derivatives_only)
        dr.eval(self.inverse_rows, self.forward_linear)
        if not derivatives_only:
            self._update_remap_error(None if changed is None else np.asarray(changed, np.int64))

    def rows(self) -> tuple[Float, Float]:
        """The stored rows ``(inverse_rows, forward_linear)``, for :meth:`restore_rows`."""
        return self.inverse_rows, self.forward_linear

    def restore_rows(self, rows: tuple[Float, Float]) -> None:
        """Put back rows that :meth:`rows` returned (same instances, same values; e.g.
        the detached rows after a step attached derivatives)."""
        self.inverse_rows, self.forward_linear = rows

    def detach(self) -> None:
        """Drop the rows' derivatives (the values stay)."""
        self.inverse_rows, self.forward_linear = dr.detach(self.inverse_rows), dr.detach(self.forward_linear)

    def _packed(self, slots: list, width: int) -> Float:
        """One packed entry per lane of width * count: a select over the slots of gathered
        matrix entries. Side-effect free and evaluated at once, so every call compiles
        to the same kernel (scatters fused unpredictably with later work and re-compiled
        on most optimisation steps)."""
        lane = dr.arange(UInt32, width * self.count)
        instance, slot = lane // width, lane % width
        flat = Float(0.0)
        for k, entry in enumerate(slots):
            value = entry if dr.width(entry) == 1 else dr.gather(Float, entry, instance)
            flat = dr.select(slot == k, value, flat)
        return flat

    def _update_remap_error(self, instances: np.ndarray | None = None) -> None:
        """Per-instance remap bound of the stored float32 matrices (error_bounds.remap_error),
        of every instance or only of ``instances``."""
        if instances is not None and len(instances) == 0:
            return
        inverse, linear = self._host_rows(instances)
        values = remap_error(linear.astype(np.float64), inverse[:, :, :3].astype(np.float64))
        if instances is None:
            self.remap_error = device_array(Float, values)
            return
        # A fresh array (not a scatter into the old one, which a pending kernel may still read).
        remap = dr.copy(self.remap_error)
        dr.scatter(remap, device_array(Float, values.astype(np.float32)),
                   device_array(UInt32, np.asarray(instances, np.uint32)))
        dr.eval(remap)
        self.remap_error = remap

    # -- lecture: "Intersecting Transformed Objects" -------------------------------------------

    def inverse(self, instance: UInt32) -> tuple[Array4f, Array4f, Array4f]:
        """Per-lane rows (A^-1 row i, b_i) of each lane's instance."""
        return _gather_rows(self.inverse_rows, instance)

    def inverse_rows_of(self, instances: list[int]) -> np.ndarray:
        """The stored float32 rows (A^-1 row i, b_i) of ``instances``, (K, 12) NumPy, values
        only (read from the device)."""
        if not instances:
            return np.zeros((0, 12), np.float32)
        index = device_array(UInt32, np.repeat(np.asarray(instances, np.uint32) * 12, 12)
                             + np.tile(np.arange(12, dtype=np.uint32), len(instances)))
        return np.asarray(dr.gather(Float, dr.detach(self.inverse_rows), index), np.float32).reshape(-1, 12)

    def forward(self, instance: UInt32) -> tuple[Array4f, Array4f, Array4f]:
        """Per-lane rows (A row i, b_i) of each lane's instance (b_i is stored in the
        inverse rows)."""
        b = [dr.gather(Float, self.inverse_rows, instance * 12 + (4 * r + 3)) for r in range(3)]
        return tuple(Array4f(*dr.gather(Array3f, self.forward_linear, instance * 3 + r), b[r])
                     for r in range(3))

    def oriented(self, instance: UInt32, normal: Any) -> Any:
        """An analytic model's outward ``normal`` at each lane's hit, negated where the
        lane's instance faces inward (:attr:`inward`)."""
        if self.inward is None:
            return normal
        return dr.select(dr.gather(Bool, self.inward, instance), -normal, normal)

    def kind_mask(self, instance: UInt32, code: int) -> Bool | bool:
        """Lanes whose instance has model kind ``code`` (True when one kind only)."""
        if self.kind_code is None:
            return True
        return dr.gather(UInt32, self.kind_code, instance) == code

    def kind_of(self, instance: int) -> str:
        """The model kind name of one instance (read on the host, see :attr:`host_codes`)."""
        codes = self.host_codes[0]
        return self.kind_names[0 if codes is None else int(codes[instance])]

    @functools.cached_property
    def host_codes(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Kind codes and mesh roots per instance as NumPy arrays (None where not stored),
        for tracing code per instance: read once, because every read of a Dr.Jit array
        waits for the kernels in flight (measured: 0.5 s behind a running kernel)."""
        return tuple(None if a is None or isinstance(a, int) else np.asarray(a)
                     for a in (self.kind_code, self.mesh_root))


def _written(flat: Float, slots: list, index: UInt32, width: int, derivatives_only: bool) -> Float:
    """A copy of the packed rows ``flat`` (``width`` entries per instance, detached) with
    entry k of instance ``index[j]`` replaced by lane j of ``slots[k]``; with
    ``derivatives_only`` the stored value stays and gains that lane's derivative. The
    scatters are evaluated by the caller at once, so the kernel is the same every call."""
    stored = dr.detach(flat)
    out = dr.copy(stored)
    for k, entry in enumerate(slots):
        position = index * width + k
        if derivatives_only:
            entry = dr.gather(Float, stored, position) + (entry - dr.detach(entry))
        dr.scatter(out, entry, position)
    return out


def _pack_rows(linear: np.ndarray, translation: np.ndarray) -> Float:
    """(N, 3, 3) linear parts and (N, 3) translations as flat float32 (A row i, b_i) packets."""
    rows = np.concatenate([linear, translation[:, :, None]], axis=2)
    return device_array(Float, rows.astype(np.float32).ravel())


def _gather_rows(flat: Float, instance: UInt32) -> tuple[Array4f, Array4f, Array4f]:
    """The three float4 row packets of each lane's instance."""
    return tuple(dr.gather(Array4f, flat, instance * 3 + r) for r in range(3))
