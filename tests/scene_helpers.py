"""Shared test fixtures: random affine instances, random rays, Mitsuba twins of our scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import instancing
from instancing.validation import reference
from instancing.core.backend import MITSUBA_VARIANT
from instancing.io.mesh_file import read_mesh

MESH_DIR = Path(__file__).resolve().parent.parent / "scenes" / "meshes"
KINDS = ["sphere", "cube", "rectangle", "disk", "cylinder", "mesh"]
#: The mesh used for the 'mesh' kind in tests.
MESH_FILE = MESH_DIR / "torus.obj"


def random_affine(rng: np.random.Generator, spread: float = 4.0, reflect: bool = False) -> np.ndarray:
    """A random invertible affine matrix: rotation, non-uniform scale, shear, translation."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    scale = np.diag(rng.uniform(0.3, 2.0, 3))
    shear = np.eye(3)
    shear[0, 1], shear[0, 2], shear[1, 2] = rng.uniform(-0.6, 0.6, 3)
    a = q @ shear @ scale
    if reflect != (np.linalg.det(a) < 0):
        a = a @ np.diag([-1.0, 1.0, 1.0])
    m = np.eye(4)
    m[:3, :3] = a
    m[:3, 3] = rng.uniform(-spread, spread, 3)
    return m


def float32_exact(x: np.ndarray) -> np.ndarray:
    """Round to float32 and back, so that both sides see exactly the same rays."""
    return np.asarray(x, np.float32).astype(np.float64)


def random_rays(rng: np.random.Generator, lo, hi, n: int):
    """Origins uniform in a box (many start inside shapes), isotropic unit directions."""
    o = rng.uniform(lo, hi, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float32_exact(o), float32_exact(d)


def write_curve_file(path: Path, curves: list[np.ndarray]) -> Path:
    """Mitsuba's curve file of ``curves`` ((n, 4) rows x, y, z, radius each) at ``path``."""
    path.write_text("\n\n".join("\n".join(" ".join(f"{v:.9g}" for v in row) for row in c) for c in curves) + "\n")
    return path


def instanced_curve_xml(path: Path, kind: str, curves: list[np.ndarray]) -> Path:
    """A Mitsuba scene file at ``path``: a ``kind`` curve of ``curves`` with its own to_world
    (points moved, radii kept) inside a shapegroup, instanced under a rotation and an uneven
    scale (which scales the radii too)."""
    curve_file = write_curve_file(path.parent / f"{path.stem}_curves.txt", curves)
    path.write_text(f'''<scene version="3.0.0">
        <shape type="shapegroup" id="hair"><shape type="{kind}">
            <string name="filename" value="{curve_file}"/>
            <transform name="to_world"><scale x="2" y="1" z="1"/><translate x="0.1" y="0" z="0"/></transform>
        </shape></shape>
        <shape type="instance"><ref id="hair"/>
            <transform name="to_world"><scale x="1" y="1.5" z="0.7"/><rotate x="0.6" y="0.8" z="0" angle="35"/>
                <translate x="0" y="0.3" z="-0.2"/></transform></shape></scene>''')
    return path


def rays_around(rng: np.random.Generator, centre, spread: float, n: int):
    """Rays from all around ``centre`` (origins 3 ``spread`` away), aimed within 0.6 ``spread``
    of it: unit float32-exact (o, d)."""
    o = centre + rng.normal(size=(n, 3)) * 3 * spread
    d = centre + rng.normal(size=(n, 3)) * 0.6 * spread - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float32_exact(o), float32_exact(d)


def as_array3f(x: np.ndarray):
    """(N, 3) NumPy rows as a Dr.Jit Array3f."""
    from instancing.core.backend import Array3f, Float
    return Array3f(*[Float(np.ascontiguousarray(x[:, k], np.float32)) for k in range(3)])


def scene_dict(kinds: list[str], matrices: list[np.ndarray]) -> dict:
    """Our scene: one instance per (kind, matrix)."""
    return {
        "models": {"torus": {"type": "obj", "filename": str(MESH_FILE)}},
        "instances": [{"model": "torus" if k == "mesh" else k, "to_world": m.tolist()}
                      for k, m in zip(kinds, matrices)],
    }


def reference_instances(kinds: list[str], matrices: list[np.ndarray], rounding=np.float64) -> list[dict]:
    """The same instances for instancing/reference.py, transforms and mesh vertices rounded
    to ``rounding`` (float32: the scene as the renderers store it)."""
    mesh = read_mesh(MESH_FILE)
    return reference.instance_list(kinds, matrices, (mesh.vertices, mesh.faces), rounding)


def mitsuba_instanced_scene(kinds: list[str], matrices: list[np.ndarray]):
    """Mitsuba twin: one shapegroup per kind, one ``instance`` per matrix."""
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    plugin = {"sphere": {"type": "sphere"}, "cube": {"type": "cube"},
              "rectangle": {"type": "rectangle"}, "disk": {"type": "disk"},
              "cylinder": {"type": "cylinder"},
              "mesh": {"type": "obj", "filename": str(MESH_FILE)}}
    scene = {"type": "scene"}
    for k in sorted(set(kinds)):
        scene[f"group_{k}"] = {"type": "shapegroup", "shape": plugin[k]}
    for i, (k, m) in enumerate(zip(kinds, matrices)):
        scene[f"inst_{i:05d}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": f"group_{k}"},
                                  "to_world": mi.ScalarTransform4f(m.tolist())}
    return mi, mi.load_dict(scene)


def mitsuba_intersect(kinds, matrices, o: np.ndarray, d: np.ndarray) -> dict:
    """Mitsuba's full ray_intersect on the instanced twin: t, n (NumPy), hit mask."""
    mi, scene = mitsuba_instanced_scene(kinds, matrices)
    ray = mi.Ray3f(mi.Point3f(*[np.ascontiguousarray(o[:, k], np.float32) for k in range(3)]),
                   mi.Vector3f(*[np.ascontiguousarray(d[:, k], np.float32) for k in range(3)]))
    si = scene.ray_intersect(ray)
    t = np.asarray(si.t, np.float64)
    return {"t": np.where(np.isfinite(t), t, np.inf), "n": np.asarray(si.n, np.float64).T,
            "p": np.asarray(si.p, np.float64).T}


def angle_deg(a: np.ndarray, b: np.ndarray, oriented: bool = True) -> np.ndarray:
    """Angle between vectors in degrees, via atan2(|a x b|, a.b) in float64 (exact near 0).

    ``oriented=False`` ignores the sign (for Mitsuba's mesh normals, which flip
    under reflections).
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    dot = np.sum(a * b, axis=1)
    dot = dot if oriented else np.abs(dot)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), dot))


def load(kinds, matrices, accel="auto") -> instancing.Scene:
    return instancing.load_scene(scene_dict(kinds, matrices), accel=accel)


def write_serialized(path: Path, meshes: list[dict], version: int = 4, double: bool = False) -> Path:
    """A serialized file as Mitsuba's format description defines it: per mesh a header
    (0x041C, version) and a zlib stream of flags, (v4) a name, counts, positions, optional
    normals, texture coordinates and colours, uint32 triangles; then the meshes' offsets
    (uint64 in v4, uint32 in v3) and their count."""
    import struct
    import zlib
    real = "<f8" if double else "<f4"
    blob, offsets = b"", []
    for k, mesh in enumerate(meshes):
        flags = (0x2000 if double else 0x1000) | (0x0001 if "normals" in mesh else 0) \
            | (0x0002 if "uvs" in mesh else 0) | (0x0008 if "colors" in mesh else 0)
        body = struct.pack("<I", flags)
        if version == 4:
            body += f"mesh{k}".encode() + b"\0"
        body += struct.pack("<QQ", len(mesh["vertices"]), len(mesh["faces"]))
        for key in ("vertices", "normals", "uvs", "colors"):
            if key in mesh:
                body += np.asarray(mesh[key], real).tobytes()
        body += np.asarray(mesh["faces"], "<u4").tobytes()
        offsets.append(len(blob))
        blob += struct.pack("<HH", 0x041C, version) + zlib.compress(body)
    table = np.array(offsets, "<u8" if version == 4 else "<u4").tobytes()
    path.write_bytes(blob + table + struct.pack("<I", len(meshes)))
    return path


def assert_textured_bsdf_is_mitsubas(table, bsdf, si, wi: np.ndarray, wo: np.ndarray, uv: np.ndarray,
                                     reach: float = 0.0, surface=None) -> None:
    """Our material table's row 0 against Mitsuba's ``bsdf`` on the surface interaction ``si``
    (shading frame the identity, its uv and wi set): f cos at the directions ``wi``, ``wo``
    (N, 3) and surface coordinates ``uv`` (2, N) to float32 round-off, and the densities where
    both directions lie on one side (Mitsuba's roughplastic and blend give their lobes'
    formulas on opposite sides, where f is 0). More than ``reach`` of Mitsuba's values are
    non-zero (the directions reach the lobe) and they vary. ``surface``: the derivatives a
    bump-mapped table reads (:class:`~instancing.materials.bump_map.SurfaceFrame`)."""
    from instancing.core.backend import Array2f, Array3f, Float, UInt32, mitsuba_module
    mi = mitsuba_module()
    vectors = [Array3f(*w.T.astype(np.float32)) for w in (wi, wo)]
    ours_f = np.asarray(table.evaluate(UInt32(0), *vectors, Array2f(*uv), surface), np.float64)
    ours_pdf = np.asarray(table.pdf(UInt32(0), *vectors, Array2f(*uv), surface), np.float64)
    wo_mi = mi.Vector3f(*[Float(wo[:, k].astype(np.float32)) for k in range(3)])
    theirs_f = np.asarray(bsdf.eval(mi.BSDFContext(), si, wo_mi), np.float64)
    theirs_pdf = np.asarray(bsdf.pdf(mi.BSDFContext(), si, wo_mi), np.float64)
    assert (theirs_f > 0).mean() > reach and np.std(theirs_f) > 0
    np.testing.assert_allclose(ours_f, theirs_f, rtol=1e-4, atol=1e-5 * np.abs(theirs_f).max())
    same_side = wi[:, 2] * wo[:, 2] > 0
    np.testing.assert_allclose(ours_pdf[same_side], theirs_pdf[same_side], rtol=1e-4,
                               atol=1e-5 * theirs_pdf.max())


class GivenNumbers:
    """A sampler stand-in that hands out given arrays in order."""

    def __init__(self, *arrays):
        self.arrays = list(arrays)

    def next_float32(self):
        return self.arrays.pop(0)

    def next_pair(self):
        """The next two arrays (as an IndependentSampler draws a pair)."""
        return self.next_float32(), self.next_float32()


def tilt_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    """n random unit directions, 85 % above the surface (z > 0) and the rest below (where
    a tilted frame may still see them)."""
    w = rng.normal(size=(n, 3))
    w[:, 2] = np.abs(w[:, 2]) * np.where(rng.random(n) < 0.85, 1.0, -1.0)
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def as_vectors(w: np.ndarray):
    """(N, 3) rows as a float32 Array3f."""
    from instancing.core.backend import Array3f
    return Array3f(*w.T.astype(np.float32))


def mitsuba_interaction(wi: np.ndarray, uv: np.ndarray, n=None, dpdu=None, dpdv=None):
    """Mitsuba's SurfaceInteraction3f with the identity shading frame, ``wi`` (N, 3), ``uv``
    (2, N) and optionally the geometric normal and dp/du, dp/dv ((N, 3) each; by default
    +z, +x and 0): (mi, si)."""
    from instancing.core.backend import Float, dr, mitsuba_module
    mi = mitsuba_module()
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.uv = mi.Point2f(Float(uv[0]), Float(uv[1]))
    si.wi = mi.Vector3f(*[Float(wi[:, k].astype(np.float32)) for k in range(3)])
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    rows = lambda v: [Float(v[:, k].astype(np.float32)) for k in range(3)]  # noqa: E731
    si.n = mi.Normal3f(0.0, 0.0, 1.0) if n is None else mi.Normal3f(*rows(n))
    si.dp_du = mi.Vector3f(1.0, 0.0, 0.0) if dpdu is None else mi.Vector3f(*rows(dpdu))
    if dpdv is not None:
        si.dp_dv = mi.Vector3f(*rows(dpdv))
    return mi, si


def assert_samples_are_mitsubas(table, bsdf, si, wi: np.ndarray, uv: np.ndarray,
                                rng: np.random.Generator, surface=None) -> tuple:
    """Samples of our table's row 0 at ``wi`` and ``uv`` (random numbers from ``rng``):
    their density is Mitsuba's ``pdf`` and their weight Mitsuba's f cos / pdf at the sampled
    direction, except delta samples (Mitsuba's pdf() is 0 there); invalid ones weigh 0.
    Returns (u, valid, delta, wo, weight) for further checks."""
    from instancing.core.backend import Array2f, Float, UInt32, mitsuba_module
    mi = mitsuba_module()
    u = rng.random((len(wi), 3)).astype(np.float32)
    numbers = [Float(u[:, k]) for k in range(3)] if table.chooses_lobe else [Float(u[:, 1]), Float(u[:, 2])]
    sample = table.sample(UInt32(0), as_vectors(wi), GivenNumbers(*numbers), Array2f(*uv), surface)
    valid = np.asarray(sample.valid)
    assert valid.mean() > 0.3
    wo = np.asarray(sample.wo, np.float64).T
    weight = np.asarray(sample.weight, np.float64).T
    delta = valid & np.broadcast_to(np.asarray(sample.delta), valid.shape)
    smooth = valid & ~delta
    ctx = mi.BSDFContext()
    wo_mi = mi.Vector3f(*[Float(wo[:, k].astype(np.float32)) for k in range(3)])
    f = np.asarray(bsdf.eval(ctx, si, wo_mi), np.float64).T
    pdf = np.asarray(bsdf.pdf(ctx, si, wo_mi), np.float64)
    np.testing.assert_allclose(np.asarray(sample.pdf)[smooth], pdf[smooth], rtol=1e-4, atol=1e-5)
    keep = smooth & (pdf > 1e-3)
    # (The weight is a ratio of two values each within 1e-4.)
    np.testing.assert_allclose(weight[keep], f[keep] / pdf[keep, None], rtol=2e-4, atol=1e-5)
    assert (weight[~valid] == 0).all()
    return u, valid, delta, wo, weight


def read_image_file(filename, raw):
    """What a scene's ``read_image`` gives: the texels of an image file and its name."""
    from instancing.io.image import read_texture
    return read_texture(filename, raw), filename


def with_textures(spec, key: str, textures: dict):
    """A material dict with each value under ``key`` (at any depth) replaced by
    ``textures[value]`` (a texture dict named in the test)."""
    if isinstance(spec, dict):
        return {k: (textures[v] if k == key else with_textures(v, key, textures)) for k, v in spec.items()}
    return spec


def assert_same_bsdf_values(table, plain, rng: np.random.Generator, surface=None) -> None:
    """Row 0 of ``table`` (a map that changes nothing) gives ``plain``'s f cos and densities
    at random directions and uv."""
    from instancing.core.backend import Array2f, UInt32
    n = 4096
    wi, wo = as_vectors(tilt_directions(rng, n)), as_vectors(tilt_directions(rng, n))
    uv = Array2f(*rng.uniform(size=(2, n)).astype(np.float32))
    for method in ("evaluate", "pdf"):
        np.testing.assert_allclose(np.asarray(getattr(table, method)(UInt32(0), wi, wo, uv, surface)),
                                   np.asarray(getattr(plain, method)(UInt32(0), wi, wo, uv)),
                                   rtol=1e-6, atol=1e-7)


def mirror_corner(reflectance: float, integrator: dict | None = None) -> dict:
    """Two mirrors meeting at a right angle under a constant sky of radiance 1, filling the
    view: each camera path is exactly two delta bounces and an escape (a dihedral corner
    turns a ray back out), radiance ``reflectance``^2 wherever no Russian roulette stops it."""
    mirror = {"model": "rectangle", "material": "mirror"}
    scene = {"materials": {"mirror": {"type": "conductor", "specular_reflectance": reflectance}},
             "instances": [
                 {**mirror, "to_world": [{"translate": [0, 50, 0]}, {"scale": 50}]},
                 {**mirror, "to_world": [{"translate": [0, 0, 50]},
                                         {"rotate": {"axis": [1, 0, 0], "angle": -90}}, {"scale": 50}]}],
             "lights": [{"type": "constant", "radiance": 1.0}],
             "camera": {"type": "perspective", "fov": 30, "width": 16, "height": 12, "to_world": [
                 {"look_at": {"origin": [0, 3, 3], "target": [0, 0, 0], "up": [0, 0, 1]}}]}}
    return scene if integrator is None else {**scene, "integrator": integrator}


def assert_roulette_closed_form(image, spp: int, reflectance: float, integrator: str, rr_depth: int):
    """An image of :func:`mirror_corner` against Mitsuba's Russian roulette in closed form:
    its path may stop a path after bounce k >= rr_depth, its volpath after k > rr_depth,
    with probability 1 - q, q the throughput's largest channel reweighted by the earlier
    survivals, at most 0.95. A path survives with probability P (the product of its q) and
    then carries reflectance^2 / P: each pixel is a whole number of survivors times that
    over spp, P of them on average (within 5 binomial standard errors), and with P = 1
    exactly reflectance^2."""
    survive, beta = 1.0, 1.0
    for bounce in (1, 2):
        beta *= reflectance
        if bounce >= rr_depth + (integrator == "volpath"):
            q = min(beta, 0.95)
            survive, beta = survive * q, beta / q
    image = np.asarray(image, np.float64)[..., 0]
    if survive == 1:
        np.testing.assert_allclose(image, reflectance ** 2, rtol=1e-5)
        return
    survivors = image * spp * survive / reflectance ** 2
    np.testing.assert_allclose(survivors, np.round(survivors), atol=1e-3)
    fraction = survivors.mean() / spp
    assert abs(fraction - survive) < 5 * np.sqrt(survive * (1 - survive) / image.size / spp), (
        rr_depth, fraction, survive)


def lamp_and_floor_scene(models: dict, materials: dict, instance: dict, camera_origin) -> instancing.Scene:
    """``instance`` (of one of ``models``) over a grey floor, lit by a disk lamp, seen by a
    64x48 camera from ``camera_origin``."""
    return instancing.load_scene({
        "models": models, "materials": {"grey": {"type": "diffuse", "reflectance": 0.6}, **materials},
        "instances": [{"model": "rectangle", "material": "grey", "to_world": [{"scale": [5, 5, 1]}]},
                      instance,
                      {"model": "disk", "material": "grey", "emitter": {"type": "area", "radiance": 8},
                       "to_world": [{"translate": [1, -1, 4]}, {"reflect": "z"}]}],
        "camera": {"type": "perspective", "fov": 40, "width": 64, "height": 48, "to_world": [
            {"look_at": {"origin": list(camera_origin), "target": [0, 0, 0.5], "up": [0, 0, 1]}}]}})


def assert_path_render_matches_mitsuba(scene: instancing.Scene, spp: int = 512) -> None:
    """Our `path` render of a 64x48 scene against Mitsuba's of the export at the same spp:
    image mean within 0.5 %, 8x8-pixel block means within 1.5 % of it (as
    tests/test_mitsuba_render.py)."""
    import mitsuba as mi
    ours = np.asarray(instancing.render(scene, "path", spp=spp, seed=3))
    mi.set_variant(MITSUBA_VARIANT)
    theirs = np.asarray(mi.render(mi.load_dict(instancing.to_mitsuba(scene, spp=spp)),
                                  integrator=mi.load_dict({"type": "path", "max_depth": -1}),
                                  spp=spp, seed=3))
    scale = theirs.mean()
    blocks = lambda img: img.reshape(6, 8, 8, 8, 3).mean(axis=(1, 3))  # noqa: E731
    assert abs(ours.mean() / scale - 1) < 0.005
    assert np.sqrt(np.mean((blocks(ours) - blocks(theirs)) ** 2)) / scale < 0.015


def turned_about_z(angle: float, tx: float, base: np.ndarray) -> np.ndarray:
    """translate(tx, 0.1, 0) @ rotate_z(angle degrees) @ base (float64)."""
    a = np.radians(angle)
    m = np.eye(4)
    m[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    m[:3, 3] = [tx, 0.1, 0.0]
    return m @ base


def assert_hit_derivatives_match(scene: instancing.Scene, base: np.ndarray, which: str, o: np.ndarray,
                                 d: np.ndarray, reference_hits, least: int) -> None:
    """d t / d param and d p / d param of the hits of rays (o, d) on the scene's one instance,
    placed by :func:`turned_about_z` (angle 20, tx 0.3) with ``which`` ('tx' or 'angle')
    tracked, against central differences (step 1e-4) of ``reference_hits(to_world)`` (the
    float64 reference's record of the same rays); rays whose two sides hit different
    primitives or jump (a silhouette) are left out, and at least ``least`` remain."""
    from instancing.core.backend import Array3f, Float, dr
    angle, tx = Float(20.0), Float(0.3)
    param = tx if which == "tx" else angle
    dr.enable_grad(param)
    scene.set_transforms(instancing.translate(Array3f(tx, 0.1, 0.0)) @ instancing.rotate_z(angle)
                         @ instancing.from_matrix(base))
    rays = [Array3f(*[Float(np.ascontiguousarray(x[:, k], np.float32)) for k in range(3)]) for x in (o, d)]
    hit = scene.intersect(*rays)
    dr.forward(param)
    grad_t, grad_p = np.asarray(dr.grad(hit.t)), np.asarray(dr.grad(hit.p)).T
    h = 1e-4
    step = (0.0, h) if which == "tx" else (h, 0.0)
    refs = [reference_hits(turned_about_z(20.0 + s * step[0], 0.3 + s * step[1], base)) for s in (1, -1)]
    ok = np.isfinite(refs[0]["t"]) & np.isfinite(refs[1]["t"]) & np.isfinite(np.asarray(hit.t))
    with np.errstate(invalid="ignore"):  # misses give inf - inf on rays excluded by ok
        ok &= (refs[0]["prim"] == refs[1]["prim"]) & (np.abs(refs[0]["t"] - refs[1]["t"]) < 100 * h)
        fd_t = (refs[0]["t"] - refs[1]["t"]) / (2 * h)
        fd_p = (refs[0]["p"] - refs[1]["p"]) / (2 * h)
    assert ok.sum() > least
    np.testing.assert_allclose(grad_t[ok], fd_t[ok], rtol=2e-3, atol=2e-3)
    np.testing.assert_allclose(grad_p[ok], fd_p[ok], rtol=2e-3, atol=2e-3)


def assert_boundary_terms_refused(model: tuple[str, dict], to_world, camera_target) -> None:
    """A scene of one instance 'moved' of ``model`` (name, spec) under a point light, its
    transform tracked: a render asking for boundary terms (sppp, sppi) is refused naming
    the model, one with the interior terms alone warns and gives finite, nonzero gradients."""
    import pytest
    from instancing.core.backend import dr
    name, spec = model
    scene = instancing.load_scene({
        "models": {name: spec}, "instances": [{"id": "moved", "model": name, "to_world": to_world}],
        "lights": [{"type": "point", "position": [0, -3, 4], "intensity": 20}],
        "camera": {"type": "perspective", "fov": 40, "width": 16, "height": 12, "to_world": [
            {"look_at": {"origin": [1, -4, 3], "target": list(camera_target), "up": [0, 0, 1]}}]}})
    params = instancing.traverse(scene)
    dr.enable_grad(params["moved.to_world"])
    params.update()
    with pytest.raises(instancing.SceneError, match=f"{spec['type']} model {name!r}.*sppp=0 and sppi=0"):
        instancing.render(scene, "direct", spp=4, sppp=4, sppi=4)
    with pytest.warns(UserWarning, match="leave out"):
        image = instancing.render(scene, "direct", spp=4, sppp=0, sppi=0)
    dr.backward(dr.mean(image.array))
    grad = np.asarray(dr.grad(params["moved.to_world"]))
    assert np.isfinite(grad).all() and np.abs(grad).max() > 0


def sliver_sphere(path: Path, bands: int = 8, segments: int = 256) -> Path:
    """An OBJ of a closed convex polyhedron of slivers, all corners on the unit sphere
    (float32-exact): ``bands`` latitude bands of ``segments`` triangles up and down, each ring
    turned half a segment from the last so that neighbours fold outward by far more than
    float32 rounding, the polar bands fans; faces wound outward. Triangles long along the
    meridians and slanted, whose boxes are mostly empty (the case for split references)."""
    theta = np.linspace(0.0, np.pi, bands + 1)[1:-1, None]
    phi = 2 * np.pi * (np.arange(segments)[None, :] + 0.5 * np.arange(bands - 1)[:, None]) / segments
    ring = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                     np.cos(theta) + 0 * phi], -1).reshape(-1, 3)
    vertices = float32_exact(np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]]))
    j = np.arange(segments)
    k = (j + 1) % segments
    faces = [np.stack([np.zeros(segments, int), 1 + j, 1 + k], 1)]
    for b in range(bands - 2):
        a0, a1 = 1 + b * segments, 1 + (b + 1) * segments
        faces += [np.stack([a0 + j, a1 + j, a0 + k], 1), np.stack([a1 + j, a1 + k, a0 + k], 1)]
    last = 1 + (bands - 2) * segments
    faces.append(np.stack([last + j, np.full(segments, len(vertices) - 1), last + k], 1))
    faces = np.concatenate(faces)
    v = vertices[faces]
    inward = np.sum(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]) * v.mean(axis=1), axis=1) < 0
    faces[inward] = faces[inward][:, ::-1]
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
    path.write_text("\n".join(lines) + "\n")
    return path
