"""B-spline curves (``instancing.models.bspline_curve``): hits, normals, surface coordinates and
derivatives against Mitsuba's ``bsplinecurve``, a float64 reference and central differences;
renders beside Mitsuba's; the errors of bad curves."""

from __future__ import annotations

import numpy as np
import pytest

import instancing
from instancing.core.backend import MITSUBA_VARIANT
from instancing.io.image import write_png
from instancing.models.bspline_curve import MAX_SPLITS, BSplineCurveData, split_pieces
from instancing.validation import reference
from instancing.validation.crosscheck import crosscheck
from scene_helpers import (angle_deg, as_array3f, instanced_curve_xml, assert_boundary_terms_refused, assert_hit_derivatives_match,
                           assert_path_render_matches_mitsuba, lamp_and_floor_scene, random_affine, rays_around,
                           turned_about_z, write_curve_file)

import mitsuba as mi  # noqa: E402  (after instancing, which selects libLLVM)

_TURNS = np.linspace(0.0, 6.0 * np.pi, 14)
#: A thin helix (radius a thirtieth of its coil's), a curve whose radius swells and shrinks
#: faster than it runs, and one with a repeated control point (a kink).
CURVES = [np.stack([0.6 * np.cos(_TURNS), 0.6 * np.sin(_TURNS), np.linspace(-1, 1, 14),
                    np.full(14, 0.02)], axis=1),
          np.array([[-1.5, -1, 0, 0.05], [-1, -0.5, 0.3, 0.4], [-0.5, -1, 0.1, 0.1], [0, -0.4, -0.2, 0.3],
                    [0.5, -1.2, 0, 0.02], [1, -0.8, 0.4, 0.25]]),
          np.array([[1, 1, 0, 0.1], [1.2, 1.1, 0, 0.1], [1.2, 1.1, 0, 0.1], [1.5, 1.0, 0.2, 0.15],
                    [1.4, 1.5, 0.3, 0.05]])]


def reference_hits(curve, to_world, o, d):
    """The float64 reference's record of rays (o, d) on one instance of ``curve``."""
    return reference.intersect_instances(reference.instance_list(
        ["bsplinecurve"], [to_world], [None], curves=[(curve.points, curve.radii, curve.first)]), o, d)


def assert_as_mitsubas_or_the_reference(ours, o, d, t, t_mi):
    """Our t of rays (o, d) on the scene ``ours`` (one curve instance) within 1e-5 of
    Mitsuba's ``t_mi`` (inf for a miss) on all but a few of them, and on those few (Mitsuba,
    through Embree, misses a tube now and then, and its float32 t is off by up to about 3e-5)
    within 1e-5 (or 1e-6 of the scene's unit) of the float64 reference's."""
    with np.errstate(invalid="ignore"):
        differ = np.flatnonzero((np.isfinite(t) != np.isfinite(t_mi)) | (np.abs(t - t_mi) > 1e-5 * t_mi))
    assert len(differ) <= 0.001 * len(t)
    ref = reference_hits(ours.description.models[0].curve, ours.to_world[0], o[differ], d[differ])
    # (A t of a few 1e-4 from an origin next to the tube: its float32 rounding of ~1e-7 first.)
    np.testing.assert_allclose(t[differ], ref["t"], rtol=1e-5, atol=1e-6)


def test_pieces_split_the_segments_in_order_until_straight():
    """Each segment's pieces cover [0, 1] in order, each the segment's own cubic on its range
    (de Casteljau's halves), and each follows its chord or was halved MAX_SPLITS times."""
    curve = BSplineCurveData.from_curves(CURVES, "test")
    bezier = curve.bezier()
    pieces, segment, span = split_pieces(bezier)
    assert np.array_equal(segment, np.sort(segment))
    for s in range(len(bezier)):
        mine = span[segment == s]
        assert mine[0, 0] == 0 and mine[-1, 1] == 1 and np.array_equal(mine[1:, 0], mine[:-1, 1])
    # The piece's cubic at its parameter w is the segment's at v0 + w (v1 - v0).
    w = np.linspace(0, 1, 7)
    bernstein = np.stack([(1 - w) ** 3, 3 * w * (1 - w) ** 2, 3 * w * w * (1 - w), w ** 3], axis=1)
    v = span[:, :1] + w * (span[:, 1:] - span[:, :1])
    whole = np.stack([(1 - v) ** 3, 3 * v * (1 - v) ** 2, 3 * v * v * (1 - v), v ** 3], axis=-1)
    np.testing.assert_allclose(np.einsum("wi,pik->pwk", bernstein, pieces),
                               np.einsum("pwi,pik->pwk", whole, bezier[segment]), atol=1e-12)
    xyz = pieces[:, :, :3]
    chord = xyz[:, 3] - xyz[:, 0]
    legs = np.abs(3 * np.diff(xyz, axis=1) - chord[:, None]).max(axis=(1, 2))
    straight = legs <= 0.2 * np.linalg.norm(chord, axis=1)
    assert (straight | (span[:, 1] - span[:, 0] == 2.0 ** -MAX_SPLITS)).all()
    assert len(pieces) > len(bezier)


def test_hits_normals_and_coordinates_match_mitsubas(tmp_path):
    """A plain curve whose to_world scales unevenly (moving the control points, not the
    radii), bump-mapped and anisotropic (so that uv, dp/du and dp/dv are computed): on
    20 000 rays from all around, hits, t, normals, uv and the tangents as Mitsuba's. Where the
    two differ, the float64 reference agrees with ours."""
    curves = write_curve_file(tmp_path / "c.txt", CURVES)
    write_png(tmp_path / "bumps.png", np.random.default_rng(0).random((16, 16, 3)))
    xml = tmp_path / "scene.xml"
    xml.write_text(f'''<scene version="3.0.0">
        <shape type="bsplinecurve"><string name="filename" value="{curves}"/>
            <transform name="to_world"><scale x="1.5" y="0.8" z="1.2"/><rotate z="1" angle="20"/>
                <translate x="0.3" y="-0.2" z="0.1"/></transform>
            <bsdf type="bumpmap"><texture type="bitmap"><string name="filename" value="bumps.png"/></texture>
                <bsdf type="roughconductor"><float name="alpha_u" value="0.1"/><float name="alpha_v" value="0.3"/></bsdf>
            </bsdf>
        </shape></scene>''')
    ours = instancing.load_scene(xml)
    mi.set_variant(MITSUBA_VARIANT)
    theirs = mi.load_file(str(xml))
    o, d = rays_around(np.random.default_rng(4), np.array([0.3, -0.2, 0.1]), 1.0, 20_000)
    hit = ours.intersect(as_array3f(o), as_array3f(d))
    si = theirs.ray_intersect(mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32))))
    t, t_mi = np.asarray(hit.t, np.float64), np.asarray(si.t, np.float64)
    t_mi = np.where(np.isfinite(t_mi), t_mi, np.inf)
    both = np.isfinite(t) & np.isfinite(t_mi)
    assert both.sum() > 2500
    assert_as_mitsubas_or_the_reference(ours, o, d, t, t_mi)
    assert (np.asarray(hit.prim)[both] == np.asarray(si.prim_index)[both]).all()
    assert np.quantile(angle_deg(np.asarray(hit.n).T[both], np.asarray(si.n).T[both]), 0.999) < 0.05
    uv, uv_mi = np.asarray(hit.uv).T[both], np.asarray(si.uv).T[both]
    du = np.abs((uv[:, 0] - uv_mi[:, 0] + 0.5) % 1.0 - 0.5)  # u wraps around the tube
    assert np.quantile(du, 0.999) < 1e-4
    np.testing.assert_allclose(uv[:, 1], uv_mi[:, 1], atol=1e-5)
    for ours_k, theirs_k in ((hit.dpdu, si.dp_du), (hit.dpdv, si.dp_dv), (hit.ss, si.sh_frame.s)):
        a, b = np.asarray(ours_k).T[both], np.asarray(theirs_k).T[both]
        assert np.quantile(angle_deg(a, b), 0.999) < 0.05
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1), rtol=1e-3)


@pytest.mark.parametrize("reflect", [False, True])
def test_instanced_curves_match_the_float64_reference(reflect):
    """Under a random affine instance (rotation, shear, uneven scale; reflected): hits, t and
    normals against the float64 NumPy reference (the circle equation's sign changes on a
    fine grid of each segment, bisected)."""
    rng = np.random.default_rng(9)
    to_world = random_affine(rng, spread=1.0, reflect=reflect)
    scene = instancing.load_scene({"models": {"c": {"type": "bsplinecurve", "curves": CURVES}},
                                   "instances": [{"model": "c", "to_world": to_world.tolist()}]})
    centre = (to_world @ [0.0, 0.0, 0.0, 1.0])[:3]
    o, d = rays_around(rng, centre, 0.5 * np.linalg.norm(to_world[:3, :3], axis=0).max(), 3000)
    hit = scene.intersect(as_array3f(o), as_array3f(d))
    ref = reference_hits(scene.description.models[0].curve, scene.to_world[0], o, d)
    t = np.asarray(hit.t, np.float64)
    assert np.isfinite(ref["t"]).sum() > 400
    assert (np.isfinite(t) != np.isfinite(ref["t"])).sum() <= 1
    both = np.isfinite(t) & np.isfinite(ref["t"])
    np.testing.assert_allclose(t[both], ref["t"][both], rtol=1e-5)
    assert np.quantile(angle_deg(np.asarray(hit.n, np.float64).T[both], ref["n"][both]), 0.999) < 0.01
    assert (np.asarray(hit.prim)[both] == ref["prim"][both]).all()


def test_a_curve_instance_renders_as_mitsubas(tmp_path):
    """Textured curves in a rotated, sheared instance over a floor under an area lamp, `path`:
    image mean within 0.5 %, 8x8-pixel block means within 1.5 % of it."""
    curves = write_curve_file(tmp_path / "c.txt", CURVES)
    assert_path_render_matches_mitsuba(lamp_and_floor_scene(
        {"c": {"type": "bsplinecurve", "filename": str(curves),
               "points_to_world": [{"translate": [0, 0, 1.2]}, {"rotate": {"axis": [0, 0, 1], "angle": -30}}]}},
        {"check": {"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": [{"scale": [4, 8, 1]}]}}},
        {"model": "c", "material": "check",
         "to_world": [[1.2, 0.3, 0, -0.2], [0, 1.0, 0.2, 0.1], [0.1, 0, 0.9, 0.1], [0, 0, 0, 1]]}, [0, -5, 4]))


@pytest.mark.parametrize("which", ["tx", "angle"])
def test_hit_derivatives_match_central_differences(which):
    """d t / d param and d p / d param of hits on a curve instance, for a translation and a
    rotation angle, against central differences of the float64 reference (step 1e-4)."""
    base = np.diag([1.5, 1.0, 1.2, 1.0])
    o, d = rays_around(np.random.default_rng(12), (turned_about_z(20.0, 0.3, base) @ [0, 0, 0, 1])[:3], 1.2, 300)
    scene = instancing.load_scene({"models": {"c": {"type": "bsplinecurve", "curves": CURVES}},
                                   "instances": [{"model": "c", "to_world": turned_about_z(20.0, 0.3, base).tolist()}]})
    curve = scene.description.models[0].curve
    assert_hit_derivatives_match(scene, base, which, o, d,
                                 lambda to_world: reference_hits(curve, to_world, o, d), 40)


@pytest.mark.parametrize("spec, message", [
    ("0 0 0 1\n1 0 0 1\n2 0 0 1\n", "curve 0 has 3 control points; a B-spline curve needs at least 4"),
    ("0 0 0 1\n1 0 0 x\n", "line 2: expected x, y, z and radius"),
    ("0 0 0 1\n1 0 0 1\n2 0 0 1\n3 0 0 -1\n", "curve 0 has a negative radius"),
    ("0 0 0 1\n1 0 0 1\n2 0 inf 1\n3 0 0 1\n", "curve 0 holds a control point that is not finite"),
    ("0 0 0 1\n1 0 0 1\n2 3e38 0 1\n3 0 0 1\n", r"curve 0 holds a control point beyond 1e\+18"),
    ("\n\n", "no control points"),
    ({}, "either a 'filename'"),
    ({"curves": CURVES, "radius": 1}, r"unknown keys \['radius'\]"),
    ({"curves": [np.ones((3, 4))]}, "curve 0 has 3 control points"),
    ({"curves": [np.ones((5, 3))]}, "rows of x, y, z and radius"),
    ({"filename": "none.txt"}, "none.txt' not found"),
    ({"curves": CURVES, "points_to_world": [{"scale": 1e20}]}, r"moves a control point beyond 1e\+18"),
])
def test_bad_curves_are_refused_by_name(tmp_path, spec, message):
    """Bad curve files (``spec`` the file's text) and bad models (``spec`` the model's keys
    besides its type), each refused naming the model and what is wrong."""
    if isinstance(spec, str):
        (tmp_path / "bad.txt").write_text(spec)
        spec = {"filename": str(tmp_path / "bad.txt")}
    with pytest.raises(instancing.SceneError, match=f"model 'c'.*{message}"):
        instancing.load_scene({"models": {"c": {"type": "bsplinecurve", **spec}}, "instances": [{"model": "c"}]})


def test_an_emitting_curve_and_boundary_terms_through_curves_are_refused():
    with pytest.raises(instancing.SceneError, match=r"instance #0.*is an bsplinecurve, which cannot emit"):
        instancing.load_scene({"models": {"c": {"type": "bsplinecurve", "curves": CURVES}},
                               "instances": [{"model": "c", "emitter": {"type": "area", "radiance": 1}}]})
    assert_boundary_terms_refused(("c", {"type": "bsplinecurve", "curves": CURVES}), [{"scale": 1}], [0, 0, 0])


def test_a_curve_in_an_instanced_shapegroup_matches_mitsubas(tmp_path):
    """A curve with its own to_world (points moved, radii kept) inside a shapegroup, instanced
    under a rotation and an uneven scale (which scales the radii too); exported back to
    Mitsuba from arrays (through a curve file the export writes): rays as Mitsuba's."""
    xml = instanced_curve_xml(tmp_path / "scene.xml", "bsplinecurve", CURVES)
    mi.set_variant(MITSUBA_VARIANT)
    arrays = instancing.load_scene({"models": {"c": {
        "type": "bsplinecurve", "curves": CURVES, "points_to_world": [{"rotate": {"axis": [0, 0, 1], "angle": 25}}]}},
        "instances": [{"model": "c", "to_world": [{"scale": [1.3, 1.0, 0.8]}]}]})
    for ours, theirs in ((instancing.load_scene(xml), mi.load_file(str(xml))),
                         (arrays, mi.load_dict(instancing.to_mitsuba(arrays)))):
        o, d = rays_around(np.random.default_rng(6), np.array([0.1, 0.3, -0.2]), 1.2, 20_000)
        t = np.asarray(ours.intersect(as_array3f(o), as_array3f(d)).t, np.float64)
        si = theirs.ray_intersect(mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)),
                                           mi.Vector3f(*d.T.astype(np.float32))))
        t_mi = np.where(np.isfinite(np.asarray(si.t)), np.asarray(si.t, np.float64), np.inf)
        assert (np.isfinite(t) & np.isfinite(t_mi)).sum() > 2500
        assert_as_mitsubas_or_the_reference(ours, o, d, t, t_mi)


def test_a_curve_scene_passes_the_crosscheck(tmp_path):
    """``instancing crosscheck`` on a scene of a curve instance: rays against Mitsuba's and the
    float64 reference's within the cross-check's tolerances."""
    scene = instancing.load_scene({
        "models": {"c": {"type": "bsplinecurve", "curves": CURVES}},
        "instances": [{"model": "c", "to_world": [{"rotate": {"axis": [1, 0, 0], "angle": 30}}, {"scale": [1, 1.3, 1]}]}],
        "camera": {"type": "perspective", "fov": 40, "width": 32, "height": 24, "to_world": [
            {"look_at": {"origin": [0, -5, 2], "target": [0, 0, 0], "up": [0, 0, 1]}}]}})
    report = crosscheck(scene, random_rays=10_000, reference_rays=500, integrators=(), out_dir=tmp_path)
    assert report.failures == []
