"""Linear curves (``instancing.models.linear_curve``): hits, normals, surface coordinates and
derivatives against Mitsuba's ``linearcurve``, a float64 reference and central differences;
renders beside Mitsuba's; the errors of bad curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import instancing
from instancing.core.backend import MITSUBA_VARIANT
from instancing.validation import reference
from scene_helpers import (angle_deg, as_array3f, instanced_curve_xml, assert_boundary_terms_refused, assert_hit_derivatives_match,
                           assert_path_render_matches_mitsuba, lamp_and_floor_scene, random_affine, rays_around,
                           turned_about_z, write_curve_file)

import mitsuba as mi  # noqa: E402  (after instancing, which selects libLLVM)

#: Curves with growing and shrinking radii, a kink, a repeated control point, and a radius
#: jump that swallows a sphere (the hull is then the larger one).
CURVES = [np.array([[0, 0, 0, 0.2], [1, 0, 0, 0.5], [1.5, 0.8, 0.3, 0.3], [1.6, 1.5, 0.2, 0.1]]),
          np.array([[-1, 1, 0.5, 0.15], [-0.4, 1.2, 0.4, 0.15], [-0.4, 1.2, 0.4, 0.15],
                    [0.2, 1.9, 0.1, 0.05]]),
          np.array([[0.5, -1, 0, 0.1], [0.6, -1, 0.1, 0.45], [1.5, -0.8, 0.2, 0.2]])]


def hits_as_mitsubas(xml: Path, rng, centre, spread):
    """Both renderers' hits of 20 000 rays from all around ``centre`` on the scene file
    ``xml``: at most 3 differ in hit or miss (rays from inside a tube's joint), t and
    normals agree; (our record, Mitsuba's, the rays both hit)."""
    ours = instancing.load_scene(xml)
    mi.set_variant(MITSUBA_VARIANT)
    theirs = mi.load_file(str(xml))
    o, d = rays_around(rng, centre, spread, 20_000)
    hit = ours.intersect(as_array3f(o), as_array3f(d))
    si = theirs.ray_intersect(mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32))))
    t, t_mi = np.asarray(hit.t, np.float64), np.asarray(si.t, np.float64)
    t_mi = np.where(np.isfinite(t_mi), t_mi, np.inf)
    both = np.isfinite(t) & np.isfinite(t_mi)
    assert both.sum() > 3000
    assert (np.isfinite(t) != np.isfinite(t_mi)).sum() <= 3
    np.testing.assert_allclose(t[both], t_mi[both], rtol=2e-4, atol=1e-6)  # float32 Mitsuba
    assert np.quantile(angle_deg(np.asarray(hit.n).T[both], np.asarray(si.n).T[both]), 0.999) < 0.05
    return hit, si, both


def test_hits_normals_and_coordinates_match_mitsubas(tmp_path):
    """A plain curve whose to_world scales unevenly (moving the control points, not the
    radii), textured (so that uv and dp/du, dp/dv are computed): on 20 000 rays from all
    around, hits, t, normals, uv and the tangents as Mitsuba's."""
    curves = write_curve_file(tmp_path / "c.txt", CURVES)
    xml = tmp_path / "scene.xml"
    xml.write_text(f'''<scene version="3.0.0">
        <shape type="linearcurve"><string name="filename" value="{curves}"/>
            <transform name="to_world"><scale x="1.5" y="0.8" z="1.2"/><rotate z="1" angle="20"/>
                <translate x="0.3" y="-0.2" z="0.1"/></transform>
            <bsdf type="diffuse"><texture name="reflectance" type="checkerboard"/></bsdf>
        </shape></scene>''')
    hit, si, both = hits_as_mitsubas(xml, np.random.default_rng(4), np.array([0.8, 0.5, 0.2]), 1.0)
    # The same segment but where a hit lies on a joint (both segments' at once).
    same = both & (np.asarray(hit.prim) == np.asarray(si.prim_index))
    assert (both & ~same).sum() <= 3
    uv, uv_mi = np.asarray(hit.uv).T[same], np.asarray(si.uv).T[same]
    # u wraps around the tube: compare on the circle.
    du = np.abs((uv[:, 0] - uv_mi[:, 0] + 0.5) % 1.0 - 0.5)
    assert np.quantile(du, 0.999) < 1e-4
    np.testing.assert_allclose(uv[:, 1], uv_mi[:, 1], atol=1e-4)
    ss, ss_mi = np.asarray(hit.ss).T[same], np.asarray(si.sh_frame.s).T[same]
    assert np.quantile(angle_deg(ss, ss_mi), 0.999) < 0.05


@pytest.mark.parametrize("reflect", [False, True])
def test_instanced_curves_match_the_float64_reference(reflect):
    """Under a random affine instance (rotation, shear, uneven scale; reflected): hits, t and
    normals against the float64 NumPy reference, segment by segment."""
    rng = np.random.default_rng(9)
    to_world = random_affine(rng, spread=1.0, reflect=reflect)
    scene = instancing.load_scene({"models": {"c": {"type": "linearcurve", "curves": CURVES}},
                                   "instances": [{"model": "c", "to_world": to_world.tolist()}]})
    centre = (to_world @ [0.5, 0.5, 0.2, 1.0])[:3]
    o, d = rays_around(rng, centre, np.linalg.norm(to_world[:3, :3], axis=0).max(), 6000)
    hit = scene.intersect(as_array3f(o), as_array3f(d))
    model = scene.description.models[0].curve
    ref = reference.intersect_instances(reference.instance_list(
        ["linearcurve"], [scene.to_world[0]], [None],
        curves=[(model.points, model.radii, model.first, model.left, model.right)]), o, d)
    t = np.asarray(hit.t, np.float64)
    assert np.isfinite(ref["t"]).sum() > 1500
    assert (np.isfinite(t) != np.isfinite(ref["t"])).sum() <= 2
    both = np.isfinite(t) & np.isfinite(ref["t"])
    np.testing.assert_allclose(t[both], ref["t"][both], rtol=1e-5)
    assert np.quantile(angle_deg(np.asarray(hit.n, np.float64).T[both], ref["n"][both]), 0.999) < 0.01
    assert (np.asarray(hit.prim)[both] != ref["prim"][both]).sum() <= 3  # hits on a joint


def test_a_curve_instance_renders_as_mitsubas(tmp_path):
    """Textured curves in a rotated, sheared instance over a floor under an area lamp, `path`:
    image mean within 0.5 %, 8x8-pixel block means within 1.5 % of it."""
    curves = write_curve_file(tmp_path / "c.txt", CURVES)
    assert_path_render_matches_mitsuba(lamp_and_floor_scene(
        {"c": {"type": "linearcurve", "filename": str(curves),
               "points_to_world": [{"rotate": {"axis": [0, 0, 1], "angle": -30}}]}},
        {"check": {"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": [{"scale": [4, 8, 1]}]}}},
        {"model": "c", "material": "check",
         "to_world": [[1.2, 0.3, 0, -0.6], [0, 1.0, 0.2, -0.4], [0.1, 0, 0.9, 0.5], [0, 0, 0, 1]]}, [0, -5, 4]))


@pytest.mark.parametrize("which", ["tx", "angle"])
def test_hit_derivatives_match_central_differences(which):
    """d t / d param and d p / d param of hits on a curve instance (spheres and cones alike),
    for a translation and a rotation angle, against central differences of the float64
    reference (step 1e-4)."""
    base = np.diag([1.5, 1.0, 1.2, 1.0])
    o, d = rays_around(np.random.default_rng(12), (turned_about_z(20.0, 0.3, base) @ [0.5, 0.5, 0.2, 1])[:3],
                   1.5, 400)
    scene = instancing.load_scene({"models": {"c": {"type": "linearcurve", "curves": CURVES}},
                                   "instances": [{"model": "c", "to_world": turned_about_z(20.0, 0.3, base).tolist()}]})
    model = scene.description.models[0].curve
    assert_hit_derivatives_match(
        scene, base, which, o, d,
        lambda to_world: reference.intersect_instances(reference.instance_list(
            ["linearcurve"], [to_world], [None],
            curves=[(model.points, model.radii, model.first, model.left, model.right)]), o, d), 60)


@pytest.mark.parametrize("text, message", [
    ("0 0 0 1\n", "curve 0 has 1 control point"),
    ("0 0 0 1\n1 0 0 x\n", "line 2: expected x, y, z and radius"),
    ("0 0 0 1\n1 0 0\n", "line 2: expected x, y, z and radius"),
    ("0 0 0 1\n1 0 0 -1\n", "curve 0 has a negative radius"),
    ("0 0 0 1\n1 0 nan 1\n", "curve 0 holds a control point that is not finite"),
    ("0 0 0 1\n1 0 0 1e39\n", r"curve 0 holds a control point beyond 1e\+18"),
    ("\n\n", "no control points"),
])
def test_bad_curve_files_are_refused_by_name(tmp_path, text, message):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(instancing.SceneError, match=f"model 'c'.*{message}"):
        instancing.load_scene({"models": {"c": {"type": "linearcurve", "filename": str(path)}},
                               "instances": [{"model": "c"}]})


@pytest.mark.parametrize("spec, message", [
    ({"type": "linearcurve"}, "either a 'filename'"),
    ({"type": "linearcurve", "curves": CURVES, "filename": "c.txt"}, "either a 'filename'"),
    ({"type": "linearcurve", "curves": CURVES, "radius": 1}, r"unknown keys \['radius'\]"),
    ({"type": "linearcurve", "curves": [[["a", 0, 0, 1], [1, 0, 0, 1]]]}, r"curves\[0\] must be an array of numbers"),
    ({"type": "linearcurve", "curves": [np.ones((3, 3))]}, "rows of x, y, z and radius"),
    ({"type": "linearcurve", "filename": "none.txt"}, "none.txt' not found"),
    ({"type": "linearcurve", "curves": CURVES, "points_to_world": [{"scale": 0}]}, "points_to_world"),
])
def test_bad_curve_models_are_refused_by_name(spec, message):
    with pytest.raises(instancing.SceneError, match=f"model 'c'.*{message}"):
        instancing.load_scene({"models": {"c": spec}, "instances": [{"model": "c"}]})


def test_an_emitting_curve_and_boundary_terms_through_curves_are_refused():
    with pytest.raises(instancing.SceneError, match=r"instance #0.*is an linearcurve, which cannot emit"):
        instancing.load_scene({"models": {"c": {"type": "linearcurve", "curves": CURVES}},
                               "instances": [{"model": "c", "emitter": {"type": "area", "radiance": 1}}]})
    assert_boundary_terms_refused(("c", {"type": "linearcurve", "curves": CURVES}), [{"scale": 1}],
                                  [0.5, 0.5, 0.2])


def test_a_curve_in_an_instanced_shapegroup_matches_mitsubas(tmp_path):
    """A curve with its own to_world (points moved, radii kept) inside a shapegroup, instanced
    under a rotation and an uneven scale (which scales the radii too): rays as Mitsuba's."""
    xml = instanced_curve_xml(tmp_path / "scene.xml", "linearcurve", CURVES)
    hits_as_mitsubas(xml, np.random.default_rng(6), np.array([1.0, 0.7, 0.2]), 1.2)


def test_curves_given_as_arrays_export_to_mitsuba():
    """Curves given as arrays (and moved by points_to_world) reach Mitsuba through a curve
    file that the export writes: its hits are ours."""
    scene = instancing.load_scene({"models": {"c": {
        "type": "linearcurve", "curves": CURVES, "points_to_world": [{"rotate": {"axis": [0, 0, 1], "angle": 25}}]}},
        "instances": [{"model": "c", "to_world": [{"scale": [1.3, 1.0, 0.8]}]}]})
    mi.set_variant(MITSUBA_VARIANT)
    theirs = mi.load_dict(instancing.to_mitsuba(scene))
    o, d = rays_around(np.random.default_rng(8), np.array([0.5, 0.8, 0.2]), 1.0, 20_000)
    t = np.asarray(scene.intersect(as_array3f(o), as_array3f(d)).t, np.float64)
    si = theirs.ray_intersect(mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32))))
    t_mi = np.asarray(si.t, np.float64)
    t_mi = np.where(np.isfinite(t_mi), t_mi, np.inf)
    both = np.isfinite(t) & np.isfinite(t_mi)
    assert both.sum() > 3000
    assert (np.isfinite(t) != np.isfinite(t_mi)).sum() <= 3
    np.testing.assert_allclose(t[both], t_mi[both], rtol=2e-4, atol=1e-6)
