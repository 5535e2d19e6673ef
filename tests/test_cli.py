"""The command line: runs on the bundled scenes, fails cleanly on bad input."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import instancing
import instancing.cli

ROOT = Path(__file__).resolve().parent.parent
SCENES = sorted((ROOT / "scenes").glob("*.json"))


def run_cli(*args):
    """The command in its own process (exit status, output, no traceback)."""
    return subprocess.run([sys.executable, "-m", "instancing", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


def run_main(capsys, *args) -> tuple[int, str, str]:
    """The command in this process (``instancing.cli.main``): status, stdout, stderr."""
    code = instancing.cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("scene", SCENES, ids=[s.name for s in SCENES])
def test_intersect_runs_on_every_bundled_scene(scene, capsys):
    code, out, err = run_main(capsys, "intersect", scene, "--rays", "20000", "--width", "24")
    assert code == 0, err
    assert "Mrays/s" in out and "instances" in out


@pytest.mark.parametrize("scene", SCENES, ids=[s.name for s in SCENES])
@pytest.mark.parametrize("integrator", ["aov", "direct", "path"])
def test_render_writes_exr_and_png_for_every_bundled_scene(scene, integrator, tmp_path, capsys):
    out = tmp_path / "image.exr"
    code, stdout, err = run_main(capsys, "render", scene, "-o", out, "--spp", "2", "--width", "24",
                                 "--height", "18", "--integrator", integrator)
    assert code == 0, err
    assert "rendered 24x18 at 2 spp" in stdout and "Msamples/s" in stdout
    image, channels = instancing.read_exr(out)
    assert image.shape == (18, 24, len(instancing.channel_names(integrator)))
    assert channels == instancing.channel_names(integrator)
    assert np.isfinite(image).all()
    assert (out.with_suffix(".png").exists()) == (integrator != "aov")


@pytest.mark.parametrize("args, message", [
    (["intersect", "no/such/scene.json"], "scene file not found"),
    (["intersect", "scenes/showcase.json", "--rays", "0"], "positive integer"),
    (["intersect", "scenes/showcase.json", "--accel", "octree"], "invalid choice"),
    (["frobnicate"], "invalid choice"),
    (["render", "scenes/showcase.json", "--integrator", "photon"], "invalid choice"),
    (["render", "scenes/showcase.json", "--spp", "-3"], "positive integer"),
    (["render", "scenes/showcase.json", "-o", "out.tif"], "expected a .exr or .png"),
    (["render", "scenes/showcase.json", "-o", "out.png", "--integrator", "aov"], "write a .exr"),
    (["render", "missing.json"], "scene file not found"),
    # No prefix abbreviations: '--sp' is not '--spp'.
    (["render", "scenes/showcase.json", "--sp", "4"], "unrecognized arguments: --sp"),
    (["recover", "scenes/recover_target.json", "--init", "scenes/recover_init.json", "--it", "3"],
     "unrecognized arguments: --it"),
    # The scene argument names what is wrong with it.
    (["render", "."], "is a folder"),
    (["render", "scenes/meshes/torus.obj"], "is a mesh file, not a scene"),
    # Seeds of the random rays, their count and the output folder, before any work.
    (["intersect", "scenes/showcase.json", "--seed", "-1"], "--seed: expected a non-negative integer"),
    (["crosscheck", "scenes/showcase.json", "--seed", "-1"], "--seed: expected a non-negative integer"),
    (["stress", "--size", "ci", "--seed", "-1"], "--seed: expected a non-negative integer"),
    (["intersect", "scenes/showcase.json", "--rays", "99999999999999"], "--rays 99999999999999 would need"),
    (["crosscheck", "scenes/showcase.json", "--rays", "99999999999999"], "--rays 99999999999999 and"),
    (["crosscheck", "scenes/light_point.json", "--integrators", "", "--rays", "64",
      "--reference-rays", "64", "--out", "/proc/no/folder"], "cannot make the output folder '/proc/no/folder'"),
    (["render", "scenes/light_point.json", "-o", "/proc/x.exr"], "cannot write in '/proc'"),
    (["render", "scenes/light_point.json", "-o", "no/such/folder/x.exr"],
     "the folder 'no/such/folder' does not exist"),
    (["render", "scenes/light_point.json", "--integrator", "path", "--max-depth", "99999999999",
      "--width", "8", "--height", "6", "--spp", "1"], "max_depth must be an integer in [-1, 4294967295]"),
    (["render", "scenes/light_point.json", "--integrator", "path", "--rr-depth", "0"],
     "--rr-depth: expected a positive integer"),
    (["render", "scenes/light_point.json", "--bsdf-samples", "-1"],
     "--bsdf-samples: expected a non-negative integer"),
    (["render", "scenes/light_point.json", "--integrator", "path", "--emitter-samples", "2", "--width", "8",
      "--height", "6", "--spp", "1"], "emitter_samples is the 'direct' integrator's"),
    (["render", "scenes/light_point.json", "--integrator", "direct", "--rr-depth", "3", "--width", "8",
      "--height", "6", "--spp", "1"], "rr_depth is the 'path' and 'volpath' integrators'"),
])
def test_bad_arguments_give_a_clear_message_and_no_traceback(args, message):
    result = run_cli(*args)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_render_to_png_writes_only_the_png(tmp_path):
    out = tmp_path / "image.png"
    result = run_cli("render", "scenes/showcase.json", "-o", str(out), "--spp", "1", "--width", "16",
                     "--height", "12")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["image.png"]
    data = out.read_bytes()
    # The PNG signature, then the IHDR chunk: width and height, big-endian.
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    assert (int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")) == (16, 12)


def test_render_takes_the_files_integrator_and_sample_count_unless_given(tmp_path, capsys):
    scene = tmp_path / "lit.xml"
    scene.write_text("""<scene version="3.0.0">
        <integrator type="prb"><integer name="max_depth" value="4"/></integrator>
        <shape type="sphere"/><emitter type="constant"/>
        <sensor type="perspective"><transform name="to_world"><lookat origin="0, 0, -4" target="0, 0, 0"
        up="0, 1, 0"/></transform><sampler type="independent"><integer name="sample_count" value="3"/>
        </sampler><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="6"/>
        <rfilter type="box"/></film></sensor></scene>""")
    code, out, err = run_main(capsys, "render", scene, "-o", tmp_path / "a.exr")
    assert code == 0, err
    assert "rendered 8x6 at 3 spp (path)" in out
    code, out, err = run_main(capsys, "render", scene, "-o", tmp_path / "b.exr", "--integrator", "direct",
                              "--spp", "2")
    assert code == 0, err
    assert "rendered 8x6 at 2 spp (direct)" in out
    # The roulette's start: the file's (Mitsuba's default 5 here), or --rr-depth.
    code, out, err = run_main(capsys, "render", scene, "-o", tmp_path / "c.exr", "--rr-depth", "1")
    assert code == 0, err
    loaded = instancing.load_scene(scene)
    for name, rr_depth in (("a.exr", 5), ("c.exr", 1)):
        np.testing.assert_array_equal(instancing.read_exr(tmp_path / name)[0], np.asarray(instancing.render(
            loaded, "path", spp=3, max_depth=4, rr_depth=rr_depth)))
    assert not np.array_equal(*(instancing.read_exr(tmp_path / name)[0] for name in ("a.exr", "c.exr")))
    # Emitters seen directly: shown unless the file or --hide-emitters hides them (the sky; a
    # box filter, so that no splat of the sphere reaches the corner).
    code, _, err = run_main(capsys, "render", scene, "-o", tmp_path / "d.exr", "--hide-emitters")
    assert code == 0, err
    hidden = instancing.read_exr(tmp_path / "d.exr")[0]
    np.testing.assert_array_equal(hidden, np.asarray(instancing.render(loaded, "path", spp=3, max_depth=4,
                                                                       hide_emitters=True)))
    shown = instancing.read_exr(tmp_path / "a.exr")[0]
    assert (hidden[0, 0] == 0).all() and (shown[0, 0] > 0).all()
    # The direct integrator's samples per strategy: --emitter-samples and --bsdf-samples (the
    # sky then drawn uniformly over the sphere, not found by the BSDF's samples: other noise).
    code, out, err = run_main(capsys, "render", scene, "-o", tmp_path / "e.exr", "--integrator", "direct",
                              "--emitter-samples", "2", "--bsdf-samples", "0")
    assert code == 0, err
    np.testing.assert_array_equal(instancing.read_exr(tmp_path / "e.exr")[0], np.asarray(instancing.render(
        loaded, "direct", spp=3, emitter_samples=2, bsdf_samples=0)))
    assert not np.array_equal(instancing.read_exr(tmp_path / "e.exr")[0], np.asarray(instancing.render(
        loaded, "direct", spp=3)))


def _sphere_file(tmp_path, integrator: str) -> Path:
    """A sphere under a sky, 8x6 at 2 spp, with the file's integrator ``integrator`` (XML)."""
    scene = tmp_path / "sphere.xml"
    scene.write_text(f"""<scene version="3.0.0">{integrator}
        <shape type="sphere"/><emitter type="constant"/>
        <sensor type="perspective"><transform name="to_world"><lookat origin="0, 0, -4" target="0, 0, 0"
        up="0, 1, 0"/></transform><sampler type="independent"><integer name="sample_count" value="2"/>
        </sampler><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="6"/>
        </film></sensor></scene>""")
    return scene


def test_render_of_a_file_with_mitsubas_aov_integrator_writes_its_channels(tmp_path, capsys):
    scene = _sphere_file(tmp_path, '<integrator type="aov"><string name="aovs" value="dd.y:depth, '
                                   'nn:sh_normal"/><integrator type="direct" name="lit"/></integrator>')
    code, out, err = run_main(capsys, "render", scene, "-o", tmp_path / "a.exr")
    assert code == 0, err
    image, names = instancing.read_exr(tmp_path / "a.exr")
    loaded = instancing.load_scene(scene)
    assert sorted(names) == sorted(["lit.R", "lit.G", "lit.B", "dd.y.T", "nn.X", "nn.Y", "nn.Z"])
    by_name = dict(zip(names, np.moveaxis(image, 2, 0)))
    in_order = [by_name[n] for n in instancing.channel_names(None, scene=loaded)]
    np.testing.assert_array_equal(np.stack(in_order, 2), np.asarray(instancing.render(loaded)))
    assert not (tmp_path / "a.png").exists()
    for args, words in ((["-o", tmp_path / "b.png"], "a PNG does not hold"),
                        (["-o", tmp_path / "c.exr", "--max-depth", "2"],
                         "['max_depth'] set with the scene file's")):
        code, _, err = run_main(capsys, "render", scene, *args)
        assert code != 0 and words in err, err
    code, out, err = run_main(capsys, "render", scene, "-o", tmp_path / "d.exr", "--integrator", "path")
    assert code == 0 and instancing.read_exr(tmp_path / "d.exr")[0].shape == (6, 8, 3), err


def test_malformed_scene_names_the_culprit(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"instances": [{"model": "sphere", "to_world": [{"scale": 0}]}]}')
    result = run_cli("intersect", str(bad))
    assert result.returncode == 2
    assert "instance #0" in result.stderr and "singular" in result.stderr
    assert "Traceback" not in result.stderr


def test_render_writes_every_camera_or_the_one_asked_for(tmp_path, capsys):
    """Several cameras: one image per camera, named by id or index; --camera picks one
    (by index or id) and writes the name given; an unknown camera is a clear error."""
    import json
    camera = {"type": "perspective", "fov": 40, "width": 12, "height": 8,
              "to_world": [{"look_at": {"origin": [0, -6, 2], "target": [0, 0, 0], "up": [0, 0, 1]}}]}
    scene = tmp_path / "views.json"
    scene.write_text(json.dumps({"instances": [{"model": "sphere"}], "lights": [
        {"type": "point", "position": [0, -4, 4], "intensity": 20}],
        "cameras": [camera, {**camera, "id": "side", "width": 6}]}))
    for folder in ("all", "1", "side"):
        (tmp_path / folder).mkdir()
    code, _, err = run_main(capsys, "render", scene, "-o", tmp_path / "all" / "v.png", "--spp", "1")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "all").iterdir()) == ["v_0.png", "v_side.png"]
    for which in ("1", "side"):
        out = tmp_path / which / "one.png"
        code, _, err = run_main(capsys, "render", scene, "-o", out, "--spp", "1", "--camera", which)
        assert code == 0, err
        assert [p.name for p in out.parent.iterdir()] == ["one.png"]
        assert int.from_bytes(out.read_bytes()[16:20], "big") == 6
    code, _, err = run_main(capsys, "render", scene, "--camera", "top", "-o", tmp_path / "x.png")
    assert code == 2 and "camera 'top': no such camera" in err


def test_render_of_a_file_with_mitsubas_moment_integrator_writes_its_channels(tmp_path, capsys):
    """All the moment channels in the .exr, the nested integrator's RGB as its preview; a
    .png alone, which would drop the moments, is refused."""
    scene = _sphere_file(tmp_path, '<integrator type="moment"><integrator type="direct"/></integrator>')
    code, out, err = run_main(capsys, "render", scene, "-o", tmp_path / "m.exr")
    assert code == 0, err
    image, names = instancing.read_exr(tmp_path / "m.exr")
    loaded = instancing.load_scene(scene)
    assert sorted(names) == sorted(instancing.channel_names(None, scene=loaded)) and len(names) == 9
    by_name = dict(zip(names, np.moveaxis(image, 2, 0)))
    rendered = np.asarray(instancing.render(loaded))
    np.testing.assert_array_equal(np.stack([by_name[c] for c in ("R", "G", "B")], 2), rendered[..., :3])
    assert (tmp_path / "m.png").exists()
    code, out, err = run_main(capsys, "render", scene, "-o", tmp_path / "only.png")
    assert code != 0 and "the scene's integrator is 'moment'" in err and "write a .exr" in err


def test_render_of_an_rgba_camera_writes_alpha_to_the_exr_and_the_png(tmp_path, capsys):
    """An rgba film: the .exr holds R, G, B and A as rendered; the PNG preview is RGBA with
    straight alpha (the colour divided by the alpha where it is not 0)."""
    import json
    import mitsuba as mi
    camera = {"type": "perspective", "fov": 40, "width": 12, "height": 8, "pixel_format": "rgba",
              "to_world": [{"look_at": {"origin": [0, -6, 0], "target": [0, 0, 0], "up": [0, 0, 1]}}]}
    scene = tmp_path / "alpha.json"
    scene.write_text(json.dumps({"instances": [{"model": "sphere"}], "camera": camera, "lights": [
        {"type": "point", "position": [0, -4, 4], "intensity": 20}]}))
    code, _, err = run_main(capsys, "render", scene, "-o", tmp_path / "a.exr", "--spp", "16")
    assert code == 0, err
    image, names = instancing.read_exr(tmp_path / "a.exr")
    assert names == ["R", "G", "B", "A"]
    np.testing.assert_array_equal(image, np.asarray(instancing.render(instancing.load_scene(scene), spp=16)))
    alpha = image[..., 3]
    assert (alpha == 0).any() and (alpha == 1).any() and ((alpha > 0) & (alpha < 1)).any()
    png = np.asarray(mi.Bitmap(str(tmp_path / "a.png")))
    assert png.shape == (8, 12, 4)
    np.testing.assert_array_equal(png[..., 3], np.floor(alpha * 255 + 0.5).astype(np.uint8))
    edge = (alpha > 0.2) & (alpha < 1)
    straight = instancing.io.image.srgb_encode(np.clip(image[..., :3] / alpha[..., None], 0, 1))
    np.testing.assert_array_equal(png[..., :3][edge], np.floor(straight[edge] * 255 + 0.5).astype(np.uint8))
