"""``instancing crosscheck`` on every bundled scene: rays and images against Mitsuba.

    python -m benchmarks.crosscheck_scenes [--width 64] [--height 48] [--spp 64]
                                           [--reference-spp 1024] [--repeats 16] [--large]

Every bundled scene with a camera (``scenes/*.json``, ``scenes/envmap.xml``, and the
material and sensor scenes ``scenes/materials/*.xml``, ``scenes/sensors/*.xml``; the large
forest, sphere field and terrain with ``--large``) goes through
:func:`instancing.validation.crosscheck.crosscheck` at a reduced film size: random rays
(hit/miss and instance agreement with Mitsuba) and the ``direct`` and ``path`` images. Per
scene and integrator it prints our 8x8-block error against Mitsuba's reference at
``--reference-spp`` beside Mitsuba's own at ``--spp`` (other seeds; both the root mean
square over ``--repeats`` renders, so that a firefly does not decide), their ratio (the
real-scenes issue's bar: at most 1.5), and whether every crosscheck tolerance held.
Results go to ``benchmarks/results_crosscheck.txt``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import instancing
from instancing.validation.crosscheck import crosscheck

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"
LARGE = ("forest", "sphere_field", "terrain")
#: The block-error ratio (ours / Mitsuba's own at the same spp) a scene must stay within.
RATIO_LIMIT = 1.5


def bundled_scenes(large: bool) -> list[Path]:
    """The bundled scenes with a camera, the large ones only with ``large``."""
    paths = [p for p in sorted(SCENES.glob("*.json")) if large or p.stem not in LARGE]
    paths += [SCENES / "envmap.xml"]
    for folder in ("materials", "sensors"):
        paths += [p for p in sorted((SCENES / folder).glob("*.xml")) if p.stem != "stage"]
    return [p for p in paths if instancing.load_scene(p).camera is not None]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=64)
    parser.add_argument("--height", type=int, default=48)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument("--rays", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=16)
    parser.add_argument("--large", action="store_true")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results_crosscheck.txt"))
    args = parser.parse_args(argv)
    lines = [f"crosscheck of the bundled scenes at {args.width}x{args.height}: ours at {args.spp} spp, "
             f"Mitsuba's reference at {args.reference_spp} spp; block error = 8x8-block error "
             f"against the reference, RMS over {args.repeats} renders of each renderer",
             f"{'scene':<28} {'integrator':<8} {'ours':>9} {'Mitsuba':>9} {'ratio':>6}  "
             f"{'ray agreement':<14} {'tolerances':<10} {'s':>5}"]
    print("\n".join(lines), flush=True)
    worst = 0.0
    for path in bundled_scenes(args.large):
        scene = instancing.load_scene(path)
        scene.set_camera(scene.camera.with_size(args.width, args.height))
        start = time.perf_counter()
        report = crosscheck(scene, random_rays=args.rays, reference_rays=1000,
                            integrators=("direct", "path"), spp=args.spp,
                            reference_spp=args.reference_spp, source=path, repeats=args.repeats)
        seconds = time.perf_counter() - start
        rows = {name: (ours, theirs) for name, ours, theirs in report.rows}
        agreement = rows["instance agreement (ties and Mitsuba's errors excluded)"][0]
        name = str(path.relative_to(SCENES))
        for integrator in ("direct", "path"):
            key = next(k for k in rows if k.startswith(f"image {integrator}: 8x8-block error"))
            ours, theirs = (float(v) for v in rows[key])
            ratio = ours / theirs if theirs > 0 else float("inf")
            worst = max(worst, ratio)
            line = (f"{name:<28} {integrator:<8} {ours:9.4g} {theirs:9.4g} {ratio:6.2f}  "
                    f"{agreement:<14} {'met' if not report.failures else 'FAILED':<10} {seconds:5.1f}")
            lines.append(line)
            print(line, flush=True)
        for failure in report.failures:
            lines.append(f"  FAIL: {failure}")
            print(lines[-1], flush=True)
    lines.append(f"worst block-error ratio {worst:.2f} (bar {RATIO_LIMIT})")
    print(lines[-1])
    Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
