"""Numerical stress suite: hard cases measured against float64 and beside Mitsuba 3.

Every case builds a small scene, traces float32-exact rays through our
``Scene`` and through Mitsuba's twin of it (``to_mitsuba``, shapegroups and
instances), and measures both against the float64 NumPy reference
(:mod:`instancing.validation.reference`):

* hit cases (instances far from the origin, tiny and huge scales, a nearly
  degenerate axis, shear with reflection, grazing rays, huge and tiny
  direction lengths): hit-point error in float32 ULP of |p - origin| (the
  scene's rendering space, :mod:`instancing.scene.rendering_space`; rays exact
  in float32 there; 99.9th percentile), relative t error, normal angle, normal orientation where the
  determinant is negative, and from every hit a reflection ray and a shadow
  ray: the rate of false self-intersections (the spawned ray finds the
  instance it leaves although float64 agrees it leaves the surface; every
  model here is convex from the side the ray leaves, so any such hit is false);
* gaps: two closed instances touching or a tiny gap apart: rays from inside
  one that pass through its surface (leaks), and shadow rays leaving a top
  face coplanar with the neighbour's that are wrongly blocked;
* transform chains: 1 000 composed random rotations (drift of T @ T^-1 from
  the identity and of the rotation from orthonormality), and points at
  infinity (w = 0) under far translations;
* placement: a sphere on a floor under a point light at the origin and 1e5 -
  1e7 from it, direct light through every pixel centre against a float64
  closed form: lit pixels within 3 %, and acne; and any loaded scene moved as a
  whole (:func:`moved_scene`), to render against itself where it was.

``run_suite`` returns :class:`StressRow` records; ``format_table`` prints them
with their targets (:data:`TARGETS`). ``python -m instancing stress`` and
``benchmarks/stress.py`` print the table.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.backend import (MITSUBA_VARIANT, Array3f, Array4f, Float, dr, rows_from_vectors,
                            vectors_from_rows)
from ..core.ray_offset import offset_origin
from ..core.transform import from_matrix, rotate, translate
from ..io.mesh_file import read_mesh
from ..io.mitsuba_export import to_mitsuba
from ..io.scene_file import load_scene
from ..materials.material import Material
from ..materials.texture import Texture
from ..rendering.integrators.direct import integrate_direct
from ..scene.description import InstanceMatrices, PointLight
from ..scene.scene import Scene
from . import reference
from .measures import angle_deg, quantile, ulp_error, ulp_spacing

#: The suite's mesh model (shipped with the package, so that an installed copy runs it).
MESH_FILE = Path(__file__).resolve().parent / "data" / "icosphere.obj"
#: Model kinds of the hit cases ("mesh" = the icosphere).
KINDS = ("sphere", "cube", "rectangle", "disk", "cylinder", "mesh")
#: Rays per model kind and case ("full": >= 1e6 spawned rays per hit case, also on the
#: degenerate axis, where fewer rays hit; "ci": the test suite's size).
SIZES = {"full": 240_000, "ci": 20_000}
#: Rays per gap case (leaks, wrongly blocked shadow rays) and per direction-length case
#: (which spawn ~1.5 rays per ray): at full size >= 1e6 rays (spawned rays) per case too.
LEAK_RAYS = {"full": 1_000_000, "ci": 20_000}
DIRECTION_RAYS = {"full": 720_000, "ci": 20_000}
#: Targets: measure -> bound (hit points within 4 ulp, no self-intersection, leak or wrong
#: block, normals oriented under reflection, float64 chains exact to 1e-6).
TARGETS = {"p ULP 99.9%": 4.0, "self-intersections": 0.0, "acne pixels": 0.0, "leaks": 0.0, "wrongly blocked": 0.0,
           "det<0 orientation ok": 1.0, "T T^-1 drift": 1e-6, "w=0 ULP max": 4.0}


@dataclass(frozen=True)
class StressRow:
    """One measure of one case: ours, Mitsuba's ('-' where not measured) and the target."""

    case: str
    measure: str
    ours: float
    mitsuba: float = float("nan")

    @property
    def target(self) -> float | None:
        return TARGETS.get(self.measure)

    @property
    def met(self) -> bool | None:
        """Whether ours meets the target (None: no target for this measure)."""
        if self.target is None:
            return None
        return self.ours >= self.target if self.measure == "det<0 orientation ok" else self.ours <= self.target


# -- scenes and their Mitsuba twins ---------------------------------------------------------------

def _scene(kinds, matrices) -> Scene:
    return load_scene({
        "models": {"ico": {"type": "obj", "filename": str(MESH_FILE)}},
        "instances": [{"model": "ico" if k == "mesh" else k, "to_world": np.asarray(m).tolist()}
                      for k, m in zip(kinds, matrices)]})


def _mitsuba_twin(scene: Scene):
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    return mi, mi.load_dict(to_mitsuba(scene, mode="instances"), optimize=False)


def _reference(kinds, matrices, o: np.ndarray, d: np.ndarray, stored: bool = False) -> dict:
    """Float64 hits of the rays on instances of ``kinds`` ("mesh": the icosphere) under
    ``matrices`` (float64), the mesh's vertices as given or, where ``stored``, rounded to
    float32 as the renderers store them."""
    mesh = read_mesh(MESH_FILE)
    instances = reference.instance_list(kinds, matrices, (mesh.vertices, mesh.faces),
                                        vertex_rounding=np.float32 if stored else np.float64)
    return reference.intersect_instances(instances, o, d)


def _trace(scene: Scene, o: np.ndarray, d: np.ndarray):
    """Our surface hits of float64 world rays: moved into the scene's rendering space in
    float64, then rounded (as :meth:`Scene.intersect` does with float64 rays); hit points
    in rendering space."""
    return scene.intersect_surface(vectors_from_rows(o - scene.origin), vectors_from_rows(d))


def _local(hits: dict, origin: np.ndarray) -> dict:
    """Reference hits with their points in rendering space (relative to ``origin``)."""
    return dict(hits, p=hits["p"] - origin)


# -- measures -------------------------------------------------------------------------------------

def _float64_rows(v) -> np.ndarray:
    return rows_from_vectors(v, np.float64)


def _q999(x: np.ndarray) -> float:
    return quantile(x, 0.999, empty=float("nan"))


def _hit_figures(t, p, n, instance, ref, ref_stored, negative_det, oriented) -> dict:
    """Hit-point, t and normal errors where both hit the same instance.

    ``ref`` is the float64 reference on the case's float64 transforms, ``ref_stored``
    on the same transforms rounded to float32 (what either renderer stores): the
    hit-point error against the latter leaves out the rounding of the scene itself.
    """
    same = np.isfinite(t) & np.isfinite(ref["t"]) & (instance == ref["instance"])
    dot = np.sum(n[same] * ref["n"][same], axis=1)
    flipped = negative_det[ref["instance"][same]]
    off = np.abs(np.sum((p[same] - ref["p"][same]) * ref["n"][same], axis=1))
    stored = np.isfinite(t) & np.isfinite(ref_stored["t"]) & (instance == ref_stored["instance"])
    return {"p ULP 99.9%": _q999(ulp_error(p[same], ref["p"][same])),
            "p ULP 99.9%, f32 scene": _q999(ulp_error(p[stored], ref_stored["p"][stored])),
            "p off-surface ULP 99.9%": _q999(off / ulp_spacing(ref["p"][same])),
            "rel t error 99.9%": _q999(np.abs(t[same] - ref["t"][same]) / ref["t"][same]),
            "normal error 99.9% (deg)": _q999(angle_deg(n[same], ref["n"][same], oriented)),
            "det<0 orientation ok": float(np.mean(dot[flipped] > 0)) if flipped.any() else float("nan")}


def _spawn_directions(d: np.ndarray, n: np.ndarray, rng: np.random.Generator):
    """Reflection directions and, on the same side, directions to random point lights."""
    side = -np.sign(np.sum(d * n, axis=1))[:, None] * n
    reflect = d - 2.0 * np.sum(d * n, axis=1)[:, None] * n
    u = rng.normal(size=d.shape)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    light = np.where(np.sum(u * side, axis=1)[:, None] > 0, u, -u)
    return reflect, light


def _truly_leaving(w: np.ndarray, d: np.ndarray, n: np.ndarray, n_ref: np.ndarray) -> np.ndarray:
    """Spawned directions that float64 agrees leave the surface to the incoming ray's side.

    A direction built from a normal that is off by more than the ray's angle to the
    surface (grazing hits) may really enter the model, and its re-hit is then real:
    such rays measure the normal error, not the offset, and are left out.
    """
    with np.errstate(invalid="ignore"):
        w_ref = np.sum(w * n_ref, axis=1)
        return (w_ref * np.sum(d * n_ref, axis=1) < 0) & (w_ref * np.sum(w * n, axis=1) > 0)


def _ours_self_hits(scene: Scene, hit, d_np: np.ndarray, n_ref: np.ndarray, rng) -> tuple[int, int]:
    """(false self-intersections, spawned rays) of reflection and shadow rays from our hits."""
    n_np = _float64_rows(hit.n)
    valid = np.asarray(hit.valid) & _leaves_outside(scene, np.asarray(hit.instance), d_np, n_np)
    reflect, light = _spawn_directions(d_np, n_np, rng)
    bad = count = 0
    for w_np, t_max in ((reflect, np.inf), (light, 1e3 * np.abs(_float64_rows(hit.p)).max(initial=1.0))):
        w = vectors_from_rows(w_np)
        origin = offset_origin(hit.p, hit.n, hit.error, w)
        leaving = valid & _truly_leaving(w_np, d_np, n_np, n_ref)
        found = scene.intersect_preliminary(origin, w, valid, t_max)
        bad += int(np.sum(leaving & (np.asarray(found.instance) == np.asarray(hit.instance))))
        count += int(leaving.sum())
    return bad, count


def _mitsuba_self_hits(mi, mscene, si, d_np, n_ref, scene, rng) -> tuple[int, int]:
    """The same measure with Mitsuba's own ``spawn_ray`` (single-instance scenes: any hit is a self-hit)."""
    n_np = _float64_rows(si.n)
    valid = np.asarray(si.is_valid()) & _leaves_outside(scene, np.zeros(len(d_np), int), d_np, n_np)
    reflect, light = _spawn_directions(d_np, n_np, rng)
    bad = count = 0
    for w_np in (reflect, light):
        leaving = valid & _truly_leaving(w_np, d_np, n_np, n_ref)
        again = mscene.ray_intersect(si.spawn_ray(mi.Vector3f(vectors_from_rows(w_np))))
        bad += int(np.sum(leaving & np.asarray(again.is_valid())))
        count += int(leaving.sum())
    return bad, count


def _leaves_outside(scene: Scene, instance: np.ndarray, d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Hits from which every ray leaving on the ray's side is outside the (convex) model:
    front hits of the closed models and the cylinder, either side of the flat ones (a ray
    that starts inside a closed model legitimately meets it again after reflection)."""
    desc = scene.description
    kind = np.array([desc.models[i].kind for i in desc.instance_model])[np.maximum(instance, 0)]
    return np.isin(kind, ["rectangle", "disk"]) | (np.sum(d * n, axis=1) < 0)


def hit_case(name: str, kinds, matrices, o: np.ndarray, d: np.ndarray, seed: int,
             spawn: bool = True, mitsuba: bool = True) -> list[StressRow]:
    """Measure one hit case (see the module docstring) for ours and Mitsuba."""
    scene = _scene(kinds, matrices)
    # Rays that float32 holds exactly in the scene's rendering space (at the world origin:
    # in world space), so that the figures measure the intersection, not the input's rounding.
    origin = scene.origin
    o = origin + (o - origin).astype(np.float32).astype(np.float64)
    d = d.astype(np.float32).astype(np.float64)
    negative_det = np.linalg.det(np.asarray(matrices)[:, :3, :3]) < 0
    # Hit points are measured in the rendering space (ulps of |p - origin|), where
    # float32 precision follows the distance from the camera or the scene's centre.
    ref = _local(_reference(kinds, matrices, o, d), origin)
    ref_stored = _local(_reference(kinds, scene.to_world, o, d, stored=True), origin)
    hit = _trace(scene, o, d)
    ours = _hit_figures(np.asarray(hit.t, np.float64), _float64_rows(hit.p), _float64_rows(hit.n),
                        np.asarray(hit.instance), ref, ref_stored, negative_det, True)
    theirs = dict.fromkeys(ours, float("nan"))
    if spawn:
        bad, count = _ours_self_hits(scene, hit, d, ref["n"], np.random.default_rng(seed))
        ours["self-intersections"], ours["spawned rays"] = bad / max(count, 1), count
        theirs["self-intersections"] = theirs["spawned rays"] = float("nan")
    if mitsuba and len(kinds) == 1:
        mi, mscene = _mitsuba_twin(scene)
        si = mscene.ray_intersect(mi.Ray3f(mi.Point3f(vectors_from_rows(o)), mi.Vector3f(vectors_from_rows(d))))
        t_mi = np.asarray(si.t, np.float64)
        # Mitsuba's figures come from single-instance cases: its instance is 0.
        inst_mi = np.where(np.isfinite(t_mi), 0, -1)
        # Mitsuba flips some normals under reflection: angles up to sign, orientation apart.
        theirs.update(_hit_figures(np.where(np.isfinite(t_mi), t_mi, np.inf),
                                   _float64_rows(si.p) - origin, _float64_rows(si.n),
                                   inst_mi, ref, ref_stored, negative_det, False))
        if spawn:
            bad, count = _mitsuba_self_hits(mi, mscene, si, d, ref["n"], scene, np.random.default_rng(seed))
            theirs["self-intersections"], theirs["spawned rays"] = bad / max(count, 1), count
    return [StressRow(name, k, v, theirs[k]) for k, v in ours.items() if not np.isnan(v)]


def _rays_at(rng, centres: np.ndarray, radius: float, distance: float, count: int):
    """Rays from random points ``distance`` from a random centre, aimed into its ball."""
    c = centres[rng.integers(0, len(centres), count)]
    u = rng.normal(size=(count, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    o = c + distance * u
    aim = c + radius * rng.uniform(-0.8, 0.8, (count, 3))
    return o, aim - o


def _placed(rng, kind_count: int, scale: float, centre: np.ndarray, spacing: float,
            linear=None) -> tuple[np.ndarray, np.ndarray]:
    """(matrices, centres): random rotations times ``scale`` (or ``linear``), in a row."""
    mats, centres = [], []
    for i in range(kind_count):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        m = np.eye(4)
        m[:3, :3] = q * scale if linear is None else q @ linear
        m[:3, 3] = centre + np.array([spacing * (i - kind_count / 2), 0.0, 0.0])
        mats.append(m)
        centres.append(m[:3, 3])
    return np.array(mats), np.array(centres)


def per_kind_cases(name: str, rng, count: int, scale: float, centre, linear=None,
                   distance: float = 4.0, kinds=KINDS, mitsuba: bool = True) -> list[StressRow]:
    """One hit case per model kind (so that Mitsuba's figures are per instance too), merged."""
    rows = []
    for kind in kinds:
        mats, centres = _placed(rng, 1, scale, np.asarray(centre, float), 0.0, linear)
        o, d = _rays_at(rng, centres, scale, distance * scale, count)
        rows += hit_case(f"{name} {kind}", [kind], mats, o, d, seed=int(rng.integers(1 << 31)),
                         mitsuba=mitsuba)
    return _merge(name, rows)


def _merge(name: str, rows: list[StressRow]) -> list[StressRow]:
    """Worst figure over the kinds of one case (rates: summed counts)."""
    out = []
    for measure in dict.fromkeys(r.measure for r in rows):
        sel = [r for r in rows if r.measure == measure]
        pick = min if measure == "det<0 orientation ok" else max
        if measure in ("self-intersections", "spawned rays"):
            pick = _mean_rate if measure == "self-intersections" else sum
        out.append(StressRow(name, measure, _reduce(pick, [r.ours for r in sel]),
                             _reduce(pick, [r.mitsuba for r in sel])))
    return out


def _mean_rate(values):
    return float(np.mean(values))


def _reduce(fn, values) -> float:
    values = [v for v in values if not np.isnan(v)]
    return float(fn(values)) if values else float("nan")


def grazing_case(rng, count: int, angle: float) -> list[StressRow]:
    """Rays meeting the surface at ``angle`` radians, per convex model kind."""
    rows = []
    mesh = read_mesh(MESH_FILE)
    for kind in KINDS:
        # A surface point q, its normal, and a tangent direction, in object space.
        if kind == "sphere":
            q = rng.normal(size=(count, 3))
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            nrm = q
        elif kind == "cylinder":
            phi = rng.uniform(0, 2 * np.pi, count)
            nrm = np.column_stack([np.cos(phi), np.sin(phi), np.zeros(count)])
            q = nrm + np.column_stack([np.zeros((count, 2)), rng.uniform(0.3, 0.7, count)])
        elif kind == "mesh":
            f = rng.integers(0, len(mesh.faces), count)
            v = mesh.vertices[mesh.faces[f]].astype(np.float32).astype(np.float64)
            b = rng.dirichlet([4, 4, 4], count)
            q = np.einsum("nk,nkj->nj", b, v)
            nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        else:
            q = np.column_stack([rng.uniform(-0.5, 0.5, (count, 2)), np.zeros(count)])
            nrm = np.tile([0.0, 0.0, 1.0], (count, 1))
            if kind == "cube":
                q[:, 2] = 1.0
        tangent = np.cross(nrm, rng.normal(size=(count, 3)))
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        d_obj = np.cos(angle) * tangent - np.sin(angle) * nrm
        # A similarity keeps the angle: rotation, scale 1.5, translation.
        mats, _ = _placed(rng, 1, 1.5, rng.uniform(-3, 3, 3), 0.0)
        m = mats[0]
        o = (q - 2.0 * d_obj) @ m[:3, :3].T + m[:3, 3]
        rows += hit_case(f"grazing {kind}", [kind], mats, o, d_obj @ m[:3, :3].T,
                         seed=int(rng.integers(1 << 31)))
    return _merge(f"grazing {angle:g} rad", rows)


def gap_case(rng, count: int, kind: str, gap: float, mitsuba: bool = True) -> list[StressRow]:
    """Two closed instances of size 2 side by side along x, ``gap`` apart (relative to size).

    Leaks: rays from inside the first whose first hit lies beyond its surface
    (float64 says the other instance is farther, or nothing is hit). Wrongly
    blocked: shadow rays leaving the first's top face (coplanar with the
    second's) upwards, grazing down to 1e-4 rad: nothing lies above.
    """
    shift = 2.0 + 2.0 * gap
    mats = np.array([np.eye(4), np.eye(4)])
    mats[1, 0, 3] = shift
    scene = _scene([kind, kind], mats)
    # Leaks: origins inside the first instance (within 0.9 of its size), random directions.
    o = rng.uniform(-0.9, 0.9, (count, 3)) * (0.55 if kind == "mesh" else 1.0)
    d = rng.normal(size=(count, 3))
    # Half the rays head for the neighbour.
    d[: count // 2, 0] = np.abs(d[: count // 2, 0]) * 4.0
    o, d = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    first, second = (reference.intersect_instances([{"kind": kind, "to_world": m, "mesh": _mesh_data(kind)}],
                                                   o, d) for m in mats)
    truly_behind = second["t"] > first["t"] * (1 + 1e-12)
    hit = _trace(scene, o, d)
    case = f"gap {gap:g} {kind}"
    ours_leak = _leak_rate(np.asarray(hit.instance), truly_behind)
    if not mitsuba:
        rows = [StressRow(case, "leaks", ours_leak), StressRow(case, "rays", count)]
        return rows + ([_blocked_row(rng, count, scene, None, None, case)] if kind == "cube" else [])
    mi, mscene = _mitsuba_twin(scene)
    si = mscene.ray_intersect(mi.Ray3f(mi.Point3f(vectors_from_rows(o)), mi.Vector3f(vectors_from_rows(d))))
    rows = [StressRow(case, "leaks", ours_leak, _leak_rate(_mitsuba_instance(mi, mscene, si), truly_behind)),
            StressRow(case, "rays", count, count)]
    if kind == "cube":
        rows.append(_blocked_row(rng, count, scene, mi, mscene, case))
    return rows


def _mesh_data(kind: str):
    if kind != "mesh":
        return None
    mesh = read_mesh(MESH_FILE)
    return mesh.vertices, mesh.faces


def _leak_rate(instance: np.ndarray, truly_behind: np.ndarray) -> float:
    leak = (instance < 0) | ((instance == 1) & truly_behind)
    return float(np.mean(leak))


def _mitsuba_instance(mi, mscene, si) -> np.ndarray:
    """Our instance index of Mitsuba's hits (-1 on a miss)."""
    pointer = np.asarray(dr.reinterpret_array(mi.UInt32, si.instance))
    ids = {int(np.asarray(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s)))[0]): int(s.id().split("_")[1])
           for s in mscene.shapes() if s.id().startswith("instance_")}
    return np.where(np.asarray(si.is_valid()), [ids.get(int(p), -1) for p in pointer], -1)


def _blocked_row(rng, count, scene, mi, mscene, case) -> StressRow:
    """Shadow rays from the first cube's top face (z = 1) upwards: any blocker is wrong
    (Mitsuba's figure too unless ``mi`` is None)."""
    o = np.column_stack([rng.uniform(-1, 1, (count, 2)), np.full(count, 3.0)])
    # Hit points spread up to the shared edge at x = 1.
    o[:, 0] = 1.0 - np.abs(o[:, 0]) ** 4
    d = np.tile([0.0, 0.0, -1.0], (count, 1))
    elevation = np.exp(rng.uniform(np.log(1e-4), np.log(np.pi / 2), count))
    azimuth = rng.uniform(-np.pi / 2, np.pi / 2, count)  # towards the neighbour
    w = np.column_stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                         np.sin(elevation)]).astype(np.float32).astype(np.float64)
    hit = _trace(scene, o, d)
    origin = offset_origin(hit.p, hit.n, hit.error, vectors_from_rows(w))
    ours = float(np.mean(np.asarray(hit.valid) & np.asarray(scene.occluded(origin, vectors_from_rows(w), Float(dr.inf)))))
    if mi is None:
        return StressRow(case, "wrongly blocked", ours)
    si = mscene.ray_intersect(mi.Ray3f(mi.Point3f(vectors_from_rows(o)), mi.Vector3f(vectors_from_rows(d))))
    blocked = mscene.ray_test(si.spawn_ray(mi.Vector3f(vectors_from_rows(w))))
    theirs = float(np.mean(np.asarray(si.is_valid()) & np.asarray(blocked)))
    return StressRow(case, "wrongly blocked", ours, theirs)


def composition_rows(rng, count: int = 1000) -> list[StressRow]:
    """1 000 composed random rotations: float64 set-up transforms, float32 per-lane ones, Mitsuba's."""
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    axes = rng.normal(size=(count, 3))
    # Unit axes: Mitsuba's rotate does not normalize its axis.
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(-180, 180, count)
    scalar = rotate(axes[0], angles[0])
    lanes = scalar.to_lanes()
    mit = mi.ScalarTransform4f().rotate(axes[0].tolist(), float(angles[0]))
    for a, g in zip(axes[1:], angles[1:]):
        step = rotate(a, g)
        scalar, lanes = scalar @ step, lanes @ step.to_lanes()
        mit = mit @ mi.ScalarTransform4f().rotate(a.tolist(), float(g))

    def drift(m, inv):
        return float(np.abs(m @ inv - np.eye(4)).max()), float(np.abs(m[:3, :3] @ m[:3, :3].T - np.eye(3)).max())

    ours64 = drift(*scalar.to_numpy())
    m32, inv32 = (x[0] for x in lanes.to_numpy())
    ours32 = drift(m32, inv32)
    theirs = drift(np.array(mit.matrix, np.float64), np.array(mit.inverse_transpose, np.float64).T)
    return [StressRow("1000 rotations, float64", "T T^-1 drift", ours64[0], theirs[0]),
            StressRow("1000 rotations, float64", "orthonormality drift", ours64[1], theirs[1]),
            StressRow("1000 rotations, float32 lanes", "T T^-1 drift", ours32[0], theirs[0]),
            StressRow("1000 rotations, float32 lanes", "orthonormality drift", ours32[1], theirs[1])]


def infinity_rows(rng, count: int) -> list[StressRow]:
    """Points at infinity (w = 0) under far translations: mapped as directions, to the ULP."""
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    m = np.eye(4)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    m[:3, :3] = q * 3.0
    m[:3, 3] = [1e6, -1e5, 1e4]
    v = rng.normal(size=(count, 3)).astype(np.float32).astype(np.float64)
    out = from_matrix(m).to_lanes().apply_homogeneous(Array4f(*[Float(v[:, k]) for k in range(3)], 0.0))
    ours = _float64_rows(Array3f(out.x, out.y, out.z))
    exact = v @ m[:3, :3].astype(np.float32).astype(np.float64).T
    theirs = _float64_rows(mi.Transform4f(m.tolist()) @ mi.Vector3f(vectors_from_rows(v)))
    return [StressRow("w=0 under translation 1e6", "w=0 ULP max", float(ulp_error(ours, exact).max()),
                      float(ulp_error(theirs, exact).max()))]


# -- placement: one scene at the origin and far from it ------------------------------------------

#: The placement case's moves: a direction off the axes times the distance, plus an offset no
#: power of two divides (so the float32 data differ from those at the origin).
PLACEMENT_DIRECTION = np.array([0.6, -0.48, 0.64])
PLACEMENT_SKEW = np.array([0.3711, -0.1234, 0.5678])
_ALBEDO, _INTENSITY, _LIGHT = 0.6, 40.0, np.array([2.0, -1.0, 5.0])


def placement(distance: float) -> np.ndarray:
    """Where the placement case's scene sits at ``distance`` from the world origin."""
    return distance * PLACEMENT_DIRECTION + (PLACEMENT_SKEW if distance else 0.0)


def ball_on_floor(at: np.ndarray, width: int = 96, height: int = 72) -> dict:
    """A unit sphere resting on a 20 x 20 floor under a point light, seen from above at an
    angle; everything moved by ``at``."""
    return {
        "materials": {"grey": {"type": "diffuse", "reflectance": _ALBEDO}},
        "instances": [
            {"id": "floor", "model": "rectangle", "material": "grey",
             "to_world": [{"translate": at.tolist()}, {"scale": 10.0}]},
            {"id": "ball", "model": "sphere", "material": "grey",
             "to_world": [{"translate": (at + [0, 0, 1.0]).tolist()}]}],
        "camera": {"type": "perspective", "fov": 40, "width": width, "height": height,
                   "to_world": [{"look_at": {"origin": (at + [0, -7, 4]).tolist(),
                                             "target": (at + [0, 0, 0.8]).tolist(),
                                             "up": [0, 0, 1]}}]},
        "lights": [{"type": "point", "position": (at + _LIGHT).tolist(), "intensity": _INTENSITY}]}


def moved_scene(scene: Scene, offset) -> Scene:
    """``scene`` with everything in it translated by ``offset`` (3 numbers, float64): its
    instances, cameras, point, spot and projector lights, and the grids of its volume
    textures (media and materials). Directions (directional lights, environments, spot
    axes) and surface textures do not move. Rendered with the same seed, the moved scene
    gives the image of the original up to rounding wherever the rendering space keeps
    its precision (``tests/test_rendering_space.py``)."""
    offset = np.asarray(offset, np.float64)
    ahead, back = np.eye(4), np.eye(4)
    ahead[:3, 3], back[:3, 3] = offset, -offset

    def texture(value):
        # A volume grid's map from world points to its unit cube follows the move.
        if isinstance(value, Texture) and value.to_local is not None:
            return dataclasses.replace(value, to_local=value.to_local @ back)
        return value

    def material(m: Material | None) -> Material | None:
        if m is None:
            return None
        return dataclasses.replace(m, values={k: texture(v) for k, v in m.values.items()},
                                   back=material(m.back),
                                   parts=None if m.parts is None else tuple(material(p) for p in m.parts))

    desc = scene.description
    return Scene(dataclasses.replace(
        desc, transforms=InstanceMatrices(ahead @ scene.to_world, scene.from_world @ back),
        cameras=tuple(dataclasses.replace(c, world_from_camera=translate(offset.tolist())
                                          @ c.world_from_camera) for c in desc.cameras),
        lights=tuple(dataclasses.replace(light, position=tuple((np.asarray(light.position) + offset).tolist()))
                     if isinstance(light, PointLight) else light for light in desc.lights),
        media={k: dataclasses.replace(m, sigma_t=texture(m.sigma_t), albedo=texture(m.albedo))
               for k, m in desc.media.items()},
        materials={name: material(m) for name, m in desc.materials.items()}))


def ball_on_floor_radiance(at: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float64 closed form of :func:`ball_on_floor`'s direct light along world rays: the
    radiance, and a mask of rays to leave out (shadow rays within 1e-4 of the sphere's
    silhouette, rays grazing the sphere, points lit at a grazing angle)."""
    centre, light = at + [0, 0, 1.0], at + _LIGHT
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    oc = o - centre
    b = np.sum(oc * d, axis=1)
    disc = b * b - (np.sum(oc * oc, axis=1) - 1.0)
    t_ball = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    t_ball = np.where(t_ball > 0, t_ball, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = (at[2] - o[:, 2]) / d[:, 2]
    q = o + np.where(np.isfinite(t_floor), t_floor, 0.0)[:, None] * d
    inside = (np.abs(q[:, 0] - at[0]) <= 10) & (np.abs(q[:, 1] - at[1]) <= 10) & (t_floor > 0)
    t_floor = np.where(inside, t_floor, np.inf)
    t = np.minimum(t_ball, t_floor)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    on_floor = t_floor < t_ball
    n = np.where(on_floor[:, None], [0.0, 0.0, 1.0], p - centre)
    to_light = light - p
    r2 = np.sum(to_light ** 2, axis=1)
    w = to_light / np.sqrt(r2)[:, None]
    cos = np.sum(n * w, axis=1)
    # The sphere's shadow on the floor: the segment p -> light passes within 1 of the centre.
    rel = centre - p
    along = np.clip(np.sum(rel * w, axis=1), 0, np.sqrt(r2))
    gap = np.linalg.norm(rel - along[:, None] * w, axis=1) - 1.0
    shadowed = on_floor & (gap < 0)
    radiance = np.where(np.isfinite(t) & ~shadowed & (cos > 0),
                        _ALBEDO / np.pi * _INTENSITY * cos / r2, 0.0)
    edge = (on_floor & (np.abs(gap) < 1e-4)) | (np.abs(disc) < 1e-6) | (np.abs(cos) < 1e-4)
    return radiance, edge


def _agreement(radiance: np.ndarray, expected: np.ndarray, edge: np.ndarray) -> tuple[float, int]:
    """(fraction of lit rays within 3 % of the closed form, acne: lit rays rendered black)."""
    lit = (expected > 0) & ~edge
    within = np.abs(radiance[lit] - expected[lit]) <= 0.03 * expected[lit]
    return float(within.mean()), int(np.sum(radiance[lit] == 0))


def placement_rows(distances=(0.0, 1e5, 1e6, 1e7), width: int = 192, height: int = 144,
                   mitsuba: bool = True) -> list[StressRow]:
    """The ball on the floor at each distance from the origin, one ray through each pixel
    centre: the fraction of lit pixels within 3 % of the float64 closed form along the same
    rays, and the acne pixels (lit by float64, black in the render). Ours traces in the
    scene's rendering space; Mitsuba, in world space, gets the float32 world rays (its
    reference follows those rays)."""
    rows = []
    for distance in distances:
        at = placement(distance)
        scene = load_scene(ball_on_floor(at, width, height))
        fraction, acne = placement_figures(scene, at)
        theirs = (float("nan"), float("nan"))
        if mitsuba:
            o, d = scene.view().pixel_centre_rays()
            theirs = _mitsuba_placement(scene, at, rows_from_vectors(o, np.float64) + scene.origin,
                                        rows_from_vectors(d, np.float64))
        case = f"placement {distance:g}"
        rows += [StressRow(case, "lit within 3 %", fraction, theirs[0]),
                 StressRow(case, "acne pixels", acne, theirs[1])]
    return rows


def placement_figures(scene: Scene, at: np.ndarray, camera: int | str = 0) -> tuple[float, int]:
    """(fraction of lit pixels within 3 % of the closed form, acne pixels) of
    :func:`ball_on_floor` at ``at`` through one ray per pixel centre of ``camera``."""
    o, d = scene.view(camera).pixel_centre_rays()
    o_world = rows_from_vectors(o, np.float64) + scene.origin
    ours = np.asarray(integrate_direct(scene, scene.light_set(), o, d, None).x, np.float64)
    return _agreement(ours, *ball_on_floor_radiance(at, o_world, rows_from_vectors(d, np.float64)))


def _mitsuba_placement(scene: Scene, at: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[float, int]:
    """Mitsuba's figures for :func:`placement_rows`: its hits of the float32 world rays, lit
    by the point light where its shadow ray (``spawn_ray_to``) reaches the light."""
    mi, mscene = _mitsuba_twin(scene)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    si = mscene.ray_intersect(mi.Ray3f(mi.Point3f(vectors_from_rows(o32)), mi.Vector3f(vectors_from_rows(d32))))
    light = at + _LIGHT
    p, n = _float64_rows(si.p), _float64_rows(si.n)
    to_light = light.astype(np.float32).astype(np.float64) - p
    r2 = np.sum(to_light ** 2, axis=1)
    cos = np.sum(n * to_light, axis=1) / np.sqrt(r2)
    blocked = np.asarray(mscene.ray_test(si.spawn_ray_to(mi.Point3f(*[float(c) for c in light]))))
    valid = np.asarray(si.is_valid())
    radiance = np.where(valid & ~blocked & (cos > 0), _ALBEDO / np.pi * _INTENSITY * cos / r2, 0.0)
    return _agreement(radiance, *ball_on_floor_radiance(at, o32.astype(np.float64), d32.astype(np.float64)))


def run_suite(size: str = "full", seed: int = 0, progress=None,
              cases: tuple[str, ...] = ()) -> list[StressRow]:
    """All cases at ``size`` ('full' or 'ci', see SIZES), or those whose names start with
    one of ``cases``; ``progress(name)`` before each case."""
    count = SIZES[size]
    rng = np.random.default_rng(seed)
    rows: list[StressRow] = []
    plan = [(f"far {t:g}", lambda t=t: per_kind_cases(f"far {t:g}", rng, count, 1.0,
                                                       t * np.array([0.6, -0.48, 0.64])))
            for t in (0.0, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7)]
    # Scaled instances sit off the origin (at 3.2 sizes): near the origin the ULP of |p|
    # vanishes and would measure the absolute error of a point against 0.
    plan += [(f"scale {s:g}", lambda s=s: per_kind_cases(f"scale {s:g}", rng, count, s,
                                                         s * np.array([2.0, -1.5, 2.0])))
             for s in (1e-4, 1e-2, 1e2, 1e4)]
    plan += [("degenerate 1e-6", lambda: per_kind_cases("degenerate axis 1e-6", rng, count, 1.0, [3, 1, 2],
                                                        linear=np.diag([1.0, 1.0, 1e-6]))),
             ("shear + reflection", lambda: per_kind_cases(
                 "shear + reflection", rng, count, 1.0, [2, -1, 3],
                 linear=np.array([[-1.0, 0.9, 0.5], [0.0, 1.2, -0.8], [0.0, 0.0, 0.7]])))]
    plan += [(f"grazing {a:g}", lambda a=a: grazing_case(rng, count, a)) for a in (1e-1, 1e-2, 1e-3, 1e-4)]
    plan += [(f"|d| {s:g}", lambda s=s: direction_length_case(rng, DIRECTION_RAYS[size], s))
             for s in (1e-12, 1e-4, 1e4, 1e12)]
    plan += [(f"gap {g:g} {k}", lambda g=g, k=k: gap_case(rng, LEAK_RAYS[size], k, g))
             for k in ("cube", "mesh") for g in (0.0, 1e-6, 1e-4, 1e-2)]
    plan += [("composition", lambda: composition_rows(rng)), ("w = 0", lambda: infinity_rows(rng, count))]
    plan += [("placement", lambda: placement_rows())]
    for name, case in plan:
        if cases and not name.startswith(tuple(cases)):
            continue
        if progress is not None:
            progress(name)
        rows += case()
    return rows


def direction_length_case(rng, count: int, length: float) -> list[StressRow]:
    """Rays whose direction has length ``length`` (t in its units), one scene of every kind."""
    # 12 apart: no instance overlaps another or holds another's ray origins.
    mats, centres = _placed(rng, len(KINDS), 1.0, np.array([1.0, 2.0, -1.0]), 12.0)
    o, d = _rays_at(rng, centres, 1.0, 5.0, count)
    d = d / np.linalg.norm(d, axis=1, keepdims=True) * length
    return hit_case(f"|d| = {length:g}", list(KINDS), mats, o, d, seed=int(rng.integers(1 << 31)),
                    mitsuba=False)


def format_table(rows: list[StressRow]) -> str:
    """The suite's table: one line per (case, measure), ours beside Mitsuba's, target and verdict."""
    width = max(len(r.case) for r in rows) + 2
    lines = [f"{'case':<{width}}{'measure':<26}{'ours':>12}{'Mitsuba':>12}{'target':>10}  met"]
    for r in rows:
        target = "" if r.target is None else (f">= {r.target:g}" if r.measure == "det<0 orientation ok"
                                              else f"<= {r.target:g}")
        verdict = "" if r.met is None else ("yes" if r.met else "NO")
        lines.append(f"{r.case:<{width}}{r.measure:<26}{_fmt(r.ours):>12}{_fmt(r.mitsuba):>12}"
                     f"{target:>10}  {verdict}")
    return "\n".join(lines)


def _fmt(x: float) -> str:
    return "-" if np.isnan(x) else f"{x:.3g}"
