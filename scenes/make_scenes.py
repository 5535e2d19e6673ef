"""Generate the example scenes in this folder (deterministic: seeded NumPy).

Run ``python scenes/make_scenes.py``; it rewrites the same files byte for byte.
Every scene uses only the analytic models and the meshes written by
``scenes/meshes/generate.py`` (no third-party data), has a 320x240 camera and
is lit by the lights listed below. What each scene shows:

* ``forest.json``: instancing. ONE mesh model (``meshes/tree.ply``) placed 400
  times on a ground rectangle, each tree with its own rotation about z,
  non-uniform scale (wider or narrower crowns, taller or shorter trees), some
  of them mirrored by ``{"reflect": "x"}``, and one of eight green and brown
  materials. Lit by a low sun (``directional``) and a sky (``constant``).
* ``cornell_box.json``: the classic Cornell box built only from transformed
  rectangles (floor, ceiling, back wall, red left wall, green right wall, all
  with their normals turned into the room) and two rotated, non-uniformly
  scaled cubes. The only light is an area emitter on a small rectangle just
  below the ceiling, mirrored by ``{"reflect": "z"}`` so that its +z normal,
  the side it emits from, points down. Best rendered with ``--integrator path``
  (colour bleeding from the walls).
* ``affine_shapes.json``: what affine maps do to every model kind:
  ellipsoids (spheres under non-uniform scale and rotation), shear given as
  raw 4x4 matrices (a leaning box, a leaning cylinder capped by a sheared disk,
  i.e. an ellipse, a slanted torus mesh), and reflections (negative
  determinant): a sheared tree and its mirror image, a sheared box and its
  mirror image. Lit by a point light and a dim environment.
* ``sphere_field.json``: 10 000 sphere instances whose transforms come from
  three ``.npy`` files of (N, 4, 4) float32 matrices
  (``sphere_field_a.npy``, ``_b``, ``_c``; an entry with a ``.npy`` file
  stands for N instances sharing one material), random positions in a box,
  random radii, on a ground rectangle; a directional light and an environment.
* ``light_point.json``, ``light_directional.json``, ``light_constant.json``,
  ``light_spot.json``, ``light_area.json``: the same small set of objects on a ground plane, each
  lit by one light type only. The area scene's lamp is an emitting elliptical disk
  (a disk under non-uniform scale), so the area light is neither a rectangle
  nor a uniformly scaled shape.
* ``recover_target.json`` and ``recover_init.json``: gradient-based recovery
  (``instancing recover recover_target.json --init recover_init.json``). Three
  instances of different kinds, each non-uniformly scaled so that its
  rotation is observable: a box, a card (rectangle) and an elliptic torus mesh,
  on a ground plane lit by a lamp at the camera, 128x128. The
  initial scene moves each by 15-20 % of its size, turns it by 18-22 degrees
  about a tilted axis, and scales its axes by +-20 % (not the card's z axis, which
  has no effect on a flat shape).
* ``materials/textures/tiles.png``: the texture of ``materials/bitmap.xml``, 64x32 8-bit
  sRGB: coloured tiles in a dark grid, a bright marker in the top-left tile (so that a
  flipped or shifted lookup shows).
* ``materials/textures/bumps.png``: the normal map of ``materials/normalmap.xml``, 64x64
  8-bit, read raw: a 4x4 grid of round bumps, their normals tilted up to 65 degrees
  towards their rims, flat between them.
* ``materials/textures/ripples.png``: the height map of ``materials/bumpmap.xml``, 64x64 8-bit
  grey (as RGB), read raw: concentric ripples around the image's centre, four periods
  across it.
* ``materials/textures/bands.vol``: the volume grid of ``materials/volume.xml``, 16 x 16 x 16
  cells of float RGB in Mitsuba's ``.vol`` format: colour bands running diagonally through
  the cube, a white cell at its (0, 0, 0) corner (so that a flipped or shifted lookup shows).
* ``media/plume.vol``: the density grid of ``media/plume.xml``, 24 x 24 x 24 cells of one float
  channel: three soft blobs of smoke (Gaussian in distance, the lowest densest) stacked
  upwards, 0.98 at most.
* ``textures/sky.exr``: the environment map of ``envmap.xml``, 128x64 latitude-longitude
  (+y up, Mitsuba's convention), float RGB: a blue sky brightening to the horizon, a
  brown ground below it and a sun (10 degrees across, 40 degrees high), so that
  lighting depends on direction and shadows are sharp.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
WIDTH, HEIGHT = 320, 240
Z_UP = [0, 0, 1]


# -- small helpers ------------------------------------------------------------------------------


def r(x, digits: int = 4):
    """Round a number or nested list so that the JSON stays short and stable."""
    if isinstance(x, (list, tuple, np.ndarray)):
        return [r(v, digits) for v in x]
    value = round(float(x), digits)
    return int(value) if value == int(value) and abs(value) < 1e15 else value


def translate(v) -> dict:
    return {"translate": r(v)}


def rotate(axis, angle: float) -> dict:
    return {"rotate": {"axis": list(axis), "angle": r(angle, 3)}}


def scale(s) -> dict:
    return {"scale": r(s)}


def look_at(origin, target, up=Z_UP) -> list:
    return [{"look_at": {"origin": r(origin), "target": r(target), "up": list(up)}}]


def camera(origin, target, fov: float) -> dict:
    return {"type": "perspective", "fov": fov, "width": WIDTH, "height": HEIGHT,
            "to_world": look_at(origin, target)}


def diffuse(rgb) -> dict:
    return {"type": "diffuse", "reflectance": r(rgb, 3)}


def ground(half_size: float, material: str = "ground") -> dict:
    """The z = 0 plane as a rectangle of the given half size, normal +z (up)."""
    return {"id": "ground", "model": "rectangle", "material": material,
            "to_world": [scale([half_size, half_size, 1])]}


def shear_matrix(linear, offset) -> list:
    """A 4x4 row-major affine matrix from a 3x3 linear part and a translation."""
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = offset
    return r(m)


def _dumps(value, indent: int = 0, step: int = 1) -> str:
    """JSON with one entry per line, but short lists and small objects kept on one line."""
    flat = json.dumps(value, separators=(", ", ": "))
    if len(flat) + indent <= 100 or not isinstance(value, (dict, list)):
        return flat
    pad, inner = " " * indent, " " * (indent + step)
    if isinstance(value, dict):
        items = [f"{inner}{json.dumps(k)}: {_dumps(v, indent + step, step)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    items = [inner + _dumps(v, indent + step, step) for v in value]
    return "[\n" + ",\n".join(items) + "\n" + pad + "]"


def write_scene(name: str, scene: dict) -> None:
    (HERE / name).write_text(_dumps(scene) + "\n")


# -- 1. forest ----------------------------------------------------------------------------------


def forest(rng: np.random.Generator, count: int = 400) -> dict:
    """One tree mesh, ``count`` instances with varied transforms and materials."""
    materials = {
        "ground": diffuse([0.32, 0.36, 0.18]),
        "pine": diffuse([0.08, 0.30, 0.10]),
        "fir": diffuse([0.12, 0.40, 0.15]),
        "spruce": diffuse([0.05, 0.22, 0.12]),
        "meadow": diffuse([0.30, 0.55, 0.15]),
        "olive": diffuse([0.35, 0.40, 0.12]),
        "autumn": diffuse([0.55, 0.35, 0.10]),
        "rust": diffuse([0.45, 0.20, 0.08]),
        "bark": diffuse([0.30, 0.20, 0.12]),
    }
    tree_materials = [m for m in materials if m != "ground"]
    weights = np.array([5, 5, 4, 3, 2, 1.2, 1, 0.6])
    weights /= weights.sum()
    # Positions in a disk of radius 15, rejecting those too close to an earlier tree
    # (a dart-throwing Poisson-disk sampler; seeded, so always the same forest).
    radius, min_gap = 15.0, 1.0
    points: list[np.ndarray] = []
    while len(points) < count:
        p = rng.uniform(-radius, radius, 2)
        if np.hypot(*p) > radius:
            continue
        if points and np.min(np.linalg.norm(np.array(points) - p, axis=1)) < min_gap:
            continue
        points.append(p)
    instances = [ground(80.0)]
    for k, (x, y) in enumerate(points):
        width = rng.uniform(0.55, 1.0)
        squash = rng.uniform(0.75, 1.25)  # non-uniform crown: x and y scaled differently
        height = rng.uniform(0.6, 1.5)
        ops = [translate([x, y, 0]), rotate(Z_UP, rng.uniform(0, 360))]
        if rng.uniform() < 0.08:
            ops.append({"reflect": "x"})
        ops.append(scale([width * squash, width / squash, height]))
        material = str(rng.choice(tree_materials, p=weights))
        instances.append({"id": f"tree{k:03d}", "model": "tree", "material": material,
                          "to_world": ops})
    return {
        "models": {"tree": {"type": "ply", "filename": "meshes/tree.ply", "face_normals": True}},
        "materials": materials,
        "instances": instances,
        "camera": camera([7, -31, 15], [-0.3, -0.5, 0], 52),
        "lights": [
            {"type": "directional", "direction": [-0.75, 0.35, -0.5], "irradiance": [3.2, 2.8, 2.2]},
            {"type": "constant", "radiance": [0.30, 0.38, 0.50]},
        ],
    }


# -- 2. Cornell box -----------------------------------------------------------------------------


def cornell_box() -> dict:
    """Room [-1, 1] x [-1, 1] x [0, 2] (z up), open at y = -1, one ceiling lamp."""
    wall = "rectangle"  # every wall is the canonical rectangle, normal turned into the room
    instances = [
        {"id": "floor", "model": wall, "material": "white", "to_world": []},
        {"id": "ceiling", "model": wall, "material": "white",
         "to_world": [translate([0, 0, 2]), {"reflect": "z"}]},
        {"id": "back", "model": wall, "material": "white",
         "to_world": [translate([0, 1, 1]), rotate([1, 0, 0], 90)]},  # normal -y
        {"id": "left", "model": wall, "material": "red",
         "to_world": [translate([-1, 0, 1]), rotate([0, 1, 0], 90)]},  # normal +x
        {"id": "right", "model": wall, "material": "green",
         "to_world": [translate([1, 0, 1]), rotate([0, 1, 0], -90)]},  # normal -x
        {"id": "tall_box", "model": "cube", "material": "white",
         "to_world": [translate([-0.34, 0.3, 0.6]), rotate(Z_UP, 17), scale([0.3, 0.29, 0.6])]},
        {"id": "short_box", "model": "cube", "material": "white",
         "to_world": [translate([0.36, -0.32, 0.3]), rotate(Z_UP, -18), scale([0.31, 0.29, 0.3])]},
        # The lamp: a small rectangle just below the ceiling, mirrored so that its
        # +z normal (the emitting side) points down into the room.
        {"id": "lamp", "model": wall, "material": "lamp",
         "to_world": [translate([0, 0, 1.985]), {"reflect": "z"}, scale([0.235, 0.19, 1])],
         "emitter": {"type": "area", "radiance": [18.4, 14.0, 6.75]}},
    ]
    return {
        "materials": {
            "white": diffuse([0.725, 0.71, 0.68]),
            "red": diffuse([0.63, 0.065, 0.05]),
            "green": diffuse([0.14, 0.45, 0.091]),
            "lamp": diffuse([0.78, 0.78, 0.78]),
        },
        "instances": instances,
        "camera": camera([0, -4.0, 1], [0, 0, 1], 47),
        "lights": [],
    }


# -- 3. affine shapes ---------------------------------------------------------------------------


def affine_shapes() -> dict:
    """Ellipsoids, sheared cube / cylinder / disk / torus, and mirrored (det < 0) pairs.

    Back row, left to right: an ellipsoid, a sheared box, a sheared torus, a leaning box
    and its mirror image. Front row: a tilted ellipsoid, a leaning elliptic tube with its
    sheared-disk cap, a leaning tree and its mirror image.
    """
    lean = np.array([[1, 0, 0.55], [0, 1, 0.2], [0, 0, 1]])  # x += 0.55 z, y += 0.2 z
    box_shear = np.array([[0.45, 0.35, 0.25], [0, 0.45, 0], [0, 0, 0.45]])
    tube = np.array([[0.4, 0.2, 0.5], [0, 0.35, 0], [0, 0, 1.3]])  # elliptic, leaning, height 1.3
    tube_at = np.array([-1.3, -0.9, 0])
    tilt = np.array([[1, 0, 0], [0, np.cos(np.radians(50)), -np.sin(np.radians(50))],
                     [0, np.sin(np.radians(50)), np.cos(np.radians(50))]])  # turned to the camera
    torus_shear = np.array([[0.8, 0.45, 0], [0, 0.7, 0], [0, 0, 0.7]]) @ tilt
    mirror_x = np.diag([-1.0, 1, 1])
    instances = [
        ground(20.0),
        # Ellipsoids: non-uniform scale, one of them also rotated.
        {"id": "ellipsoid", "model": "sphere", "material": "red",
         "to_world": [translate([-2.9, 1.7, 0.5]), rotate(Z_UP, 25), scale([1.0, 0.45, 0.5])]},
        {"id": "tilted_ellipsoid", "model": "sphere", "material": "orange",
         "to_world": [translate([-2.7, -0.9, 0.56]), rotate([0.3, 1, 0], -55), scale([0.3, 0.4, 0.85])]},
        # Shear from raw matrices: cube, capped tube (the cap is a sheared disk), torus mesh.
        {"id": "sheared_box", "model": "cube", "material": "blue",
         "to_world": shear_matrix(box_shear, [-1.0, 1.9, 0.45])},
        {"id": "sheared_tube", "model": "cylinder", "material": "gold",
         "to_world": shear_matrix(tube, tube_at)},
        {"id": "sheared_cap", "model": "disk", "material": "teal",
         # The tube's matrix after lifting the unit disk to the tube's top (z = 1).
         "to_world": shear_matrix(tube, tube @ [0, 0, 1] + tube_at)},
        {"id": "sheared_torus", "model": "torus", "material": "purple",
         "to_world": shear_matrix(torus_shear, [0.8, 2.0, 0.7])},
        # Reflections (negative determinant): each shape's right-hand neighbour is its
        # mirror image in x; the lean shows which is which.
        {"id": "leaning_box", "model": "cube", "material": "pink",
         "to_world": shear_matrix(0.35 * lean, [2.5, 2.1, 0.35])},
        {"id": "mirrored_box", "model": "cube", "material": "pink",
         "to_world": [translate([3.9, 2.1, 0.35]), {"reflect": "x"},
                      {"matrix": shear_matrix(0.35 * lean, [0, 0, 0])}]},
        {"id": "leaning_tree", "model": "tree", "material": "green",
         "to_world": shear_matrix(0.75 * lean, [0.5, -0.8, 0])},
        {"id": "mirrored_tree", "model": "tree", "material": "green",
         "to_world": shear_matrix(mirror_x @ (0.75 * lean), [3.0, -0.8, 0])},
    ]
    return {
        "models": {"torus": {"type": "obj", "filename": "meshes/torus.obj"},
                   "tree": {"type": "ply", "filename": "meshes/tree.ply", "face_normals": True}},
        "materials": {
            "ground": diffuse([0.6, 0.6, 0.58]),
            "red": diffuse([0.8, 0.15, 0.1]),
            "orange": diffuse([0.85, 0.45, 0.1]),
            "blue": diffuse([0.15, 0.3, 0.8]),
            "gold": diffuse([0.85, 0.65, 0.2]),
            "teal": diffuse([0.1, 0.6, 0.6]),
            "purple": diffuse([0.5, 0.2, 0.7]),
            "green": diffuse([0.2, 0.6, 0.25]),
            "pink": diffuse([0.85, 0.35, 0.5]),
        },
        "instances": instances,
        "camera": camera([0.4, -6.6, 5.2], [0.4, 0.6, 0.45], 56),
        "lights": [
            {"type": "point", "position": [-2.5, -3.5, 6.0], "intensity": [90, 85, 75]},
            {"type": "constant", "radiance": [0.18, 0.2, 0.24]},
        ],
    }


# -- 4. sphere field ----------------------------------------------------------------------------


def sphere_field(rng: np.random.Generator, count: int = 10_000) -> tuple[dict, dict[str, np.ndarray]]:
    """``count`` spheres from three .npy matrix files (one material each)."""
    radius = rng.uniform(0.06, 0.2, count)
    centre = np.column_stack([rng.uniform(-9, 9, count), rng.uniform(-9, 9, count),
                              radius + rng.uniform(0, 2.5, count)])
    matrices = np.zeros((count, 4, 4), np.float32)
    matrices[:, [0, 1, 2], [0, 1, 2]] = radius[:, None]
    matrices[:, :3, 3] = centre
    matrices[:, 3, 3] = 1
    group = rng.choice(3, count, p=[0.45, 0.35, 0.2])
    files, instances = {}, [ground(40.0)]
    for g, (suffix, material) in enumerate(zip("abc", ["coral", "sky", "cream"])):
        name = f"sphere_field_{suffix}.npy"
        files[name] = np.ascontiguousarray(matrices[group == g])
        instances.append({"id": f"spheres_{suffix}", "model": "sphere", "material": material,
                          "to_world": name})
    scene = {
        "materials": {
            "ground": diffuse([0.55, 0.55, 0.55]),
            "coral": diffuse([0.85, 0.3, 0.2]),
            "sky": diffuse([0.2, 0.45, 0.85]),
            "cream": diffuse([0.9, 0.85, 0.7]),
        },
        "instances": instances,
        "camera": camera([0, -15, 7.5], [0, -1, 0.5], 60),
        "lights": [
            {"type": "directional", "direction": [0.4, 0.6, -1.0], "irradiance": [2.8, 2.7, 2.5]},
            {"type": "constant", "radiance": [0.25, 0.28, 0.33]},
        ],
    }
    return scene, files


# -- 5. one scene per light type ----------------------------------------------------------------


def light_scene(light: str) -> dict:
    """A sphere, a box and a torus on a ground plane, lit by one light type only."""
    instances = [
        ground(25.0),
        {"id": "ball", "model": "sphere", "material": "red",
         "to_world": [translate([-1.3, 0.2, 0.6]), scale(0.6)]},
        {"id": "box", "model": "cube", "material": "blue",
         "to_world": [translate([0.2, 0.8, 0.5]), rotate(Z_UP, 30), scale([0.5, 0.5, 0.5])]},
        {"id": "torus", "model": "torus", "material": "gold",
         "to_world": [translate([1.4, -0.6, 0.3]), scale(0.75)]},
    ]
    lights = {
        "point": [{"type": "point", "position": [1.5, -1.5, 3.0], "intensity": [25, 24, 22]}],
        "directional": [{"type": "directional", "direction": [0.5, 0.7, -1.0],
                         "irradiance": [3.0, 2.9, 2.7]}],
        "constant": [{"type": "constant", "radiance": [0.9, 0.95, 1.0]}],
        "spot": [{"type": "spot", "intensity": [40, 38, 34], "cutoff_angle": 28, "beam_width": 18,
                  "to_world": look_at([1.5, -1.5, 3.0], [0.0, 0.2, 0.4])}],
        "area": [],
    }[light]
    if light == "area":
        # An elliptical lamp: a disk under non-uniform scale, mirrored so that its +z
        # normal (the side it emits from) faces down. (An ellipsoid would do for us, but
        # Mitsuba's sphere refuses non-uniform scale, and this scene is cross-checked.)
        instances.append({"id": "lamp", "model": "disk", "material": "white",
                          "to_world": [translate([0.1, 0.4, 2.2]), rotate(Z_UP, 20),
                                       {"reflect": "z"}, scale([1.0, 0.45, 1.0])],
                          "emitter": {"type": "area", "radiance": [16.0, 14.0, 11.0]}})
    return {
        "models": {"torus": {"type": "obj", "filename": "meshes/torus.obj"}},
        "materials": {
            "ground": diffuse([0.6, 0.6, 0.6]),
            "red": diffuse([0.8, 0.15, 0.1]),
            "blue": diffuse([0.15, 0.3, 0.8]),
            "gold": diffuse([0.85, 0.65, 0.2]),
            "white": diffuse([0.8, 0.8, 0.8]),
        },
        "instances": instances,
        "camera": camera([0, -5.6, 4.4], [0, 0.2, 0.4], 52),
        "lights": lights,
    }


# -- 7. recovery --------------------------------------------------------------------------------

#: (id, model, material, translation, rotation axis, angle, scale) of the recovery targets.
RECOVERY_TARGETS = [
    ("box", "cube", "blue", [-1.5, 0.3, 0.5], [0.5, -0.3, 1.0], 40.0, [0.5, 0.35, 0.42]),
    ("card", "rectangle", "red", [0.05, 0.7, 0.75], [1.0, 0.15, 0.1], 72.0, [0.5, 0.38, 1.0]),
    ("ring", "torus", "gold", [1.6, -0.1, 0.55], [1.0, 0.2, 0.0], 60.0, [0.6, 0.42, 0.5]),
]
#: Per instance: translation offset (fraction of its size, along a direction), extra rotation
#: (object-space axis, degrees) and per-axis scale factors of the initial guess.
RECOVERY_PERTURBATIONS = {
    "box": (0.2, [1.0, -0.5, 0.3], [0.2, 1.0, 0.3], 20.0, [1.2, 0.8, 1.2]),
    # A rectangle's z scale changes nothing: it is left alone.
    "card": (0.2, [-0.4, 0.2, 1.0], [0.3, 1.0, 0.2], 22.0, [1.2, 0.8, 1.0]),
    "ring": (0.15, [0.3, 1.0, -0.4], [0.1, 1.0, 0.6], 18.0, [1.2, 1.2, 0.8]),
}
#: Extent of each model kind along its object axes (the torus mesh spans 2 x 2 x 0.6).
MODEL_EXTENT = {"cube": [2, 2, 2], "rectangle": [2, 2, 0], "torus": [2, 2, 0.6]}


#: The recovery scenes' camera position (also their lamp's).
CAMERA_ORIGIN = [0.0, -4.4, 2.0]


def recovery_scene(perturbed: bool) -> dict:
    """The recovery target, or its perturbed initial guess (see the module docstring)."""
    instances = [ground(6.0)]
    for name, model, material, t, axis, angle, s in RECOVERY_TARGETS:
        ops = [translate(t), rotate(axis, angle)]
        if perturbed:
            size, direction, extra_axis, extra_angle, factors = RECOVERY_PERTURBATIONS[name]
            # The instance's size: the largest extent of its scaled model.
            extent = max(np.asarray(MODEL_EXTENT[model]) * s)
            offset = size * extent * np.asarray(direction) / np.linalg.norm(direction)
            ops = [translate(np.asarray(t) + offset), rotate(axis, angle),
                   rotate(extra_axis, extra_angle)]
            s = list(np.asarray(s) * factors)
        instances.append({"id": name, "model": model, "material": material,
                          "to_world": ops + [scale(s)]})
    cam = camera(CAMERA_ORIGIN, [0.0, 0.2, 0.5], 48)
    cam.update(width=128, height=128)
    return {
        "models": {"torus": {"type": "obj", "filename": "meshes/torus.obj"}},
        "materials": {"ground": diffuse([0.55, 0.55, 0.55]), "red": diffuse([0.8, 0.2, 0.15]),
                      "blue": diffuse([0.2, 0.35, 0.8]), "gold": diffuse([0.85, 0.65, 0.2])},
        "instances": instances,
        "camera": cam,
        # A lamp at the camera: its shadows hide behind the objects that cast them (this
        # renderer does not differentiate shadow boundaries), and its inverse-square
        # fall-off tells near from far, which the silhouettes alone barely do.
        "lights": [{"type": "point", "position": CAMERA_ORIGIN, "intensity": [22, 21, 20]}],
    }


def terrain() -> dict:
    """The large-mesh scene: one heightfield of 100 352 triangles (meshes/terrain.ply,
    smooth: its vertex normals), scaled to 16 x 16 units, under a low sun and a sky."""
    return {
        "models": {"terrain": {"type": "ply", "filename": "meshes/terrain.ply"}},
        "materials": {"ground": diffuse([0.42, 0.38, 0.3])},
        "instances": [{"id": "terrain", "model": "terrain", "material": "ground",
                       "to_world": [scale([8, 8, 8])]}],
        "camera": camera([-5.5, -4.5, 5.5], [2.0, 2.5, -0.5], 60),
        "lights": [{"type": "directional", "direction": [0.85, -0.35, -0.4], "irradiance": [2.6, 2.4, 2.1]},
                   {"type": "constant", "radiance": [0.22, 0.27, 0.36]}],
    }


def tiles_texture(width: int = 64, height: int = 32, tile: int = 8) -> np.ndarray:
    """(height, width, 3) uint8 sRGB codes of coloured tiles in a dark grid, with a bright
    marker in the top-left tile."""
    y, x = np.mgrid[0:height, 0:width]
    tx, ty = x // tile, y // tile
    hue = (tx * 0.13 + ty * 0.29) % 1.0
    rgb = 0.5 + 0.4 * np.cos(2 * np.pi * (hue[..., None] + [0.0, 1 / 3, 2 / 3]))
    rgb[(x % tile == 0) | (y % tile == 0)] = 0.08
    rgb[2:6, 2:6] = [1.0, 0.95, 0.6]
    return np.round(rgb * 255).astype(np.uint8)


def bumps_texture(size: int = 64, cells: int = 4) -> np.ndarray:
    """(size, size, 3) uint8 codes of a normal map, (n + 1) / 2 per component: round bumps
    in a ``cells`` x ``cells`` grid (normals along (x, y, sqrt(0.64 - r^2) + 0.3) within
    radius 0.8 of a cell's centre, x and y in [-1, 1] across it), +z between them."""
    cell = size // cells
    y, x = np.mgrid[0:size, 0:size]
    x = ((x % cell) + 0.5) / cell * 2.0 - 1.0
    y = ((y % cell) + 0.5) / cell * 2.0 - 1.0
    r2 = x * x + y * y
    inside = r2 < 0.64
    n = np.stack([np.where(inside, x, 0.0), np.where(inside, y, 0.0),
                  np.where(inside, np.sqrt(np.maximum(0.64 - r2, 0.0)) + 0.3, 1.0)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.round((n + 1.0) / 2.0 * 255).astype(np.uint8)


def ripples_texture(size: int = 64, periods: float = 4.0) -> np.ndarray:
    """(size, size, 3) uint8 grey codes of a height map: 0.5 + 0.4 cos of the distance
    from the centre, ``periods`` ripples from the centre to an edge's middle."""
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size - 0.5
    height = 0.5 + 0.4 * np.cos(2.0 * np.pi * periods * 2.0 * np.hypot(x, y))
    return np.repeat(np.round(height * 255).astype(np.uint8)[..., None], 3, axis=2)


def sky(width: int = 128, height: int = 64) -> np.ndarray:
    """(height, width, 3) float32 linear radiance of a sky with a sun, latitude-longitude:
    row j at theta = pi j / (height - 1) from +y, column i at phi = 2 pi (i + 1/2) / width,
    direction (sin phi sin theta, cos theta, -cos phi sin theta)."""
    theta = np.pi * np.arange(height) / (height - 1)
    phi = 2 * np.pi * (np.arange(width) + 0.5) / width
    t, f = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(f) * np.sin(t), np.cos(t), -np.cos(f) * np.sin(t)], axis=-1)
    up = d[..., 1:2]
    rgb = np.where(up > 0, np.array([0.25, 0.45, 0.9]) * (0.5 + 0.8 * (1 - up)),
                   np.array([0.18, 0.14, 0.1]))
    elevation, azimuth = np.radians(40.0), 1.0
    sun = np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation),
                    -np.cos(azimuth) * np.cos(elevation)])
    rgb[d @ sun > np.cos(np.radians(5.0))] = [100.0, 95.0, 82.0]
    return rgb.astype(np.float32)


def bands_grid(size: int = 16) -> np.ndarray:
    """(z, y, x, 3) float32 cell values of ``materials/textures/bands.vol`` (module docstring)."""
    z, y, x = np.meshgrid(*(np.arange(size) + 0.5,) * 3, indexing="ij")
    phase = 2 * np.pi * (x + 0.5 * y + 0.25 * z) / size
    grid = np.stack([0.5 + 0.4 * np.sin(phase), 0.5 + 0.4 * np.sin(phase + 2.1),
                     0.5 + 0.4 * np.sin(2 * phase + 4.2)], axis=-1)
    grid[0, 0, 0] = 1.0
    return grid.astype(np.float32)


def plume_grid(size: int = 24) -> np.ndarray:
    """(z, y, x, 1) float32 cell values of ``media/plume.vol`` (module docstring)."""
    z, y, x = np.meshgrid(*(np.linspace(0, 1, size),) * 3, indexing="ij")
    density = np.zeros((size, size, size))
    for cx, cy, cz, radius, peak in [(0.5, 0.5, 0.3, 0.22, 1.0), (0.42, 0.55, 0.55, 0.18, 0.8),
                                     (0.6, 0.45, 0.72, 0.15, 0.6)]:
        density += peak * np.exp(-2 * ((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / radius ** 2)
    return density.astype(np.float32)[..., None]


def write_volume_grid(path: Path, values: np.ndarray) -> None:
    """``values`` (z, y, x, channels) as a Mitsuba ``.vol`` file over the unit cube."""
    z, y, x, c = values.shape
    header = struct.pack("<3sBiiiii6f", b"VOL", 3, 1, x, y, z, c, 0, 0, 0, 1, 1, 1)
    path.write_bytes(header + values.astype("<f4").tobytes())


def write_png(path: Path, codes: np.ndarray) -> None:
    """Write 8-bit RGB codes as a PNG (filter 0 on every row, zlib level 9)."""
    height, width, _ = codes.shape
    raw = b"".join(b"\x00" + codes[row].tobytes() for row in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"sRGB", b"\x00")
                     + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def main() -> None:
    write_scene("forest.json", forest(np.random.default_rng(2024)))
    write_scene("cornell_box.json", cornell_box())
    write_scene("affine_shapes.json", affine_shapes())
    scene, files = sphere_field(np.random.default_rng(10_000))
    for name, matrices in files.items():
        np.save(HERE / name, matrices)
    write_scene("sphere_field.json", scene)
    for light in ("point", "directional", "constant", "spot", "area"):
        write_scene(f"light_{light}.json", light_scene(light))
    write_scene("recover_target.json", recovery_scene(perturbed=False))
    write_scene("recover_init.json", recovery_scene(perturbed=True))
    write_scene("terrain.json", terrain())
    write_png(HERE / "materials" / "textures" / "tiles.png", tiles_texture())
    write_png(HERE / "materials" / "textures" / "bumps.png", bumps_texture())
    write_png(HERE / "materials" / "textures" / "ripples.png", ripples_texture())
    write_volume_grid(HERE / "materials" / "textures" / "bands.vol", bands_grid())
    write_volume_grid(HERE / "media" / "plume.vol", plume_grid())
    # (Imported here: the other scenes need no renderer to be written.)
    from instancing.io.image import write_exr
    (HERE / "textures").mkdir(exist_ok=True)
    write_exr(HERE / "textures" / "sky.exr", sky())


if __name__ == "__main__":
    main()
