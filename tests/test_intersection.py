"""Ray/instance intersection against the float64 reference, Mitsuba 3 and brute force.

Rays are rounded to float32 before either side sees them, so that the
reference measures our arithmetic and not the rounding of the input.
"""

from __future__ import annotations

import numpy as np
import pytest

import instancing
from instancing.core.backend import BACKEND_NAME, Array3f, Float, dr

from instancing.scene import scene as scene_module
from instancing.validation import reference
from scene_helpers import (KINDS, MESH_FILE, angle_deg, float32_exact, load, mitsuba_intersect,
                           random_affine, random_rays, reference_instances)

#: One float32 rounding of a unit vector moves it by up to ~2^-24 rad per
#: component, i.e. ~3.4e-6 degrees: the floor of any float32 normal. On flat
#: shapes both Mitsuba and we sit at this floor, so there we require ours to be
#: within two such roundings when Mitsuba happens to be lower on the sample.
FLOAT32_NORMAL_FLOOR_DEG = 2 * np.degrees(2.0 ** -24 * np.sqrt(3))


def _errors(t, n, ref, oriented=True):
    both = np.isfinite(t) & np.isfinite(ref["t"])
    rel_t = np.abs(t[both] - ref["t"][both]) / ref["t"][both]
    return rel_t, angle_deg(n[both], ref["n"][both], oriented)


@pytest.mark.parametrize("kind", KINDS)
def test_model_under_random_affine_matches_reference_and_beats_mitsuba(kind):
    rng = np.random.default_rng(KINDS.index(kind) + 10)
    # Six instances: rotation, non-uniform scale, shear, translation; half reflected.
    matrices = [random_affine(rng, 3.0, reflect=i % 2 == 1) for i in range(6)]
    kinds = [kind] * len(matrices)
    scene = load(kinds, matrices)
    lo, hi = scene.bounds
    o, d = random_rays(rng, lo, hi, 40_000)
    ref = reference.intersect_instances(reference_instances(kinds, matrices), o, d)
    ours = scene.intersect(o, d)

    # Hit/miss agrees except on grazing rays: at most 1e-4 of all rays.
    disagree = np.isfinite(ours.t) != np.isfinite(ref["t"])
    assert disagree.sum() <= 1e-4 * len(o), disagree.sum()
    both = np.isfinite(ours.t) & np.isfinite(ref["t"])
    # The same instance wins wherever the two nearest hits are clearly distinct.
    assert np.array_equal(ours.instance[both], ref["instance"][both])
    assert np.array_equal(ours.instance[~np.isfinite(ours.t)], np.full((~np.isfinite(ours.t)).sum(), -1))
    if kind == "mesh":
        assert np.array_equal(ours.prim[both], ref["prim"][both])
    # p lies on the ray at t (the lecture: world hit point from t on the original ray).
    np.testing.assert_allclose(ours.p[both], o[both] + ours.t[both, None] * d[both],
                               rtol=0, atol=1e-5 * max(1.0, np.abs(o).max() + ours.t[both].max()))

    rel_t, ang = _errors(ours.t, ours.n, ref, oriented=True)
    assert np.median(rel_t) <= 1e-6
    # Normals are outward as the model defines them, reflections included.
    assert ang.max() < 1.0

    mi = mitsuba_intersect(kinds, matrices, o, d)
    # Mitsuba flips mesh normals under reflection; measure its error up to sign.
    mi_rel_t, mi_ang = _errors(mi["t"], mi["n"], ref, oriented=False)
    ours_t999, mi_t999 = np.quantile(rel_t, 0.999), np.quantile(mi_rel_t, 0.999)
    ours_n999, mi_n999 = np.quantile(ang, 0.999), np.quantile(mi_ang, 0.999)
    assert ours_t999 <= mi_t999, (ours_t999, mi_t999)
    # On CUDA, Mitsuba's meshes go through OptiX, whose float32 triangle normals round as
    # ours do: there ours may be one float32 rounding of a normal above Mitsuba's.
    slack = FLOAT32_NORMAL_FLOOR_DEG / 2 if BACKEND_NAME == "cuda" and kind == "mesh" else 0.0
    assert ours_n999 <= max(mi_n999, FLOAT32_NORMAL_FLOOR_DEG) + slack, (ours_n999, mi_n999)


def _mixed_scene(rng, n, clustered):
    kinds = [KINDS[i % len(KINDS)] for i in range(n)]
    matrices = []
    centres = rng.uniform(-40, 40, (3, 3))
    for i in range(n):
        m = random_affine(rng, 10.0, reflect=i % 3 == 0)
        if clustered:
            m[:3, 3] = centres[i % 3] + rng.normal(0, 1.5, 3)
        matrices.append(m)
    return kinds, matrices


@pytest.mark.parametrize("clustered", [False, True])
def test_grid_and_bvh_return_exactly_the_brute_force_hits(clustered):
    rng = np.random.default_rng(7 + clustered)
    kinds, matrices = _mixed_scene(rng, 150, clustered)
    scene = load(kinds, matrices, accel="brute")
    lo, hi = scene.bounds
    o, d = random_rays(rng, lo, hi, 30_000)
    # Half the rays start among the instances, so that clusters are hit too.
    near = np.array(matrices)[rng.integers(0, len(matrices), 15_000), :3, 3]
    o[:15_000] = float32_exact(near + rng.normal(0, 3, near.shape))
    brute = scene.intersect(o, d)
    assert np.isfinite(brute.t).sum() > 5000  # the sample really hits things
    for accel in ("grid", "bvh"):
        scene.set_accel(accel)
        assert scene.accel == accel
        hits = scene.intersect(o, d)
        for field in ("t", "instance", "prim"):
            np.testing.assert_array_equal(getattr(hits, field), getattr(brute, field),
                                          err_msg=f"{accel}: {field}")


@pytest.mark.parametrize("accel", ["brute", "grid", "bvh"])
def test_any_hit_shadow_queries_agree_with_the_nearest_hit(accel):
    # occluded() stops at the first hit it finds (any-hit); it must answer exactly what the
    # nearest hit says, for every segment length, and report a real hit of the segment.
    rng = np.random.default_rng(11)
    kinds, matrices = _mixed_scene(rng, 150, clustered=False)
    scene = load(kinds, matrices, accel=accel)
    lo, hi = scene.bounds
    o, d = random_rays(rng, lo, hi, 20_000)
    near = scene.intersect(o, d)
    # Segment ends: before, at about and beyond the nearest hit, and unbounded.
    t_max = np.where(np.isfinite(near.t), near.t * rng.choice([0.5, 0.999, 1.001, 3.0], len(o)),
                     rng.uniform(1.0, 200.0, len(o))).astype(np.float32)
    t_max[::7] = np.inf
    O, D = (Array3f(*[a[:, k] for k in range(3)]) for a in (o, d))
    blocked = np.asarray(scene.occluded(O, D, Float(t_max)))
    expected = near.t < t_max
    assert 3000 < expected.sum() < len(o) - 3000  # both answers are well represented
    np.testing.assert_array_equal(blocked, expected)
    t_first = np.asarray(scene.intersect_preliminary(O, D, True, Float(t_max), any_hit=True).t)
    t_nearest = np.asarray(scene.intersect_preliminary(O, D).t)  # phase 1, as any-hit's t
    # The hit it stopped at lies on the segment, no nearer than the nearest hit.
    assert np.all((t_first[blocked] >= t_nearest[blocked]) & (t_first[blocked] < t_max[blocked]))
    assert np.all(np.isinf(t_first[~blocked]) | (t_first[~blocked] >= t_max[~blocked]))
    # ... and it did stop early: some lanes report a hit behind the nearest one.
    assert np.sum(t_first[blocked] > t_nearest[blocked]) > 20


def test_unrolled_returns_exactly_the_brute_force_hits_and_shadow_answers():
    # 12 overlapping instances of every kind (two meshes, reflections, one duplicate for
    # exact ties), as 'auto' unrolls them: nearest hits equal brute force's field for
    # field, and shadow queries answer what the nearest hit says.
    rng = np.random.default_rng(29)
    kinds, matrices = _mixed_scene(rng, 11, clustered=False)
    kinds, matrices = kinds + [kinds[4]], matrices + [matrices[4]]
    scene = load(kinds, matrices, accel="unrolled")  # auto's pick on LLVM
    lo, hi = scene.bounds
    o, d = random_rays(rng, lo, hi, 30_000)
    # Half the rays start near an instance, so that every instance is hit often.
    near = np.array(matrices)[rng.integers(0, len(matrices), 15_000), :3, 3]
    o[:15_000] = float32_exact(near + rng.normal(0, 1, near.shape))
    brute = _unrolled_matches_brute_force(scene, o, d, rng, 200.0)
    assert np.isfinite(brute.t).sum() > 3000 and (brute.instance == 4).any()
    assert not (brute.instance == len(kinds) - 1).any()  # the duplicate loses every tie


def _unrolled_matches_brute_force(scene, o, d, rng, far):
    """Assert that the unrolled ``scene`` answers the rays as brute force does: the nearest
    hits field for field, and shadow queries (segments ending before, at about and beyond
    the nearest hit, or up to ``far`` on a miss) what the nearest hit says. Returns brute
    force's hits."""
    hits = scene.intersect(o, d)
    scene.set_accel("brute")
    brute = scene.intersect(o, d)
    for field in ("t", "instance", "prim"):
        np.testing.assert_array_equal(getattr(hits, field), getattr(brute, field), err_msg=field)
    scene.set_accel("unrolled")
    t_max = np.where(np.isfinite(brute.t), brute.t * rng.choice([0.5, 0.999, 1.001, 3.0], len(o)),
                     rng.uniform(1.0, far, len(o))).astype(np.float32)
    O, D = (Array3f(*[a[:, k] for k in range(3)]) for a in (o, d))
    blocked = np.asarray(scene.occluded(O, D, Float(t_max)))
    expected = brute.t < t_max
    assert 1000 < expected.sum() < len(o) - 1000  # both answers are well represented
    np.testing.assert_array_equal(blocked, expected)
    return brute


@pytest.mark.parametrize("kind", KINDS)
def test_instances_tested_nearest_box_first_return_the_brute_force_hits(kind):
    # Meshes, and analytic models five or more of a kind, are tested kind by kind nearest
    # box first, in rounds, every lane in the instance its round picked (rows, and a mesh's
    # BVH root, per lane): nine of the kind in a row along x (meshes of two files), so that
    # rays along the row cross up to all of their boxes, with reflections and an exact
    # duplicate (ties go to the lower index), among three instances of other kinds tested
    # on their own.
    from instancing.scene.intersection import ROUNDS_MIN_INSTANCES
    assert ROUNDS_MIN_INSTANCES <= 9
    rng = np.random.default_rng(41)
    matrices, models = [], []
    for i in range(9):
        m = random_affine(rng, 1.0, reflect=i % 3 == 1)
        m[0, 3] = 2.5 * i
        matrices.append(m)
        models.append(("ring" if i % 2 else "torus") if kind == "mesh" else kind)
    matrices.append(matrices[4].copy())
    models.append(models[4])
    for other in [k for k in ("disk", "cube", "rectangle", "sphere") if k != kind][:3]:
        matrices.append(random_affine(rng, 1.0) @ np.diag([0.5, 0.5, 0.5, 1.0]))
        matrices[-1][0, 3] = rng.uniform(0.0, 20.0)
        models.append(other)
    description = {"models": {"torus": {"type": "obj", "filename": str(MESH_FILE)},
                              "ring": {"type": "obj", "filename": str(MESH_FILE.parent / "torus_uv.obj")}},
                   "instances": [{"model": k, "to_world": m.tolist()} for k, m in zip(models, matrices)]}
    scene = instancing.load_scene(description, accel="unrolled")
    lo, hi = scene.bounds
    o, d = random_rays(rng, lo, hi, 30_000)
    # Half the rays start before one end of the row and run along it.
    o[:15_000] = float32_exact(np.array([-3.0, 0.0, 0.0]) + rng.normal(0, 1, (15_000, 3)))
    along = np.array([1.0, 0.0, 0.0]) + rng.normal(0, 0.05, (15_000, 3))
    d[:15_000] = float32_exact(along / np.linalg.norm(along, axis=1, keepdims=True))
    brute = _unrolled_matches_brute_force(scene, o, d, rng, 50.0)
    # The sample reaches deep rounds: rays whose third-nearest box of the row begins before
    # their hit.
    box_lo, box_hi = scene.instance_bounds(range(10))
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (box_lo[None] - o[:, None]) / d[:, None], (box_hi[None] - o[:, None]) / d[:, None]
    t_in = np.maximum(np.nanmax(np.minimum(t1, t2), axis=2), 0.0)
    crossed = (t_in <= np.nanmin(np.maximum(t1, t2), axis=2)) & (t_in <= brute.t[:, None])
    assert (crossed.sum(axis=1) >= 3).sum() > 1000
    assert np.isin(np.arange(10), brute.instance).sum() >= 8  # most of the row wins somewhere
    assert (brute.instance == 4).any() and not (brute.instance == 9).any()  # the duplicate loses


@pytest.mark.parametrize("kind", KINDS)
def test_a_scene_scaled_by_a_power_of_two_hits_as_before_scaled_exactly(kind):
    """Placement invariance across float32's range: scene and rays scaled by 2^e (e = +-70,
    +-100, about 1e+-21 and 1e+-30) give the unit scene's hits, t times 2^e to the bit and
    the same normals. (A quadric's |d|^2 in object space, 2^-2e, left float32's range past
    about 1e19 until the direction was brought to unit exponent first. Near 1e-35 the
    scene's own products reach float32's subnormals, where results vary by 1e-5.)"""
    rng = np.random.default_rng(KINDS.index(kind) + 70)
    a = random_affine(rng, 1.0)
    lo, hi = load([kind], [a]).bounds
    # Rays from 4 units out, aimed within the box's reach of its centre.
    _, d = random_rays(rng, lo, hi, 4000)
    o = float32_exact(0.5 * (lo + hi) - 4.0 * d + rng.uniform(-1, 1, (4000, 1)) * 0.5 * (hi - lo))
    unit = load([kind], [a]).intersect(o, d)
    assert 0.2 < np.isfinite(unit.t).mean() < 0.95
    for e in (70, -70, 100, -100):
        scale = np.diag([2.0 ** e] * 3 + [1.0])
        scaled = load([kind], [scale @ a]).intersect(o * 2.0 ** e, d)
        np.testing.assert_array_equal(scaled.t, unit.t * 2.0 ** e, err_msg=f"2^{e}")
        np.testing.assert_array_equal(scaled.n, unit.n, err_msg=f"2^{e}")
        np.testing.assert_array_equal(scaled.instance, unit.instance)


def test_wide_scales_bound_the_direction_lengths_without_inverting():
    """A unit direction's object-space length lies in [1 / sigma_max, 1 / sigma_min] of
    the linear part: wide past 2^40 either way, from bounds that hold for any matrix."""
    from instancing.models.analytic import WIDE_SCALE, wide_scales
    rng = np.random.default_rng(5)
    assert not wide_scales(np.stack([random_affine(rng, 3.0) for _ in range(50)]))
    # (The bounds are loose by up to sqrt(3) and 3 on a uniform scale: 2^-39 counts as wide.)
    for s, wide in ((2.0 ** 39, False), (2.0 ** 41, True), (2.0 ** -38, False), (2.0 ** -41, True)):
        assert wide_scales(np.diag([s, s, s, 1.0])[None]) == wide, s
    # One axis squashed: sigma_min 2^-41 while the others stay 1.
    assert wide_scales(np.diag([1.0, 2.0 ** -41, 1.0, 1.0])[None])
    # The bounds are safe, never optimistic: random matrices against their singular values.
    for _ in range(200):
        m = np.eye(4)
        m[:3, :3] = rng.normal(size=(3, 3)) * 2.0 ** rng.uniform(-45, 45)
        sigma = np.linalg.svd(m[:3, :3], compute_uv=False)
        if sigma[0] > WIDE_SCALE or sigma[2] < 1 / WIDE_SCALE:
            assert wide_scales(m[None])


def test_a_sphere_moved_to_a_wide_scale_by_an_update_is_traced_as_scaled():
    """The scene notes a wide scale installed after loading (the quadric test is traced
    anew): the unit sphere's hits, t times 2^70 exactly."""
    from instancing.core.backend import Matrix4f
    rng = np.random.default_rng(9)
    scene = load(["sphere"], [np.eye(4)])
    assert not scene.instances.wide_scales
    d = float32_exact(rng.normal(size=(2000, 3)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = float32_exact(d)
    o = float32_exact(-4.0 * d + rng.uniform(-1, 1, (2000, 3)))
    unit = scene.intersect(o, d)
    params = instancing.traverse(scene)
    params["0.to_world"] = Matrix4f(np.diag([2.0 ** 70] * 3 + [1.0]).tolist())
    params.update()
    assert scene.instances.wide_scales
    scaled = scene.intersect(o * 2.0 ** 70, d)
    assert 0.2 < np.isfinite(unit.t).mean() < 0.95
    np.testing.assert_array_equal(scaled.t, unit.t * 2.0 ** 70)
    np.testing.assert_array_equal(scaled.n, unit.n)


def test_auto_unrolls_small_scenes_only_and_unrolled_has_a_limit(monkeypatch):
    from instancing.scene.scene import UNROLL_LIMIT, UNROLL_MAX_INSTANCES
    monkeypatch.setattr(scene_module, "AUTO_BVH", False)  # the LLVM backend's rule
    rng = np.random.default_rng(31)
    for n, expected in ((UNROLL_MAX_INSTANCES, "unrolled"), (UNROLL_MAX_INSTANCES + 1, "grid")):
        matrices = [random_affine(rng, 20.0) for _ in range(n)]
        assert load(["sphere"] * n, matrices).accel == expected
    matrices = [random_affine(rng, 20.0) for _ in range(UNROLL_LIMIT + 1)]
    with pytest.raises(instancing.SceneError, match="'unrolled' tests at most"):
        load(["sphere"] * len(matrices), matrices, accel="unrolled")


def test_auto_picks_bvh_for_clustered_and_grid_for_uniform(monkeypatch):
    monkeypatch.setattr(scene_module, "AUTO_BVH", False)  # the LLVM backend's rule
    rng = np.random.default_rng(3)
    uniform = load(*_mixed_scene(rng, 300, clustered=False))
    assert uniform.accel == "grid"
    # Three tight clusters far apart: most grid cells empty, a few overfull.
    kinds = ["sphere"] * 900
    matrices = []
    for i in range(900):
        m = np.eye(4)
        m[:3, :3] *= 0.2
        m[:3, 3] = np.array([[-500, 0, 0], [500, 0, 0], [0, 500, 0]])[i % 3] + rng.normal(0, 2, 3)
        matrices.append(m)
    assert load(kinds, matrices).accel == "bvh"


def test_auto_picks_the_bvh_for_a_few_thousand_meshes_with_the_grids_hits(monkeypatch):
    """Mostly meshes, up to MESH_BVH_MAX_INSTANCES (lowered here to 20): the BVH, which
    returns the hits the grid does; one more instance, or more analytic instances than
    meshes: the grid."""
    monkeypatch.setattr(scene_module, "AUTO_BVH", False)  # the LLVM backend's rule
    monkeypatch.setattr(scene_module, "MESH_BVH_MAX_INSTANCES", 20)
    rng = np.random.default_rng(23)
    matrices = [random_affine(rng, 10.0) for _ in range(41)]
    tori = load(["mesh"] * 20, matrices[:20])
    assert tori.accel == "bvh"
    assert load(["mesh"] * 21, matrices[:21]).accel == "grid"
    assert load(["mesh"] * 10 + ["sphere"] * 10, matrices[:20]).accel == "bvh"
    assert load(["mesh"] * 9 + ["sphere"] * 11, matrices[:20]).accel == "grid"
    o, d = random_rays(rng, *tori.bounds, 20_000)
    ours = tori.intersect(o, d)
    assert np.isfinite(ours.t).sum() > 1000  # the sample really hits tori (1 241 of them)
    tori.set_accel("grid")
    grid = tori.intersect(o, d)
    for field in ("t", "instance", "prim"):
        np.testing.assert_array_equal(getattr(ours, field), getattr(grid, field))


@pytest.mark.parametrize("meshes, spheres, nested", [(12, 0, True), (10, 10, True), (9, 11, False)])
def test_an_instance_bvh_of_mostly_meshes_walks_its_instances_after_its_steps(meshes, spheres, nested):
    """A top-level BVH where at least half the instances are meshes walks in nested loops
    (steps, then the instances reached, whose mesh walks run together); otherwise in one
    flat loop. Either way its hits are the brute force's."""
    rng = np.random.default_rng(29)
    kinds = ["mesh"] * meshes + ["sphere"] * spheres
    matrices = [random_affine(rng, 6.0) for _ in kinds]
    scene = load(kinds, matrices, accel="bvh")
    assert scene.bvh.nested is nested
    o, d = random_rays(rng, *scene.bounds, 20_000)
    ours = scene.intersect(o, d)
    assert np.isfinite(ours.t).sum() > 2000
    scene.set_accel("brute")
    brute = scene.intersect(o, d)
    for field in ("t", "instance", "prim"):
        np.testing.assert_array_equal(getattr(ours, field), getattr(brute, field))


def test_auto_on_cuda_picks_the_bvh_at_every_size(monkeypatch):
    """The CUDA backend's rule (AUTO_BVH): the BVH for 3 and 300 instances, with the hits of
    the structure the LLVM rule picks."""
    rng = np.random.default_rng(17)
    for n in (3, 300):
        kinds, matrices = ["cube"] * n, [random_affine(rng, 20.0) for _ in range(n)]
        monkeypatch.setattr(scene_module, "AUTO_BVH", False)
        other = load(kinds, matrices)
        monkeypatch.setattr(scene_module, "AUTO_BVH", True)
        scene = load(kinds, matrices)
        assert scene.accel == "bvh" and other.accel in ("unrolled", "grid")
        lo, hi = scene.bounds
        o, d = random_rays(rng, lo, hi, 20_000)
        ours, theirs = scene.intersect(o, d), other.intersect(o, d)
        np.testing.assert_array_equal(ours.instance, theirs.instance)
        np.testing.assert_array_equal(ours.t, theirs.t)


def test_instanced_mesh_equals_pretransformed_mesh(tmp_path):
    rng = np.random.default_rng(11)
    m = random_affine(rng, 2.0, reflect=True)
    mesh = instancing.io.mesh_file.read_mesh(MESH_FILE)
    world_vertices = mesh.vertices @ m[:3, :3].T + m[:3, 3]
    path = tmp_path / "moved.obj"
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in world_vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    path.write_text("\n".join(lines) + "\n")
    instanced = load(["mesh"], [m])
    direct = instancing.load_scene({"models": {"moved": {"type": "obj", "filename": str(path)}},
                                    "instances": [{"model": "moved"}]})
    o, d = random_rays(rng, *instanced.bounds, 20_000)
    a, b = instanced.intersect(o, d), direct.intersect(o, d)
    both = np.isfinite(a.t) & np.isfinite(b.t)
    assert (np.isfinite(a.t) != np.isfinite(b.t)).sum() <= 2  # edge-grazing rays only
    assert both.sum() > 2000
    # Same triangle, same distance to float32 accuracy of the two formulations.
    assert np.mean(a.prim[both] == b.prim[both]) > 0.999
    np.testing.assert_allclose(a.t[both], b.t[both], rtol=2e-4, atol=1e-6)
    # Normals: the instance keeps the model's outward orientation (inverse transpose),
    # the pre-transformed copy's winding is flipped by the reflection (det < 0).
    same = both & (a.prim == b.prim)
    assert np.all(angle_deg(a.n[same], -b.n[same]) < 0.05)


def _sheared_sphere(angle_deg_value, tx):
    """world_from_object = translate(tx, 0.2, 0) @ rotate_y(angle) @ shear/scale (float64 NumPy)."""
    a = np.radians(angle_deg_value)
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    lin = rot @ np.array([[1.2, 0.3, 0.0], [0.0, 0.8, 0.1], [0.0, 0.0, 1.5]])
    m = np.eye(4)
    m[:3, :3] = lin
    m[:3, 3] = [tx, 0.2, 0.0]
    return m


@pytest.mark.parametrize("kind", ["sphere", "cylinder", "mesh"])
def test_forward_derivatives_match_central_differences(kind):
    """d t / d param and d p / d param for a translation component and a rotation angle.

    Central differences of the float64 reference with step 1e-4 (units / degrees);
    the truncation error is O(h^2) ~ 1e-8, far below the 1e-3 tolerance, which
    covers float32 rounding of the AD path (t ~ 5, derivatives ~ 1).
    """
    rng = np.random.default_rng(5)
    angle0, tx0 = 20.0, 0.1
    base = _sheared_sphere(0.0, 0.0)
    shear = base.copy()
    shear[:3, 3] = 0
    n = 64
    if kind == "cylinder":
        # Across the (tilted) axis: from -x, heights within the cylinder's z range.
        o = np.column_stack([np.full(n, -6.0), rng.uniform(-0.5, 0.5, n), rng.uniform(0.2, 1.2, n)])
        d = np.tile([1.0, 0.0, 0.0], (n, 1))
    else:
        o = np.column_stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n), np.full(n, -6.0)])
        d = np.tile([0.0, 0.0, 1.0], (n, 1))
    o, d = float32_exact(o), float32_exact(d)

    scene = load([kind], [_sheared_sphere(angle0, tx0)])
    angle, tx = Float(angle0), Float(tx0)
    for which, param in (("angle", angle), ("tx", tx)):
        dr.enable_grad(param)
        world_from_object = (instancing.translate(Array3f(tx, 0.2, 0.0))
                             @ instancing.rotate_y(angle) @ instancing.from_matrix(shear))
        scene.set_transforms(world_from_object)
        hit = scene.intersect(Array3f(*[Float(o[:, k]) for k in range(3)]),
                              Array3f(*[Float(d[:, k]) for k in range(3)]))
        dr.forward(param)
        grad_t = np.asarray(dr.grad(hit.t))
        grad_p = np.asarray(dr.grad(hit.p)).T
        dr.disable_grad(param)

        h = 1e-4
        plus = dict(angle=angle0 + h, tx=tx0) if which == "angle" else dict(angle=angle0, tx=tx0 + h)
        minus = dict(angle=angle0 - h, tx=tx0) if which == "angle" else dict(angle=angle0, tx=tx0 - h)
        ref_p = reference.intersect_instances(
            reference_instances([kind], [_sheared_sphere(plus["angle"], plus["tx"])]), o, d)
        ref_m = reference.intersect_instances(
            reference_instances([kind], [_sheared_sphere(minus["angle"], minus["tx"])]), o, d)
        ok = np.isfinite(ref_p["t"]) & np.isfinite(ref_m["t"]) & (ref_p["instance"] >= 0)
        # Skip rays whose FD straddles a triangle edge (mesh) or a silhouette.
        ok &= (ref_p["prim"] == ref_m["prim"]) & np.isfinite(np.asarray(hit.t))
        assert ok.sum() > n // 3
        with np.errstate(invalid="ignore"):  # misses give inf - inf on rays excluded by ok
            fd_t = (ref_p["t"] - ref_m["t"]) / (2 * h)
            fd_p = (ref_p["p"] - ref_m["p"]) / (2 * h)
        np.testing.assert_allclose(grad_t[ok], fd_t[ok], rtol=1e-3, atol=1e-3, err_msg=which)
        np.testing.assert_allclose(grad_p[ok], fd_p[ok], rtol=1e-3, atol=1e-3, err_msg=which)


def _traced_operations(scene) -> int:
    """Operations in the kernels that one intersect call compiles and runs."""
    o = np.array([[0.0, 0.0, -50.0]] * 4)
    d = np.array([[0.0, 0.0, 1.0]] * 4)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        scene.intersect(o, d)
        history = dr.kernel_history()
    return sum(k["operation_count"] for k in history if k["type"] == dr.KernelType.JIT)


def test_kernels_contain_only_the_model_kinds_present():
    sphere = np.eye(4)
    only_spheres = instancing.load_scene({"instances": [{"model": "sphere"}]}, accel="brute")
    # Declared but unused models are not traced either.
    unused_mesh = instancing.load_scene({
        "models": {"torus": {"type": "obj", "filename": str(MESH_FILE)}, "tube": {"type": "cylinder"}},
        "instances": [{"model": "sphere"}]}, accel="brute")
    assert only_spheres.kind_names == unused_mesh.kind_names == ["sphere"]
    base = max(_traced_operations(only_spheres), _traced_operations(unused_mesh))
    for other in ["cube", "rectangle", "disk", "cylinder", "mesh"]:
        scene = load(["sphere", other], [sphere, sphere], accel="brute")
        assert scene.kind_names == ["sphere", other]
        # Each extra kind adds its whole test (tens of operations at least).
        assert _traced_operations(scene) > base + 20, other


def test_rays_of_any_direction_length_give_t_in_direction_units():
    scene = instancing.load_scene({"instances": [{"model": "sphere", "to_world": [{"translate": [0, 0, 5]}]}]})
    o = np.zeros((3, 3))
    d = np.array([[0, 0, 1.0], [0, 0, 1e-3], [0, 0, 1e3]])
    hits = scene.intersect(o, d)
    np.testing.assert_allclose(hits.t, [4.0, 4e3, 4e-3], rtol=1e-6)
    np.testing.assert_allclose(hits.p, [[0, 0, 4]] * 3, atol=1e-5)


def test_intersect_rejects_malformed_ray_arrays():
    scene = instancing.load_scene({"instances": [{"model": "sphere"}]})
    with pytest.raises(ValueError, match="origins and directions"):
        scene.intersect(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="origins and directions"):
        scene.intersect(np.zeros((4, 3)), np.zeros((5, 3)))


@pytest.mark.parametrize("which, row, value", [
    ("origin", 3, np.nan), ("origin", 0, -np.inf), ("direction", 5, np.nan),
    ("direction", 2, np.inf), ("direction", 4, None)])
def test_intersect_refuses_rays_without_a_nearest_hit_naming_the_first(which, row, value):
    """A NaN or infinite origin or direction, or a zero direction, is refused naming the
    ray, not returned as a miss."""
    scene = instancing.load_scene({"instances": [{"model": "sphere"}]})
    o = np.tile([0.0, 0.0, -5.0], (8, 1))
    d = np.tile([0.0, 0.0, 1.0], (8, 1))
    if value is None:
        d[row] = 0.0
    else:
        (o if which == "origin" else d)[row, 1] = value
    with pytest.raises(ValueError, match=rf"ray {row} \(of 8, 1 bad\)"):
        scene.intersect(o, d)
    assert (scene.intersect(np.delete(o, row, 0), np.delete(d, row, 0)).instance == 0).all()


@pytest.mark.parametrize("name", ["cornell_box", "affine_shapes", "light_area"])
def test_accelerations_agree_on_bundled_scenes_including_coincident_faces(name):
    """The Cornell box's tall block stands exactly on the floor: rays from inside the
    block hit both at the same t. Exact ties go to the lower stored index in every
    structure, so grid, BVH and brute force agree instance for instance."""
    from pathlib import Path
    scene = instancing.load_scene(Path(__file__).resolve().parent.parent / "scenes" / f"{name}.json",
                                  accel="brute")
    rng = np.random.default_rng(1)
    o, d = random_rays(rng, *scene.bounds, 20_000)
    brute = scene.intersect(o, d)
    for accel in ("grid", "bvh", "unrolled"):
        scene.set_accel(accel)
        hits = scene.intersect(o, d)
        np.testing.assert_array_equal(hits.t, brute.t)
        np.testing.assert_array_equal(hits.instance, brute.instance)


def test_phase_two_skipped_by_packets_that_miss_gives_the_full_record_of_every_lane():
    """Without derivatives, phase 2 runs in a branch that all-miss packets skip; the
    record equals the one computed on every lane (what a derivative-tracking call runs)."""
    rng = np.random.default_rng(61)
    kinds = [KINDS[i % len(KINDS)] for i in range(30)]
    scene = load(kinds, [random_affine(rng, 6.0, reflect=i % 3 == 0) for i in range(30)])
    lo, hi = scene.bounds
    o, d = random_rays(rng, lo, hi, 8000)
    # Blocks of rays pointing away from the scene: whole packets with no hit.
    o[:2000] = hi + 50.0
    d[:2000] = np.abs(d[:2000])
    o, d = Array3f(float32_exact(o).T), Array3f(float32_exact(d).T)
    skipping = scene.intersect_surface(o, d)
    hit = scene.intersect_preliminary(o, d)
    every_lane = instancing.scene.intersection._surface_record(scene.instances, o, d, hit)
    valid = np.asarray(every_lane.valid)
    assert 0.2 < valid[2000:].mean() < 0.9 and not valid[:2000].any()
    for field in ("t", "p", "n", "error", "instance", "prim", "valid"):
        np.testing.assert_array_equal(np.asarray(getattr(skipping, field)),
                                      np.asarray(getattr(every_lane, field)))


def _surface_scene(models: dict, kinds: list[str], matrices: list[np.ndarray]) -> instancing.Scene:
    """Instances of the given models under the given matrices, in an anisotropic rough metal
    whose colour is a checkerboard (a texture makes the surface records carry uv; the
    anisotropy, the shading tangent)."""
    return instancing.load_scene({
        "models": models,
        "materials": {"t": {"type": "roughconductor", "alpha_u": 0.1, "alpha_v": 0.3,
                            "specular_reflectance": {"type": "checkerboard"}}},
        "instances": [{"model": kind, "material": "t", "to_world": [{"matrix": m.tolist()}]}
                      for kind, m in zip(kinds, matrices)]})


def _surface_records(tmp_path, mode, derivatives=False):
    """Our surface records and Mitsuba's on the exported scene at the hits of random rays
    on every analytic shape under random affine maps, on a mesh with OBJ texture
    coordinates (Mitsuba's v flip), a PLY with u v and a mesh without any: (kinds, models,
    our record, Mitsuba's, where both hit the same surface, our instance per ray). With
    ``derivatives``, our records carry dp/du and dp/dv."""
    import plyfile
    from instancing.core.backend import Array3f, mitsuba_module
    mi = mitsuba_module()
    rng = np.random.default_rng(21)
    vertices = rng.uniform(-1, 1, size=(6, 3))
    vertex = np.empty(6, dtype=[(c, "f4") for c in "xyzuv"])
    for k, c in enumerate("xyz"):
        vertex[c] = vertices[:, k]
    vertex["u"], vertex["v"] = rng.uniform(0, 1, 6), rng.uniform(0, 1, 6)
    face = np.empty(4, dtype=[("vertex_indices", "O")])
    for i, tri in enumerate([[0, 1, 2], [2, 3, 4], [4, 5, 0], [1, 3, 5]]):
        face[i] = (np.array(tri, dtype="i4"),)
    ply = tmp_path / "uv.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"),
                     plyfile.PlyElement.describe(face, "face")]).write(str(ply))
    models = {"torus_uv": {"type": "obj", "filename": str(MESH_FILE.with_name("torus_uv.obj"))},
              "ply_uv": {"type": "ply", "filename": str(ply)},
              "plain": {"type": "obj", "filename": str(MESH_FILE), "face_normals": True}}
    kinds = ["sphere", "cube", "rectangle", "disk", "cylinder", "torus_uv", "ply_uv", "plain"]
    matrices = [np.eye(4) for _ in kinds]
    for k, m in enumerate(matrices):
        m[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * rng.uniform(0.7, 1.3, 3)
        if kinds[k] == "sphere" and mode == "shapes":
            # Mitsuba's plain sphere takes similarities only (exact in float32 here).
            m[:3, :3] = [[0.0, -0.75, 0.0], [0.0, 0.0, 0.75], [-0.75, 0.0, 0.0]]
        m[:3, 3] = [3.0 * k, 0.0, 0.0]
    scene = _surface_scene(models, kinds, matrices)
    scene.instances.surface_derivatives = derivatives
    n = 20_000
    o = np.stack([rng.uniform(-1.5, 3 * len(kinds), n), rng.uniform(-1.5, 1.5, n), np.full(n, 5.0)], 1)
    d = np.stack([rng.normal(0, 0.15, n), rng.normal(0, 0.15, n), -np.ones(n)], 1)
    o, d = float32_exact(o), float32_exact(d / np.linalg.norm(d, axis=1, keepdims=True))
    hit = scene.intersect_surface(Array3f(*o.T), Array3f(*d.T))
    mitsuba_scene = mi.load_dict(instancing.to_mitsuba(scene, mode=mode))
    theirs = mitsuba_scene.ray_intersect(mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*d.T)))
    both = np.asarray(hit.valid) & np.asarray(theirs.is_valid())
    # The same surface hit (where both see the same nearest hit).
    same = both & np.isclose(np.asarray(hit.t), np.asarray(theirs.t), rtol=1e-4, atol=0)
    # (The Mitsuba scene must outlive the lazily evaluated record: returned with it.)
    return kinds, models, hit, theirs, same, np.asarray(hit.instance), mitsuba_scene


@pytest.mark.parametrize("mode", ["shapes", "instances"])
def test_surface_coordinates_are_mitsubas(tmp_path, mode):
    """uv at the hits of random rays (:func:`_surface_records`): against Mitsuba's ``si.uv``
    on the exported scene (its own shape plugins; meshes built with our corner uvs; a mesh
    without uvs has barycentric ones)."""
    kinds, models, hit, theirs, same, instance, _ = _surface_records(tmp_path, mode)
    ours_uv, their_uv = np.asarray(hit.uv, np.float64), np.asarray(theirs.uv, np.float64)
    for k, kind in enumerate(kinds):
        mine = same & (instance == k)
        assert mine.sum() > 100, kind
        difference = np.abs(ours_uv[:, mine] - their_uv[:, mine])
        if kind in ("sphere", "cylinder"):
            difference[0] = np.minimum(difference[0], 1 - difference[0])  # u wraps at the seam
        if kind == "disk":
            difference[1] = np.minimum(difference[1], 1 - difference[1])
        # Mitsuba's float32 round-off: its cylinder's angle from a float32 point; on meshes
        # its barycentrics, from float32 positions up to ~25 units out (a step of ~2e-6)
        # over triangle edges of ~0.1 (ours come from the float64 re-intersection).
        limit = 2e-4 if kind in models else 5e-5
        assert difference.max() < limit, (kind, difference.max())


@pytest.mark.parametrize("mode", ["shapes", "instances"])
def test_surface_derivatives_are_mitsubas(tmp_path, mode):
    """dp/du and dp/dv with their lengths (what bump maps tilt the frame by) at the hits of
    random rays, against Mitsuba's ``si.dp_du`` and ``si.dp_dv``: within 1e-4 of their
    length (Mitsuba's float32 derivatives from float32 points; ours from the float64
    re-intersection)."""
    kinds, models, hit, theirs, same, instance, _ = _surface_records(tmp_path, mode, derivatives=True)
    for ours, mine_name in ((hit.dpdu, "dp_du"), (hit.dpdv, "dp_dv")):
        ours = np.asarray(ours, np.float64).T
        their = np.asarray(getattr(theirs, mine_name), np.float64).T
        for k, kind in enumerate(kinds):
            mine = same & (instance == k)
            assert mine.sum() > 100, kind
            scale = np.maximum(np.linalg.norm(their[mine], axis=1), 1e-3)
            error = np.linalg.norm(ours[mine] - their[mine], axis=1) / scale
            assert error.max() < 1e-4, (kind, mine_name, error.max())  # (measured: <= 2.5e-5)


@pytest.mark.parametrize("mode", ["shapes", "instances"])
def test_shading_tangents_are_mitsubas(tmp_path, mode):
    """The shading frame's first axis where a material is anisotropic: dp/du of each
    shape (its own parameterisation; a mesh's from its uvs, or with none, from its
    barycentrics: the edge v1 - v0) made orthogonal to the shading normal, against
    Mitsuba's ``si.sh_frame.s`` at the same hits within 0.01 degrees (Mitsuba's float32
    dp/du from float32 points)."""
    kinds, models, hit, theirs, same, instance, _ = _surface_records(tmp_path, mode)
    ours_s = np.asarray(hit.ss, np.float64).T
    their_s = np.asarray(theirs.sh_frame.s, np.float64).T
    for k, kind in enumerate(kinds):
        mine = same & (instance == k)
        assert mine.sum() > 100, kind
        error = angle_deg(ours_s[mine], their_s[mine])
        assert error.max() < 0.01, (kind, error.max())


@pytest.mark.parametrize("model", ["rectangle", "disk", "sphere", "cube", "cylinder"])
def test_hits_through_an_edge_have_finite_surface_coordinates(model):
    """Rays aimed at a textured shape's rim (its outline seen from the ray origins): where
    phase 1 (float32) hits and the float64 re-test misses, the record keeps phase 1's t and
    takes the point, normal and surface coordinates there, so that none is NaN (before: the
    coordinates of such hits were NaN, and so was a textured lamp's or material's value,
    seen as NaN pixels)."""
    scene = instancing.load_scene({
        "materials": {"checks": {"type": "diffuse", "reflectance": {"type": "checkerboard"}}},
        "instances": [{"model": model, "material": "checks",
                       "to_world": [{"rotate": {"axis": [1, 2, 3], "angle": 30}}, {"scale": [0.9, 0.6, 0.8]}]}]})
    rng = np.random.default_rng(4)
    n = 20000
    angle = rng.uniform(0, 2 * np.pi, n)
    # Points on the rim of the unit square / disk / the sphere's and cylinder's outline from +z,
    # the cube's edges at z = 1: targets within float32 rounding of the boundary.
    rim = np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)
    if model in ("rectangle", "cube"):
        rim /= np.abs(rim[:, :2]).max(axis=1, keepdims=True)
        rim[:, 2] = 1.0 if model == "cube" else 0.0
    m = (instancing.rotate([1, 2, 3], 30) @ instancing.scale([0.9, 0.6, 0.8])).to_numpy()[0]
    target = rim @ m[:3, :3].T
    direction = np.array([0.0, 0.0, -1.0]) @ np.linalg.inv(m[:3, :3])
    direction = np.broadcast_to(direction / np.linalg.norm(direction), (n, 3))
    origin = target - 4.0 * direction
    hit = scene.intersect_surface(Array3f(*(origin - scene.origin).T.astype(np.float32)),
                                  Array3f(*direction.T.astype(np.float32)))
    valid = np.asarray(hit.valid)
    assert valid.sum() > 100
    for name in ("uv", "p", "n"):
        values = np.asarray(getattr(hit, name), np.float64).T[valid]
        assert np.isfinite(values).all(), (name, np.flatnonzero(~np.isfinite(values).all(axis=1))[:5])
    albedo = np.asarray(scene.albedo(hit), np.float64).T[valid]
    assert np.isfinite(albedo).all()
