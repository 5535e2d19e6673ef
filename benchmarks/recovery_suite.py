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
axis) of the target. Printed per view count: the success rate, and for the successes the
median iterations and seconds until the iterate first met the tolerances.

Beside ours, on the first problems (``--mitsuba-problems``, default 10: two of each kind;
Mitsuba's steps cost about three times ours here), the same recovery with its
``direct_projective`` integrator: the object as one plain mesh (the same shape tessellated:
a UV sphere, an open tube, Mitsuba's cube, two triangles, the torus) whose vertices are
transformed by the parameters in Dr.Jit each step, the same Adam schedule, iterate average,
learning rates, spp and images.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

import instancing
from instancing.ad.recovery import recover, transform_errors

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
VIEW_COUNTS = (1, 2, 4)


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
    targets = [instancing.render(target_scene, "direct", spp=256, seed=11, camera=k)
               for k in range(views)]
    params = instancing.traverse(instancing.load_scene(scene_dict(p, p["start"], views, width)))
    history = recover(params, targets, [f"object.{x}" for x in ("translation", "rotation", "scale")],
                      iterations=iterations, spp=spp,
                      target_to_world={"object": target_scene.to_world[1]})
    final = history.errors[-1]["object"]
    until, seconds = _until_met(history)
    return {"errors": list(final), "success": _met(final), "iterations": until, "seconds": seconds,
            "seconds_per_iteration": float(np.median(history.seconds))}


def run(problems: int, iterations: int, spp: int, width: int, mitsuba: int,
        save=None) -> dict:
    """Every problem at every view count (ours, and Mitsuba's on the first ``mitsuba``
    problems), and the table; ``save`` is called with the results so far after each row."""
    rows = []

    def results() -> dict:
        return {"problems": problems, "iterations": iterations, "spp": spp, "width": width,
                "mitsuba_problems": min(mitsuba, problems), "rows": rows, "table": summary(rows)}

    for index in range(problems):
        p = problem(index)
        for views in VIEW_COUNTS:
            start = time.perf_counter()
            row = {"problem": index, "kind": p["kind"], "light": p["light"], "views": views,
                   "start": list(transform_errors(p["start"], p["target"])),
                   "ours": ours(p, views, width, iterations, spp)}
            if index < mitsuba:
                from benchmarks.recovery_mitsuba import recover_mitsuba
                row["mitsuba"] = recover_mitsuba(p, views, width, iterations, spp)
            rows.append(row)
            cells = [f"{name}: {'ok ' if r['success'] else 'no '}" +
                     "/".join(f"{e:.3g}" for e in r["errors"])
                     for name, r in (("ours", row["ours"]), ("mitsuba", row.get("mitsuba")))
                     if r is not None]
            print(f"problem {index:>2} {p['kind']:<17} light {p['light']:<16} {views} view(s): "
                  f"{'; '.join(cells)} ({time.perf_counter() - start:.0f} s)", flush=True)
            if save is not None:
                save(results())
    print("\n".join(summary(rows) + failures(rows)))
    return results()


def summary(rows: list[dict]) -> list[str]:
    """Success rate, median iterations and seconds to success, per view count and renderer;
    and per kind."""
    lines = [f"{'renderer':<9} {'views':>5} {'success':>9} {'median its':>11} {'median s':>9}"]
    for name in ("ours", "mitsuba"):
        for views in VIEW_COUNTS:
            got = [r[name] for r in rows if r["views"] == views and name in r]
            if not got:
                continue
            wins = [g for g in got if g["success"]]
            its = [g["iterations"] for g in wins if g["iterations"] is not None]
            secs = [g["seconds"] for g in wins if g["seconds"] is not None]
            lines.append(f"{name:<9} {views:>5} {len(wins):>4}/{len(got):<4} "
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


def failures(rows: list[dict]) -> list[str]:
    """The problems ours failed from 2 or more views: kind, final errors and how near the
    model is to a rotational symmetry (:func:`near_symmetry`)."""
    lines = []
    for r in rows:
        if r["views"] >= 2 and not r["ours"]["success"]:
            e = r["ours"]["errors"]
            lines.append(f"failed: problem {r['problem']:>2} {r['kind']:<17} {r['views']} views: "
                         f"{e[0]:.2g} of the size, {e[1]:.3g} deg, scale {e[2]:.2g}; "
                         f"closest axes differ by {100 * near_symmetry(r['problem']):.1f} %")
    return lines
