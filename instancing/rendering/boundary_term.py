"""Boundary term of image derivatives: edge sampling of moving instances' silhouettes.

A pixel value is an integral over the film, ``I = int f(x; theta) k(x) dx``
(k: the pixel filter, x in pixels). Where f jumps across a curve that moves
with theta (a silhouette, a crease of a flat-shaded mesh, the rim of an open
shape), the derivative gains a line integral (Li et al., "Differentiable
Monte Carlo Ray Tracing through Edge Sampling", 2018)::

    dI/dtheta = int df/dtheta k dx  +  oint (f(x - eps n) - f(x + eps n)) (n . dx/dtheta) k dl

The first term is the interior term (AD through the re-attached
intersection and shading); this module estimates the second.

**Curves in object space.** Affine maps send tangent rays to tangent rays,
so a silhouette seen from the camera at world position c is the image of the
silhouette seen from ``c_obj = M^-1 c`` on the untransformed model. Each
model's discontinuity curves are computed in closed form in object space
(float64, once per frame) and mapped through the instance's differentiable
``world_from_object``; this holds for any invertible affine map, shear and
reflection included:

* sphere: the circle of tangency ``x . c_obj = 1`` (none from inside);
* cylinder: the two tangent lines ``q . c_xy = 1`` (from outside its
  infinite extension) and the rims at z = 0 and z = 1 (open ends);
* disk: its rim; rectangle: its four sides;
* cube and meshes: edges whose two faces are not coplanar (flat shading
  jumps there) unless both faces look away from the camera (one-sided
  materials are black there on both sides), and every boundary or
  non-manifold edge.

Curves hidden behind other surfaces are sampled too; there both side rays
see the occluder and the term vanishes. Curves of instances that do not move
are skipped (their velocity is zero).

**Estimator.** A curve is picked with probability proportional to its
approximate film length (a floor keeps every curve possible), a point on it
uniformly in its parameter; the density per unit film length follows from
the film speed of the parameterisation. f is evaluated by the integrator on
both sides of the point, ``EDGE_OFFSET`` pixels away, with the same random
numbers; the velocity ``n . dx/dtheta`` comes from AD through the projection
of the moving point ``M(theta) x_obj`` (tangential sliding of a smooth
silhouette along the surface does not change the normal velocity, so
x_obj is kept fixed). The contribution has value 0 and derivative equal to
the boundary term, and is splatted into the pixels through the filter.

Limitations: only primary visibility (camera rays). Discontinuities seen
by shadow rays and BSDF-sampled rays (shadow boundaries, silhouettes in
reflections) are not sampled; the README states the measured bias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.backend import Array3f, Bool, Float, UInt32, device_arrays, dr
from ..core.rng import sample_streams
from ..core.transform import world_point, world_vector
from ..models.curves import Curves
from ..scene.camera import PerspectiveCamera

#: Distance (pixels) of the two side samples from the curve.
EDGE_OFFSET = 1e-3
#: Points per curve for the film-length estimate that drives curve selection.
POLYLINE_POINTS = 9
#: Every curve gets at least this fraction of the mean selection weight, so a
#: curve whose polyline estimate misses its visible part is still sampled.
WEIGHT_FLOOR = 0.01
#: Seed offsets that separate the boundary samples' streams (curve and point choice, and
#: the integrator's numbers on both sides of the curve) from the interior ones.
BOUNDARY_STREAM_SEED = 0x2545F491
SIDE_STREAM_SEED = 0x68E31DA4


def selection_weights(curves: Curves, to_world: np.ndarray, camera: PerspectiveCamera) -> np.ndarray:
    """Approximate film length (pixels) of each curve, floored; the curve-selection weights.

    ``to_world``: (K, 4, 4) world_from_object matrix of each curve's instance.
    """
    s = np.linspace(0.0, 1.0, POLYLINE_POINTS)
    pts = curves.points(s)
    world = np.einsum("kij,ksj->ksi", to_world[:, :3, :3], pts) + to_world[:, None, :3, 3]
    x, y, in_front = camera.project(Array3f(*[np.ascontiguousarray(world[..., k].ravel(), np.float32)
                                             for k in range(3)]))
    film = np.stack([np.asarray(x), np.asarray(y)], axis=-1).reshape(len(curves), POLYLINE_POINTS, 2)
    front = np.asarray(in_front).reshape(len(curves), POLYLINE_POINTS)
    step = np.linalg.norm(np.diff(film, axis=1), axis=-1)
    both = front[:, 1:] & front[:, :-1]
    length = np.where(both, np.minimum(step, 4.0 * (camera.width + camera.height)), 0.0).sum(axis=1)
    floor = WEIGHT_FLOOR * max(length.mean(), 1e-3)
    return np.maximum(length, floor)


@dataclass
class BoundarySampler:
    """Dr.Jit form of a frame's curves with their selection distribution."""

    count: int  # padded capacity (a power of two)
    instance: UInt32
    circle: UInt32  # 1 for circles, 0 for segments
    c: Array3f
    u: Array3f
    v: Array3f
    cdf: Float
    probability: Float

    @staticmethod
    def build(curves: Curves, weights: np.ndarray) -> "BoundarySampler":
        """Upload the curves, padded to a power of two (padding is never picked), so that
        the sampling kernel changes only when the curve count crosses a power of two."""
        capacity = 1 << max(0, int(len(curves) - 1).bit_length())
        pad = capacity - len(curves)

        total = weights.sum()
        cdf = np.concatenate([np.cumsum(weights) / total, np.full(pad, 2.0)])
        cdf[len(curves) - 1] = 1.0
        probability = np.concatenate([weights / total, np.ones(pad)])
        # In Dr.Jit's own storage (backend.device_arrays): an array wrapping a NumPy
        # buffer makes a recorded optimisation step record anew whenever the buffer's
        # alignment differs.
        points = [np.concatenate([a, np.zeros((pad, 3))])[:, k] for a in (curves.c, curves.u, curves.v)
                  for k in range(3)]
        floats = device_arrays(Float, *points, cdf, probability)
        ints = device_arrays(UInt32, np.concatenate([curves.instance, np.zeros(pad, np.int64)]),
                             np.concatenate([curves.circle, np.zeros(pad, bool)]))
        return BoundarySampler(capacity, ints[0], ints[1], Array3f(*floats[0:3]),
                               Array3f(*floats[3:6]), Array3f(*floats[6:9]), floats[9], floats[10])

    def sample(self, u_pick: Float, u_param: Float) -> tuple[UInt32, Array3f, Array3f, Float]:
        """Pick curves and points on them: (instance, object point, d point / ds, probability)."""
        # First curve whose cumulative weight exceeds u_pick (u_pick < 1 <= the last real entry).
        k = dr.binary_search(0, self.count - 1, lambda i: dr.gather(Float, self.cdf, i) <= u_pick)
        circle = dr.gather(UInt32, self.circle, k) != 0
        c, u, v = (dr.gather(Array3f, a, k) for a in (self.c, self.u, self.v))
        sin, cos = dr.sincos(2.0 * math.pi * u_param)
        a = dr.select(circle, cos, u_param)
        b = dr.select(circle, sin, 0.0)
        point = c + u * a + v * b
        tangent = dr.select(circle, (v * cos - u * sin) * (2.0 * math.pi), u)
        return dr.gather(UInt32, self.instance, k), point, tangent, dr.gather(Float, self.probability, k)


def _gaussian_weight(offset: Float, stddev: float, radius: float) -> Float:
    """Truncated normal density (per pixel) of a film offset, 0 beyond the radius."""
    norm = stddev * math.sqrt(2 * math.pi) * math.erf(radius / (stddev * math.sqrt(2)))
    return dr.select(dr.abs(offset) <= radius, dr.exp(-0.5 * dr.square(offset / stddev)) / norm, 0.0)


def boundary_sampler(scene, camera: PerspectiveCamera) -> BoundarySampler | None:
    """The frame's curve-selection distribution: the moving instances' discontinuity
    curves seen from the camera, with their weights (host work, from the detached
    transforms); None when no moving instance has a curve."""
    moving = scene.moving_instances
    if not len(moving):
        return None
    cam_pos = np.asarray(camera.world_from_camera.matrix, np.float64)[:3, 3]
    curves = scene.discontinuity_curves(cam_pos, moving)
    if not len(curves):
        return None
    return BoundarySampler.build(curves, selection_weights(
        curves, scene.instances.to_world_of(curves.instance), camera))


def boundary_term(sampler_data: BoundarySampler | None, scene, camera: PerspectiveCamera,
                  radiance: Callable, channels: int, sppp: int, seed: UInt32, max_lanes: int,
                  filter_radius: float | None, filter_stddev: float) -> list[Float] | None:
    """Per-pixel boundary contribution (value 0, derivative = the boundary term).

    Args:
        sampler_data: the frame's curves (:func:`boundary_sampler`); the Dr.Jit work
            here reads only arrays, so an optimisation step can be recorded.
        scene: the scene; only ``scene.moving_instances`` contribute.
        camera: the camera the image is rendered from.
        radiance: ``radiance(o, d, sampler) -> list[Float]`` of ``channels``
            values per ray (the integrator, evaluated detached here).
        sppp: boundary samples per pixel (the total is sppp * W * H).
        seed: render seed (an opaque UInt32).
        max_lanes: samples traced at once at most.
        filter_radius: None for the box filter, else the Gaussian's radius (pixels).
        filter_stddev: the Gaussian's standard deviation (pixels).

    Returns:
        one Float of W * H pixels per channel (row-major), or None when there are
        no curves or no samples.
    """
    if sampler_data is None or sppp <= 0:
        return None
    w, h = camera.width, camera.height
    total = sppp * w * h
    image = [dr.zeros(Float, w * h) for _ in range(channels)]
    table = scene.instances
    for first in range(0, total, max_lanes):
        lanes = min(max_lanes, total - first)
        index = dr.arange(UInt32, lanes) + dr.opaque(UInt32, first)
        rng = sample_streams(index, seed + BOUNDARY_STREAM_SEED)
        instance, x_obj, tangent, probability = sampler_data.sample(rng.next_float32(),
                                                                    rng.next_float32())
        # Map the curve point through the instance's differentiable transform.
        rows = table.forward(instance)
        p = world_point(rows, x_obj)
        fx, fy, in_front = camera.project(p)
        # Film-space tangent and unit normal of the curve at the sample (detached).
        with dr.suspend_grad():
            tx, ty = camera.film_velocity(p, world_vector(rows, tangent))
            speed = dr.sqrt(dr.fma(tx, tx, ty * ty))
            nx, ny = ty / speed, -tx / speed
            x0, y0 = dr.detach(fx), dr.detach(fy)
            margin = 0.0 if filter_radius is None else filter_radius
            valid = in_front & (speed > 0) & (x0 >= -margin) & (x0 < w + margin) \
                & (y0 >= -margin) & (y0 < h + margin)
            # Step 1: f on both sides of the curve, with the same random numbers.
            sides = []
            for sign in (-1.0, 1.0):
                o, d = camera.rays((x0 + sign * EDGE_OFFSET * nx) / w,
                                   (y0 + sign * EDGE_OFFSET * ny) / h)
                side_rng = sample_streams(index, seed + SIDE_STREAM_SEED)
                sides.append(radiance(o, d, side_rng))
            # Step 2: Monte Carlo weight 1 / (pdf per film length * sample count).
            weight = dr.select(valid, speed / (probability * total), 0.0)
        # Step 3: normal velocity of the moving point (AD), value 0.
        velocity = nx * (fx - x0) + ny * (fy - y0)
        for ch in range(channels):
            contribution = (sides[0][ch] - sides[1][ch]) * weight * velocity
            _splat(image[ch], contribution, x0, y0, valid, w, h, filter_radius, filter_stddev)
    return image


def _splat(target: Float, value: Float, x: Float, y: Float, valid: Bool, w: int, h: int,
           radius: float | None, stddev: float) -> None:
    """Add film-space contributions to the pixels whose filter covers (x, y)."""
    if radius is None:
        px, py = UInt32(dr.floor(x)), UInt32(dr.floor(y))
        dr.scatter_reduce(dr.ReduceOp.Add, target, value, py * w + px, valid)
        return
    reach = int(math.ceil(radius))
    bx, by = dr.floor(x), dr.floor(y)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            px, py = bx + dx, by + dy
            inside = valid & (px >= 0) & (px < w) & (py >= 0) & (py < h)
            k = _gaussian_weight(px + 0.5 - x, stddev, radius) * _gaussian_weight(py + 0.5 - y, stddev, radius)
            dr.scatter_reduce(dr.ReduceOp.Add, target, value * k,
                              UInt32(py) * w + UInt32(px), inside & (k > 0))
