"""The README and docs/: a five-minute README, links that resolve, no commit hashes, and a
performance page that is the one the benchmark results generate."""

from __future__ import annotations

import os
import re
from pathlib import Path

from benchmarks import machine, performance_page

REPO = Path(__file__).resolve().parent.parent
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def test_readme_is_a_five_minute_guide():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    # The two commands, exactly as the set-up and CI run them.
    assert "bash setup.sh && .venv/bin/instancing render scenes/showcase.json -o showcase.exr" in text
    assert "bash setup.sh && .venv/bin/python -m pytest -q" in text


def test_every_relative_link_resolves():
    broken = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" not in target and not (page.parent / target).exists():
                broken.append(f"{page.relative_to(REPO)} -> {target}")
    assert not broken, broken


def test_no_commit_hashes_in_readme_and_docs():
    # A hash is 7 - 40 hex digits with at least one letter and one digit, standing alone.
    hashes = [f"{page.name}: {word}" for page in PAGES
              for word in re.findall(r"\b[0-9a-f]{7,40}\b", page.read_text())
              if re.search(r"[a-f]", word) and re.search(r"[0-9]", word)]
    assert not hashes, hashes


def test_performance_page_is_generated_from_the_results():
    assert performance_page.main(["--check"]) == 0



def test_public_scenes_are_summarised_by_group_from_their_figures():
    """The page's public-scenes part: each matching file's time at equal error in its group's
    geometric mean, non-matching files named (with the note of a reference that Mitsuba
    renders biased) and refused ones, the headline over all runs."""
    run = {"settings": {"folders": ["data"], "size": [64, 48], "spp": 256, "reference_spp": 4096,
                        "repeats": 4},
           "files": [
               {"file": "data/bsdf_a.xml", "verdict": "match", "ours_error": 1.0, "mitsuba_error": 1.0,
                "ours_s": 2.0, "mitsuba_s": 1.0, "equal_error": 2.0},
               {"file": "data/bsdf_b.xml", "verdict": "match", "ours_error": 1.0, "mitsuba_error": 1.0,
                "ours_s": 8.0, "mitsuba_s": 1.0, "equal_error": 8.0},
               {"file": "data/lego/scene.xml", "verdict": "match", "ours_error": 1.0,
                "mitsuba_error": 2.0, "ours_s": 2.0, "mitsuba_s": 1.0, "equal_error": 0.5},
               # A match without a noise measure (a file's aov integrator): timed, not at equal error.
               {"file": "data/integrator_aov.xml", "verdict": "match", "ours_error": 1.0,
                "mitsuba_error": 1.0, "ours_s": 3.0, "mitsuba_s": 1.0, "equal_error": None},
               {"file": "data/bsdf_c.xml", "verdict": "MISS", "ours_error": 3.0, "mitsuba_error": 1.0,
                "ours_s": 1.0, "mitsuba_s": 1.0, "equal_error": None,
                "detail": "block error ours 3.0000, Mitsuba's 1.0000 (3.00x); render ours 1.000 s"},
               {"file": "data/hello.xml", "verdict": "MISS", "ours_error": 4.0, "mitsuba_error": 1.0,
                "ours_s": 1.0, "mitsuba_s": 1.0, "equal_error": None,
                "detail": "block error ours 4.0000 (4.00x); Mitsuba 3.9.1's direct is biased (tests/t.py::a)"},
               {"file": "data/shape_x.xml", "verdict": "refused", "detail": 'x.xml:3: <shape type="x">: '
                "shape type 'x' is not supported; supported: ['sphere']"}]}
    text = "\n".join(performance_page.public_section([run]))
    assert "| bsdf | 2 | 4.00x | 4.00x | 2.00x - 8.00x | 0 |" in text
    assert "| lego | 1 | 2.00x | 0.50x | 0.50x | 1 |" in text
    assert "| integrator | 1 | 3.00x | - | - | - |" in text
    assert "| all | 4 | 3.13x | 2.00x | 0.50x - 8.00x | 1 |" in text
    assert "match 3" not in text and "match 4" in text
    assert "`bsdf_c.xml` (3.00x Mitsuba's error)" in text
    assert "`hello.xml` (4.00x Mitsuba's error; Mitsuba 3.9.1's direct is biased (tests/t.py::a))" in text
    assert "`shape_x.xml` (shape type 'x' is not supported)" in text
    lines = performance_page.headline({}, None, [run, run])
    assert lines == ["* Mitsuba's example scenes (8 files that both render alike, 6 with a noise measure): "
                     "our time at equal error 2.00x Mitsuba's (geometric mean; 0.50x - 8.00x, ours "
                     "faster on 2)."]


def test_the_page_names_the_machine_of_each_results_part():
    """Each part's machine as its results record it (benchmarks/machine.py), "not recorded"
    for results from before the records; this machine's description read from the system."""
    here = machine.describe()
    assert here["cores"] == os.cpu_count() and here["threads"] >= 1 and here["cpu"]
    assert machine.line(here).startswith(f"{here['cpu']}, {here['cores']} logical cores")
    results = {"intersect": {}, "intersect_machine": here, "loading": {}}
    run = {"settings": {"folders": ["mitsuba-data"]}, "machine": here, "files": []}
    text = "\n".join(performance_page.machines_section(results, [("gradients", {}), ("recovery", None),
                                                                  ("public scenes", run)]))
    assert f"| `python -m benchmarks`: intersect | {machine.line(here)} |" in text
    assert "| `python -m benchmarks`: loading | not recorded |" in text
    assert f"| public scenes | {machine.line(here)} |" in text
    assert "recovery" not in text and "gradients" not in text  # (no results, or empty ones)


def _figures(text: str) -> set[float]:
    """Decimal numbers and ratios ("98x"); version numbers such as 3.9.1 left out."""
    return {float(n) for n in re.findall(r"(?<![\d.])\d+\.\d+(?![\d.])|(?<![\d.])\d+(?=x)", text)}


def test_readme_performance_figures_are_the_generated_pages():
    """Every figure of the README's performance summary is one of the generated performance
    page's summary (the README is written by hand; its figures must not outlive a benchmark
    run)."""
    readme = (REPO / "README.md").read_text()
    summary = readme.split("## Performance in brief", 1)[1].split("\n## ", 1)[0]
    page = (REPO / "docs" / "performance.md").read_text()
    in_short = page.split("In short:", 1)[1].split("\n## ", 1)[0]
    missing = sorted(_figures(summary) - _figures(in_short))
    assert _figures(summary) and not missing, missing
