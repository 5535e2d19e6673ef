"""Per-instance materials at scale: a forest of one tree mesh, every tree with its own
``roughplastic`` colour and roughness, against the same forest wearing one shared material.

The target (materials issue): our render time with per-instance materials within 1.2x of
the shared material's. Mitsuba cannot give instances of one shape group their own BSDF, so
its per-instance form is one shape group per material (``to_mitsuba``'s export); its time
for that form is printed beside its shared-material time.

Times are medians of ``--repeats`` renders per form after one warm-up render each (kernels
compiled), each render waited for to the end; our two forms alternate, Mitsuba's are timed
one after the other with only that scene loaded (see below); ours and Mitsuba's are measured
in the same run at the same spp and film size, Mitsuba's ``direct``
and ``path`` integrators against ours. Load times are printed too (ours: the material table
with one rough-coating quadrature per material; Mitsuba's: ``load_dict`` of the export, which
precomputes the same per roughplastic).

Mitsuba's per-material form outgrows the machine at 1 024 trees; ``--probe TREES`` times it
where it still runs: that many trees, at ``--probe-size`` and ``--probe-spp``, ours and
Mitsuba's per-material forms (one render each after a warm-up, Mitsuba's peak memory from
its child), merged into the JSON as ``probe`` without re-running the rest.

Usage: python -m benchmarks.materials [--trees 1024] [--spp 16] [--size 320 240]
           [--repeats 5] [--mitsuba-repeats 2] [--json benchmarks/results_materials.json]
       python -m benchmarks.materials --probe 512 [--probe-size 80 60] [--probe-spp 4]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import instancing
from benchmarks.machine import describe
from instancing.core.backend import dr, mitsuba_module

ROOT = Path(__file__).resolve().parent.parent
TREE = str(ROOT / "scenes" / "meshes" / "tree.ply")


def forest(trees: int, per_instance: bool, size: tuple[int, int], seed: int = 1) -> dict:
    """``trees`` instances of the tree mesh on a square field, each its own roughplastic
    (random colour and roughness) or all one."""
    rng = np.random.default_rng(seed)
    side = float(np.sqrt(trees)) * 2.2
    materials = {"ground": {"type": "diffuse", "reflectance": [0.3, 0.33, 0.2]}}
    instances = [{"id": "ground", "model": "rectangle", "material": "ground",
                  "to_world": [{"scale": [side, side, 1]}]}]
    shared = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
              "diffuse_reflectance": [0.1, 0.35, 0.12]}
    if not per_instance:
        materials["leaves"] = shared
    for k in range(trees):
        name = f"leaves{k:05d}" if per_instance else "leaves"
        if per_instance:
            materials[name] = {"type": "roughplastic", "distribution": "ggx",
                               "alpha": float(rng.uniform(0.05, 0.5)),
                               "diffuse_reflectance": rng.uniform(0.05, 0.6, 3).round(4).tolist()}
        x, y = rng.uniform(-side * 0.9, side * 0.9, 2)
        instances.append({"id": f"tree{k:05d}", "model": "tree", "material": name, "to_world": [
            {"translate": [float(x), float(y), 0.0]},
            {"rotate": {"axis": [0, 0, 1], "angle": float(rng.uniform(0, 360))}},
            {"scale": rng.uniform(0.6, 1.3, 3).round(3).tolist()}]})
    return {"models": {"tree": {"type": "ply", "filename": TREE, "face_normals": True}},
            "materials": materials, "instances": instances,
            "lights": [{"type": "directional", "direction": [-1, 0.6, -2], "irradiance": 3},
                       {"type": "constant", "radiance": [0.25, 0.3, 0.35]}],
            "camera": {"type": "perspective", "fov": 55, "width": size[0], "height": size[1],
                       "to_world": [{"look_at": {"origin": [0.3 * side, -1.1 * side, 0.45 * side],
                                                 "target": [0, 0, 0], "up": [0, 0, 1]}}]}}


#: Memory a Mitsuba child may use (bytes of address space): below the machine's 24 GiB.
MITSUBA_MEMORY_CAP = 16 << 30


def _text(value, unit: str = " s") -> str:
    return f"{value:.3f}{unit}" if isinstance(value, float) else str(value)


def _mitsuba_child(args, form: str) -> dict:
    """Mitsuba's load and render times of one form, from a child process capped at
    MITSUBA_MEMORY_CAP; ``{"failed": reason}`` when it dies."""
    command = [sys.executable, "-m", "benchmarks.materials", "--mitsuba-form", form,
               "--trees", str(args.trees), "--spp", str(args.spp), "--size", *map(str, args.size),
               "--mitsuba-repeats", str(args.mitsuba_repeats)]

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (MITSUBA_MEMORY_CAP, MITSUBA_MEMORY_CAP))

    try:
        done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=3600,
                              preexec_fn=cap)
    except subprocess.TimeoutExpired:
        return {"failed": "over 1 hour"}
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        # The first error line is the root cause of a chained traceback.
        errors = [line.strip() for line in done.stderr.splitlines() if "Error" in line]
        reason = (errors or done.stderr.strip().splitlines() or ["no output"])[0]
        return {"failed": f"exit {done.returncode} under the {MITSUBA_MEMORY_CAP >> 30} GiB "
                          f"address-space cap ({reason[:160]})"}
    return json.loads(lines[-1])


def _mitsuba_form(args) -> None:
    """The child's work: load the form in Mitsuba and time its renders (one JSON line)."""
    scene = instancing.load_scene(forest(args.trees, args.mitsuba_form == "per-instance",
                                         tuple(args.size)))
    mi = mitsuba_module()
    exported = instancing.to_mitsuba(scene, spp=args.spp)
    t0 = time.perf_counter()
    loaded = mi.load_dict(exported)
    out = {"load_s": time.perf_counter() - t0}
    for integrator in ("direct", "path"):
        out[integrator] = _median_alternating({0: _theirs(mi, loaded, integrator, args.spp)},
                                              args.mitsuba_repeats)[0]
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / (1 << 20)
    print(json.dumps(out), flush=True)


def _ours(scene, integrator: str, spp: int):
    return lambda: _finished(instancing.render(scene, integrator, spp=spp, seed=1))


def _theirs(mi, scene, integrator: str, spp: int):
    mint = mi.load_dict({"type": integrator})
    return lambda: _finished(mi.render(scene, integrator=mint, spp=spp, seed=1))


def _finished(image) -> None:
    """Wait until the image is computed (Dr.Jit launches kernels asynchronously)."""
    dr.eval(image)
    dr.sync_thread()


def _median_alternating(renders: dict, repeats: int) -> dict:
    """Median wall time per form, the forms alternating (after one warm-up each)."""
    for render in renders.values():
        render()
    times = {name: [] for name in renders}
    for _ in range(repeats):
        for name, render in renders.items():
            t0 = time.perf_counter()
            render()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def _probe(args) -> None:
    """Both per-material forms at ``args.probe`` trees, the probe size and spp (one timed
    render each after a warm-up), merged into the JSON as ``probe``."""
    size = tuple(args.probe_size)
    scene = instancing.load_scene(forest(args.probe, True, size))
    ours = {integrator: _median_alternating({0: _ours(scene, integrator, args.probe_spp)}, 1)[0]
            for integrator in ("direct", "path")}
    child_args = argparse.Namespace(trees=args.probe, spp=args.probe_spp, size=size, mitsuba_repeats=1)
    mitsuba = _mitsuba_child(child_args, "per-instance")
    probe = {"trees": args.probe, "size": list(size), "spp": args.probe_spp, "ours": ours,
             "mitsuba": mitsuba}
    print(json.dumps(probe))
    path = Path(args.json)
    results = json.loads(path.read_text()) if path.exists() else {}
    results["probe"] = probe
    path.write_text(json.dumps(results, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trees", type=int, default=1024)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--size", type=int, nargs=2, default=(320, 240))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--mitsuba-repeats", type=int, default=2,
                        help="Mitsuba's renders per form (its per-instance form takes a minute each)")
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results_materials.json"))
    parser.add_argument("--probe", type=int, default=0,
                        help="time both per-material forms at this many trees only (see above)")
    parser.add_argument("--probe-size", type=int, nargs=2, default=(80, 60))
    parser.add_argument("--probe-spp", type=int, default=4)
    parser.add_argument("--mitsuba-form", choices=("per-instance", "shared"),
                        help=argparse.SUPPRESS)  # the child process of _mitsuba_child
    args = parser.parse_args()
    if args.mitsuba_form:
        _mitsuba_form(args)
        return
    if args.probe:
        _probe(args)
        return
    size = tuple(args.size)

    scenes, load = {}, {}
    for form, per_instance in (("per-instance", True), ("shared", False)):
        description = forest(args.trees, per_instance, size)
        t0 = time.perf_counter()
        scenes[form] = instancing.load_scene(description)
        load[form] = time.perf_counter() - t0
    integrators = ("direct", "path")
    timed = {}
    for integrator in integrators:
        timed.update({(integrator, "ours", form): t for form, t in _median_alternating(
            {form: _ours(scenes[form], integrator, args.spp) for form in scenes}, args.repeats).items()})
    # Mitsuba, each form in a process of its own: Dr.Jit dispatches Mitsuba's BSDF calls
    # over every BSDF object alive, so the per-instance scene's materials would slow the
    # shared one (measured: 0.5 s -> 13 s per render at 256), and at 1 024 materials its
    # renders outgrew the machine's 24 GiB (killed): a child under a memory cap reports it.
    mitsuba_load = {}
    for form in scenes:
        child = _mitsuba_child(args, form)
        mitsuba_load[form] = child.get("load_s", child.get("failed"))
        for integrator in integrators:
            timed[(integrator, "mitsuba", form)] = child.get(integrator, child.get("failed"))
    results = {"trees": args.trees, "spp": args.spp, "size": list(size), "repeats": args.repeats,
               "mitsuba_repeats": args.mitsuba_repeats,
               "materials": {form: len(scene.material_names) for form, scene in scenes.items()},
               "load_s": load, "mitsuba_load_s": mitsuba_load, "integrators": {}}
    for integrator in integrators:
        row = {who: {form: timed[(integrator, who, form)] for form in scenes}
               for who in ("ours", "mitsuba")}
        for who in row:
            both = [row[who][form] for form in scenes]
            row[who]["ratio"] = (both[0] / both[1] if all(isinstance(t, float) for t in both)
                                 else None)
        results["integrators"][integrator] = row
        print(f"{integrator:6s} ours: per-instance {_text(row['ours']['per-instance'])}, shared "
              f"{_text(row['ours']['shared'])}, ratio {_text(row['ours']['ratio'], 'x')} "
              f"(target <= 1.2); Mitsuba (one shapegroup per material): "
              f"{_text(row['mitsuba']['per-instance'])}, shared {_text(row['mitsuba']['shared'])}, "
              f"ratio {_text(row['mitsuba']['ratio'], 'x')}")
    print(f"load: ours per-instance {load['per-instance']:.2f} s ({args.trees} roughplastic "
          f"materials), shared {load['shared']:.2f} s; Mitsuba per-instance "
          f"{_text(mitsuba_load['per-instance'])}, shared {_text(mitsuba_load['shared'])}")
    path = Path(args.json)
    if path.exists() and "probe" in json.loads(path.read_text()):
        results["probe"] = json.loads(path.read_text())["probe"]  # (its own run: --probe)
    results["machine"] = describe()
    path.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
