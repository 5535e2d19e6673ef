"""The command line: runs on the bundled scenes, fails cleanly on bad input."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
SCENES = sorted((ROOT / "scenes").glob("*.json"))


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "instancing", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("scene", SCENES, ids=[s.name for s in SCENES])
def test_intersect_runs_on_every_bundled_scene(scene):
    result = run_cli("intersect", str(scene), "--rays", "20000", "--width", "24")
    assert result.returncode == 0, result.stderr
    assert "Mrays/s" in result.stdout and "instances" in result.stdout


@pytest.mark.parametrize("scene", SCENES, ids=[s.name for s in SCENES])
@pytest.mark.parametrize("integrator", ["aov", "direct", "path"])
def test_render_writes_exr_and_png_for_every_bundled_scene(scene, integrator, tmp_path):
    out = tmp_path / "image.exr"
    result = run_cli("render", str(scene), "-o", str(out), "--spp", "2", "--width", "24",
                     "--height", "18", "--integrator", integrator)
    assert result.returncode == 0, result.stderr
    assert "rendered 24x18 at 2 spp" in result.stdout and "Msamples/s" in result.stdout
    import instancing
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


def test_malformed_scene_names_the_culprit(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"instances": [{"model": "sphere", "to_world": [{"scale": 0}]}]}')
    result = run_cli("intersect", str(bad))
    assert result.returncode == 2
    assert "instance #0" in result.stderr and "singular" in result.stderr
    assert "Traceback" not in result.stderr
