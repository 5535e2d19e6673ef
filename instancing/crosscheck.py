"""Cross-check against Mitsuba 3: the same scene, the same rays, measured agreement.

Rays: one camera ray through every pixel centre plus random rays through the
scene's bounds go through our ``scene.intersect`` and Mitsuba's
``scene.ray_intersect`` on the exported scene (plain shapes where Mitsuba
accepts every transform, ``shapegroup`` + ``instance`` otherwise). A float64
NumPy reference (:mod:`instancing.reference`) intersects a subset, so that a
disagreement can be blamed on one side. Images: our ``aov``/``direct``/``path``
renders against Mitsuba's at high spp (relative RMSE), with difference images.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import reference
from .backend import MITSUBA_VARIANT, dr
from .camera import PerspectiveCamera
from .errors import SceneError
from .instances import MESH_KIND
from .io.image import write_exr, write_png
from .mitsuba_export import to_mitsuba
from .rendering import render
from .scene import Scene

#: Default tolerances (also stated in the README).
TOLERANCES = {
    "hit_miss_rate": 1e-4,        # rays hit by one renderer only (grazing rays)
    "instance_agreement": 1.0,    # where both hit at the same t (rel. 1e-4)
    "median_rel_t_vs_float64": 1e-6,
    "image_rel_rmse": 0.01,       # direct / path against Mitsuba at high spp
}


@dataclass
class CrosscheckReport:
    """Figures of one cross-check; ``failures`` lists the tolerances exceeded."""

    rows: list[tuple[str, str, str]] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    def add(self, name: str, ours: str, mitsuba: str = "") -> None:
        self.rows.append((name, ours, mitsuba))

    def table(self) -> str:
        width = max(len(r[0]) for r in self.rows) + 2
        lines = [f"{'measure':<{width}} {'ours':>22} {'Mitsuba':>22}"]
        lines += [f"{n:<{width}} {o:>22} {m:>22}" for n, o, m in self.rows]
        lines += [f"FAIL: {f}" for f in self.failures] or ["all tolerances met"]
        return "\n".join(lines)


def _mitsuba():
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    return mi


def _export_mode(scene: Scene) -> str:
    """Plain shapes when Mitsuba accepts every transform (faster there), else instances."""
    try:
        to_mitsuba(scene, mode="shapes")
        return "shapes"
    except SceneError:
        return "instances"


def _random_rays(scene: Scene, count: int, rng: np.random.Generator):
    lo, hi = scene.bounds
    pad = 0.05 * (hi - lo)
    o = rng.uniform(lo - pad, hi + pad, (count, 3)).astype(np.float32)
    d = rng.normal(size=(count, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    return o, d


def _mitsuba_hits(mi, mscene, mode: str, o: np.ndarray, d: np.ndarray):
    """t, p, n and our instance index of Mitsuba's nearest hits (NumPy)."""
    ray = mi.Ray3f(mi.Point3f(*[np.ascontiguousarray(o[:, k]) for k in range(3)]),
                   mi.Vector3f(*[np.ascontiguousarray(d[:, k]) for k in range(3)]))
    si = mscene.ray_intersect(ray)
    pointer = si.shape if mode == "shapes" else si.instance
    registry = np.asarray(dr.reinterpret_array(mi.UInt32, pointer))
    # Registry id of each exported shape or instance -> our instance index.
    lookup = {}
    objects = mscene.shapes()
    for obj in objects:
        name = obj.id()
        if name.startswith(("shape_", "instance_")):
            lookup[int(np.asarray(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(obj)))[0])] = \
                int(name.split("_")[1])
    if mode == "instances":
        # Emitting instances are plain shapes even in this mode.
        shape_registry = np.asarray(dr.reinterpret_array(mi.UInt32, si.shape))
        registry = np.where(registry == 0, shape_registry, registry)
    instance = np.array([lookup.get(int(r), -1) for r in registry], np.int64)
    t = np.asarray(si.t, np.float64)
    valid = np.isfinite(t)
    return {"t": np.where(valid, t, np.inf), "p": np.asarray(si.p, np.float64).T,
            "n": np.asarray(si.n, np.float64).T, "instance": np.where(valid, instance, -1)}


def _angle_deg(a, b, oriented=True):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    dot = np.sum(a * b, axis=1)
    dot = dot if oriented else np.abs(dot)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), dot))


def _reference_instances(scene: Scene) -> list[dict]:
    desc = scene.description
    out = []
    for i in range(len(desc.instance_ids)):
        model = desc.models[desc.instance_model[i]]
        mesh = (model.mesh.vertices, model.mesh.faces) if model.kind == MESH_KIND else None
        out.append({"kind": "mesh" if mesh is not None else model.kind, "to_world": desc.to_world[i],
                    "mesh": mesh})
    return out


def _blame(scene: Scene, o, d, rays: np.ndarray, other_instance: np.ndarray,
           ours_t: np.ndarray, ours_instance: np.ndarray) -> tuple[int, int, int]:
    """Classify instance disagreements with the float64 reference: (ties, ours wrong, Mitsuba wrong).

    A tie: the other renderer's instance is hit (float64) at our t within 1e-4, i.e.
    coincident surfaces where either answer is right.
    """
    instances = _reference_instances(scene)
    ties = ours_wrong = theirs_wrong = 0
    for k in rays:
        ray_o, ray_d = o[k:k + 1].astype(np.float64), d[k:k + 1].astype(np.float64)
        other = reference.intersect_instances([instances[other_instance[k]]], ray_o, ray_d)["t"][0]
        if abs(other - ours_t[k]) <= 1e-4 * ours_t[k]:
            ties += 1
        elif reference.intersect_instances(instances, ray_o, ray_d)["instance"][0] == ours_instance[k]:
            theirs_wrong += 1
        else:
            ours_wrong += 1
    return ties, ours_wrong, theirs_wrong


def _stat(values: np.ndarray, q: float) -> str:
    """A quantile as text, '-' for an empty sample."""
    return _fmt(float(np.quantile(values, q))) if len(values) else "-"


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def check_rays(scene: Scene, report: CrosscheckReport, random_rays: int, reference_rays: int,
               seed: int, out_dir: Path | None) -> None:
    """The ray section of the cross-check (see the module docstring)."""
    mi = _mitsuba()
    rng = np.random.default_rng(seed)
    o, d = _random_rays(scene, random_rays, rng)
    if scene.camera is not None:
        co, cd = PerspectiveCamera.from_dict(scene.camera).pixel_centre_rays()
        o = np.concatenate([np.asarray(co, np.float32).T, o])
        d = np.concatenate([np.asarray(cd, np.float32).T, d])
    mode = _export_mode(scene)
    # optimize=False: Mitsuba would otherwise merge meshes sharing a BSDF into one shape,
    # and hits could no longer be traced back to instances.
    mscene = mi.load_dict(to_mitsuba(scene, mode=mode), optimize=False)
    ours_t0 = time.perf_counter()
    ours = scene.intersect(o, d)
    ours_time = time.perf_counter() - ours_t0
    mi_t0 = time.perf_counter()
    theirs = _mitsuba_hits(mi, mscene, mode, o, d)
    mi_time = time.perf_counter() - mi_t0
    n = len(o)
    report.add("rays (camera + random)", str(n), f"export: {mode}")
    report.add("time for all rays (s)", _fmt(ours_time), _fmt(mi_time))
    ours_hit, mi_hit = np.isfinite(ours.t), np.isfinite(theirs["t"])
    disagree = ours_hit != mi_hit
    rate = disagree.sum() / n
    report.add("hit/miss disagreement", f"{disagree.sum()} ({rate:.2e})")
    if rate > TOLERANCES["hit_miss_rate"]:
        report.failures.append(f"hit/miss disagreement {rate:.2e} > {TOLERANCES['hit_miss_rate']}")
    both = ours_hit & mi_hit
    rel_t = np.abs(ours.t[both] - theirs["t"][both]) / theirs["t"][both]
    size = float(np.linalg.norm(scene.bounds[1] - scene.bounds[0]))
    pos = np.linalg.norm(ours.p[both] - theirs["p"][both], axis=1) / size
    # Instances must agree unless the two hits are a tie: coincident surfaces (e.g. a box
    # standing on the floor) at the same t, where each renderer may pick either.
    differ = np.flatnonzero(both & (ours.instance != theirs["instance"]))
    ties, ours_wrong, theirs_wrong = _blame(scene, o, d, differ, theirs["instance"], ours.t,
                                            ours.instance)
    agree = 1.0 - ours_wrong / max(both.sum(), 1)
    report.add("rel. t difference median / 99.9%", f"{_stat(rel_t, 0.5)} / {_stat(rel_t, 0.999)}")
    report.add("position difference / scene size, max", _stat(pos, 1.0))
    report.add("normal angle difference 99.9% (deg)",
               _stat(_angle_deg(ours.n[both], theirs["n"][both], False), 0.999))
    report.add("instance disagreements: ties / ours wrong / Mitsuba wrong",
               f"{ties} / {ours_wrong} / {theirs_wrong}")
    report.add("instance agreement (ties and Mitsuba's errors excluded)", f"{agree:.6f}")
    if agree < TOLERANCES["instance_agreement"]:
        report.failures.append(f"instance agreement {agree:.6f} < 1 ({ours_wrong} rays where float64 "
                               "sides with Mitsuba)")

    # Float64 reference on a random subset of the rays: blame each side.
    subset = np.sort(rng.choice(n, size=min(reference_rays, n), replace=False))
    ref = reference.intersect_instances(_reference_instances(scene), o[subset].astype(np.float64),
                                        d[subset].astype(np.float64))
    figures = {}
    for name, t, normal, instance, oriented in (
            ("ours", ours.t, ours.n, ours.instance, True),
            ("mitsuba", theirs["t"], theirs["n"], theirs["instance"], False)):
        t, normal, instance = t[subset], normal[subset], instance[subset]
        h = np.isfinite(t) & np.isfinite(ref["t"])
        err = np.abs(t[h] - ref["t"][h]) / ref["t"][h]
        # Normals only where both name the same instance: on coincident faces (ties) the
        # other face's normal is an equally right answer, not an error.
        same = h & (instance == ref["instance"])
        ang = _angle_deg(normal[same], ref["n"][same], oriented)
        wrong = int((np.isfinite(t) != np.isfinite(ref["t"])).sum())
        figures[name] = (wrong, _stat(err, 0.5), _stat(err, 0.999), _stat(ang, 0.999))
    labels = (f"vs float64 ({len(subset)} rays): hit/miss wrong", "vs float64: median rel. t error",
              "vs float64: 99.9% rel. t error", "vs float64: 99.9% normal error (deg, same instance)")
    for k, label in enumerate(labels):
        report.add(label, str(figures["ours"][k]), str(figures["mitsuba"][k]))
    median = float(figures["ours"][1]) if figures["ours"][1] != "-" else 0.0
    if median > TOLERANCES["median_rel_t_vs_float64"]:
        report.failures.append(f"median rel. t error vs float64 {median:.2e} > 1e-6")
    if out_dir is not None and disagree.any():
        np.savez(out_dir / "ray_disagreements.npz", origin=o[disagree], direction=d[disagree],
                 ours_t=ours.t[disagree], ours_instance=ours.instance[disagree],
                 mitsuba_t=theirs["t"][disagree], mitsuba_instance=theirs["instance"][disagree])


def check_images(scene: Scene, report: CrosscheckReport, integrators, spp: int, reference_spp: int,
                 out_dir: Path | None) -> None:
    """The image section: our renders against Mitsuba's at ``reference_spp``."""
    mi = _mitsuba()
    mscene = mi.load_dict(to_mitsuba(scene, mode=_export_mode(scene), spp=reference_spp))
    for integrator in integrators:
        t0 = time.perf_counter()
        if integrator == "aov":
            ours = np.asarray(render(scene, "aov", spp=spp, aovs=["depth", "normal"]))
            mi_integrator = {"type": "aov", "aovs": "dd.y:depth,nn:geo_normal"}
        else:
            ours = np.asarray(render(scene, integrator, spp=spp))
            mi_integrator = {"type": integrator} if integrator == "direct" else \
                {"type": "path", "max_depth": -1}
        ours_time = time.perf_counter() - t0
        t0 = time.perf_counter()
        theirs = np.asarray(mi.render(mscene, integrator=mi.load_dict(mi_integrator), spp=reference_spp))
        mi_time = time.perf_counter() - t0
        if integrator == "aov":
            theirs = theirs[..., -4:]  # Mitsuba puts the AOVs after its RGB(A) channels
        rel_rmse = float(np.sqrt(np.mean((ours - theirs) ** 2)) / max(np.abs(theirs).mean(), 1e-12))
        report.add(f"image {integrator}: rel. RMSE ({spp} vs {reference_spp} spp)", _fmt(rel_rmse))
        report.add(f"image {integrator}: time (s)", _fmt(ours_time), _fmt(mi_time))
        if integrator != "aov" and rel_rmse > TOLERANCES["image_rel_rmse"]:
            report.failures.append(f"{integrator} relative RMSE {rel_rmse:.4f} > {TOLERANCES['image_rel_rmse']}")
        if out_dir is not None:
            diff = ours - theirs
            write_exr(out_dir / f"diff_{integrator}.exr", diff)
            if diff.shape[-1] in (1, 3, 4):
                write_png(out_dir / f"diff_{integrator}.png", np.abs(diff) / max(np.abs(diff).max(), 1e-12))


def crosscheck(scene: Scene, *, random_rays: int = 1 << 20, reference_rays: int = 20_000,
               integrators=("aov", "direct", "path"), spp: int = 256, reference_spp: int = 1024,
               out_dir: str | Path | None = None, seed: int = 0) -> CrosscheckReport:
    """Run both renderers on ``scene`` and measure their agreement.

    Args:
        scene: a loaded scene (images need its camera).
        random_rays: random rays through the scene's bounds (plus one per pixel).
        reference_rays: rays also intersected by the float64 reference (brute force).
        integrators: images to compare; empty for rays only.
        spp, reference_spp: our samples per pixel and Mitsuba's.
        out_dir: where to write disagreements (npz) and difference images (EXR, PNG).
        seed: random seed of the rays.

    Returns:
        A :class:`CrosscheckReport`; ``report.failures`` is empty when every tolerance holds.
    """
    report = CrosscheckReport()
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    check_rays(scene, report, random_rays, reference_rays, seed, out)
    if integrators and scene.camera is not None:
        check_images(scene, report, integrators, spp, reference_spp, out)
    return report
