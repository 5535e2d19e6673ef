"""Tests of :mod:`instancing.scene.camera` against Mitsuba 3's ``perspective`` sensor.

The claim under test: a camera description (fov along x, film width and
height, ``to_world``) gives the same rays in both systems, so the same camera
renders the same picture. For each camera below we build the Mitsuba twin with
Mitsuba's own transform builders (``ScalarTransform4f().translate(..)
.rotate(..).look_at(..)``, never our matrices) and compare
``PerspectiveCamera.rays(u, v)`` with ``Sensor.sample_ray(time, sample1,
sample2=(u, v), sample3)``. Mitsuba documents ``sample2`` as "the sample
position in fractional pixel coordinates relative to the crop window of the
underlying film": with no crop window that is the film position in [0, 1]^2,
the meaning of our (u, v). ``sample3`` (aperture position) is ignored by the
pinhole ``perspective`` sensor.

What Mitsuba does differently, measured here and accounted for below:

* Mitsuba starts its rays on the near clip plane (``near_clip``, default 0.01):
  ray.o = camera position + d * near_clip / d_z, with d_z the cosine between
  the ray and the viewing axis. Ours start at the camera position (no near
  clip), so we compare Mitsuba's origin with ``o + near_clip / dot(d, forward) * d``.
* Mitsuba's ``ScalarTransform4f.rotate`` expects a unit axis (a non-unit axis
  gives a scaled matrix, which the sensor then refuses with "Scale factors in
  the camera-to-world transformation are not allowed!"); our ``rotate`` operation
  normalises its axis. The Mitsuba twins are therefore given unit axes.
* Mitsuba refuses any scale in a sensor's ``to_world``; so does ours, and
  shear too (``test_scale_or_shear_in_to_world_is_rejected_like_mitsuba``).

Tolerances:
* directions: 1e-4 degrees (1.7e-6 rad). Both sides work in float32 (epsilon
  6e-8); Mitsuba goes through its float32 sample-to-camera projective matrix,
  we through tan(fov/2) and a float32 3x3 product, then both normalise. Each
  side alone is within ~2e-5 degrees of a float64 closed form (measured:
  5e-6 to 2e-5 degrees over the cameras here, the worst at fov 150-170), so
  1e-4 degrees leaves a 5x margin while still catching any convention slip
  (a pixel at these film sizes spans more than 0.01 degrees).
* origins: 2e-5 absolute on coordinates of size <= 10 (float32 ulp there is
  1e-6; Mitsuba's near-plane offset divides by a float32 d_z that is as small
  as cos(85 degrees) at fov 170).
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

import instancing  # noqa: F401  (selects the backend before Dr.Jit/Mitsuba start)
from instancing.core import transform as tf
from instancing.core.backend import BACKEND_NAME, Float
from instancing.io.scene_file import parse_camera
from instancing.scene.camera import CameraBatch, PerspectiveCamera
from instancing.core.errors import SceneError

import mitsuba as mi  # noqa: E402  (after instancing, which selects libLLVM)

ANGLE_TOL_DEG = 1e-4   # direction agreement (see module docstring)
ORIGIN_TOL = 2e-5      # origin agreement, absolute (see module docstring)
MI_NEAR_CLIP = 0.01    # Mitsuba's default near_clip


pytestmark = pytest.mark.usefixtures("mitsuba_backend_variant")


# --- the cameras -------------------------------------------------------------------------
# Each case: fov (degrees along x), width, height, and to_world as our list of operations
# (or a 4x4 matrix); the Mitsuba twin's transform is built from the same description with
# Mitsuba's own builders by `mitsuba_transform`.

def _look_at(origin, target, up):
    return {"look_at": {"origin": origin, "target": target, "up": up}}


def _rotation_translation_matrix() -> list[list[float]]:
    """A rigid 4x4 matrix written out by hand: rotate 35 degrees about y, then translate."""
    c, s = math.cos(math.radians(35)), math.sin(math.radians(35))
    return [[c, 0, s, 0.5], [0, 1, 0, -1.0], [-s, 0, c, 2.0], [0, 0, 0, 1]]


CAMERAS = {
    "identity_square": (45, 32, 32, []),
    "wide_look_at_y_up": (60, 64, 32, [_look_at([1, 2, 3], [0, 0, 0], [0, 1, 0])]),
    "tall_look_at_z_up": (30, 24, 80, [_look_at([4, -3, 2], [0, 1, 0.5], [0, 0, 1])]),
    "narrow_look_at_x_up": (5, 40, 40, [_look_at([-2, 0.5, 1], [3, 1, -2], [1, 0, 0])]),
    "very_wide_tilted_up": (150, 120, 20, [_look_at([0, 1, -5], [0.2, 0.1, 0], [0.3, 1, -0.2])]),
    "very_tall_fov_170": (170, 40, 300, [_look_at([0.3, -0.2, 5], [1, 2, 3], [0.2, 1, 0.1])]),
    "ops_translate_rotate_look_at": (70, 48, 36, [
        {"translate": [1, 0, -2]},
        {"rotate": {"axis": [0, 1, 1], "angle": 30}},
        _look_at([1, 2, 3], [0.3, -0.2, 5], [0.2, 1, 0.1])]),
    "ops_roll_then_translate": (40, 50, 30, [
        {"translate": [0, 0, -4]},
        {"rotate": {"axis": [0, 0, 1], "angle": 90}}]),
    "matrix": (40, 33, 21, _rotation_translation_matrix()),
}


def mitsuba_transform(to_world) -> "mi.ScalarTransform4f":
    """The Mitsuba twin of a to_world description, chained with Mitsuba's own builders."""
    if to_world and all(isinstance(row, list) for row in to_world) and len(to_world) == 4 \
            and not isinstance(to_world[0], dict):
        return mi.ScalarTransform4f(to_world)
    t = mi.ScalarTransform4f()
    for op in to_world:
        (name, arg), = op.items()
        if name == "translate":
            t = t.translate(arg)
        elif name == "rotate":
            axis = np.asarray(arg["axis"], float)
            t = t.rotate((axis / np.linalg.norm(axis)).tolist(), arg["angle"])  # Mitsuba wants a unit axis
        elif name == "look_at":
            t = t.look_at(origin=arg["origin"], target=arg["target"], up=arg["up"])
        else:
            raise AssertionError(f"no Mitsuba twin for {name!r}")
    return t


def our_camera(name: str) -> PerspectiveCamera:
    fov, width, height, to_world = CAMERAS[name]
    return parse_camera({"type": "perspective", "fov": fov, "width": width,
                                        "height": height, "to_world": to_world})


def mitsuba_sensor_dict(name: str, **extra) -> dict:
    fov, width, height, to_world = CAMERAS[name]
    return {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": mitsuba_transform(to_world),
            "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}},
            **extra}


def mitsuba_rays(sensor, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 origins and directions of Mitsuba's rays through film positions (u, v)."""
    ray, _ = sensor.sample_ray(time=0, sample1=0, sample2=mi.Point2f(u, v),
                               sample3=mi.Point2f(0.5, 0.5))
    return (np.array(ray.o, np.float64).T, np.array(ray.d, np.float64).T)


def our_rays(camera: PerspectiveCamera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o, d = camera.rays(Float(u), Float(v))
    return np.array(o, np.float64).T, np.array(d, np.float64).T


def pixel_centres(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Row-major film positions of the pixel centres, rounded as Dr.Jit and Mitsuba round them.

    Dr.Jit turns a division by a scalar into a product with its float32 reciprocal (so does
    Mitsuba's film sampling, ``(pixel + offset) * rcp(size)``): (x + 0.5) * fl(1 / W) can be
    one ulp from the correctly rounded (x + 0.5) / W. One ulp of film position is harmless
    (1e-5 degrees on a normal camera) but the fov-170, 40x300 camera here spans 179.3 degrees
    vertically, where it moves a ray by 1e-4 degrees, so both systems get the very same floats.
    """
    y, x = np.divmod(np.arange(width * height), width)
    u = np.float32(x + 0.5) * np.float32(1 / width)
    v = np.float32(y + 0.5) * np.float32(1 / height)
    return u.astype(np.float32), v.astype(np.float32)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rows in degrees via atan2(|a x b|, a.b) in float64 (accurate near 0)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))


def film_samples(n: int = 4000, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Seeded film positions in [0, 1]^2 plus the corners, edge midpoints and the centre."""
    rng = np.random.default_rng(seed)
    grid = np.array([0.0, 0.5, 1.0])
    uu, vv = np.meshgrid(grid, grid)
    u = np.concatenate([uu.ravel(), rng.random(n)]).astype(np.float32)
    v = np.concatenate([vv.ravel(), rng.random(n)]).astype(np.float32)
    return u, v


def camera_from_world_linear(name: str) -> np.ndarray:
    """float64 inverse of the linear part of the Mitsuba twin's to_world."""
    m = np.array(mitsuba_transform(CAMERAS[name][3]).matrix, np.float64)
    return np.linalg.inv(m[:3, :3])


# --- agreement with Mitsuba --------------------------------------------------------------

@pytest.mark.parametrize("name", CAMERAS)
def test_directions_match_mitsuba(name):
    u, v = film_samples()
    _, ours = our_rays(our_camera(name), u, v)
    _, theirs = mitsuba_rays(mi.load_dict(mitsuba_sensor_dict(name)), u, v)
    np.testing.assert_allclose(np.linalg.norm(ours, axis=1), 1.0, atol=1e-6)
    worst = angle_deg(ours, theirs).max()
    assert worst < ANGLE_TOL_DEG, f"{name}: directions differ from Mitsuba's by up to {worst:.3g} degrees"


@pytest.mark.parametrize("name", CAMERAS)
def test_origins_match_mitsuba_after_its_near_clip_offset(name):
    """Mitsuba's origin is ours moved to the near plane: o + near_clip / dot(d, forward) * d."""
    u, v = film_samples()
    camera = our_camera(name)
    o, d = our_rays(camera, u, v)
    mo, _ = mitsuba_rays(mi.load_dict(mitsuba_sensor_dict(name)), u, v)
    position = np.array(camera.world_from_camera.matrix, np.float64)[:3, 3]
    np.testing.assert_array_equal(o, np.broadcast_to(position.astype(np.float32), o.shape))
    forward = np.array(camera.world_from_camera.matrix, np.float64)[:3, 2]
    forward /= np.linalg.norm(forward)
    expected = o + (MI_NEAR_CLIP / (d @ forward))[:, None] * d
    np.testing.assert_allclose(mo, expected, rtol=0, atol=ORIGIN_TOL)


@pytest.mark.parametrize("name", ["wide_look_at_y_up", "ops_translate_rotate_look_at"])
def test_origins_match_mitsuba_with_tiny_near_clip(name):
    """With near_clip -> 0 Mitsuba's origins become the camera position, like ours."""
    u, v = film_samples(500)
    o, d = our_rays(our_camera(name), u, v)
    mo, md = mitsuba_rays(mi.load_dict(mitsuba_sensor_dict(name, near_clip=1e-6)), u, v)
    np.testing.assert_allclose(mo, o, rtol=0, atol=ORIGIN_TOL)
    assert angle_deg(d, md).max() < ANGLE_TOL_DEG


@pytest.mark.parametrize("name", CAMERAS)
def test_pixel_centre_rays_match_mitsuba_pixel_centres(name):
    camera = our_camera(name)
    u, v = pixel_centres(camera.width, camera.height)
    _, ours = (np.array(a, np.float64).T for a in camera.pixel_centre_rays())
    _, theirs = mitsuba_rays(mi.load_dict(mitsuba_sensor_dict(name)), u, v)
    assert angle_deg(ours, theirs).max() < ANGLE_TOL_DEG


# --- orientation, field of view axis and aspect ------------------------------------------

@pytest.mark.parametrize("name", CAMERAS)
def test_orientation_fov_axis_and_aspect_in_camera_space(name):
    """Top-left looks to camera +x (left) and +y (up); fov spans x; y spans tan(fov/2) * H / W.

    Both systems' rays, taken back to camera space with the float64 inverse of Mitsuba's
    to_world, are compared with the closed form ((1 - 2u) tan(fov/2), (1 - 2v) tan(fov/2) H/W, 1).
    """
    fov, width, height, _ = CAMERAS[name]
    u = np.array([0, 1, 0, 1, 0.5, 0, 0.5, 1, 0.5], np.float32)
    v = np.array([0, 0, 1, 1, 0.5, 0.5, 0, 0.5, 1], np.float32)
    inv = camera_from_world_linear(name)
    _, ours = our_rays(our_camera(name), u, v)
    _, theirs = mitsuba_rays(mi.load_dict(mitsuba_sensor_dict(name)), u, v)
    tan_half = math.tan(math.radians(fov) / 2)
    expected = np.stack([(1 - 2 * u.astype(float)) * tan_half,
                         (1 - 2 * v.astype(float)) * tan_half * height / width,
                         np.ones(len(u))], axis=1)
    for who, d in (("ours", ours), ("Mitsuba", theirs)):
        local = d @ inv.T
        assert np.all(local[:, 2] > 0), f"{who}: rays must look down camera +z"
        signs = np.sign(np.round(local[:4, :2] / local[:4, 2:], 6))
        # top-left, top-right, bottom-left, bottom-right: +x is left, +y is up
        np.testing.assert_array_equal(signs, [[1, 1], [-1, 1], [1, -1], [-1, -1]], err_msg=who)
        assert angle_deg(local[4:5], np.array([[0.0, 0.0, 1.0]]))[0] < ANGLE_TOL_DEG, \
            f"{who}: the film centre must look along the viewing direction"
        # left and right edge midpoints are fov/2 off axis: the fov is horizontal
        np.testing.assert_allclose(angle_deg(local[[5, 7]], np.array([[0.0, 0, 1]] * 2)), fov / 2,
                                   atol=ANGLE_TOL_DEG, err_msg=who)
        assert angle_deg(local, expected).max() < ANGLE_TOL_DEG, f"{who}: not the closed form"


def test_top_left_pixel_of_mitsuba_image_is_our_top_left_ray():
    """End to end: a small sphere put on our ray through pixel (x0, y0) appears at row y0,
    column x0 of the image Mitsuba renders (row 0 at the top), on a rolled, non-square camera."""
    name = "ops_roll_then_translate"
    camera = our_camera(name)
    w, h = camera.width, camera.height
    x0, y0 = 9, 3  # near the top-left corner, u = 0.19 != v = 0.12
    o, d = our_rays(camera, np.float32([(x0 + 0.5) / w]), np.float32([(y0 + 0.5) / h]))
    distance = 10.0
    pixel_angle = math.radians(CAMERAS[name][0]) / w
    radius = distance * math.tan(1.5 * pixel_angle)  # about three pixels across
    centre = (o[0] + distance * d[0]).tolist()
    sensor = mitsuba_sensor_dict(name)
    sensor["sampler"] = {"type": "independent", "sample_count": 16}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "dd.y:depth"},
                          "sensor": sensor,
                          "ball": {"type": "sphere", "center": centre, "radius": radius}})
    depth = np.array(mi.render(scene, seed=1))[..., 0]
    assert depth.shape == (h, w)
    assert depth[y0, x0] > 0, "Mitsuba's image does not show the ball at our pixel"
    rows, cols = np.nonzero(depth > 0)
    assert abs(rows.mean() - y0) <= 1 and abs(cols.mean() - x0) <= 1
    assert rows.max() <= y0 + 3 and cols.max() <= x0 + 3, "the ball spills far from our pixel"


# --- pixel_centre_rays -------------------------------------------------------------------

@pytest.mark.parametrize("size", [(7, 5), (5, 7), (1, 1), (1, 9), (13, 1)])
def test_pixel_centre_rays_are_row_major_pixel_centres(size):
    width, height = size
    camera = our_camera("tall_look_at_z_up").with_size(width, height)
    o, d = (np.array(a, np.float64).T for a in camera.pixel_centre_rays())
    assert o.shape == d.shape == (width * height, 3)
    # row-major: x varies fastest; the positions ((x + 0.5) / W, (y + 0.5) / H) differ from
    # the correctly rounded quotients by at most one float32 ulp (see pixel_centres)
    u, v = pixel_centres(width, height)
    y, x = np.divmod(np.arange(width * height), width)
    np.testing.assert_allclose(u, (x + 0.5) / width, rtol=1.2e-7, atol=0)
    np.testing.assert_allclose(v, (y + 0.5) / height, rtol=1.2e-7, atol=0)
    eo, ed = our_rays(camera, u, v)
    np.testing.assert_array_equal(o, eo)
    # The same float32 arithmetic on LLVM; on CUDA, ptxas contracts a * b + c into one fma
    # differently in the fused kernel and in the one fed with evaluated (u, v): up to one
    # float32 ulp per component (measured on an H200: 3.3e-6 degrees).
    assert angle_deg(d, ed).max() < (1e-6 if BACKEND_NAME == "llvm" else 7e-6)


# --- parse_camera validation ----------------------------------------------------------------

def test_parse_camera_defaults():
    camera = parse_camera({"type": "perspective"})
    assert (camera.fov, camera.width, camera.height, camera.rfilter) == (45.0, 256, 256, "box")
    np.testing.assert_array_equal(np.array(camera.world_from_camera.matrix, np.float64), np.eye(4))


def test_parse_camera_accepts_boundary_values():
    camera = parse_camera({"type": "perspective", "fov": 179.5, "width": 1,
                                          "height": 1 << 15, "rfilter": "gaussian"})
    assert (camera.fov, camera.width, camera.height, camera.rfilter) == (179.5, 1, 1 << 15, "gaussian")
    assert parse_camera({"type": "perspective", "fov": 1}).fov == 1.0


@pytest.mark.parametrize("rfilter, expected", [
    ({"type": "box"}, ("box", None)), ({"type": "gaussian"}, ("gaussian", None)),
    ({"type": "gaussian", "stddev": 0.5}, ("gaussian", None)),
    ({"type": "gaussian", "stddev": 1.5}, ("gaussian", 1.5)), ({"type": "tent", "radius": 32}, ("tent", 32.0)),
    ({"type": "mitchell"}, ("mitchell", None)), ({"type": "mitchell", "B": 1 / 3, "C": 1 / 3}, ("mitchell", None)),
    ({"type": "mitchell", "B": 0.2}, ("mitchell", None, (0.2, 1 / 3))), ("catmullrom", ("catmullrom", None)),
    ({"type": "lanczos", "lobes": 2}, ("lanczos", 2.0)), ({"type": "lanczos", "lobes": 3}, ("lanczos", None))])
def test_parse_camera_reconstruction_filter_with_its_size(rfilter, expected):
    """A filter as a dict with Mitsuba's size parameter (or a mitchell filter's B and C); its
    default size is stored as None, so that equal filters batch together."""
    camera = parse_camera({"type": "perspective", "rfilter": rfilter})
    assert (camera.rfilter, camera.rfilter_size, camera.rfilter_bc) == (expected + (None,))[:3]


BAD_CAMERAS = {
    "not_a_dict": "perspective",
    "none": None,
    "missing_type": {"fov": 45},
    "radiancemeter": {"type": "radiancemeter"},
    "orthographic_fov": {"type": "orthographic", "fov": 45},
    "thinlens_no_aperture": {"type": "thinlens", "fov": 45},
    "thinlens_zero_aperture": {"type": "thinlens", "aperture_radius": 0},
    "thinlens_zero_focus": {"type": "thinlens", "aperture_radius": 0.1, "focus_distance": 0},
    "perspective_aperture": {"type": "perspective", "aperture_radius": 0.1},
    "near_clip_negative": {"type": "perspective", "near_clip": -0.01},
    "near_clip_nan": {"type": "perspective", "near_clip": float("nan")},
    "unknown_key_fov_axis": {"type": "perspective", "fov_axis": "x"},
    "unknown_key_film": {"type": "perspective", "film": {"type": "hdrfilm"}},
    "fov_zero": {"type": "perspective", "fov": 0},
    "fov_180": {"type": "perspective", "fov": 180},
    "fov_negative": {"type": "perspective", "fov": -30},
    "fov_huge": {"type": "perspective", "fov": 270},
    "fov_nan": {"type": "perspective", "fov": float("nan")},
    "fov_inf": {"type": "perspective", "fov": float("inf")},
    "fov_string": {"type": "perspective", "fov": "45"},
    "fov_bool": {"type": "perspective", "fov": True},
    "fov_none": {"type": "perspective", "fov": None},
    "fov_list": {"type": "perspective", "fov": [45]},
    "width_zero": {"type": "perspective", "width": 0},
    "width_negative": {"type": "perspective", "width": -4},
    "width_float": {"type": "perspective", "width": 64.0},
    "width_string": {"type": "perspective", "width": "64"},
    "width_bool": {"type": "perspective", "width": True},
    "width_too_large": {"type": "perspective", "width": (1 << 15) + 1},
    "height_zero": {"type": "perspective", "height": 0},
    "height_float": {"type": "perspective", "height": 2.5},
    "height_none": {"type": "perspective", "height": None},
    "rfilter_sinc": {"type": "perspective", "rfilter": "sinc"},
    "rfilter_dict_sinc": {"type": "perspective", "rfilter": {"type": "sinc"}},
    "rfilter_box_size": {"type": "perspective", "rfilter": {"type": "box", "radius": 1}},
    "rfilter_gaussian_radius": {"type": "perspective", "rfilter": {"type": "gaussian", "radius": 2}},
    "rfilter_stddev_zero": {"type": "perspective", "rfilter": {"type": "gaussian", "stddev": 0}},
    "rfilter_stddev_string": {"type": "perspective", "rfilter": {"type": "gaussian", "stddev": "1"}},
    "rfilter_stddev_too_wide": {"type": "perspective", "rfilter": {"type": "gaussian", "stddev": 8.5}},
    "rfilter_radius_nan": {"type": "perspective", "rfilter": {"type": "tent", "radius": float("nan")}},
    "rfilter_number": {"type": "perspective", "rfilter": 1},
    "to_world_string": {"type": "perspective", "to_world": "camera.npy"},
    "to_world_number": {"type": "perspective", "to_world": 3},
    "to_world_3x3": {"type": "perspective", "to_world": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
    "to_world_singular": {"type": "perspective", "to_world": [[0, 0, 0, 0]] * 3 + [[0, 0, 0, 1]]},
    "to_world_projective": {"type": "perspective",
                            "to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]},
    "to_world_unknown_op": {"type": "perspective", "to_world": [{"shear": [1, 0, 0]}]},
    "to_world_bad_translate": {"type": "perspective", "to_world": [{"translate": [1, 2]}]},
    "to_world_look_at_degenerate": {"type": "perspective",
                                    "to_world": [_look_at([1, 1, 1], [1, 1, 1], [0, 1, 0])]},
    "to_world_look_at_up_parallel": {"type": "perspective",
                                     "to_world": [_look_at([0, 0, 0], [0, 2, 0], [0, 1, 0])]},
    "to_world_nan": {"type": "perspective", "to_world": [{"translate": [0, float("nan"), 0]}]},
}


@pytest.mark.parametrize("name", BAD_CAMERAS)
def test_parse_camera_rejects_bad_camera_naming_it(name):
    with pytest.raises(SceneError, match="camera"):
        parse_camera(BAD_CAMERAS[name])


# --- what Mitsuba refuses ----------------------------------------------------------------

@pytest.mark.parametrize("op", [{"scale": 2}, {"scale": [1, 2, 1]},
                                {"matrix": [[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}])
def test_scale_or_shear_in_to_world_is_rejected_like_mitsuba(op):
    """Mitsuba refuses a scaled sensor to_world; so do we (scale or shear would distort the view)."""
    with pytest.raises(RuntimeError, match="[Ss]cale"):
        mi.load_dict({"type": "perspective", "fov": 45,
                      "to_world": mi.ScalarTransform4f().translate([1, 2, 3]).scale(2)})
    with pytest.raises(SceneError, match="camera: to_world must be rigid"):
        parse_camera({"type": "perspective", "to_world": [{"translate": [1, 2, 3]}, op]})



# --- near clip, thin lens, orthographic ------------------------------------------------------

OTHER_SENSORS = {
    "perspective_near_clip": {"type": "perspective", "fov": 50, "near_clip": 0.7},
    "thinlens": {"type": "thinlens", "fov": 40, "aperture_radius": 0.3, "focus_distance": 4.5,
                 "near_clip": 0.05},
    "orthographic": {"type": "orthographic", "near_clip": 0.2},
}
#: Scale sets an orthographic camera's extent (as in Mitsuba); the others stay rigid.
SENSOR_TO_WORLD = [_look_at([1, 2, -6], [0, 0.5, 0], [0, 1, 0])]


@pytest.mark.parametrize("name", OTHER_SENSORS)
def test_sensor_rays_match_mitsuba(name):
    """Origins (on the near plane) and directions of Mitsuba's sensor of the same type,
    through the same film positions and, for the thin lens, the same aperture samples."""
    spec = OTHER_SENSORS[name]
    to_world = SENSOR_TO_WORLD + ([{"scale": [2.5, 1.5, 1]}] if name == "orthographic" else [])
    camera = parse_camera({**spec, "width": 40, "height": 30, "to_world": to_world})
    u, v = film_samples(2000)
    rng = np.random.default_rng(3)
    a = rng.random((2, len(u))).astype(np.float32)
    o, d = camera.rays(Float(u), Float(v), (Float(a[0]), Float(a[1])))
    o, d = np.array(o, np.float64).T, np.array(d, np.float64).T
    mitsuba_spec = {key: value for key, value in spec.items()}
    if "fov" in spec:
        mitsuba_spec["fov_axis"] = "x"
    sensor = mi.load_dict({**mitsuba_spec, "to_world": mitsuba_transform(SENSOR_TO_WORLD).scale(
        [2.5, 1.5, 1] if name == "orthographic" else [1, 1, 1]),
        "film": {"type": "hdrfilm", "width": 40, "height": 30, "rfilter": {"type": "box"}}})
    ray, _ = sensor.sample_ray(time=0, sample1=0, sample2=mi.Point2f(u, v),
                               sample3=mi.Point2f(a[0], a[1]))
    mo, md = np.array(ray.o, np.float64).T, np.array(ray.d, np.float64).T
    assert angle_deg(d, md).max() < 1e-3
    np.testing.assert_allclose(o, mo, rtol=0, atol=1e-5)
    if name == "thinlens":
        # The lens spreads the origins over its aperture; all rays of one film position
        # meet on the focal plane.
        spread = np.linalg.norm(o - o.mean(axis=0), axis=1)
        assert 0.1 < spread.max() <= 0.3 + 0.1


def test_pinhole_rays_start_on_the_near_plane():
    camera = parse_camera({"type": "perspective", "fov": 60, "near_clip": 0.5, "width": 8,
                           "height": 8, "to_world": SENSOR_TO_WORLD})
    o, d = (np.array(x, np.float64).T for x in camera.pixel_centre_rays())
    eye = np.array(camera.world_from_camera.matrix, np.float64)[:3, 3]
    forward = np.array(camera.world_from_camera.matrix, np.float64)[:3, 2]
    np.testing.assert_allclose((o - eye) @ forward, 0.5, rtol=1e-5)
    np.testing.assert_allclose(np.cross(o - eye, d), 0.0, atol=1e-5)


#: Pairs of cameras of one type that differ in everything a batch stores per view.
BATCHED = {
    "perspective": [
        {"type": "perspective", "fov": 40, "to_world": SENSOR_TO_WORLD},
        {"type": "perspective", "fov": 75, "near_clip": 0.3,
         "to_world": [_look_at([-4, 1, 3], [0, 0, 0], [0, 0, 1])]}],
    "thinlens": [
        {"type": "thinlens", "fov": 40, "aperture_radius": 0.3, "focus_distance": 4.5,
         "to_world": SENSOR_TO_WORLD},
        {"type": "thinlens", "fov": 55, "aperture_radius": 0.05, "focus_distance": 9.0,
         "near_clip": 0.2, "to_world": [_look_at([-4, 1, 3], [0, 0, 0], [0, 0, 1])]}],
    "orthographic": [
        {"type": "orthographic", "to_world": SENSOR_TO_WORLD + [{"scale": [2.5, 1.5, 1]}]},
        {"type": "orthographic", "near_clip": 0.4,
         "to_world": [_look_at([-4, 1, 3], [0, 0, 0], [0, 0, 1])]}],
}


@pytest.mark.parametrize("kind", BATCHED)
def test_a_camera_batch_gives_each_lane_its_views_rays(kind):
    """Lanes of a batch, each with its own view, get exactly the rays their camera gives
    alone (the same float32 arithmetic on gathered instead of opaque values)."""
    from instancing.core.backend import UInt32
    from instancing.scene.camera import CameraBatch
    cameras = [parse_camera({**spec, "width": 40, "height": 30}) for spec in BATCHED[kind]]
    u, v = film_samples(1500)
    rng = np.random.default_rng(5)
    a = rng.random((2, len(u))).astype(np.float32)
    view = rng.integers(0, len(cameras), len(u)).astype(np.uint32)
    aperture = (Float(a[0]), Float(a[1])) if cameras[0].aperture_samples else None
    batch = CameraBatch(cameras)
    o, d = (np.array(x, np.float64).T for x in
            cameras[0].rays(Float(u), Float(v), aperture, batch.lanes(UInt32(view))))
    for k, camera in enumerate(cameras):
        lanes = view == k
        own = (Float(a[0][lanes]), Float(a[1][lanes])) if aperture is not None else None
        ok, dk = (np.array(x, np.float64).T for x in
                  camera.rays(Float(u[lanes]), Float(v[lanes]), own))
        np.testing.assert_array_equal(o[lanes], ok)
        np.testing.assert_array_equal(d[lanes], dk)
    assert not np.allclose(o[view == 0].mean(axis=0), o[view == 1].mean(axis=0))


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
def test_a_camera_batch_projects_each_lanes_points_through_its_view(kind):
    """project and film_velocity with a batch's lanes: each lane's point lands where its own
    camera puts it (float32 to a few ulps of the film), and the projection inverts the lane's
    rays through random film positions."""
    from instancing.core.backend import Array3f, UInt32
    from instancing.scene.camera import CameraBatch
    cameras = [parse_camera({**spec, "width": 40, "height": 30}) for spec in BATCHED[kind]]
    rng = np.random.default_rng(6)
    n = 1500
    view = rng.integers(0, len(cameras), n).astype(np.uint32)
    u, v = rng.uniform(0.05, 0.95, (2, n)).astype(np.float32)
    batch = CameraBatch(cameras)
    lanes = batch.lanes(UInt32(view))
    o, d = cameras[0].rays(Float(u), Float(v), None, lanes)
    depth = Float(rng.uniform(2.0, 6.0, n).astype(np.float32))
    p = o + d * depth
    velocity = Array3f(*[Float(c) for c in rng.normal(size=(3, n)).astype(np.float32)])
    x, y, front = cameras[0].project(p, lanes)
    vx, vy = cameras[0].film_velocity(p, velocity, lanes)
    x, y, vx, vy = (np.array(a, np.float64) for a in (x, y, vx, vy))
    assert np.asarray(front).all()
    np.testing.assert_allclose(x, u * 40, atol=2e-3)
    np.testing.assert_allclose(y, v * 30, atol=2e-3)
    for k, camera in enumerate(cameras):
        mine = view == k
        pk = Array3f(*[Float(np.array(c, np.float32)[mine]) for c in p])
        vk = Array3f(*[Float(np.array(c, np.float32)[mine]) for c in velocity])
        xk, yk, _ = camera.project(pk)
        vxk, vyk = camera.film_velocity(pk, vk)
        np.testing.assert_allclose(x[mine], np.array(xk, np.float64), rtol=0, atol=1e-4)
        np.testing.assert_allclose(y[mine], np.array(yk, np.float64), rtol=0, atol=1e-4)
        np.testing.assert_allclose(vx[mine], np.array(vxk, np.float64), rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(vy[mine], np.array(vyk, np.float64), rtol=1e-5, atol=1e-4)


def test_cameras_group_into_runs_that_share_a_wavefront():
    """Consecutive cameras of one type, film size, filter, seed and pixel format form one
    batch, up to the pixel budget; any other camera starts a new one. Cameras that differ
    refuse a batch."""
    from instancing.scene.camera import CameraBatch
    spec = {"type": "perspective", "fov": 40, "width": 8, "height": 6, "to_world": SENSOR_TO_WORLD}
    cameras = [parse_camera(s) for s in (spec, {**spec, "fov": 60}, {**spec, "width": 9},
                                         {**spec, "width": 9}, {"type": "orthographic", "width": 8, "height": 6},
                                         {**spec, "rfilter": "gaussian"}, spec, spec, {**spec, "seed": 3}, spec,
                                         {**spec, "pixel_format": "rgba"})]
    runs = [indices for _, indices in CameraBatch.group(cameras, max_pixels=2 * 9 * 6)]
    assert runs == [[0, 1], [2, 3], [4], [5], [6, 7], [8], [9], [10]]
    assert [len(b) for b, _ in CameraBatch.group(cameras[:2], max_pixels=47)] == [1, 1]
    for other in (cameras[2], cameras[8], cameras[10]):
        with pytest.raises(SceneError, match="type, film size, window, filter, sampler, seed or pixel format differ"):
            CameraBatch([cameras[0], other])


# --- film crop and principal point -----------------------------------------------------------

#: A window of a 40 x 30 film (Mitsuba's crop), and off-centre films of the perspective camera.
CROP = {"x": 10, "y": 5, "width": 20, "height": 10}
CROPPED = {
    "perspective_crop": ({"type": "perspective", "fov": 50, "near_clip": 0.05}, CROP, None),
    "perspective_principal_point": ({"type": "perspective", "fov": 50, "near_clip": 0.05}, None,
                                    [0.1, -0.2]),
    "perspective_both": ({"type": "perspective", "fov": 70, "near_clip": 0.3},
                         {"x": 3, "y": 20, "width": 37, "height": 10}, [-0.25, 0.05]),
    "thinlens_crop": ({"type": "thinlens", "fov": 40, "aperture_radius": 0.3, "focus_distance": 4.5,
                       "near_clip": 0.05},
                      {"x": 0, "y": 12, "width": 31, "height": 7}, None),
    "orthographic_crop": ({"type": "orthographic", "near_clip": 0.2}, {"width": 17, "height": 29}, None),
}


def _cropped_pair(name):
    """Our camera and Mitsuba's sensor (built from Mitsuba's own keys) of a CROPPED case."""
    spec, crop, point = CROPPED[name]
    ours = {**spec, "width": 40, "height": 30, "to_world": SENSOR_TO_WORLD}
    film = {"type": "hdrfilm", "width": 40, "height": 30, "rfilter": {"type": "box"}}
    theirs = {**spec, "to_world": mitsuba_transform(SENSOR_TO_WORLD), "film": film}
    if "fov" in spec:
        theirs["fov_axis"] = "x"
    if crop is not None:
        ours["crop"] = crop
        film.update({f"crop_{key}": value for key, value in
                     (("offset_x", crop.get("x")), ("offset_y", crop.get("y")),
                      ("width", crop.get("width")), ("height", crop.get("height"))) if value is not None})
    if point is not None:
        ours["principal_point"] = point
        theirs.update(principal_point_offset_x=point[0], principal_point_offset_y=point[1])
    return parse_camera(ours), mi.load_dict(theirs)


@pytest.mark.parametrize("name", CROPPED)
def test_cropped_and_off_centre_films_give_mitsubas_rays(name):
    """Image positions over a crop window, on an off-centre film, or both: Mitsuba's rays
    (its sample2 runs over the crop window), image size the crop's."""
    camera, sensor = _cropped_pair(name)
    assert [camera.width, camera.height] == list(sensor.film().crop_size())
    u, v = film_samples(2000)
    a = np.random.default_rng(8).random((2, len(u))).astype(np.float32)
    o, d = camera.rays(Float(u), Float(v), (Float(a[0]), Float(a[1])))
    o, d = np.array(o, np.float64).T, np.array(d, np.float64).T
    ray, _ = sensor.sample_ray(time=0, sample1=0, sample2=mi.Point2f(u, v),
                               sample3=mi.Point2f(a[0], a[1]))
    mo, md = np.array(ray.o, np.float64).T, np.array(ray.d, np.float64).T
    assert angle_deg(d, md).max() < 1e-3
    np.testing.assert_allclose(o, mo, rtol=0, atol=1e-5)


def test_a_crop_shows_the_window_of_the_whole_films_pixels():
    """The cropped camera's pixel-centre rays are the whole film's in its window (to a
    float32 rounding of the film position), and a camera at another image size keeps the
    window: the same rays through the same film fractions."""
    whole = parse_camera({"type": "perspective", "fov": 50, "width": 40, "height": 30,
                          "to_world": SENSOR_TO_WORLD})
    cropped = parse_camera({"type": "perspective", "fov": 50, "width": 40, "height": 30,
                            "crop": CROP, "to_world": SENSOR_TO_WORLD})
    d_whole = np.array(whole.pixel_centre_rays()[1], np.float64).T.reshape(30, 40, 3)
    d_crop = np.array(cropped.pixel_centre_rays()[1], np.float64).T.reshape(10, 20, 3)
    window = d_whole[5:15, 10:30].reshape(-1, 3)
    assert angle_deg(d_crop.reshape(-1, 3), window).max() < 1e-4
    # Three times the pixels each way: the same window of a 120 x 90 film, the same rays;
    # twice the width alone: a wider film (its aspect follows the image's, as uncropped).
    u, v = film_samples(500)
    rays = {size: np.array(cropped.with_size(*size).rays(Float(u), Float(v))[1], np.float64).T
            for size in ((20, 10), (60, 30), (40, 10))}
    assert cropped.with_size(60, 30).window == cropped.window
    assert angle_deg(rays[60, 30], rays[20, 10]).max() < 1e-4
    assert angle_deg(rays[40, 10], rays[20, 10]).max() > 1.0


@pytest.mark.parametrize("name", ["perspective_crop", "perspective_principal_point", "perspective_both"])
def test_projection_inverts_the_rays_of_a_cropped_or_off_centre_film(name):
    """project() puts points along the rays through image positions back at those positions
    (in image pixels), and film_velocity() is its derivative (central differences)."""
    camera, _ = _cropped_pair(name)
    _assert_projection_inverts_rays(camera, np.random.default_rng(9), (2.0, 6.0), 1e-3, 2e-2)


def _assert_projection_inverts_rays(camera, rng, depths, h, tolerance):
    """project() puts points at ``depths`` along the rays through random image positions back
    at those positions, and film_velocity() matches central differences of step ``h`` (to
    ``tolerance`` of their largest value). Returns the rays (o, d)."""
    from instancing.core.backend import Array3f
    u, v = rng.uniform(0.02, 0.98, (2, 800)).astype(np.float32)
    o, d = camera.rays(Float(u), Float(v))
    p = o + d * Float(rng.uniform(*depths, 800).astype(np.float32))
    x, y, front = camera.project(p)
    assert np.asarray(front).all()
    np.testing.assert_allclose(np.array(x), u * camera.width, atol=2e-3)
    np.testing.assert_allclose(np.array(y), v * camera.height, atol=2e-3)
    velocity = rng.normal(size=(3, 800))
    p64 = np.array(p, np.float64)
    ends = [camera.project(Array3f(*[Float((p64[k] + s * h * velocity[k]).astype(np.float32))
                                     for k in range(3)])) for s in (1, -1)]
    fd = [(np.array(ends[0][i], np.float64) - np.array(ends[1][i], np.float64)) / (2 * h) for i in (0, 1)]
    vx, vy = camera.film_velocity(p, Array3f(*[Float(c.astype(np.float32)) for c in velocity]))
    scale = np.abs(np.concatenate(fd)).max()
    np.testing.assert_allclose(np.array(vx), fd[0], rtol=0, atol=tolerance * scale)
    np.testing.assert_allclose(np.array(vy), fd[1], rtol=0, atol=tolerance * scale)
    return o, d


def test_orthographic_projection_inverts_its_rays_and_film_velocity_is_its_derivative():
    """An orthographic camera (scaled, cropped): project() puts points along the rays through
    image positions back at those positions, whatever their depth past the near plane, and
    film_velocity() is its derivative (central differences in float64 of the float32
    projection); points before the near plane are not in front; the viewpoint is the
    direction back along the view, at infinity."""
    camera = parse_camera({"type": "orthographic", "width": 40, "height": 30, "near_clip": 0.5,
                           "crop": {"x": 10, "y": 5, "width": 20, "height": 15},
                           "to_world": SENSOR_TO_WORLD + [{"scale": [2.5, 1.5, 1]}]})
    o, d = _assert_projection_inverts_rays(camera, np.random.default_rng(12), (0.1, 6.0), 1e-2, 2e-3)
    assert not np.asarray(camera.project(o - d * 0.1)[2]).any()
    forward = np.array(d, np.float64)[:, 0]
    np.testing.assert_allclose(camera.viewpoint(), np.append(-forward, 0.0), atol=1e-6)


@pytest.mark.parametrize("crop, message", [
    ({"x": 40}, "x must be an integer in \\[0, 39\\]"),
    ({"x": 10, "width": 31}, "width must be an integer in \\[1, 30\\]"),
    ({"y": -1}, "y must be an integer in \\[0, 29\\]"),
    ({"height": 0}, "height must be an integer in \\[1, 30\\]"),
    ({"x": 1.5}, "x must be an integer"),
    ({"left": 3}, "unknown keys \\['left'\\]"),
    ([0, 0, 10, 10], " must be a dict"),
])
def test_a_crop_outside_the_film_is_refused_naming_it(crop, message):
    with pytest.raises(SceneError, match="camera: crop" + ("" if "dict" in message else ": ") + message):
        parse_camera({"type": "perspective", "width": 40, "height": 30, "crop": crop})


@pytest.mark.parametrize("spec", [
    {"type": "perspective", "principal_point": [0.1]},
    {"type": "perspective", "principal_point": [0.1, float("nan")]},
    {"type": "perspective", "principal_point": "centre"},
    {"type": "thinlens", "aperture_radius": 0.1, "principal_point": [0.1, 0.0]},
    {"type": "orthographic", "principal_point": [0.1, 0.0]},
])
def test_a_bad_principal_point_or_one_on_another_camera_is_refused(spec):
    """As Mitsuba: only the perspective sensor has a principal point."""
    with pytest.raises(SceneError, match="principal_point"):
        parse_camera(spec)


def test_a_crop_defaults_to_the_rest_of_the_film():
    camera = parse_camera({"type": "perspective", "width": 40, "height": 30, "crop": {"x": 3, "y": 20}})
    assert (camera.width, camera.height) == (37, 10)
    assert camera.window == (3 / 40, 20 / 30, 1.0, 1.0)


@pytest.mark.parametrize("value", [1, "true", None])
def test_sample_border_must_be_a_boolean(value):
    with pytest.raises(SceneError, match="camera: sample_border must be true or false"):
        parse_camera({"type": "perspective", "sample_border": value})
    assert parse_camera({"type": "orthographic", "sample_border": True}).sample_border


@pytest.mark.parametrize("change, words", [
    (dict(width=0), "width must be an integer in [1, 32768], got 0"),
    (dict(width=8.5), "width must be an integer in [1, 32768], got 8.5"),
    (dict(rfilter="sinc"), "rfilter: must be one of ['box', 'gaussian', 'tent', 'mitchell', 'catmullrom', 'lanczos']"),
    (dict(rfilter="lanczos", rfilter_size=2.5), "rfilter: lobes must be a whole number (Mitsuba's is an integer)"),
    (dict(rfilter="box", rfilter_size=2.0), "the box filter has no size"),
    (dict(rfilter="mitchell", rfilter_size=2.0), "the mitchell filter has no size"),
    (dict(rfilter="catmullrom", rfilter_bc=(0.0, 0.5)), "B and C are the mitchell filter's, not 'catmullrom'"),
    (dict(rfilter="mitchell", rfilter_bc=(0.0, math.inf)), "B and C must be finite numbers, got (0.0, inf)"),
    (dict(world_from_camera=np.eye(4)), "to_world must be an instancing.Transform"),
    (dict(world_from_camera=tf.scale(2.0)), "to_world must be rigid"),
    (dict(fov=math.nan), "fov must be a number of degrees in (0, 180), got nan"),
    (dict(near_clip=-1.0), "near_clip must be a non-negative number, got -1.0"),
    (dict(window=(0.5, 0.0, 0.5, 1.0)), "window must be (x0, y0, x1, y1)"),
    (dict(aperture_radius=-0.1), "aperture_radius must be a positive number, got -0.1")])
def test_a_camera_made_directly_checks_its_values(change, words):
    """Cameras built without a scene file (directly or by ``dataclasses.replace``) check
    their values as the parser does (they failed later, inside a render, or rendered black)."""
    from instancing.scene.camera import ThinLensCamera
    values = dict(world_from_camera=tf.translate([0.0, 0.0, -5.0]), width=8, height=6,
                  aperture_radius=0.1) | change
    with pytest.raises(SceneError) as err:
        ThinLensCamera(**values)
    assert words in str(err.value)


def test_a_scene_refuses_a_camera_with_an_unknown_medium_or_a_taken_id():
    scene = instancing.load_scene({
        "instances": [{"model": "sphere"}],
        "cameras": [{"type": "perspective", "id": "a"}, {"type": "perspective", "id": "b"}]})
    with pytest.raises(SceneError, match="camera id 'a' is another camera's already"):
        scene.set_camera(PerspectiveCamera(world_from_camera=tf.translate([0.0, 0.0, -5.0]), width=8,
                                           height=6, id="a"), "b")
    with pytest.raises(SceneError, match="medium 'fog' is none of the scene's media"):
        scene.set_camera(PerspectiveCamera(world_from_camera=tf.translate([0.0, 0.0, -5.0]), width=8,
                                           height=6, medium="fog"), "b")
    assert [c.id for c in scene.cameras] == ["a", "b"]


@pytest.mark.parametrize("value", ["sobol", "Independent", 1, None, ["ldsampler"]])
def test_a_cameras_sampler_is_one_of_mitsubas_sampler_types(value):
    """A camera's sampler names one of Mitsuba's sampler types (default ``independent``);
    every other value is refused by name, from a scene file and from code alike."""
    assert parse_camera({"type": "perspective"}).sampler == "independent"
    for kind in ("independent", "stratified", "multijitter", "orthogonal", "ldsampler"):
        camera = parse_camera({"type": "perspective", "sampler": kind})
        assert (camera.sampler, camera.stratified) == (kind, kind != "independent")
    with pytest.raises(SceneError, match=r"camera: sampler must be one of \['independent', "):
        parse_camera({"type": "perspective", "sampler": value})
    with pytest.raises(SceneError, match="sampler must be one of"):
        dataclasses.replace(parse_camera({"type": "perspective"}), sampler=value)


def test_cameras_with_different_samplings_do_not_share_a_wavefront():
    """Views traced as one wavefront draw their samples one way: a stratified camera and an
    independent one of the same film do not batch (two stratified types do)."""
    first = parse_camera({"type": "perspective", "sampler": "ldsampler"})
    assert first.batches_with(dataclasses.replace(first, sampler="multijitter"))
    assert not first.batches_with(dataclasses.replace(first, sampler="independent"))
    with pytest.raises(SceneError, match="cannot share a wavefront"):
        CameraBatch((first, dataclasses.replace(first, sampler="independent")))


# --- the camera's seed ---------------------------------------------------------------------------

def _seeded_scene(sampler: str, seed: int | None) -> "instancing.Scene":
    camera = {"type": "perspective", "fov": 40, "width": 12, "height": 9, "to_world": SENSOR_TO_WORLD,
              "sampler": sampler, **({} if seed is None else {"seed": seed})}
    return instancing.load_scene({"instances": [{"model": "sphere"}, {"model": "cube", "to_world": [
        {"translate": [0, -1.5, 0]}, {"scale": [3, 0.2, 3]}]}],
        "lights": [{"type": "point", "position": [1, 3, -2], "intensity": 20},
                   {"type": "constant", "radiance": 0.2}], "camera": camera})


@pytest.mark.parametrize("sampler", ["independent", "ldsampler"])
def test_a_cameras_seed_is_added_to_the_renders_seed(sampler):
    """A camera's seed (Mitsuba's sampler's) is added to the seed a render is given, modulo
    2^32, as Mitsuba adds its sampler's: the image of camera seed 5 at seed 0 is, bit for
    bit, that of camera seed 0 at seed 5, and camera seed 5 at seed 2^32 - 1 that of seed 4."""
    def image(camera_seed, seed, integrator="path"):
        return np.asarray(instancing.render(_seeded_scene(sampler, camera_seed), integrator, spp=4, seed=seed))
    assert _seeded_scene(sampler, None).camera.seed == 0
    for integrator in ("direct", "path"):
        np.testing.assert_array_equal(image(5, 0, integrator), image(0, 5, integrator))
    np.testing.assert_array_equal(image(5, 2 ** 32 - 1), image(0, 4))
    assert not np.array_equal(image(5, 0), image(0, 0))


@pytest.mark.parametrize("value", [-1, 2 ** 32, 1.5, True, "3", None])
def test_a_cameras_seed_is_a_32_bit_unsigned_integer(value):
    """Anything else is refused by name, from a scene file and from code alike."""
    with pytest.raises(SceneError, match=r"camera: seed must be an integer in \[0, 4294967295\]"):
        parse_camera({"type": "perspective", "seed": value})
    with pytest.raises(SceneError, match="seed must be an integer"):
        dataclasses.replace(parse_camera({"type": "perspective"}), seed=value)


@pytest.mark.parametrize("spec, message", [
    ({"sampler": "independent", "jitter": False}, "camera: jitter: false applies to the samplers "
                                                  "['stratified', 'multijitter', 'orthogonal'], not 'independent'"),
    ({"sampler": "ldsampler", "jitter": False}, "not 'ldsampler'"),
    ({"sampler": "stratified", "jitter": 0}, "camera: jitter must be true or false, got 0"),
    ({"sampler": "stratified", "jitter": "false"}, "camera: jitter must be true or false, got 'false'")])
def test_a_cameras_jitter_is_a_flag_of_the_stratified_samplers(spec, message):
    with pytest.raises(SceneError, match=re.escape(message)):
        parse_camera({"type": "perspective", **spec})


def test_an_unjittered_camera_renders_its_pixels_centres_at_one_sample():
    """One sample of an unjittered stratified camera is its pixel's centre: the image's
    depth is the depth at the pixels' centres (as traced by scene.intersect), the same for
    every seed; a jittered camera's is not."""
    scene = _seeded_scene("stratified", 0)
    camera = dataclasses.replace(scene.camera, jitter=False)
    scene.set_camera(camera)
    depth = [np.asarray(instancing.render(scene, "aov", spp=1, seed=s, aovs=["depth"]))[..., 0] for s in (0, 7)]
    np.testing.assert_array_equal(depth[0], depth[1])
    u = (np.arange(camera.width) + 0.5) / camera.width
    v = (np.arange(camera.height) + 0.5) / camera.height
    uu, vv = np.meshgrid(u, v)
    o, d = camera.rays(Float(uu.ravel()), Float(vv.ravel()))
    hit = scene.intersect(o, d)
    t = np.where(np.asarray(hit.valid), np.asarray(hit.t), 0).reshape(depth[0].shape)
    np.testing.assert_allclose(depth[0], t, rtol=1e-5, atol=1e-5)
    scene.set_camera(dataclasses.replace(camera, jitter=True))
    jittered = np.asarray(instancing.render(scene, "aov", spp=1, seed=0, aovs=["depth"]))[..., 0]
    assert np.abs(jittered - t).max() > 1e-2


def test_mitsuba_adds_its_samplers_seed_to_the_renders_as_ours_does():
    """The reference for the rule above: Mitsuba's image with a sampler of seed 5 rendered at
    seed 0 is its image with a sampler of seed 0 at seed 5, and differs from seed 0's."""
    scene = _seeded_scene("independent", 0)
    images = {}
    for sampler_seed, seed in ((5, 0), (0, 5), (0, 0)):
        exported = instancing.to_mitsuba(scene)
        exported["sensor"]["sampler"]["seed"] = sampler_seed
        exported["integrator"] = {"type": "path"}
        images[sampler_seed, seed] = np.asarray(mi.render(mi.load_dict(exported), spp=4, seed=seed))
    np.testing.assert_array_equal(images[5, 0], images[0, 5])
    assert not np.array_equal(images[5, 0], images[0, 0])
