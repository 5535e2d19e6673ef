"""The benchmark suite's one entry point: ``python -m benchmarks``.

Runs, in this order and in one invocation, so that every ratio against
Mitsuba 3 is measured in the same run on the same machine:

* ``intersect``: intersection throughput of every model kind, 10 .. 100 000
  instances, beside Mitsuba's ``ray_intersect_preliminary`` and full
  ``ray_intersect`` (:mod:`benchmarks.intersect`);
* ``render``: render time against error for ``direct`` and ``path`` on the
  bundled scenes, both renderers, the speed-up at equal error and a log-log
  plot (:mod:`benchmarks.render_error`);
* ``scale``: load and build time, memory per instance, first against later
  frames and optimisation steps, 1e3 .. 1e6 instances (:mod:`benchmarks.scale`);
* ``loading``: ``load_scene`` of 1e4 and 1e5 instances given as matrices in a dict (and as
  operation lists), a JSON file, an ``.npy`` file and Mitsuba XML, beside Mitsuba's
  ``load_file`` of the XML (:mod:`benchmarks.loading`).

Each part prints its own table; the results of all parts are written to one
JSON file (default ``benchmarks/results.json``), each with the time it started and the
machine it ran on (:mod:`benchmarks.machine`);
``--parts`` updates the parts it runs and keeps the others' entries.
``--quick`` runs every part at a small size (a smoke test of the suite, not
figures to quote; it never mixes with full results in one file).
The stress suite (``python -m benchmarks.stress``) and the gradient benchmarks
(``python -m benchmarks.gradients``, ``python -m benchmarks.recovery``) have
their own entry points: they measure accuracy rather than speed.

Usage: python -m benchmarks [--parts intersect render scale loading] [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from benchmarks import intersect, loading, render_error, scale
from benchmarks.machine import describe, line

ROOT = Path(__file__).resolve().parent.parent

#: Each part's entry point and its arguments at full and at --quick size.
PARTS = {
    "intersect": (intersect.main, [], ["--kinds", "sphere", "mesh", "--counts", "10", "1000",
                                       "--rays", "65536", "--repeats", "1"]),
    "render": (render_error.main, [], ["--scenes", "light_point", "--width", "32", "--height", "24",
                                       "--max-spp", "4", "--target-spp", "2", "--reference-spp", "16",
                                       "--repeats", "1", "--plot", ""]),
    "scale": (scale.main, [], ["--counts", "1000", "--repeats", "1", "--size", "32", "--rays", "65536",
                               "--step-max", "1000"]),
    "loading": (loading.main, [], ["--counts", "1000", "--triangles", "20000", "--repeats", "1"]),
}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--parts", nargs="+", choices=list(PARTS), default=list(PARTS))
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke test of the suite")
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results.json"),
                        help="where to write the results of every part ('' for nowhere)")
    args = parser.parse_args(argv)
    path = Path(args.json) if args.json else None
    previous = json.loads(path.read_text()) if path is not None and path.is_file() else {}
    results = previous if previous.get("quick") == args.quick else {}
    results["quick"] = args.quick
    machine = describe()
    print(f"machine: {line(machine)}", flush=True)
    for name in args.parts:
        run, full, quick = PARTS[name]
        print(f"\n== {name} ==", flush=True)
        results[f"{name}_started"] = time.strftime("%Y-%m-%d %H:%M:%S")
        results[f"{name}_machine"] = machine
        start = time.perf_counter()
        results[name] = run(quick if args.quick else full)
        results[f"{name}_seconds"] = time.perf_counter() - start
    if path is not None:
        path.write_text(json.dumps(results, indent=1, default=float))
        print(f"\nresults written to {args.json}")
    return results


if __name__ == "__main__":
    main()
