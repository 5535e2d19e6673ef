"""Gradient error against time, ours beside Mitsuba's projective integrators, with shadows in view.

    python -m benchmarks.gradient_mitsuba [--light point|area] [--integrator direct|path]
                                          [--size 32] [--spp 16,64,256,1024] [--repeats 3]

On scenes Mitsuba can differentiate (plain shapes, no instances: a similarity-scaled sphere,
a sheared cube and a rectangle in front of a wall, lit off the camera so that their shadows
are in view: by the point light, or with ``--light area`` by a rectangle area lamp, whose
soft shadows both renderers sample), the gradient image of the object's translation along (1, 0.5, 0)
is computed at several sample counts by both renderers: ours (``direct``, sppc = sppp = sppi =
spp) and Mitsuba 3's ``direct_projective`` (sppc = sppp = sppi = spp; forward mode), or with
``--integrator path`` ours ``path`` and Mitsuba's ``prb_projective`` (both max_depth 3), each
timed (median of ``--repeats`` after a warm-up that compiles the kernels) and compared with
one central difference of our detached renders at 16 384 spp (the error measure of
tests/test_gradients.py). Both renderers run in this one process, alternating per sample
count. The equal-error speed-up is Mitsuba's time over ours at the errors both reach
(log-log interpolation of each time-error curve). Writes the ``"mitsuba"`` (point light) or
``"mitsuba_area"`` entry of ``benchmarks/results_gradients.json`` (``"mitsuba_path"`` and
``"mitsuba_area_path"`` for ``path``; ``_<size>`` appended at another ``--size``).

Mitsuba 3.9.1's projective integrators sample no shadow boundaries of point lights (it logs
"No valid indirect silhouette samples were found"): its error here stops at the bias of the
missing term, so the curves may share no error range; the script then says so and prints
both renderers' lowest errors.
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
from instancing.validation.gradient_check import (SHADOW_LIGHT, finite_difference_image,
                                                  gradient_image, penumbra_scene, relative_error,
                                                  validation_scene)

import mitsuba as mi  # noqa: E402  (after instancing, which selects libLLVM)

ROOT = Path(__file__).resolve().parents[1]
MESH = str(ROOT / "scenes" / "meshes" / "torus.obj")
TANGENT = np.array([1.0, 0.5, 0.0])
STEP = 0.004
FD_SPP = 16384
#: Film side of the recorded comparisons (other sizes are stored as separate entries).
DEFAULT_SIZE = 32
#: Longest path of ``--integrator path`` (both renderers; Mitsuba's meaning of max_depth).
PATH_DEPTH = 3
#: Mitsuba's projective integrator beside each of ours.
MITSUBA_INTEGRATORS = {"direct": "direct_projective", "path": "prb_projective"}
#: Plain-shape transforms Mitsuba accepts (its sphere: similarity transforms only).
TRANSFORMS = {
    "sphere": [{"translate": [0.13, -0.07, 0]}, {"scale": 0.9}],
    "cube": None,
    "rectangle": None,
}


def _scene(model: str, size: int, light: str) -> instancing.Scene:
    if light == "area":
        description = penumbra_scene(model, size, MESH, "rectangle")
    else:
        description = validation_scene(model, size, MESH)
        description["lights"][0]["position"] = SHADOW_LIGHT
    if TRANSFORMS[model] is not None:
        description["instances"][0]["to_world"] = TRANSFORMS[model]
    return instancing.load_scene(description)


def _timed(function) -> tuple[np.ndarray, float]:
    function()  # warm-up: tracing and compilation
    times, result = [], None
    for _ in range(REPEATS):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return result, statistics.median(times)


def _depth(integrator: str) -> dict:
    return {"max_depth": PATH_DEPTH} if integrator == "path" else {}


def _mitsuba_gradient(scene: instancing.Scene, spp: int, integrator: str):
    description = instancing.to_mitsuba(scene, mode="shapes", spp=spp)
    description["integrator"] = {"type": MITSUBA_INTEGRATORS[integrator], "sppc": spp,
                                 "sppp": spp, "sppi": spp, **_depth(integrator)}
    mitsuba_scene = mi.load_dict(description)
    params = mi.traverse(mitsuba_scene)
    # obj is the scene's first instance: a shape with a to_world, or a mesh (the cube) whose
    # vertex positions move.
    key = "shape_0000000.to_world"
    mesh = key not in params
    if mesh:
        key = "shape_0000000.vertex_positions"
        initial = dr.unravel(mi.Point3f, params[key])
    else:
        initial = mi.Transform4f(params[key])

    def run() -> np.ndarray:
        x = mi.Float(0.0)
        dr.enable_grad(x)
        offset = mi.Vector3f(*[x * float(c) for c in TANGENT])
        params[key] = (dr.ravel(initial + offset) if mesh
                       else mi.Transform4f().translate(offset) @ initial)
        params.update()
        image = mi.render(mitsuba_scene, params, spp=spp, seed=1)
        dr.forward(x)
        return np.array(dr.grad(image))

    return run


def _equal_error_speedup(ours: list[tuple[float, float]], theirs: list[tuple[float, float]]
                         ) -> float | None:
    """Median over Mitsuba's points of t_mitsuba(e) / t_ours(e), with t_ours interpolated
    log-log at e where our curve covers it; None where the curves share no error range."""
    ours = sorted((e, t) for t, e in ours if e > 0)
    errors, times = np.log([e for e, _ in ours]), np.log([t for _, t in ours])
    ratios = []
    for t_theirs, e in theirs:
        if e <= 0 or not errors.min() <= np.log(e) <= errors.max():
            continue
        order = np.argsort(errors)
        t_ours = np.exp(np.interp(np.log(e), errors[order], times[order]))
        ratios.append(t_theirs / t_ours)
    return float(np.median(ratios)) if ratios else None


def main(argv=None) -> None:
    global REPEATS
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--light", choices=("point", "area"), default="point")
    parser.add_argument("--integrator", choices=tuple(MITSUBA_INTEGRATORS), default="direct")
    parser.add_argument("--size", type=int, default=DEFAULT_SIZE)
    parser.add_argument("--spp", default="16,64,256,1024")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    REPEATS = args.repeats
    mi.set_variant(MITSUBA_VARIANT)
    counts = [int(s) for s in args.spp.split(",")]
    integrator, depth = args.integrator, _depth(args.integrator)
    results = {"size": args.size, "spp": counts, "light": args.light, "integrator": integrator,
               "mitsuba_integrator": MITSUBA_INTEGRATORS[integrator], **depth, "models": {}}
    print(f"{'model':<10} {'spp':>5} {'ours s':>8} {'ours err':>9} {'mitsuba s':>10} {'mitsuba err':>12}")
    for model in TRANSFORMS:
        scene = _scene(model, args.size, args.light)
        params = instancing.traverse(scene)
        reference = finite_difference_image(params, "obj.translation", TANGENT, STEP,
                                            integrator=integrator, spp=FD_SPP, seed=2, **depth)
        rows = []
        for spp in counts:
            ours, t_ours = _timed(lambda: gradient_image(
                params, "obj.translation", TANGENT, integrator=integrator, spp=spp, sppp=spp,
                sppi=spp, seed=1, **depth))
            theirs, t_theirs = _timed(_mitsuba_gradient(scene, spp, integrator))
            row = {"spp": spp, "ours_s": t_ours, "ours_error": relative_error(ours, reference),
                   "mitsuba_s": t_theirs, "mitsuba_error": relative_error(theirs, reference)}
            rows.append(row)
            print(f"{model:<10} {spp:>5} {t_ours:>8.3f} {row['ours_error']:>9.4f} {t_theirs:>10.3f} "
                  f"{row['mitsuba_error']:>12.4f}", flush=True)
        speedup = _equal_error_speedup([(r["ours_s"], r["ours_error"]) for r in rows],
                                       [(r["mitsuba_s"], r["mitsuba_error"]) for r in rows])
        results["models"][model] = {"rows": rows, "speedup_equal_error": speedup}
        best = (min(r["ours_error"] for r in rows), min(r["mitsuba_error"] for r in rows))
        print(f"{model:<10} equal-error speed-up (Mitsuba time / ours): "
              + (f"no common error range (lowest error: ours {best[0]:.4f}, Mitsuba {best[1]:.4f})"
                 if speedup is None else f"{speedup:.2f}x"), flush=True)
    out = ROOT / "benchmarks" / "results_gradients.json"
    merged = json.loads(out.read_text()) if out.is_file() else {}
    entry = (("mitsuba" if args.light == "point" else "mitsuba_area")
             + ("_path" if integrator == "path" else "")
             + (f"_{args.size}" if args.size != DEFAULT_SIZE else ""))
    merged[entry] = results
    out.write_text(json.dumps(merged, indent=1, default=float))
    print(f"wrote {out}")


REPEATS = 3

if __name__ == "__main__":
    main()
