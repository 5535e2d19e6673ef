"""Spawning rays off surfaces (instancing/core/ray_offset.py): offset_origin and
shadow_distance checked in float64 on float32 inputs, and spawned rays traced in loaded
scenes (no self-intersection at t ~ 0)."""

import numpy as np
import pytest

import instancing
from instancing.core import ray_offset
from instancing.core.backend import Array3f, Float, device_arrays, dr
from instancing.core.warp import square_to_cosine_hemisphere, to_frame
from scene_helpers import float32_exact, random_affine

#: float32 unit roundoff.
EPS32 = 2.0 ** -24


def _vectors(x: np.ndarray) -> Array3f:
    # In Dr.Jit's own (aligned) storage: kernels reading wrapped NumPy buffers are compiled
    # for the buffers' alignment, so each call could compile anew (backend.device_array).
    return Array3f(*device_arrays(Float, *[x[:, k].astype(np.float32) for k in range(3)]))


def _rows(v: Array3f) -> np.ndarray:
    return np.asarray(v, np.float64).T


def _evaluated(hit):
    """Evaluate every field of a Dr.Jit hit record in one kernel (read one by one, each
    field would trace and compile the whole intersection again)."""
    dr.eval(hit.t, hit.p, hit.n, hit.error, hit.instance, hit.prim, hit.valid)
    return hit


def _unit(rng, n):
    v = rng.normal(size=(n, 3))
    return float32_exact(v / np.linalg.norm(v, axis=1, keepdims=True))


def _points_normals_directions(seed: int, n: int = 20_000):
    """float32 points over seven decades of magnitude, unit normals, any directions."""
    rng = np.random.default_rng(seed)
    p = float32_exact(rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-3, 4, (n, 1)))
    return rng, p, _unit(rng, n), float32_exact(rng.normal(size=(n, 3)))


@pytest.mark.parametrize("relative_error", [1e-7, 1e-5, 1e-2, 1.0])
def test_offset_origin_leaves_the_error_box_on_the_side_of_w(relative_error):
    """dot(offset, n) has the sign of dot(w, n), and the moved point lies beyond the
    error box's farthest extent along n, dot(|n|, error)."""
    rng, p, n, w = _points_normals_directions(1)
    error = float32_exact(np.abs(p) * relative_error * rng.uniform(0.5, 4.0, p.shape))
    moved = _rows(ray_offset.offset_origin(*(_vectors(a) for a in (p, n, error, w))))
    side = np.sign(np.sum(w * n, axis=1))
    along = np.sum((moved - p) * n, axis=1)
    assert (side != 0).all()
    assert np.array_equal(np.sign(along), side)
    required = np.sum(np.abs(n) * error, axis=1)
    # The float32 distance dot(|n|, error) (3 roundings), offset n * distance (1) and n's
    # float32 length (|n|^2 = 1 +- 3u) can fall short of the exact box extent by a few
    # units of roundoff; the final step to the next float adds more than that except
    # where the offset dwarfs p (relative error 1: measured 1.5e-7 short).
    assert (side * along >= required * (1 - 8 * EPS32)).all()


def test_offset_origin_steps_at_least_one_float_even_when_the_offset_rounds_away():
    """An error far below p's float spacing: p + offset rounds back to p, and every
    coordinate with a non-zero normal component still moves exactly one float to the
    side of w (rounding cannot eat the offset)."""
    _, p, n, w = _points_normals_directions(2)
    error = np.full_like(p, 1e-25)
    moved = _rows(ray_offset.offset_origin(*(_vectors(a) for a in (p, n, error, w))))
    side = np.sign(np.sum(w * n, axis=1))
    towards = np.where(side[:, None] * n > 0, np.inf, -np.inf).astype(np.float32)
    expected = np.nextafter(p.astype(np.float32), towards).astype(np.float64)
    nonzero = n != 0
    assert nonzero.mean() > 0.99
    np.testing.assert_array_equal(moved[nonzero], expected[nonzero])
    assert (np.sign(np.sum((moved - p) * n, axis=1)) == side).all()


def test_zero_error_adds_no_fixed_epsilon():
    """No fixed epsilon: a point known exactly (error 0, e.g. on an untransformed flat
    shape) stays where it is (pbrt-v4's OffsetRayOrigin)."""
    _, p, n, w = _points_normals_directions(3, 1000)
    moved = _rows(ray_offset.offset_origin(*(_vectors(a) for a in (p, n, np.zeros_like(p), w))))
    np.testing.assert_array_equal(moved, p)


def test_shadow_distance_is_a_unit_direction_and_a_length_just_short_of_the_target():
    rng, origin, _, _ = _points_normals_directions(4)
    target = float32_exact(origin + rng.normal(size=origin.shape) * 10.0 ** rng.uniform(-2, 3, (len(origin), 1)))
    w, t_max = ray_offset.shadow_distance(_vectors(origin), _vectors(target))
    w, t_max = _rows(w), np.asarray(t_max, np.float64)
    delta = target - origin
    dist = np.linalg.norm(delta, axis=1)
    # Unit and parallel to target - origin up to a few float32 roundings (subtraction,
    # norm, division).
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=8 * EPS32)
    np.testing.assert_allclose(w, delta / dist[:, None], atol=8 * EPS32)
    # The length is short by SHADOW_SHORTENING relative, up to the same few roundings:
    # the shortening (16 units of roundoff) dominates them, so the ray always ends before
    # the target.
    shortening = 1.0 - t_max / dist
    np.testing.assert_allclose(shortening, ray_offset.SHADOW_SHORTENING, atol=8 * EPS32)
    assert (t_max < dist).all()
    assert ray_offset.SHADOW_SHORTENING > 8 * EPS32


# -- spawned rays in loaded scenes -----------------------------------------------------------

SPAWN_KINDS = ["sphere", "cube", "cylinder", "rectangle", "disk"]


@pytest.fixture(scope="module")
def spawn_scene():
    """One scene of the five analytic kinds, each twice under a random affine map: near
    the origin and about 1e3 away (where float32 error boxes are largest), 12 units apart
    so that no two overlap. Returns the scene and, per instance, the hit records of 2048
    rays aimed at it from outside its box (float32-exact rays, Dr.Jit records)."""
    rng = np.random.default_rng(11)
    kinds, matrices = [], []
    for far in (0.0, 1.0):
        for k, kind in enumerate(SPAWN_KINDS):
            m = random_affine(rng, 0.5)
            m[:3, 3] += np.array([12.0 * k, 0.0, 0.0]) + far * np.array([1000.0, -700.0, 400.0])
            kinds.append(kind)
            matrices.append(m)
    scene = instancing.load_scene({"instances": [{"model": k, "to_world": m.tolist()}
                                                 for k, m in zip(kinds, matrices)]})
    lo, hi = scene.instance_bounds(np.arange(len(kinds)))
    o, d = [], []
    for i in range(len(kinds)):
        centre, radius = 0.5 * (lo[i] + hi[i]), 0.5 * np.linalg.norm(hi[i] - lo[i])
        start = centre + 3.0 * radius * _unit(rng, 2048)
        aim = centre + 0.4 * (hi[i] - lo[i]) * rng.uniform(-1, 1, (2048, 3))
        o.append(start)
        d.append((aim - start) / np.linalg.norm(aim - start, axis=1, keepdims=True))
    o, d = float32_exact(np.concatenate(o)), float32_exact(np.concatenate(d))
    hit = _evaluated(scene.intersect(_vectors(o), _vectors(d)))
    target = np.repeat(np.arange(len(kinds)), 2048)
    instance = np.asarray(hit.instance)
    for i in range(len(kinds)):
        assert (instance[target == i] == i).mean() > 0.2, kinds[i]
    return scene, kinds, hit, instance


def _outward_directions(rng, hit, n_lanes):
    """Cosine-weighted directions around the hit normal (grazing ones included), plus a
    quarter of nearly tangent ones (1e-3 rad above the surface)."""
    u1 = Float(rng.random(n_lanes, dtype=np.float32))
    u2 = Float(rng.random(n_lanes, dtype=np.float32))
    w = _rows(to_frame(hit.n, square_to_cosine_hemisphere(u1, u2)))
    n = _rows(hit.n)
    tangent = np.cross(n, _unit(rng, n_lanes))
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-30)
    grazing = tangent + 1e-3 * n
    nearly_tangent = rng.random(n_lanes) < 0.25
    w[nearly_tangent] = grazing[nearly_tangent]
    return float32_exact(w / np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-30))


def test_rays_leaving_a_convex_surface_outward_never_hit_it_again(spawn_scene):
    """Each of these shapes lies on one side of its tangent plane, so a ray leaving its
    surface outward (dot(w, n) > 0) from an offset origin never hits the same instance
    again; a self-intersection at t ~ 0 would (and does for many of them without the
    offset)."""
    scene, kinds, hit, instance = spawn_scene
    w = _outward_directions(np.random.default_rng(12), hit, len(instance))
    valid = instance >= 0
    assert (np.sum(w * _rows(hit.n), axis=1)[valid] > 0).all()
    origin = ray_offset.offset_origin(hit.p, hit.n, hit.error, _vectors(w))
    again = np.asarray(scene.intersect(origin, _vectors(w)).instance)
    # Control: started at the hit points themselves, many of the same rays re-hit their
    # own surface (measured: a third to a half), so the check below can fail.
    unmoved = np.asarray(scene.intersect(hit.p, _vectors(w)).instance)
    assert (unmoved[valid] == instance[valid]).mean() > 0.1
    for i, kind in enumerate(kinds):
        mine = instance == i
        assert mine.sum() > 500
        assert not (again[mine] == i).any(), (kind, i, (again[mine] == i).sum())


def test_rays_leaving_a_closed_surface_inward_hit_its_far_side(spawn_scene):
    """Inward rays (dot(w, n) < 0) from an offset origin cross the shape: their next hit
    is the far side, at the chord length the float64 closed form gives in object space
    (never a re-hit at t ~ 0). Hits within an error box of an edge of the cube, whose
    offset origin may land beyond the adjacent face (outside the cube in float64: that
    ray then enters through the adjacent face), are left out; they are rare."""
    scene, kinds, hit, instance = spawn_scene
    w_all = -_outward_directions(np.random.default_rng(13), hit, len(instance))
    origin_all = _rows(ray_offset.offset_origin(hit.p, hit.n, hit.error, _vectors(w_all)))
    for i, kind in enumerate(kinds):
        if kind not in ("sphere", "cube"):
            continue
        mine = instance == i
        w, origin = w_all[mine], origin_all[mine]
        # Far side in float64 object space: the exit parameter of the ray from the
        # (offset) origin, with the stored matrix.
        inv = np.linalg.inv(scene.to_world[i])
        o_obj = origin @ inv[:3, :3].T + inv[:3, 3]
        d_obj = w @ inv[:3, :3].T
        if kind == "sphere":
            a = np.sum(d_obj * d_obj, axis=1)
            b = np.sum(o_obj * d_obj, axis=1)
            c = np.sum(o_obj * o_obj, axis=1) - 1.0
            t_exit = (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a
            inside = c < 0
        else:
            with np.errstate(divide="ignore"):
                t_slab = np.stack([(-1.0 - o_obj) / d_obj, (1.0 - o_obj) / d_obj])
            t_exit = np.max(t_slab, axis=0).min(axis=1)
            inside = np.abs(o_obj).max(axis=1) < 1.0
        chord = inside & (t_exit > 1e-4)
        assert chord.mean() > 0.99, (kind, i, chord.mean())
        again = _evaluated(scene.intersect(_vectors(origin[chord]), _vectors(w[chord])))
        assert (np.asarray(again.instance) == i).all(), (kind, i)
        # float32 intersection against float64 on the same stored matrix: measured 6e-8
        # relative near the origin; 1e-5 leaves room for the float32 world -> object map
        # 1e3 away and for the shortest chords (rays 1e-3 rad inside the tangent plane),
        # and is far from a re-hit at t ~ 0.
        np.testing.assert_allclose(np.asarray(again.t, np.float64), t_exit[chord], rtol=1e-5)
