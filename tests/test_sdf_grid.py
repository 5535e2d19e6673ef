"""SDF grids (``instancing.models.sdf_grid``): hits, normals and derivatives against a float64
march of the interpolant and central differences, Mitsuba's ``sdfgrid`` on rays and in a
render, and the errors of bad grids."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import instancing
from instancing.core.backend import MITSUBA_VARIANT, Array3f, Float
from instancing.models.sdf_grid import SDFGridData, tight_boxes
from instancing.validation import reference
from scene_helpers import (angle_deg, assert_boundary_terms_refused, assert_hit_derivatives_match, assert_path_render_matches_mitsuba,
                           float32_exact, lamp_and_floor_scene, random_affine, turned_about_z)

import mitsuba as mi  # noqa: E402  (after instancing, which selects libLLVM)


def corner_grid(counts, field):
    """Values (nz, ny, nx) of ``field(x, y, z)`` at the grid's corners over [0, 1]^3."""
    nx, ny, nz = counts
    z, y, x = np.meshgrid(np.linspace(0, 1, nz), np.linspace(0, 1, ny), np.linspace(0, 1, nx),
                          indexing="ij")
    return field(x, y, z)


def torus(x, y, z, major=0.28, minor=0.11):
    x, y, z = x - 0.5, y - 0.5, z - 0.5
    return np.sqrt((np.sqrt(x * x + y * y) - major) ** 2 + z * z) - minor


def blobs(x, y, z):
    """A non-distance field: a smooth sum of bumps, its zero set several pieces."""
    return (0.35 - np.exp(-((x - 0.3) ** 2 + (y - 0.4) ** 2 + (z - 0.5) ** 2) / 0.03)
            - 0.8 * np.exp(-((x - 0.7) ** 2 + (y - 0.6) ** 2 + (z - 0.4) ** 2) / 0.02)
            + 0.1 * np.sin(9 * x) * np.cos(7 * y))


GRIDS = {"torus 24^3": ((24, 24, 24), torus), "torus 21x13x17": ((21, 13, 17), torus),
         "blobs 16x20x12": ((16, 20, 12), blobs)}


def write_vol(path, values, channels=1):
    """A Mitsuba volume grid file of ``values`` (nz, ny, nx[, channels])."""
    nz, ny, nx = values.shape[:3]
    with open(path, "wb") as f:
        f.write(b"VOL" + bytes([3]) + struct.pack("<iiiii", 1, nx, ny, nz, channels)
                + struct.pack("<6f", 0, 0, 0, 1, 1, 1) + np.asarray(values, "<f4").tobytes())
    return path


def grid_scene(values, to_world=None, normals="smooth", extra=None):
    instance = {"model": "g"} | ({} if to_world is None else {"to_world": np.asarray(to_world).tolist()})
    return instancing.load_scene({"models": {"g": {"type": "sdfgrid", "values": values,
                                                   "normals": normals}},
                                  "instances": [instance] + (extra or [])})


def rays_at_grid(rng, to_world, n):
    """Rays from all around the grid's instance, aimed into its box."""
    centre = (to_world @ [0.5, 0.5, 0.5, 1.0])[:3]
    size = np.linalg.norm(to_world[:3, :3], axis=0).max()
    o = centre + rng.normal(size=(n, 3)) * 2 * size
    d = centre + rng.uniform(-0.5, 0.5, (n, 3)) * size - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float32_exact(o), float32_exact(d)


def as_array3(x):
    return Array3f(*[Float(np.ascontiguousarray(x[:, k], np.float32)) for k in range(3)])


@pytest.mark.parametrize("grid", list(GRIDS))
@pytest.mark.parametrize("reflect", [False, True])
def test_hits_and_normals_match_a_float64_march_of_the_interpolant(grid, reflect):
    """Under a random affine map (rotation, shear, non-uniform scale; with a reflection),
    rays aimed at the grid: hit or miss as the reference's first sign change of the
    interpolant (bisected in float64) but for grazing rays, t to float32 precision, the
    geometric normal the gradient's inverse transpose."""
    counts, field = GRIDS[grid]
    values = corner_grid(counts, field).astype(np.float32)
    rng = np.random.default_rng(7)
    to_world = random_affine(rng, reflect=reflect)
    scene = grid_scene(values, to_world, normals="analytic")
    o, d = rays_at_grid(rng, to_world, 3000)
    hit = scene.intersect(as_array3(o), as_array3(d))
    t, n = np.asarray(hit.t, np.float64), np.asarray(hit.n, np.float64).T
    ref = reference.intersect_instances(
        reference.instance_list(["sdfgrid"], [scene.to_world[0]], [None], grids=[values]), o, d)
    ours_hit, ref_hit = np.isfinite(t), np.isfinite(ref["t"])
    assert ref_hit.sum() > 300
    assert (ours_hit != ref_hit).sum() <= 3
    both = ours_hit & ref_hit
    np.testing.assert_allclose(t[both], ref["t"][both], rtol=2e-6)
    assert np.quantile(angle_deg(n[both], ref["n"][both]), 0.999) < 0.01


@pytest.mark.parametrize("grid", list(GRIDS))
def test_tight_voxel_boxes_hold_the_voxels_zero_set(grid):
    """Every zero of the interpolant found on a 64^3 lattice of each voxel holding surface
    lies in the voxel's tight box (the box of its edges' crossings)."""
    counts, field = GRIDS[grid]
    grid = SDFGridData.checked(corner_grid(counts, field), True, "test")
    filled = np.argwhere(grid.occupied())[:, ::-1]  # (x, y, z) of the voxels holding surface
    s = grid.corners(filled[:: max(1, len(filled) // 60)]).astype(np.float64)
    # Brute force: a voxel whose corners share one sign holds no zero (nor one of zeros alone).
    everything = np.argwhere(np.ones(grid.occupied().shape, bool))[:, ::-1]
    all_corners = grid.corners(everything)
    mixed = ~((all_corners > 0).all(1) | (all_corners < 0).all(1) | (all_corners == 0).all(1))
    assert np.array_equal(mixed, grid.occupied().ravel())
    lo, hi = tight_boxes(s)
    u = np.linspace(0, 1, 64)
    x, y, z = np.meshgrid(u, u, u, indexing="ij")
    checked = 0
    for corners, box_lo, box_hi in zip(s, lo, hi):
        f = sum(corners[c] * (x if c & 1 else 1 - x) * (y if c & 2 else 1 - y) * (z if c & 4 else 1 - z)
                for c in range(8))
        # Sign changes between lattice neighbours: the zero set passes between them.
        for axis in range(3):
            a = np.take(f, range(63), axis=axis)
            b = np.take(f, range(1, 64), axis=axis)
            where = np.nonzero(a * b <= 0)
            points = np.stack([g[where] for g in (x, y, z)], axis=1)
            points[:, axis] += 0.5 / 63  # the middle of the lattice edge
            assert np.all(points >= box_lo - 1 / 63) and np.all(points <= box_hi + 1 / 63)
            checked += len(points)
    assert checked > 1000


def _mitsuba_rays(values, to_world, normals, o, d):
    mi.set_variant(MITSUBA_VARIANT)
    scene = mi.load_dict({"type": "scene", "g": {
        "type": "sdfgrid", "grid": mi.TensorXf(values[..., None]), "normals": normals,
        "to_world": mi.ScalarTransform4f(to_world.tolist())}})
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)),
                                      mi.Vector3f(*d.T.astype(np.float32))))
    t = np.asarray(si.t, np.float64)
    return (np.where(np.isfinite(t), t, np.inf), np.asarray(si.n, np.float64).T,
            np.asarray(si.sh_frame.n, np.float64).T)


@pytest.mark.parametrize("normals", ["smooth", "analytic"])
def test_hits_and_normals_match_mitsubas(normals):
    """Mitsuba's sdfgrid on the same rays: hits, t, geometric and shading normals (smooth:
    its blend of the eight voxels' gradients around the nearest corner). Its to_world here
    scales and translates: Mitsuba 3.9.1 bounds a plain grid's voxels by their transformed
    corners (wrong under rotation), and its grids with x and z counts that differ miss
    everything (their voxel sizes read the axes swapped; checked)."""
    values = corner_grid((20, 26, 20), torus).astype(np.float32)
    to_world = np.diag([2.0, 1.5, 1.0, 1.0])
    to_world[:3, 3] = [0.2, -0.1, 0.3]
    o, d = rays_at_grid(np.random.default_rng(3), to_world, 20_000)
    hit = grid_scene(values, to_world, normals).intersect(as_array3(o), as_array3(d))
    t, n, sn = (np.asarray(hit.t, np.float64), np.asarray(hit.n, np.float64).T,
                np.asarray(hit.sn, np.float64).T)
    t_mi, n_mi, sn_mi = _mitsuba_rays(values, to_world, normals, o, d)
    both = np.isfinite(t) & np.isfinite(t_mi)
    assert both.sum() > 3000
    assert (np.isfinite(t) != np.isfinite(t_mi)).sum() <= 2
    # Mitsuba refines its root to 1e-5 in the voxel's units.
    np.testing.assert_allclose(t[both], t_mi[both], rtol=2e-5)
    assert np.quantile(angle_deg(n[both], n_mi[both]), 0.999) < 0.01
    assert np.quantile(angle_deg(sn[both], sn_mi[both]), 0.999) < 0.01
    if normals == "smooth":
        # The smooth normals are not the geometric ones (else the test above proves nothing).
        assert np.median(angle_deg(sn[both], n[both])) > 0.1


def test_a_rotated_grid_instance_renders_as_mitsubas(tmp_path):
    """A grid instanced under a rotation, shear and scale above a floor, lit by an area lamp,
    `path`: image mean within 0.5 %, 8x8-pixel block means within 1.5 % of it (as the other
    render comparisons)."""
    vol = write_vol(tmp_path / "blobs.vol", corner_grid((20, 16, 20), blobs).astype(np.float32))
    to_world = [[1.6, 0.5, 0.2, -0.9], [-0.4, 1.5, 0.3, -0.8], [0.1, -0.3, 1.2, 0.1], [0, 0, 0, 1]]
    assert_path_render_matches_mitsuba(lamp_and_floor_scene(
        {"blobs": {"type": "sdfgrid", "filename": str(vol)}},
        {"red": {"type": "roughplastic", "diffuse_reflectance": [0.7, 0.2, 0.1]}},
        {"model": "blobs", "material": "red", "to_world": to_world}, [0, -6, 4]))


@pytest.mark.parametrize("which", ["tx", "angle"])
def test_hit_derivatives_match_central_differences(which):
    """d t / d param and d p / d param of hits on a grid instance, for a translation and a
    rotation angle, against central differences of the float64 reference (step 1e-4; the
    reference's bisection is exact to 1e-15, so the differences' own error is O(h^2))."""
    values = corner_grid((24, 24, 24), torus).astype(np.float32)
    base = np.diag([2.0, 2.0, 1.5, 1.0])
    o, d = rays_at_grid(np.random.default_rng(11), turned_about_z(20.0, 0.3, base), 300)
    assert_hit_derivatives_match(
        grid_scene(values, turned_about_z(20.0, 0.3, base)), base, which, o, d,
        lambda to_world: reference.intersect_instances(reference.instance_list(
            ["sdfgrid"], [to_world], [None], grids=[values]), o, d), 50)


def test_the_boundary_terms_refuse_a_scene_with_a_grid():
    """A grid has no curves to sample: sppp / sppi are refused by name while something
    moves; the interior terms (sppp=0, sppi=0) render."""
    values = corner_grid((16, 16, 16), torus).astype(np.float32)
    assert_boundary_terms_refused(("knot", {"type": "sdfgrid", "values": values}), [{"scale": 2}], [1, 1, 1])


GOOD = {"type": "sdfgrid", "values": corner_grid((8, 8, 8), torus).tolist()}


@pytest.mark.parametrize("spec, message", [
    (GOOD | {"filename": "x.vol"}, "either a 'filename'.*or 'values'"),
    ({"type": "sdfgrid"}, "either a 'filename'"),
    (GOOD | {"normals": "flat"}, "'normals' must be one of"),
    (GOOD | {"radius": 1}, r"unknown keys \['radius'\]"),
    ({"type": "sdfgrid", "values": [[["a", "b"], ["c", "d"]]] * 2}, "must be an array of numbers"),
    ({"type": "sdfgrid", "values": np.ones((2, 2, 1))}, "at least 2 x 2 x 2 values"),
    ({"type": "sdfgrid", "values": np.ones((3, 3, 3))}, "no voxel of the grid holds a surface"),
    ({"type": "sdfgrid", "values": np.zeros((3, 3, 3))}, "no voxel of the grid holds a surface"),
    ({"type": "sdfgrid", "values": np.where(np.arange(27).reshape(3, 3, 3) == 5, np.nan, -1.0)},
     "1 of the grid's values are not finite"),
    ({"type": "sdfgrid", "filename": "missing.vol"}, "missing.vol' not found"),
])
def test_bad_grid_models_are_refused_by_name(tmp_path, spec, message):
    with pytest.raises(instancing.SceneError, match=f"model 'g'.*{message}"):
        instancing.load_scene({"models": {"g": spec}, "instances": [{"model": "g"}]})


def test_a_colour_volume_and_an_emitting_grid_are_refused(tmp_path):
    colour = write_vol(tmp_path / "c.vol", np.zeros((4, 4, 4, 3), np.float32) - 1, channels=3)
    with pytest.raises(instancing.SceneError, match="model 'g'.*3 channels; an SDF grid reads 1"):
        instancing.load_scene({"models": {"g": {"type": "sdfgrid", "filename": str(colour)}},
                               "instances": [{"model": "g"}]})
    with pytest.raises(instancing.SceneError, match=r"instance #0 \('lamp'\).*is an sdfgrid, which cannot emit"):
        instancing.load_scene({"models": {"g": GOOD}, "instances": [
            {"id": "lamp", "model": "g", "emitter": {"type": "area", "radiance": 1}}]})


def test_mitsuba_files_with_grids_load_and_refuse_bad_ones(tmp_path):
    """An ``sdfgrid`` shape of a Mitsuba file, in a shapegroup and instanced, becomes one
    grid model; a bad ``normals`` and a missing file are named with their line."""
    write_vol(tmp_path / "t.vol", corner_grid((12, 12, 12), torus).astype(np.float32))
    shape = '<shape type="sdfgrid"><string name="filename" value="{}"/>{}</shape>'
    xml = ('<scene version="3.0.0"><shape type="shapegroup" id="g">{}</shape>'
           '<shape type="instance"><ref id="g"/><transform name="to_world"><rotate z="1" angle="30"/>'
           '</transform></shape></scene>')
    path = tmp_path / "scene.xml"
    path.write_text(xml.format(shape.format("t.vol", '<string name="normals" value="analytic"/>')))
    scene = instancing.load_scene(path)
    (model,) = scene.description.models
    assert model.type == "sdfgrid" and not model.grid.smooth and model.grid.values.shape == (12, 12, 12)
    path.write_text(xml.format(shape.format("t.vol", '<string name="normals" value="flat"/>')))
    with pytest.raises(instancing.SceneError, match=r"scene.xml:1.*normals 'flat' is not one of"):
        instancing.load_scene(path)
    path.write_text(xml.format(shape.format("none.vol", "")))
    with pytest.raises(instancing.SceneError, match=r"grid file 'none.vol' not found"):
        instancing.load_scene(path)


def test_crosscheck_refuses_a_grid_mitsuba_cannot_trace():
    """Mitsuba 3.9.1 finds no hit on a grid whose x and z counts differ: the cross-check
    says so instead of measuring it."""
    from instancing.validation.crosscheck import crosscheck
    scene = grid_scene(corner_grid((21, 13, 17), torus).astype(np.float32))
    with pytest.raises(instancing.SceneError, match=r"crosscheck: SDF grid model 'g' has 21 x 13 x 17 values"):
        crosscheck(scene, integrators=())
