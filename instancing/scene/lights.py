"""Light sources, with the units and meaning of Mitsuba's plugins of the same names.

* ``point``: ``position``, ``intensity`` (W/sr): irradiance I cos / r^2.
* ``spot``: a point light whose intensity falls off with the angle to its axis (Mitsuba's
  profile: 1 within ``beam_width``, linear in the angle to 0 at ``cutoff_angle``), times a
  texture projected onto its cone where it has one.
* ``projector``: a point light projecting a texture through a pinhole's frustum
  (:class:`~instancing.scene.description.ProjectorLight`).
* ``directional``: ``direction`` (the direction the light travels), ``irradiance`` (W/m^2).
* ``constant``: ``radiance`` arriving from every direction, or ``envmap``: a
  latitude-longitude image of it (the environment, :mod:`instancing.scene.environment`).
* ``area`` emitters on instances (``"emitter": {"type": "area", "radiance": [r, g, b]}``):
  radiance leaving the front side (the side the model's normal points to), on any model
  under any affine transform; a bitmap or checkerboard radiance is looked up at the
  surface coordinates of the emitting point, as Mitsuba's.

Area emitters are sampled by area in object space and mapped by the instance's
transform; the world-area density follows from the local area scale of the affine map,
``|det A| / |A^T n_world|``, so non-uniform scale and shear are sampled exactly.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass

import numpy as np

from ..core.backend import (Array2f, Array3f, Array4f, Bool, Float, TensorXf, UInt32, device_array,
                            device_arrays, device_vectors, dr)
from ..core.box import outward32
from ..core.error_bounds import transformed_point_error
from ..core.transform import world_point
from ..core.warp import unit_sphere_cone_pdf, unit_sphere_cone_sample
from ..materials.texture import TextureSet
from ..models.analytic import ANALYTIC_MODELS
from .description import ENVIRONMENTS, PointLight, ProjectorLight, SpotLight
from .environment import Environment
from .instance_table import MESH_KIND
from .intersection import WorldBoxes

NO_EMITTER = 0xFFFFFFFF
#: The arrays of a light's texture set that parameters give: texels, checkerboard colours.
TEXTURE_ARRAYS = ("texels", "color0", "color1")
#: Area emitters that the ``direct`` integrator's BSDF rays test one by one before the
#: rest of the scene, at most (as many as the 'unrolled' structure tests).
EMITTERS_TESTED_FIRST = 12
#: Squared distance from a round sphere's centre (in radii) past which a point samples it
#: by its cone: points on the sphere itself (its own emission's shading) take it by area,
#: the same from the emitter sample and from the BSDF ray that finds it.
ROUND_OUTSIDE = 1.0 + 1e-3


def _frame_rows(light: SpotLight | ProjectorLight) -> tuple[Array3f, Array3f, Array3f]:
    """The rows of a spot's or projector's world-to-light rotation, as opaque values."""
    return tuple(dr.opaque(Array3f, row.tolist()) for row in np.reshape(light.light_from_world, (3, 3)))


def _texture_set(light: SpotLight | ProjectorLight) -> TextureSet | None:
    """A spot's or projector's texture as a one-texture set (None without one)."""
    return None if light.texture is None else TextureSet([light.texture])


def _to_light(rows: tuple[Array3f, Array3f, Array3f], d: Array3f) -> Array3f:
    """World direction ``d`` in a light's frame."""
    return Array3f(*(dr.dot(row, d) for row in rows))


@dataclass(frozen=True)
class SpotProfile:
    """A spot light's falloff as kernels read it: its world-to-light rows and angles (opaque),
    and its texture (a one-texture set) where it has one."""

    rows: tuple[Array3f, Array3f, Array3f]
    cos_cutoff: Float
    cos_beam: Float
    cutoff: Float
    inverse_transition: Float
    uv_scale: Float
    texture: TextureSet | None = None

    @staticmethod
    def of(light: SpotLight) -> "SpotProfile":
        cutoff, beam = np.radians(light.cutoff_angle), np.radians(light.beam_width)
        inverse = 1.0 / (cutoff - beam) if cutoff > beam else np.inf
        return SpotProfile(_frame_rows(light),
                           *(dr.opaque(Float, float(x)) for x in (np.cos(cutoff), np.cos(beam),
                                                                   cutoff, inverse,
                                                                   0.5 / np.tan(cutoff))),
                           _texture_set(light))

    def emission(self, d: Array3f) -> Array3f:
        """The intensity's factor towards world direction ``d`` (from the light): the
        falloff, times the texture at the direction's point of the cone's image (Mitsuba's
        ``direction_to_uv``) where the spot has one."""
        local = _to_light(self.rows, d)
        cos_theta = local.z / dr.norm(local)
        ramp = (self.cutoff - dr.acos(dr.clip(cos_theta, -1.0, 1.0))) * self.inverse_transition
        inside = cos_theta > self.cos_cutoff
        falloff = dr.select(inside, dr.select(cos_theta >= self.cos_beam, 1.0, ramp), 0.0)
        if self.texture is None:
            return Array3f(falloff)
        scale = self.uv_scale / local.z
        uv = Array2f(dr.fma(local.x, scale, 0.5), dr.fma(local.y, scale, 0.5))
        return falloff * self.texture.eval(UInt32(0), uv, inside)


@dataclass(frozen=True)
class ProjectorProfile:
    """A projector's frustum as kernels read it: its world-to-light rows, the film's
    half-extents (tan of half the field of view, along x and y) and its texture (a
    one-texture set, or None: constant)."""

    rows: tuple[Array3f, Array3f, Array3f]
    half_width: Float
    half_height: Float
    texture: TextureSet | None = None

    @staticmethod
    def of(light: ProjectorLight) -> "ProjectorProfile":
        half_width = np.tan(0.5 * np.radians(light.fov))
        return ProjectorProfile(_frame_rows(light), dr.opaque(Float, float(half_width)),
                                dr.opaque(Float, float(half_width / light.aspect)), _texture_set(light))

    def emission(self, d: Array3f) -> Array3f:
        """The intensity's factor towards world direction ``d`` (from the light): pi times
        the texture where ``d`` meets the film (Mitsuba's perspective projection: u from
        the left edge as the light looks, v from the top), over cos^3 of its angle to the
        axis (the inverse of a pinhole's importance, Mitsuba's), 0 outside the frustum."""
        local = _to_light(self.rows, d)
        u = 0.5 - 0.5 * local.x / (local.z * self.half_width)
        v = 0.5 - 0.5 * local.y / (local.z * self.half_height)
        inside = (local.z > 0) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
        cos_theta = local.z / dr.norm(local)
        value = Array3f(1.0) if self.texture is None else self.texture.eval(UInt32(0), Array2f(u, v), inside)
        return dr.select(inside, dr.pi * value / (cos_theta * cos_theta * cos_theta), 0.0)


@dataclass(frozen=True)
class DeltaLight:
    """A point or directional light as kernels read it (sampled deterministically, no
    MIS): ``vector`` is the position (point) or travel direction (directional),
    ``power`` the intensity (point) or irradiance (directional), opaque ``Array3f`` values;
    a spot light or projector is a point light with its ``profile`` (the intensity's factor
    per direction, :meth:`SpotProfile.emission`)."""

    kind: str
    vector: Array3f
    power: Array3f
    profile: SpotProfile | ProjectorProfile | None = None

    def irradiance_at(self, p: Array3f) -> Array3f:
        """A point light's irradiance at points ``p`` (on a surface facing it): its intensity
        towards them (times its profile) over the squared distance."""
        irradiance = self.power / dr.squared_norm(self.vector - p)
        if self.profile is not None:
            irradiance *= self.profile.emission(p - self.vector)
        return irradiance


class LightSet:
    """Dr.Jit-side lights of a scene: delta lights, environment, area emitters."""

    def __init__(self, scene):
        desc = scene.description
        lights = scene.rendering_lights
        environment = [light for light in lights if isinstance(light, ENVIRONMENTS)]
        #: The environment (constant or map), or None.
        self.environment = Environment(environment[0]) if environment else None
        area = {i: list(emitter.radiance) for i, emitter in desc.emitters.items()}
        # Textured radiance: the emitters' textures as one set, and per slot its index.
        textures = []
        for emitter in desc.emitters.values():
            if emitter.texture is not None and not any(emitter.texture is t for t in textures):
                textures.append(emitter.texture)
        #: The emitters' textures (None where no emitter is textured), and per textured
        #: emitter (instance index) its texture's index among them.
        self.emitter_textures = TextureSet(textures) if textures else None
        self.texture_index = {i: next(k for k, t in enumerate(textures) if t is emitter.texture)
                              for i, emitter in desc.emitters.items() if emitter.texture is not None}
        # The delta lights' vectors and powers enter kernels as opaque values, not literals:
        # a scene with a moved or recoloured light reuses the compiled kernels.
        self.delta = [DeltaLight("point", dr.opaque(Array3f, light.position),
                                 dr.opaque(Array3f, light.intensity), _profile(light))
                      if isinstance(light, PointLight)
                      else DeltaLight("directional", dr.opaque(Array3f, light.direction),
                                      dr.opaque(Array3f, light.irradiance))
                      for light in lights if not isinstance(light, ENVIRONMENTS)]
        # Where each scene light (index into scene.lights) sits among the delta lights.
        self.delta_slot = {i: j for j, i in enumerate(
            i for i, light in enumerate(lights) if not isinstance(light, ENVIRONMENTS))}
        self.area_instances = sorted(area)
        #: Whether emitter sampling takes round spheres by the cone they subtend (less noise
        #: than by area; :meth:`spheres_by_cone`): renders without derivatives (the boundary
        #: terms hold the sampled points fixed on the emitters, as area sampling does).
        self.sphere_cones = False
        self.round_spheres = None
        self.inward = None
        if not self.area_instances:
            return
        # Emitter slot of each instance (user order), for BSDF-sampled hits (only scenes
        # with area emitters need one per instance).
        slot = np.full(len(desc.instance_ids), NO_EMITTER, np.uint32)
        slot[self.area_instances] = np.arange(len(self.area_instances), dtype=np.uint32)
        self.emitter_of_instance = device_array(UInt32, slot)
        rows = scene.instances.to_world_of(self.area_instances)
        radiance = np.array([area[i] for i in self.area_instances], np.float32)
        self.radiance = device_vectors(radiance)
        if self.emitter_textures is not None:
            texture_of = [desc.emitters[i].texture for i in self.area_instances]
            self.texture_of_slot = device_array(UInt32, np.array(
                [NO_EMITTER if t is None else next(k for k, s in enumerate(textures) if s is t)
                 for t in texture_of], np.uint32))
        # Forward affine rows (A, b) for mapping samples, the inverse's linear part for
        # normals, and |det A| for area densities.
        inverse = scene.instances.from_world_of(self.area_instances)
        entries = device_arrays(
            Float, *[rows[:, r, c].astype(np.float32) for r in range(3) for c in range(4)],
            *[inverse[:, r, c].astype(np.float32) for r in range(3) for c in range(3)],
            np.abs(np.linalg.det(rows[:, :3, :3])).astype(np.float32))
        self.forward, self.inverse, self.abs_det = entries[:12], entries[12:21], entries[21]
        models = [desc.models[desc.instance_model[i]] for i in self.area_instances]
        self.kinds = sorted({m.kind for m in models})
        self.kind_of = device_array(UInt32, np.array([self.kinds.index(m.kind) for m in models],
                                                     np.uint32))
        # Analytic emitters turned inside out emit inward: per slot a flag, None where none is.
        inward = np.array([m.inward for m in models], bool)
        self.inward = device_array(Bool, inward) if inward.any() else None
        if MESH_KIND in self.kinds:
            meshes = scene.instances.meshes
            mesh_of_model = {i: j for j, i in enumerate(scene._mesh_models)}
            mesh = [mesh_of_model.get(desc.instance_model[i], 0) for i in self.area_instances]
            self.mesh_first = device_array(UInt32, meshes.triangle_offsets[mesh].astype(np.uint32))
            self.mesh_count = device_array(UInt32, meshes.triangle_counts[mesh].astype(np.uint32))
            mesh_area = np.array(meshes.object_areas)[mesh]
        object_area = [mesh_area[j] if m.kind == MESH_KIND else ANALYTIC_MODELS[m.kind].object_area
                       for j, m in enumerate(models)]
        self.object_area = device_array(Float, np.array(object_area, np.float32))
        # Round spheres (a sphere under a rotation, a uniform scale and a translation) may be
        # sampled by the cone of directions they subtend (:attr:`sphere_cones`); per slot a
        # flag, None where the scene has none.
        linear = rows[:, :3, :3].astype(np.float64)
        gram = np.einsum("nji,njk->nik", linear, linear)
        scale2 = np.trace(gram, axis1=1, axis2=2)[:, None, None] / 3
        round_ = (np.array([m.kind == "sphere" for m in models]) & (np.linalg.det(linear) > 0)
                  & np.all(np.abs(gram - scale2 * np.eye(3)) <= 1e-6 * scale2, axis=(1, 2)))
        self.round_spheres = device_array(UInt32, round_.astype(np.uint32)) if round_.any() else None
        # Flat emitters (rectangles, disks) have one world normal each, A^-T (0, 0, 1):
        # a BSDF-sampled hit on them needs no surface record (integrators.direct).
        self.flat_normals = None
        if all(m.kind in ANALYTIC_MODELS and ANALYTIC_MODELS[m.kind].flat for m in models):
            normals = inverse[:, 2, :3] / np.linalg.norm(inverse[:, 2, :3], axis=1, keepdims=True)
            self.flat_normals = device_vectors(np.where(inward[:, None], -normals, normals))
        self._meshes = scene.instances.meshes
        # The instance table and each emitter's instance: moving emitters take their
        # derivatives from the table's (attached) rows.
        self._table = scene.instances
        self.instance_of_slot = device_array(UInt32, np.array(self.area_instances, np.uint32))
        # World boxes (float32, rounded outward) of a few emitters, for BSDF rays that
        # test the emitters before the scene (integrators.direct).
        self.boxes = None
        if len(self.area_instances) <= EMITTERS_TESTED_FIRST:
            self.boxes = WorldBoxes(self.area_instances,
                                    *outward32(*scene.instance_bounds(self.area_instances)),
                                    scene.instances)
        self.remap_error = dr.gather(Float, scene.instances.remap_error,
                                     device_array(UInt32, np.array(self.area_instances, np.uint32)))
        # Evaluated now: left pending, the gather was folded into the first render's
        # kernel only, so that the second render compiled a kernel of its own (measured
        # 0.7 s on a 16-instance scene).
        dr.eval(self.remap_error)

    def attach_delta(self, light: int, vector: Array3f, power: Array3f) -> None:
        """Give delta light ``light`` (an index into the scene's lights) the derivatives of
        ``vector`` (its position or travel direction) and ``power``; the stored values stay."""
        j = self.delta_slot[light]
        stored = self.delta[j]
        self.delta[j] = dataclasses.replace(stored, vector=stored.vector + (vector - dr.detach(vector)),
                                            power=stored.power + (power - dr.detach(power)))

    def attach_emitter(self, instance: int, radiance: Array3f) -> None:
        """Give the area emitter of ``instance`` the derivatives of ``radiance``; the stored
        value stays."""
        self.radiance = _with_derivatives(self.radiance, radiance,
                                          UInt32(self.area_instances.index(instance)))

    def attach_emitter_texels(self, instance: int, texels: TensorXf) -> None:
        """Give the bitmap of the area emitter of ``instance`` (and of the emitters sharing
        it) the derivatives of ``texels`` ((H, W, 3)); the stored texels stay."""
        textures = self.emitter_textures
        start, (h, w) = textures.texel_range(self.texture_index[instance])
        textures.texels = _with_derivatives(textures.texels, texels.array,
                                            dr.arange(UInt32, h * w * 3) + start)

    def attach_emitter_color(self, instance: int, field: str, color: Array3f) -> None:
        """Give checkerboard colour ``field`` ("color0" or "color1") of the area emitter of
        ``instance`` (and of the emitters sharing it) the derivatives of ``color``."""
        textures = self.emitter_textures
        setattr(textures, field, _with_derivatives(getattr(textures, field), color,
                                                   UInt32(self.texture_index[instance])))

    def attach_profile_texels(self, light: int, texels: TensorXf) -> None:
        """Give the bitmap of spot or projector ``light`` (an index into the scene's lights)
        the derivatives of ``texels`` ((H, W, 3)); the stored texels stay."""
        textures = self.delta[self.delta_slot[light]].profile.texture
        textures.texels = textures.texels + (texels.array - dr.detach(texels.array))

    def attach_profile_color(self, light: int, field: str, color: Array3f) -> None:
        """Give checkerboard colour ``field`` of spot or projector ``light`` the derivatives
        of ``color``."""
        textures = self.delta[self.delta_slot[light]].profile.texture
        setattr(textures, field, getattr(textures, field) + (color - dr.detach(color)))

    def _texture_sets(self) -> list[TextureSet]:
        """The emitters' textures and each spot's or projector's, in that order."""
        return ([] if self.emitter_textures is None else [self.emitter_textures]) + [
            light.profile.texture for light in self.delta
            if light.profile is not None and light.profile.texture is not None]

    @property
    def texture_arrays(self) -> list:
        """What the lights' textures read (texels, checkerboard colours), set after set."""
        return [getattr(textures, name) for textures in self._texture_sets()
                for name in TEXTURE_ARRAYS]

    @texture_arrays.setter
    def texture_arrays(self, arrays: list) -> None:
        names = [(textures, name) for textures in self._texture_sets() for name in TEXTURE_ARRAYS]
        for (textures, name), array in zip(names, arrays):
            setattr(textures, name, array)

    @property
    def differentiable(self) -> bool:
        """Whether some light's values carry derivatives."""
        arrays = [a for light in self.delta for a in (light.vector, light.power)] + self.texture_arrays
        if self.area_instances:
            arrays.append(self.radiance)
        if self.environment is not None:
            arrays.append(self.environment.values)
        return bool(dr.grad_enabled(*arrays))

    # -- area emitters ------------------------------------------------------------------------

    def moving(self) -> bool:
        """Whether instance transforms carry derivatives (then so do the emitters')."""
        return bool(dr.grad_enabled(self._table.inverse_rows, self._table.forward_linear))

    def _matrix(self, slot: UInt32):
        """Emitter ``slot``'s forward rows (A row r, b_r) and inverse linear part, row-major
        flat lists, with |det A|: the stored values, with the derivatives of the instance
        table's rows where transforms carry them."""
        f = [dr.gather(Float, a, slot) for a in self.forward]
        inv = [dr.gather(Float, a, slot) for a in self.inverse]
        abs_det = dr.gather(Float, self.abs_det, slot)
        if self.moving():
            instance = dr.gather(UInt32, self.instance_of_slot, slot)
            forward = [c for row in self._table.forward(instance) for c in (row.x, row.y, row.z, row.w)]
            inverse = [c for row in self._table.inverse(instance) for c in (row.x, row.y, row.z)]
            f = [v + (g - dr.detach(g)) for v, g in zip(f, forward)]
            inv = [v + (g - dr.detach(g)) for v, g in zip(inv, inverse)]
            a = [forward[4 * r:4 * r + 3] for r in range(3)]
            det = (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
                   - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
                   + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]))
            signed = dr.sign(dr.detach(det)) * det
            abs_det = abs_det + (signed - dr.detach(signed))
        return f, inv, abs_det

    def area_density_scale(self, slot: UInt32, n_world: Array3f) -> Float:
        """World area per unit object area at a point with world normal n: |det A| / |A^T n|."""
        f, _, abs_det = self._matrix(slot)
        at_n = Array3f(f[0] * n_world.x + f[4] * n_world.y + f[8] * n_world.z,
                       f[1] * n_world.x + f[5] * n_world.y + f[9] * n_world.z,
                       f[2] * n_world.x + f[6] * n_world.y + f[10] * n_world.z)
        return abs_det / dr.norm(at_n)

    def _cone_seen_from(self, slot: UInt32, toward: Array3f) -> tuple[Bool, Array3f]:
        """(Whether emitter ``slot`` is a round sphere sampled by its cone from the world
        point ``toward``, which lies outside it; that point in the sphere's object space)."""
        f, inv, _ = self._matrix(slot)
        local = toward - Array3f(f[3], f[7], f[11])
        seen = Array3f(*[inv[3 * r] * local.x + inv[3 * r + 1] * local.y + inv[3 * r + 2] * local.z
                         for r in range(3)])
        cone = (dr.gather(UInt32, self.round_spheres, slot) != 0) & (dr.squared_norm(seen) > ROUND_OUTSIDE)
        return cone, seen

    @property
    def cones_sampled(self) -> bool:
        """Whether some emitter is sampled by its cone (:attr:`sphere_cones`)."""
        return self.sphere_cones and self.round_spheres is not None

    @contextlib.contextmanager
    def spheres_by_cone(self, on: bool):
        """Emitter sampling takes round spheres by their cones (``on``) in the kernels traced
        in this context."""
        before, self.sphere_cones = self.sphere_cones, on
        try:
            yield
        finally:
            self.sphere_cones = before

    def cone_pdf(self, slot: UInt32, toward: Array3f) -> Float:
        """Solid-angle density of sampling emitter ``slot`` from the world point ``toward``
        where :meth:`sample_area_emitter` samples it by its cone from there, else 0."""
        cone, seen = self._cone_seen_from(slot, toward)
        return dr.select(cone, unit_sphere_cone_pdf(seen), 0.0)

    def sample_area_emitter(self, slot: UInt32, u1: Float, u2: Float, toward: Array3f | None = None):
        """A point on area emitter ``slot``: (world point, unit world normal, pdf per world
        area, componentwise error bound of the point as in :mod:`instancing.core.error_bounds`,
        its surface coordinates where an emitter is textured, else 0; the solid-angle pdf
        seen from ``toward`` where a round sphere is sampled by its cone from there
        (:attr:`sphere_cones`), else 0)."""
        p = Array3f(0.0)
        n = Array3f(0.0)
        error = Array3f(0.0)
        uv = Array2f(0.0)
        pdf_cone = Float(0.0)
        textured = self.emitter_textures is not None
        kind = dr.gather(UInt32, self.kind_of, slot)
        for code, name in enumerate(self.kinds):
            mask = kind == code
            if name == MESH_KIND:
                first = dr.gather(UInt32, self.mesh_first, slot)
                count = dr.gather(UInt32, self.mesh_count, slot)
                p_k, position, (b1, b2) = self._meshes.sample_area(first, count, u1, u2)
                n_k = self._meshes.normal(position)
                e_k = self._meshes.point_error(position)
                uv_k = Array2f(*self._meshes.uv(position, b1, b2)) if textured else uv
            else:
                model = ANALYTIC_MODELS[name]
                p_k = model.sample_area(u1, u2)
                if name == "sphere" and toward is not None and self.cones_sampled:
                    cone, seen = self._cone_seen_from(slot, toward)
                    p_k = dr.select(cone, unit_sphere_cone_sample(seen, u1, u2), p_k)
                    pdf_cone = dr.select(mask & cone, unit_sphere_cone_pdf(seen), pdf_cone)
                n_k = model.normal(p_k, UInt32(0))
                if self.inward is not None:
                    n_k = dr.select(dr.gather(Bool, self.inward, slot), -n_k, n_k)
                e_k = model.point_error(p_k)
                uv_k = Array2f(*model.uv(p_k)) if textured else uv
            p = dr.select(mask, p_k, p)
            n = dr.select(mask, n_k, n)
            error = dr.select(mask, e_k, error)
            uv = dr.select(mask, uv_k, uv)
        f, inv, _ = self._matrix(slot)
        # Map the object-space sample: point by (A, b) with its error bound, normal by the
        # inverse transpose (moving emitters: the point and normal carry derivatives).
        rows = tuple(Array4f(*f[4 * r:4 * r + 4]) for r in range(3))
        world = world_point(rows, p)
        with dr.suspend_grad():
            error = transformed_point_error(rows, p, error, dr.gather(Float, self.remap_error, slot))
        normal = Array3f(*[inv[c] * n.x + inv[3 + c] * n.y + inv[6 + c] * n.z for c in range(3)])
        normal = normal / dr.norm(normal)
        pdf_area = 1.0 / (dr.gather(Float, self.object_area, slot) * self.area_density_scale(slot, normal))
        return world, normal, pdf_area, error, uv, pdf_cone

    def area_pdf(self, slot: UInt32, n_world: Array3f) -> Float:
        """Density per world area of sampling a given point on emitter ``slot``."""
        return 1.0 / (dr.gather(Float, self.object_area, slot) * self.area_density_scale(slot, n_world))

    def flat_normal(self, slot: UInt32) -> Array3f:
        """Unit world normal of flat emitter ``slot`` (only when ``flat_normals`` exists)."""
        return dr.gather(Array3f, self.flat_normals, slot)

    def emitter_radiance(self, slot: UInt32, uv: Array2f | None = None,
                         active: Bool | bool = True) -> Array3f:
        """Emitter ``slot``'s radiance at surface coordinates ``uv`` (a textured one's
        texture there, looked up on the ``active`` lanes; ``uv`` needed only where some
        emitter is textured)."""
        radiance = dr.gather(Array3f, self.radiance, slot)
        if self.emitter_textures is None:
            return radiance
        texture = dr.gather(UInt32, self.texture_of_slot, slot)
        textured = active & (texture != NO_EMITTER)
        return dr.select(textured, radiance * self.emitter_textures.eval(texture, uv, textured), radiance)

    def is_area_emitter(self, instance) -> tuple[Bool, UInt32]:
        """(hit is an area emitter, its slot) for user instance indices (-1 = miss). The
        slot is clamped into range where the hit is not an emitter, so that gathers by it
        stay in bounds; their values there are to be discarded."""
        slot = dr.gather(UInt32, self.emitter_of_instance, UInt32(dr.maximum(instance, 0)))
        is_emitter = (instance >= 0) & (slot != NO_EMITTER)
        return is_emitter, dr.minimum(slot, len(self.area_instances) - 1)


def _with_derivatives(stored, value, index: UInt32):
    """``stored`` (a detached array) plus the derivatives of ``value`` at entries ``index``:
    equal to ``stored`` in value."""
    change = dr.zeros(type(stored), dr.width(stored))
    dr.scatter(change, value - dr.detach(value), index)
    return stored + change


def _profile(light: PointLight) -> SpotProfile | ProjectorProfile | None:
    """A point-like light's directional profile, None for a plain point light."""
    if isinstance(light, SpotLight):
        return SpotProfile.of(light)
    if isinstance(light, ProjectorLight):
        return ProjectorProfile.of(light)
    return None
