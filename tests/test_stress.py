"""The numerical stress suite (instancing/stress.py) in a reduced size, its targets as assertions.

Seeded rays, float64 references. Mitsuba's figures are left to the benchmark
(``python -m benchmarks.stress``); here only ours are asserted. Targets that
float32 cannot reach are expected failures with the measured figure in the
reason (see the README's robustness section).
"""

from __future__ import annotations

import numpy as np
import pytest

import instancing
from instancing.validation import reference, stress
from instancing.core.backend import Array3f, Float
from instancing.rendering.integrators.direct import integrate_direct
from instancing.scene.lights import LightSet

#: Rays per case in CI.
COUNT = 4000
FAR = 1e5 * np.array([0.6, -0.48, 0.64])


def _figures(rows) -> dict:
    return {r.measure: r.ours for r in rows}


def _assert_targets(rows):
    missed = [(r.case, r.measure, r.ours, r.target) for r in rows if r.met is False]
    assert not missed, missed


@pytest.mark.parametrize("distance", [1e5, 1e6, 1e7])
def test_far_from_origin_hits_as_at_the_origin_and_no_self_intersection(distance):
    """Hit points 1e5 - 1e7 from the origin (moved off any power-of-two grid) are as accurate,
    in ulps of their distance from the rendering origin, as the same instances' at the origin
    (against the float64 scene, which the float32 rounding of the transform dominates), within
    4 ulp of the stored scene, and spawn without self-intersections."""
    def figures(centre):
        rows = stress.per_kind_cases("far", np.random.default_rng(1), COUNT, 1.0, centre, mitsuba=False)
        return _figures(rows)

    far, near = figures(stress.placement(distance)), figures(np.zeros(3))
    assert far["self-intersections"] == 0.0 and far["spawned rays"] > COUNT
    assert far["p ULP 99.9%, f32 scene"] <= stress.TARGETS["p ULP 99.9%"]
    for measure in ("p ULP 99.9%", "p off-surface ULP 99.9%", "normal error 99.9% (deg)"):
        assert far[measure] <= 1.1 * near[measure] + 1e-9, (measure, far[measure], near[measure])


@pytest.mark.slow
def test_shear_and_reflection_keep_normals_outward_and_spawn_cleanly():
    rng = np.random.default_rng(2)
    linear = np.array([[-1.0, 0.9, 0.5], [0.0, 1.2, -0.8], [0.0, 0.0, 0.7]])  # det < 0
    rows = stress.per_kind_cases("shear", rng, COUNT, 1.0, [2, -1, 3], linear=linear, mitsuba=False)
    figures = _figures(rows)
    assert figures["det<0 orientation ok"] == 1.0
    assert figures["self-intersections"] == 0.0


def test_nearly_degenerate_axis_spawns_without_self_intersection():
    rng = np.random.default_rng(3)
    rows = stress.per_kind_cases("degenerate", rng, COUNT, 1.0, [3, 1, 2], linear=np.diag([1.0, 1.0, 1e-6]),
                                 mitsuba=False)
    figures = _figures(rows)
    assert figures["self-intersections"] == 0.0
    # Phase 2 in float64 maps the origin across the 1e-6 axis without amplified rounding.
    assert figures["p ULP 99.9%"] <= stress.TARGETS["p ULP 99.9%"]


def test_nearly_degenerate_axis_keeps_analytic_normals():
    """The inverse scales o - b by 1e6 across the thin axis; in float32 that flipped normals
    near the rim (99.9th percentile 180 degrees). The squashed mesh is left out: its two
    faces lie < 2 ulp of t apart, which float32 traversal cannot order."""
    rng = np.random.default_rng(3)
    rows = stress.per_kind_cases("degenerate", rng, COUNT, 1.0, [3, 1, 2], linear=np.diag([1.0, 1.0, 1e-6]),
                                 kinds=("sphere", "cube", "rectangle", "disk"), mitsuba=False)
    assert _figures(rows)["normal error 99.9% (deg)"] < 1e-4


def test_ordinary_scales_hit_within_4_ulp_of_the_float32_scene():
    """Against the float64 reference on the float32-rounded transforms, hit points are within
    the 4 ulp target; against the float64 transforms the scene's own rounding adds more
    (moved along the ray by 1/cos of the incidence: see the README)."""
    rng = np.random.default_rng(10)
    rows = stress.per_kind_cases("scale", rng, COUNT, 100.0, 100.0 * np.array([2.0, -1.5, 2.0]),
                                 mitsuba=False)
    assert _figures(rows)["p ULP 99.9%, f32 scene"] <= stress.TARGETS["p ULP 99.9%"]


@pytest.mark.parametrize("length", [1e-12, 1e12])
def test_huge_and_tiny_direction_lengths_hit_within_4_ulp(length):
    _assert_targets(stress.direction_length_case(np.random.default_rng(11), COUNT, length))


@pytest.mark.slow
@pytest.mark.parametrize("scale", [1e-4, 1e4])
def test_tiny_and_huge_scales_spawn_without_self_intersection(scale):
    rng = np.random.default_rng(4)
    rows = stress.per_kind_cases("scale", rng, COUNT, scale, scale * np.array([2.0, -1.5, 2.0]),
                                 mitsuba=False)
    figures = _figures(rows)
    assert figures["self-intersections"] == 0.0
    # Across the surface the point is within the 4 ulp target even where it is not along it,
    # and along it too against the float32-rounded scene.
    assert figures["p off-surface ULP 99.9%"] <= stress.TARGETS["p ULP 99.9%"]
    assert figures["p ULP 99.9%, f32 scene"] <= stress.TARGETS["p ULP 99.9%"]


@pytest.mark.parametrize("kind, gap", [("cube", 0.0), ("cube", 1e-6), ("mesh", 0.0), ("mesh", 1e-4)])
def test_touching_instances_neither_leak_nor_wrongly_block(kind, gap):
    rows = stress.gap_case(np.random.default_rng(5), COUNT, kind, gap, mitsuba=False)
    _assert_targets(rows)


def test_float64_transform_chains_stay_within_1e6_of_identity():
    rows = stress.composition_rows(np.random.default_rng(6))
    row = next(r for r in rows if r.case.endswith("float64") and r.measure == "T T^-1 drift")
    assert row.met, row.ours


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="float32 per-lane chains drift 1.8e-6 .. 2.7e-6 after 1 000 rotations "
                   "(~1 ulp per product; Mitsuba's float32 chain 1.7e-6); float64 ones drift 1e-14")
def test_float32_lane_chains_stay_within_1e6_of_identity():
    rows = stress.composition_rows(np.random.default_rng(6))
    row = next(r for r in rows if r.case.endswith("float32 lanes") and r.measure == "T T^-1 drift")
    assert row.met, row.ours


def test_points_at_infinity_ignore_translation():
    _assert_targets(stress.infinity_rows(np.random.default_rng(7), COUNT))


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="at 1e-3 rad the hit moves along the ray by the float32 "
                   "rounding of the surface over sin(angle): ~9e3 ulp, Mitsuba 1.9e4")
def test_grazing_hits_within_4_ulp():
    rows = stress.grazing_case(np.random.default_rng(8), 2000, 1e-3)
    _assert_targets(rows)


@pytest.mark.slow
def test_grazing_rays_spawn_without_self_intersection():
    rows = stress.grazing_case(np.random.default_rng(8), 2000, 1e-4)
    figures = _figures(rows)
    assert figures["self-intersections"] == 0.0


def _far_scene():
    """A plane (20 x 20) and a unit sphere resting 1 above it, at FAR, lit by a sun from above."""
    centre = FAR
    return instancing.load_scene({
        "materials": {"grey": {"type": "diffuse", "reflectance": 0.5}},
        "instances": [
            {"model": "rectangle", "material": "grey",
             "to_world": [{"translate": centre.tolist()}, {"scale": 10.0}]},
            {"model": "sphere", "material": "grey",
             "to_world": [{"translate": (centre + [0, 0, 2.0]).tolist()}]}],
        "lights": [{"type": "directional", "direction": [0.3, 0.2, -1.0], "irradiance": 3.0}],
    })


def test_far_from_origin_direct_lighting_matches_closed_form_without_acne():
    """Direct lighting at 1e5 from the origin, per camera ray: (albedo / pi) E cos where the
    float64 reference sees the sun, 0 in the sphere's shadow. Rays whose shadow ray grazes
    the sphere's silhouette (within 1e-4 of its radius) are left out."""
    scene = _far_scene()
    rng = np.random.default_rng(9)
    n = 20_000
    eye = FAR + np.array([0.0, -9.0, 6.0])
    aim = FAR + np.column_stack([rng.uniform(-8, 8, (n, 2)), np.zeros(n)])
    aim[: n // 4] = FAR + [0, 0, 2.0] + rng.normal(size=(n // 4, 3)) * 0.7  # the sphere
    o = np.tile(eye, (n, 1)).astype(np.float32).astype(np.float64)
    d = (aim - o).astype(np.float32).astype(np.float64)
    # The integrator traces in the scene's rendering space: origins moved there in float64.
    local = o - scene.origin
    radiance = integrate_direct(scene, LightSet(scene), Array3f(*[Float(local[:, k]) for k in range(3)]),
                                Array3f(*[Float(d[:, k]) for k in range(3)]), None)
    ours = np.asarray(radiance.x, np.float64)

    instances = [{"kind": "rectangle", "to_world": scene.to_world[0]},
                 {"kind": "sphere", "to_world": scene.to_world[1]}]
    ref = reference.intersect_instances(instances, o, d)
    sun = -np.array([0.3, 0.2, -1.0]) / np.linalg.norm([0.3, 0.2, -1.0])
    cos = ref["n"] @ sun
    # Float64 shadow test against the sphere (centre c, radius 1): distance of the sun ray
    # from the centre, and whether the centre lies ahead of the point.
    rel = FAR + [0, 0, 2.0] - ref["p"]
    ahead = rel @ sun
    miss_distance = np.linalg.norm(rel - ahead[:, None] * sun, axis=1)
    shadowed = (ahead > 0) & (miss_distance < 1.0) & (ref["instance"] == 0)
    silhouette = np.abs(miss_distance - 1.0) < 1e-4
    expected = np.where(shadowed | (cos <= 0), 0.0, 0.5 / np.pi * 3.0 * cos)
    ok = np.isfinite(ref["t"]) & ~silhouette & (ref["instance"] >= 0)
    assert ok.sum() > 0.9 * n and (shadowed & ok).sum() > 200 and (ref["instance"] == 1).sum() > 2000
    # Acne would show as lit points turned black (self-shadowed); leaks as shadowed points lit.
    np.testing.assert_allclose(ours[ok], expected[ok], rtol=1e-3, atol=1e-6)
