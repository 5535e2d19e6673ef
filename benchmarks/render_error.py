"""Render time against error: ours and Mitsuba 3 on the bundled scenes, in the same run.

For every bundled scene with a camera (``direct`` and ``path``; the terrain is
one mesh of 100 352 triangles) and the participating-media scenes
(``volpath``: fog, plume, smoke, subsurface, window in scenes/media), both
renderers render the same scene at a reduced film size (``--width/--height``,
128x96 by default, the camera's filter kept) for spp = 1, 2, 4, ...
``--max-spp``; a renderer whose median render exceeds ``--max-render-s``
(4 s) stops there, which keeps the default run near 20 minutes on two cores
(our forest renders are ~25x slower per sample than Mitsuba's). For each
renderer and spp the script prints

* the wall time of ``instancing.render`` and of ``mi.render`` on the scene
  exported by ``instancing.to_mitsuba`` (plain shapes where Mitsuba accepts
  every transform, ``shapegroup`` + ``instance`` otherwise, as
  ``instancing.validation.crosscheck`` does; Mitsuba's ``direct``, ``path`` and ``volpath``
  with ``max_depth`` -1, ours with the same), the median of ``--repeats`` renders
  after one warm-up render at the same spp (the "first" column: it includes
  any kernel compilation; the timed renders include a compilation only when
  the renderer traces a kernel that is not in Dr.Jit's cache, which the
  diagnostics below count; ours replays the warm-up's ``dr.freeze``
  recording, ``render``'s default, and traces nothing). The clock stops after
  the image is copied to NumPy, which waits for the kernels;
* the relative RMSE against a reference image,
  ``sqrt(mean((img - ref)^2)) / mean(ref)`` over all pixels and channels,
  as the root mean square of the errors of the timed renders. Each render has
  its own seed, and the reference's seeds are different from all of them.

Reference (``--reference``): by default Mitsuba at ``--reference-spp``
(4096) spp, rendered in chunks of at most ``--chunk-spp`` with distinct seeds
and averaged. Mitsuba is the independent renderer the project validates
against, and the faster of the two per sample here, so it gives the least
noisy reference for the time; any bias of ours against it then shows as our
error floor. ``both`` averages the two renderers (half the samples each), so
that neither is favoured; ``ours`` uses ours alone. The reference's own noise
is estimated from the difference of its two halves (for ``both``: Mitsuba's
half against ours, which then also contains any bias between them) and
printed; a measured error near it is the reference's noise, not the renderer's.

Equal-error speed-up: the target error is the error Mitsuba reaches at
``--target-spp`` (64; or at the highest spp it reached below that within the
time cap); each renderer's time at that error is interpolated between the
measured spp in log(time)-log(error), and the speed-up is Mitsuba's time /
ours (> 1: we are faster). "n/r" means the renderer's curve does not reach the
target within the measured spp (an error floor above it, or the time cap).
A curve that a few bright pixels (fireflies) dominate rises and falls from
one spp to the next, and its first crossing of the target is then a matter of
luck. The variance model ("model" column) uses every spp instead: an unbiased
renderer's expected squared error at n spp is ref_noise^2 + V / n, each spp
gives an estimate (error^2 - ref_noise^2) * n of the variance per sample V,
and V is their median (over the spp whose excess is at least ref_noise^2).
Mitsuba at the target spp and ours at target_spp * V_ours / V_mitsuba spp
then have equal expected error; their times are interpolated between the
measured spp, and the model's speed-up is Mitsuba's time over ours. On
well-behaved curves the two speed-ups agree.
With ``--sampler`` (a Mitsuba sampler type) both renderers draw their samples with it, ours
with its stratified sampler for every type but ``independent``; the variance model then
does not hold (stratified samples' error falls faster than one over the square root of
the samples), and the first crossing is the figure to read.
The error floor is each renderer's error at its highest spp (printed as
error@spp); a floor well above the other renderer's shows a bias between
them, a floor at the reference's noise shows nothing.

Estimators differ where Mitsuba's ``direct`` picks one emitter per sample
among several (scenes with a point or directional light besides the sky)
while ours traces a shadow ray to every point and directional light: ours
costs more per sample and has less variance, which is what comparing at
equal error, not at equal spp, accounts for.

Diagnostics: one more render per renderer at the target spp with Dr.Jit's
kernel history on gives the kernels launched, how many missed the kernel
cache (and were compiled), the compile and the execution time, and the rest
of the wall time ("host": tracing the kernels, launches, copies).

By default the reference scenes of the transform recovery
(recover_init/recover_target: three instances under one point light) are
left out: they add nothing that light_point does not show.

Usage: python benchmarks/render_error.py [--scenes cornell_box forest] [--integrators direct path volpath]
       [--rfilter gaussian] [--sampler multijitter] [--width 128 --height 96] [--max-render-s 4]
       [--max-spp 256] [--reference-spp 4096] [--repeats 3]
       [--plot docs/render_error.png] [--json results.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import time
from pathlib import Path

import numpy as np

import instancing
from instancing.core.backend import MITSUBA_VARIANT, dr
from instancing.core.errors import SceneError
from instancing.scene.camera import RFILTERS, SAMPLERS

SCENE_DIR = Path(__file__).resolve().parent.parent / "scenes"
#: Scenes left out by default (see the module docstring).
SKIPPED_SCENES = ("recover_init", "recover_target")
#: The participating-media scenes (scenes/media/<name>.xml), rendered with ``volpath`` only.
MEDIUM_SCENES = ("fog", "plume", "smoke", "subsurface", "window")
#: Seed ranges: measured renders count up from MEASURE_SEED, reference chunks from REFERENCE_SEED.
MEASURE_SEED = 1_000
REFERENCE_SEED = 1_000_000


def default_scenes() -> list[str]:
    """Every bundled scene with a camera, minus SKIPPED_SCENES."""
    names = []
    for path in sorted(SCENE_DIR.glob("*.json")):
        if path.stem in SKIPPED_SCENES:
            continue
        if instancing.load_scene(path).camera is not None:
            names.append(path.stem)
    return names


def mitsuba():
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    return mi


class Renderers:
    """Both renderers on one scene and integrator, at one film size."""

    def __init__(self, name: str, integrator: str, width: int, height: int, rfilter: str | None = None,
                 sampler: str | None = None):
        self.mi = mitsuba()
        self.scene = instancing.load_scene(SCENE_DIR / "media" / f"{name}.xml" if name in MEDIUM_SCENES
                                           else SCENE_DIR / f"{name}.json")
        if rfilter is not None:
            # Both renderers with this reconstruction filter at its default size.
            self.scene.set_camera(dataclasses.replace(self.scene.camera, rfilter=rfilter, rfilter_size=None))
        if sampler is not None:
            # Both renderers with this sampler type (the export names it to Mitsuba).
            self.scene.set_camera(dataclasses.replace(self.scene.camera, sampler=sampler))
        self.integrator, self.width, self.height = integrator, width, height
        # Export: plain shapes where Mitsuba accepts every transform (faster there), else instances.
        try:
            desc, self.mode = instancing.to_mitsuba(self.scene, mode="shapes"), "shapes"
        except SceneError:
            desc, self.mode = instancing.to_mitsuba(self.scene, mode="instances"), "instances"
        # to_mitsuba writes the camera's film size; render both at the reduced one.
        desc["sensor"]["film"]["width"] = width
        desc["sensor"]["film"]["height"] = height
        self.mscene = self.mi.load_dict(desc)
        self.mintegrator = self.mi.load_dict(
            {"type": "direct"} if integrator == "direct" else {"type": integrator, "max_depth": -1})

    def ours(self, spp: int, seed: int) -> np.ndarray:
        image = instancing.render(self.scene, self.integrator, spp=spp, seed=seed,
                                  width=self.width, height=self.height)
        return np.array(image, dtype=np.float64)  # the copy waits for the kernels

    def theirs(self, spp: int, seed: int) -> np.ndarray:
        image = self.mi.render(self.mscene, integrator=self.mintegrator, spp=spp, seed=seed)
        return np.array(image, dtype=np.float64)[..., :3]

    def render(self, who: str, spp: int, seed: int) -> np.ndarray:
        return self.ours(spp, seed) if who == "ours" else self.theirs(spp, seed)


def rel_rmse(image: np.ndarray, ref: np.ndarray) -> float:
    """sqrt(mean((image - ref)^2)) / mean(ref) over all pixels and channels."""
    return float(np.sqrt(np.mean((image - ref) ** 2)) / max(float(np.mean(ref)), 1e-12))


def reference(r: Renderers, which: str, spp: int, chunk: int) -> tuple[np.ndarray, float, float]:
    """(reference image, its estimated relative noise, seconds spent).

    The chunks are split into two halves A and B (for 'both': Mitsuba's and
    ours); ref = (A + B) / 2, whose noise variance is estimated by
    mean((A - B)^2) / 4.
    """
    start = time.perf_counter()
    half = max(1, spp // 2)
    halves = []
    seed = REFERENCE_SEED
    for k, who in enumerate(("mitsuba", "ours") if which == "both" else (which, which)):
        total, done = 0.0, 0
        while done < half:
            count = min(chunk, half - done)
            total = total + r.render(who, count, seed) * count
            done += count
            seed += 1
        halves.append(total / half)
    ref = 0.5 * (halves[0] + halves[1])
    noise = float(np.sqrt(np.mean((halves[0] - halves[1]) ** 2)) / 2 / max(float(np.mean(ref)), 1e-12))
    return ref, noise, time.perf_counter() - start


def sweep(r: Renderers, ref: np.ndarray, spps: list[int], repeats: int, max_render_s: float) -> dict:
    """Per spp and renderer: first-render time, median timed render, RMS relative error.

    The two renderers alternate render by render, so that load from other jobs
    on the machine hits both alike. A renderer whose median render takes more
    than ``max_render_s`` skips the higher spp (its curve ends there).
    """
    out = {who: {"spp": [], "first_s": [], "time_s": [], "error": []} for who in ("ours", "mitsuba")}
    active = ["ours", "mitsuba"]
    seed = MEASURE_SEED
    for spp in spps:
        if not active:
            break
        times = {who: [] for who in active}
        errors = {who: [] for who in active}
        for k in range(repeats + 1):
            for who in active:
                start = time.perf_counter()
                image = r.render(who, spp, seed)
                spent = time.perf_counter() - start
                seed += 1
                if k == 0:
                    out[who]["first_s"].append(spent)
                else:
                    times[who].append(spent)
                    errors[who].append(rel_rmse(image, ref) ** 2)
        for who in list(active):
            out[who]["spp"].append(spp)
            out[who]["time_s"].append(statistics.median(times[who]))
            out[who]["error"].append(math.sqrt(statistics.fmean(errors[who])))
            if out[who]["time_s"][-1] > max_render_s:
                active.remove(who)
    return out


def time_at_error(curve: dict, target: float) -> float:
    """Time at which the curve's error first falls to ``target`` (log-log interpolation).

    NaN when the error never gets that low; the first point's time when even it is below.
    """
    t, e = curve["time_s"], curve["error"]
    if e[0] <= target:
        return t[0]
    for i in range(len(e) - 1):
        if e[i] >= target >= e[i + 1] and e[i] > e[i + 1]:
            w = (math.log(target) - math.log(e[i])) / (math.log(e[i + 1]) - math.log(e[i]))
            return math.exp(math.log(t[i]) + w * (math.log(t[i + 1]) - math.log(t[i])))
    return float("nan")


def variance_per_sample(curve: dict, ref_noise: float) -> float:
    """The renderer's variance per sample (relative to the reference's mean, squared).

    An unbiased renderer's expected squared error at n spp is ref_noise^2 + V / n
    (the reference's noise adds to every render's); each measured spp gives one
    estimate (error^2 - ref_noise^2) * n of V, and V is their median over the spp
    whose excess error^2 - ref_noise^2 is at least ref_noise^2 (below it the
    estimate is mostly the reference's noise). The median keeps a spp whose few
    renders caught a firefly, or missed one, from deciding. NaN when no spp
    qualifies.
    """
    noise2 = ref_noise * ref_noise
    estimates = [(e * e - noise2) * n for n, e in zip(curve["spp"], curve["error"]) if e * e >= 2 * noise2]
    return statistics.median(estimates) if estimates else float("nan")


def time_at_spp(curve: dict, spp: float) -> float:
    """The median render time at ``spp``, interpolated in log(time)-log(spp) between the
    measured spp; the first spp's time below it (a render takes at least one sample per
    pixel), NaN above the last."""
    s, t = curve["spp"], curve["time_s"]
    if spp <= s[0]:
        return t[0]
    if spp > s[-1]:
        return float("nan")
    return math.exp(float(np.interp(math.log(spp), np.log(s), np.log(t))))


def model_times(curves: dict, ref_noise: float, target_spp: int) -> tuple[float, float, float]:
    """(ours s, Mitsuba s, ours spp) at equal error by the variance model.

    The target is Mitsuba's variance at ``target_spp``, V_mitsuba / target_spp; ours
    reaches it at target_spp * V_ours / V_mitsuba spp.
    """
    v_ours = variance_per_sample(curves["ours"], ref_noise)
    v_mi = variance_per_sample(curves["mitsuba"], ref_noise)
    spp_ours = target_spp * v_ours / v_mi if v_mi > 0 else float("nan")
    return time_at_spp(curves["ours"], spp_ours), time_at_spp(curves["mitsuba"], target_spp), spp_ours


#: The two estimators of the equal-error speed-up: result key, name.
ESTIMATORS = (("speedup_equal_error", "first crossing"), ("speedup_variance_model", "variance model"))


def kernel_profile(r: Renderers, who: str, spp: int) -> dict:
    """Kernels launched by one render, cache misses, compile and execution seconds."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # drop earlier entries
    start = time.perf_counter()
    r.render(who, spp, MEASURE_SEED - 1)
    wall = time.perf_counter() - start
    history = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    out = {"wall_s": wall, "kernels": len(history),
           "misses": sum(1 for h in history if not h["cache_hit"]),
           "compile_s": sum(h["codegen_time"] + h["backend_time"] for h in history) / 1e3,
           "execute_s": sum(h["execution_time"] for h in history) / 1e3}
    # The rest of the wall time: tracing the kernels in Python/C++, launches, copies.
    out["host_s"] = max(0.0, wall - out["compile_s"] - out["execute_s"])
    return out


def run_one(name: str, integrator: str, args) -> dict:
    start = time.perf_counter()
    r = Renderers(name, integrator, args.width, args.height, args.rfilter, args.sampler)
    # Warm both up once (first compilation of each, at the lowest spp).
    r.ours(1, 0)
    r.theirs(1, 0)
    ref, ref_noise, ref_s = reference(r, args.reference, args.reference_spp, args.chunk_spp)
    spps = [1 << k for k in range(int(math.log2(args.max_spp)) + 1)]
    curves = sweep(r, ref, spps, args.repeats, args.max_render_s)
    # Mitsuba's error at the target spp (or at the highest it reached within the time cap).
    mi_spps = curves["mitsuba"]["spp"]
    target_spp = max(s for s in mi_spps if s <= args.target_spp) if mi_spps[0] <= args.target_spp else mi_spps[0]
    target = curves["mitsuba"]["error"][mi_spps.index(target_spp)]
    t_ours, t_mi = time_at_error(curves["ours"], target), time_at_error(curves["mitsuba"], target)
    m_ours, m_mi, m_spp = model_times(curves, ref_noise, target_spp)
    row = {"scene": name, "integrator": integrator, "mitsuba_mode": r.mode,
           "width": args.width, "height": args.height, "reference": args.reference,
           "reference_spp": args.reference_spp, "reference_noise": ref_noise, "reference_s": ref_s,
           "curves": curves, "target_spp": target_spp, "target_error": target,
           "ours_time_at_target": t_ours, "mitsuba_time_at_target": t_mi,
           "speedup_equal_error": t_mi / t_ours,
           "variance_ours": variance_per_sample(curves["ours"], ref_noise),
           "variance_mitsuba": variance_per_sample(curves["mitsuba"], ref_noise),
           "ours_spp_model": m_spp, "ours_time_model": m_ours, "mitsuba_time_model": m_mi,
           "speedup_variance_model": m_mi / m_ours,
           "floor_ours": curves["ours"]["error"][-1], "floor_mitsuba": curves["mitsuba"]["error"][-1],
           "floor_spp_ours": curves["ours"]["spp"][-1], "floor_spp_mitsuba": curves["mitsuba"]["spp"][-1],
           "profile": {who: kernel_profile(r, who, target_spp) for who in ("ours", "mitsuba")}}
    row["total_s"] = time.perf_counter() - start
    return row


HEADER = (f"{'scene':<17} {'integ':<6} {'spp':>5} {'ours s':>8} {'(first)':>8} {'ours err':>9} "
          f"{'mi s':>8} {'(first)':>8} {'mi err':>9} {'mi/ours s':>9}")


def print_rows(row: dict) -> None:
    o, m = row["curves"]["ours"], row["curves"]["mitsuba"]
    blank = f"{'-':>8} {'-':>8} {'-':>9}"
    for i, spp in enumerate(sorted(set(o["spp"]) | set(m["spp"]))):
        cols = []
        for c in (o, m):
            if spp in c["spp"]:
                j = c["spp"].index(spp)
                cols.append(f"{c['time_s'][j]:>8.3f} {c['first_s'][j]:>8.3f} {c['error'][j]:>9.4f}")
            else:
                cols.append(blank)
        ratio = (m["time_s"][m["spp"].index(spp)] / o["time_s"][o["spp"].index(spp)]
                 if spp in o["spp"] and spp in m["spp"] else float("nan"))
        print(f"{row['scene']:<17} {row['integrator']:<6} {spp:>5} {cols[0]} {cols[1]} {_fmt(ratio, '9.2f'):>9}",
              flush=True)


SUMMARY_HEADER = (f"{'scene':<17} {'integ':<6} {'mi mode':<9} {'target':>12} {'ours s':>7} "
                  f"{'mi s':>7} {'speed-up':>8} {'model':>7} {'floor ours':>14} {'floor mi':>14} "
                  f"{'ref noise':>9} "
                  f"{'host/compile/exec s ours':>24} {'miss':>5} {'host/compile/exec s mi':>22} {'miss':>5}")


def _fmt(x: float, spec: str) -> str:
    return "n/r" if math.isnan(x) else format(x, spec)


def summary_line(row: dict) -> str:
    p, q = row["profile"]["ours"], row["profile"]["mitsuba"]
    target = f"{row['target_error']:.4f}@{row['target_spp']}"
    floor_ours = f"{row['floor_ours']:.4f}@{row['floor_spp_ours']}"
    floor_mi = f"{row['floor_mitsuba']:.4f}@{row['floor_spp_mitsuba']}"
    return (f"{row['scene']:<17} {row['integrator']:<6} {row['mitsuba_mode']:<9} {target:>12} "
            f"{_fmt(row['ours_time_at_target'], '7.3f'):>7} {_fmt(row['mitsuba_time_at_target'], '7.3f'):>7} "
            f"{_fmt(row['speedup_equal_error'], '8.2f'):>8} {_fmt(row['speedup_variance_model'], '7.2f'):>7} "
            f"{floor_ours:>14} {floor_mi:>14} "
            f"{row['reference_noise']:>9.4f} {_profile(p):>24} {p['misses']:>2}/{p['kernels']:<2} "
            f"{_profile(q):>22} {q['misses']:>2}/{q['kernels']:<2}")


def _profile(p: dict) -> str:
    return f"{p['host_s']:.3f}/{p['compile_s']:.3f}/{p['execute_s']:.3f}"


def plot(rows: list[dict], path: str) -> None:
    """Error against time, log-log, one panel per scene and integrator."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter
    cols = min(4, len(rows))
    nrows = math.ceil(len(rows) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 2.9 * nrows), squeeze=False)
    for ax, row in zip(axes.flat, rows):
        for who, colour in (("ours", "tab:blue"), ("mitsuba", "tab:orange")):
            c = row["curves"][who]
            ax.loglog(c["time_s"], c["error"], "o-", ms=3, color=colour,
                      label="ours" if who == "ours" else "Mitsuba")
            for spp, t, e in zip(c["spp"], c["time_s"], c["error"]):
                if spp in (1, row["target_spp"], c["spp"][-1]):
                    ax.annotate(str(spp), (t, e), fontsize=6, color=colour,
                                xytext=(3, 3), textcoords="offset points")
        ax.axhline(row["target_error"], color="grey", lw=0.7, ls="--")
        ax.axhline(row["reference_noise"], color="grey", lw=0.7, ls=":")
        speedup = _fmt(row["speedup_equal_error"], ".2f")
        model = _fmt(row["speedup_variance_model"], ".2f")
        ax.set_title(f"{row['scene']} / {row['integrator']}  (Mitsuba/ours {speedup}, model {model})",
                     fontsize=8)
        ax.tick_params(labelsize=7)
        ax.xaxis.set_minor_formatter(NullFormatter())  # crowded minor labels on short log ranges
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wall time (s)", fontsize=7)
        ax.set_ylabel("relative RMSE", fontsize=7)
        ax.grid(True, which="both", lw=0.3, alpha=0.5)
    axes.flat[0].legend(fontsize=7)
    for ax in list(axes.flat)[len(rows):]:
        ax.axis("off")
    fig.suptitle(f"error vs time, {rows[0]['width']}x{rows[0]['height']}; labels: spp; "
                 "dashed: target error, dotted: reference noise", fontsize=9)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=None,
                        help="scene names in scenes/ and scenes/media/ (default: every one with a camera "
                             "but recover_*; 'volpath' runs on the media scenes, the others do not)")
    parser.add_argument("--integrators", nargs="+", default=["direct", "path", "volpath"],
                        choices=["direct", "path", "volpath"])
    parser.add_argument("--rfilter", choices=RFILTERS, default=None,
                        help="every scene's reconstruction filter, at its default size (default: each "
                             "scene's own; Mitsuba's scenes default to gaussian)")
    parser.add_argument("--sampler", choices=SAMPLERS, default=None,
                        help="every scene's sampler type, Mitsuba's and ours (default: each scene's own, "
                             "independent in the bundled scenes)")
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=96)
    parser.add_argument("--max-spp", type=int, default=256, help="a power of two")
    parser.add_argument("--target-spp", type=int, default=64,
                        help="the target error is Mitsuba's at this spp (a power of two)")
    parser.add_argument("--reference", choices=["mitsuba", "ours", "both"], default="mitsuba")
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--chunk-spp", type=int, default=1024, help="spp per reference render call")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-render-s", type=float, default=4.0,
                        help="a renderer skips higher spp once its median render takes longer")
    parser.add_argument("--plot", default="docs/render_error.png", help="PNG path; '' for none")
    parser.add_argument("--json", default=None, help="write the measurements to this JSON file")
    args = parser.parse_args(argv)
    for name in ("width", "height", "max_spp", "target_spp", "reference_spp", "chunk_spp", "repeats",
                 "max_render_s"):
        if getattr(args, name) <= 0:
            parser.error(f"--{name.replace('_', '-')} must be positive")
    for name in ("max_spp", "target_spp"):
        if getattr(args, name) & (getattr(args, name) - 1):
            parser.error(f"--{name.replace('_', '-')} must be a power of two")
    available = default_scenes() + list(SKIPPED_SCENES) + list(MEDIUM_SCENES)
    unknown = [s for s in args.scenes or [] if s not in available]
    if unknown:
        parser.error(f"unknown scenes {unknown}; available: {available}")
    scenes = args.scenes or default_scenes() + list(MEDIUM_SCENES)
    jobs = [(s, i) for i in args.integrators for s in scenes
            if (s in MEDIUM_SCENES) == (i == "volpath")]

    rfilter, sampler = args.rfilter or "the scenes' own", args.sampler or "the scenes' own"
    print(f"render time vs relative RMSE, {args.width}x{args.height}, filter: {rfilter}; sampler: {sampler}; "
          f"reference: {args.reference} "
          f"at {args.reference_spp} spp; times: median of {args.repeats} after a warm-up at the same spp "
          f"(first: the warm-up render)")
    print(HEADER)
    start = time.perf_counter()
    rows = []
    for name, integrator in jobs:
        row = run_one(name, integrator, args)
        print_rows(row)
        print("  summary: " + summary_line(row).strip(), flush=True)
        rows.append(row)
        _save(args.json, {"args": vars(args), "total_s": time.perf_counter() - start, "rows": rows})
    print(f"\nequal error: target = Mitsuba's error at {args.target_spp} spp; speed-up = Mitsuba s / ours s "
          f"(> 1: ours faster) where each curve first reaches the target; model: the same from each "
          f"renderer's variance per sample (median over spp); floor = error@spp at the highest spp measured; "
          f"profile: one render at "
          f"the target spp, host (tracing, launches) / compile / execute seconds, kernel cache misses/kernels")
    print(SUMMARY_HEADER)
    for row in rows:
        print(summary_line(row))
    for key, name in ESTIMATORS:
        speedups = [r[key] for r in rows if not math.isnan(r[key])]
        if speedups:
            mean = math.exp(statistics.fmean(math.log(s) for s in speedups))
            print(f"geometric mean speed-up at equal error ({name}): {mean:.2f} over {len(speedups)} cases")
    total = time.perf_counter() - start
    print(f"total {total:.0f} s")
    if args.plot:
        plot(rows, args.plot)
        print(f"plot: {args.plot}")
    result = {"args": vars(args), "total_s": total, "rows": rows}
    if args.json:
        _save(args.json, result)
        print(f"json: {args.json}")
    return result


def _save(path: str | None, result: dict) -> None:
    """The measurements so far, rewritten after every row: a run cut short keeps what it measured."""
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
