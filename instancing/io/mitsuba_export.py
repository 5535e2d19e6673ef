"""``to_mitsuba``: the same scene as a dict for ``mitsuba.load_dict``.

Two modes:

* ``"instances"`` (default): each (model, material) pair becomes a
  ``shapegroup`` (Mitsuba's instances cannot carry their own material) and each
  instance an ``instance`` with its ``to_world``. Mitsuba supports no emitters
  inside shape groups and takes no media from instances, so emitting instances and
  those with an interior or exterior medium are always plain shapes.
* ``"shapes"``: every instance is a plain shape with ``to_world`` (smooth meshes: a
  mesh in world space). Mitsuba's
  sphere refuses non-uniform scale and shear; such spheres raise an error in
  this mode (use ``"instances"``). Reflected shapes whose normals Mitsuba
  would turn inward are turned back (see FLIPPED_BY_REFLECTION); mirrored
  meshes, SDF grids (given to Mitsuba by their values) and curves stay instances.

Flat-shaded meshes refer to their files with ``face_normals``; smooth ones are built
as Mitsuba meshes holding their corner normals (so that both renderers shade with
the same normals, whether they came from the file or were computed).

The camera becomes a ``perspective`` sensor with an ``hdrfilm`` of the same
size and filter and a tiny near clip (our rays start at the camera), point,
directional and constant lights keep their plugin names and units. Media keep their
types and are referred to by the shapes and the sensor (a homogeneous extinction above 1
given as its largest channel in ``scale``, since Mitsuba reads an RGB extinction as a
reflectance).
"""

from __future__ import annotations

import functools
import hashlib
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from ..core.arguments import integer
from ..core.backend import mitsuba_module
from ..core.errors import SceneError
from ..core.transform import is_similarity
from ..materials.bump_map import BumpMap
from ..materials.material import Material
from ..materials.normal_map import NormalMap
from ..materials.parameter import COLOR, NUMBER
from ..materials.texture import Texture
from ..models.linear_curve import ControlPointCurves
from ..models.mesh import MeshData
from ..rendering.film import DEFAULT_SPP
from ..scene.camera import RFILTER_SIZES, WHOLE_FILM
from ..scene.description import (AreaEmitter, ConstantLight, EnvironmentMap, IntegratorChoice, PointLight,
                                 ProjectorLight, SpotLight)
from ..scene.instance_table import BSPLINE_KIND, CURVE_KIND, GRID_KIND, MESH_KIND
from ..scene.medium import Medium
from ..scene.scene import Scene, require_scene

#: Mitsuba's default near clip is 0.01; ours is 0, so export a negligible one.
NEAR_CLIP = 1e-5
_PLUGIN = {"sphere": "sphere", "cube": "cube", "rectangle": "rectangle", "disk": "disk",
           "cylinder": "cylinder"}
#: Kinds whose normals Mitsuba 3.9.1 turns inward as plain shapes under a to_world with a
#: negative determinant (measured; its disk and cylinder keep them outward, and so do all
#: kinds inside instances). The export turns them back (meshes and the sphere by
#: ``flip_normals``; the cube and rectangle, which Mitsuba merges with unflipped copies, as
#: meshes built in world space with their winding reversed), so that one-sided materials
#: and emitters face the same way in both renderers, and textures read the same surface
#: coordinates.
FLIPPED_BY_REFLECTION = ("sphere", "cube", "rectangle", MESH_KIND)


@functools.lru_cache(maxsize=None)
def _flat_mesh(kind: str) -> MeshData:
    """The ``cube`` (Mitsuba's own mesh) or the ``rectangle`` ([-1, 1]^2, normal +z) as a
    mesh with the surface coordinates of ours (and Mitsuba's), shaded flat."""
    if kind == "rectangle":
        vertices = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
        faces = np.array([[0, 1, 2], [2, 3, 0]])
        uvs = 0.5 * (vertices[:, :2] + 1.0)
    else:
        params = mitsuba_module().traverse(mitsuba_module().load_dict({"type": "cube"}))
        vertices = np.array(params["vertex_positions"], np.float64).reshape(-1, 3)
        faces = np.array(params["faces"], np.int64).reshape(-1, 3)
        uvs = np.array(params["vertex_texcoords"], np.float64).reshape(-1, 2)
    return MeshData(vertices, faces, None, uvs[faces])


def _transform(mi, matrix: np.ndarray):
    return mi.ScalarTransform4f(np.asarray(matrix, np.float64).tolist())


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(c) for c in value]}


def mitsuba_bsdf(material: Material,
                 current: Callable[[Texture], Texture] = lambda texture: texture) -> dict:
    """The material as a Mitsuba BSDF dict (a conductor's named ``material`` as the ``eta``
    and ``k`` it resolved to; ``twosided`` around one-sided BSDFs; ``blendbsdf`` with its
    two BSDFs, ``mask`` with its nested one; a normal- or bump-mapped BSDF inside its
    ``normalmap`` or ``bumpmap``;
    textures as Mitsuba's texture dicts, each as ``current`` gives it: the scene's table gives
    those whose texels changed since the material was loaded)."""

    def lobe(m: Material) -> dict:
        spec = {"type": m.type}
        if m.type == "mask":  # its nested BSDF (the null lobe is implied)
            spec["bsdf"] = mitsuba_bsdf(m.parts[1], current)
        elif m.parts is not None:  # a blend: its two BSDFs
            spec.update(bsdf_0=mitsuba_bsdf(m.parts[0], current),
                        bsdf_1=mitsuba_bsdf(m.parts[1], current))
        for key, parameter in m.lobe.parameters.items():
            if key == "material" or key not in m.values:
                continue  # resolved into eta and k; an anisotropic roughness has no alpha
            if key in ("alpha_u", "alpha_v") and "alpha" in m.values:
                continue  # isotropic: alpha states both
            value = m.values[key]
            if value is None:
                continue  # stated by another key (principled's eta or specular)
            if isinstance(value, Texture):
                spec[key] = _texture(value, parameter.kind)
            else:
                spec[key] = _rgb(value) if parameter.kind == COLOR else value
        return _around(m.normal_map or m.bump_map, spec, current)

    if material.back is None:
        return _around(material.outer, lobe(material), current)
    sides = {"front": lobe(material)}
    if material.back is not material:
        sides["back"] = lobe(material.back)
    return _around(material.outer, {"type": "twosided", **sides}, current)


def _around(tilt: NormalMap | BumpMap | None, spec: dict, current: Callable[[Texture], Texture]) -> dict:
    """``spec`` inside Mitsuba's ``normalmap`` or ``bumpmap`` for ``tilt`` (as it is for None),
    the map's texture as ``current`` gives it."""
    if tilt is None:
        return spec
    options = {"flip_invalid_normals": tilt.flip_invalid_normals,
               "use_shadowing_function": tilt.use_shadowing_function, "bsdf": spec}
    texture = current(tilt.texture)
    if isinstance(tilt, NormalMap):
        return {"type": "normalmap", "normalmap": _texture(texture, COLOR), **options}
    return {"type": "bumpmap", "texture": _texture(texture, NUMBER), "scale": tilt.scale, **options}


def _texture(texture: Texture, kind: str) -> dict:
    """A texture as Mitsuba's ``bitmap``, ``checkerboard``, ``mesh_attribute`` or ``volume``
    dict (a 2D ``to_uv`` as the 4x4 transform Mitsuba takes)."""
    mi = mitsuba_module()
    if texture.type == "mesh_attribute":
        return {"type": "mesh_attribute", "name": texture.attribute, "scale": texture.scale}
    if texture.type == "volume":
        # The grid's own box, where it was used, is folded into to_world; a grid that no file
        # holds (a constvolume's one cell) goes as its values.
        source = ({"filename": texture.filename} if texture.filename
                  else {"grid": mi.VolumeGrid(np.ascontiguousarray(texture.texels, np.float32))})
        return {"type": "volume", "volume": {
            "type": "gridvolume", **source, "filter_type": texture.filter,
            "wrap_mode": texture.wrap, "raw": texture.raw, "accel": False,
            "to_world": mi.ScalarTransform4f(np.linalg.inv(texture.to_local))}}
    to_uv = np.eye(4)
    to_uv[np.ix_([0, 1, 3], [0, 1, 3])] = texture.to_uv
    spec = {"type": texture.type, "to_uv": mi.ScalarTransform4f(to_uv)}
    if texture.type == "checkerboard" and kind == COLOR and max(*texture.color0, *texture.color1) > 1:
        # Mitsuba's checkerboard reads its colours as reflectances (at most 1), which a
        # lamp's need not be: the same pattern as a 2x2 bitmap, looked up nearest (color0
        # where u and v lie in the same half of their unit interval).
        c0, c1 = texture.color0, texture.color1
        pattern = mi.Bitmap(np.array([[c0, c1], [c1, c0]], np.float32))
        return {**spec, "type": "bitmap", "bitmap": pattern, "raw": True, "filter_type": "nearest",
                "wrap_mode": "repeat", "accel": False}
    if texture.type == "checkerboard":
        for key, color in (("color0", texture.color0), ("color1", texture.color1)):
            spec[key] = _rgb(color) if kind == COLOR else color[0]
        return spec
    # accel off: on CUDA, Mitsuba's hardware lookups interpolate with 8-bit weights. Texels
    # that no file holds (set through the scene's parameters) go as an image, linear (a
    # Bitmap object: a tensor given as "data" is moved out by the first load of the dict).
    source = ({"filename": texture.filename, "raw": texture.raw} if texture.filename else
              {"bitmap": mi.Bitmap(np.asarray(texture.texels, np.float32)), "raw": True})
    return {**spec, **source, "filter_type": texture.filter, "wrap_mode": texture.wrap, "accel": False}


def _area_emitter(emitter: AreaEmitter) -> dict:
    """An instance's area emitter as Mitsuba's (its radiance a colour or its texture)."""
    return {"type": "area", "radiance": (_rgb(emitter.radiance) if emitter.texture is None
                                         else _texture(emitter.texture, COLOR))}


def _projector(mi, light: ProjectorLight) -> dict:
    """A projector as Mitsuba's: its intensity as a constant irradiance, or as the scale of
    its texture (where it is grey: Mitsuba's scale is one number)."""
    to_world = np.eye(4)
    to_world[:3, :3] = np.linalg.inv(np.reshape(light.light_from_world, (3, 3)))
    to_world[:3, 3] = light.position
    spec = {"type": "projector", "to_world": _transform(mi, to_world), "fov": light.fov, "fov_axis": "x"}
    if light.texture is None:
        return {**spec, "irradiance": _rgb(light.intensity), "scale": 1.0}
    if len(set(light.intensity)) != 1:
        raise SceneError(f"to_mitsuba: projector {light.id!r} has a textured irradiance and an "
                         f"intensity of several colours {list(light.intensity)}, which Mitsuba's "
                         "projector (one scale) cannot hold")
    return {**spec, "irradiance": _texture(light.texture, COLOR), "scale": float(light.intensity[0])}


def _medium(medium: Medium) -> dict:
    """A medium of the same type, extinction (a colour, or a heterogeneous medium's
    gridvolume), albedo (a colour or a gridvolume) and phase function."""
    albedo = (_texture(medium.albedo, COLOR)["volume"] if isinstance(medium.albedo, Texture)
              else _rgb(medium.albedo))
    if medium.type == "heterogeneous":
        sigma_t, scale = _texture(medium.sigma_t, COLOR)["volume"], medium.scale
    else:
        extinction = medium.extinction
        top = float(extinction.max())
        scale = top if top > 1 else 1.0
        sigma_t = _rgb(extinction / scale)
    return {"type": medium.type, "sigma_t": sigma_t, "scale": scale,
            "albedo": albedo, "sample_emitters": medium.sample_emitters,
            "has_spectral_extinction": medium.has_spectral_extinction,
            "phase": {"type": "hg", "g": medium.g} if medium.phase == "hg" else {"type": "isotropic"}}


def _mesh_object(mi, mesh: MeshData, matrix: np.ndarray, bsdf, emitter=None, media=None):
    """A Mitsuba mesh with ``mesh``'s corner normals and uvs where it has them (a vertex per
    distinct position, normal and uv, as Mitsuba's OBJ reader makes them), its points mapped
    by ``matrix`` and its normals by the inverse transpose; a mirroring matrix reverses the
    winding, so that the geometric normal stays on the side ours is."""
    corner = mesh.faces.reshape(-1)
    named = mesh.attributes or {}
    vertex_names = [name for name in named if name.startswith("vertex_")]
    per_corner = [a.reshape(len(corner), -1) for a in (mesh.normals, mesh.uvs) if a is not None]
    per_corner += [mesh.attribute_corners(name).reshape(len(corner), -1) for name in vertex_names]
    keys = np.concatenate([corner[:, None].astype(np.float64), *per_corner], axis=1)
    unique, index = np.unique(keys, axis=0, return_inverse=True)
    positions = mesh.vertices[unique[:, 0].astype(np.int64)] @ matrix[:3, :3].T + matrix[:3, 3]
    faces = index.reshape(-1, 3)
    if np.linalg.det(matrix[:3, :3]) < 0:
        faces = faces[:, ::-1]
    props = mi.Properties()
    props["bsdf"] = bsdf
    if emitter is not None:
        props["emitter"] = emitter
    for side, medium in (media or {}).items():
        props[side] = medium
    out = mi.Mesh("exported", len(unique), len(faces), props, has_vertex_normals=mesh.normals is not None,
                  has_vertex_texcoords=mesh.uvs is not None)
    params = mi.traverse(out)
    params["vertex_positions"] = mi.Float(positions.astype(np.float32).ravel())
    if mesh.normals is not None:
        normals = unique[:, 1:4] @ np.linalg.inv(matrix[:3, :3])
        params["vertex_normals"] = mi.Float(normals.astype(np.float32).ravel())
    if mesh.uvs is not None:
        params["vertex_texcoords"] = mi.Float(unique[:, -2:].astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    # Attributes: a vertex attribute's values at the distinct vertices (its columns last in
    # their keys, in order), a face attribute's at each face's first corner.
    column = unique.shape[1] - sum(named[name].shape[-1] for name in vertex_names)
    for name in vertex_names:
        size = named[name].shape[-1]
        out.add_attribute(name, size, unique[:, column:column + size].astype(np.float32).ravel())
        column += size
    for name in named:
        if name.startswith("face_"):
            out.add_attribute(name, named[name].shape[-1], named[name].astype(np.float32).ravel())
    return out


def _curve_file(curve: ControlPointCurves) -> Path:
    """Curves given as arrays written as a Mitsuba curve file (Mitsuba reads curves from
    files only): in the temporary folder, named by a hash of its text, so that exporting
    the same curves again reuses it."""
    rows = np.concatenate([curve.points, curve.radii[:, None]], axis=1)
    lines = [" ".join(repr(float(v)) for v in row) for row in rows]
    # An empty line before every curve's first point but the file's first.
    starts = set(curve.curve_starts().tolist())
    text = "\n".join(("\n" if k in starts and k else "") + line for k, line in enumerate(lines)) + "\n"
    path = Path(tempfile.gettempdir()) / f"instancing-curves-{hashlib.sha1(text.encode()).hexdigest()}.txt"
    if not path.exists():
        path.write_text(text)
    return path


def to_mitsuba(scene: Scene, mode: str = "instances", spp: int | None = None) -> dict:
    """A ``mitsuba.load_dict`` description of ``scene`` (see the module docstring).

    Args:
        scene: a loaded scene.
        mode: 'instances' (shapegroup + instance) or 'shapes' (plain shapes with to_world).
        spp: the sensors' sample count (for each camera's sampler type, which Mitsuba's
            sampler may round); default: each camera's own (the file's), else 64. The
            scene's integrator, where one of ours renders it, is exported as that one (with
            its ``max_depth``, ``rr_depth``, ``hide_emitters``, ``emitter_samples`` and
            ``bsdf_samples``).

    Raises:
        TypeError: ``scene`` is not a loaded :class:`~instancing.Scene`.
        SceneError: unknown mode, or a sphere Mitsuba would refuse in 'shapes' mode.
    """
    require_scene(scene, "to_mitsuba")
    if spp is not None:
        spp = integer("spp", spp, 1, 2 ** 32 - 1, "to_mitsuba")  # (Mitsuba's sample_count is 32-bit)
    if mode not in ("instances", "shapes"):
        raise SceneError(f"to_mitsuba: unknown mode {mode!r}; expected 'instances' or 'shapes'")
    mi = mitsuba_module()
    desc = scene.description
    out: dict = {"type": "scene"}
    # Materials are keyed by index: our names may hold characters Mitsuba reserves ('.' in
    # the names the XML importer gives anonymous BSDFs).
    material_key = {name: f"mat_{k}" for k, name in enumerate(scene.material_names)}
    for name, key in material_key.items():
        out[key] = mitsuba_bsdf(scene.materials[name], scene.bsdfs.current_texture)

    bsdfs: dict[str, object] = {}
    medium_key = {name: f"medium_{k}" for k, name in enumerate(desc.media)}
    for name, key in medium_key.items():
        out[key] = _medium(desc.media[name])

    @functools.cache
    def medium(name: str):
        """The medium as a Mitsuba object (for meshes built here), made once."""
        return mi.load_dict(out[medium_key[name]])

    def bsdf(material: str):
        """The material as a Mitsuba object (for meshes built here), made once."""
        if material not in bsdfs:
            bsdfs[material] = mi.load_dict(out[material_key[material]])
        return bsdfs[material]

    def shape(model_index: int, material: str) -> dict:
        model = desc.models[model_index]
        if model.kind == MESH_KIND:
            spec = {"type": model.type, "filename": str(model.filename), "face_normals": True}
            if model.flipped:
                spec["flip_normals"] = True
        elif model.kind in (CURVE_KIND, BSPLINE_KIND):
            spec = {"type": model.kind, "filename": str(model.filename or _curve_file(model.curve))}
            if model.filename is not None and model.points_to_world is not None:
                spec["to_world"] = _transform(mi, model.points_to_world)
        elif model.kind == GRID_KIND:
            spec = {"type": "sdfgrid", "grid": mi.TensorXf(model.grid.values[..., None]),
                    "normals": "smooth" if model.grid.smooth else "analytic"}
        else:
            spec = {"type": _PLUGIN[model.kind]}
            if model.flipped:
                spec["flip_normals"] = True
        spec["bsdf"] = {"type": "ref", "id": material_key[material]}
        return spec

    def smooth(model_index: int) -> bool:
        """Whether the model is a mesh built here (with its normals or uvs, or one mesh of
        a serialized file), not read from its file by Mitsuba."""
        model = desc.models[model_index]
        return model.mesh is not None and (model.mesh.normals is not None or model.mesh.uvs is not None
                                           or model.type == "serialized")

    groups: dict[tuple[int, str], str] = {}
    # The per-instance data once (the description computes matrices and names on demand).
    to_world, materials = scene.to_world, desc.instance_material
    for i, instance_id in enumerate(desc.instance_ids):
        model_index, material = int(desc.instance_model[i]), materials[i]
        matrix = to_world[i]
        emitter = desc.emitters.get(i)
        media = {side: name for side, name in zip(("interior", "exterior"), desc.instance_media.get(i, ()))
                 if name}
        plain = emitter is not None or bool(media)
        kind, flipped = desc.models[model_index].kind, desc.models[model_index].flipped
        mirrored = kind in FLIPPED_BY_REFLECTION and np.linalg.det(matrix[:3, :3]) < 0
        # A mirrored mesh stays an instance in 'shapes' mode too: as a plain shape it would need
        # flip_normals, and Mitsuba then fails to merge it with unflipped copies at load time.
        if smooth(model_index) and (mode == "shapes" or plain):
            # Built here in world space, its normals written (and its winding kept outward).
            out[f"shape_{i:07d}"] = _mesh_object(
                mi, desc.models[model_index].mesh, matrix, bsdf(material),
                None if emitter is None else mi.load_dict(_area_emitter(emitter)),
                {side: medium(name) for side, name in media.items()})
            continue
        # A grid stays an instance too: Mitsuba 3.9.1 bounds a plain grid's voxels by their
        # transformed corners' box, which is wrong under rotation; and so does a curve, whose
        # plain to_world would not scale its radii.
        if (mode == "shapes" and not (mirrored and kind == MESH_KIND)
                and kind not in (GRID_KIND, CURVE_KIND, BSPLINE_KIND) or plain):
            if kind == "sphere" and not is_similarity(matrix):
                raise SceneError(f"to_mitsuba: instance {instance_id!r} is a sphere under non-uniform "
                                 "scale or shear, which Mitsuba's sphere refuses as a plain shape"
                                 + (" (and Mitsuba instances no emitter)" if emitter else
                                    " (and Mitsuba instances nothing with a medium)" if media else
                                    "; use mode='instances'"))
            spec = shape(model_index, material)
            if mirrored and kind in (MESH_KIND, "sphere"):
                # (A mesh here is an emitter: it cannot be instanced. The sphere keeps its
                # map, so its surface coordinates stay ours.)
                spec["flip_normals"] = not spec.get("flip_normals", False)
            elif kind in ("cube", "rectangle") and (mirrored or flipped):
                # The cube and rectangle, which Mitsuba merges with unflipped copies
                # (flip_normals would make them incompatible): built here in world space,
                # their winding as ours and their surface coordinates kept.
                out[f"shape_{i:07d}"] = _mesh_object(
                    mi, _flat_mesh(kind).flipped() if flipped else _flat_mesh(kind), matrix, bsdf(material),
                    None if emitter is None else mi.load_dict(_area_emitter(emitter)),
                    {side: medium(name) for side, name in media.items()})
                continue
            spec["to_world"] = _transform(mi, matrix)
            if emitter is not None:
                spec["emitter"] = _area_emitter(emitter)
            for side, name in media.items():
                spec[side] = {"type": "ref", "id": medium_key[name]}
            out[f"shape_{i:07d}"] = spec
            continue
        key = (model_index, material)
        if key not in groups:
            groups[key] = f"group_{len(groups)}"
            out[groups[key]] = {"type": "shapegroup", "shape": (
                _mesh_object(mi, desc.models[model_index].mesh, np.eye(4), bsdf(material))
                if smooth(model_index) else shape(model_index, material))}
        out[f"instance_{i:07d}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": groups[key]},
                                    "to_world": _transform(mi, matrix)}
    for k, light in enumerate(scene.lights):
        if isinstance(light, SpotLight):
            to_world = np.eye(4)
            to_world[:3, :3] = np.linalg.inv(np.reshape(light.light_from_world, (3, 3)))
            to_world[:3, 3] = light.position
            out[f"light_{k}"] = {"type": "spot", "to_world": _transform(mi, to_world),
                                 "intensity": _rgb(light.intensity),
                                 "cutoff_angle": light.cutoff_angle, "beam_width": light.beam_width}
            if light.texture is not None:
                out[f"light_{k}"]["texture"] = _texture(light.texture, COLOR)
        elif isinstance(light, ProjectorLight):
            out[f"light_{k}"] = _projector(mi, light)
        elif isinstance(light, PointLight):
            out[f"light_{k}"] = {"type": "point", "position": list(light.position),
                                 "intensity": _rgb(light.intensity)}
        elif isinstance(light, ConstantLight):
            out[f"light_{k}"] = {"type": "constant", "radiance": _rgb(light.radiance)}
        elif isinstance(light, EnvironmentMap):
            # (Texels set through the scene's parameters, which no file holds, as an image.)
            source = ({"filename": light.filename} if light.filename else
                      {"bitmap": mi.Bitmap(np.asarray(light.texels, np.float32))})
            out[f"light_{k}"] = {"type": "envmap", **source, "scale": light.scale,
                                 "to_world": _transform(mi, light.to_world)}
        else:
            out[f"light_{k}"] = {"type": "directional", "direction": list(light.direction),
                                 "irradiance": _rgb(light.irradiance)}
    for k, camera in enumerate(scene.cameras):
        # (Mitsuba's scene lists its sensors in the dict's order: camera k is sensor k.)
        out["sensor" if k == 0 else f"sensor_{k}"] = {
            "type": camera.type, "near_clip": camera.near_clip or NEAR_CLIP,
            **({} if camera.type == "orthographic" else {"fov": camera.fov, "fov_axis": "x"}),
            **({"aperture_radius": camera.aperture_radius,
                "focus_distance": camera.focus_distance} if camera.type == "thinlens" else {}),
            **({"principal_point_offset_x": camera.principal_point[0],
                "principal_point_offset_y": camera.principal_point[1]}
               if camera.type == "perspective" and camera.principal_point != (0.0, 0.0) else {}),
            "to_world": _transform(mi, np.array(camera.world_from_camera.matrix)),
            "film": {"type": "hdrfilm", **_film_size(camera), "pixel_format": camera.pixel_format,
                     "rfilter": _rfilter(camera),
                     **({"sample_border": True} if camera.sample_border else {})},
            "sampler": {"type": camera.sampler,
                        "sample_count": spp if spp is not None else camera.spp or DEFAULT_SPP,
                        **({"seed": camera.seed} if camera.seed else {}),
                        **({} if camera.jitter else {"jitter": False})},
            **({"medium": {"type": "ref", "id": medium_key[camera.medium]}} if camera.medium else {}),
        }
    choice = scene.description.integrator
    if choice is not None and choice.name is not None:
        out["integrator"] = _integrator(choice)
    return out


def _integrator(choice: IntegratorChoice) -> dict:
    """Mitsuba's integrator of ours that renders ``choice``, with its settings; Mitsuba's
    ``aov`` (with its AOVs) and ``moment`` with, under their labels, the integrators nested
    in them."""
    if choice.name in ("aov", "moment"):
        aovs = ({"aovs": ", ".join(f"{label}:{kind}" for label, kind in choice.aovs)}
                if choice.name == "aov" else {})
        return {"type": choice.name, **aovs, **{label: _integrator(nested) for label, nested in choice.nested}}
    # (Mitsuba's depths are 32-bit signed: larger ones bound nothing either.)
    return {"type": choice.name, **{key: min(value, (1 << 31) - 1) for key, value in (
        ("max_depth", choice.max_depth), ("rr_depth", choice.rr_depth)) if value is not None},
        **({} if choice.hide_emitters is None else {"hide_emitters": choice.hide_emitters}),
        **{key: value for key, value in (("emitter_samples", choice.emitter_samples),
                                         ("bsdf_samples", choice.bsdf_samples)) if value is not None}}


def _film_size(camera) -> dict:
    """The camera's film size, and its crop window where it shows part of the film: Mitsuba
    takes them in whole pixels, which a window scaled to another image size may not give."""
    if camera.window == WHOLE_FILM:
        return {"width": camera.width, "height": camera.height}
    x0, y0, x1, y1 = camera.window
    width, height = camera.width / (x1 - x0), camera.height / (y1 - y0)
    pixels = [width, height, x0 * width, y0 * height]
    whole = [round(p) for p in pixels]
    if any(abs(p - q) > 1e-6 * max(1.0, abs(p)) for p, q in zip(pixels, whole)):
        raise SceneError(f"to_mitsuba: camera {camera.id or camera.type!r}: its crop window at "
                          f"{camera.width} x {camera.height} is not a whole number of film pixels "
                          f"(film {pixels[0]:g} x {pixels[1]:g}, offset {pixels[2]:g}, {pixels[3]:g})")
    return {"width": whole[0], "height": whole[1], "crop_offset_x": whole[2],
            "crop_offset_y": whole[3], "crop_width": camera.width, "crop_height": camera.height}


def _rfilter(camera) -> dict:
    """The camera's reconstruction filter as a Mitsuba plugin dict (with its size, or a
    mitchell filter's B and C, if any)."""
    if camera.rfilter_bc is not None:
        return {"type": camera.rfilter, "B": camera.rfilter_bc[0], "C": camera.rfilter_bc[1]}
    size = RFILTER_SIZES[camera.rfilter]
    if size is None or camera.rfilter_size is None:
        return {"type": camera.rfilter}
    # (A Lanczos filter's lobes are an integer in Mitsuba.)
    value = int(camera.rfilter_size) if camera.rfilter == "lanczos" else camera.rfilter_size
    return {"type": camera.rfilter, size[0]: value}
