"""The cross-check against Mitsuba: agreement on a small scene, and the exit status."""

import subprocess
import sys
from pathlib import Path

import numpy as np

import instancing
from instancing.crosscheck import crosscheck

ROOT = Path(__file__).resolve().parent.parent


def test_rays_agree_with_mitsuba_and_float64_on_a_bundled_scene(tmp_path):
    scene = instancing.load_scene(ROOT / "scenes" / "light_point.json")
    report = crosscheck(scene, random_rays=20_000, reference_rays=3_000, integrators=(), out_dir=tmp_path)
    rows = {name: (ours, theirs) for name, ours, theirs in report.rows}
    assert rows["hit/miss disagreement"][0].startswith("0 ")
    assert rows["instance agreement (ties excluded)"][0].startswith("1.000000")
    assert float(rows["vs float64: median rel. t error"][0]) <= 1e-6
    assert report.failures == []


def test_coincident_faces_count_as_ties_not_disagreements(tmp_path):
    scene = instancing.load_scene(ROOT / "scenes" / "cornell_box.json")
    report = crosscheck(scene, random_rays=20_000, reference_rays=1_000, integrators=(), out_dir=tmp_path)
    agreement = dict((n, o) for n, o, _ in report.rows)["instance agreement (ties excluded)"]
    assert agreement.startswith("1.000000")


def test_image_tolerance_failures_give_a_non_zero_exit(tmp_path):
    # 2 spp against 8 spp cannot be within 1 % relative RMSE: the command must say so.
    result = subprocess.run(
        [sys.executable, "-m", "instancing", "crosscheck", "scenes/light_point.json", "--rays", "2000",
         "--reference-rays", "500", "--spp", "2", "--reference-spp", "8", "--integrators", "direct",
         "--width", "24", "--height", "18", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 1, result.stderr
    assert "FAIL: direct relative RMSE" in result.stdout
    assert (tmp_path / "diff_direct.exr").exists()
    image, _ = instancing.read_exr(tmp_path / "diff_direct.exr")
    assert np.isfinite(image).all()
