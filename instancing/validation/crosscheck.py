"""Cross-check against Mitsuba 3: the same scene, the same rays, measured agreement.

Rays: one camera ray through every pixel centre plus random rays through the
scene's bounds go through our ``scene.intersect`` and Mitsuba's
``scene.ray_intersect`` on the exported scene (plain shapes where Mitsuba
accepts every transform, ``shapegroup`` + ``instance`` otherwise). A float64
NumPy reference (:mod:`instancing.validation.reference`) intersects a subset, so that a
disagreement can be blamed on one side. Images: our ``aov``/``direct``/``path``
renders against Mitsuba's at high spp (relative RMSE), with difference images.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from ..core.backend import MITSUBA_VARIANT, dr, rows_from_vectors
from ..core.errors import SceneError
from ..io.image import write_exr, write_png
from ..io.output_file import replaced
from ..io.mitsuba_export import to_mitsuba
from ..io.scene_file import parse_scene
from ..rendering.film import render
from ..scene.instance_table import MESH_KIND
from ..scene.scene import Scene
from . import reference
from .measures import angle_deg, block_error, quantile, root_mean_square

#: Pixels per side of the blocks of the block error (validation.measures.block_error).
BLOCK = 8
#: Default tolerances (also stated in the README).
TOLERANCES = {
    "hit_miss_rate": 1e-4,        # rays hit by one renderer only (grazing rays)
    "instance_agreement": 1.0,    # where both hit at the same t (rel. 1e-4)
    "median_rel_t_vs_float64": 1e-6,
    "image_rel_rmse": 0.01,       # direct / path against Mitsuba at high spp ...
    "image_noise_margin": 1.1,    # ... or 1.1x Mitsuba's own where its noise exceeds 1 %
    # Our 99.9% t and normal errors against float64 may not exceed Mitsuba's on the same
    # rays; for normals at least two float32 roundings of a unit vector are allowed.
    "normal_float32_floor_deg": 6.8e-6,
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


def _mitsuba_hits(mi, mscene, o: np.ndarray, d: np.ndarray):
    """t, p, n and our instance index of Mitsuba's nearest hits (NumPy)."""
    ray = mi.Ray3f(mi.Point3f(*[np.ascontiguousarray(o[:, k]) for k in range(3)]),
                   mi.Vector3f(*[np.ascontiguousarray(d[:, k]) for k in range(3)]))
    si = mscene.ray_intersect(ray)
    # Registry id of each exported shape or instance -> our instance index.
    lookup = {}
    objects = mscene.shapes()
    for obj in objects:
        name = obj.id()
        if name.startswith(("shape_", "instance_")):
            lookup[int(np.asarray(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(obj)))[0])] = \
                int(name.split("_")[1])
    # The instance hit, or the plain shape where there is none (emitters are plain shapes in
    # both modes, mirrored meshes instances in both).
    registry = np.asarray(dr.reinterpret_array(mi.UInt32, si.instance))
    shape_registry = np.asarray(dr.reinterpret_array(mi.UInt32, si.shape))
    registry = np.where(registry == 0, shape_registry, registry)
    instance = np.array([lookup.get(int(r), -1) for r in registry], np.int64)
    t = np.asarray(si.t, np.float64)
    valid = np.isfinite(t)
    return {"t": np.where(valid, t, np.inf), "p": rows_from_vectors(si.p, np.float64),
            "n": rows_from_vectors(si.n, np.float64), "instance": np.where(valid, instance, -1),
            "prim": np.where(valid, np.asarray(si.prim_index, np.int64), -1)}


def _reference_instances(scene: Scene, to_world: np.ndarray | None = None) -> list[dict]:
    """The scene's instances for :func:`reference.intersect_instances`.

    Default: the scene as the renderers store it (its float32 transforms, mesh vertices and
    curve control points rounded to float32). With ``to_world`` (N, 4, 4): the scene as given,
    those float64 transforms and the mesh vertices and control points as read.
    """
    desc = scene.description
    rounding = np.float32 if to_world is None else np.float64
    to_world = np.asarray(scene.to_world if to_world is None else to_world, np.float64)
    models = [desc.models[m] for m in desc.instance_model]
    return reference.instance_list(
        ["mesh" if m.kind == MESH_KIND else m.kind for m in models], to_world,
        [(m.mesh.vertices, m.mesh.faces) if m.kind == MESH_KIND else None for m in models], rounding,
        grids=[m.grid.values if m.grid is not None else None for m in models],
        curves=[None if m.curve is None else _curve_arrays(m.curve, rounding) for m in models])


def _curve_arrays(curve, rounding) -> tuple:
    """A curve model's arrays as the reference takes them, in its fields' order: (points,
    radii, first) and, for linear curves, (left, right); the points and radii rounded to
    ``rounding`` (float32: as the renderers store them)."""
    arrays = [getattr(curve, f.name) for f in fields(curve)]
    return tuple([np.asarray(a).astype(rounding).astype(np.float64) for a in arrays[:2]] + arrays[2:])


def _float64_figures(instances: list[dict], o, d, subset, ours, theirs) -> dict:
    """Per renderer: (hit/miss wrong, median rel. t, 99.9% rel. t, 99.9% normal angle, ties)
    against the float64 reference on ``instances`` for the rays in ``subset``."""
    o, d = o[subset].astype(np.float64), d[subset].astype(np.float64)
    ref = reference.intersect_instances(instances, o, d)
    figures = {}
    for name, t, normal, instance, prim, oriented in (
            ("ours", ours.t, ours.n, ours.instance, ours.prim, True),
            ("mitsuba", theirs["t"], theirs["n"], theirs["instance"], theirs["prim"], False)):
        t, normal, instance, prim = t[subset], normal[subset], instance[subset], prim[subset]
        h = np.isfinite(t) & np.isfinite(ref["t"])
        err = np.abs(t[h] - ref["t"][h]) / ref["t"][h]
        # Normals only where both name the same surface: on coincident faces (ties) the
        # other face's normal is an equally right answer, not an error.
        ties = _coincident(instances, o, d, ref, h, instance, prim)
        same = h & (instance == ref["instance"]) & ~ties
        ang = angle_deg(normal[same], ref["n"][same], oriented)
        wrong = int((np.isfinite(t) != np.isfinite(ref["t"])).sum())
        figures[name] = (wrong, quantile(err, 0.5), quantile(err, 0.999), quantile(ang, 0.999),
                         int(ties.sum()))
    return figures


def _coincident(instances: list[dict], o, d, ref: dict, hit: np.ndarray, instance: np.ndarray,
                prim: np.ndarray) -> np.ndarray:
    """Rays where a renderer hit another surface than the float64 reference (another
    instance, or another triangle of the same mesh) that float64 finds at the reference's t
    within 1e-4 (relative): coincident surfaces, where either answer is right (a box standing
    on the floor; a mesh holding a quad twice, with opposite windings, as Mitsuba's Cornell
    box ceiling does)."""
    mesh = np.array([instances[i]["kind"] == "mesh" if i >= 0 else False for i in instance])
    other = hit & ((instance != ref["instance"]) | (mesh & (prim != ref["prim"])))
    ties = np.zeros(len(o), bool)
    for k in np.flatnonzero(other):
        surface = instances[instance[k]]
        if surface["kind"] == "mesh":
            vertices, faces = surface["mesh"]
            surface = dict(surface, mesh=(vertices, faces[prim[k]:prim[k] + 1]))
        t = reference.intersect_instances([surface], o[k:k + 1], d[k:k + 1])["t"][0]
        ties[k] = abs(t - ref["t"][k]) <= 1e-4 * ref["t"][k]
    return ties


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
    return _fmt(quantile(values, q)) if len(values) else "-"


def _fmt(x: float | int) -> str:
    return str(x) if isinstance(x, int) else f"{x:.3g}"


def check_rays(scene: Scene, report: CrosscheckReport, random_rays: int, reference_rays: int,
               seed: int, out_dir: Path | None, given_to_world: np.ndarray | None = None) -> None:
    """The ray section of the cross-check (see the module docstring); ``given_to_world``:
    the float64 transforms the scene was loaded from, for the reference on the scene as given."""
    mi = _mitsuba()
    rng = np.random.default_rng(seed)
    o, d = _random_rays(scene, random_rays, rng)
    if scene.camera is not None:
        co, cd = scene.camera.pixel_centre_rays()
        o = np.concatenate([rows_from_vectors(co), o])
        d = np.concatenate([rows_from_vectors(cd), d])
    mode = _export_mode(scene)
    # optimize=False: Mitsuba would otherwise merge meshes sharing a BSDF into one shape,
    # and hits could no longer be traced back to instances.
    mscene = mi.load_dict(to_mitsuba(scene, mode=mode), optimize=False)
    ours_t0 = time.perf_counter()
    ours = scene.intersect(o, d)
    ours_time = time.perf_counter() - ours_t0
    mi_t0 = time.perf_counter()
    theirs = _mitsuba_hits(mi, mscene, o, d)
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
               _stat(angle_deg(ours.n[both], theirs["n"][both], False), 0.999))
    report.add("instance disagreements: ties / ours wrong / Mitsuba wrong",
               f"{ties} / {ours_wrong} / {theirs_wrong}")
    report.add("instance agreement (ties and Mitsuba's errors excluded)", f"{agree:.6f}")
    if agree < TOLERANCES["instance_agreement"]:
        report.failures.append(f"instance agreement {agree:.6f} < 1 ({ours_wrong} rays where float64 "
                               "sides with Mitsuba)")

    # Float64 references on a random subset of the rays: blame each side.
    subset = np.sort(rng.choice(n, size=min(reference_rays, n), replace=False))
    stored = _float64_figures(_reference_instances(scene), o, d, subset, ours, theirs)
    references = [(f"vs float64, float32 scene ({len(subset)} rays)", stored)]
    if given_to_world is not None:
        references.append(("vs float64, scene as given", _float64_figures(
            _reference_instances(scene, given_to_world), o, d, subset, ours, theirs)))
    labels = ("hit/miss wrong", "median rel. t error", "99.9% rel. t error",
              "99.9% normal error (deg, same surface)", "coincident-surface ties (normals left out)")
    for scene_name, figures in references:
        for k, label in enumerate(labels):
            report.add(f"{scene_name}: {label}", _fmt(figures["ours"][k]), _fmt(figures["mitsuba"][k]))
    median = references[-1][1]["ours"][1]
    if median > TOLERANCES["median_rel_t_vs_float64"]:
        report.failures.append(f"median rel. t error vs float64 {median:.2e} > 1e-6")
    # Our tail errors may not exceed Mitsuba's on the same rays, against the scene as both
    # renderers hold it (transforms rounded to float32: against the float64 transforms, the
    # tails of both measure that rounding, moved along short rays). Normals on flat shapes sit
    # at the float32 floor of a unit vector in both renderers, where the floor decides.
    for k, what, floor in ((2, "rel. t", 0.0), (3, "normal", TOLERANCES["normal_float32_floor_deg"])):
        if stored["ours"][k] > max(stored["mitsuba"][k], floor):
            report.failures.append(f"99.9% {what} error vs float64 (float32 scene) {stored['ours'][k]:.3g}"
                                   f" > Mitsuba's {stored['mitsuba'][k]:.3g}")
    if out_dir is not None and disagree.any():
        with replaced(out_dir / "ray_disagreements.npz") as partial:
            np.savez(partial, origin=o[disagree], direction=d[disagree],
                     ours_t=ours.t[disagree], ours_instance=ours.instance[disagree],
                     mitsuba_t=theirs["t"][disagree], mitsuba_instance=theirs["instance"][disagree])


def _rel_rmse(image: np.ndarray, reference: np.ndarray) -> float:
    """RMSE over pixels and channels divided by the reference's mean (the README's definition)."""
    return float(np.sqrt(np.mean((image - reference) ** 2)) / max(np.abs(reference).mean(), 1e-12))


def check_images(scene: Scene, report: CrosscheckReport, integrators, spp: int, reference_spp: int,
                 out_dir: Path | None, repeats: int = 1) -> None:
    """The image section: our renders at ``spp`` against Mitsuba's at ``reference_spp``.

    For ``direct`` and ``path``, Mitsuba also renders at ``spp`` with other seeds
    against the same reference: its relative RMSE is the Monte Carlo floor that
    ours is measured beside, and ``sqrt(max(0, MSE_ours - MSE_Mitsuba))`` (relative)
    is the part of our difference in excess of it (bias, or noisier sampling than
    Mitsuba's; 0 where ours is the less noisy, which can hide a bias smaller than
    the difference in noise). With ``repeats`` > 1 both renderers render that many
    times (seeds 0, 1, ... for ours, 1, 2, ... for Mitsuba's) and each error is the
    root mean square over the renders: one firefly, or a bright edge covered by a few
    samples more or less, then no longer decides a comparison.
    """
    mi = _mitsuba()
    mscene = mi.load_dict(to_mitsuba(scene, mode=_export_mode(scene), spp=reference_spp))
    if repeats > 1:
        report.add("images: renders per renderer at the low spp (errors: RMS over them)", str(repeats),
                   str(repeats))
    for integrator in integrators:
        t0 = time.perf_counter()
        if integrator == "aov":
            ours = [np.asarray(render(scene, "aov", spp=spp, aovs=["depth", "normal"]))]
            mi_integrator = {"type": "aov", "aovs": "dd.y:depth,nn:geo_normal"}
        else:
            ours = [np.asarray(render(scene, integrator, spp=spp, seed=k)) for k in range(repeats)]
            mi_integrator = {"type": integrator} if integrator == "direct" else \
                {"type": integrator, "max_depth": -1}
        ours_time = (time.perf_counter() - t0) / len(ours)
        mi_integrator = mi.load_dict(mi_integrator)
        t0 = time.perf_counter()
        theirs = np.asarray(mi.render(mscene, integrator=mi_integrator, spp=reference_spp))
        mi_time = time.perf_counter() - t0
        if integrator == "aov":
            theirs = theirs[..., -4:]  # Mitsuba puts the AOVs after its RGB(A) channels
        rel_rmse = root_mean_square([_rel_rmse(image, theirs) for image in ours])
        report.add(f"image {integrator}: rel. RMSE vs Mitsuba {reference_spp} spp", f"{_fmt(rel_rmse)} ({spp} spp)")
        report.add(f"image {integrator}: time (s)", f"{_fmt(ours_time)} ({spp} spp)",
                   f"{_fmt(mi_time)} ({reference_spp} spp)")
        if integrator != "aov":
            same_spp = [np.asarray(mi.render(mscene, integrator=mi_integrator, spp=spp, seed=1 + k))
                        for k in range(repeats)]
            floor = root_mean_square([_rel_rmse(image, theirs) for image in same_spp])
            excess = np.sqrt(max(rel_rmse ** 2 - floor ** 2, 0.0))
            report.add(f"image {integrator}: Mitsuba's own rel. RMSE at {spp} spp", "", _fmt(floor))
            report.add(f"image {integrator}: rel. RMSE in excess of Mitsuba's own", _fmt(excess))
            # Bias apart from noise: 8x8-block means average the noise down, a bias stays
            # (the images cropped to whole blocks).
            h, w = (theirs.shape[0] // BLOCK) * BLOCK, (theirs.shape[1] // BLOCK) * BLOCK
            if h and w:
                def blocks(images):
                    return root_mean_square([block_error(image[:h, :w], theirs[:h, :w], BLOCK) for image in images])
                report.add(f"image {integrator}: {BLOCK}x{BLOCK}-block error vs Mitsuba {reference_spp} "
                           f"spp (ours / Mitsuba at {spp} spp)", _fmt(blocks(ours)), _fmt(blocks(same_spp)))
            # Within 1 %, or, where Monte Carlo noise alone exceeds that (Mitsuba's own error
            # at the same spp), within that noise (10 % margin for the spread of the estimate).
            allowed = max(TOLERANCES["image_rel_rmse"], TOLERANCES["image_noise_margin"] * floor)
            if rel_rmse > allowed:
                report.failures.append(f"{integrator} relative RMSE {rel_rmse:.4f} > {allowed:.4f} "
                                       f"(1 %, or 1.1x Mitsuba's own {floor:.4f} at {spp} spp)")
        if out_dir is not None:
            diff = ours[0] - theirs
            write_exr(out_dir / f"diff_{integrator}.exr", diff)
            if diff.shape[-1] in (1, 3, 4):
                write_png(out_dir / f"diff_{integrator}.png", np.abs(diff) / max(np.abs(diff).max(), 1e-12))


def crosscheck(scene: Scene, *, random_rays: int = 1 << 20, reference_rays: int = 20_000,
               integrators=("aov", "direct", "path"), spp: int = 1024, reference_spp: int = 4096,
               out_dir: str | Path | None = None, seed: int = 0,
               source: str | Path | dict | None = None, repeats: int = 1) -> CrosscheckReport:
    """Run both renderers on ``scene`` and measure their agreement.

    Args:
        scene: a loaded scene (images need its camera).
        random_rays: random rays through the scene's bounds (plus one per pixel).
        reference_rays: rays also intersected by the float64 reference (brute force).
        integrators: images to compare; empty for rays only.
        spp, reference_spp: our samples per pixel and Mitsuba's.
        out_dir: where to write disagreements (npz) and difference images (EXR, PNG).
        seed: random seed of the rays.
        source: the file or dict the scene was loaded from; when given, errors are also
            measured against its float64 transforms (the built scene holds their float32
            rounding, the reference for the tolerances on the error tails).
        repeats: renders per renderer at ``spp`` (``direct`` and ``path``), the image
            errors being their root mean square over them.

    Returns:
        A :class:`CrosscheckReport`; ``report.failures`` is empty when every tolerance holds.
    """
    if repeats < 1:
        raise ValueError(f"crosscheck: repeats must be at least 1, got {repeats}")
    for model in scene.description.models:
        if model.grid is not None and model.grid.values.shape[0] != model.grid.values.shape[2]:
            nz, ny, nx = model.grid.values.shape
            raise SceneError(f"crosscheck: SDF grid model {model.name!r} has {nx} x {ny} x {nz} values; "
                             "Mitsuba 3.9.1 finds no hit on a grid whose x and z counts differ (its "
                             "voxel sizes read the axes swapped), so the comparison would measure that")
    report = CrosscheckReport()
    out = Path(out_dir) if out_dir is not None else None
    given = None if source is None else parse_scene(source).transforms.to_world
    if out is not None:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise SceneError(f"crosscheck: cannot make the output folder {str(out)!r}: "
                             f"{err.strerror or err}") from None
    check_rays(scene, report, random_rays, reference_rays, seed, out, given)
    if integrators and scene.camera is not None:
        check_images(scene, report, integrators, spp, reference_spp, out, repeats)
    return report
