"""Fuzzed inputs for the readers: valid scenes and files, mutated by ``hypothesis``.

Each reader must either accept an input or raise one of the package's documented
exceptions (:class:`instancing.InstancingError` and its subclasses: ``SceneError``,
``MeshFileError``, ``TransformError``, ``ImageFileError``, ...): never another exception, a
NumPy warning, a crash or a hang. The inputs start from valid ones, so that the mutations
reach deep into each reader instead of stopping at its first check:

* scene dicts: a valid scene whose values at random places are replaced by random JSON
  (numbers of every size, integers beyond float64's range too, NaN and infinities, strings,
  lists, objects), keys dropped or added;
* JSON scene files: such a scene as text with plain instance entries of random matrices
  around its instances, with random bytes edited half of the time;
* Mitsuba XML: a valid scene text with random characters replaced, deleted or inserted and
  attribute values replaced by random text;
* OBJ, PLY (ASCII and binary) and serialized meshes, and EXR images: valid files with random
  bytes replaced, deleted or inserted, or cut short.

``tests/test_*`` run a fixed number of examples, derandomized (the same examples on every
run); ``python -m benchmarks.fuzz`` runs many more.
"""

from __future__ import annotations

import copy
import json
import re
import tempfile
import warnings
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, settings, strategies as st

import instancing
from instancing.io.image import read_exr, write_exr
from instancing.io.mesh_file import read_mesh
from instancing.io.volume_grid import read_volume_grid

#: Per-example time limit (ms): a reader that hangs on some input fails the example.
DEADLINE_MS = 20_000


def ci_settings(examples: int) -> settings:
    """Hypothesis settings of the CI run: ``examples`` examples, the same on every run."""
    return settings(max_examples=examples, derandomize=True, deadline=DEADLINE_MS,
                    database=None, suppress_health_check=[HealthCheck.too_slow])


# -- values ---------------------------------------------------------------------------------------

JSON_LEAVES = (st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70)
               | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=12)
               | st.sampled_from([0, -1, 1e300, -1e-300, 10 ** 400, -10 ** 400, "sphere", "diffuse",
                                  "x.obj", "", [], {}]))
JSON_VALUES = st.recursive(JSON_LEAVES, lambda inner: st.lists(inner, max_size=5)
                           | st.dictionaries(st.text(max_size=8), inner, max_size=4), max_leaves=12)

#: A valid scene touching most of the dict format: models, materials (textures included),
#: instances (a batch too), an emitter, lights, cameras.
VALID_SCENE = {
    "models": {"ball": {"type": "sphere"}, "pipe": {"type": "cylinder"}},
    "materials": {
        "red": {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]},
        "gold": {"type": "roughconductor", "material": "Au", "alpha": 0.2},
        "leaf": {"type": "mask", "opacity": {"type": "checkerboard", "color0": 1, "color1": 0.2},
                 "blade": {"type": "twosided", "bsdf": {"type": "diffuse"}}},
        "mix": {"type": "blendbsdf", "weight": 0.3, "a": {"type": "plastic"},
                "b": {"type": "dielectric", "int_ior": 1.5}},
    },
    "instances": [
        {"id": "a", "model": "ball", "material": "red",
         "to_world": [{"translate": [0, 0, 1]}, {"rotate": {"axis": [0, 0, 1], "angle": 30}},
                      {"scale": [1, 2, 0.5]}]},
        {"id": "b", "model": "pipe", "material": "gold", "to_world": [{"matrix": [
            [1, 0.2, 0, 0], [0, 1, 0, 2], [0, 0, 1, 0], [0, 0, 0, 1]]}]},
        {"id": "c", "model": "rectangle", "material": "leaf", "to_world": [{"scale": 4}]},
        {"id": "lamp", "model": "disk", "material": "mix", "emitter": {"type": "area", "radiance": 5},
         "to_world": [{"translate": [0, 0, 4]}, {"reflect": "z"}]},
    ],
    "lights": [{"type": "point", "position": [1, 2, 3], "intensity": 10},
               {"type": "spot", "intensity": 5, "cutoff_angle": 30,
                "to_world": [{"look_at": {"origin": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0]}}]},
               {"type": "constant", "radiance": 0.2}],
    "cameras": [{"type": "perspective", "fov": 40, "width": 16, "height": 12, "spp": 8,
                 "rfilter": {"type": "mitchell", "B": 0.3, "C": 0.35},
                 "to_world": [{"look_at": {"origin": [0, -6, 3], "target": [0, 0, 0], "up": [0, 0, 1]}}]},
                {"id": "top", "type": "orthographic", "width": 8, "height": 8, "pixel_format": "rgba",
                 "sampler": "stratified", "jitter": False}],
    "integrator": {"type": "prb", "max_depth": 4, "rr_depth": 3},
}


def _places(value, path=()):
    """Every (path, value) in a JSON-like value: dict keys and list indices."""
    yield path, value
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _places(item, path + (key,))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _places(item, path + (index,))


@st.composite
def mutated_scenes(draw) -> dict:
    """VALID_SCENE with one to four mutations: a value replaced by random JSON, a key or list
    item removed, or a key added."""
    scene = copy.deepcopy(VALID_SCENE)
    for _ in range(draw(st.integers(1, 4))):
        places = [p for p, _ in _places(scene) if p]
        path = draw(st.sampled_from(places))
        parent = scene
        for step in path[:-1]:
            parent = parent[step]
        action = draw(st.sampled_from(["replace", "replace", "remove", "add"]))
        if action == "replace":
            parent[path[-1]] = draw(JSON_VALUES)
        elif action == "remove":
            del parent[path[-1]]
        elif isinstance(parent, dict):
            parent[draw(st.text(max_size=10))] = draw(JSON_VALUES)
        else:
            parent.append(draw(JSON_VALUES))
    return scene


@st.composite
def mutated_json(draw) -> bytes:
    """A mutated scene as a JSON file's bytes, with plain instance entries (a model and one
    4x4 matrix, of random numbers or JSON values and of random shape) around its instances,
    half of the time with random bytes edited (:func:`mutated_bytes`)."""
    scene = draw(mutated_scenes())
    matrix = st.lists(st.lists(JSON_LEAVES | st.floats(), min_size=3, max_size=5), min_size=3,
                      max_size=5) | st.just(np.eye(4).tolist())
    plain = st.fixed_dictionaries({"model": st.sampled_from(["ball", "pipe"]), "to_world": matrix},
                                  optional={"id": st.text(max_size=4), "material": JSON_LEAVES})
    if isinstance(scene.get("instances"), list):
        scene["instances"] = (draw(st.lists(plain, max_size=3)) + scene["instances"]
                              + draw(st.lists(plain, max_size=3)))
    text = json.dumps(scene).encode()
    return draw(mutated_bytes(text)) if draw(st.booleans()) else text


# -- bytes ----------------------------------------------------------------------------------------

@st.composite
def mutated_bytes(draw, data: bytes) -> bytes:
    """``data`` with one to six edits: bytes replaced, deleted or inserted, or cut short."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 6))):
        if not out:
            break
        at = draw(st.integers(0, len(out) - 1))
        action = draw(st.sampled_from(["replace", "delete", "insert", "truncate"]))
        chunk = draw(st.binary(min_size=1, max_size=8))
        if action == "replace":
            out[at:at + len(chunk)] = chunk
        elif action == "delete":
            del out[at:at + len(chunk)]
        elif action == "insert":
            out[at:at] = chunk
        else:
            del out[at:]
    return bytes(out)


VALID_XML = """<scene version="3.0.0">
    <default name="res" value="16"/>
    <bsdf type="roughplastic" id="paint"><rgb name="diffuse_reflectance" value="0.2 0.4 0.6"/>
        <float name="alpha" value="0.2"/></bsdf>
    <shape type="sphere"><point name="center" x="0" y="0" z="1"/><float name="radius" value="0.5"/>
        <ref id="paint"/></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="3"/><rotate x="1" angle="10"/></transform>
        <bsdf type="mask"><float name="opacity" value="0.5"/><bsdf type="diffuse"/></bsdf></shape>
    <shape type="disk"><boolean name="flip_normals" value="true"/>
        <transform name="to_world"><translate z="3"/></transform>
        <emitter type="area"><rgb name="radiance" value="4"/></emitter></shape>
    <emitter type="point"><point name="position" x="1" y="2" z="3"/><rgb name="intensity" value="10"/></emitter>
    <integrator type="path"><integer name="max_depth" value="5"/></integrator>
    <sensor type="perspective"><float name="fov" value="45"/>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <transform name="to_world"><lookat origin="0, -5, 2" target="0, 0, 0" up="0, 0, 1"/></transform>
        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/>
            <rfilter type="tent"/></film></sensor>
</scene>
"""

@st.composite
def mutated_xml(draw) -> str:
    """VALID_XML with attribute values replaced by random text and characters edited."""
    text = VALID_XML
    spans = [m.span(1) for m in re.finditer(r'="([^"]*)"', text)]
    for _ in range(draw(st.integers(0, 3))):
        start, end = draw(st.sampled_from(spans))
        text = text[:start] + draw(st.text(max_size=10)).replace('"', "'") + text[end:]
        spans = [m.span(1) for m in re.finditer(r'="([^"]*)"', text)]
    if draw(st.booleans()):
        text = draw(mutated_bytes(text.encode())).decode("utf-8", "replace")
    return text


VALID_OBJ = b"""# a pyramid with normals and texture coordinates
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0.5 0.5 1
vt 0 0
vt 1 0
vt 0.5 1
vn 0 0 -1
vn 0 -0.7 0.7
f 1/1/1 3/2/1 2/3/1
f 1/1/1 4/2/1 3/3/1
f 1/1/2 2/2/2 5/3/2
f 2/1/2 3/2/2 5/3/2
f 3/1/2 4/2/2 5/3/2
f 4/1/2 1/2/2 5/3/2
"""


def ply_bytes(binary: bool) -> bytes:
    """A valid PLY pyramid (vertex normals, vertex colours and a face attribute), ASCII or
    binary little-endian."""
    from plyfile import PlyData, PlyElement
    vertex = np.array([(0, 0, 0, 0, 0, 1, 255, 0, 0), (1, 0, 0, 0, 0, 1, 0, 255, 0),
                       (1, 1, 0, 0, 0, 1, 0, 0, 255), (0, 1, 0, 0, 0, 1, 9, 9, 9),
                       (0.5, 0.5, 1, 0, 0, 1, 128, 128, 128)],
                      dtype=[(n, "f4") for n in ("x", "y", "z", "nx", "ny", "nz")]
                      + [(n, "u1") for n in ("red", "green", "blue")])
    faces = np.array([([0, 2, 1], 0.5), ([0, 3, 2], 0.25), ([0, 1, 4], 1.0), ([1, 2, 4], 0.0),
                      ([2, 3, 4], 0.75), ([3, 0, 4], 0.125)],
                     dtype=[("vertex_indices", "i4", (3,)), ("gloss_0", "f4")])
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "pyramid.ply"
        PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(faces, "face")],
                text=not binary).write(str(path))
        return path.read_bytes()


def volume_grid_bytes() -> bytes:
    """A valid Mitsuba volume grid: 3 x 2 x 2 cells of RGB."""
    import struct
    header = struct.pack("<3sBiiiii6f", b"VOL", 3, 1, 3, 2, 2, 3, 0, 0, 0, 1, 1, 1)
    return header + (np.arange(36, dtype="<f4") / 36).tobytes()


def serialized_bytes() -> bytes:
    """A valid serialized file holding one pyramid (format 4, normals)."""
    from scene_helpers import write_serialized
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]], np.float32)
    faces = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]], np.uint32)
    with tempfile.TemporaryDirectory() as folder:
        path = write_serialized(Path(folder) / "pyramid.serialized",
                                [{"vertices": vertices, "faces": faces,
                                  "normals": np.tile([0.0, 0.0, 1.0], (5, 1)).astype(np.float32)}])
        return path.read_bytes()


def exr_bytes() -> bytes:
    """A valid 4x3 RGB EXR image."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "image.exr"
        write_exr(path, np.random.default_rng(0).uniform(0, 1, (3, 4, 3)).astype(np.float32))
        return path.read_bytes()


# -- the property ---------------------------------------------------------------------------------

def accepts_or_refuses(read, *args) -> None:
    """``read(*args)`` returns, or raises an InstancingError; NumPy's RuntimeWarnings (a
    division by zero in a degenerate mesh, say) are failures too."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        try:
            read(*args)
        except instancing.InstancingError:
            pass


def load_scene_text(text: str, suffix: str) -> None:
    """Write ``text`` (str or bytes) to a scene or mesh file and read it with the reader its
    suffix chooses (``load_scene`` for .xml and .json, ``read_mesh`` for meshes,
    ``read_exr``, ``read_volume_grid`` for .vol)."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"input{suffix}"
        path.write_bytes(text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text)
        reader = {".xml": instancing.load_scene, ".json": instancing.load_scene,
                  ".exr": read_exr, ".vol": read_volume_grid}.get(suffix, read_mesh)
        accepts_or_refuses(reader, path)


def load_scene_dict(scene: dict) -> None:
    accepts_or_refuses(instancing.load_scene, scene)
