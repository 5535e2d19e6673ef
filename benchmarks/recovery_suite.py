"""Success rates of transform recovery on seeded random problems, by number of views.

    python -m benchmarks.recovery --part suite [--problems 50] [--mitsuba-problems 10]
                                  [--iterations 300] [--spp 8] [--width 64]

Each problem is one object on a floor: an ellipsoid, an elliptic cylinder, a box, a flat
card or a torus mesh (in turn), at a random orientation and anisotropic scale, its start
moved by up to 20 % of its size, turned by up to 25 degrees about a random axis and scaled
by up to 20 % per axis (each between half and all of that); lit by a point light at the
first camera (even problems) or off the cameras (odd problems: its shadow on the floor in
view). Cameras look at the object from 30 degrees above the floor, 90 degrees apart around
it; a problem is recovered from the first 1, 2 and 4 of them. A recovery succeeds when the
returned transform is within 1 % of the size (translation), 1 degree and 1 % (every scale
axis) of the target. Both renderers descend coarse to fine: the loss compares the images
blurred by a Gaussian whose width starts at a twentieth of the film's and shrinks to none
over the first half of the run (``recover``'s ``blur_start``, ``blur_fraction``), so that a
mesh's facets do not hold the descent before the outline matches. Printed per view count:
the success rate, and for the successes the median iterations and seconds until the iterate
first met the tolerances. Targets are rendered at TARGET_SPP, converged: their noise would
move the optimum.

Beside ours, on the first problems (``--mitsuba-problems``, default 10: two of each kind;
Mitsuba's steps cost about three times ours here), the same recovery with its
``direct_projective`` integrator: the object as one plain mesh (the same shape tessellated:
a UV sphere, an open tube, Mitsuba's cube, two triangles, the torus) whose vertices are
transformed by the parameters in Dr.Jit each step, the same Adam schedule, iterate average,
learning rates, spp, images and coarse-to-fine loss; and again on the plain loss ("mitsuba
plain"), in case the blur does not suit it.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

import instancing
from instancing.ad.recovery import (AVERAGE_FRACTION, LR, LR_FINAL_RATIO, default_sppc, recover,
                                     transform_errors)

ROOT = Path(__file__).resolve().parents[1]
TORUS = ROOT / "scenes" / "meshes" / "torus.obj"
KINDS = ("ellipsoid", "elliptic cylinder", "box", "card", "mesh")
#: Per kind: the model, and its scale before the random factor (a card keeps z = 1).
MODELS = {"ellipsoid": ("sphere", (0.5, 0.36, 0.26)), "elliptic cylinder": ("cylinder", (0.4, 0.26, 0.9)),
          "box": ("cube", (0.45, 0.33, 0.25)), "card": ("rectangle", (0.55, 0.38, 1.0)),
          "mesh": ("torus", (0.5, 0.4, 0.45))}
#: Largest perturbation: translation as a fraction of the size, degrees, relative scale.
OFFSETS = (0.2, 25.0, 0.2)
#: The object's centre, the cameras' distance and elevation (degrees), the off-camera light.
CENTRE = np.array([0.0, 0.0, 0.75])
DISTANCE, ELEVATION = 4.2, 30.0
OFF_LIGHT = [2.5, -1.0, 4.5]
TOLERANCES = (0.01, 1.0, 0.01)
#: Samples per pixel of the target images: converged, so that their noise does not move the
#: optimum (at 256 spp it held a near-symmetric ellipsoid 1.4 degrees off).
TARGET_SPP = 4096
VIEW_COUNTS = (1, 2, 4)
#: The rows' recoveries: ours, Mitsuba's with the same coarse-to-fine loss, and Mitsuba's on
#: the plain loss (in case the blur does not suit it).
RENDERERS = ("ours", "mitsuba", "mitsuba plain")
#: Coarse to fine: the blur's first standard deviation as a fraction of the film width, and
#: the fraction of the iterations over which it shrinks to none.
BLUR, BLUR_FRACTION = 0.05, 0.5
#: The targets the suite is held to: the success rate per view count, and the kinds whose
#: every problem is to be recovered from 2 views.
TARGET_RATES = {4: 0.95, 2: 0.80}
TARGET_KINDS = ("ellipsoid", "elliptic cylinder")
#: Turns about the model's z axis that map it onto itself (the torus mesh's 24 segments):
#: with the scale's small anisotropy the turned target gives nearly the target's images.
SYMMETRY_TURNS = {"torus": 15.0}


def _rotation(axis, degrees) -> np.ndarray:
    return instancing.rotate([float(a) for a in axis], float(degrees)).to_numpy()[0][:3, :3]


def problem(index: int, seed: int = 2026) -> dict:
    """Problem ``index``: its kind, light, and target and start matrices."""
    rng = np.random.default_rng([seed, index])
    kind = KINDS[index % len(KINDS)]
    model, base = MODELS[kind]
    scale = np.array(base) * rng.uniform(0.85, 1.15, 3)
    if kind == "card":
        scale[2] = 1.0
    rotation = _rotation(rng.normal(size=3), rng.uniform(0, 360))
    # A cylinder's and a torus's extent is not centred on the model's origin.
    pivot = {"cylinder": [0, 0, -0.5]}.get(model, [0, 0, 0])
    target = np.eye(4)
    target[:3, :3] = rotation @ np.diag(scale)
    target[:3, 3] = CENTRE + target[:3, :3] @ np.array(pivot)
    size = 2.0 * np.linalg.svd(target[:3, :3], compute_uv=False)[0]
    shift = rng.normal(size=3)
    shift *= OFFSETS[0] * size * rng.uniform(0.5, 1.0) / np.linalg.norm(shift)
    turn = _rotation(rng.normal(size=3), OFFSETS[1] * rng.uniform(0.5, 1.0))
    grow = 1.0 + OFFSETS[2] * rng.uniform(0.5, 1.0, 3) * rng.choice([-1.0, 1.0], 3)
    if kind == "card":
        grow[2] = 1.0
    start = np.eye(4)
    start[:3, :3] = turn @ rotation @ np.diag(scale * grow)
    start[:3, 3] = target[:3, 3] + shift
    return {"index": index, "kind": kind, "model": model,
            "light": "at the camera" if index % 2 == 0 else "off the cameras",
            "target": target, "start": start}


def cameras(views: int, width: int) -> list[dict]:
    """The first ``views`` of four cameras around the object."""
    out = []
    for k in range(views):
        azimuth = math.radians(-90 + 90 * k)
        elevation = math.radians(ELEVATION)
        eye = CENTRE + DISTANCE * np.array([math.cos(azimuth) * math.cos(elevation),
                                            math.sin(azimuth) * math.cos(elevation),
                                            math.sin(elevation)])
        out.append({"type": "perspective", "fov": 30, "width": width, "height": width,
                    "to_world": [{"look_at": {"origin": eye.tolist(), "target": CENTRE.tolist(),
                                              "up": [0, 0, 1]}}]})
    return out


def scene_dict(p: dict, matrix: np.ndarray, views: int, width: int) -> dict:
    """Problem ``p`` with its object at ``matrix``, seen from ``views`` cameras."""
    eye = cameras(1, width)[0]["to_world"][0]["look_at"]["origin"]
    light = eye if p["light"] == "at the camera" else OFF_LIGHT
    return {"models": {"torus": {"type": "obj", "filename": str(TORUS)}},
            "materials": {"floor": {"type": "diffuse", "reflectance": [0.5, 0.5, 0.5]},
                          "paint": {"type": "diffuse", "reflectance": [0.75, 0.45, 0.2]}},
            "instances": [{"id": "floor", "model": "rectangle", "material": "floor",
                           "to_world": [{"scale": [4, 4, 1]}]},
                          {"id": "object", "model": p["model"], "material": "paint",
                           "to_world": [{"matrix": matrix.tolist()}]}],
            "cameras": cameras(views, width),
            "lights": [{"type": "point", "position": list(map(float, light)),
                        "intensity": [25.0, 25.0, 25.0]}]}


def _met(errors) -> bool:
    return all(e < t for e, t in zip(errors, TOLERANCES))


def _until_met(history) -> tuple[int | None, float | None]:
    """The first iteration whose iterate met the tolerances, and the seconds until then."""
    for it, errors in enumerate(history.errors[:-1]):
        if _met(errors["object"]):
            return it + 1, float(sum(history.seconds[:it + 1]))
    return None, None


def ours(p: dict, views: int, width: int, iterations: int, spp: int) -> dict:
    """Recover problem ``p`` from ``views`` views with this renderer."""
    target_scene = instancing.load_scene(scene_dict(p, p["target"], views, width))
    targets = [instancing.render(target_scene, "direct", spp=TARGET_SPP, seed=11, camera=k)
               for k in range(views)]
    params = instancing.traverse(instancing.load_scene(scene_dict(p, p["start"], views, width)))
    history = recover(params, targets, [f"object.{x}" for x in ("translation", "rotation", "scale")],
                      iterations=iterations, spp=spp, blur_start=BLUR * width,
                      blur_fraction=BLUR_FRACTION,
                      target_to_world={"object": target_scene.to_world[1]})
    final = history.errors[-1]["object"]
    until, seconds = _until_met(history)
    return {"errors": list(final), "success": _met(final), "iterations": until, "seconds": seconds,
            "seconds_per_iteration": float(np.median(history.seconds)),
            "to_world": params.scene.to_world[1].tolist()}


def settings(problems: int, iterations: int, spp: int, width: int, mitsuba: int) -> dict:
    """What a run is run with, saved beside its rows (a resumed run must match): the
    arguments of :func:`run`, the derivative's samples, the targets' samples, the blur and
    ``recover``'s default learning-rate schedule, which both renderers follow."""
    return {"problems": problems, "iterations": iterations, "spp": spp, "sppc": default_sppc(spp),
            "target_spp": TARGET_SPP, "width": width, "mitsuba_problems": min(mitsuba, problems),
            "blur": BLUR, "blur_fraction": BLUR_FRACTION, "lr": LR, "lr_final_ratio": LR_FINAL_RATIO,
            "average_fraction": AVERAGE_FRACTION}


def run(problems: int, iterations: int, spp: int, width: int, mitsuba: int,
        save=None, rows: list[dict] | None = None) -> dict:
    """Every problem at every view count (ours, and Mitsuba's on the first ``mitsuba``
    problems), and the table; ``save`` is called with the results so far after each row.
    ``rows``: those of an interrupted run with the same settings, which are not run again."""
    rows = list(rows or [])
    done = {(r["problem"], r["views"]) for r in rows}

    def results() -> dict:
        return {**settings(problems, iterations, spp, width, mitsuba), "rows": rows,
                "table": summary(rows)}

    for index in range(problems):
        p = problem(index)
        for views in VIEW_COUNTS:
            if (index, views) in done:
                continue
            start = time.perf_counter()
            row = {"problem": index, "kind": p["kind"], "light": p["light"], "views": views,
                   "start": list(transform_errors(p["start"], p["target"])),
                   "ours": ours(p, views, width, iterations, spp)}
            if index < mitsuba:
                from benchmarks.recovery_mitsuba import recover_mitsuba
                row["mitsuba"] = recover_mitsuba(p, views, width, iterations, spp,
                                                 BLUR * width, BLUR_FRACTION)
                row["mitsuba plain"] = recover_mitsuba(p, views, width, iterations, spp,
                                                       0.0, BLUR_FRACTION)
            rows.append(row)
            cells = [f"{name}: {'ok ' if row[name]['success'] else 'no '}" +
                     "/".join(f"{e:.3g}" for e in row[name]["errors"])
                     for name in RENDERERS if name in row]
            print(f"problem {index:>2} {p['kind']:<17} light {p['light']:<16} {views} view(s): "
                  f"{'; '.join(cells)} ({time.perf_counter() - start:.0f} s)", flush=True)
            if save is not None:
                save(results())
    print("\n".join(summary(rows) + target_lines(rows) + failures(rows)))
    return results()


def summary(rows: list[dict]) -> list[str]:
    """Success rate, median iterations and seconds to success, per view count and renderer;
    and per kind."""
    lines = [f"{'renderer':<13} {'views':>5} {'success':>9} {'median its':>11} {'median s':>9}"]
    for name in RENDERERS:
        for views in VIEW_COUNTS:
            got = [r[name] for r in rows if r["views"] == views and name in r]
            if not got:
                continue
            wins = [g for g in got if g["success"]]
            its = [g["iterations"] for g in wins if g["iterations"] is not None]
            secs = [g["seconds"] for g in wins if g["seconds"] is not None]
            lines.append(f"{name:<13} {views:>5} {len(wins):>4}/{len(got):<4} "
                         f"{np.median(its) if its else float('nan'):>11.0f} "
                         f"{np.median(secs) if secs else float('nan'):>9.1f}")
    lines.append(f"{'kind':<18} " + " ".join(f"{v} view(s)" for v in VIEW_COUNTS) + "  (ours)")
    for kind in KINDS:
        cells = []
        for views in VIEW_COUNTS:
            got = [r["ours"]["success"] for r in rows if r["kind"] == kind and r["views"] == views]
            cells.append(f"{sum(got):>4}/{len(got):<4}")
        lines.append(f"{kind:<18} " + " ".join(cells))
    return lines


def target_lines(rows: list[dict]) -> list[str]:
    """Ours against :data:`TARGET_RATES` and :data:`TARGET_KINDS`, one line each."""
    lines = []
    for views, rate in TARGET_RATES.items():
        got = [r["ours"]["success"] for r in rows if r["views"] == views]
        if got:
            lines.append(f"target: >= {100 * rate:g} % from {views} views: {sum(got)}/{len(got)} "
                         f"= {100 * sum(got) / len(got):.0f} %: "
                         f"{'met' if sum(got) >= rate * len(got) else 'missed'}")
    for kind in TARGET_KINDS:
        got = [r["ours"]["success"] for r in rows if r["views"] == 2 and r["kind"] == kind]
        if got:
            lines.append(f"target: every {kind} from 2 views: {sum(got)}/{len(got)}: "
                         f"{'met' if all(got) else 'missed'}")
    return lines


def near_symmetry(index: int) -> float:
    """How close problem ``index``'s target is to a rotational symmetry: the relative
    difference of the two closest axis lengths of its model's scale (0 for a body of
    revolution about the third axis; the rotation about that axis then leaves no trace in the
    image). A card has only two axes that matter, and a cylinder or torus only the z axis as
    its axis of revolution, so those pairs are the ones measured for them."""
    p = problem(index)
    axes = np.linalg.norm(p["target"][:3, :3], axis=0)
    pairs = {"card": [(0, 1)], "cylinder": [(0, 1)], "torus": [(0, 1)]}.get(
        p["model"], [(0, 1), (0, 2), (1, 2)])
    return min(abs(axes[i] - axes[j]) / max(axes[i], axes[j]) for i, j in pairs)


def symmetric_copy(index: int, to_world) -> tuple[float, float] | None:
    """For a model that turns onto itself (:data:`SYMMETRY_TURNS`): the nearest turned copy
    of problem ``index``'s target to the matrix ``to_world`` (degrees about the model's z
    axis, other than 0) and the rotation error (degrees) against it; None for other models."""
    p = problem(index)
    step = SYMMETRY_TURNS.get(p["model"])
    if step is None:
        return None
    turns = [k * step for k in range(1, int(round(360 / step)))]
    errors = [transform_errors(np.asarray(to_world), p["target"] @ _turn_z(t))[1] for t in turns]
    best = int(np.argmin(errors))
    return (turns[best] if turns[best] <= 180 else turns[best] - 360), errors[best]


def _turn_z(degrees: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = _rotation([0, 0, 1], degrees)
    return m


def failures(rows: list[dict]) -> list[str]:
    """The problems ours failed from 2 or more views: kind, final errors, how near the model
    is to a rotational symmetry (:func:`near_symmetry`) and, for a model that turns onto
    itself, how far the result is from the nearest turned copy (:func:`symmetric_copy`)."""
    lines = []
    for r in rows:
        if r["views"] >= 2 and not r["ours"]["success"]:
            e = r["ours"]["errors"]
            copy = symmetric_copy(r["problem"], r["ours"]["to_world"]) \
                if "to_world" in r["ours"] else None
            lines.append(f"failed: problem {r['problem']:>2} {r['kind']:<17} {r['views']} views: "
                         f"{e[0]:.2g} of the size, {e[1]:.3g} deg, scale {e[2]:.2g}; "
                         f"closest axes differ by {100 * near_symmetry(r['problem']):.1f} %"
                         + ("" if copy is None else
                            f"; {copy[1]:.2g} deg from the target turned {copy[0]:g} deg "
                            f"about its axis (the same mesh)"))
    return lines
