"""Every example runs in a small configuration."""

import runpy
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
SMALL_ARGS = {"intersect_instances.py": ["--count", "6", "--rays", "8"],
              "crosscheck_scene.py": ["--rays", "4000", "--spp", "16", "--size", "24"],
              "recover_transforms.py": ["--iterations", "2", "--spp", "1", "--reference-spp", "2"]}
EXPECTED = {"intersect_instances.py": ["instances", "t="],
            "crosscheck_scene.py": ["hit/miss disagreement", "image direct"],
            "recover_transforms.py": ["2 iterations", "box", "recovered.json"]}


@pytest.mark.parametrize("name", sorted(p.name for p in EXAMPLES.glob("*.py")))
def test_example_runs(name, monkeypatch, capsys, tmp_path):
    assert name in SMALL_ARGS, f"add a small configuration for {name}"
    monkeypatch.chdir(tmp_path)  # examples that write files write them here
    monkeypatch.setattr(sys, "argv", [name] + SMALL_ARGS[name])
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    out = capsys.readouterr().out
    assert all(text in out for text in EXPECTED[name])
