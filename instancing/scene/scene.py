"""The scene builder and the public intersection entry point.

:class:`Scene` takes a validated description (made by
:func:`instancing.io.scene_file.load_scene`), loads the models once each, stores
flat per-instance arrays, computes the instances' world bounds and builds the
acceleration structure over them (the lecture's uniform grid, or a BVH where
the grid would be poor; a scene of a few instances needs none: each ray tests
them one after the other, see UNROLL_MAX_INSTANCES). ``Scene.intersect`` then
answers ray queries with the two-phase method of :mod:`instancing.scene.intersection`.

Per instance, a built scene keeps only what kernels gather (float32 matrices,
and model kind, mesh and material indices where they vary) and the
acceleration structure, 124 bytes per instance for a uniform sphere field
(benchmarks/scale.py); the float64 input matrices and the per-instance world
boxes are released after the build.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from ..accel.bvh import BVHKernel, build_bvh, refit_bvh
from ..accel.grid import GridKernel, build_grid, update_grid
from ..core.backend import (BACKEND_NAME, Array3f, Bool, Float, UInt32, device_array, device_arrays,
                            dr, host_array, rows_from_vectors)
from ..core.arguments import indices, integer
from ..core.box import outward32
from ..core.errors import SceneError
from ..core.kernel_recording import Recordings, call_recorded, jit_state, recordings_of
from ..core.memory import PEAK_BYTES_PER_INSTANCE, require_memory
from ..core.transform import Transform, check_affine_matrix
from ..models.analytic import ANALYTIC_MODELS, transformed_box_bounds, wide_scales
from ..models.curves import Curves
from ..materials.bsdf import BSDFTable
from ..materials.material import attribute_reads
from ..materials.texture import Coordinates, LookupPoint
from ..models.bspline_curve import BSplineCurveLibrary
from ..models.linear_curve import LinearCurveLibrary
from ..models.mesh import MeshLibrary
from ..models.sdf_grid import SDFGridLibrary
from .camera import Camera
from .description import AreaEmitter, Light, SceneDescription
from .instance_table import BSPLINE_KIND, CURVE_KIND, GRID_KIND, MESH_KIND, InstanceTable
from .intersection import (PreliminaryHit, SurfaceHit, WorldBoxes, intersect_preliminary,
                           intersect_preliminary_in_passes, reintersect)
from .lights import LightSet
from .medium import MediaTable
from .rendering_space import RenderingSpace

#: Instances per BVH leaf at the top level.
INSTANCE_LEAF_SIZE = 2
#: The grid is rejected in favour of the BVH when the cells that hold the
#: references hold more than this many on average (sum c^2 / sum c: the
#: occupancy a reference sees), i.e. when dense clusters defeat the uniform
#: subdivision.
GRID_MAX_OCCUPANCY = 12.0

#: 'auto' walks the BVH instead of the grid where most instances are meshes and there are at
#: most this many: a mesh instance's test is a walk of its own, which the grid repeats in every
#: cell the ray shares with it and the BVH runs once (benchmarks/intersect.py fields of tori and
#: the mesh scenes; docs/how-it-works.md).
MESH_BVH_MAX_INSTANCES = 200000
#: 'auto' tests scenes of at most this many instances one after the other in a loop
#: unrolled at trace time (:func:`~instancing.scene.intersection.intersect_preliminary`)
#: instead of walking a structure: faster than the grid up to about 12 instances
#: (benchmarks/render_error.py scenes; docs/how-it-works.md).
UNROLL_MAX_INSTANCES = 12
#: 'auto' on the CUDA backend: the BVH for every scene. On an H200 (benchmarks/intersect.py,
#: 2^20 random rays) it traced 2.0-3.7x the grid's rate at 1 000 and 10 000 instances of
#: every kind and 3.1x the unrolled loop's at 10 meshes; at 10 analytic instances the grid
#: was 1.1-1.3x faster (not acted on: no GPU check of that rule yet). The grid and unrolled
#: choices above are the LLVM backend's measurements.
AUTO_BVH = BACKEND_NAME == "cuda"
#: Instances that 'unrolled' accepts at most when asked for explicitly.
UNROLL_LIMIT = 256
#: Rays from which :meth:`Scene.intersect` walks the grid in passes: below it the passes'
#: own kernel launches cost more than they save (benchmarks/intersect.py; docs/how-it-works.md).
PASSES_MIN_RAYS = 1 << 18
#: Bytes of grid and instance data (see :meth:`Scene._walk_bytes`) from which such a
#: batch is first sorted by where its rays enter the grid (:mod:`instancing.accel.ray_order`):
#: where the data outgrows the CPU's second-level TLB the sort pays for itself
#: (benchmarks/intersect.py; docs/how-it-works.md).
SORT_MIN_WALK_BYTES = 6 << 20
#: Mitsuba's ``math::RayEpsilon`` in float32 (1500 ulp of 1): how much its scene bounding
#: sphere grows, and its radius when the scene has no shapes (:attr:`Scene.bounding_sphere`).
_SPHERE_EPSILON = 1500 * 2.0 ** -24

Accel = Literal["auto", "grid", "bvh", "unrolled", "brute"]


@dataclass(frozen=True)
class Hits:
    """Nearest hits as NumPy arrays (see :class:`~instancing.scene.intersection.SurfaceHit`).

    ``t`` (N,), ``p`` (N, 3) world points (float64 for float64 rays), ``n`` (N, 3),
    ``instance`` (N,) with -1 on a miss, ``prim`` (N,) with -1 on a miss.
    """

    t: np.ndarray
    p: np.ndarray
    n: np.ndarray
    instance: np.ndarray
    prim: np.ndarray


class Scene:
    """A built scene: instances, models, materials and the acceleration structures.

    Create it with :func:`load_scene`.
    """

    def __init__(self, description: SceneDescription, accel: Accel = "auto"):
        count = len(description.instance_model)
        require_memory(count * PEAK_BYTES_PER_INSTANCE, f"building a scene of {count} instances")
        # Counts builds of the acceleration structure (load, set_transforms, set_accel):
        # recorded renders and queries (instancing.core.kernel_recording) of an older
        # revision are dropped.
        self.revision = 0
        self.recordings = Recordings()
        # The description without its float64 matrices: once rounded into the instance
        # table, the stored float32 matrices are the scene's transforms.
        self.description = replace(description, transforms=None)
        self.instance_ids = description.instance_ids
        self.materials = description.materials
        # World-space cameras and lights, as given; kernels see them in rendering space.
        self.cameras = description.cameras
        self.lights = description.lights
        self.space = RenderingSpace.for_scene(description.cameras, description.transforms.to_world)
        models = description.models
        model_kind = [m.kind for m in models]
        used = np.unique(description.instance_model)
        # Kinds in a fixed order, only those some instance uses.
        kind_names = [k for k in list(ANALYTIC_MODELS) + [MESH_KIND, GRID_KIND, CURVE_KIND, BSPLINE_KIND]
                      if any(model_kind[i] == k for i in used)]
        mesh_models = [int(i) for i in used if model_kind[i] == MESH_KIND]
        meshes = (MeshLibrary([models[i].mesh for i in mesh_models],
                              [f"model {models[i].name!r} (file '{models[i].filename}')"
                               for i in mesh_models]) if mesh_models else None)
        grid_models = [int(i) for i in used if model_kind[i] == GRID_KIND]
        grids = SDFGridLibrary([models[i].grid for i in grid_models]) if grid_models else None
        curve_models = [int(i) for i in used if model_kind[i] == CURVE_KIND]
        curves = LinearCurveLibrary([models[i].curve for i in curve_models]) if curve_models else None
        bspline_models = [int(i) for i in used if model_kind[i] == BSPLINE_KIND]
        bsplines = (BSplineCurveLibrary([models[i].curve for i in bspline_models]) if bspline_models
                    else None)
        root_of_model = np.zeros(len(models), np.int64)
        for walked, library in ((mesh_models, meshes), (grid_models, grids), (curve_models, curves),
                                (bspline_models, bsplines)):
            for j, i in enumerate(walked):
                root_of_model[i] = library.root_refs[j]
        code_of_model = np.array([kind_names.index(k) if k in kind_names else -1
                                  for k in model_kind])
        self._mesh_models, self._meshes = mesh_models, meshes
        # The models of each kind that has a library of its own, in library order.
        self._library_models = {GRID_KIND: grid_models, CURVE_KIND: curve_models, BSPLINE_KIND: bspline_models}
        # Instances are stored in the scene's order. (Storing them in Morton order of
        # their centres for locality was measured: no gain at 100 000 instances, 2.0
        # Mrays/s either way, so the simpler layout stays.)
        model = description.instance_model
        # Moved into rendering space in float64, then rounded once by the table.
        to_world = self.space.matrices(description.transforms.to_world)
        from_world = self.space.inverses(description.transforms.from_world)
        self.instances = InstanceTable(
            to_world=to_world, from_world=from_world, kind_names=kind_names,
            kind_code=code_of_model[model], mesh_root=root_of_model[model], meshes=meshes, grids=grids,
            curves=curves, bsplines=bsplines, inward=np.array([m.inward for m in models], bool)[model])
        # World bounds of the stored (float32) transforms, which are what rays are traced
        # against: the input's float64 matrices can bound the traced surface short by a
        # rounding (a grazing hit was missed). Only the scene's box is kept.
        lo, hi = self._world_bounds(self.instances.to_world)
        self._build_accel(accel, lo, hi)
        # Materials: one flat table (materials.bsdf); a material index per instance only
        # when the instances use more than one.
        self.material_names = list(self.materials)
        _check_attribute_reads(description)
        self.bsdfs = BSDFTable([self.materials[m] for m in self.material_names],
                               None if meshes is None else meshes.attribute_corners, self.space.origin)
        # Surface coordinates are computed only where a material or emitter reads a texture,
        # the hit triangle and its barycentrics only where a material reads a mesh attribute.
        self.instances.surface_uv = self.bsdfs.textures is not None or any(
            emitter.texture is not None for emitter in description.emitters.values())
        self.instances.surface_attributes = (self.bsdfs.textures is not None
                                             and self.bsdfs.textures.has_attributes)
        # Shading tangents (from dp/du) only where a material is anisotropic or normal-mapped.
        self.instances.surface_tangents = (self.bsdfs.anisotropic or self.bsdfs.normal_mapped
                                           or self.bsdfs.bump_mapped)
        # The derivatives dp/du and dp/dv with their lengths only where a material is bump-mapped.
        self.instances.surface_derivatives = self.bsdfs.bump_mapped
        # Participating media: a table only where an instance or a camera names one.
        self.media = _media_table(description, self.space.origin)
        material = description.instance_material_index
        # instance_material: the one material index (int), or one per instance (UInt32).
        if len(material) == 0 or (material == material[0]).all():
            self.instance_material = int(material[0]) if len(material) else 0
        else:
            self.instance_material = device_array(UInt32, np.asarray(material, np.uint32))
        # The instances whose transforms carry derivatives (set by set_transforms), and the
        # point and directional lights whose values do (indices into lights).
        self.moving_instances = np.zeros(0, np.int64)
        self.moving_lights = np.zeros(0, np.int64)
        self._light_set: LightSet | None = None

    @property
    def to_world(self) -> np.ndarray:
        """(N, 4, 4) float64 world_from_object matrices: the stored float32 values, exactly,
        moved back from rendering space (:attr:`origin` added in float64)."""
        return self.space.world_matrices(self.instances.to_world)

    @property
    def from_world(self) -> np.ndarray:
        """(N, 4, 4) float64 object_from_world matrices from the stored float32 inverses."""
        return self.space.world_inverses(self.instances.from_world)

    def to_world_of(self, instances: Any) -> np.ndarray:
        """float64 world_from_object matrices of ``instances`` (an index, slice or index
        array; counted from the end where negative, as NumPy does)."""
        if not isinstance(instances, slice):
            instances = indices("instances", instances, len(self.instance_ids), "to_world_of", negative=True)
        return self.space.world_matrices(self.instances.to_world_of(instances))

    @property
    def origin(self) -> np.ndarray:
        """The world point at the origin of the rendering space (float64 (3,); see
        :mod:`instancing.scene.rendering_space`): the first camera's position (or the
        instances' centre), or 0 for a scene near the world origin."""
        return self.space.origin.copy()

    def view(self, which: int | str = 0) -> Camera:
        """Camera ``which`` (an index or id) in rendering space, as kernels trace it."""
        return self.space.camera(self.cameras[self.camera_index(which)])

    @property
    def rendering_lights(self) -> tuple[Light, ...]:
        """:attr:`lights` in rendering space (point and spot lights moved), as kernels see them."""
        return tuple(self.space.light(light) for light in self.lights)

    @property
    def camera(self) -> Camera | None:
        """The first camera (the one renders use by default), or None."""
        return self.cameras[0] if self.cameras else None

    def camera_index(self, which: int | str) -> int:
        """The index into :attr:`cameras` of camera ``which`` (an index or an id)."""
        ids = [camera.id for camera in self.cameras]
        if isinstance(which, str) and which and which in ids:
            return ids.index(which)
        if (isinstance(which, (int, np.integer)) and not isinstance(which, bool)
                and 0 <= which < len(self.cameras)):
            return int(which)
        named = f"; ids {[i for i in ids if i]}" if any(ids) else ""
        raise SceneError(f"camera {which!r}: no such camera; the scene has "
                         f"{len(self.cameras)} (indices 0 to {len(self.cameras) - 1}{named})"
                         if self.cameras else f"camera {which!r}: the scene has no camera")

    def camera_name(self, k: int) -> str:
        """Camera ``k``'s id, or its index where it has none (for file names and messages)."""
        return self.cameras[k].id or str(k)

    def set_camera(self, camera: Camera | None, which: int | str = 0) -> None:
        """Render from another camera: it replaces camera ``which`` (an index or id; it
        keeps that camera's id if it has none; a scene without cameras gets it as its only
        one). ``None`` removes every camera.
        :func:`instancing.io.scene_file.parse_camera` makes one from a scene file's dict."""
        if camera is None:
            self.cameras = ()
            return
        if not isinstance(camera, Camera):
            raise SceneError(f"set_camera: expected a Camera (see instancing.parse_camera), "
                             f"got {type(camera).__name__}")
        if camera.medium and camera.medium not in self.description.media:
            raise SceneError(f"set_camera: the camera's medium {camera.medium!r} is none of the scene's "
                             f"media {sorted(self.description.media)}")
        if not self.cameras and which == 0:
            self.cameras = (camera,)
            return
        k = self.camera_index(which)
        if not camera.id:  # (it keeps the name it replaces)
            camera = replace(camera, id=self.cameras[k].id)
        if camera.id and camera.id in [c.id for j, c in enumerate(self.cameras) if j != k]:
            raise SceneError(f"set_camera: camera id {camera.id!r} is another camera's already")
        self.cameras = self.cameras[:k] + (camera,) + self.cameras[k + 1:]

    def set_light(self, index: int, light: Light) -> None:
        """Replace light ``index`` of :attr:`lights` by a record of the same kind and id
        (moved, turned or re-coloured)."""
        old = self.lights[integer("index", index, 0, len(self.lights) - 1, "set_light", IndexError)]
        if type(light) is not type(old) or getattr(light, "id", None) != getattr(old, "id", None):
            raise SceneError(f"set_light: light {index} is a {type(old).__name__} "
                             f"{getattr(old, 'id', '')!r}, got {light!r}")
        self.lights = self.lights[:index] + (light,) + self.lights[index + 1:]
        self._light_set = None

    def set_emitter(self, instance: int, emitter: AreaEmitter) -> None:
        """Replace the area emitter of ``instance`` (which has one) by ``emitter``
        (re-coloured)."""
        if instance not in self.description.emitters:
            raise SceneError(f"set_emitter: instance {instance} has no area emitter")
        self.description.emitters[instance] = emitter
        self._light_set = None

    def set_moving_lights(self, lights: np.ndarray) -> None:
        """Mark the point and directional lights (indices into :attr:`lights`) whose values
        carry derivatives from now on: every instance's shadow moves with them."""
        self.moving_lights = indices("lights", lights, len(self.lights), "set_moving_lights", unique=True)

    @property
    def reflectance(self) -> Array3f:
        """The diffuse materials' reflectances (one lane per material, in ``material_names``
        order; 0 for other types), as the material table holds them."""
        return self.bsdfs.reflectance

    def set_reflectance(self, reflectance: Array3f) -> None:
        """Replace the diffuse materials' reflectances (one lane per material, in
        ``material_names`` order), e.g. with grad-enabled values."""
        if dr.width(reflectance) != len(self.material_names):
            raise SceneError(f"set_reflectance: expected {len(self.material_names)} lanes, "
                             f"got {dr.width(reflectance)}")
        self.bsdfs.set_value("reflectance", reflectance)

    def set_material_constants(self, material: str, changes: dict, part: int | None = None) -> None:
        """Give material ``material`` (or its ``part``-th part, a blend's or mask's BSDF) new
        constant parameter values (already validated, e.g. by :func:`instancing.traverse`):
        the table's columns and the scene's material record (which exports read) follow."""
        self.materials[material] = self.bsdfs.set_constants(self.material_names.index(material),
                                                            changes, part)

    def light_set(self) -> LightSet:
        """The lights as Dr.Jit arrays, built on first use and kept until the transforms change.

        Kept because rebuilding them for every render wrapped fresh NumPy buffers whose
        alignment hints changed the render kernel's hash: measured, a recompilation of
        ~0.7 s on every render of a scene with an area light.
        """
        if self._light_set is None:
            self._light_set = LightSet(self)
        return self._light_set

    @property
    def kind_names(self) -> list[str]:
        """Model kinds present in the scene (only these are traced)."""
        return list(self.instances.kind_names)

    @property
    def differentiable(self) -> bool:
        """True when instance transforms, material parameters or light values (of delta
        lights, area emitters and the environment) carry derivatives (and AD is not
        suspended)."""
        return bool(dr.grad_enabled(self.instances.inverse_rows) or self.bsdfs.differentiable
                    or (self._light_set is not None and self._light_set.differentiable))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box (lo, hi) of all instances, float64 (after instances moved by
        ``set_transforms(..., changed=...)`` it may be larger than the tight box)."""
        return self.space.world_points(self._bounds[0]), self.space.world_points(self._bounds[1])

    @property
    def bounding_sphere(self) -> tuple[list[float], float]:
        """Rendering-space centre and radius of the sphere around :attr:`bounds`, as Mitsuba's
        scene bounding sphere (its radius grown by 1e-4 relative, at least 1e-4; around the
        world origin where the scene has no instances): where it puts lights at infinity."""
        if not len(self.instance_ids):
            return [float(c) for c in -np.asarray(self.space.origin, np.float64)], _SPHERE_EPSILON
        lo, hi = self._bounds
        radius = 0.5 * float(np.linalg.norm(np.asarray(hi, np.float64) - lo))
        return [float(c) for c in 0.5 * (np.asarray(lo, np.float64) + hi)], max(_SPHERE_EPSILON,
                                                                               radius * (1 + _SPHERE_EPSILON))

    def instance_bounds(self, instances: Any) -> tuple[np.ndarray, np.ndarray]:
        """Rendering-space boxes (lo, hi), each (K, 3) float64, of ``instances`` (K indices)
        under their stored transforms."""
        instances = indices("instances", instances, len(self.instance_ids), "instance_bounds")
        return self._world_bounds(self.instances.to_world_of(instances), instances)

    def _world_bounds(self, to_world: np.ndarray,
                      instances: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Boxes (K, 3) under ``to_world`` (K, 4, 4; the stored, rendering-space matrices
        wherever the scene calls it) of ``instances`` (default: all, in the user's order):
        exact for quadrics, transformed object box for meshes, grids and curves."""
        desc, mesh_models, meshes = self.description, self._mesh_models, self._meshes
        model = desc.instance_model if instances is None else desc.instance_model[instances]
        n = len(to_world)
        lo, hi = np.empty((n, 3)), np.empty((n, 3))
        for i, spec in enumerate(desc.models):
            # (Every instance of one model: the whole arrays, not a mask's copies.)
            sel = model == i if len(desc.models) > 1 else slice(None)
            if len(desc.models) > 1 and not sel.any():
                continue
            if spec.kind == MESH_KIND:
                obj_lo, obj_hi = meshes.object_bounds[mesh_models.index(i)]
                lo[sel], hi[sel] = transformed_box_bounds(to_world[sel], obj_lo, obj_hi)
            elif spec.kind in self._library_models:
                library = self.instances.libraries[spec.kind]
                obj_lo, obj_hi = library.object_bounds[self._library_models[spec.kind].index(i)]
                lo[sel], hi[sel] = transformed_box_bounds(to_world[sel], obj_lo, obj_hi)
            else:
                lo[sel], hi[sel] = ANALYTIC_MODELS[spec.kind].world_bounds(to_world[sel])
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            bad = int(np.argmax(~(np.isfinite(lo).all(1) & np.isfinite(hi).all(1))))
            bad = bad if instances is None else int(instances[bad])
            raise SceneError(f"instance {self.instance_ids[bad]!r}: world bounds overflow "
                             "(transform too large for the model)")
        return lo, hi

    def set_mesh_attribute(self, model: int, name: str, values: np.ndarray) -> None:
        """Give mesh model ``model`` new values of its attribute ``name`` ((N, dim), the
        shape it has, finite), which the materials reading it see from now on."""
        spec = self.description.models[model]
        old = (spec.mesh.attributes or {}).get(name) if spec.mesh is not None else None
        if old is None or self.bsdfs.textures is None or name not in self.bsdfs.textures.attribute_names:
            raise SceneError(f"set_mesh_attribute: model {spec.name!r} has no attribute {name!r} "
                             "that a material reads")
        values = np.asarray(values, np.float32)
        if values.shape != np.shape(old):
            raise SceneError(f"set_mesh_attribute: {spec.name!r}.{name} takes values of shape "
                             f"{np.shape(old)}, got shape {values.shape}")
        if not np.isfinite(values).all():
            raise SceneError(f"set_mesh_attribute: {spec.name!r}.{name} takes finite values, got "
                             f"{int((~np.isfinite(values)).sum())} non-finite")
        mesh = self._meshes.set_attribute(self.mesh_index(model), name, values)
        self.description.models[model].mesh = mesh
        self.bsdfs.textures.set_attributes(self._meshes.attribute_corners)

    @property
    def curveless_model_names(self) -> list[str]:
        """The names of the models some instance uses whose discontinuity curves are not
        known (SDF grids and curves): no boundary term samples them."""
        return [self.description.models[i].name for models in self._library_models.values() for i in models]

    def mesh_index(self, model: int) -> int:
        """The index in the scene's mesh library (``instances.meshes``) of mesh model ``model``."""
        return self._mesh_models.index(model)

    def discontinuity_curves(self, viewpoint: np.ndarray, instances: np.ndarray,
                             creases: bool = True) -> Curves:
        """Object-space discontinuity curves of ``instances`` (K indices) seen from
        ``viewpoint``, float64: a world point (3,), or a homogeneous one (4,) (w = 0: a
        viewer at infinity in that direction, as a directional light). Each instance's
        model's curves seen from ``M^-1 viewpoint`` (:mod:`instancing.models.curves`),
        from its stored transform; without ``creases``, only the curves that cast shadows
        (no edges between two faces on one side of the viewpoint). A mesh's creases carry
        their jump scales (:meth:`~instancing.models.curves.EdgeTopology.scaled_discontinuity_curves`)
        where its material is a plain diffuse one, every other curve 1."""
        desc = self.description
        homogeneous = np.append(viewpoint, 1.0) if len(viewpoint) == 3 else np.asarray(viewpoint)
        # The normals' turn bounds a crease's jump on plain diffuse surfaces alone (a glossy
        # highlight or a texture seam may jump far more there).
        plain = np.array([self.materials[name].plain_diffuse for name in self.material_names], bool)
        plain_instance = plain[np.asarray(desc.instance_material_index)]
        parts: list[tuple] = []
        for model_index, model in enumerate(desc.models):
            rows = instances[desc.instance_model[instances] == model_index]
            if not len(rows):
                continue
            from_world = self.instances.from_world_of(rows)
            local = np.einsum("mij,j->mi", from_world, homogeneous)
            source = (self._meshes.edges(self.mesh_index(model_index))
                      if model.kind == MESH_KIND else ANALYTIC_MODELS[model.kind])
            if model.kind == MESH_KIND:
                (which, circle, c, u, v), scale = source.scaled_discontinuity_curves(local, creases)
                scale = np.where(plain_instance[rows[which]], scale, 1.0)
            else:
                which, circle, c, u, v = source.discontinuity_curves(local, creases)
                scale = np.ones(len(which))
            parts.append((rows[which], circle, c, u, v, scale))
        if not parts:
            empty = np.zeros((0, 3))
            return Curves(np.zeros(0, np.int64), np.zeros(0, bool), empty, empty, empty)
        return Curves(*[np.concatenate(p) for p in zip(*parts)])

    def _build_accel(self, accel: Accel, lo: np.ndarray, hi: np.ndarray) -> None:
        """Build the top-level structure over the world boxes ``lo``, ``hi`` (N, 3); 'auto'
        unrolls small scenes and otherwise prefers the grid unless it is clustered or mostly
        meshes with at most MESH_BVH_MAX_INSTANCES instances (on CUDA: the BVH, see AUTO_BVH). The
        boxes are not kept (only their union), except by 'unrolled', which tests them."""
        if accel not in ("auto", "grid", "bvh", "unrolled", "brute"):
            raise SceneError(f"unknown acceleration structure {accel!r}; "
                             "expected auto, grid, bvh, unrolled or brute")
        self.revision += 1
        # (A scene without instances: a box at the origin, which nothing uses.)
        self._bounds = (lo.min(axis=0), hi.max(axis=0)) if len(lo) else (np.zeros(3), np.zeros(3))
        self.grid = self.bvh = self._bvh_items = self._instance_boxes = None
        self._requested_accel = self.accel = accel
        if accel == "unrolled" and len(lo) > UNROLL_LIMIT:
            raise SceneError(f"'unrolled' tests at most {UNROLL_LIMIT} instances (its kernel grows "
                             f"with their number); this scene has {len(lo)}: use auto, grid or bvh")
        if accel == "auto" and (AUTO_BVH or UNROLL_MAX_INSTANCES < len(lo) <= MESH_BVH_MAX_INSTANCES
                                and self._mostly_meshes()):
            accel = "bvh"
        # A scene without instances has nothing to structure: every choice tests its zero boxes.
        if accel == "unrolled" or not len(lo) or (accel == "auto" and len(lo) <= UNROLL_MAX_INSTANCES):
            lo32, hi32 = outward32(lo, hi)
            self._instance_boxes = WorldBoxes(range(len(lo)), lo32, hi32, self.instances)
            self.accel = "unrolled"
            return
        if accel in ("auto", "grid"):
            arrays = build_grid(lo, hi)
            if arrays is not None and accel == "auto":
                counts = arrays.cell_count.astype(np.float64)
                if (counts ** 2).sum() > GRID_MAX_OCCUPANCY * counts.sum():
                    arrays = None
            if arrays is None and accel == "grid":
                raise SceneError("the instances' bounds need too many grid references; use the BVH")
            if arrays is not None:
                self.grid = GridKernel(arrays)
                self.accel = "grid"
        if self.grid is None and accel not in ("brute", "unrolled"):
            arrays = build_bvh(lo, hi, INSTANCE_LEAF_SIZE)
            # Where most instances are meshes, an instance's test is a walk of its own: the
            # lanes that reach instances test them together, after the steps (nested loops).
            self.bvh = BVHKernel(arrays, nested=self._mostly_meshes())
            self._bvh_items = device_array(UInt32, arrays.order.astype(np.uint32))
            self.accel = "bvh"

    def _mostly_meshes(self) -> bool:
        """Whether at least half of the instances are meshes."""
        table = self.instances
        if MESH_KIND not in table.kind_names:
            return False
        codes = table.host_codes[0]
        mesh = table.kind_names.index(MESH_KIND)
        return codes is None or 2 * int((codes == mesh).sum()) >= len(codes)

    # -- queries ----------------------------------------------------------------------------

    def intersect_preliminary(self, o: Array3f, d: Array3f, active: Bool | bool = True,
                              t_max: Float | float = dr.inf, any_hit: bool = False) -> PreliminaryHit:
        """Phase 1 only on rays in rendering space: (t, stored instance, leaf-order
        primitive), detached from AD (with ``any_hit``: the first hit found, see
        :func:`intersect_preliminary`)."""
        if self.accel == "grid":
            traverse, items = self.grid.traverse, self.grid.items
        elif self.accel == "bvh":
            traverse, items = self.bvh.traverse, self._bvh_items
        else:
            traverse, items = None, None
        return intersect_preliminary(self.instances, traverse, items, o, d, active, t_max, any_hit,
                                     unrolled=self._instance_boxes)

    def intersect_surface(self, o: Array3f, d: Array3f, active: Bool | bool = True,
                          t_max: Float | float = dr.inf, uv: bool | None = None) -> SurfaceHit:
        """Both phases on Dr.Jit rays in rendering space (see :attr:`origin`): the
        differentiable surface record of hits in (0, t_max) (with surface coordinates where
        ``uv``; by default where materials read textures)."""
        return reintersect(self.instances, o, d, self.intersect_preliminary(o, d, active, t_max), uv)

    def occluded(self, o: Array3f, d: Array3f, t_max: Float, active: Bool | bool = True) -> Bool:
        """Shadow test on a ray in rendering space: does anything lie on it at
        0 < t < t_max? (detached; stops at the first hit found)"""
        return self.intersect_preliminary(o, d, active, t_max, any_hit=True).valid

    def intersect(self, origins: Any, directions: Any) -> Hits | SurfaceHit:
        """Nearest hit of each ray ``o + t d`` with t > 0.

        Args:
            origins, directions: world rays, NumPy (N, 3) arrays or Dr.Jit ``Array3f``.
                Directions need not be unit length; t is in their units. Float64
                origins are moved into the rendering space (:attr:`origin`) before
                they are rounded to float32, and the hit points come back in float64:
                far from the world origin they keep the precision of the scene's
                own coordinates.

        Returns:
            :class:`Hits` of NumPy arrays for NumPy input, or a
            :class:`~instancing.scene.intersection.SurfaceHit` of Dr.Jit arrays
            (differentiable) for Dr.Jit input. Fields: ``t`` (inf on a miss),
            world ``p``, unit world geometric normal ``n``, ``instance``
            (-1 on a miss) and ``prim``.

        A batch of PASSES_MIN_RAYS rays or more walks the grid in passes
        (:func:`~instancing.scene.intersection.intersect_preliminary_in_passes`: the same
        hits, faster on incoherent rays), sorted by where the rays enter the grid in
        scenes of SORT_MIN_WALK_BYTES or more, evaluating between them unless called
        inside traced or recorded code. A Dr.Jit record is returned unevaluated (traced
        every call, so that what uses it joins its kernel). NumPy queries replay a
        recording of their kernels per batch width (:meth:`_evaluated_hits`): a query of a few
        rays costs about 0.2 - 0.3 ms instead of 0.6 - 1.5 ms.
        """
        jit = [a is not None and dr.is_jit_v(a) for a in (origins, directions)]
        if jit[0] != jit[1]:
            raise TypeError("intersect: origins and directions must be both Dr.Jit arrays or both NumPy "
                            f"arrays, got {type(origins).__name__} and {type(directions).__name__}")
        if jit[0]:
            o, d = Array3f(origins), Array3f(directions)
            if min(dr.width(o), dr.width(d)) == 0 or 1 != min(dr.width(o), dr.width(d)) != max(
                    dr.width(o), dr.width(d)):
                raise ValueError(f"intersect: origins and directions must hold the same number of rays "
                                 f"(or one of them one), got {dr.width(o)} and {dr.width(d)}")
            # Float32 world rays: moved into rendering space and back in float32.
            shift = Array3f(*[float(c) for c in self.space.origin]) if self.space.moved else None
            local = o if shift is None else o - shift
            hit = reintersect(self.instances, local, d, self._batch_preliminary(local, d))
            return hit if shift is None else replace(hit, p=hit.p + shift)
        origins, directions = _ray_arrays(origins, directions)
        wide = origins.dtype == np.float64
        if len(origins) == 0:
            # No rays, no hits (Dr.Jit arrays of width 0 cannot be traced).
            return Hits(t=np.zeros(0, np.float32), p=np.zeros((0, 3), origins.dtype),
                        n=np.zeros((0, 3), np.float32), instance=np.zeros(0, np.int64),
                        prim=np.zeros(0, np.int64))
        # Origins of either precision are moved into rendering space in float64, then
        # rounded to float32.
        o = self.space.points(origins) if self.space.moved else origins
        # In Dr.Jit's own storage (one copy kernel): a kernel reading NumPy buffers is made
        # for their alignment, so wrapped buffers would record a query anew per alignment.
        with np.errstate(over="ignore", under="ignore"):
            o32, d32 = np.asarray(o, np.float32), np.asarray(directions, np.float32)
        if np.float64 in (origins.dtype, directions.dtype):
            _check_rays(o32, d32, origins, directions, " in float32, as they are traced (the origins "
                        "relative to the scene's origin, scene.origin)")
        columns = device_arrays(Float, *o32.T, *d32.T)
        t, p, n, instance, prim = self._evaluated_hits(Array3f(*columns[:3]), Array3f(*columns[3:]))
        # Hit points: rendering space plus the origin, in float64 for float64 rays.
        p = rows_from_vectors(p)
        if self.space.moved or wide:
            p = self.space.world_points(p)
        return Hits(t=host_array(t, np.float32), p=p if wide else p.astype(np.float32),
                    n=rows_from_vectors(n), instance=host_array(instance, np.int64),
                    prim=host_array(prim, np.int64))

    def _evaluated_hits(self, o: Array3f, d: Array3f) -> tuple:
        """The evaluated (t, p, n, instance, prim) of rays in rendering space, replayed from
        a recording per batch width (:mod:`instancing.core.kernel_recording`) where the batch
        runs in one traced pass: tracing both phases costs 0.4 - 1.2 ms per call, more than
        the kernels of a few thousand rays. A width is recorded at its second query (a
        recording costs 1.5 - 6x a traced query, which queries of ever new widths would pay
        every call). Batches that walk the grid in passes (which evaluate between them) and
        transforms with derivatives are traced every call."""
        table = self.instances
        if (dr.grad_enabled(table.inverse_rows, table.forward_linear)
                or (self.accel == "grid" and dr.width(o) >= PASSES_MIN_RAYS)):
            return _hit_fields(self, o, d)
        return call_recorded(recordings_of(self, "intersect"), dr.width(o), _hit_fields, (self, o, d),
                             _intersect_state, record_at=2)

    def _batch_preliminary(self, o: Array3f, d: Array3f) -> PreliminaryHit:
        """Phase 1 for a batch of rays that may be evaluated now: through the grid in passes
        (:func:`~instancing.scene.intersection.intersect_preliminary_in_passes`) for large
        batches, where that pays; else in one traced loop, as inside traced or recorded
        code (symbolic loops, ``dr.freeze``), where nothing may be evaluated."""
        if (self.accel == "grid" and dr.width(o) >= PASSES_MIN_RAYS
                and not dr.flag(dr.JitFlag.SymbolicScope) and not dr.flag(dr.JitFlag.FreezingScope)):
            return intersect_preliminary_in_passes(
                self.instances, self.grid, o, d,
                sort_rays=self._walk_bytes() >= SORT_MIN_WALK_BYTES)
        return self.intersect_preliminary(o, d)

    def _walk_bytes(self) -> int:
        """Bytes of the arrays that a grid walk reads at places the rays decide: the grid's
        cell table and references and the instances' rows for phase 1."""
        return 4 * (dr.width(self.grid.cell_start) + dr.width(self.grid.items)
                    + dr.width(self.instances.inverse_rows))

    def material_of(self, hit: SurfaceHit) -> UInt32:
        """The material (index into ``material_names``) at each hit (0 on a miss)."""
        if isinstance(self.instance_material, int):
            return dr.opaque(UInt32, self.instance_material)
        return dr.gather(UInt32, self.instance_material, UInt32(dr.maximum(hit.instance, 0)))

    def lookup_point(self, hit: SurfaceHit) -> Coordinates:
        """Where the materials' textures are looked up at each hit: its surface coordinates,
        with its triangle, barycentrics and point where a material reads mesh attributes or
        volumes."""
        textures = self.bsdfs.textures
        if textures is not None and (textures.has_attributes or textures.has_volumes):
            return LookupPoint(hit.uv, hit.triangle, hit.prim_uv, hit.p)
        return hit.uv

    def albedo(self, hit: SurfaceHit) -> Array3f:
        """The albedo of the material at each hit (Mitsuba's ``albedo`` AOV: a diffuse
        reflectance, a metal's specular reflectance; 0 on a miss)."""
        return dr.select(hit.valid, self.bsdfs.albedo(self.material_of(hit), self.lookup_point(hit)), 0.0)

    def set_transforms(self, world_from_object: Transform, matrices: np.ndarray | None = None,
                       moving: np.ndarray | None = None, changed: np.ndarray | None = None) -> None:
        """Move every instance: a per-lane transform with one lane per instance.

        Args:
            world_from_object: per-lane transform (``Matrix4f`` of width N, or
                width 1 for all; with ``changed``, one lane per changed instance).
                Its inverse is used as stored (built from its parts, so gradients
                reach their parameters).
            matrices: the same transforms as (N, 4, 4) float64, when the caller
                has them (saves a round trip and keeps float64 precision for
                the bounds); otherwise read back from the lanes. With ``changed``:
                only those instances' matrices, (K, 4, 4).
            moving: indices of the instances whose transforms carry derivatives
                (the boundary term samples only their edges); default: all
                instances when the transform is grad-enabled, else none.
            changed: indices of the only instances whose transforms differ from the
                stored ones (the caller vouches for the others); default: all. Then
                only their rows are written, their matrices checked, their remap
                bounds and world boxes computed, and a grid updated in place (their
                references moved) or a BVH refitted (its boxes above them recomputed,
                see :func:`~instancing.accel.bvh.refit_bvh`) instead of built anew: an
                optimisation step that moves 8 of 1e6 instances costs O(grid references)
                or O(BVH nodes) NumPy work, not a full build.

        World bounds and the acceleration structure are rebuilt from the
        detached matrices. The instances store the transforms in float32;
        :attr:`to_world` reads those back.

        Raises:
            TypeError: ``world_from_object`` is not a :class:`~instancing.Transform`.
        """
        if not isinstance(world_from_object, Transform):
            raise TypeError(
                f"set_transforms: world_from_object must be an instancing.Transform (per lane, "
                f"or one for all), got {type(world_from_object).__name__}; for (N, 4, 4) NumPy "
                "matrices m pass from_matrix(matrices_to_lanes(m)) "
                "(instancing.core.transform) and matrices=m")
        lanes = world_from_object.to_lanes()
        n = len(self.instance_ids)
        width = dr.width(lanes.matrix)
        if moving is not None:
            moving = indices("moving", moving, n, "set_transforms", unique=True)
        if changed is not None:
            if matrices is None:
                raise ValueError("set_transforms: 'changed' needs the changed instances' matrices")
            changed = indices("changed", changed, n, "set_transforms", unique=True).reshape(-1)
            _check_lanes(width, matrices, len(changed), "changed instances")
            if np.shape(matrices) == (4, 4) and len(changed) != 1:
                matrices = np.broadcast_to(matrices, (len(changed), 4, 4))
            fwd = np.asarray(matrices, np.float64).reshape(len(changed), 4, 4)
            check_affine_matrix(fwd, "set_transforms: to_world")
            fwd = self.space.matrices(fwd)
            lanes = self._rendering_lanes(lanes, fwd)
            if len(changed):
                self.instances.set_transforms(lanes, changed)
            if len(changed) > n // 4:
                # Most instances move: a full build, which the in-place update would
                # only repeat with extra bookkeeping.
                full = self.instances.to_world
                full[changed] = fwd  # the changed instances' float64 state
                changed, fwd = None, full
        else:
            _check_lanes(width, matrices, n, "instances")
            fwd = np.broadcast_to(np.asarray(lanes.to_numpy()[0] if matrices is None else matrices,
                                             np.float64), (n, 4, 4))
            check_affine_matrix(fwd, "set_transforms: to_world")
            fwd = self.space.matrices(fwd)
            lanes = self._rendering_lanes(lanes, fwd)
            self.instances.set_transforms(lanes)
        self.instances.wide_scales |= wide_scales(fwd)
        if moving is None:
            moving = np.arange(n) if dr.grad_enabled(lanes.matrix) else np.zeros(0, np.int64)
        self.moving_instances = np.asarray(moving, np.int64)
        self._light_set = None  # area emitters may have moved
        if changed is None:
            self._build_accel(self._requested_accel, *self._world_bounds(fwd))
            return
        if len(changed) and self.accel not in ("grid", "bvh"):
            self._build_accel(self._requested_accel, *self._world_bounds(self.instances.to_world))
            return
        if len(changed):
            lo, hi = self._world_bounds(fwd, changed)
            if self.accel == "grid":
                arrays = update_grid(self.grid.arrays(), changed, lo, hi)
                self.grid = None if arrays is None else GridKernel(arrays)
                rebuilt = self.grid is None
            else:
                # The BVH keeps its shape; its boxes are refitted from the stored transforms
                # (as a full build of it would read them).
                tree = refit_bvh(self.bvh, np.asarray(self._bvh_items).astype(np.int64), changed,
                                 lambda items: self._world_bounds(self.instances.to_world_of(items),
                                                                  items))
                self.bvh = tree
                rebuilt = tree is None
            if rebuilt:
                # A moved box left the grid's box, or the refitted BVH lost too much of its
                # quality: build anew over the stored transforms.
                self._build_accel(self._requested_accel, *self._world_bounds(self.instances.to_world))
                return
            # The scene's box grows with the moved boxes (it does not shrink until a full build).
            self._bounds = (np.minimum(self._bounds[0], lo.min(axis=0)),
                            np.maximum(self._bounds[1], hi.max(axis=0)))
        self.revision += 1

    def _rendering_lanes(self, lanes: Transform, matrices: np.ndarray) -> Transform:
        """World ``lanes`` in rendering space: translations from ``matrices`` (rendering
        space, float64, one per lane), carrying the lanes' derivatives; the inverse's
        translation -A^-1 b recomputed from them."""
        if not self.space.moved:
            return lanes
        m, inv = lanes.matrix, lanes.inverse_matrix
        rows = [[m[r][c] for c in range(4)] for r in range(4)]
        inverse_rows = [[inv[r][c] for c in range(4)] for r in range(4)]
        b = []
        for r in range(3):
            value = device_array(Float, np.ascontiguousarray(matrices[:, r, 3], np.float32))
            b.append(value + (m[r][3] - dr.detach(m[r][3])))
            rows[r][3] = b[r]
        for r in range(3):
            inverse_rows[r][3] = -dr.fma(inv[r][2], b[2], dr.fma(inv[r][1], b[1], inv[r][0] * b[0]))
        return Transform(type(m)(rows), type(m)(inverse_rows))

    def set_moving(self, moving: np.ndarray) -> None:
        """Mark the instances whose transforms carry derivatives from now on (the boundary
        term samples their edges); the stored transforms stay, detached."""
        self.instances.detach()
        self.moving_instances = indices("moving", moving, len(self.instance_ids), "set_moving", unique=True)
        self.revision += 1

    def set_accel(self, accel: Accel) -> None:
        """Rebuild the top-level structure with another choice (for comparisons), over the
        world boxes of the stored transforms."""
        self._build_accel(accel, *self._world_bounds(self.instances.to_world))


def require_scene(scene: Any, caller: str) -> None:
    """Refuse anything but a built :class:`Scene` given to ``caller`` (a scene dict or file
    goes through :func:`~instancing.load_scene` first).

    Raises:
        TypeError: naming the caller, the type given and what to do.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"{caller}: scene must be a Scene, got {type(scene).__name__}; call "
                        "instancing.load_scene(...) on a scene dict or file first")


def _media_table(description: SceneDescription, origin: np.ndarray) -> MediaTable | None:
    """The media that the instances and cameras name, with each instance's interior and
    exterior medium (None when none is named)."""
    used = {name for pair in description.instance_media.values() for name in pair if name}
    used |= {camera.medium for camera in description.cameras if camera.medium}
    if not used:
        return None
    names = [name for name in description.media if name in used]
    index = {name: k for k, name in enumerate(names, 1)}
    count = len(description.instance_model)
    interior, exterior = np.zeros(count, np.uint32), np.zeros(count, np.uint32)
    for instance, (inside, outside) in description.instance_media.items():
        interior[instance], exterior[instance] = index.get(inside, 0), index.get(outside, 0)
    return MediaTable([description.media[name] for name in names], interior, exterior, origin,
                      [index[camera.medium] for camera in description.cameras if camera.medium])


def _ray_arrays(origins: Any, directions: Any) -> tuple[np.ndarray, np.ndarray]:
    """The rays as (N, 3) float arrays (float64 kept, anything else as float32), checked."""
    o, d = (np.asarray(a) for a in (origins, directions))
    if o.dtype.kind not in "fiu" or d.dtype.kind not in "fiu":
        raise ValueError(f"origins and directions must be arrays of numbers, got {o.dtype} and {d.dtype}")
    o, d = (a if a.dtype == np.float64 else a.astype(np.float32, copy=False) for a in (o, d))
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins and directions must both be (N, 3) arrays, got "
                         f"{o.shape} and {d.shape}")
    _check_rays(o, d, o, d)
    return o, d


def _check_rays(o: np.ndarray, d: np.ndarray, origins: np.ndarray, directions: np.ndarray,
                traced: str = "") -> None:
    """Refuse a NaN, infinite or zero ray (``o``, ``d`` as given, or ``traced`` as rounded to
    float32 in rendering space), which has no nearest hit, naming the first one by the
    caller's ``origins`` and ``directions``: rather than return it as a miss. Tested on the
    whole arrays and per column first (reductions along rows of three are slow), row by row
    only to name the culprit."""
    if not (np.isfinite(o).all() and np.isfinite(d).all()
            and ((d[:, 0] != 0) | (d[:, 1] != 0) | (d[:, 2] != 0)).all()):
        bad = ~(np.isfinite(o).all(axis=1) & np.isfinite(d).all(axis=1)) | ~(d != 0).any(axis=1)
        i = int(np.argmax(bad))
        raise ValueError(f"ray {i} (of {len(o)}, {int(bad.sum())} bad) has origin {origins[i].tolist()} "
                         f"and direction {directions[i].tolist()}: origins must be finite and "
                         f"directions finite and nonzero{traced}")


def _check_lanes(width: int, matrices: Any, count: int, what: str) -> None:
    """set_transforms' transform lanes (one for all, or one per instance it sets) and
    matrices (none, (count, 4, 4), or one (4, 4) with one lane) against the ``count``
    instances it sets."""
    if width not in (1, count):
        raise ValueError(f"set_transforms: world_from_object has {width} lanes for {count} {what} "
                         "(expected one per instance, or one for all)")
    if matrices is not None:
        shape = np.shape(matrices)
        if shape not in ((count, 4, 4), (4, 4)) or (shape == (4, 4) and width != 1):
            raise ValueError(f"set_transforms: matrices has shape {shape}, expected ({count}, 4, 4) "
                             f"for {count} {what}")


def _check_attribute_reads(description: SceneDescription) -> None:
    """Refuse a mesh attribute that an instance's material reads but its model cannot give:
    the model is no mesh or has no such attribute, the attribute has neither 1 nor 3 values
    (3 for a number parameter: Mitsuba would read 0), or a value is not finite."""
    names = list(description.materials)
    reads = {k: attribute_reads(description.materials[name]) for k, name in enumerate(names)}
    if not any(reads.values()):
        return
    pairs, first = np.unique(np.stack([np.asarray(description.instance_model, np.int64),
                                       np.asarray(description.instance_material_index, np.int64)],
                                      axis=1), axis=0, return_index=True)
    for (model_index, material_index), i in zip(pairs, first):
        model = description.models[model_index]
        for key, number, texture in reads[material_index]:
            where = (f"instance {description.instance_ids[int(i)]!r} (model {model.name!r}): material "
                     f"{names[material_index]!r} reads mesh attribute {texture.attribute!r} for {key!r}")
            values = None if model.mesh is None else (model.mesh.attributes or {}).get(texture.attribute)
            if values is None:
                has = [] if model.mesh is None else sorted(model.mesh.attributes or {})
                raise SceneError(f"{where}, which the model does not have"
                                 + (f" (it has {has})" if model.mesh is not None else
                                    " (an analytic model has no attributes)"))
            size = values.shape[-1]
            if size not in ((1,) if number else (1, 3)):
                raise SceneError(f"{where}: it holds {size} values per "
                                 f"{texture.attribute.split('_')[0]}; a "
                                 f"{'number' if number else 'colour'} reads "
                                 f"{'1' if number else '1 or 3'}")
            bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
            if bad.size:
                one, many = (("vertex", "vertices") if texture.attribute.startswith("vertex_")
                              else ("triangle", "triangles"))
                raise SceneError(f"{where}, which is not finite at {bad.size} {many} (the first: "
                                 f"{one} {bad[0]}, counting from 0)")


def _hit_fields(scene: Scene, o: Array3f, d: Array3f) -> tuple:
    """(t, p, n, instance, prim) of both phases on rays in rendering space, evaluated
    together."""
    hit = reintersect(scene.instances, o, d, scene._batch_preliminary(o, d))
    fields = hit.t, hit.p, hit.n, hit.instance, hit.prim
    dr.eval(fields)
    return fields


def _intersect_state(scene: Scene, o: Array3f, d: Array3f) -> list:
    """The Dr.Jit arrays that :func:`_hit_fields` reads (the instances with their models, and
    the structure over them), as extra inputs of its recording."""
    return jit_state(scene.instances, scene.grid, scene.bvh, scene._bvh_items, scene._instance_boxes)
