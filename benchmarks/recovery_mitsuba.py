"""Mitsuba 3's side of the recovery suite (:mod:`benchmarks.recovery_suite`): the same
problem recovered with ``direct_projective``, the object one plain mesh whose vertices the
parameters transform.

The mesh is the problem's shape tessellated (a 64 x 32 UV sphere and a 64-segment open tube,
shaded smoothly; Mitsuba's cube and two triangles, flat; the torus OBJ as it is), in model
coordinates; each step moves its vertices by ``translate(t) rotate(q) scale(s)`` built in
Dr.Jit from the optimised t, q (normalized) and s, renders every view, and takes Adam with
the schedule of :func:`instancing.ad.recovery.recover` (its learning rates per part scaled
as there, its default learning-rate schedule, the mean of the last quarter of the iterates, the
suite's coarse-to-fine blur of both images in the loss, the derivative from samples of its
own: the image at ``spp`` rendered without derivatives, the derivative from a render at
``recover``'s default ``sppc`` with another seed). Mitsuba renders its own targets (at the
suite's TARGET_SPP) so that each renderer matches images of its own shape.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

import instancing
from instancing.ad.recovery import (AVERAGE_FRACTION, LR, LR_FINAL_RATIO, RECOVERABLE,
                                     blur_sigma, blur_taps, default_sppc, image_loss,
                                     transform_errors)
from instancing.core.backend import dr, mitsuba_module
from instancing.core.transform import decompose, quaternion_rows, rotate_quaternion

from benchmarks.recovery_suite import TARGET_SPP, TORUS, _met, scene_dict



def _uv_sphere(rings: int = 32, segments: int = 64) -> tuple[np.ndarray, np.ndarray]:
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    return v, _grid_faces(rings, segments)


def _tube(segments: int = 64) -> tuple[np.ndarray, np.ndarray]:
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    v = np.concatenate([np.stack([np.cos(phi), np.sin(phi), np.full(segments, z)], -1)
                        for z in (0.0, 1.0)])
    return v, _grid_faces(1, segments)


def _grid_faces(rows: int, segments: int) -> np.ndarray:
    """Two triangles per quad of a (rows + 1) x segments grid wrapping around."""
    faces = []
    for r in range(rows):
        for c in range(segments):
            a, b = r * segments + c, r * segments + (c + 1) % segments
            faces += [[a, b, b + segments], [a, b + segments, a + segments]]
    return np.array(faces, np.uint32)


def _mesh_file(mi, model: str, folder: Path) -> tuple[str, bool]:
    """A PLY file of ``model`` in model coordinates, and whether it is shaded flat."""
    if model == "torus":
        return str(TORUS), False
    if model == "cube":
        mesh = mi.load_dict({"type": "cube"})
        flat = True
    else:
        if model == "sphere":
            v, f = _uv_sphere()
        elif model == "cylinder":
            v, f = _tube()
        else:
            v, f = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float), \
                np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
        mesh = mi.Mesh(model, len(v), len(f), has_vertex_normals=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
        params["faces"] = mi.UInt32(f.ravel())
        params.update()
        flat = model == "rectangle"
    path = folder / f"{model}.ply"
    mesh.write_ply(str(path))
    return str(path), flat


def _scene(mi, p: dict, views: int, width: int, spp: int, folder: Path):
    """Mitsuba's scene of problem ``p``: ours exported without the object, plus its mesh."""
    floor_only = scene_dict(p, p["target"], views, width)
    floor_only["instances"] = floor_only["instances"][:1]
    description = instancing.to_mitsuba(instancing.load_scene(floor_only), mode="shapes", spp=spp)
    filename, flat = _mesh_file(mi, p["model"], folder)
    description["object"] = {"type": "obj" if filename.endswith(".obj") else "ply",
                             "filename": filename, "face_normals": flat,
                             "bsdf": {"type": "diffuse", "reflectance": {
                                 "type": "rgb", "value": [0.75, 0.45, 0.2]}}}
    description["integrator"] = {"type": "direct_projective"}
    return mi.load_dict(description)


def _matrix(t, q, s) -> list[list]:
    """Rows of translate(t) rotate(q / |q|) scale(s) (differentiable Dr.Jit values)."""
    r = quaternion_rows(q.x, q.y, q.z, q.w)
    return [[r[i][j] * s[j] for j in range(3)] + [t[i]] for i in range(3)]


def recover_mitsuba(p: dict, views: int, width: int, iterations: int, spp: int,
                    blur_start: float, blur_fraction: float) -> dict:
    """Recover problem ``p`` from ``views`` views with Mitsuba's ``direct_projective``
    (coarse to fine as ``recover``'s ``blur_start``, ``blur_fraction``)."""
    mi = mitsuba_module()
    import drjit.opt
    # (Its projective integrator warns on every render that a point light's scene has no
    # indirect silhouettes to sample.)
    mi.set_log_level(mi.LogLevel.Error)
    with tempfile.TemporaryDirectory() as folder:
        scene = _scene(mi, p, views, width, spp, Path(folder))
    params = mi.traverse(scene)
    key = "object.vertex_positions"
    model = dr.unravel(mi.Point3f, params[key])
    sensors = scene.sensors()

    def place(matrix):
        return dr.ravel(mi.Point3f(*[sum(matrix[i][j] * model[j] for j in range(3)) + matrix[i][3]
                                     for i in range(3)]))

    t1, q1, s1, _ = decompose(p["target"])
    params[key] = place(_matrix(*_vectors(mi, t1, q1, s1)))
    params.update()
    targets = [mi.render(scene, sensor=sensor, spp=TARGET_SPP, seed=11) for sensor in sensors]
    t0, q0, s0, _ = decompose(p["start"])
    size = 2.0 * float(np.linalg.svd(p["start"][:3, :3], compute_uv=False)[0])
    opt = drjit.opt.Adam(lr=LR)
    opt["t"], opt["q"], opt["s"] = _vectors(mi, t0, q0, s0)
    rates = {"t": LR * RECOVERABLE["translation"] * size, "q": LR * RECOVERABLE["rotation"],
             "s": LR * RECOVERABLE["scale"]}
    averaged = max(1, round(AVERAGE_FRACTION * iterations))
    radius = int(np.ceil(3 * blur_start)) if blur_start > 0 else 0
    sums, seconds, met_at = {}, [], None
    for it in range(iterations):
        start = time.perf_counter()
        decay = LR_FINAL_RATIO ** (it / max(1, iterations - 1))
        opt.set_learning_rate({k: rate * decay for k, rate in rates.items()})
        params[key] = place(_matrix(opt["t"], opt["q"], opt["s"]))
        params.update()
        taps = blur_taps(blur_sigma(it, iterations, blur_start, blur_fraction),
                         radius) if radius else None
        loss = 0.0
        for k, sensor in enumerate(sensors):
            # The image's value from spp samples, its derivative from sppc others.
            seed = it * len(sensors) + k
            value = mi.render(scene, sensor=sensor, spp=spp, seed=seed)
            derivative = mi.render(scene, params, sensor=sensor, spp=default_sppc(spp),
                                   seed=seed + 0x40000000)
            image = dr.detach(value) + (derivative - dr.detach(derivative))
            loss += image_loss(image, targets[k], taps) / len(sensors)
        dr.backward(loss)
        opt.step()
        dr.eval(opt)
        seconds.append(time.perf_counter() - start)
        current = _numpy_matrix(opt)
        if met_at is None and _met(transform_errors(current, p["target"])):
            met_at = it + 1
        if it >= iterations - averaged:
            for k in ("t", "q", "s"):
                value = np.array(opt[k]).ravel()
                if k == "q" and "q" in sums and np.dot(value, sums["q"]) < 0:
                    value = -value
                sums[k] = sums.get(k, 0.0) + value
    final = _numpy_matrix({k: v / averaged for k, v in sums.items()})
    errors = transform_errors(final, p["target"])
    return {"errors": list(errors), "success": _met(errors), "iterations": met_at,
            "seconds": None if met_at is None else float(sum(seconds[:met_at])),
            "seconds_per_iteration": float(np.median(seconds))}


def _vectors(mi, t, q, s) -> tuple:
    """NumPy parts as Mitsuba vectors (t, q, s)."""
    return (mi.Vector3f(*map(float, t)), mi.Vector4f(*map(float, q)), mi.Vector3f(*map(float, s)))


def _numpy_matrix(values) -> np.ndarray:
    """The float64 matrix of parameters t, q, s (Dr.Jit or NumPy values)."""
    t, q, s = (np.array(values[k], np.float64).ravel() for k in ("t", "q", "s"))
    m = np.eye(4)
    m[:3, :3] = rotate_quaternion(q.tolist()).to_numpy()[0][:3, :3] @ np.diag(s)
    m[:3, 3] = t
    return m
