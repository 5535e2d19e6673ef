"""Scaling to a million instances: load time, memory per instance, first versus later frames.

For N sphere instances (the uniform field of ``benchmarks/intersect.py``,
default N = 1e3, 1e4, 1e5, 1e6), each N in a fresh process (so that its
memory figures are its own), with a camera looking at the field and one
directional light, measures:

1. Load: ``instancing.load_scene`` wall time, split into parsing (the
   ``parse_scene`` call inside it, timed by wrapping it) and building (the
   rest: instance table, world bounds, acceleration structure). Then
   ``scene.intersect`` on ``--rays`` random rays (as in intersect.py): the
   first call (tracing and compiling) against the median of later calls.
2. Memory per instance beyond the shared models:
   (a) resident memory (VmRSS, and the peak VmHWM, read from /proc/self/status;
   the peak is reset just before loading) grown from just before
   ``load_scene`` to after loading and rendering, divided by N. The input
   matrices exist before the baseline and are not counted. Fixed costs (LLVM,
   compiled kernels) weigh on small N, so the table also gives the slope
   between consecutive N;
   (b) the bytes the scene holds: every Dr.Jit array, NumPy array and large
   Python container reachable from the Scene object through its attributes
   (found by walking ``vars()`` recursively, not by name, so the breakdown
   follows the code), each counted once, with bytes per instance. The
   parameter object of an optimisation (``instancing.traverse``) is walked
   the same way and reported apart. The issue's target is at most 128 B per
   instance beyond the shared models.
3. First image versus later frames: ``instancing.render(scene, "direct",
   spp=--spp)``, the first call (tracing and LLVM compilation) against the
   median of ``--repeats`` later calls with other seeds, and how many kernels
   each later call compiled (``dr.kernel_history()``: JIT launches not found
   in the in-memory kernel cache). A repeat with the first seed must give the
   identical image. The same for optimisation steps
   (:class:`instancing.OptimisationStep`: update, render, L2 loss,
   ``dr.backward``, Adam step) with the translations of 8 instances
   differentiated, for N up to ``--step-max``. ``wall - kernels`` is the time
   spent outside kernels (Python tracing, scene updates). Later frames and
   later steps are replayed from ``dr.freeze`` recordings. Separate small
   processes compare renders traced afresh (``frozen=False``) with replayed
   ones at FREEZE_PROBE_SPP samples per pixel: wall and kernel times and
   whether the images are identical.
4. That 1e6 instances load and render: the largest N must give an image
   with lit pixels.

Dr.Jit keeps compiled kernels on disk (~/.drjit). Each worker gets its own
empty HOME, so "first" includes the full LLVM compilation (a cold cache, as
on a new machine); a second short process per N with the now warm disk
cache gives the first image a returning user sees.

Usage: python -m benchmarks.scale [--counts 1000 10000 100000 1000000] [--repeats 5]
           [--size 256] [--spp 4] [--rays 1048576] [--step-max 1000000] [--json PATH]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: The issue's memory target per instance beyond the shared models.
#: Sample counts at which dr.freeze is tried (a replay skips tracing; its kernels may differ).
FREEZE_PROBE_SPP = (4, 64)
TARGET_BYTES_PER_INSTANCE = 128
#: Seconds one worker may take (the 1e6 scene loads, renders, steps and traces rays).
WORKER_TIMEOUT = 1500
#: Instances whose translation carries derivatives in the optimisation step.
MOVING_INSTANCES = 8
#: Rows of the breakdown below this many bytes per instance are summed into one line.
BREAKDOWN_MIN_BYTES = 0.5
_RESULT = "SCALE-RESULT "


# -- measurements in the worker process ----------------------------------------------------

def _status() -> dict[str, int]:
    """VmRSS and VmHWM of this process in bytes."""
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0]) * 1024
    return out


def _reset_peak() -> bool:
    """Reset VmHWM to the current RSS (Linux: write 5 to clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _settle(dr) -> dict[str, int]:
    """RSS after finishing queued work and returning cached allocations."""
    dr.sync_thread()
    gc.collect()
    dr.flush_malloc_cache()
    return _status()


def scene_description(n: int, size: int) -> dict:
    """The uniform sphere field of intersect.py seen by a camera, lit by a directional light."""
    from benchmarks.intersect import sphere_field
    return {"instances": [{"model": "sphere", "to_world": sphere_field(n)}],
            "camera": {"type": "perspective", "fov": 40, "width": size, "height": size,
                       "to_world": [{"look_at": {"origin": [0, 0, -35], "target": [0, 0, 0],
                                                 "up": [0, 1, 0]}}]},
            "lights": [{"type": "directional", "direction": [0.3, -1.0, 0.5], "irradiance": 3}]}


def _kernels(dr, history: list[dict]) -> dict:
    """Launch statistics of one call: JIT kernels, those not in the in-memory cache
    (compiled by LLVM or loaded from the disk cache), compile and kernel time in ms."""
    jit = [k for k in history if k["type"] == dr.KernelType.JIT]
    new = [k for k in jit if not k.get("cache_hit", 1) or k.get("cache_disk", 0)]
    return {"launches": len(history), "jit": len(jit), "new": len(new),
            "compiled": sum(1 for k in new if not k.get("cache_disk", 0)),
            "compile_ms": sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in new),
            "kernel_ms": sum(k.get("execution_time", 0.0) for k in history),
            "hashes": sorted({k["hash"] for k in jit})}


def _timed_call(dr, fn) -> tuple[float, dict, object]:
    """Wall time, kernel statistics and result of fn() (which must finish its work)."""
    dr.kernel_history()  # clear
    start = time.perf_counter()
    result = fn()
    dr.sync_thread()
    seconds = time.perf_counter() - start
    return seconds, _kernels(dr, dr.kernel_history()), result


# -- the memory walk -----------------------------------------------------------------------

_SCALARS = (str, bytes, int, float, bool, type(None), complex)


def held_arrays(root, name: str, n: int, seen: dict | None = None) -> list[dict]:
    """Every Dr.Jit array, NumPy array and large Python container reachable from ``root``.

    Walks attributes (``vars()``, ``__slots__``), lists, tuples and dicts
    recursively, into objects of this project and of ``drjit`` (Dr.Jit arrays
    and nested ones: ``Array3f``, ``Matrix4f``, tensors). Each buffer is
    counted once (NumPy views by their base, Dr.Jit arrays by variable index;
    literals hold no memory). Returns rows ``{path, kind, bytes, count}``;
    pass the same ``seen`` to a second call to count only what it adds.
    """
    import drjit as dr
    seen = {} if seen is None else seen
    rows: list[dict] = []

    def add(path, kind, nbytes, key):
        if key in seen:
            return
        seen[key] = path
        rows.append({"path": path, "kind": kind, "bytes": int(nbytes)})

    def jit_leaves(value, out):
        if dr.is_tensor_v(value):
            jit_leaves(value.array, out)
        elif dr.depth_v(value) > 1 or (not dr.is_jit_v(value) and dr.is_array_v(value)):
            for i in range(len(value)):
                jit_leaves(value[i], out)
        elif dr.is_jit_v(value):
            out.append(value)

    def visit(obj, path, depth):
        if depth > 12 or isinstance(obj, _SCALARS):
            return
        if isinstance(obj, np.ndarray):
            base = obj
            while isinstance(base.base, np.ndarray):
                base = base.base
            add(path, f"numpy {obj.dtype} {tuple(obj.shape)}", base.nbytes, ("np", id(base)))
            return
        if dr.is_array_v(obj):
            leaves = []
            jit_leaves(obj, leaves)
            stored = [v for v in leaves if v.state != dr.VarState.Literal and v.index != 0]
            fresh = [v for v in stored if ("dr", v.index) not in seen]
            if fresh:
                nbytes = sum(dr.width(v) * dr.itemsize_v(v) for v in fresh)
                unevaluated = any(v.state == dr.VarState.Unevaluated for v in fresh)
                kind = f"drjit {type(obj).__name__} x{dr.width(obj)}" + (" (pending)" if unevaluated else "")
                rows.append({"path": path, "kind": kind, "bytes": int(nbytes)})
                for v in fresh:
                    seen[("dr", v.index)] = path
            return
        key = ("py", id(obj))
        if key in seen:
            return
        if isinstance(obj, (list, tuple, set, frozenset)):
            seen[key] = path
            items = list(obj)
            scalars = [x for x in items if isinstance(x, _SCALARS)]
            own = sys.getsizeof(obj) + sum(sys.getsizeof(x) for x in {id(x): x for x in scalars}.values()
                                           if ("py", id(x)) not in seen)
            if len(items) >= 64:
                rows.append({"path": path, "kind": f"python {type(obj).__name__}[{len(items)}]",
                             "bytes": own})
            if len(scalars) < len(items):
                for i, x in enumerate(items[:100_000]):
                    visit(x, f"{path}[{i}]", depth + 1)
            return
        if isinstance(obj, dict):
            seen[key] = path
            if len(obj) >= 64:
                own = sys.getsizeof(obj) + sum(sys.getsizeof(k) + sys.getsizeof(v) for k, v in obj.items()
                                               if isinstance(v, _SCALARS))
                rows.append({"path": path, "kind": f"python dict[{len(obj)}]", "bytes": own})
            for k, v in list(obj.items())[:100_000]:
                visit(v, f"{path}[{k!r}]", depth + 1)
            return
        module = type(obj).__module__ or ""
        if not (module.startswith("instancing") or module.startswith("drjit")):
            return
        if callable(obj) and not hasattr(obj, "__dict__"):
            return
        seen[key] = path
        attrs = dict(vars(obj)) if hasattr(obj, "__dict__") else {}
        for slot in getattr(type(obj), "__slots__", ()):
            if hasattr(obj, slot):
                attrs[slot] = getattr(obj, slot)
        for attr, value in attrs.items():
            visit(value, f"{path}.{attr}", depth + 1)

    visit(root, name, 0)
    for row in rows:
        row["per_instance"] = row["bytes"] / n
    return rows


def _drjit_storage(dr) -> int | None:
    """Bytes of all live Dr.Jit variables (from ``dr.whos``), to check the walk misses nothing."""
    text = dr.whos(True) or ""
    match = re.search(r"Storage\s*:\s*([\d.]+)\s*(B|KiB|MiB|GiB)\s+on device", text)
    if not match:
        return None
    return int(float(match.group(1)) * {"B": 1, "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30}[match.group(2)])


# -- the worker ----------------------------------------------------------------------------

def worker(n: int, repeats: int, size: int, spp: int, rays: int, step: bool, warm_only: bool) -> dict:
    """Everything measured for one N, in this (fresh) process."""
    import drjit as dr
    import drjit.opt
    import instancing
    import instancing.io.scene_file as scene_file
    from benchmarks.intersect import random_rays
    from instancing.core.backend import Array3f
    from instancing.ad.recovery import image_loss

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    out: dict = {"instances": n, "size": size, "spp": spp}
    source = scene_description(n, size)
    gc.collect()

    # 1. Load, with the parse_scene call inside load_scene timed on its own.
    parse = scene_file.parse_scene
    parse_s = []

    def timed_parse(*args, **kwargs):
        start = time.perf_counter()
        try:
            return parse(*args, **kwargs)
        finally:
            parse_s.append(time.perf_counter() - start)

    base = _settle(dr)
    out["peak_reset"] = _reset_peak()
    scene_file.parse_scene = timed_parse
    try:
        start = time.perf_counter()
        scene = instancing.load_scene(source)
        dr.sync_thread()
        out["load_s"] = time.perf_counter() - start
    finally:
        scene_file.parse_scene = parse
    out["parse_s"] = sum(parse_s)
    out["build_s"] = out["load_s"] - out["parse_s"]
    out["accel"] = scene.accel
    loaded = _settle(dr)

    # 3. First image, then later frames with other seeds, then the first seed again.
    def frame(seed):
        image = instancing.render(scene, "direct", spp=spp, seed=seed)
        dr.eval(image)
        return image

    out["render_first_s"], first_k, image = _timed_call(dr, lambda: frame(0))
    first_image = np.array(image)
    del image
    out["render_first_kernels"] = first_k
    out["lit_fraction"] = float((first_image.sum(axis=2) > 0).mean())
    if warm_only:
        out["intersect_first_s"], k, _ = _timed_call(dr, lambda: _intersect_once(dr, scene, rays, random_rays))
        out["intersect_first_kernels"] = k
        return out
    later = [_timed_call(dr, lambda s=seed: frame(s)) for seed in range(1, repeats + 1)]
    out["render_later_s"] = statistics.median(t for t, _, _ in later)
    out["render_later_kernels"] = [k for _, k, _ in later]
    out["render_later_new"] = max(k["new"] for _, k, _ in later)
    out["render_later_kernel_ms"] = statistics.median(k["kernel_ms"] for _, k, _ in later)
    del later
    again_s, again_k, again = _timed_call(dr, lambda: frame(0))
    out["render_repeat_identical"] = bool(np.array_equal(np.array(again), first_image))
    out["render_repeat_new"] = again_k["new"]
    del again
    rendered = _settle(dr)
    out["rss"] = {"base": base["VmRSS"], "loaded": loaded["VmRSS"], "rendered": rendered["VmRSS"],
                  "peak": rendered["VmHWM"]}

    # 2b. What the scene holds.
    seen: dict = {}
    out["held"] = held_arrays(scene, "scene", n, seen)
    out["drjit_storage"] = _drjit_storage(dr)

    # 1b. Intersection of random rays: first call against later calls.
    o, d = random_rays(*scene.bounds, rays)
    o = Array3f(*[o[:, k] for k in range(3)])
    d = Array3f(*[d[:, k] for k in range(3)])

    def intersect():
        hit = scene.intersect(o, d)
        dr.eval(hit.t, hit.p, hit.n, hit.instance, hit.prim)
        return hit

    out["intersect_first_s"], out["intersect_first_kernels"], hit = _timed_call(dr, intersect)
    out["hit_fraction"] = float((np.asarray(hit.instance) >= 0).mean())
    del hit
    times = [_timed_call(dr, intersect) for _ in range(repeats)]
    out["intersect_later_s"] = statistics.median(t for t, _, _ in times)
    out["intersect_later_new"] = max(k["new"] for _, k, _ in times)
    out["rays"] = rays
    del times, o, d

    # 3b. Optimisation steps: 8 instances' translations, L2 loss against the first image.
    if step:
        params = instancing.traverse(scene)
        opt = drjit.opt.Adam(lr=0.01)
        for i in np.linspace(0, n - 1, min(MOVING_INSTANCES, n)).astype(int):
            key = f"{scene.instance_ids[i]}.translation"
            opt[key] = params[key]
        target = instancing.core.backend.TensorXf(first_image)
        step = instancing.OptimisationStep(params, opt, image_loss, spp=spp)

        def one_step(seed):
            step(seed, target)
            dr.eval(opt.state)

        steps = [_timed_call(dr, lambda s=seed: one_step(s)) for seed in range(repeats + 3)]
        out["step_first_s"] = steps[0][0]
        out["step_later_s"] = statistics.median(t for t, _, _ in steps[3:])
        out["step_recordings"] = step.recordings
        out["step_new"] = [k["new"] for _, k, _ in steps]
        out["step_compile_ms"] = [round(k["compile_ms"], 1) for _, k, _ in steps]
        out["step_later_kernel_ms"] = statistics.median(k["kernel_ms"] for _, k, _ in steps[3:])
        # The scene again (set_transforms keeps its own copies), then what the parameters add.
        seen_after: dict = {}
        out["held_after_steps"] = held_arrays(scene, "scene", n, seen_after)
        out["params_held"] = held_arrays(params, "params", n, seen_after)
        out["rss_after_steps"] = _settle(dr)
    return out


def _intersect_once(dr, scene, rays, random_rays):
    from instancing.core.backend import Array3f
    o, d = random_rays(*scene.bounds, rays)
    hit = scene.intersect(Array3f(*[o[:, k] for k in range(3)]), Array3f(*[d[:, k] for k in range(3)]))
    dr.eval(hit.t, hit.p, hit.n, hit.instance, hit.prim)


def freeze_probe(n: int, size: int, spp: int, repeats: int) -> dict:
    """Replayed renders (``dr.freeze``, the default) against renders traced afresh
    (``frozen=False``): wall and kernel times (in its own process: a recording that meets
    a host callback aborts it)."""
    import drjit as dr
    import instancing
    from instancing.core.kernel_recording import recordings_of
    scene = instancing.load_scene(scene_description(n, size))
    calls = {name: (lambda f=flag: instancing.render(scene, "direct", spp=spp, seed=0, frozen=f))
             for name, flag in (("plain", False), ("frozen", True))}
    images, times, kernels = {}, {"plain": [], "frozen": []}, {"plain": [], "frozen": []}
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for name, fn in calls.items():
            images[name] = np.array(fn())  # compiles, or records
        for _ in range(repeats):
            for name, fn in calls.items():
                dr.kernel_history()
                start = time.perf_counter()
                dr.eval(fn())
                dr.sync_thread()
                times[name].append(time.perf_counter() - start)
                kernels[name].append(sum(k.get("execution_time", 0.0) for k in dr.kernel_history()) / 1e3)
    return {"plain_s": statistics.median(times["plain"]), "frozen_s": statistics.median(times["frozen"]),
            "plain_kernel_s": statistics.median(kernels["plain"]),
            "frozen_kernel_s": statistics.median(kernels["frozen"]),
            "recordings": sum(f.n_recordings for f in recordings_of(scene, "render").functions()),
            "identical": bool(np.array_equal(images["plain"], images["frozen"]))}


# -- the parent: one process per N, tables ------------------------------------------------------

def _run_worker(config: dict, home: str) -> dict:
    env = dict(os.environ, HOME=home, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    try:
        proc = subprocess.run([sys.executable, "-m", "benchmarks.scale", "--worker", json.dumps(config)],
                              cwd=ROOT, env=env, capture_output=True, text=True, timeout=WORKER_TIMEOUT)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {WORKER_TIMEOUT} s"}
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith(_RESULT):
            return json.loads(line[len(_RESULT):])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"error": f"exit code {proc.returncode}: " + " | ".join(tail)}


def measure(counts, repeats: int, size: int, spp: int, rays: int, step_max: int) -> dict:
    rows = []
    print(TIME_HEADER, flush=True)
    for n in counts:
        with tempfile.TemporaryDirectory(prefix="scale-home-") as home:
            config = {"mode": "full", "n": n, "repeats": repeats, "size": size, "spp": spp,
                      "rays": rays, "step": n <= step_max}
            row = _run_worker(config, home)
            if "error" not in row:
                warm = _run_worker(dict(config, mode="warm"), home)
                row["warm"] = warm
        row.setdefault("instances", n)
        rows.append(row)
        print(time_line(row), flush=True)
    probes = []
    for probe_spp in FREEZE_PROBE_SPP:
        with tempfile.TemporaryDirectory(prefix="scale-home-") as home:
            probe = _run_worker({"mode": "freeze", "n": 1000, "size": 64, "spp": probe_spp,
                                 "repeats": repeats}, home)
        probes.append(dict(probe, spp=probe_spp))
    return {"rows": rows, "freeze": probes, "target_bytes_per_instance": TARGET_BYTES_PER_INSTANCE,
            "repeats": repeats}


TIME_HEADER = (f"{'instances':>9} {'accel':>5} {'parse s':>7} {'build s':>7} {'1st img':>7} "
               f"{'warm 1st':>8} {'later':>6} {'new':>3} {'same':>4} {'1st isect':>9} "
               f"{'Mrays/s':>7} {'1st step':>8} {'step':>6} {'kernel':>6} {'new/step':>12}")


def _f(value, fmt: str, width: int) -> str:
    return f"{value:{width}{fmt}}" if isinstance(value, (int, float)) else f"{'-':>{width}}"


def time_line(r: dict) -> str:
    if "error" in r:
        return f"{r['instances']:>9} error: {r['error']}"
    warm = r.get("warm", {})
    steps = "/".join(str(k) for k in r["step_new"]) if "step_new" in r else "-"
    return (f"{r['instances']:>9} {r['accel']:>5} {r['parse_s']:7.2f} {r['build_s']:7.2f} "
            f"{r['render_first_s']:7.2f} {_f(warm.get('render_first_s'), '.2f', 8)} "
            f"{r['render_later_s']:6.3f} {r['render_later_new']:>3} "
            f"{'yes' if r['render_repeat_identical'] else 'NO':>4} {r['intersect_first_s']:9.2f} "
            f"{r['rays'] / r['intersect_later_s'] / 1e6:7.2f} {_f(r.get('step_first_s'), '.2f', 8)} "
            f"{_f(r.get('step_later_s'), '.3f', 6)} {_f(r.get('step_later_kernel_ms', 0) / 1e3 if 'step_later_kernel_ms' in r else None, '.3f', 6)} {steps:>12}")


def _group(kind: str) -> str:
    return kind.split()[0]


def memory_table(rows: list[dict]) -> list[str]:
    lines = [f"{'instances':>9} {'RSS MB':>7} {'peak MB':>7} {'grown B/i':>9} {'peak B/i':>8} "
             f"{'slope B/i':>9} {'drjit B/i':>9} {'numpy B/i':>9} {'python B/i':>10} {'held B/i':>8} "
             f"{'target':>6} {'in opt B/i':>10}"]
    previous = None
    for r in rows:
        if "error" in r:
            continue
        n, rss = r["instances"], r["rss"]
        grown = rss["rendered"] - rss["base"]
        peak = rss["peak"] - rss["base"]
        slope = ((grown - previous[1]) / (n - previous[0])) if previous else None
        previous = (n, grown)
        by = {g: sum(x["bytes"] for x in r["held"] if _group(x["kind"]) == g) / n
              for g in ("drjit", "numpy", "python")}
        held = sum(by.values())
        params = (sum(x["bytes"] for x in r["held_after_steps"] + r["params_held"]) / n
                  if "params_held" in r else None)
        lines.append(f"{n:>9} {rss['rendered'] / 2**20:7.0f} {rss['peak'] / 2**20:7.0f} "
                     f"{grown / n:9.0f} {peak / n:8.0f} {_f(slope, '.0f', 9)} {by['drjit']:9.1f} "
                     f"{by['numpy']:9.1f} {by['python']:10.1f} {held:8.1f} "
                     f"{'met' if held <= TARGET_BYTES_PER_INSTANCE else 'MISSED':>6} "
                     f"{_f(params, '.0f', 10)}")
    return lines


def breakdown_table(row: dict, key: str = "held") -> list[str]:
    n = row["instances"]
    items = sorted(row[key], key=lambda x: -x["bytes"])
    big = [x for x in items if x["per_instance"] >= BREAKDOWN_MIN_BYTES]
    small = [x for x in items if x["per_instance"] < BREAKDOWN_MIN_BYTES]
    lines = [f"  {'held by':<40} {'kind':<38} {'MB':>8} {'B/inst':>7}"]
    for x in big:
        lines.append(f"  {x['path']:<40} {x['kind']:<38} {x['bytes'] / 2**20:8.2f} {x['per_instance']:7.1f}")
    if small:
        total = sum(x["bytes"] for x in small)
        lines.append(f"  {f'({len(small)} smaller arrays)':<40} {'':<38} {total / 2**20:8.2f} {total / n:7.2f}")
    total = sum(x["bytes"] for x in items)
    lines.append(f"  {'total':<40} {'':<38} {total / 2**20:8.2f} {total / n:7.1f}")
    return lines


def report(result: dict) -> None:
    rows = [r for r in result["rows"] if "error" not in r]
    print()
    print("Memory (RSS grown from before load_scene to after load + renders; 'held': arrays and")
    print(f"large containers reachable from the Scene; target {TARGET_BYTES_PER_INSTANCE} B/instance; "
          "'in opt': the scene after optimisation steps plus its instancing.traverse state)")
    for line in memory_table(result["rows"]):
        print(line)
    if rows:
        big = rows[-1]
        print()
        walked = sum(x["bytes"] for x in big["held"] if x["kind"].startswith("drjit"))
        print(f"What the scene holds at {big['instances']} instances (its Dr.Jit arrays: {walked / 2**20:.2f} MB; "
              f"all live Dr.Jit variables: "
              f"{(big['drjit_storage'] or 0) / 2**20:.2f} MB):")
        for line in breakdown_table(big):
            print(line)
        if "params_held" in big:
            print("During optimisation: the scene after the steps, then what instancing.traverse adds:")
            for line in breakdown_table(big, "held_after_steps") + breakdown_table(big, "params_held"):
                print(line)
        print()
        for r in rows:
            k = r["render_first_kernels"]
            print(f"{r['instances']:>9}: first image compiled {k['compiled']} kernels "
                  f"({k['compile_ms'] / 1e3:.2f} s in LLVM), later frames {r['render_later_new']} new, "
                  f"kernel time {r['render_later_kernel_ms'] / 1e3:.3f} of {r['render_later_s']:.3f} s"
                  + (f"; steps ({r['step_recordings']} recordings): new kernels {r['step_new']}, kernel time "
                     f"{r['step_later_kernel_ms'] / 1e3:.3f} of {r['step_later_s']:.3f} s"
                     if "step_new" in r else ""))
        last = rows[-1]
        print(f"largest scene: {last['instances']} instances loaded in {last['load_s']:.2f} s, "
              f"first image {last['render_first_s']:.2f} s, {100 * last['lit_fraction']:.0f} % of pixels lit")
    for probe in result.get("freeze", []):
        if "error" in probe:
            print(f"dr.freeze(render) at {probe['spp']} spp: fails: {probe['error']}")
        else:
            print(f"dr.freeze(render) at 1000 instances, 64x64, {probe['spp']} spp: traced "
                  f"{probe['plain_s']:.4f} s (kernels {probe['plain_kernel_s']:.4f} s), replayed "
                  f"{probe['frozen_s']:.4f} s (kernels {probe['frozen_kernel_s']:.4f} s), "
                  f"{probe['recordings']} recording, images identical: {probe['identical']}")


def main(argv=None) -> dict | None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[1000, 10000, 100000, 1000000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--size", type=int, default=256, help="image width and height")
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--rays", type=int, default=1 << 20)
    parser.add_argument("--step-max", type=int, default=1_000_000,
                        help="largest N for which optimisation steps are timed")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        config = json.loads(args.worker)
        if config["mode"] == "freeze":
            result = freeze_probe(config["n"], config["size"], config["spp"], config["repeats"])
        else:
            result = worker(config["n"], config["repeats"], config["size"], config["spp"],
                            config["rays"], config["step"], config["mode"] == "warm")
        print(_RESULT + json.dumps(result), flush=True)
        return
    if min(args.counts) < 1 or min(args.repeats, args.size, args.spp, args.rays) < 1:
        parser.error("counts, repeats, size, spp and rays must be positive")
    print(f"Sphere instances, {args.size}x{args.size} 'direct' at {args.spp} spp, {args.rays} random rays; "
          f"seconds, 'later' = median of {args.repeats}; each N in its own process with a cold "
          "kernel cache ('warm 1st': a second process with the disk cache filled)")
    result = measure(args.counts, args.repeats, args.size, args.spp, args.rays, args.step_max)
    report(result)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
