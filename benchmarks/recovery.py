"""Recovery of instance transforms: success rates, many instances, the bundled scenes.

    python -m benchmarks.recovery [--part suite,steps,many,bundled,coarse,shadow]
                                  [--iterations 300] [--spp 8] [--problems 50]
                                  [--mitsuba-problems 10] [--width 64]

Without ``--part``, the success-rate suite. Parts:

1. suite: seeded recovery problems (one object on a floor, recovered from 1, 2 and 4
   views), ours beside Mitsuba's ``direct_projective``: success rates, median iterations
   and seconds to success (:mod:`benchmarks.recovery_suite`).
2. steps: seconds per optimisation step with 10, 100 and 1 000 instances optimised (a
   field of objects on a floor, four views, one group key per part).
3. many: 100 instances of that field recovered jointly from four views, with the settings
   of ``MANY`` (``--iterations`` and ``--spp`` do not apply); writes
   ``docs/recover_many.png`` (per view: target, start, recovered).
4. bundled: ``scenes/recover_init.json`` -> ``scenes/recover_target.json`` (box,
   card, elliptic torus mesh; translations off by 15-20 % of their
   size, rotations by 18-22 degrees, scales by 20 %), 128x128: iterations, time
   per iteration, and the final errors against the targets (1 % of the size,
   1 degree, 1 %). Writes ``docs/recover_convergence.png`` and ``docs/recover.png``
   (target | before | after).
5. coarse: the box alone moved by 1.5 times its size, so that it no longer
   overlaps its target: plain descent against blurred-loss descent (blur from
   16 px down to 0 over the first half), same iterations and seeds.
6. shadow: the bundled scenes with the lamp moved off the camera
   (SHADOW_LIGHT), so that every instance's shadow on the ground is in view:
   recovery with the shadow-boundary term (sppi) and, for comparison, without it.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import drjit as dr
import drjit.opt
import numpy as np

import instancing
from benchmarks import recovery_suite
from benchmarks.machine import describe
from instancing.ad.recovery import (recover, recover_files, transform_errors,
                                     write_convergence_plot)
from instancing.core.backend import Array3f, Array4f, Float, Matrix4f
from instancing.core.transform import quaternion_product
from instancing.io.image import write_png

ROOT = Path(__file__).resolve().parents[1]
TARGET = ROOT / "scenes" / "recover_target.json"
INIT = ROOT / "scenes" / "recover_init.json"
#: Where the shadow part puts the lamp (the bundled scenes have it at the camera).
SHADOW_LIGHT = [3.0, -2.0, 5.0]


def shadowed_copies(folder: Path, light=SHADOW_LIGHT) -> tuple[Path, Path]:
    """The bundled target and init scenes with the lamp at ``light``, written to ``folder``
    (mesh paths made absolute): (target, init)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for source in (TARGET, INIT):
        scene = json.loads(source.read_text())
        for model in scene["models"].values():
            if "filename" in model:
                model["filename"] = str((source.parent / model["filename"]).resolve())
        scene["lights"][0]["position"] = list(light)
        paths.append(folder / source.name)
        paths[-1].write_text(json.dumps(scene, indent=1))
    return paths[0], paths[1]


def _summary(run, iterations: int, spp: int) -> dict:
    final = run.history.errors[-1]
    return {"iterations": iterations, "spp": spp,
            "seconds_per_iteration": float(np.median(run.history.seconds)),
            "initial": run.history.errors[0], "final": final,
            "met": {name: bool(e[0] < 0.01 and e[1] < 1.0 and e[2] < 0.01) for name, e in final.items()}}


def bundled(iterations: int, spp: int, out: Path) -> dict:
    run = recover_files(str(TARGET), str(INIT), str(out), iterations=iterations, spp=spp)
    print(run.table(), flush=True)
    docs = ROOT / "docs"
    write_convergence_plot(run.history, str(docs / "recover_convergence.png"))
    import mitsuba as mi
    strip = np.concatenate([np.array(mi.Bitmap(str(out / f"{n}.png"))) for n in ("target", "before", "after")], 1)
    mi.Bitmap(strip).write(str(docs / "recover.png"))
    return _summary(run, iterations, spp)


def shadow(iterations: int, spp: int, out: Path) -> dict:
    """The bundled recovery with shadows in view, with and without the shadow term."""
    target, init = shadowed_copies(out / "scenes")
    results = {"light": SHADOW_LIGHT}
    for label, sppi in (("with the shadow term", None), ("without (sppi 0)", 0)):
        run = recover_files(str(target), str(init), str(out / f"sppi_{sppi}"), iterations=iterations,
                            spp=spp, sppi=sppi)
        print(f"-- {label}\n{run.table()}", flush=True)
        results[label] = _summary(run, iterations, spp)
    return results


def coarse_to_fine(iterations: int, spp: int) -> dict:
    target_scene = instancing.load_scene(TARGET)
    target = instancing.render(target_scene, "direct", spp=256, seed=5)
    results = {}
    for blur_start in (0.0, 16.0):
        scene = instancing.load_scene(TARGET)
        params = instancing.traverse(scene)
        box = scene.instance_ids.index("box")
        size = 2.0 * np.linalg.svd(scene.to_world[box][:3, :3], compute_uv=False)[0]
        t = np.array(params["box.translation"]).ravel()
        params["box.translation"] = (t + 1.5 * size * np.array([0.8, 0.0, 0.6])).tolist()
        params.update()
        history = recover(params, target, ["box.translation"], iterations=iterations, spp=spp,
                          blur_start=blur_start, target_to_world=target_scene.to_world)
        start, end = history.errors[0]["box"][0], history.errors[-1]["box"][0]
        label = "blurred loss" if blur_start else "plain loss"
        print(f"{label:<13} translation error / size: {start:.3f} -> {end:.4f}", flush=True)
        results[label] = {"initial": start, "final": end}
    return results


# -- many instances: a field of objects on a floor, seen from four sides ----------------------

#: Grid spacing of the field and the objects' half sizes (before their random scales).
FIELD_SPACING = 1.0
FIELD_HALF_SIZE = (0.3, 0.22, 0.16)
#: Perturbation of the field's objects: translation (fraction of the size), degrees, scale.
FIELD_OFFSETS = (0.1, 10.0, 0.1)
#: Height of each object's lowest point above the floor.
FIELD_GAP = 0.02
#: The field's cameras' field of view, degrees.
FIELD_FOV = 45.0


def field_scenes(n: int, width: int, views: int = 4, seed: int = 0,
                 offsets=FIELD_OFFSETS) -> tuple[dict, dict]:
    """(target, init) scene dicts: n objects (boxes and ellipsoids, one batch each, so that
    each batch is one group of :func:`instancing.traverse`) on a square grid, each resting
    ``FIELD_GAP`` above a floor,
    ``views`` cameras around the field looking down at 50 degrees, each framing the whole
    field, two directional lights;
    the init scene's objects moved, turned and scaled by up to ``offsets``."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    cells = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n]
    centre = (side - 1) * FIELD_SPACING / 2
    xy = cells * FIELD_SPACING - centre + rng.uniform(-0.1, 0.1, (n, 2))
    half = np.array(FIELD_HALF_SIZE) * rng.uniform(0.85, 1.15, (n, 3))
    axes = rng.normal(size=(n, 3))
    angles = rng.uniform(0, 360, n)
    target = [_matrix([x, y, 0.0], a, angle, half_)
              for (x, y), half_, a, angle in zip(xy, half, axes, angles)]
    # Each object rests FIELD_GAP above the floor: its lowest point (a cube's lowest corner,
    # even indices; an ellipsoid's lowest point, odd ones) lifted to that height.
    for k, m in enumerate(target):
        depth = np.abs(m[2, :3]).sum() if k % 2 == 0 else np.linalg.norm(m[2, :3])
        m[2, 3] = depth + FIELD_GAP
    size = 2 * half.max(axis=1)
    init = []
    for m, s in zip(target, size):
        shift = rng.normal(size=3)
        shift *= offsets[0] * s * rng.uniform(0.5, 1.0) / np.linalg.norm(shift)
        turn = _matrix([0, 0, 0], rng.normal(size=3), offsets[1] * rng.uniform(0.5, 1.0), np.ones(3))
        grow = 1.0 + offsets[2] * rng.uniform(0.5, 1.0) * rng.choice([-1, 1], 3)
        moved = m.copy()
        moved[:3, :3] = turn[:3, :3] @ m[:3, :3] @ np.diag(grow)
        moved[:3, 3] += shift
        init.append(moved)
    extent = side * FIELD_SPACING / 2 + 0.5
    # Every view frames the whole field: its corners, up to the tallest object, inside the film.
    reach = (side - 1) * FIELD_SPACING / 2 + 1.2 * max(FIELD_HALF_SIZE)
    corners = np.array([[x, y, z] for x in (-reach, reach) for y in (-reach, reach)
                        for z in (0.0, 2.4 * max(FIELD_HALF_SIZE))])
    cameras = []
    for k, a in enumerate(np.radians(45 + 360 / views * np.arange(views))):
        direction = np.array([np.cos(a) * 0.64, np.sin(a) * 0.64, 0.77])
        origin = direction * _framing_distance(direction, corners, FIELD_FOV)
        cameras.append({"id": f"view{k}", "type": "perspective", "fov": FIELD_FOV, "width": width,
                        "height": width, "to_world": [{"look_at": {
                            "origin": origin.tolist(), "target": [0, 0, 0], "up": [0, 0, 1]}}]})

    def scene(matrices):
        boxes, eggs = np.array(matrices[0::2]), np.array(matrices[1::2])
        instances = [{"id": "floor", "model": "rectangle", "material": "floor",
                      "to_world": [{"scale": [extent + 1, extent + 1, 1]}]},
                     {"id": "box", "model": "cube", "material": "blue", "to_world": boxes}]
        if len(eggs):
            instances.append({"id": "egg", "model": "sphere", "material": "gold", "to_world": eggs})
        return {"materials": {"floor": {"type": "diffuse", "reflectance": [0.5, 0.5, 0.5]},
                              "blue": {"type": "diffuse", "reflectance": [0.2, 0.35, 0.8]},
                              "gold": {"type": "diffuse", "reflectance": [0.85, 0.6, 0.2]}},
                "instances": instances, "cameras": cameras,
                "lights": [{"type": "directional", "direction": [-0.3, -0.2, -1.0], "irradiance": 3.0},
                           {"type": "directional", "direction": [0.4, 0.5, -1.0], "irradiance": 1.0}]}

    return scene(target), scene(init)


def _framing_distance(direction: np.ndarray, points: np.ndarray, fov: float,
                      margin: float = 0.03) -> float:
    """The distance along ``direction`` (from the origin, looking at it, z up) from which a
    square film of field of view ``fov`` holds every point, ``margin`` of its half-width
    inside its edges (bisection: the points' angles shrink with the distance)."""
    forward = -direction / np.linalg.norm(direction)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    limit = np.tan(np.radians(fov / 2)) * (1 - margin)

    def fits(distance: float) -> bool:
        q = points + distance * forward
        depth = q @ forward
        return bool((depth > 0).all() and (np.abs(np.stack([q @ right, q @ up])) <= limit * depth).all())

    near, far = 0.0, 1.0
    while not fits(far):
        near, far = far, 2 * far
    for _ in range(50):
        near, far = (near, (near + far) / 2) if fits((near + far) / 2) else ((near + far) / 2, far)
    return far


def _matrix(t, axis, angle, scale) -> np.ndarray:
    return (instancing.translate(list(map(float, t)))
            @ instancing.rotate(list(map(float, axis)), float(angle))
            @ instancing.scale(list(map(float, scale)))).to_numpy()[0]


def field_keys(scene) -> list[str]:
    """The groups' keys of a field scene: every object's translation, rotation and scale."""
    groups = [name for name in ("box", "egg") if f"{name}[0]" in scene.instance_ids]
    return [f"{g}.{p}" for g in groups for p in ("translation", "rotation", "scale")]


def field_problem(n: int, width: int, views: int, spp: int) -> tuple:
    """A field of ``n`` objects: its target scene, the targets rendered at ``spp`` through
    every camera, and the perturbed scene with its parameters."""
    target_dict, init_dict = field_scenes(n, width, views)
    target_scene = instancing.load_scene(target_dict)
    targets = [instancing.render(target_scene, "direct", spp=spp, seed=7, camera=k)
               for k in range(views)]
    scene = instancing.load_scene(init_dict)
    return target_scene, targets, scene, instancing.traverse(scene)


def step_times(counts, width: int, views: int, spp: int, steps: int) -> list[dict]:
    """Seconds per optimisation step (update, render of every view, loss, backward, Adam)
    with every object of fields of ``counts`` objects optimised (translation, rotation,
    scale through one group per model): the first step and the median of later ones."""
    from instancing.ad.recovery import views_loss
    rows = []
    for n in counts:
        _, targets, scene, params = field_problem(n, width, views, 16)
        opt = drjit.opt.Adam(lr=0.01)
        for key in field_keys(scene):
            opt[key] = params[key]
        step = instancing.OptimisationStep(params, opt, views_loss, spp=spp,
                                           cameras=list(range(views)))
        seconds = []
        for it in range(steps):
            start = time.perf_counter()
            loss = step(it, targets, None)
            dr.eval(loss, opt.state)
            seconds.append(time.perf_counter() - start)
        row = {"optimised": n, "keys": len(list(opt.keys())), "first_s": seconds[0],
               "later_s": float(np.median(seconds[3:])), "recordings": step.recordings}
        print(f"{n:>6} instances optimised ({row['keys']} keys): first step {row['first_s']:.1f} s, "
              f"later steps {row['later_s']:.3f} s (median of {steps - 3}), "
              f"{row['recordings']} recording(s)", flush=True)
        rows.append(row)
    return rows


#: The many part: field size, film, the targets' samples per pixel, and the recovery's
#: settings (:func:`instancing.ad.recovery.recover`). Each object's bounding box is about 17
#: pixels across in every view (median, :func:`object_pixels`), so its rotation is read from
#: sub-pixel silhouette shifts and the image term's noise limits it. On a 16-object field
#: with the objects at the size of a 192-pixel film of the old framing: 4 spp for all three terms
#: met 12 of 16 (the eggs' rotations up to 2.3 degrees); 16 or 32 spp for the image with 4
#: for the silhouette and shadow terms, 1.2x / 1.3x the time, met 15 and 16 of 16 (median
#: rotation error 0.25 -> 0.12 / 0.18 degrees); a final learning rate of 0.1 instead of 0.3
#: of the start and the mean of the last half of the iterates narrowed it further. Pixels
#: decide the rest: on 25 objects at 96 and at 128 pixels (192 and 256 for 100 objects), all
#: 25 met, and the largest errors fell 0.0026 -> 0.0007 of the size, 0.97 -> 0.25 degrees and
#: 0.8 % -> 0.3 % scale at 1.7x the time per iteration. Views that frame the whole field
#: (none cutting an object) met the last corner objects: 98 -> 100 of 100.
MANY = {"instances": 100, "views": 4, "width": 336, "target_spp": 1024, "iterations": 300,
        "spp": 32, "sppp": 4, "sppi": 4, "lr_final_ratio": 0.1, "average_fraction": 0.5}


def many(instances: int, views: int, width: int, target_spp: int, **settings) -> dict:
    """``instances`` objects recovered jointly from ``views`` views (targets rendered at
    ``target_spp``, ``settings`` passed to ``recover``): final errors against the targets;
    writes ``docs/recover_many.png`` (per view: target, start, recovered)."""
    n, iterations, spp = instances, settings["iterations"], settings["spp"]
    target_scene, targets, scene, params = field_problem(n, width, views, target_spp)
    ids = [i for i in scene.instance_ids if i != "floor"]
    before = [instancing.render(scene, "direct", spp=128, seed=7, camera=k) for k in range(views)]
    history = recover(params, targets, field_keys(scene), **settings,
                      target_to_world={i: target_scene.to_world[scene.instance_ids.index(i)]
                                       for i in ids})
    after = [instancing.render(scene, "direct", spp=128, seed=7, camera=k) for k in range(views)]
    # One row per view: target | start | recovered.
    rows = [np.concatenate([np.array(image) for image in row], 1)
            for row in zip(targets, before, after)]
    write_png(ROOT / "docs" / "recover_many.png", np.concatenate(rows, 0))
    final = np.array([history.errors[-1][i] for i in ids])
    start = np.array([history.errors[0][i] for i in ids])
    met = (final[:, 0] < 0.01) & (final[:, 1] < 1.0) & (final[:, 2] < 0.01)
    print(f"{n} instances, {views} views {width}x{width}, {iterations} iterations at {spp} spp: "
          f"{np.median(history.seconds):.2f} s per iteration; within 1 % / 1 deg / 1 %: "
          f"{met.sum()} of {n}")
    for label, e in (("start", start), ("final", final)):
        print(f"  {label}: translation/size median {np.median(e[:, 0]):.4f} max {e[:, 0].max():.4f}; "
              f"rotation deg median {np.median(e[:, 1]):.3f} max {e[:, 1].max():.3f}; "
              f"scale median {np.median(e[:, 2]):.4f} max {e[:, 2].max():.4f}", flush=True)
    # The misses, with how near each target is to a body of revolution (the relative gap of
    # its two closest axis lengths: an ellipsoid turned about a near-axis barely changes).
    failed = []
    for i, e in zip(np.array(ids)[~met].tolist(), final[~met]):
        axes = np.sort(np.linalg.svd(target_scene.to_world[scene.instance_ids.index(i)][:3, :3],
                                     compute_uv=False))
        gap = float(np.min(np.diff(axes) / axes[1:]))
        # The iterate's rotation error every tenth of the run: still falling, or settled.
        trace = [history.errors[k][i][1] for k in range(0, iterations, max(1, iterations // 10))]
        failed.append({"id": i, "errors": e.tolist(), "axis_gap": gap, "rotation_trace": trace})
        print(f"  missed {i}: {e[0]:.4f} of the size, {e[1]:.3f} deg, scale {e[2]:.4f}; "
              f"closest axes differ by {100 * gap:.1f} %; rotation of the iterates every "
              f"{max(1, iterations // 10)} iterations: " + " ".join(f"{r:.2f}" for r in trace),
              flush=True)
    kinds = {}
    for kind in ("box", "egg"):
        of_kind = np.array([i.startswith(kind + "[") for i in ids])
        if of_kind.any():
            kinds[kind] = {"met": int(met[of_kind].sum()), "count": int(of_kind.sum()),
                           "final_median": np.median(final[of_kind], axis=0).tolist()}
            print(f"  {kind}: {kinds[kind]['met']} of {kinds[kind]['count']} within; median "
                  + " / ".join(f"{v:.4g}" for v in kinds[kind]["final_median"]), flush=True)
    pixels, cut = object_pixels(target_scene, ids, views)
    print(f"  objects in the views: {np.median(pixels):.1f} pixels across (median), {cut} of "
          f"{len(pixels)} object views cut by a film edge", flush=True)
    return {"instances": n, "views": views, "width": width, "target_spp": target_spp, **settings,
            "object_pixels": float(np.median(pixels)), "object_views_cut": cut,
            "kinds": kinds, "failed": failed,
            "seconds_per_iteration": float(np.median(history.seconds)), "met": int(met.sum()),
            "final_max": final.max(axis=0).tolist(), "final_median": np.median(final, axis=0).tolist(),
            "start_max": start.max(axis=0).tolist()}


def object_pixels(scene, ids: list[str], views: int) -> tuple[list[float], int]:
    """Per object and view, the larger side in pixels of the film box that holds the object's
    bounding box corners; and how many of those film boxes cross a film edge."""
    corners = np.array([[x, y, z, 1.0] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    world = np.concatenate([corners @ np.asarray(scene.to_world[scene.instance_ids.index(i)]).T
                            for i in ids])[:, :3]
    sides, cut = [], 0
    for k in range(views):
        camera = scene.cameras[k]
        x, y, _ = camera.project(Array3f(*[Float(world[:, j].astype(np.float32)) for j in range(3)]))
        boxes = np.stack([np.array(x), np.array(y)], -1).reshape(len(ids), 8, 2)
        low, high = boxes.min(axis=1), boxes.max(axis=1)
        sides += (high - low).max(axis=1).tolist()
        cut += int(((low < 0) | (high > [camera.width, camera.height])).any(axis=1).sum())
    return sides, cut


# -- rotation parameterisations: quaternion against the alternatives, far from the target ------

#: Start angles (degrees from the target, about random axes) and iterations of the study.
ROTATION_ANGLES = (30.0, 90.0, 150.0, 175.0)
ROTATION_AXES = 2


def _rotation_vector(w):
    """Rotation by the vector w (axis times angle, radians) as a quaternion (x, y, z, w)."""
    angle = dr.norm(w)
    half = 0.5 * angle
    # sin(a/2)/a, continued at a = 0.
    k = dr.select(angle > 1e-6, dr.sin(half) / dr.maximum(angle, 1e-6), 0.5)
    return Array4f(w.x * k, w.y * k, w.z * k, dr.cos(half))


def _six_d(a, b, start: np.ndarray) -> Matrix4f:
    """Zhou et al. 2019: two 3-vectors, Gram-Schmidt, the rotation with those columns,
    applied to the start matrix (in world space): the whole matrix, differentiable."""
    x = dr.normalize(a)
    y = dr.normalize(b - dr.dot(x, b) * x)
    z = dr.cross(x, y)
    r = [[x.x, y.x, z.x], [x.y, y.y, z.y], [x.z, y.z, z.z]]
    rows = [Array4f(*[sum(r[i][k] * float(start[k, j]) for k in range(3)) for j in range(3)],
                    float(start[i, 3])) for i in range(3)]
    return Matrix4f(*rows, Array4f(0.0, 0.0, 0.0, 1.0))


#: Three boxes (centre, half sizes) that make a model with no rotational symmetry.
ASYMMETRIC_PARTS = (((0.0, 0.0, 0.0), (0.8, 0.5, 0.2)), ((0.6, 0.3, 0.5), (0.15, 0.15, 0.35)),
                    ((-0.5, -0.4, 0.35), (0.25, 0.08, 0.18)))


def asymmetric_mesh(path: Path) -> Path:
    """Write an OBJ of :data:`ASYMMETRIC_PARTS` (a slab with a post and a fin): every turn of
    it changes its image, so rotation errors need no symmetry taken out."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    lines = []
    for k, (centre, half) in enumerate(ASYMMETRIC_PARTS):
        lines += [f"v {' '.join(f'{c:g}' for c in np.array(centre) + np.array(half) * v)}"
                  for v in corners]
        lines += [f"f {' '.join(str(8 * k + i + 1) for i in quad)}" for quad in quads]
    path.write_text("\n".join(lines) + "\n")
    return path


def rotation_study(iterations: int, spp: int) -> dict:
    """An asymmetric model (:func:`asymmetric_mesh`) seen from two views, started far off in
    rotation only: the rotation recovered through a quaternion (instancing's parameter), a
    rotation vector and the 6D form, each applied on top of the start; final angle to the
    target."""
    from benchmarks.recovery_suite import cameras
    from instancing.ad.recovery import views_loss
    rng = np.random.default_rng(31)
    target_m = _matrix([0.0, 0.0, 0.75], [0.3, -0.5, 0.8], 40.0, [0.7, 0.7, 0.7])
    mesh = asymmetric_mesh(Path(tempfile.mkdtemp()) / "asymmetric.obj")

    def scene(m):
        return instancing.load_scene({
            "models": {"asymmetric": {"type": "obj", "filename": str(mesh), "face_normals": True}},
            "materials": {"floor": {"type": "diffuse", "reflectance": [0.5, 0.5, 0.5]},
                          "paint": {"type": "diffuse", "reflectance": [0.75, 0.45, 0.2]}},
            "instances": [{"id": "floor", "model": "rectangle", "material": "floor",
                           "to_world": [{"scale": [4, 4, 1]}]},
                          {"id": "box", "model": "asymmetric", "material": "paint",
                           "to_world": [{"matrix": m.tolist()}]}],
            "cameras": cameras(2, 64),
            "lights": [{"type": "point", "position": [2.5, -1.0, 4.5], "intensity": [25.0] * 3}]})

    target_scene = scene(target_m)
    targets = [instancing.render(target_scene, "direct", spp=256, seed=3, camera=k) for k in (0, 1)]
    # Learning rates of about 0.03 radians per step for each form (a quaternion component
    # moves by half the angle).
    rate = {"quaternion": 0.015, "rotation vector": 0.03, "6D": 0.03}
    rows = []
    for angle in ROTATION_ANGLES:
        for _ in range(ROTATION_AXES):
            axis = rng.normal(size=3)
            start_m = target_m.copy()
            start_m[:3, :3] = _matrix([0, 0, 0], axis, angle, [1, 1, 1])[:3, :3] @ target_m[:3, :3]
            for form in ("quaternion", "rotation vector", "6D"):
                s = scene(start_m)
                params = instancing.traverse(s)
                q_start = Array4f(params["box.rotation"])
                opt = drjit.opt.Adam(lr=0.03)
                if form == "quaternion":
                    opt["q"] = Array4f(q_start)
                elif form == "rotation vector":
                    opt["w"] = Array3f(0.0)
                else:
                    opt["a"], opt["b"] = Array3f(1, 0, 0), Array3f(0, 1, 0)
                def install():
                    # The rotation from the optimised values, pushed into the scene.
                    if form == "6D":
                        params["box.to_world"] = _six_d(opt["a"], opt["b"], start_m)
                    elif form == "rotation vector":
                        params["box.rotation"] = Array4f(*quaternion_product(
                            _rotation_vector(opt["w"]), q_start))
                    else:
                        params["box.rotation"] = opt["q"]
                    params.update()

                for it in range(iterations):
                    opt.set_learning_rate({k: rate[form] * 0.3 ** (it / (iterations - 1))
                                           for k in opt.keys()})
                    install()
                    images = [instancing.render(s, "direct", spp=spp, seed=it * 2 + k, camera=k)
                              for k in (0, 1)]
                    dr.backward(views_loss(images, targets))
                    opt.step()
                for key in opt.keys():
                    opt[key] = type(opt[key])(dr.detach(opt[key]))
                install()
                error = transform_errors(s.to_world[1], target_m)[1]
                rows.append({"angle": angle, "form": form, "error": error})
                print(f"start {angle:>5.0f} deg  {form:<16} -> {error:7.3f} deg", flush=True)
    summary = {}
    for form in ("quaternion", "rotation vector", "6D"):
        got = [r for r in rows if r["form"] == form]
        summary[form] = {"solved": sum(r["error"] < 1.0 for r in got), "runs": len(got),
                         "median_error": float(np.median([r["error"] for r in got]))}
        print(f"{form:<16} within 1 degree: {summary[form]['solved']} of {len(got)}, "
              f"median final error {summary[form]['median_error']:.3f} deg")
    return {"iterations": iterations, "spp": spp, "rows": rows, "summary": summary}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--part", default="suite")
    parser.add_argument("--problems", type=int, default=50, help="suite: number of problems")
    parser.add_argument("--width", type=int, default=64, help="suite: film width and height")
    parser.add_argument("--mitsuba-problems", type=int, default=10,
                        help="suite: problems Mitsuba also runs (the first ones)")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--out", default=str(ROOT / "recover_out"))
    parser.add_argument("--resume", action="store_true",
                        help="suite: go on with the saved run of the same settings")
    args = parser.parse_args(argv)
    path = ROOT / "benchmarks" / "results_recovery.json"
    # Parts run separately update their entry and keep the others.
    results = json.loads(path.read_text()) if path.is_file() else {}
    parts = args.part.split(",")
    unknown = set(parts) - {"suite", "steps", "many", "rotation", "bundled", "coarse", "shadow"}
    if unknown:
        parser.error(f"unknown parts {sorted(unknown)}")
    if "suite" in parts:
        print(f"== success rates: {args.problems} problems, 1, 2 and 4 views ==")
        def save(partial: dict) -> None:
            path.write_text(json.dumps({**results, "suite": partial}, indent=1))

        settings = recovery_suite.settings(args.problems, args.iterations, args.spp, args.width,
                                           args.mitsuba_problems)
        saved = results.get("suite", {})
        if args.resume and {k: saved.get(k) for k in settings} != settings:
            parser.error(f"--resume: the saved suite ran with "
                         f"{ {k: saved.get(k) for k in settings} }, not {settings}")
        results["suite"] = recovery_suite.run(args.problems, args.iterations, args.spp, args.width,
                                              args.mitsuba_problems, save,
                                              saved["rows"] if args.resume else None)
    if "bundled" in parts:
        print("== bundled recovery scenes, 128x128 ==")
        results["bundled"] = bundled(args.iterations, args.spp, Path(args.out))
    if "coarse" in parts:
        print("== coarse to fine: the box moved by 1.5 times its size ==")
        results["coarse"] = coarse_to_fine(min(args.iterations, 150), args.spp)
    if "shadow" in parts:
        print(f"== the bundled scenes with the lamp at {SHADOW_LIGHT}: shadows in view ==")
        results["shadow"] = shadow(args.iterations, args.spp, Path(args.out) / "shadow")
    if "steps" in parts:
        print("== seconds per optimisation step against the optimised instances "
              "(4 views 128x128, 2 spp) ==")
        results["steps"] = step_times((10, 100, 1000), 128, 4, 2, 8)
    if "rotation" in parts:
        print("== rotation parameterisations: an asymmetric model started 30 to 175 degrees off ==")
        results["rotation"] = rotation_study(min(args.iterations, 200), args.spp)
    if "many" in parts:
        print(f"== {MANY['instances']} instances recovered jointly from {MANY['views']} views ==")
        results["many"] = many(**MANY)
    results["machine"] = describe()
    path.write_text(json.dumps(results, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
