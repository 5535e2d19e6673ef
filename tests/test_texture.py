"""Textures (instancing/materials/texture.py): lookups against Mitsuba's own ``bitmap`` and
``checkerboard`` plugins at the same surface coordinates, mesh attributes against Mitsuba's
``eval_attribute`` at the same hits, textured BSDFs against Mitsuba's BSDFs holding those
textures, the parameters' validation.

Reference: Mitsuba 3's texture plugins (``mi.load_dict``) evaluated with ``eval`` on a
surface interaction whose ``uv`` is set; agreement to float32 round-off.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import instancing
from instancing.core.backend import Array2f, Array3f, Bool, Float, UInt32, dr, mitsuba_module
from instancing.core.errors import SceneError
from instancing.io.image import ImageFileError, read_texture
from instancing.io.mesh_file import read_mesh
from instancing.io.mitsuba_export import mitsuba_bsdf
from instancing.materials.bsdf import BSDFTable
from instancing.materials.material import parse_material
from instancing.materials.texture import TextureSet, luminance, parse_texture
from scene_helpers import assert_textured_bsdf_is_mitsubas

N = 2048


def _read(filename, raw):
    return read_texture(filename, raw), filename


def _mitsuba_uv(uv: np.ndarray):
    mi = mitsuba_module()
    si = dr.zeros(mi.SurfaceInteraction3f, uv.shape[1])
    si.uv = mi.Point2f(Float(uv[0]), Float(uv[1]))
    return mi, si


def _ours(spec: dict, uv: np.ndarray) -> np.ndarray:
    texture = parse_texture("t", spec, lambda value, where: value, _read)
    lanes = UInt32(np.zeros(uv.shape[1], np.uint32))
    return np.asarray(TextureSet([texture]).eval(lanes, Array2f(*uv), Bool(True)), np.float64)


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """An 8-bit RGB PNG, an 8-bit grey PNG and a float RGB EXR with random texels."""
    mi = mitsuba_module()
    folder = tmp_path_factory.mktemp("textures")
    rng = np.random.default_rng(3)
    rgb = folder / "rgb.png"
    mi.Bitmap((rng.uniform(size=(5, 7, 3)) * 255).astype(np.uint8), mi.Bitmap.PixelFormat.RGB).write(str(rgb))
    grey = folder / "grey.png"
    mi.Bitmap((rng.uniform(size=(4, 3, 1)) * 255).astype(np.uint8), mi.Bitmap.PixelFormat.Y).write(str(grey))
    exr = folder / "float.exr"
    mi.Bitmap(rng.uniform(0, 3, size=(6, 4, 3)).astype(np.float32), mi.Bitmap.PixelFormat.RGB).write(str(exr))
    return {"rgb": str(rgb), "grey": str(grey), "exr": str(exr)}


#: A to_uv with scale, rotation and translation (Mitsuba takes a 4x4; its x, y part acts on uv).
TO_UV = [[1.5, -0.8, 0.0, 0.3], [0.6, 2.0, 0.0, -0.2], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


@pytest.mark.parametrize("image", ["rgb", "grey", "exr"])
@pytest.mark.parametrize("wrap", ["repeat", "mirror", "clamp"])
@pytest.mark.parametrize("filter_type", ["bilinear", "nearest"])
def test_bitmap_lookups_are_mitsubas(images, image, wrap, filter_type):
    """Random uv well outside [0, 1] (every wrap mode at work), 8-bit sRGB and float images,
    raw and decoded, with and without a to_uv map."""
    rng = np.random.default_rng(len(image) + len(wrap) + len(filter_type))
    uv = rng.uniform(-1.5, 2.5, size=(2, N)).astype(np.float32)
    for raw in (False, True):
        for to_uv in (None, TO_UV):
            spec = {"type": "bitmap", "filename": images[image], "wrap_mode": wrap,
                    "filter_type": filter_type, "raw": raw}
            mi, si = _mitsuba_uv(uv)
            theirs = dict(spec, accel=False)  # float interpolation on CUDA too, as ours
            if to_uv is not None:
                spec["to_uv"], theirs["to_uv"] = to_uv, mi.ScalarTransform4f(to_uv)
            reference = np.asarray(mi.load_dict(theirs).eval(si), np.float64)
            reference = np.broadcast_to(reference, (3, N))  # a grey image gives one channel
            # Round-off: the float32 texel coordinates (up to ~40 after to_uv) differ by an ulp
            # (~4e-6) where the map's products are summed in another order; times a texel
            # difference of up to 1.
            np.testing.assert_allclose(_ours(spec, uv), reference, rtol=0, atol=1e-5)


@pytest.mark.parametrize("image", ["rgb", "grey", "exr"])
@pytest.mark.parametrize("wrap", ["repeat", "mirror", "clamp"])
def test_bitmap_gradients_are_mitsubas(images, image, wrap):
    """The luminance's derivatives by (u, v) (what bump maps read) against Mitsuba's
    ``eval_1_grad`` at random uv, with and without a to_uv map; 0 for nearest lookups."""
    rng = np.random.default_rng([9, len(image), len(wrap)])
    uv = rng.uniform(-1.5, 2.5, size=(2, N)).astype(np.float32)
    lanes = UInt32(np.zeros(N, np.uint32))
    for filter_type in ("bilinear", "nearest"):
        for to_uv in (None, TO_UV):
            spec = {"type": "bitmap", "filename": images[image], "wrap_mode": wrap,
                    "filter_type": filter_type, "raw": True}
            mi, si = _mitsuba_uv(uv)
            theirs = dict(spec, accel=False)
            if to_uv is not None:
                spec["to_uv"], theirs["to_uv"] = to_uv, mi.ScalarTransform4f(to_uv)
            reference = np.asarray(mi.load_dict(theirs).eval_1_grad(si), np.float64)
            texture = parse_texture("t", spec, lambda value, where: value, _read)
            ours = np.asarray(TextureSet([texture]).gradient(lanes, Array2f(*uv), Bool(True)), np.float64)
            if filter_type == "nearest":
                assert (ours == 0).all() and (reference == 0).all()
                continue
            assert np.abs(reference).max() > 1.0  # (texel differences times the resolution)
            # Round-off as for the lookups, times the resolution and the map's entries.
            print("GRADERR", image, wrap, to_uv is None, np.abs(ours - reference).max() / np.abs(reference).max())
            np.testing.assert_allclose(ours, reference, rtol=0, atol=2e-4 * np.abs(reference).max())


def test_checkerboard_is_mitsubas():
    rng = np.random.default_rng(5)
    uv = rng.uniform(-3, 3, size=(2, N)).astype(np.float32)
    mi, si = _mitsuba_uv(uv)
    for spec in ({"type": "checkerboard"},
                 {"type": "checkerboard", "color0": [0.9, 0.1, 0.2], "color1": [0.0, 0.5, 1.0],
                  "to_uv": TO_UV}):
        theirs = {**spec, "to_uv": mi.ScalarTransform4f(spec.get("to_uv", np.eye(4).tolist()))}
        for key in ("color0", "color1"):
            if key in spec:
                theirs[key] = {"type": "rgb", "value": spec[key]}
        reference = np.broadcast_to(np.asarray(mi.load_dict(theirs).eval(si), np.float64), (3, N))
        ours = _ours(spec, uv)
        np.testing.assert_allclose(ours, reference, rtol=1e-6)
        assert len(np.unique(ours[0])) == 2


def test_luminance_is_mitsubas():
    mi = mitsuba_module()
    rgb = np.random.default_rng(1).uniform(size=(3, 100)).astype(np.float32)
    np.testing.assert_allclose(np.asarray(luminance(Array3f(*rgb))),
                               np.asarray(mi.luminance(mi.Color3f(*rgb))), rtol=1e-6)


#: Textured materials: every texturable parameter kind (colour, number by luminance) in
#: lobes that read it per lookup, and plastic, whose lobe choice reads a texture's mean.
TEXTURED = {
    "diffuse_bitmap": {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": "rgb"}},
    "diffuse_checker": {"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": TO_UV}},
    "rough_alpha_bitmap": {"type": "roughconductor", "material": "Al",
                           "alpha": {"type": "bitmap", "filename": "rgb", "wrap_mode": "mirror"}},
    "rough_alpha_checker": {"type": "roughconductor", "alpha": {"type": "checkerboard",
                                                                "color0": 0.05, "color1": 0.5}},
    "plastic_textured": {"type": "plastic",
                         "diffuse_reflectance": {"type": "bitmap", "filename": "exr", "raw": True},
                         "specular_reflectance": {"type": "checkerboard", "color0": 1.0,
                                                  "color1": 0.3}},
    "roughplastic_textured": {"type": "roughplastic", "alpha": 0.3,
                              "diffuse_reflectance": {"type": "bitmap", "filename": "grey"}},
    "roughdielectric_textured": {"type": "roughdielectric",
                                 "alpha": {"type": "bitmap", "filename": "grey"},
                                 "specular_transmittance": {"type": "checkerboard"}},
    "twosided_textured": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
        "type": "checkerboard", "color0": [0.8, 0.7, 0.1]}}},
}


def _with_files(spec, images):
    if isinstance(spec, dict):
        return {k: (images[v] if k == "filename" else _with_files(v, images)) for k, v in spec.items()}
    return spec


@pytest.mark.parametrize("name", sorted(TEXTURED))
def test_textured_bsdfs_are_mitsubas(images, name):
    """f cos and pdf at random directions and random uv, against Mitsuba's BSDF holding
    the same textures (its own plugins, built from our export of the material)."""
    spec = _with_files(TEXTURED[name], images)
    rng = np.random.default_rng(sorted(TEXTURED).index(name))
    w = rng.normal(size=(2, N, 3))
    w[..., 2] = np.abs(w[..., 2]) * np.where(rng.random(N) < 0.8, 1, -1)
    wi, wo = (x / np.linalg.norm(x, axis=1, keepdims=True) for x in w)
    uv = rng.uniform(-0.5, 1.5, size=(2, N)).astype(np.float32)
    material = parse_material("m", spec, _read)
    mi, si = _mitsuba_uv(uv)
    bsdf = mi.load_dict(mitsuba_bsdf(material))
    si.wi = mi.Vector3f(*[Float(wi[:, k].astype(np.float32)) for k in range(3)])
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    assert_textured_bsdf_is_mitsubas(BSDFTable([material]), bsdf, si, wi, wo, uv)


def test_texture_means_are_mitsubas(images):
    """Plastic picks its lobes by the mean of its textures, as Mitsuba's ``mean()``."""
    mi = mitsuba_module()
    for spec in ({"type": "bitmap", "filename": images["exr"]},
                 {"type": "bitmap", "filename": images["rgb"]},
                 {"type": "checkerboard", "color0": [0.9, 0.1, 0.2], "color1": 0.3}):
        texture = parse_texture("t", spec, lambda value, where: value, _read)
        theirs = dict(spec)
        if "color0" in spec:
            theirs["color0"] = {"type": "rgb", "value": spec["color0"]}
        np.testing.assert_allclose(texture.mean, np.asarray(mi.load_dict(theirs).mean()).item(),
                                   rtol=1e-5)


def test_a_to_uv_given_as_operations_is_mitsubas_transform():
    """``to_uv`` as a list of operations, as ``to_world`` takes them: the checkerboard of
    Mitsuba's transform built by its own translate, rotate and scale."""
    rng = np.random.default_rng(8)
    uv = rng.uniform(-3, 3, size=(2, N)).astype(np.float32)
    mi, si = _mitsuba_uv(uv)
    ops = [{"translate": [0.3, -0.2, 0]}, {"rotate": {"axis": [0, 0, 1], "angle": 30}}, {"scale": [1.5, 2, 1]}]
    to_uv = mi.ScalarTransform4f().translate([0.3, -0.2, 0]).rotate([0, 0, 1], 30).scale([1.5, 2, 1])
    reference = np.broadcast_to(np.asarray(mi.load_dict({"type": "checkerboard", "to_uv": to_uv}).eval(si),
                                           np.float64), (3, N))
    np.testing.assert_allclose(_ours({"type": "checkerboard", "to_uv": ops}, uv), reference, rtol=1e-6)


@pytest.mark.parametrize("spec, words", [
    ({"type": "diffuse", "reflectance": {"type": "wood"}}, ["unknown texture type", "'wood'", "bitmap"]),
    ({"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": [{"shear": 1}]}},
     ["to_uv[0]", "unknown operation 'shear'"]),
    ({"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": [{"scale": [1, 0, 1]}]}},
     ["to_uv", "scale", "singular"]),
    ({"type": "diffuse", "reflectance": {"type": "checkerboard", "colour0": 1}},
     ["'colour0'", "did you mean 'color0'", "texture"]),
    ({"type": "diffuse", "reflectance": {"type": "checkerboard", "color0": 2.0}}, ["color0", "[0.0, 1.0]"]),
    ({"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": [[1, 0], [0, 1]]}}, ["to_uv"]),
    ({"type": "diffuse", "reflectance": {"type": "checkerboard",
                                         "to_uv": [[1, 0, 0], [0, 1, 0], [0, 0, float("nan")]]}}, ["to_uv"]),
    ({"type": "diffuse", "reflectance": {"type": "bitmap"}}, ["needs a 'filename'"]),
    ({"type": "diffuse", "reflectance": {"type": "bitmap", "filename": "x.png", "wrap_mode": "tile"}},
     ["wrap_mode", "mirror"]),
    ({"type": "diffuse", "reflectance": {"type": "bitmap", "filename": "x.png", "raw": "yes"}}, ["raw"]),
    ({"type": "roughplastic", "alpha": {"type": "checkerboard"}}, ["'alpha'", "not a texture"]),
    ({"type": "plastic", "int_ior": {"type": "checkerboard"}}, ["'int_ior'", "not a texture"]),
    ({"type": "diffuse", "reflectance": {"type": "mesh_attribute"}}, ["'reflectance'", "needs a 'name'"]),
    ({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "color"}},
     ["'vertex_' or 'face_'", "'color'"]),
    ({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color",
                                         "scale": float("inf")}}, ["reflectance'.scale", "finite"]),
    ({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color",
                                         "to_uv": np.eye(3).tolist()}}, ["'to_uv'", "mesh_attribute"]),
    ({"type": "plastic", "diffuse_reflectance": {"type": "mesh_attribute", "name": "vertex_color"}},
     ["material 'm'", "'diffuse_reflectance'", "no mean"]),
    ({"type": "roughplastic", "specular_reflectance": {"type": "mesh_attribute", "name": "face_c"}},
     ["material 'm'", "'specular_reflectance'", "no mean"]),
    ({"type": "normalmap", "normalmap": {"type": "mesh_attribute", "name": "vertex_n"},
      "bsdf": {"type": "diffuse"}}, ["'normalmap' must be", "bitmap or checkerboard"]),
    ({"type": "bumpmap", "h": {"type": "mesh_attribute", "name": "vertex_h"},
      "bsdf": {"type": "diffuse"}}, ["needs a bitmap", "'mesh_attribute'"]),
    ({"type": "normalmap", "normalmap": {"type": "volume", "volume": {"type": "gridvolume"}},
      "bsdf": {"type": "diffuse"}}, ["'normalmap' must be", "bitmap or checkerboard"]),
])
def test_bad_textures_name_the_key(spec, words):
    with pytest.raises(SceneError) as err:
        parse_material("m", spec, lambda filename, raw: (np.zeros((1, 1, 3), np.float32), filename))
    for word in words:
        assert word in str(err.value), str(err.value)


def test_missing_and_unreadable_images_are_errors(tmp_path):
    with pytest.raises(ImageFileError, match="does not exist"):
        read_texture(tmp_path / "none.png")
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    with pytest.raises(ImageFileError, match="junk.png"):
        read_texture(junk)
    scene = {"materials": {"m": {"type": "diffuse", "reflectance": {"type": "bitmap",
                                                                   "filename": "none.png"}}},
             "instances": [{"model": "sphere", "material": "m"}]}
    with pytest.raises(SceneError, match=r"material 'm': texture 'none.png'.*none\.png"):
        instancing.load_scene(scene, base_dir=tmp_path)


MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"


def _attribute_material(name: str, **extra) -> dict:
    texture = {"type": "mesh_attribute", "name": name, **extra}
    if name == "vertex_roughness" and not extra:
        return {"type": "roughconductor", "alpha": texture}
    return {"type": "diffuse", "reflectance": texture}


@pytest.mark.parametrize("name, extra", [("vertex_color", {"scale": 0.8}), ("face_tint_color", {}),
                                         ("vertex_roughness", {"scale": 1.0}), ("vertex_roughness", {})])
def test_mesh_attributes_at_hits_are_mitsubas(name, extra):
    """A mesh attribute read by a material, at random hits on a turned and sheared torus
    (meshes/torus_colors.ply), against Mitsuba's ``eval_attribute`` (a colour parameter:
    a vertex colour interpolated, a face tint, a one-value roughness as grey) and
    ``eval_attribute_1`` (a number parameter: the roughness as a rough conductor's alpha)
    on the same rays, where both hit the same triangle; to 2e-6 / cos(angle of incidence),
    float32 round-off of Mitsuba's barycentrics (measured: 3e-8 median, 2.4e-5 at cos 0.001;
    with b1 and b2 swapped, errors of 0.13 - 0.16)."""
    from instancing.core.backend import MITSUBA_VARIANT
    mi = mitsuba_module()
    mi.set_variant(MITSUBA_VARIANT)
    rng = np.random.default_rng(11)
    matrix = np.array([[0.8, 0.3, 0.1, 0.2], [-0.2, 0.9, 0.4, -0.1], [0.1, -0.3, 1.1, 0.5], [0, 0, 0, 1]])
    scene = instancing.load_scene({
        "models": {"torus": {"type": "ply", "filename": str(MESHES / "torus_colors.ply")}},
        "materials": {"m": _attribute_material(name, **extra)},
        "instances": [{"model": "torus", "material": "m", "to_world": matrix.tolist()}]})
    theirs_scene = mi.load_dict({"type": "scene", "torus": {
        "type": "ply", "filename": str(MESHES / "torus_colors.ply"),
        "to_world": mi.ScalarTransform4f(matrix)}})
    # Rays towards random points of the surface, from random directions.
    mesh = read_mesh(MESHES / "torus_colors.ply")
    corners = mesh.vertices[mesh.faces] @ matrix[:3, :3].T + matrix[:3, 3]
    pick = rng.integers(0, len(corners), N)
    b = rng.dirichlet([1, 1, 1], N)
    target = np.einsum("nk,nkc->nc", b, corners[pick])
    d = rng.normal(size=(N, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = target - 3.0 * d
    hit = scene.intersect_surface(Array3f(*(o - scene.origin).T.astype(np.float32)),
                                  Array3f(*d.T.astype(np.float32)))
    number = name == "vertex_roughness" and not extra
    point = scene.lookup_point(hit)
    ours = (scene.bsdfs.roughness(scene.material_of(hit), point) if number else scene.albedo(hit))
    ours = np.asarray(ours, np.float64).reshape(-1 if number else 3, N).T.reshape(N, -1)
    si = theirs_scene.ray_intersect(mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)),
                                             mi.Vector3f(*d.T.astype(np.float32))))
    shape = theirs_scene.shapes()[0]
    theirs = shape.eval_attribute_1(name, si) if number else shape.eval_attribute(name, si)
    theirs = np.asarray(theirs, np.float64).reshape(-1 if number else 3, N).T.reshape(N, -1)
    theirs = theirs * extra.get("scale", 1.0)
    same = np.asarray(hit.valid) & np.asarray(si.is_valid()) & (
        np.asarray(hit.prim) == np.asarray(si.prim_index))
    assert same.mean() > 0.9 and np.std(theirs[same]) > 0.01
    # Mitsuba's barycentrics come from its float32 world hit point, whose error along the
    # surface grows as 1 / cos of the ray's angle to the normal: so does the tolerance.
    cos = np.abs(np.sum(np.asarray(hit.n, np.float64).T * d, axis=1))
    error = np.abs(ours - theirs).max(axis=1)
    worst = np.argmax(np.where(same, error * cos, 0.0))
    assert error[worst] * cos[worst] <= 2e-6, (error[worst], cos[worst], ours[worst], theirs[worst])


def write_volume_grid(path, values: np.ndarray, lo=(0, 0, 0), hi=(1, 1, 1)) -> str:
    """A Mitsuba ``.vol`` file of ``values`` (z, y, x, channels) float32."""
    import struct
    z, y, x, c = values.shape
    header = struct.pack("<3sBiiiii6f", b"VOL", 3, 1, x, y, z, c, *lo, *hi)
    path.write_bytes(header + values.astype("<f4").tobytes())
    return str(path)


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("wrap", ["clamp", "repeat", "mirror"])
@pytest.mark.parametrize("filter_type", ["trilinear", "nearest"])
def test_volume_textures_at_hits_are_mitsubas(tmp_path, channels, wrap, filter_type):
    """A ``volume`` texture (a gridvolume of 5 x 4 x 3 cells, turned, scaled and moved, its
    unit cube covering part of a sphere, so that the wrap modes show) read by a diffuse at
    random hits, against Mitsuba's own texture plugin evaluated at the same world points,
    in a scene whose rendering space is moved (all of it 64 units from the origin, where the
    rendering space puts the camera at 0); with ``use_grid_bbox`` for the colour grids."""
    from instancing.core.backend import MITSUBA_VARIANT
    mi = mitsuba_module()
    mi.set_variant(MITSUBA_VARIANT)
    rng = np.random.default_rng(channels * 7 + len(wrap) + len(filter_type))
    values = rng.uniform(0, 1, (3, 4, 5, channels)).astype(np.float32)
    filename = write_volume_grid(tmp_path / "grid.vol", values, lo=(-0.5, 0.0, 0.25), hi=(1.5, 2.0, 1.0))
    far = np.array([64.0, 0.0, 0.0])
    to_world = (instancing.translate(far + [-0.3, 0.2, 0.1]) @ instancing.rotate([1, 2, 3], 40)
                @ instancing.scale([0.9, 0.6, 1.2])).to_numpy()[0]
    volume = {"type": "gridvolume", "filename": filename, "wrap_mode": wrap, "filter_type": filter_type,
              "to_world": to_world.tolist(), "use_grid_bbox": channels == 3}
    scene = instancing.load_scene({
        "materials": {"m": {"type": "diffuse", "reflectance": {"type": "volume", "volume": volume}}},
        "instances": [{"model": "sphere", "material": "m", "to_world": [{"translate": far.tolist()}]}],
        "camera": {"type": "perspective", "fov": 30, "width": 8, "height": 8, "to_world": [
            {"look_at": {"origin": (far + [4, 3, 2]).tolist(), "target": far.tolist(), "up": [0, 0, 1]}}]}})
    assert np.abs(scene.origin).max() > 60
    theirs_texture = mi.load_dict({"type": "volume", "volume": {
        **{k: v for k, v in volume.items() if k != "to_world"}, "to_world": mi.ScalarTransform4f(to_world)}})
    d = rng.normal(size=(N, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = far - 3.0 * d + rng.uniform(-0.6, 0.6, (N, 3))
    hit = scene.intersect_surface(Array3f(*(o - scene.origin).T.astype(np.float32)),
                                  Array3f(*d.T.astype(np.float32)))
    ours = np.asarray(scene.albedo(hit), np.float64).T
    p = np.asarray(hit.p, np.float64).T + scene.origin
    si = dr.zeros(mi.SurfaceInteraction3f, N)
    si.p = mi.Point3f(*p.T.astype(np.float32))
    theirs = np.asarray(theirs_texture.eval(si), np.float64).reshape(3, N).T
    valid = np.asarray(hit.valid)
    assert valid.mean() > 0.5 and np.std(theirs[valid]) > 0.05
    # Exported, the texture is Mitsuba's own again (the grid's box folded into to_world).
    exported = mi.load_dict(instancing.to_mitsuba(scene)["mat_0"]["reflectance"])
    np.testing.assert_allclose(np.asarray(exported.eval(si), np.float64).reshape(3, N).T, theirs,
                               rtol=0, atol=1e-5)
    # Mitsuba reads the grid at the float32 world point (an ulp of 64 is 7.6e-6), which moves
    # its lookup by up to that times the grid's slope (values in [0, 1] over cells of 0.1).
    np.testing.assert_allclose(ours[valid], theirs[valid], rtol=0, atol=1e-4)


def test_constant_volume_textures_are_mitsubas():
    """A ``volume`` texture's constvolume (a colour, and a number for a grey one; turned,
    scaled and moved) read by a diffuse at random hits inside and outside its unit cube: its
    value everywhere, as Mitsuba's constvolume gives at the same points; exported (a
    gridvolume of one cell), Mitsuba's plugin gives it too."""
    from instancing.core.backend import MITSUBA_VARIANT
    mi = mitsuba_module()
    mi.set_variant(MITSUBA_VARIANT)
    rng = np.random.default_rng(31)
    to_world = (instancing.translate([0.3, -0.2, 0.1]) @ instancing.rotate([1, 2, 3], 40)
                @ instancing.scale([1.2, 1.0, 0.9])).to_numpy()[0]
    d = rng.normal(size=(N, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = -3.0 * d + rng.uniform(-0.6, 0.6, (N, 3))
    for value, theirs_value in (([0.7, 0.2, 0.45], {"type": "rgb", "value": [0.7, 0.2, 0.45]}), (0.35, 0.35)):
        volume = {"type": "constvolume", "value": value, "to_world": to_world.tolist()}
        scene = instancing.load_scene({
            "materials": {"m": {"type": "diffuse", "reflectance": {"type": "volume", "volume": volume}}},
            "instances": [{"model": "sphere", "material": "m"}]})
        hit = scene.intersect_surface(Array3f(*o.T.astype(np.float32)), Array3f(*d.T.astype(np.float32)))
        ours = np.asarray(scene.albedo(hit), np.float64).T
        si = dr.zeros(mi.SurfaceInteraction3f, N)
        si.p = mi.Point3f(*(np.asarray(hit.p, np.float64).T + scene.origin).T.astype(np.float32))
        theirs_texture = mi.load_dict({"type": "volume", "volume": {
            "type": "constvolume", "value": theirs_value, "to_world": mi.ScalarTransform4f(to_world)}})
        # (Mitsuba's constvolume gives one value for all points: a width-1 array.)
        theirs = np.broadcast_to(np.asarray(theirs_texture.eval(si), np.float64).reshape(3, -1), (3, N)).T
        exported = mi.load_dict(instancing.to_mitsuba(scene)["mat_0"]["reflectance"])
        valid = np.asarray(hit.valid)
        inside = np.all(np.abs(_unit_cube_coordinates(to_world, np.asarray(hit.p).T) - 0.5) < 0.5, axis=1)
        assert valid.mean() > 0.5 and 0.05 < inside[valid].mean() < 0.95
        np.testing.assert_allclose(theirs[valid], np.broadcast_to(value, (valid.sum(), 3)), rtol=1e-6)
        np.testing.assert_allclose(ours[valid], theirs[valid], rtol=1e-6)
        np.testing.assert_allclose(np.asarray(exported.eval(si), np.float64).reshape(3, N).T[valid],
                                   theirs[valid], rtol=1e-6)


def _unit_cube_coordinates(to_world: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points ``p`` (N, 3) in the unit-cube coordinates of a volume placed by ``to_world``."""
    return (np.linalg.inv(to_world) @ np.hstack([p, np.ones((len(p), 1))]).T).T[:, :3]


@pytest.mark.parametrize("volume, words", [
    (None, ["'reflectance'.volume", "'gridvolume'", "'constvolume'"]),
    ({"type": "cubevolume", "value": 0.5}, ["'cubevolume'", "'gridvolume'", "'constvolume'"]),
    ({"type": "constvolume", "value": [0.5, 0.2]}, ["'reflectance'.volume.value", "3 numbers"]),
    ({"type": "constvolume", "value": 0.5, "filename": "grid.vol"}, ["'filename'", "constvolume"]),
    ({"type": "constvolume", "to_world": np.diag([1, 1, 0, 1]).tolist()}, ["to_world", "invertible"]),
    ({"type": "gridvolume"}, ["needs a 'filename'"]),
    ({"type": "gridvolume", "filename": "grid.vol", "wrap": "clamp"}, ["'wrap'", "volume"]),
    ({"type": "gridvolume", "filename": "grid.vol", "wrap_mode": "tile"}, ["wrap_mode", "'tile'"]),
    ({"type": "gridvolume", "filename": "grid.vol", "filter_type": "cubic"}, ["filter_type", "trilinear"]),
    ({"type": "gridvolume", "filename": "grid.vol", "to_world": np.diag([1, 0, 1, 1]).tolist()},
     ["to_world", "invertible"]),
    ({"type": "gridvolume", "filename": "missing.vol"}, ["material 'm'", "'missing.vol'", "not found"]),
    ({"type": "gridvolume", "filename": "six.vol"}, ["six.vol", "6 channels"]),
    ({"type": "gridvolume", "filename": "short.vol"}, ["short.vol", "header says"]),
    ({"type": "gridvolume", "filename": "nan.vol"}, ["nan.vol", "1 values are not finite"]),
    ({"type": "gridvolume", "filename": "grid.vol", "use_grid_bbox": True}, ["empty bounding box"]),
])
def test_bad_volume_textures_are_refused(tmp_path, volume, words):
    """A volume texture's volume: its type; a constvolume's value, keys and transform; a
    gridvolume's keys, modes, transform and file (missing, other channel counts, truncated,
    non-finite values, an empty box used), each refused naming the material and what is
    wrong."""
    write_volume_grid(tmp_path / "grid.vol", np.ones((2, 2, 2, 1)), hi=(0, 0, 0))
    write_volume_grid(tmp_path / "six.vol", np.ones((2, 2, 2, 6)))
    (tmp_path / "short.vol").write_bytes((tmp_path / "grid.vol").read_bytes()[:-4])
    write_volume_grid(tmp_path / "nan.vol", np.array([np.nan, 1, 1, 1, 1, 1, 1, 1]).reshape(2, 2, 2, 1))
    texture = {"type": "volume", **({} if volume is None else {"volume": volume})}
    with pytest.raises(SceneError) as err:
        instancing.load_scene({"materials": {"m": {"type": "diffuse", "reflectance": texture}},
                               "instances": [{"model": "sphere", "material": "m"}]}, base_dir=tmp_path)
    for word in words:
        assert word in str(err.value), str(err.value)
