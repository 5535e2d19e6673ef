"""SDF grids: rays against a grid model, ours and Mitsuba's ``sdfgrid`` in the same run.

A torus's signed distance sampled on a ``--counts``^3 grid, placed by a scale and a translation
(Mitsuba 3.9.1 bounds a plain grid's voxels wrongly under rotation), and 2^20 rays from
all around it aimed into its box. Times are medians of ``--repeats`` calls in alternation
after one warm-up call each, each call waited for to the end: our traversal alone (t and
ids, ``intersect_preliminary``) against Mitsuba's ``ray_intersect_preliminary``, and our full
hit record (``intersect``: float64 re-intersection, point, normals) against Mitsuba's
``ray_intersect``. Also printed: the hits on which both agree, and the largest relative
difference of their distances.

Usage: python -m benchmarks.sdf_grid [--counts 40] [--rays 1048576] [--repeats 7]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import instancing
from instancing.core.backend import MITSUBA_VARIANT, Array3f, Float, dr, mitsuba_module


def torus_values(n: int) -> np.ndarray:
    """A torus's signed distance (major radius 0.3, minor 0.12) at the corners of an n^3 grid
    over [0, 1]^3, (z, y, x) float32."""
    z, y, x = np.meshgrid(*(np.linspace(0.0, 1.0, n),) * 3, indexing="ij")
    x, y, z = x - 0.5, y - 0.5, z - 0.5
    return (np.sqrt((np.sqrt(x * x + y * y) - 0.3) ** 2 + z * z) - 0.12).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, default=40, help="grid values per axis")
    parser.add_argument("--rays", type=int, default=1 << 20)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    values = torus_values(args.counts)
    to_world = np.array([[2.0, 0, 0, 0.2], [0, 1.8, 0, 0.1], [0, 0, 1.5, 0.3], [0, 0, 0, 1]])
    rng = np.random.default_rng(0)
    centre = (to_world @ [0.5, 0.5, 0.5, 1.0])[:3]
    o = centre + rng.normal(size=(args.rays, 3)) * 4
    d = centre + rng.uniform(-1.0, 1.0, (args.rays, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o, d = o.astype(np.float32), d.astype(np.float32)

    ours = instancing.load_scene({"models": {"torus": {"type": "sdfgrid", "values": values}},
                                  "instances": [{"model": "torus", "to_world": to_world.tolist()}]})
    o_ours, d_ours = (Array3f(*[Float(np.ascontiguousarray(a[:, k])) for k in range(3)]) for a in (o, d))
    mi = mitsuba_module()
    mi.set_variant(MITSUBA_VARIANT)
    theirs = mi.load_dict({"type": "scene", "torus": {
        "type": "sdfgrid", "grid": mi.TensorXf(values[..., None]),
        "to_world": mi.ScalarTransform4f(to_world.tolist())}})
    ray = mi.Ray3f(mi.Point3f(*[np.ascontiguousarray(o[:, k]) for k in range(3)]),
                   mi.Vector3f(*[np.ascontiguousarray(d[:, k]) for k in range(3)]))
    calls = {"ours, t and ids": lambda: ours.intersect_preliminary(o_ours, d_ours).t,
             "Mitsuba's preliminary": lambda: theirs.ray_intersect_preliminary(ray).t,
             "ours, full record": lambda: ours.intersect(o_ours, d_ours).t,
             "Mitsuba's full": lambda: theirs.ray_intersect(ray).t}

    def timed(call) -> float:
        start = time.perf_counter()
        dr.eval(call())
        dr.sync_thread()
        return (time.perf_counter() - start) * 1e3

    times: dict[str, list[float]] = {name: [] for name in calls}
    for call in calls.values():
        timed(call)
    for _ in range(args.repeats):
        for name, call in calls.items():
            times[name].append(timed(call))
    median = {name: statistics.median(t) for name, t in times.items()}
    print(f"SDF grid {args.counts}^3 (a torus), {args.rays} rays aimed at it; ms, median of "
          f"{args.repeats} in alternation")
    for mine, other in (("ours, t and ids", "Mitsuba's preliminary"), ("ours, full record", "Mitsuba's full")):
        print(f"  {mine:<18} {median[mine]:8.1f}   {other:<22} {median[other]:8.1f}   "
              f"ours {median[other] / median[mine]:.2f}x as fast")
    t_ours = np.asarray(ours.intersect(o_ours, d_ours).t, np.float64)
    t_theirs = np.asarray(theirs.ray_intersect(ray).t, np.float64)
    hit_ours, hit_theirs = np.isfinite(t_ours), np.isfinite(t_theirs)
    both = hit_ours & hit_theirs
    rel = np.abs(t_ours[both] - t_theirs[both]) / t_theirs[both]
    print(f"  hits: ours {hit_ours.sum()}, Mitsuba's {hit_theirs.sum()}, one only {(hit_ours != hit_theirs).sum()}; "
          f"distances differ by at most {rel.max():.1e} (relative)")


if __name__ == "__main__":
    main()
