"""Differentiable rendering: gradient validation, shadow-boundary bias, cost per iteration.

    python -m benchmarks.gradients [--part validation,shadow,shadow_path,lights,penumbra,
                                           interreflection,reflected,contact,touching,delta,
                                           depth,cost] [--size 32]

1. validation: gradient images of every model kind with respect to translation,
   rotation and scale against central finite differences (the full version of
   tests/test_gradients.py: all 18 pairs), error = mean over the support of
   |a - r| / max(|r|, 0.2 max|r|).
2. shadow: the same with the lamp moved off the camera, so that the object's
   shadow on the wall is in view, with the shadow-boundary term (sppi) and, for
   comparison, without it (sppi = 0: the bias that term removes); shadow_path: the same
   in `path` (max_depth 3), where the wall also shows the shadow's edges by a bounce
   (the hard shadows seen from the path's vertices).
   These parts also print the finite differences' own seed-to-seed spread (two
   central differences with different seeds): the target is an error of at most
   1.5x that spread and at most 5 %.
3. lights: moving lamps against central differences: a point light's position
   and a directional light's direction (shadows in view), and an area-emitting
   rectangle and sphere (translation, rotation; no occluder between lamp and wall).
4. penumbra: soft shadows in view: every model kind and transform parameter under a
   rectangle area lamp off the camera (`direct` and `path`, max_depth 3), each kind's
   translation under a sphere lamp and under the environment, and the lamps' own
   translation and rotation with an ellipsoid between lamp and wall; with the secondary
   boundary term (sppi) and without it.
5. interreflection: each closed model kind seen only through diffuse interreflection
   (out of view, lit by a directional light), translated, `path` (max_depth 3); with and
   without the term.
6. reflected: a cube's and an ellipsoid's shadow on a floor seen only through a screen
   (path, max_depth 3 and 5), the soft shadow of a rectangle lamp and the hard shadow of a
   point light (and a torus mesh's), with and without the secondary term.
7. contact: each model kind sinking into a floor, a cube and an ellipsoid sinking into a
   box, mesh tiles and a faceted mesh sphere, and a cube, an ellipsoid and an elliptic
   cylinder sinking into a big sphere and a big cylinder (contact curves; where two curved
   surfaces meet, the curve where their quadrics meet), translation and rotation, against
   central differences with their spread, and without the contact term.
   touching: light bounced between an instance and the floor it stands in (`path`,
   max_depth 3; an upright panel and each model kind, moved and turned), against central
   differences, and without path replay's slide of near vertices.
   delta: moving mirrors and glass, a glossy bounce, and silhouettes seen in flat mirrors.
8. depth: peak memory and time of one reverse-mode `path` gradient step (the Cornell
   box, 128x128, 4 spp; render, L2 loss, dr.backward) at max_depth 3, 8 and 16, each in
   its own process: the evaluated bounce loop keeps every bounce's state for the
   backward pass.
9. cost: time (median of 3) and peak memory of one forward + backward iteration
   (update, render, L2 loss, dr.backward, Adam step; ours as one recorded
   instancing.OptimisationStep) at 128x128 and 256x256 with 10, 100 and
   1 000 sphere instances, every instance's translation differentiated, next to
   Mitsuba's direct_projective on the same spheres as plain shapes (Mitsuba
   cannot differentiate instances), each configuration in its own process.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MESH = str(ROOT / "scenes" / "meshes" / "torus.obj")
STEP = 0.004
FD_SPP = 16384
#: Seconds one cost process may take (tracing, 3 warm-up and 3 timed iterations).
WORKER_TIMEOUT = 600
#: Processes per renderer and cost configuration, run in alternation.
COST_ROUNDS = 3
#: The reflected-shadow cases: image size, and per light our secondary samples and the
#: finite differences' samples per pixel (both need many: see
#: gradient_check.reflected_penumbra_case; the point light's differences take a smaller step).
REFLECTED_SIZE = 8
REFLECTED_SAMPLES = {"area": (1048576, 262144), "point": (262144, 1048576)}
#: (model, light, max_depth) of the reflected cases.
REFLECTED_CASES = [("cube", "area", 3), ("sphere", "area", 3), ("cube", "area", 5),
                   ("cube", "point", 3), ("sphere", "point", 3), ("mesh", "point", 3),
                   ("cube", "point", 5)]


def validation(size: int, light_offset: float = 0.0, integrator: str = "direct") -> list[list]:
    """Rows [model, parameter, error, finite differences' spread, error without the shadow
    term (None with the light at the camera)]; ``integrator`` 'path' renders max_depth 3."""
    import instancing
    from instancing.validation.gradient_check import (VALIDATION_TRANSFORMS, finite_difference_image, gradient_image,
                                      relative_error, validation_scene, validation_tangent)
    args = {"integrator": integrator, "max_depth": 3 if integrator == "path" else None}
    rows = []
    for model in VALIDATION_TRANSFORMS:
        for name in ("translation", "rotation", "scale"):
            description = validation_scene(model, size, MESH)
            description["lights"][0]["position"] = [light_offset, light_offset, -5]
            scene = instancing.load_scene(description)
            params = instancing.traverse(scene)
            tangent = validation_tangent(params, name)
            spp = 2048 if model in ("sphere", "cylinder") else 256
            if model == "mesh" and integrator == "path":
                # Path replay's interior term on the torus is the noisiest of these (paths
                # bouncing on it twice).
                spp = 8192
            start = time.perf_counter()
            ours = gradient_image(params, f"obj.{name}", tangent, spp=spp, sppp=1024, sppi=1024,
                                  seed=1, **args)
            seconds = time.perf_counter() - start
            refs = [finite_difference_image(params, f"obj.{name}", tangent, STEP, spp=FD_SPP,
                                            seed=seed, **args)
                    for seed in (2, 3)]
            error, spread = relative_error(ours, refs[0]), relative_error(refs[1], refs[0])
            without = None
            if light_offset:
                without = relative_error(gradient_image(
                    params, f"obj.{name}", tangent, spp=spp, sppp=1024, sppi=0, seed=1, **args),
                    refs[0])
            rows.append([model, name, error, spread, without])
            print(f"{model:<10} {name:<12} error {error:6.3f}  FD spread {spread:6.3f}"
                  + ("" if without is None else f"  without the shadow term {without:6.3f}")
                  + f"  ({spp} spp, {seconds:.1f} s)", flush=True)
    return rows


def lights(size: int) -> list[list]:
    """Rows [case, error, finite differences' spread] for moving lamps."""
    import instancing
    from instancing.validation.gradient_check import (SHADOW_LIGHT, finite_difference_image,
                                                      gradient_image, lamp_scene, relative_error,
                                                      rotation_tangent, validation_scene)
    cases = []
    for kind, key, tangent, step in (
            ("point", "lamp.position", [1.0, 0.3, 0.2], STEP),
            # A short tangent (0.1): the doubled step keeps the difference's noise level.
            ("directional", "lamp.direction", [0.0, 0.1, 0.0], 2 * STEP)):
        description = validation_scene("cube", size, MESH)
        description["lights"] = [
            {"type": "point", "id": "lamp", "position": SHADOW_LIGHT, "intensity": [30, 30, 30]}
            if kind == "point" else
            {"type": "directional", "id": "lamp", "direction": [-0.3, -0.3, 1], "irradiance": [3, 3, 3]}]
        cases.append((f"{kind} light {key.split('.')[1]}", description, key, np.array(tangent), step,
                      "direct"))
    for kind in ("rectangle", "sphere"):
        for name in ("translation", "rotation"):
            cases.append((f"area {kind} lamp {name}", lamp_scene(kind, size), f"lamp.{name}", name,
                          STEP, "direct"))
    rows = []
    for label, description, key, tangent, step, integrator in cases:
        params = instancing.traverse(instancing.load_scene(description))
        if isinstance(tangent, str):
            tangent = (np.array([1.0, 0.5, 0.3]) if tangent == "translation"
                       else rotation_tangent(np.array(params[key]).ravel(), [0.0, 1.0, 0.3]))
        ours = gradient_image(params, key, tangent, integrator=integrator, spp=2048, sppp=512,
                              sppi=2048, seed=1)
        refs = [finite_difference_image(params, key, tangent, step, integrator=integrator,
                                        spp=FD_SPP, seed=seed) for seed in (2, 3)]
        error, spread = relative_error(ours, refs[0]), relative_error(refs[1], refs[0])
        rows.append([label, error, spread])
        print(f"{label:<32} error {error:6.4f}  FD spread {spread:6.4f}", flush=True)
    return rows


#: The contact part's cases per receiver: what sinks into it.
CONTACT_MODELS = {"box": ("cube", "sphere"), "tiles": ("cube", "sphere"), "boulder": ("cube", "sphere"),
                  "dome": ("cube", "sphere", "cylinder"), "drum": ("cube", "sphere", "cylinder")}


def contact(size: int, receivers: tuple = ("floor", "box", "tiles", "boulder", "dome", "drum")
            ) -> list[list]:
    """Rows [model, parameter, error, finite differences' spread, error without the contact
    term] for instances sinking into a floor (every model kind), and the models of
    CONTACT_MODELS sinking into the other receivers (a box face, mesh tiles, a faceted mesh
    sphere; a big sphere and a big cylinder, where a sphere or a cylinder meets them along
    the curve where two quadrics meet)."""
    import instancing
    import instancing.rendering.film as film
    from instancing.validation.gradient_check import (CONTACT_TRANSFORMS, contact_scene,
                                                      finite_difference_image, gradient_image,
                                                      relative_error, rotation_tangent)
    rows = []
    cases = [(m, p, r) for r in receivers
             for m in (CONTACT_TRANSFORMS if r == "floor" else CONTACT_MODELS[r])
             for p in ("translation", "rotation")]
    for model, name, receiver in cases:
        label = model if receiver == "floor" else f"{model} in {receiver}"
        params = instancing.traverse(instancing.load_scene(contact_scene(model, size, MESH, receiver)))
        key = f"obj.{name}"
        tangent = (np.array([0.3, 0.2, 1.0]) if name == "translation"
                   else rotation_tangent(np.array(params[key]).ravel(), [1.0, 0.0, 0.0]))
        ours = gradient_image(params, key, tangent, integrator="direct", spp=4096, sppp=4096,
                              seed=1)
        samplers = film.contact_samplers
        film.contact_samplers = lambda scene, cameras: [None] * len(cameras)
        try:
            without = gradient_image(params, key, tangent, integrator="direct", spp=4096,
                                     sppp=4096, seed=1)
        finally:
            film.contact_samplers = samplers
        refs = [finite_difference_image(params, key, tangent, STEP, integrator="direct",
                                        spp=8192, seed=seed) for seed in (2, 3)]
        row = [label, name, relative_error(ours, refs[0]), relative_error(refs[1], refs[0]),
               relative_error(without, refs[0])]
        rows.append(row)
        print(f"{label:<18} {name:<12} error {row[2]:6.3f}  FD spread {row[3]:6.3f}  "
              f"without the contact term {row[4]:6.3f}", flush=True)
    return rows


def touching(size: int) -> list[list]:
    """Rows [model, parameter, error, our spread (two seeds), finite differences' spread,
    error without the slide] for light bounced between an instance and the floor it stands
    in (``path``, max_depth 3): an upright panel and each model kind, moved and turned."""
    import instancing
    import instancing.rendering.integrators.path as path
    from instancing.validation.gradient_check import (bounce_contact_scene, bounce_contact_tangent,
                                                      finite_difference_image, gradient_image,
                                                      relative_error)
    rows = []
    for model in ("rectangle", "cube", "sphere", "cylinder", "mesh"):
        for name in ("translation", "rotation"):
            params = instancing.traverse(instancing.load_scene(bounce_contact_scene(model, size, MESH)))
            key, tangent = f"obj.{name}", bounce_contact_tangent(params, model, name)
            ours = [gradient_image(params, key, tangent, spp=4096, seed=seed) for seed in (1, 2)]
            reach = path.SLIDE_REACH
            path.SLIDE_REACH = 0.0
            try:
                without = gradient_image(params, key, tangent, spp=4096, seed=1)
            finally:
                path.SLIDE_REACH = reach
            refs = [finite_difference_image(params, key, tangent, STEP, spp=16384, seed=seed)
                    for seed in (2, 3)]
            label = "panel" if model == "rectangle" else model
            row = [label, name, relative_error(ours[0], refs[0]), relative_error(ours[1], ours[0]),
                   relative_error(refs[1], refs[0]), relative_error(without, refs[0])]
            rows.append(row)
            print(f"{label:<10} {name:<12} error {row[2]:6.4f}  our spread {row[3]:6.4f}  FD spread "
                  f"{row[4]:6.4f}  without the slide {row[5]:6.4f}", flush=True)
    return rows


#: Delta-lobe cases (label, model, material, parameter, max_depth): what a moving mirror or
#: glass shows under a smooth environment, through path replay's chains of delta lobes.
DELTA_CASES = [
    ("mirror cube", "cube", {"type": "conductor", "material": "Au"}, "rotation", 3),
    ("mirror ellipsoid", "sphere", {"type": "conductor", "material": "Au"}, "translation", 3),
    ("glass pane", "rectangle", {"type": "dielectric"}, "rotation", 3),
    ("glass cube", "cube", {"type": "dielectric"}, "rotation", 4),
    ("glass ellipsoid", "sphere", {"type": "dielectric"}, "translation", 4)]
#: Our samples per pixel, and the central differences', of the delta-lobe cases (16x16).
DELTA_SPP, DELTA_FD_SPP, DELTA_SIZE = 16384, 65536, 16


def delta() -> list[list]:
    """Rows [case, parameter, max_depth, error, our own spread (two seeds), finite
    differences' spread] for the DELTA_CASES, the glossy bounce (a rough metal floor
    reflecting a spot onto a moving panel, whose BSDF must see the previous vertex move), and
    an ellipsoid moving over a mirror and a smooth plastic floor (silhouettes seen in flat
    mirrors)."""
    import instancing
    from instancing.validation.gradient_check import (delta_lobe_scene, finite_difference_image,
                                                      glossy_bounce_scene, gradient_image,
                                                      mirror_floor_scene, parameter, relative_error,
                                                      smooth_environment_map)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        environment = smooth_environment_map(Path(folder) / "environment.exr")
        cases = [(label, delta_lobe_scene(model, material, DELTA_SIZE, environment), name, depth, None)
                 for label, model, material, name, depth in DELTA_CASES]
        # (The panel moves towards the camera.)
        cases.append(("glossy bounce", glossy_bounce_scene(DELTA_SIZE), "translation", 3, [0.0, 0.0, 1.0]))
        floors = (("mirror", {"type": "conductor", "material": "Ag"}),
                  ("plastic", {"type": "plastic", "diffuse_reflectance": [0.2, 0.2, 0.25]}))
        cases += [(f"ellipsoid over a {label} floor", mirror_floor_scene(DELTA_SIZE, floor), "translation",
                   3, None) for label, floor in floors]
        for label, description, name, depth, direction in cases:
            params = instancing.traverse(instancing.load_scene(description))
            key, tangent = parameter(params, name)
            tangent = tangent if direction is None else np.array(direction)
            args = {"integrator": "path", "max_depth": depth}
            ours = [gradient_image(params, key, tangent, spp=DELTA_SPP, sppp=4096, sppi=256, seed=seed,
                                   **args) for seed in (1, 4)]
            refs = [finite_difference_image(params, key, tangent, STEP, spp=DELTA_FD_SPP, seed=seed, **args)
                    for seed in (2, 3)]
            row = [label, name, depth, relative_error(ours[0], refs[0]), relative_error(ours[1], ours[0]),
                   relative_error(refs[1], refs[0])]
            rows.append(row)
            print(f"{label:<18} {name:<12} max_depth {depth}  error {row[3]:6.3f}  our spread {row[4]:6.3f}  "
                  f"FD spread {row[5]:6.3f}", flush=True)
    return rows


def penumbra(size: int) -> list[list]:
    """Rows [model, parameter, light, integrator, error, spread, error without the
    secondary boundary term, seconds] for soft shadows in view."""
    from instancing.validation.gradient_check import PENUMBRA_CASES, penumbra_case
    rows = []
    for model, name, light, integrator in PENUMBRA_CASES:
        case = penumbra_case(model, name, light, integrator, size, MESH, without=True)
        rows.append(_case_row([model, name, light, integrator], case))
    return rows


def interreflection(size: int) -> list[list]:
    """Rows [model, error, spread, error without the secondary boundary term, seconds] for
    an object seen only through interreflection."""
    from instancing.validation.gradient_check import INTERREFLECTION_MODELS, interreflection_case
    rows = []
    for model in INTERREFLECTION_MODELS:
        spp = 8192 if model in ("sphere", "cylinder") else 2048
        case = interreflection_case(model, size, MESH, spp, without=True)
        rows.append([model, case["error"], case["spread"], case["without"], case["seconds"]])
        print(f"{model:<10} error {case['error']:6.4f}  FD spread {case['spread']:6.4f}  "
              f"without the term {case['without']:6.4f}  ({spp} spp, {case['seconds']:.1f} s)",
              flush=True)
    return rows


def reflected(size: int) -> list[list]:
    """Rows [model, light, max_depth, size, error, spread, error without the secondary term,
    seconds] for an object's shadow seen only by one bounce (the screen scene, ``size``
    pixels): the area lamp's penumbra and the point light's hard shadow."""
    from instancing.validation.gradient_check import reflected_penumbra_case
    rows = []
    for model, light, max_depth in REFLECTED_CASES:
        case = reflected_penumbra_case(model, size, MESH, max_depth, *REFLECTED_SAMPLES[light],
                                       light, without=True)
        rows.append(_case_row([model, light, max_depth, size], case))
    return rows


def _case_row(labels: list, case: dict) -> list:
    """A table row: ``labels``, then the case's error, spread, error without the term and
    seconds (printed as it comes)."""
    print(" ".join(f"{label!s:<10}" for label in labels)
          + f" error {case['error']:6.4f}  FD spread {case['spread']:6.4f}  without the term "
            f"{case['without']:6.4f}  ({case['seconds']:.1f} s)", flush=True)
    return list(labels) + [case["error"], case["spread"], case["without"], case["seconds"]]


def _grid_of_spheres(count: int, size: int) -> dict:
    side = int(np.ceil(np.sqrt(count)))
    spacing = 4.0 / side
    instances = [{"id": f"s{i}", "model": "sphere", "material": "paint",
                  "to_world": [{"translate": [(i % side - (side - 1) / 2) * spacing,
                                              (i // side - (side - 1) / 2) * spacing, 0]},
                               {"scale": 0.35 * spacing}]} for i in range(count)]
    instances.append({"id": "wall", "model": "rectangle",
                      "to_world": [{"translate": [0, 0, 2]}, {"rotate": {"axis": [0, 1, 0], "angle": 180}},
                                   {"scale": 5}]})
    return {"camera": {"type": "perspective", "fov": 45, "width": size, "height": size,
                       "to_world": [{"look_at": {"origin": [0, 0, -6], "target": [0, 0, 0],
                                                 "up": [0, 1, 0]}}]},
            "materials": {"paint": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]}},
            "lights": [{"type": "point", "position": [1, 2, -6], "intensity": [40, 40, 40]}],
            "instances": instances}


def _worker_figures(step, warmups: int) -> dict:
    """Seconds per ``step(seed)`` (median of 3 after ``warmups`` warm-up calls, which trace
    and compile) and the process's peak resident set."""
    for seed in range(warmups):
        step(seed)
    times = []
    for seed in range(warmups, warmups + 3):
        start = time.perf_counter()
        step(seed)
        times.append(time.perf_counter() - start)
    return {"seconds": statistics.median(times),
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def depth_worker(depth: int, size: int, spp: int) -> dict:
    """One reverse-mode path step (the Cornell box's tall box moving) at ``max_depth``
    ``depth``, in a fresh process: seconds (median of 3 after a warm-up) and peak RSS."""
    import drjit as dr
    import instancing
    # A closed room: paths keep bouncing until the depth limit or Russian roulette.
    scene = instancing.load_scene(ROOT / "scenes" / "cornell_box.json")
    params = instancing.traverse(scene)
    key = "tall_box.translation"

    def step(seed):
        dr.enable_grad(params[key])
        params.update()
        image = instancing.render(scene, "path", spp=spp, seed=seed, max_depth=depth,
                                  width=size, height=size)
        dr.backward(dr.mean(dr.square(image.array)))
        grad = dr.grad(params[key])
        dr.eval(grad)
        dr.sync_thread()
        dr.disable_grad(params[key])

    return _worker_figures(step, warmups=1)


#: The last revision whose `path` gradients ran AD through an evaluated bounce loop (before
#: path replay): the depth part's baseline.
EVALUATED_LOOP_REVISION = "44a1355"


def depth(size: int = 256, spp: int = 8, baseline: str | None = EVALUATED_LOOP_REVISION) -> list[dict]:
    """Rows {method, max_depth, seconds, peak_mb}: this tree's path replay and, from a git
    worktree of ``baseline`` in the same run, the evaluated loop it replaced."""
    rows = []
    print(f"{'method':<16} {'max_depth':>9} {'s/step':>8} {'peak MB':>8}")
    with tempfile.TemporaryDirectory() as tmp:
        trees = [("path replay", ROOT)]
        if baseline:
            tree = Path(tmp) / "baseline"
            made = subprocess.run(["git", "worktree", "add", "--detach", str(tree), baseline],
                                  cwd=ROOT, capture_output=True, text=True)
            if made.returncode == 0:
                trees.append(("evaluated loop", tree))
            else:
                print(f"no baseline ({baseline}): {made.stderr.strip()}")
        try:
            for method, tree in trees:
                for max_depth in (3, 8, 16):
                    out = subprocess.run(
                        [sys.executable, "-m", "benchmarks.gradients", "--depth-worker",
                         json.dumps([max_depth, size, spp])], cwd=tree, capture_output=True,
                        text=True, timeout=WORKER_TIMEOUT, env={**os.environ, "PYTHONPATH": str(tree)})
                    last = out.stdout.strip().splitlines()[-1] if out.returncode == 0 else "{}"
                    row = {"method": method, "max_depth": max_depth, "size": size, "spp": spp,
                           **json.loads(last[last.index("{"):])}
                    rows.append(row)
                    print(f"{method:<16} {max_depth:>9} {row.get('seconds', float('nan')):>8.3f} "
                          f"{row.get('peak_mb', float('nan')):>8.0f}", flush=True)
        finally:
            if len(trees) > 1:
                subprocess.run(["git", "worktree", "remove", "--force", str(trees[1][1])], cwd=ROOT,
                               capture_output=True)
    return rows


def cost_worker(renderer: str, count: int, size: int, spp: int) -> dict:
    """One configuration, run in a fresh process: seconds per iteration and peak RSS."""
    import drjit as dr
    import drjit.opt
    import instancing
    scene = instancing.load_scene(_grid_of_spheres(count, size))
    target = np.array(instancing.render(scene, "direct", spp=spp, seed=7), np.float32)
    if renderer == "ours":
        from instancing.ad.recovery import image_loss
        params = instancing.traverse(scene)
        opt = drjit.opt.Adam(lr=1e-3)
        for i in range(count):
            opt[f"s{i}.translation"] = params[f"s{i}.translation"]
        # No shadow term, as Mitsuba's direct_projective with sppi 0 below: the same work.
        step = instancing.OptimisationStep(params, opt, image_loss, spp=spp, sppi=0)
        target_tensor = instancing.core.backend.TensorXf(target)

        def iteration(seed):
            step(seed, target_tensor)
            dr.eval(opt.state)
            dr.sync_thread()
    else:
        import mitsuba as mi
        mi.set_variant(instancing.core.backend.MITSUBA_VARIANT)
        description = instancing.to_mitsuba(scene, mode="shapes", spp=spp)
        description["integrator"] = {"type": "direct_projective", "sppi": 0}
        mscene = mi.load_dict(description)
        mparams = mi.traverse(mscene)
        keys = [f"shape_{i:07d}.to_world" for i in range(count)]
        initial = {k: mi.Transform4f(mparams[k]) for k in keys}
        opt = drjit.opt.Adam(lr=1e-3)
        for k in keys:
            opt[k] = mi.Vector3f(0.0)
        mtarget = mi.TensorXf(target)

        def iteration(seed):
            for k in keys:
                mparams[k] = mi.Transform4f().translate(opt[k]) @ initial[k]
            mparams.update()
            image = mi.render(mscene, mparams, spp=spp, seed=seed)
            dr.backward(dr.mean(dr.square(image - mtarget), axis=None))
            opt.step()
            dr.eval(opt)
            dr.sync_thread()
    # Three warm-up steps: tracing and compilation (the first steps fuse kernels differently).
    return _worker_figures(iteration, warmups=3)


def _cost_run(renderer: str, count: int, size: int, spp: int) -> dict:
    """One worker process of the cost part: its figures, or NaN and the error it ended with."""
    try:
        out = subprocess.run([sys.executable, "-m", "benchmarks.gradients", "--worker",
                              json.dumps([renderer, count, size, spp])], cwd=ROOT,
                             capture_output=True, text=True, timeout=WORKER_TIMEOUT)
    except subprocess.TimeoutExpired:
        out = subprocess.CompletedProcess([], 1, "", f"timed out after {WORKER_TIMEOUT} s")
    if out.returncode != 0:
        return {"seconds": float("nan"), "peak_mb": float("nan"),
                "error": out.stderr.strip().splitlines()[-1:]}
    # The worker's last line is its JSON (after any colour codes Mitsuba's log left).
    last = out.stdout.strip().splitlines()[-1]
    return json.loads(last[last.index("{"):])


def cost(spp: int) -> list[dict]:
    """Per configuration, COST_ROUNDS rounds of one process each for ours and Mitsuba, in
    alternation (load from other jobs hits both alike); a renderer's seconds are the median
    over its rounds, its memory the largest peak. A renderer that fails is not run again."""
    rows = []
    print(f"{'instances':>9} {'size':>5} {'ours s/it':>10} {'MB':>6} {'mitsuba s/it':>13} {'MB':>6} "
          f"{'ratio':>6}  (rounds: ours / mitsuba s)")
    for size in (128, 256):
        for count in (10, 100, 1000):
            runs = {"ours": [], "mitsuba": []}
            for _ in range(COST_ROUNDS):
                for renderer, done in runs.items():
                    if not done or "error" not in done[-1]:
                        done.append(_cost_run(renderer, count, size, spp))
            row = {"instances": count, "size": size}
            for renderer, done in runs.items():
                good = [r for r in done if "error" not in r]
                row[renderer] = ({"seconds": statistics.median(r["seconds"] for r in good),
                                  "peak_mb": max(r["peak_mb"] for r in good),
                                  "rounds": [r["seconds"] for r in good]} if good else done[-1])
            ours, theirs = row["ours"], row["mitsuba"]
            rounds = " / ".join(", ".join(f"{s:.3f}" for s in r.get("rounds", [])) or "-"
                                for r in (ours, theirs))
            print(f"{count:>9} {size:>5} {ours['seconds']:>10.3f} {ours['peak_mb']:>6.0f} "
                  f"{theirs['seconds']:>13.3f} {theirs['peak_mb']:>6.0f} "
                  f"{theirs['seconds'] / ours['seconds']:>6.2f}  ({rounds})", flush=True)
            rows.append(row)
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--part", default="validation,shadow,shadow_path,lights,penumbra,interreflection,"
                                          "reflected,contact,touching,delta,depth,cost")
    parser.add_argument("--size", type=int, default=32, help="validation image size")
    parser.add_argument("--spp", type=int, default=4, help="samples per pixel of a cost iteration")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--depth-worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(cost_worker(*json.loads(args.worker))))
        return
    if args.depth_worker:
        print(json.dumps(depth_worker(*json.loads(args.depth_worker))))
        return
    out = ROOT / "benchmarks" / "results_gradients.json"
    # Parts run separately update their entry and keep the others.
    results = json.loads(out.read_text()) if out.is_file() else {}
    parts = args.part.split(",")
    runs = [
        ("validation", "gradient images vs central finite differences (light at the camera)",
         lambda: validation(args.size)),
        ("shadow", "the same with the lamp 1.5 units off the camera: visible shadows",
         lambda: validation(args.size, light_offset=1.5)),
        ("shadow_path", "the same in path (max_depth 3): shadows seen directly and by a bounce",
         lambda: validation(args.size, light_offset=1.5, integrator="path")),
        ("lights", "moving lamps vs central finite differences", lambda: lights(args.size)),
        ("penumbra", "soft shadows in view (area lamps, environment): secondary boundary term",
         lambda: penumbra(args.size)),
        ("interreflection", "an object seen only through interreflection (path, max_depth 3)",
         lambda: interreflection(args.size)),
        ("reflected", "a shadow seen only by one bounce (path): the secondary term at the path's vertices",
         lambda: reflected(REFLECTED_SIZE)),
        ("contact", "instances sinking into a floor (contact curves) vs central finite differences",
         lambda: contact(args.size)),
        ("touching", "light bounced between touching instances (path, max_depth 3): the slide",
         lambda: touching(args.size)),
        ("delta", "moving mirrors and glass, and a glossy bounce (path replay's chains of vertices)",
         delta),
        ("depth", "one reverse-mode path step against max_depth: path replay and the evaluated loop",
         depth),
        ("cost", f"one forward + backward iteration, {args.spp} spp, every translation differentiated",
         lambda: cost(args.spp)),
    ]
    for name, title, run in runs:
        if name in parts:
            print(f"== {title} ==")
            results[name] = run()
    from benchmarks.machine import describe  # (imported here, as instancing is throughout)
    results["machine"] = describe()
    out.write_text(json.dumps(results, indent=1, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
