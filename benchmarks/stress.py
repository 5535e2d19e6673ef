"""Numerical stress suite (see :mod:`instancing.validation.stress`) and the throughput cost of error bounds.

Prints the stress table (ours beside Mitsuba 3, against float64, with the
robustness issue's targets), then the intersection throughput on the
benchmark's 1 000-sphere field, same rays, same run:

* phase 1 only (traversal: t, instance, primitive);
* the full hit record (t, p, n, instance, prim) without the error bound;
* the full hit record with the error bound (what the integrators use);
* the full record with bounds plus one offset reflection ray traced per hit.

Usage: python -m benchmarks.stress [--size full|ci] [--rays 1048576] [--repeats 5] [--skip-suite]
       [--cases NAME ...] [--skip-throughput]
"""

from __future__ import annotations

import argparse


import instancing
from instancing.core.backend import Array3f, dr
from instancing.core.ray_offset import offset_origin
from instancing.validation.stress import format_table, run_suite

from .intersect import random_rays, sphere_field, timed


def throughput(rays: int, repeats: int) -> list[tuple[str, float]]:
    """(label, Mrays/s) of the four variants in the module docstring."""
    scene = instancing.load_scene({"instances": [{"model": "sphere", "to_world": sphere_field(1000)}]})
    o_np, d_np = random_rays(*scene.bounds, rays)
    o = Array3f(*[o_np[:, k] - scene.origin[k] for k in range(3)])  # in rendering space
    d = Array3f(*[d_np[:, k] for k in range(3)])

    def phase1():
        hit = scene.intersect_preliminary(o, d)
        dr.eval(hit.t, hit.instance, hit.position)
        dr.sync_thread()

    def full(with_error: bool, spawn: bool = False):
        def run():
            hit = scene.intersect_surface(o, d)
            fields = [hit.t, hit.p, hit.n, hit.instance, hit.prim] + ([hit.error] if with_error else [])
            if spawn:
                w = d - 2.0 * dr.dot(d, hit.n) * hit.n
                fields.append(scene.occluded(offset_origin(hit.p, hit.n, hit.error, w), w, dr.inf, hit.valid))
            dr.eval(*fields)
            dr.sync_thread()
        return run

    variants = [("phase 1 only (t, instance, prim)", phase1),
                ("full record, no error bound", full(False)),
                ("full record with error bound", full(True)),
                ("with error bound + offset reflection ray", full(True, True))]
    return [(label, rays / timed(fn, repeats) / 1e6) for label, fn in variants]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", choices=["full", "ci"], default="full")
    parser.add_argument("--rays", type=int, default=1 << 20)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-suite", action="store_true", help="throughput only")
    parser.add_argument("--cases", nargs="*", default=[],
                        help="only the cases whose names start with these (e.g. far placement)")
    parser.add_argument("--skip-throughput", action="store_true", help="the suite only")
    args = parser.parse_args(argv)
    if not args.skip_suite:
        print(format_table(run_suite(args.size, cases=tuple(args.cases))))
    if args.skip_throughput:
        return
    print(f"\nthroughput, 1 000 spheres, {args.rays} random rays (Mrays/s, median of {args.repeats})")
    rates = throughput(args.rays, args.repeats)
    for label, rate in rates:
        print(f"  {label:<44} {rate:8.2f}")
    print(f"  error bound costs {1 - rates[2][1] / rates[1][1]:.1%} of the full record's throughput")


if __name__ == "__main__":
    main()
