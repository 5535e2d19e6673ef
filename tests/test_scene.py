"""The scene (instancing/scene/scene.py): every acceleration choice against brute force,
the stored transforms, camera/reflectance setters, bounds, discontinuity curves seen from
a world point, and the shadow-ray query against the nearest-hit query."""

import numpy as np
import pytest

import instancing
from instancing.core.backend import Array3f, Float, device_arrays, dr
from instancing.core import transform as tf
from instancing.models.analytic import ANALYTIC_MODELS
from scene_helpers import KINDS, MESH_FILE, load, random_affine, random_rays

N_INSTANCES = 12
CAMERA = {"type": "perspective", "fov": 40, "width": 16, "height": 12,
          "to_world": [{"look_at": {"origin": [0, -9, 3], "target": [0, 0, 0], "up": [0, 0, 1]}}]}


def _random_scene(seed: int, accel: str = "brute", n: int = N_INSTANCES):
    rng = np.random.default_rng(seed)
    kinds = [KINDS[i % len(KINDS)] for i in range(n)]
    matrices = [random_affine(rng, 4.0, reflect=i % 4 == 3) for i in range(n)]
    return rng, kinds, np.stack(matrices), load(kinds, matrices, accel=accel)


def _vectors(x: np.ndarray) -> Array3f:
    # In Dr.Jit's own (aligned) storage: kernels reading wrapped NumPy buffers are compiled
    # for the buffers' alignment, so each call could compile anew (backend.device_array).
    return Array3f(*device_arrays(Float, *[x[:, k].astype(np.float32) for k in range(3)]))


@pytest.fixture(scope="module")
def brute():
    """A random 12-instance scene (all six kinds, some reflected) on brute force, with
    random rays and their brute-force hits."""
    rng, kinds, matrices, scene = _random_scene(0)
    o, d = random_rays(rng, *scene.bounds, 20_000)
    return kinds, matrices, o, d, scene.intersect(o, d)


@pytest.mark.parametrize("accel", ["grid", "bvh", "unrolled"])
def test_intersect_with_every_acceleration_equals_brute_force(brute, accel):
    """Phase 1 finds the same nearest instance whatever walks the instances, and phase 2
    re-intersects only that instance: every field is bit-identical."""
    kinds, matrices, o, d, expected = brute
    scene = load(kinds, list(matrices), accel=accel)
    assert scene.accel == accel
    hits = scene.intersect(o, d)
    assert 0.1 < np.isfinite(expected.t).mean() < 0.95  # both hits and misses
    for field in ("t", "p", "n", "instance", "prim"):
        np.testing.assert_array_equal(getattr(hits, field), getattr(expected, field), err_msg=field)


def test_hits_are_misses_or_points_on_the_ray_with_unit_normals(brute):
    _, _, o, d, hits = brute
    miss = ~np.isfinite(hits.t)
    assert (hits.instance[miss] == -1).all() and (hits.prim[miss] == -1).all()
    assert (hits.instance[~miss] >= 0).all() and (hits.t[~miss] > 0).all()
    hit = ~miss
    t = hits.t[hit].astype(np.float64)
    # float32 world points: within a few float32 ulps of the scene's coordinates (|x| < ~20).
    np.testing.assert_allclose(hits.p[hit], o[hit] + t[:, None] * d[hit], atol=2e-5)
    np.testing.assert_allclose(np.linalg.norm(hits.n[hit], axis=1), 1.0, atol=1e-6)


@pytest.mark.parametrize("offset", [0.0, 1e6 + 0.37])
def test_to_world_is_the_float32_rounding_of_the_input_in_rendering_space(brute, offset):
    """Stored: the input moved to the rendering space (by -origin, in float64) and rounded
    to float32; handed back: that plus the origin, in float64. Near the world origin the
    origin stays 0; far from it, it is within a few extents of the scene's centre."""
    kinds, matrices, _, _, _ = brute
    matrices = matrices.copy()
    matrices[:, :3, 3] += offset
    scene = load(kinds, list(matrices))
    origin = scene.origin
    t = matrices[:, :3, 3]
    centre, extent = 0.5 * (t.min(axis=0) + t.max(axis=0)), np.ptp(t, axis=0).max()
    if offset == 0.0:
        assert (origin == 0).all()
    else:
        assert np.abs(origin - centre).max() < 4 * extent and (origin != 0).all()
    moved = matrices.copy()
    moved[:, :3, 3] -= origin
    expected = moved.astype(np.float32).astype(np.float64)
    expected[:, :3, 3] += origin
    np.testing.assert_array_equal(scene.to_world, expected)
    np.testing.assert_array_equal(scene.from_world[:, :3, :3],
                                  np.linalg.inv(matrices)[:, :3, :3].astype(np.float32).astype(np.float64))


def test_set_camera_accepts_cameras_and_none_and_rejects_anything_else():
    scene = instancing.load_scene({"instances": [{"model": "sphere"}]})
    assert scene.camera is None
    camera = instancing.parse_camera(CAMERA)
    scene.set_camera(camera)
    assert scene.camera is camera
    for wrong in (CAMERA, "perspective", camera.world_from_camera):
        with pytest.raises(instancing.SceneError, match="expected a Camera"):
            scene.set_camera(wrong)
    assert scene.camera is camera
    scene.set_camera(None)
    assert scene.camera is None


def test_set_reflectance_needs_one_lane_per_material_and_feeds_albedo():
    scene = instancing.load_scene({
        "materials": {"a": {"type": "diffuse", "reflectance": [0.1, 0.2, 0.3]},
                      "b": {"type": "diffuse", "reflectance": 0.9}},
        "instances": [{"model": "sphere", "material": "a", "to_world": [{"translate": [-2, 0, 0]}]},
                      {"model": "sphere", "material": "b", "to_world": [{"translate": [2, 0, 0]}]}],
    })
    # (The default material is always defined, last.)
    assert scene.material_names == ["a", "b", "default"]
    for lanes in (1, 2, 4):
        with pytest.raises(instancing.SceneError, match="expected 3 lanes"):
            scene.set_reflectance(Array3f(Float(np.full(lanes, 0.5, np.float32)), 0.5, 0.5))
    new = np.array([[0.7, 0.6, 0.5], [0.05, 0.15, 0.25], [1.0, 1.0, 1.0]], np.float32)
    scene.set_reflectance(_vectors(new))
    o = np.array([[-2, -5, 0], [2, -5, 0], [0, -5, 0]], np.float64)
    d = np.tile([0, 1.0, 0], (3, 1))
    hit = scene.intersect(_vectors(o), _vectors(d))  # albedo(hit) reads it once
    albedo = np.asarray(scene.albedo(hit)).T
    np.testing.assert_array_equal(albedo, np.array([new[0], new[1], [0, 0, 0]], np.float32))


def test_bounds_are_the_union_of_the_instance_boxes_and_boxes_are_exact_for_quadrics(brute):
    """At load the scene box is the union of instance_bounds (both bound the stored float32
    transforms); analytic instances' boxes are their models' exact world bounds under the
    stored matrices (closed form for spheres)."""
    kinds, matrices, _, _, _ = brute
    scene = load(kinds, list(matrices))
    lo, hi = scene.bounds
    box_lo, box_hi = scene.instance_bounds(np.arange(N_INSTANCES))
    assert (box_lo >= lo).all() and (box_hi <= hi).all()
    np.testing.assert_array_equal(lo, box_lo.min(0))
    np.testing.assert_array_equal(hi, box_hi.max(0))
    for kind in ANALYTIC_MODELS:
        which = np.flatnonzero(np.array(kinds) == kind)
        ref_lo, ref_hi = ANALYTIC_MODELS[kind].world_bounds(scene.to_world[which])
        np.testing.assert_array_equal(box_lo[which], ref_lo)
        np.testing.assert_array_equal(box_hi[which], ref_hi)
    spheres = np.flatnonzero(np.array(kinds) == "sphere")
    m = scene.to_world[spheres]
    radius = np.linalg.norm(m[:, :3, :3], axis=2)
    np.testing.assert_allclose(box_lo[spheres], m[:, :3, 3] - radius, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(box_hi[spheres], m[:, :3, 3] + radius, rtol=1e-14, atol=1e-14)


def test_discontinuity_curves_belong_to_the_given_instances_and_are_tangent_in_world_space(brute):
    """Curves of the listed instances only; for spheres (a silhouette from every point
    outside them) each world curve point X = M x has a world normal A^-T x perpendicular
    to X - viewpoint: the tangency survives the affine map."""
    kinds, matrices, _, _, _ = brute
    scene = load(kinds, list(matrices))
    viewpoint = np.array([0.3, -25.0, 7.0])
    chosen = np.array([0, 1, 2, 5, 6, 9, 10])
    curves = scene.discontinuity_curves(viewpoint, chosen)
    assert len(curves) > 0
    assert set(curves.instance) <= set(chosen)
    assert set(curves.instance) == set(chosen)  # every one of these kinds shows a curve from far
    empty = scene.discontinuity_curves(viewpoint, np.zeros(0, np.int64))
    assert len(empty) == 0
    spheres = np.flatnonzero(np.array(kinds)[curves.instance] == "sphere")
    assert len(spheres) == np.sum(np.array(kinds)[chosen] == "sphere") > 0
    s = np.linspace(0, 1, 17)[:-1]
    x = curves.points(s)[spheres]
    m = scene.to_world[curves.instance[spheres]]
    world = np.einsum("kij,ksj->ksi", m[:, :3, :3], x) + m[:, None, :3, 3]
    normal = np.einsum("kji,ksj->ksi", scene.from_world[curves.instance[spheres]][:, :3, :3], x)
    cosine = np.sum(normal * (world - viewpoint), 2) / (
        np.linalg.norm(normal, axis=2) * np.linalg.norm(world - viewpoint, axis=2))
    # float64 throughout; from_world is the stored float32 inverse, not the exact inverse
    # of the stored forward matrix (about 1e-7 relative, times the condition number).
    np.testing.assert_allclose(cosine, 0.0, atol=1e-5)


def test_discontinuity_curves_seen_from_infinity_are_tangent_to_the_view_direction(brute):
    """A homogeneous viewpoint (direction, 0), as a directional light sees the scene: every
    sphere instance shows one curve, whose world points X = M x have world normals
    A^-T x perpendicular to the direction."""
    kinds, matrices, _, _, _ = brute
    scene = load(kinds, list(matrices))
    direction = np.array([0.3, -0.8, 0.52])
    spheres = np.flatnonzero(np.array(kinds) == "sphere")
    curves = scene.discontinuity_curves(np.append(direction, 0.0), spheres)
    np.testing.assert_array_equal(np.sort(curves.instance), spheres)
    x = curves.points(np.linspace(0, 1, 17)[:-1])
    normal = np.einsum("kji,ksj->ksi", scene.from_world[curves.instance][:, :3, :3], x)
    cosine = normal @ direction / (np.linalg.norm(normal, axis=2) * np.linalg.norm(direction))
    # The curve (from A^-1 direction) and the normal use the same stored inverse: exact up
    # to float64 rounding.
    np.testing.assert_allclose(cosine, 0.0, atol=1e-12)


@pytest.mark.parametrize("accel", ["brute", "grid", "bvh", "unrolled"])
def test_occluded_agrees_with_the_nearest_hit_closer_than_t_max(brute, accel):
    kinds, matrices, o, d, expected = brute
    scene = load(kinds, list(matrices), accel=accel)
    rng = np.random.default_rng(9)
    t_max = rng.uniform(0, 20, len(o)).astype(np.float32)
    t_max[::7] = np.inf
    blocked = np.asarray(scene.occluded(_vectors(o), _vectors(d), Float(t_max)))
    nearest = expected.t.astype(np.float64)
    # Rays whose nearest hit is within float32 rounding of t_max may go either way.
    with np.errstate(invalid="ignore"):  # inf - inf where both are infinite
        clear = np.abs(nearest - t_max) > 1e-5 * np.maximum(1.0, t_max)
    clear[~np.isfinite(t_max)] = True
    assert clear.mean() > 0.999
    assert 0.1 < blocked.mean() < 0.9
    np.testing.assert_array_equal(blocked[clear], (nearest < t_max)[clear])


@pytest.mark.parametrize("accel", ["grid", "bvh", "unrolled"])
def test_moved_instances_are_hit_as_by_brute_force_on_the_same_stored_transforms(accel):
    """set_transforms(..., changed=...) updates the grid in place, refits the BVH or takes
    new boxes and rows for the unrolled tests (opaque scalars read from the table); the
    hits then equal brute force over the same stored matrices (set_accel('brute'))."""
    rng, kinds, matrices, scene = _random_scene(1, accel)
    changed = np.array([3, 10])  # a few: updated in place (more than N/4 rebuild)
    new = np.stack([random_affine(rng, 6.0) for _ in changed])
    new[:, :3, 3] = matrices[changed, :3, 3] + rng.uniform(-1, 1, (len(changed), 3))
    scene.set_transforms(tf.from_matrix(tf.matrices_to_lanes(new)), matrices=new, changed=changed)
    np.testing.assert_array_equal(scene.to_world[changed], new.astype(np.float32).astype(np.float64))
    o, d = random_rays(rng, *scene.bounds, 20_000)
    hits = scene.intersect(o, d)
    scene.set_accel("brute")
    expected = scene.intersect(o, d)
    assert np.isin(expected.instance, changed).sum() > 100
    np.testing.assert_array_equal(hits.t, expected.t)
    np.testing.assert_array_equal(hits.instance, expected.instance)


def test_bad_inputs_are_rejected():
    scene = instancing.load_scene({"instances": [{"model": "sphere"}]})
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        scene.intersect(np.zeros((4, 3)), np.zeros((3, 3)))
    with pytest.raises(instancing.SceneError, match="unknown acceleration"):
        scene.set_accel("octree")


@pytest.mark.parametrize("o, d, words", [
    # Float64 rays that float32, as traced, cannot hold: an origin beyond its range, a
    # direction whose components all round to 0 (they came back as misses).
    ([[1e300, 0.0, 0.0]], [[1.0, 0.0, 0.0]], ["ray 0", "1e+300", "float32"]),
    ([[0.0, 0.0, -5.0]], [[1e-50, 1e-50, 1e-50]], ["ray 0", "1e-50", "float32"]),
    (None, None, ["arrays of numbers"]),
    ([["a", "b", "c"]], [["a", "b", "c"]], ["arrays of numbers"]),
    (Array3f(0.0, 0.0, -5.0), np.array([[0.0, 0.0, 1.0]]), ["both Dr.Jit arrays or both NumPy"]),
    (Array3f([0.0] * 2, [0.0] * 2, [-5.0] * 2), Array3f([0.0] * 3, [0.0] * 3, [1.0] * 3), ["2 and 3"])])
def test_rays_that_cannot_be_traced_are_refused_naming_them(o, d, words):
    scene = instancing.load_scene({"instances": [{"model": "sphere"}]})
    with pytest.raises((ValueError, TypeError)) as err:
        scene.intersect(np.asarray(o) if isinstance(o, list) else o, np.asarray(d) if isinstance(d, list) else d)
    for word in words:
        assert word in str(err.value), (word, str(err.value))


def test_a_direction_of_one_lane_serves_every_origin():
    scene = instancing.load_scene({"instances": [{"model": "sphere"}]})
    hits = scene.intersect(Array3f([0.0, 0.5], [0.0, 0.0], [-5.0, -5.0]), Array3f(0.0, 0.0, 1.0))
    np.testing.assert_allclose(np.asarray(hits.t), [4.0, 5.0 - np.sqrt(0.75)], rtol=1e-6)


@pytest.mark.parametrize("changed, words", [
    ([2], (IndexError, "changed holds 2, outside [0, 2)")),
    ([-1], (IndexError, "changed holds -1")),
    ([0, 0], (IndexError, "holds 0 more than once")),
    ([0.5], (TypeError, "changed must be integer indices"))])
def test_changed_instances_outside_the_scene_are_refused_before_anything_is_written(changed, words):
    """(An index outside the table was written past its end: the process aborted later.)"""
    scene = instancing.load_scene({"instances": [{"model": "sphere"}, {"model": "sphere",
                                                                       "to_world": [{"translate": [3, 0, 0]}]}]})
    before = scene.to_world.copy()
    m = np.tile(np.eye(4), (len(changed), 1, 1))
    with pytest.raises(words[0]) as err:
        scene.set_transforms(tf.from_matrix(tf.matrices_to_lanes(m)), matrices=m, changed=changed)
    assert words[1] in str(err.value)
    np.testing.assert_array_equal(scene.to_world, before)
    hits = scene.intersect(np.array([[0.0, 0.0, -5.0], [3.0, 0.0, -5.0]]), np.array([[0.0, 0.0, 1.0]] * 2))
    np.testing.assert_array_equal(hits.instance, [0, 1])


def test_transform_lanes_and_matrices_must_match_the_instances_they_set():
    scene = instancing.load_scene({"instances": [{"model": "sphere"}] * 3})
    three = np.tile(np.eye(4), (3, 1, 1))
    with pytest.raises(ValueError, match="2 lanes for 3 instances"):
        scene.set_transforms(tf.from_matrix(tf.matrices_to_lanes(three[:2])))
    with pytest.raises(ValueError, match=r"matrices has shape \(2, 4, 4\), expected \(3, 4, 4\)"):
        scene.set_transforms(tf.from_matrix(tf.matrices_to_lanes(three)), matrices=three[:2])
    with pytest.raises(ValueError, match="3 lanes for 2 changed instances"):
        scene.set_transforms(tf.from_matrix(tf.matrices_to_lanes(three)), matrices=three[:2], changed=[0, 1])
    with pytest.raises(IndexError, match="moving holds 5"):
        scene.set_transforms(tf.from_matrix(tf.matrices_to_lanes(three)), matrices=three, moving=[5])
    # One lane and one matrix for all, or for the changed ones.
    scene.set_transforms(tf.translate([1.0, 0.0, 0.0]), matrices=tf.translate([1.0, 0.0, 0.0]).to_numpy()[0])
    scene.set_transforms(tf.translate([2.0, 0.0, 0.0]), matrices=tf.translate([2.0, 0.0, 0.0]).to_numpy()[0],
                         changed=[0, 2])
    np.testing.assert_array_equal(scene.to_world[:, 0, 3], [2.0, 1.0, 2.0])


def test_instances_are_indexed_within_the_scene():
    scene = instancing.load_scene({"instances": [{"model": "sphere", "to_world": [{"translate": [k, 0, 0]}]}
                                                 for k in range(3)]})
    np.testing.assert_array_equal(scene.to_world_of([-1, 0])[:, 0, 3], [2.0, 0.0])
    for bad, error in ((3, IndexError), (-4, IndexError), (0.9, TypeError), ("ball", TypeError)):
        with pytest.raises(error, match="to_world_of: instances"):
            scene.to_world_of(bad)
    with pytest.raises(IndexError, match="instance_bounds: instances holds 3"):
        scene.instance_bounds([3])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_no_rays_give_empty_hits_of_the_usual_types(dtype):
    """(0, 3) ray arrays once failed inside Dr.Jit (operands of sizes 1 and 0)."""
    scene = _random_scene(2)[3]
    rng = np.random.default_rng(5)
    o, d = (a.astype(dtype) for a in random_rays(rng, *scene.bounds, 3))
    empty, some = scene.intersect(o[:0], d[:0]), scene.intersect(o, d)
    for field in ("t", "p", "n", "instance", "prim"):
        got, usual = getattr(empty, field), getattr(some, field)
        assert got.dtype == usual.dtype and got.shape == (0,) + usual.shape[1:], field


@pytest.mark.parametrize("value", [np.tile(np.eye(4), (N_INSTANCES, 1, 1)), np.eye(4).tolist(), None])
def test_set_transforms_names_the_transform_it_takes(value):
    """The docs promise a Transform (per lane or one for all); NumPy matrices and lists are
    refused saying how to make one, and the scene keeps its transforms."""
    scene = _random_scene(3)[3]
    before = scene.to_world
    with pytest.raises(TypeError) as err:
        scene.set_transforms(value)
    message = str(err.value)
    assert "set_transforms: world_from_object must be an instancing.Transform" in message
    assert type(value).__name__ in message and "matrices_to_lanes" in message
    np.testing.assert_array_equal(scene.to_world, before)


def test_unrolled_instances_keep_a_grazing_hit_on_the_stored_surface():
    """The unrolled structure's world boxes bound the stored float32 transforms, not the
    input's float64 ones, which bound a surface short by a rounding: this grazing ray hits
    the stored cube and sphere (brute force), and 'unrolled' (auto's pick on LLVM) must find it too."""
    m = [[0.26474916059722137, -0.9780268280270532, 0.25505023252135767, 1.2516918689268852],
         [-0.6350346206198311, 0.27021694948672864, -0.40429265410810744, 7.310978383038654],
         [1.0100505098849304, -0.7117269482455743, -0.36763268308073177, -1.674945290887651],
         [0, 0, 0, 1]]
    o = np.array([[0.20685730874538422, -12.176482200622559, -2.507357597351074]], np.float32)
    d = np.array([[0.0, 1.0, 0.0]], np.float32)
    for kind in ("sphere", "cube"):
        description = {"instances": [{"model": kind, "to_world": m}]}
        unrolled = instancing.load_scene(description, accel="unrolled")  # auto's pick on LLVM
        t = unrolled.intersect(o, d).t
        assert np.isfinite(t).all(), kind
        np.testing.assert_array_equal(t, instancing.load_scene(description, accel="brute").intersect(o, d).t)



def test_set_camera_replaces_one_view_by_index_or_id_and_keeps_its_name():
    scene = instancing.load_scene({"instances": [{"model": "sphere"}],
                                   "cameras": [CAMERA, {**CAMERA, "id": "top"}]})
    other = instancing.parse_camera({**CAMERA, "fov": 20})
    scene.set_camera(other, "top")
    assert scene.cameras[1].fov == 20 and scene.cameras[1].id == "top"
    assert scene.cameras[0].fov == 40
    scene.set_camera(other, 0)
    assert scene.camera.fov == 20 and scene.camera.id == ""
    with pytest.raises(instancing.SceneError, match="camera 'side': no such camera"):
        scene.set_camera(other, "side")


def test_numpy_and_drjit_rays_get_the_same_hits_in_a_scene_with_meshes():
    rng = np.random.default_rng(31)
    matrices = np.stack([random_affine(rng) for _ in range(5)])
    scene = instancing.load_scene({"models": {"torus": {"type": "obj", "filename": str(MESH_FILE)}},
                                   "instances": [{"model": "torus", "to_world": matrices},
                                                 {"model": "sphere"}]})
    # NumPy rays come back evaluated; a Dr.Jit record is evaluated by the caller.
    o, d = random_rays(rng, *scene.bounds, 4096)
    hits = scene.intersect(o, d)
    assert np.isfinite(hits.t).mean() > 0.1 and (hits.prim > 0).any()
    record = scene.intersect(Array3f(*o.T.astype(np.float32)), Array3f(*d.T.astype(np.float32)))
    dr.eval(record.t, record.instance, record.prim)
    np.testing.assert_array_equal(hits.t, np.asarray(record.t))
    np.testing.assert_array_equal(hits.instance, np.asarray(record.instance).astype(np.int32))
    np.testing.assert_array_equal(hits.prim, np.asarray(record.prim))


def test_mesh_scenes_walk_the_grid_in_passes_with_the_same_hits():
    from instancing.scene.intersection import reintersect
    from instancing.scene.scene import PASSES_MIN_RAYS
    rng = np.random.default_rng(32)
    matrices = np.stack([random_affine(rng) for _ in range(20)])
    scene = instancing.load_scene({"models": {"torus": {"type": "obj", "filename": str(MESH_FILE)}},
                                   "instances": [{"model": "torus", "to_world": matrices}]},
                                  accel="grid")
    o, d = random_rays(rng, *scene.bounds, PASSES_MIN_RAYS)
    passes = scene.intersect(o, d)  # in passes
    # Phase 1 in one loop, no passes, and its record.
    jo, jd = Array3f(*(o - scene.origin).T.astype(np.float32)), Array3f(*d.T.astype(np.float32))
    loop = reintersect(scene.instances, jo, jd, scene.intersect_preliminary(jo, jd))
    dr.eval(loop.t, loop.instance, loop.prim)
    assert np.isfinite(passes.t).mean() > 0.1
    np.testing.assert_array_equal(passes.t, np.asarray(loop.t))
    np.testing.assert_array_equal(passes.instance, np.asarray(loop.instance).astype(np.int32))
    np.testing.assert_array_equal(passes.prim, np.asarray(loop.prim))


def _drjit_hits(scene, o, d):
    """The Dr.Jit record of NumPy rays (traced every call), as NumPy (t, p, n, instance, prim)."""
    record = scene.intersect(Array3f(*o.T.astype(np.float32)), Array3f(*d.T.astype(np.float32)))
    dr.eval(record.t, record.p, record.n, record.instance, record.prim)
    return (np.asarray(record.t), np.asarray(record.p).T, np.asarray(record.n).T,
            np.asarray(record.instance), np.asarray(record.prim))


def _intersect_recordings(scene):
    from instancing.core.kernel_recording import recordings_of
    return {width: frozen for width, (frozen, _) in recordings_of(scene, "intersect").entries.items()}


@pytest.mark.parametrize("accel", ["grid", "bvh", "unrolled", "brute"])
def test_numpy_queries_replay_one_recording_per_batch_width_with_the_traced_hits(accel):
    """NumPy queries are recorded once per batch width, at its second query, and replayed
    (the Dr.Jit record is traced every call): bit for bit the same hits, for new rays and
    after the scene moved; a width queried once is traced, not recorded."""
    rng = np.random.default_rng(33)
    matrices = np.stack([random_affine(rng) for _ in range(6)])
    cylinders = matrices[:3].copy()
    cylinders[:, :3, :3] *= 1.1
    scene = instancing.load_scene({"models": {"torus": {"type": "obj", "filename": str(MESH_FILE)}},
                                   "instances": [{"model": "torus", "to_world": matrices},
                                                 {"model": "cylinder", "to_world": cylinders}]},
                                  accel=accel)

    def check(count):
        o, d = random_rays(rng, *scene.bounds, count)
        hits = scene.intersect(o, d)
        assert np.isfinite(hits.t).mean() > 0.05
        for ours, traced in zip((hits.t, hits.p, hits.n, hits.instance, hits.prim), _drjit_hits(scene, o, d)):
            np.testing.assert_array_equal(ours, traced.astype(ours.dtype))

    for count in (700, 700, 700, 300, 700, 300, 500):
        check(count)
    recordings = _intersect_recordings(scene)
    assert sorted(recordings) == [300, 700]
    assert all(frozen.n_recordings == 1 for frozen in recordings.values())
    # Moved: a new revision, whose first query records again.
    moved = matrices.copy()
    moved[:, :3, 3] += 0.4
    scene.set_transforms(tf.from_matrix(tf.matrices_to_lanes(np.concatenate([moved, cylinders]))))
    assert _intersect_recordings(scene) == {}
    for _ in range(3):
        check(700)
    assert _intersect_recordings(scene)[700].n_recordings == 1


def test_batches_in_passes_and_moving_transforms_are_traced_not_recorded(monkeypatch):
    from instancing.scene import scene as scene_module
    rng = np.random.default_rng(34)
    scene = load(["sphere"] * 20, [random_affine(rng) for _ in range(20)], accel="grid")
    o, d = random_rays(rng, *scene.bounds, 600)
    monkeypatch.setattr(scene_module, "PASSES_MIN_RAYS", 512)
    for _ in range(2):
        scene.intersect(o, d)  # walks the grid in passes, which evaluate between them
    assert _intersect_recordings(scene) == {}
    params = instancing.traverse(scene)
    key = next(k for k in params if k.endswith(".translation"))
    dr.enable_grad(params[key])
    params.update()
    scene.set_accel("bvh")
    for _ in range(2):
        hits = scene.intersect(o, d)
    assert _intersect_recordings(scene) == {}
    np.testing.assert_array_equal(hits.t, _drjit_hits(scene, o, d)[0])


@pytest.mark.parametrize("accel", ["auto", "grid", "bvh", "unrolled", "brute"])
def test_a_scene_without_instances_misses_under_every_structure(accel):
    """Nothing to structure: every choice (and auto on either backend) loads, every ray
    misses, and shadow rays are unblocked (each raised a bare ValueError or failed in
    its loop before)."""
    scene = instancing.load_scene({"lights": [{"type": "constant", "radiance": [1, 1, 1]}]}, accel=accel)
    o, d = np.zeros((5, 3)), np.tile([0.0, 0.6, 0.8], (5, 1))
    hits = scene.intersect(o, d)
    assert np.isinf(hits.t).all() and (hits.instance == -1).all()
    assert not np.asarray(scene.occluded(Array3f(*o.T), Array3f(*d.T), Float(10.0))).any()
    scene.set_accel("bvh" if accel != "bvh" else "grid")
    assert np.isinf(scene.intersect(o, d).t).all()


# --- mesh attributes read by materials ---------------------------------------

def _attribute_scene(material: dict, model: dict | None = None, **file_props) -> dict:
    from pathlib import Path
    torus = Path(__file__).resolve().parent.parent / "scenes" / "meshes" / "torus_colors.ply"
    return {"models": {"m": model or {"type": "ply", "filename": str(torus), **file_props}},
            "materials": {"paint": material},
            "instances": [{"id": "first", "model": "m", "material": "paint"}]}


def _write_coloured_triangle(path, colour) -> str:
    import plyfile
    vertex = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("r", "f4"), ("g", "f4"), ("b", "f4")])
    vertex["x"], vertex["y"] = [0, 1, 0], [0, 0, 1]
    vertex["r"], vertex["g"], vertex["b"] = np.asarray(colour, np.float32).T
    face = np.empty(1, dtype=[("vertex_indices", "O")])
    face["vertex_indices"] = [np.array([0, 1, 2], "i4")]
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"),
                     plyfile.PlyElement.describe(face, "face")]).write(str(path))
    return str(path)


@pytest.mark.parametrize("material, model, words", [
    ({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_colour"}}, None,
     ["instance 'first' (model 'm')", "material 'paint'", "'vertex_colour'", "does not have",
      "'face_tint_color'", "'vertex_color'"]),
    ({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}},
     {"type": "sphere"}, ["instance 'first' (model 'm')", "analytic model has no attributes"]),
    ({"type": "roughconductor", "alpha": {"type": "mesh_attribute", "name": "vertex_color"}}, None,
     ["'vertex_color' for 'alpha'", "3 values per vertex", "a number reads 1"]),
    ({"type": "blendbsdf", "weight": {"type": "mesh_attribute", "name": "face_tint_color"},
      "a": {"type": "diffuse"}, "b": {"type": "twosided", "x": {
          "type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_gloss"}}}},
     None, ["'face_tint_color' for 'weight'", "3 values per face", "a number reads 1"]),
])
def test_mesh_attributes_a_model_cannot_give_are_refused(material, model, words):
    """A material reading a mesh attribute on a model without it (another name, an analytic
    model), or with 3 values for a number parameter (Mitsuba would read 0), names the
    instance, model, material, attribute and parameter."""
    with pytest.raises(instancing.SceneError) as err:
        instancing.load_scene(_attribute_scene(material, model))
    for word in words:
        assert word in str(err.value), str(err.value)


def test_non_finite_mesh_attributes_are_refused_where_read(tmp_path):
    """A NaN vertex colour is refused when a material reads it (not when none does)."""
    path = _write_coloured_triangle(tmp_path / "nan.ply", [[0.5] * 3, [np.nan, 0.1, 0.1], [0.2] * 3])
    reads = {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}
    model = {"type": "ply", "filename": path}
    instancing.load_scene(_attribute_scene({"type": "diffuse"}, model))
    with pytest.raises(instancing.SceneError, match="'vertex_color'.*not finite at 1 vertices .the first: vertex 1"):
        instancing.load_scene(_attribute_scene(reads, model))


def test_a_one_value_attribute_reads_as_grey_and_scaled(tmp_path):
    """The albedo of a diffuse reading a one-value vertex attribute (scaled) at the triangle's
    centroid is the mean of its corners' values times the scale, grey."""
    import plyfile
    vertex = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("w_0", "f4")])
    vertex["x"], vertex["y"], vertex["w_0"] = [0, 1, 0], [0, 0, 1], [0.1, 0.4, 0.7]
    face = np.empty(1, dtype=[("vertex_indices", "O")])
    face["vertex_indices"] = [np.array([0, 1, 2], "i4")]
    path = tmp_path / "w.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"),
                     plyfile.PlyElement.describe(face, "face")]).write(str(path))
    scene = instancing.load_scene(_attribute_scene(
        {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_w", "scale": 0.5}},
        {"type": "ply", "filename": str(path)}))
    o = np.array([[1 / 3, 1 / 3, 1.0]]) - scene.origin
    hit = scene.intersect_surface(_vectors(o.astype(np.float32)), _vectors(np.array([[0, 0, -1.0]])))
    np.testing.assert_allclose(np.asarray(scene.albedo(hit)).ravel(), [0.2] * 3, rtol=1e-6)
