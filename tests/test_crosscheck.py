"""The cross-check against Mitsuba: agreement on a small scene, and the exit status."""

from pathlib import Path

import numpy as np
import pytest

import instancing
from instancing import cli
from instancing.validation import crosscheck as crosscheck_module
from instancing.validation.crosscheck import crosscheck
from instancing.rendering.film import render

ROOT = Path(__file__).resolve().parent.parent


SCENES = sorted((ROOT / "scenes").glob("*.json"))


#: Bundled scenes whose check takes 15 - 25 s here (a million rays; the float64 reference
#: against 100 352 triangles): slow cases.
LARGE_SCENES = ("forest", "sphere_field", "terrain")


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.slow) if p.stem in LARGE_SCENES
                                  else p for p in SCENES], ids=[p.stem for p in SCENES])
def test_rays_agree_with_mitsuba_and_float64_on_every_bundled_scene(path, tmp_path):
    scene = instancing.load_scene(path)
    report = crosscheck(scene, random_rays=10_000, reference_rays=500, integrators=(), out_dir=tmp_path,
                        source=path)
    rows = {name: (ours, theirs) for name, ours, theirs in report.rows}
    assert rows["hit/miss disagreement"][0].startswith("0 ")
    assert rows["instance agreement (ties and Mitsuba's errors excluded)"][0].startswith("1.000000")
    assert float(rows["vs float64, scene as given: median rel. t error"][0]) <= 1e-6
    assert float(rows["vs float64, float32 scene (500 rays): median rel. t error"][0]) <= 1e-6
    assert report.failures == []


def test_coincident_faces_count_as_ties_not_disagreements(tmp_path):
    scene = instancing.load_scene(ROOT / "scenes" / "cornell_box.json")
    report = crosscheck(scene, random_rays=20_000, reference_rays=1_000, integrators=(), out_dir=tmp_path)
    rows = dict((n, o) for n, o, _ in report.rows)
    ties, ours_wrong, _ = rows["instance disagreements: ties / ours wrong / Mitsuba wrong"].split(" / ")
    assert int(ties) > 0 and int(ours_wrong) == 0


@pytest.mark.parametrize("reversed_first", [False, True])
def test_coplanar_faces_within_one_mesh_are_ties_not_normal_errors(tmp_path, reversed_first):
    """A mesh holding a quad twice with opposite windings (as Mitsuba's Cornell box ceiling
    does): a renderer may hit either copy, with either normal; the float64 check counts those
    rays as ties and leaves their normals out instead of failing on 180-degree errors."""
    faces = ["f 1 2 3", "f 1 3 4", "f 1 3 2", "f 1 4 3"]
    if reversed_first:
        faces = faces[2:] + faces[:2]
    mesh = tmp_path / "double_quad.obj"
    mesh.write_text("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n" + "\n".join(faces) + "\n")
    scene = instancing.load_scene({
        "models": {"ceiling": {"type": "obj", "filename": str(mesh), "face_normals": True}},
        "instances": [{"id": "ceiling", "model": "ceiling", "to_world": [{"translate": [0, 0, 2]}, {"scale": 2}]},
                      {"id": "floor", "model": "rectangle", "to_world": [{"scale": 3}]}],
        "camera": {"type": "perspective", "fov": 60, "width": 48, "height": 36,
                   "to_world": [{"look_at": {"origin": [0, -1.5, 1], "target": [0, 0, 2], "up": [0, 0, 1]}}]}})
    report = crosscheck(scene, random_rays=5_000, reference_rays=2_000, integrators=(), out_dir=tmp_path)
    rows = {name: ours for name, ours, _ in report.rows}
    # (Our traversal keeps the other copy than the reference's on this mesh, in either order.)
    assert int(rows["vs float64, float32 scene (2000 rays): coincident-surface ties (normals left out)"]) > 20
    assert float(rows["vs float64, float32 scene (2000 rays): 99.9% normal error (deg, same surface)"]) < 1e-3
    assert report.failures == []


def test_image_tolerance_failures_give_a_non_zero_exit(tmp_path, monkeypatch, capsys):
    # Our direct render made 5 % too bright: far outside 1 % and Monte Carlo noise at 64 spp.
    def brighter(*args, **kwargs):
        return render(*args, **kwargs) * 1.05

    monkeypatch.setattr(crosscheck_module, "render", brighter)
    status = cli.main(["crosscheck", "scenes/light_point.json", "--rays", "2000", "--reference-rays", "500",
                       "--spp", "64", "--reference-spp", "256", "--integrators", "direct",
                       "--width", "24", "--height", "18", "--out", str(tmp_path)])
    assert status == 1
    out = capsys.readouterr().out
    assert "FAIL: direct relative RMSE" in out
    assert (tmp_path / "diff_direct.exr").exists()
    image, _ = instancing.read_exr(tmp_path / "diff_direct.exr")
    assert np.isfinite(image).all() and image.mean() > 0


def test_images_agree_with_mitsuba_within_monte_carlo_noise(tmp_path):
    report = crosscheck(instancing.load_scene(ROOT / "scenes" / "light_area.json"), random_rays=1000,
                        reference_rays=100, integrators=("direct",), spp=64, reference_spp=256)
    rows = {name: (ours, theirs) for name, ours, theirs in report.rows}
    ours = float(rows["image direct: rel. RMSE vs Mitsuba 256 spp"][0].split()[0])
    floor = float(rows["image direct: Mitsuba's own rel. RMSE at 64 spp"][1])
    assert ours <= 1.1 * floor
    assert report.failures == []


def test_image_part_reports_block_errors_next_to_mitsubas_own():
    """Bias apart from noise: the 8x8-block error of our render against Mitsuba's
    reference, beside Mitsuba's own at the same spp (a material scene, read from XML)."""
    scene = instancing.load_scene(ROOT / "scenes" / "materials" / "roughconductor.xml", width=64, height=48)
    report = crosscheck(scene, random_rays=1000, reference_rays=100, integrators=("direct",),
                        spp=256, reference_spp=4096)
    rows = {name: (ours, theirs) for name, ours, theirs in report.rows}
    ours, theirs = (float(v) for v in rows["image direct: 8x8-block error vs Mitsuba 4096 spp "
                                           "(ours / Mitsuba at 256 spp)"])
    assert 0 < ours <= 1.5 * theirs
    assert report.failures == []


def test_repeated_renders_give_the_root_mean_square_of_their_errors(monkeypatch):
    """With repeats, both renderers render that many times at the low spp (ours with
    seeds 0, 1, ...) and each image error is the RMS over the renders: recomputed here
    from the same renders."""
    scene = instancing.load_scene(ROOT / "scenes" / "light_point.json")
    scene.set_camera(scene.camera.with_size(24, 16))
    seeds = []

    def recorded(*args, **kwargs):
        seeds.append(kwargs["seed"])
        return render(*args, **kwargs)

    monkeypatch.setattr(crosscheck_module, "render", recorded)
    report = crosscheck(scene, random_rays=1000, reference_rays=100, integrators=("direct",),
                        spp=16, reference_spp=256, repeats=3)
    rows = {name: (ours, theirs) for name, ours, theirs in report.rows}
    assert seeds == [0, 1, 2]
    assert rows["images: renders per renderer at the low spp (errors: RMS over them)"] == ("3", "3")
    mi = crosscheck_module._mitsuba()
    mscene = mi.load_dict(instancing.to_mitsuba(scene, spp=256))
    reference = np.asarray(mi.render(mscene, integrator=mi.load_dict({"type": "direct"}), spp=256))
    errors = [np.sqrt(np.mean((np.asarray(render(scene, "direct", spp=16, seed=k)) - reference) ** 2))
              / np.abs(reference).mean() for k in range(3)]
    ours = float(rows["image direct: rel. RMSE vs Mitsuba 256 spp"][0].split()[0])
    np.testing.assert_allclose(ours, np.sqrt(np.mean(np.square(errors))), rtol=1e-3)
    with pytest.raises(ValueError, match="repeats"):
        crosscheck(scene, random_rays=100, reference_rays=10, integrators=("direct",), repeats=0)
