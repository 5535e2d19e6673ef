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
    (["render", "scenes/showcase.json", "-o", "out.png"], "expected a .exr"),
    (["render", "missing.json"], "scene file not found"),
])
def test_bad_arguments_give_a_clear_message_and_no_traceback(args, message):
    result = run_cli(*args)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_malformed_scene_names_the_culprit(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"instances": [{"model": "sphere", "to_world": [{"scale": 0}]}]}')
    result = run_cli("intersect", str(bad))
    assert result.returncode == 2
    assert "instance #0" in result.stderr and "singular" in result.stderr
    assert "Traceback" not in result.stderr
