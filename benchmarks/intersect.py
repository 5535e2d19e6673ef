"""Intersection throughput: ``scene.intersect`` against Mitsuba 3 on the same instances and rays.

For N instances of each model kind (sphere, cube, rectangle, disk, cylinder,
torus mesh) and 1M random rays (origins inside the scene's bounds, isotropic
directions), prints Mrays/s of

* ours: the full hit record (t, p, n, instance, prim) through the grid and
  the BVH, and which one the scene builder picks;
* ours "t+ids": phase 1 alone with the picked structure (t, instance, leaf
  position), before the float64 record: like for like with Embree's
  preliminary query;
* Mitsuba's ``ray_intersect_preliminary`` and full ``ray_intersect`` on the
  same instances (one ``shapegroup`` holding the model, N ``instance``s).

Mitsuba's full ``ray_intersect`` slows down steeply with the instance count,
so it gets a single timed call and only up to 1 000 instances (see
MITSUBA_FULL_RAYS); its rate is reported. Every other figure is the median of
``--repeats`` timed runs after one warm-up run (which also compiles the
kernels), ours with each structure and Mitsuba's preliminary query taking turns
in every round, so that load from other jobs on the machine hits them alike. A clustered sphere scene (a few dense clusters in a large empty box)
shows why the builder switches to the BVH there. Rows are measured one after
the other, so load from other jobs on a shared machine can move the
1 000 -> 100 000 ratio between them; the script therefore also times those two
sphere scenes in alternation and prints that ratio.

The field keeps its box (20 units wide) and its volume fraction as N grows:
sizes shrink as N^(-1/3), so the mean free path measured in grid cells is the
same at every N, but the box's optical depth grows as N^(1/3): more rays hit
something, and the rays that miss cross more cells (see :func:`sphere_field`).
In a field of constant density instead, larger N means longer rays before the
first hit, whatever the structure. Every kind but the sphere is randomly
rotated. ``scene.intersect`` walks the grid in passes for batches this large
(:func:`instancing.scene.intersection.intersect_preliminary_in_passes`), and in scenes
whose grid and instance rows take 6 MiB or more (here from about 70 000
instances) it first sorts the rays by where they enter the grid
(:mod:`instancing.accel.ray_order`); the sort is part of the timed call, and the script
also times phase 1 with and without it in alternation at 100 000 instances.

Last, queries of a few rays (1, 16, 4 096), NumPy in and out, are timed per query against
Mitsuba's preliminary query from the same NumPy arrays (:func:`small_batches`): there the
fixed cost of a call, not the walk, decides.

Usage: python -m benchmarks.intersect [--kinds sphere mesh] [--counts 10 1000 10000 100000]
       [--rays 1048576] [--repeats 5] [--json out.json] [--no-mitsuba-full]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

import instancing
from instancing.core.backend import MITSUBA_VARIANT, dr
from instancing.scene.intersection import intersect_preliminary_in_passes


def sphere_field(n: int, seed: int = 0, clustered: bool = False) -> np.ndarray:
    """(n, 4, 4) to_world matrices of spheres in a 20-unit box at constant volume fraction.

    Radii are 0.3..0.6 at n = 1000 and scale as n^(-1/3): the spheres fill the same
    fraction of the box at every n, so the mean free path is the same number of grid
    cells, but the box's optical depth grows as n^(1/3): more random rays hit something
    (the benchmark prints the fraction) and travel farther before they do.
    """
    rng = np.random.default_rng(seed)
    half = 10.0
    shrink = (1000.0 / n) ** (1.0 / 3.0)
    if clustered:
        # Eight tight clusters in a box 20x wider than they are.
        centres = rng.uniform(-20 * half, 20 * half, (8, 3))
        pos = centres[rng.integers(0, 8, n)] + rng.normal(0.0, half / 8, (n, 3))
    else:
        pos = rng.uniform(-half, half, (n, 3))
    radius = rng.uniform(0.3, 0.6, n) * shrink
    m = np.zeros((n, 4, 4))
    m[:, 0, 0] = m[:, 1, 1] = m[:, 2, 2] = radius
    m[:, :3, 3] = pos
    m[:, 3, 3] = 1.0
    return m


#: Model kinds of the benchmark: ours (scene-file model) and Mitsuba's plugin for the same
#: canonical shape. Mitsuba's cube is a 12-triangle mesh; "mesh" is the bundled torus.
TORUS = Path(__file__).resolve().parent.parent / "scenes" / "meshes" / "torus.obj"
KINDS = {"sphere": {"type": "sphere"}, "cube": {"type": "cube"}, "rectangle": {"type": "rectangle"},
         "disk": {"type": "disk"}, "cylinder": {"type": "cylinder"},
         "mesh": {"type": "obj", "filename": str(TORUS)}}


def instance_field(kind: str, n: int, seed: int = 0, clustered: bool = False) -> np.ndarray:
    """(n, 4, 4) to_world matrices of ``kind`` placed as :func:`sphere_field`'s spheres.

    Every kind but the sphere also gets a random rotation (flat shapes would otherwise
    all face one way); the sizes are the spheres' radii.
    """
    m = sphere_field(n, seed, clustered)
    if kind != "sphere":
        rng = np.random.default_rng(seed + 1)
        q, r = np.linalg.qr(rng.normal(size=(n, 3, 3)))
        q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]  # uniform rotations
        q[np.linalg.det(q) < 0, :, 0] *= -1.0
        m[:, :3, :3] = q @ m[:, :3, :3]
    return m


def load_field(kind: str, matrices: np.ndarray):
    """Our scene of ``kind`` instances under ``matrices``."""
    model = "mesh" if kind == "mesh" else kind
    models = {"mesh": {"type": "obj", "filename": str(TORUS)}} if kind == "mesh" else {}
    return instancing.load_scene({"models": models,
                                  "instances": [{"model": model, "to_world": matrices}]})


def random_rays(lo: np.ndarray, hi: np.ndarray, count: int, seed: int = 1):
    """Origins uniform in the box, isotropic unit directions (float32-exact)."""
    rng = np.random.default_rng(seed)
    o = rng.uniform(lo, hi, (count, 3)).astype(np.float32)
    d = rng.normal(size=(count, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    return o, d


def timed(fn, repeats: int) -> float:
    """Median wall time of fn() over repeats runs, after one warm-up run."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def jit_rays(o_np: np.ndarray, d_np: np.ndarray):
    """Dr.Jit copies (Array3f origins, directions) of (N, 3) NumPy rays."""
    return (instancing.core.backend.Array3f(*[o_np[:, k] for k in range(3)]),
            instancing.core.backend.Array3f(*[d_np[:, k] for k in range(3)]))


def intersect_call(scene, o_np, d_np):
    """A function that computes the rays' full hit record with the scene's current structure."""
    o, d = jit_rays(o_np, d_np)

    def run():
        hit = scene.intersect(o, d)
        dr.eval(hit.t, hit.p, hit.n, hit.instance, hit.prim)
        dr.sync_thread()

    return run


def preliminary_call(scene, o_np, d_np):
    """A function that computes phase 1 alone (t, instance, leaf position), as
    ``scene.intersect`` runs it before its float64 record: the like-for-like measure of
    Embree's preliminary query."""
    o, d = jit_rays(o_np, d_np)

    def run():
        hit = scene._batch_preliminary(o, d)  # (the passes and ray sort included)
        dr.eval(hit.t, hit.instance, hit.position)
        dr.sync_thread()

    return run


def alternating(calls: list, repeats: int) -> list[float]:
    """Median wall time of each call, the calls timed in turn in each of ``repeats``
    rounds after one warm-up round (which also compiles the kernels): load from other
    jobs on the machine hits all of them alike."""
    for call in calls:
        call()
    times = [[] for _ in calls]
    for _ in range(repeats):
        for call, spent in zip(calls, times):
            start = time.perf_counter()
            call()
            spent.append(time.perf_counter() - start)
    return [statistics.median(spent) for spent in times]


def interleaved_rates(counts, rays: int, repeats: int) -> list[float]:
    """Ours (picked structure) on uniform fields of several sizes, timed in alternation;
    the median Mrays/s per scene."""
    calls = []
    for n in counts:
        scene = instancing.load_scene({"instances": [{"model": "sphere", "to_world": sphere_field(n)}]})
        calls.append(intersect_call(scene, *random_rays(*scene.bounds, rays)))
    return [rays / spent / 1e6 for spent in alternating(calls, repeats)]


def sort_gain(kind: str, n: int, rays: int, repeats: int) -> tuple[float, float]:
    """Phase 1 in passes on the uniform field of ``n`` ``kind`` instances, with the rays
    as they come and sorted by grid entry cell (what ``scene.intersect`` does from
    SORT_MIN_WALK_BYTES), timed in alternation; the median seconds of each."""
    scene = load_field(kind, instance_field(kind, n))
    scene.set_accel("grid")
    o_np, d_np = random_rays(*scene.bounds, rays)
    o, d = jit_rays(o_np - scene.origin, d_np)  # phase 1 takes rays in rendering space

    def phase1(sort_rays):
        hit = intersect_preliminary_in_passes(scene.instances, scene.grid, o, d,
                                              sort_rays=sort_rays)
        dr.eval(hit.t, hit.instance, hit.position)
        dr.sync_thread()

    phase1(False), phase1(True)  # warm-up (compiles the kernels)
    times = {False: [], True: []}
    for _ in range(repeats):
        for sort_rays, spent in times.items():
            start = time.perf_counter()
            phase1(sort_rays)
            spent.append(time.perf_counter() - start)
    return statistics.median(times[False]), statistics.median(times[True])


def mitsuba_scene(matrices: np.ndarray, kind: str = "sphere"):
    """Mitsuba's twin: one shapegroup holding the model, one ``instance`` per matrix."""
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    scene = {"type": "scene", "group": {"type": "shapegroup", "model": dict(KINDS[kind])}}
    for i, m in enumerate(matrices):
        scene[f"i{i}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                          "to_world": mi.ScalarTransform4f(m.tolist())}
    return mi, mi.load_dict(scene)


def _mitsuba_ray(mi, o_np, d_np):
    return mi.Ray3f(mi.Point3f(*[o_np[:, k] for k in range(3)]), mi.Vector3f(*[d_np[:, k] for k in range(3)]))


def mitsuba_preliminary_call(mi, scene, o_np, d_np):
    """A function that computes Mitsuba's (Embree's) preliminary hits of the rays."""
    ray = _mitsuba_ray(mi, o_np, d_np)

    def run():
        pi = scene.ray_intersect_preliminary(ray)
        dr.eval(pi.t, pi.prim_index, pi.shape_index)
        dr.sync_thread()

    return run


def mitsuba_full_rate(mi, scene, o_np, d_np) -> float:
    """Mitsuba's full ``ray_intersect`` rate from one timed call (see MITSUBA_FULL_RAYS),
    after a warm-up on a small batch that compiles its kernels."""
    def trace(ray):
        si = scene.ray_intersect(ray)
        dr.eval(si.t, si.p, si.n, si.shape, si.prim_index)
        dr.sync_thread()

    trace(_mitsuba_ray(mi, o_np[:4096], d_np[:4096]))
    ray = _mitsuba_ray(mi, o_np, d_np)
    start = time.perf_counter()
    trace(ray)
    return len(o_np) / (time.perf_counter() - start) / 1e6


#: Rays given to Mitsuba's full ray_intersect per instance count (one timed
#: call). Each call re-traces one callable per instance: measured here, ~12 s
#: per call at 1 000 instances nearly independent of the ray count, and at
#: 10 000 instances a single call ran for over 20 minutes and grew to 22 GB
#: before we stopped it, so 10 000 and more are skipped on a 24 GB machine.
MITSUBA_FULL_RAYS = {10: 1 << 20, 1000: 1 << 20}


def run(kinds, counts, rays: int, repeats: int, on_row=None, mitsuba_full: bool = True) -> list[dict]:
    """One row per (kind, count), plus a clustered sphere field at the largest count.

    ``on_row(rows)`` is called after each row, so that a run cut short keeps what it measured;
    ``mitsuba_full`` False skips Mitsuba's full ``ray_intersect`` (seconds per row with
    instances, on either backend).
    """
    plan = [(kind, c, False) for kind in kinds for c in counts]
    if "sphere" in kinds:
        plan.append(("sphere", max(counts), True))
    rows = []
    for kind, n, clustered in plan:
        matrices = instance_field(kind, n, clustered=clustered)
        start = time.perf_counter()
        scene = load_field(kind, matrices)
        build_s = time.perf_counter() - start
        lo, hi = scene.bounds
        o, d = random_rays(lo, hi, rays)
        picked = scene.accel
        # The picked structure, the grid and the BVH (each forced on a scene of its own) and
        # Embree's preliminary query, timed in alternation.
        structures = {picked: scene}
        for accel in ("grid", "bvh"):
            if accel not in structures:
                structures[accel] = load_field(kind, matrices)
                structures[accel].set_accel(accel)
        mi, mscene = mitsuba_scene(matrices, kind)
        calls = [intersect_call(s, o, d) for s in structures.values()]
        spent = alternating(calls + [preliminary_call(scene, o, d),
                                     mitsuba_preliminary_call(mi, mscene, o, d)], repeats)
        rates = {accel: rays / t / 1e6 for accel, t in zip(structures, spent)}
        row = {"kind": kind, "instances": n, "clustered": clustered, "picked": picked,
               "build_s": build_s, "grid": rates["grid"], "bvh": rates["bvh"],
               "ours": rates[picked], "ours_prelim": rays / spent[-2] / 1e6,
               "mi_prelim": rays / spent[-1] / 1e6}
        row["hit_fraction"] = float((scene.intersect(o, d).instance >= 0).mean())
        del structures, calls
        full_rays = 0 if clustered or not mitsuba_full else min(MITSUBA_FULL_RAYS.get(n, 0), rays)
        row["mi_full_rays"] = full_rays
        row["mi_full"] = (mitsuba_full_rate(mi, mscene, o[:full_rays], d[:full_rays])
                          if full_rays else float("nan"))
        rows.append(row)
        print_row(row, flush=True)
        if on_row:
            on_row(rows)
    return rows


#: The queries of a few rays (NumPy in and out) whose fixed cost :func:`small_batches` times:
#: scenes (kind, instances) and rays per query.
SMALL_SCENES = (("rectangle", 10), ("mesh", 10), ("sphere", 1000), ("mesh", 1000))
SMALL_BATCHES = (1, 16, 4096)
#: Timed rounds of each small query (each takes well under a millisecond or two).
SMALL_REPEATS = 41


def small_batches(repeats: int = SMALL_REPEATS) -> list[dict]:
    """Milliseconds per query of a few rays, in alternation: ours (``scene.intersect`` on NumPy
    rays, its kernels replayed from a recording per batch width), our Dr.Jit record of the
    same rays (traced every call) and Mitsuba's preliminary query (its rays built from the
    NumPy arrays, t and primitive index read back), the median of each."""
    rows = []
    for kind, n in SMALL_SCENES:
        matrices = instance_field(kind, n)
        scene = load_field(kind, matrices)
        mi, mscene = mitsuba_scene(matrices, kind)
        for count in SMALL_BATCHES:
            o, d = random_rays(*scene.bounds, count)

            def ours(o=o, d=d):
                scene.intersect(o, d)

            def theirs(o=o, d=d):
                hit = mscene.ray_intersect_preliminary(_mitsuba_ray(mi, o, d))
                np.asarray(hit.t), np.asarray(hit.prim_index)

            ours()  # (a width is recorded at its second query: alternating's warm-up replays)
            spent = alternating([ours, intersect_call(scene, o, d), theirs], repeats)
            rows.append({"kind": kind, "instances": n, "rays": count, "ours_ms": 1e3 * spent[0],
                         "traced_ms": 1e3 * spent[1], "mi_prelim_ms": 1e3 * spent[2]})
            print_small(rows[-1], flush=True)
    return rows


SMALL_HEADER = (f"{'kind':>9} {'instances':>10} {'rays':>6} {'ours ms':>8} {'traced ms':>10} "
                f"{'mi prelim ms':>13} {'ours/prelim':>12}")


def print_small(r: dict, flush: bool = False) -> None:
    print(f"{r['kind']:>9} {r['instances']:>10} {r['rays']:>6} {r['ours_ms']:>8.3f} {r['traced_ms']:>10.3f} "
          f"{r['mi_prelim_ms']:>13.3f} {r['mi_prelim_ms'] / r['ours_ms']:>12.2f}", flush=flush)


HEADER = (f"{'kind':>9} {'instances':>10} {'layout':>9} {'picked':>8} {'build s':>8} {'ours':>7} {'grid':>7} "
          f"{'bvh':>7} {'t+ids':>8} {'mi prelim':>9} {'mi full':>8} {'(rays)':>9} {'ours/prelim':>11} "
          f"{'t+ids/prel':>11} {'ours/full':>9} {'hit %':>6}")


def print_row(r: dict, flush: bool = False) -> None:
    print(f"{r['kind']:>9} {r['instances']:>10} {'clustered' if r['clustered'] else 'uniform':>9} {r['picked']:>8} "
          f"{r['build_s']:>8.2f} {r['ours']:>7.2f} {r['grid']:>7.2f} {r['bvh']:>7.2f} "
          f"{r['ours_prelim']:>8.2f} {r['mi_prelim']:>9.2f} {r['mi_full']:>8.4f} {r['mi_full_rays']:>9} "
          f"{r['ours'] / r['mi_prelim']:>11.2f} {r['ours_prelim'] / r['mi_prelim']:>11.2f} "
          f"{r['ours'] / r['mi_full']:>9.0f} {100 * r['hit_fraction']:>6.1f}", flush=flush)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--kinds", nargs="+", choices=list(KINDS), default=list(KINDS))
    parser.add_argument("--counts", type=int, nargs="+", default=[10, 1000, 10000, 100000])
    parser.add_argument("--rays", type=int, default=1 << 20)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", help="also write the rows as JSON to this file")
    parser.add_argument("--no-mitsuba-full", action="store_true",
                        help="skip Mitsuba's full ray_intersect (its column then reads nan)")
    args = parser.parse_args(argv)
    if min(args.counts) < 1 or args.rays < 1 or args.repeats < 1:
        parser.error("counts, rays and repeats must be positive")
    print(f"Mrays/s, median of {args.repeats} runs, {args.rays} random rays")
    print(HEADER)
    def save(rows):
        if args.json:
            Path(args.json).write_text(json.dumps({"rows": rows}, indent=1, default=float))

    rows = run(args.kinds, args.counts, args.rays, args.repeats, on_row=save,
               mitsuba_full=not args.no_mitsuba_full)
    results = {"rows": rows}
    for kind in args.kinds:
        ref, big = (next((r for r in rows if r["kind"] == kind and r["instances"] == n
                          and not r["clustered"]), None) for n in (1000, 100000))
        if ref and big:
            results[f"fall_{kind}"] = ref["ours"] / big["ours"]
            print(f"{kind}: throughput 1000 -> 100000 instances falls by {ref['ours'] / big['ours']:.2f}x "
                  f"(rays that hit: {100 * ref['hit_fraction']:.0f} % -> {100 * big['hit_fraction']:.0f} %)")
    if "fall_sphere" in results:
        small, large = interleaved_rates([1000, 100000], args.rays, args.repeats)
        results["fall_sphere_alternating"] = small / large
        print(f"sphere, timed in alternation: {small:.2f} -> {large:.2f} Mrays/s, "
              f"falls by {small / large:.2f}x")
    if 100000 in args.counts:
        for kind in args.kinds:
            plain, ordered = sort_gain(kind, 100000, args.rays, args.repeats)
            results[f"sort_gain_{kind}"] = plain / ordered
            print(f"{kind} 100000: phase 1 in passes, rays as they come -> sorted by entry cell, "
                  f"in alternation: {1e3 * plain:.0f} -> {1e3 * ordered:.0f} ms ({plain / ordered:.2f}x)")
    print(f"\nQueries of a few rays, NumPy in and out: ms per query, median of {SMALL_REPEATS} in "
          "alternation (ours replayed; 'traced': our Dr.Jit record, traced every call; "
          "ours/prelim: Mitsuba's time over ours)")
    print(SMALL_HEADER)
    results["small_batches"] = small_batches()
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    return results


if __name__ == "__main__":
    main()
