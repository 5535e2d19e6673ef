"""Intersection accuracy against float64, ours beside Mitsuba 3 on the same rays.

For every model kind, six random affine instances (rotation, non-uniform
scale, shear, translation; half of them reflected) and ``--rays`` random rays
through their bounds (many starting inside the shapes), rounded to float32
before either renderer sees them, prints the median and 99.9th-percentile
relative t error and the 99.9th-percentile normal angle of both renderers
against the float64 reference (:mod:`instancing.validation.reference`) on

* the scene as given (float64 transforms), and
* the scene as both renderers store it (transforms and mesh vertices rounded
  to float32): this isolates each renderer's arithmetic from the rounding of
  its input.

The same comparison, on fewer rays, is asserted by
``tests/test_intersection.py``. Mitsuba's mesh normals flip under reflection,
so its angles are taken up to sign.

Usage: python -m benchmarks.accuracy [--rays 100000] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from instancing.validation import reference

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from scene_helpers import (KINDS, angle_deg, load, mitsuba_intersect,  # noqa: E402
                           random_affine, random_rays, reference_instances)


def _figures(t, n, ref, oriented) -> tuple[float, float, float]:
    both = np.isfinite(t) & np.isfinite(ref["t"])
    rel_t = np.abs(t[both] - ref["t"][both]) / ref["t"][both]
    ang = angle_deg(n[both], ref["n"][both], oriented)
    return float(np.median(rel_t)), float(np.quantile(rel_t, 0.999)), float(np.quantile(ang, 0.999))


def measure(kind: str, rays: int, seed: int) -> dict:
    """Errors of ours and Mitsuba's against both float64 references for one model kind."""
    rng = np.random.default_rng(seed + KINDS.index(kind))
    matrices = [random_affine(rng, 3.0, reflect=i % 2 == 1) for i in range(6)]
    kinds = [kind] * len(matrices)
    scene = load(kinds, matrices)
    o, d = random_rays(rng, *scene.bounds, rays)
    ours = scene.intersect(o, d)
    theirs = mitsuba_intersect(kinds, matrices, o, d)
    row = {"kind": kind}
    for name, rounding in (("given", np.float64), ("float32", np.float32)):
        ref = reference.intersect_instances(reference_instances(kinds, matrices, rounding), o, d)
        row[name] = {"ours": _figures(ours.t, ours.n, ref, True),
                     "mitsuba": _figures(theirs["t"], theirs["n"], ref, False)}
    return row


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rays", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.rays < 1:
        parser.error("--rays must be positive")
    print(f"{args.rays} rays per kind, 6 random affine instances; median / 99.9% relative t error, "
          "99.9% normal error (deg); ours | Mitsuba")
    print(f"{'kind':>10} {'scene':>8} {'ours t':>20} {'Mitsuba t':>20} {'ours n':>9} {'Mitsuba n':>9}")
    rows = []
    for kind in KINDS:
        row = measure(kind, args.rays, args.seed)
        rows.append(row)
        for name in ("given", "float32"):
            (om, ot, on), (mm, mt, mn) = row[name]["ours"], row[name]["mitsuba"]
            print(f"{kind:>10} {name:>8} {om:>9.2g} / {ot:<8.2g} {mm:>9.2g} / {mt:<8.2g} "
                  f"{on:>9.2g} {mn:>9.2g}", flush=True)
    return rows


if __name__ == "__main__":
    main()
