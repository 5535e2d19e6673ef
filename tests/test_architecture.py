"""The package's architecture: its layers (import-linter contracts in pyproject.toml),
no import cycles, and no scene parsing outside ``instancing.io``."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LINT = [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
        "sys.exit(lint_imports_command())"]


def _lint(root: Path) -> subprocess.CompletedProcess:
    """lint-imports on the package and pyproject.toml under ``root`` (that copy first on
    the path)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run(LINT, cwd=root, env=env, capture_output=True, text=True, timeout=120)


def _lint_with(tmp_path: Path, module: str, line: str) -> subprocess.CompletedProcess:
    """lint-imports on a copy of the package with ``line`` appended to ``module`` (a path
    under instancing/)."""
    root = tmp_path / "repo"
    shutil.copytree(REPO / "instancing", root / "instancing",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(REPO / "pyproject.toml", root / "pyproject.toml")
    target = root / "instancing" / module
    target.write_text(target.read_text() + f"\n{line}  # noqa: E402,F401\n")
    return _lint(root)


def test_layer_and_cycle_contracts_hold():
    result = _lint(REPO)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "2 kept, 0 broken" in result.stdout


def test_an_upward_import_breaks_the_layer_contract(tmp_path):
    result = _lint_with(tmp_path, "core/warp.py", "from ..rendering import film")
    assert result.returncode != 0
    assert "Layers: cli > validation" in result.stdout and "BROKEN" in result.stdout
    assert "instancing.core.warp -> instancing.rendering.film" in result.stdout


def test_an_import_cycle_within_a_layer_breaks_the_cycle_contract(tmp_path):
    # scene.scene imports scene.lights; the reverse import closes a cycle inside one layer.
    result = _lint_with(tmp_path, "scene/lights.py", "from . import scene")
    assert result.returncode != 0
    assert "No import cycles" in result.stdout and "BROKEN" in result.stdout


def test_no_scene_parsing_outside_io():
    """Scene files and dicts are parsed once, by instancing.io: rendering, differentiation
    and the command line read typed records only."""
    places = [*(REPO / "instancing" / "rendering").rglob("*.py"),
              *(REPO / "instancing" / "ad").rglob("*.py"), REPO / "instancing" / "cli.py"]
    found = [f"{path.relative_to(REPO)}:{number}" for path in places
             for number, line in enumerate(path.read_text().splitlines(), 1)
             if re.search(r"from_dict|parse_transform|parse_scene|parse_camera|parse_lights", line)]
    assert not found, found
