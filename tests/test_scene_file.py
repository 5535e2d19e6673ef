"""Tests of the scene description reader :mod:`instancing.io.scene_file` and ``load_scene``.

Transforms are compared with Mitsuba 3's ``ScalarTransform4f`` chains (float32, so to
~1e-6 relative to the largest entry, with slack for a few products: 1e-5) and with
float64 NumPy matrices (1e-12). Every malformed input must raise ``SceneError`` (or
``MeshFileError`` for mesh files) whose message names the culprit.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given

import instancing
from instancing.core.errors import MeshFileError, SceneError
from instancing.io.image import write_png
from instancing.io.mesh_file import read_mesh
from instancing.core import transform as tf
from instancing.core.transform_spec import parse_transforms
from instancing.io.scene_file import parse_scene, parse_transform

import mitsuba as mi  # noqa: E402  (after instancing, which selects libLLVM)
import fuzz_inputs as fuzz

mi.set_variant("scalar_rgb")

MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"
F64 = 1e-12


def minimal(**extra):
    """A valid one-instance scene dict, updated with ``extra`` top-level entries."""
    scene = {"models": {"ball": {"type": "sphere"}},
             "materials": {"red": {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]}},
             "instances": [{"id": "a", "model": "ball", "material": "red"}]}
    scene.update(extra)
    return scene


def with_instance(**fields):
    """``minimal()`` whose instance "a" has ``fields`` added."""
    scene = minimal()
    scene["instances"][0].update(fields)
    return scene


def scene_error(source, *words, exc=SceneError):
    """Parse ``source`` expecting ``exc`` whose message contains every one of ``words``."""
    with pytest.raises(exc) as err:
        parse_scene(source)
    message = str(err.value)
    for w in words:
        assert w in message, f"{w!r} not in {message!r}"
    return message


def random_affine(rng):
    m = np.eye(4)
    m[:3, :4] = rng.uniform(-2, 2, (3, 4))
    m[:3, :3] += 3 * np.eye(3)  # well conditioned
    return m


# --- to_world operation lists against Mitsuba ------------------------------------------------

def random_ops(rng, n):
    """Random op list and the same chain built with Mitsuba's ScalarTransform4f."""
    ops, chain = [], mi.ScalarTransform4f()
    for _ in range(n):
        kind = rng.choice(["translate", "rotate", "scale", "scale1", "matrix", "look_at", "reflect"])
        if kind == "translate":
            v = rng.uniform(-10, 10, 3).tolist()
            ops.append({"translate": v})
            chain = chain.translate(v)
        elif kind == "rotate":
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)  # Mitsuba does not normalize
            angle = float(rng.uniform(-180, 180))
            ops.append({"rotate": {"axis": axis.tolist(), "angle": angle}})
            chain = chain.rotate(axis.tolist(), angle)
        elif kind == "scale":
            s = rng.uniform(0.2, 5, 3).tolist()
            ops.append({"scale": s})
            chain = chain.scale(s)
        elif kind == "scale1":
            s = float(rng.uniform(0.2, 5))
            ops.append({"scale": s})
            chain = chain.scale(s)
        elif kind == "matrix":
            m = random_affine(rng)
            ops.append({"matrix": m.tolist()})
            chain = chain @ mi.ScalarTransform4f(mi.ScalarMatrix4f(m))
        elif kind == "look_at":
            o, t, up = rng.uniform(-5, 5, 3), rng.uniform(-5, 5, 3), rng.normal(size=3)
            ops.append({"look_at": {"origin": o.tolist(), "target": t.tolist(), "up": up.tolist()}})
            chain = chain.look_at(origin=o.tolist(), target=t.tolist(), up=up.tolist())
        else:
            # Reflect has no Mitsuba builder: a scale by -1 along the axis is the same matrix.
            axis = str(rng.choice(["x", "y", "z"]))
            ops.append({"reflect": axis})
            chain = chain.scale([-1.0 if a == axis else 1.0 for a in "xyz"])
    return ops, chain


@pytest.mark.parametrize("seed", range(8))
def test_operation_lists_compose_like_mitsuba(seed):
    rng = np.random.default_rng(seed)
    ops, chain = random_ops(rng, int(rng.integers(1, 6)))
    t = parse_transform(ops)
    m, inv = t.to_numpy()
    ref = np.array(chain.matrix, dtype=np.float64)
    # Mitsuba is float32: a few rounded products of O(10) entries.
    assert np.abs(m - ref).max() <= 1e-5 * max(1.0, np.abs(ref).max()), (ops, m, ref)
    # The stored inverse is the float64 inverse of the composed matrix.
    np.testing.assert_allclose(m @ inv, np.eye(4), atol=F64 * np.linalg.cond(m) * 10)


def _random_operation(rng):
    kind = rng.choice(["translate", "rotate", "scale", "scale1", "matrix", "look_at", "reflect"])
    if kind == "translate":
        return {"translate": rng.uniform(-10, 10, 3).tolist()}
    if kind == "rotate":
        return {"rotate": {"axis": rng.normal(size=3).tolist(), "angle": float(rng.uniform(-720, 720))}}
    if kind in ("scale", "scale1"):
        return {"scale": rng.uniform(0.2, 5, 3).tolist() if kind == "scale" else float(rng.uniform(0.2, 5))}
    if kind == "matrix":
        return {"matrix": random_affine(rng).tolist()}
    if kind == "look_at":
        return {"look_at": {"origin": rng.uniform(-5, 5, 3).tolist(), "target": rng.uniform(-5, 5, 3).tolist(),
                            "up": rng.normal(size=3).tolist()}}
    return {"reflect": str(rng.choice(["x", "y", "z"]))}


def _builder_chain(ops):
    """An operation list composed by the scalar builders of instancing.core.transform (float64
    Dr.Jit matrices), one operation at a time."""
    chain = tf.identity()
    for op in ops:
        (name, arg), = op.items()
        chain = chain @ {"translate": lambda: tf.translate(arg), "scale": lambda: tf.scale(arg),
                         "rotate": lambda: tf.rotate(arg.get("axis"), arg.get("angle")),
                         "matrix": lambda: tf.from_matrix(arg), "reflect": lambda: tf.reflect(arg),
                         "look_at": lambda: tf.look_at(arg["origin"], arg["target"], arg["up"])}[name]()
    return chain.to_numpy()


def test_operation_lists_built_as_batches_match_the_scalar_builders():
    """Many operation lists (every operation, 1 to 5 of them, so that many share their
    sequence of operations and are built as one NumPy batch): each matrix and inverse is
    the scalar builders' chain to float64 rounding, and the same whether its entry is parsed
    among the others or alone."""
    rng = np.random.default_rng(31)
    values = [[_random_operation(rng) for _ in range(rng.integers(1, 6))] for _ in range(3000)]
    values += [[{"rotate": {"axis": [a, 2 * a, -a], "angle": 40.0}}, {"translate": [1, 2, 3]}]
               for a in (1e-200, 1e200, 1.0)]  # (axis lengths whose squares under- and overflow)
    fwd, inv = parse_transforms(values, lambda i: f"#{i}")
    reference = [_builder_chain(ops) for ops in values]
    for name, ours, theirs in (("matrix", fwd, [r[0] for r in reference]),
                               ("inverse", inv, [r[1] for r in reference])):
        theirs = np.stack(theirs)
        scale = np.abs(theirs).max(axis=(1, 2))
        error = (np.abs(ours - theirs).max(axis=(1, 2)) / scale).max()
        assert error <= 8 * F64, (name, error)
    np.testing.assert_allclose(fwd[-3:], np.repeat(fwd[-1:], 3, axis=0), rtol=0, atol=4 * F64)
    for i in rng.choice(len(values), 50, replace=False):
        alone = parse_transform(values[i]).to_numpy()
        np.testing.assert_array_equal(alone[0], fwd[i])
        np.testing.assert_array_equal(alone[1], inv[i])


@pytest.mark.parametrize("bad, first, words", [
    ({0: [{"scale": 2}], 3: [{"translate": [math.nan, 0, 0]}], 10: [{"scale": [1, 0, 1]}]},
     3, ["translate", "non-finite"]),
    ({0: [{"scale": 2}, {"translate": [0, 0, 1]}], 10: [{"scale": [1, 0, 1]}, {"translate": [0, 0, 1]}],
      3: [{"translate": [0, 0, 1]}, {"scale": 0}]}, 3, ["scale", "singular"]),
    ({5: [{"matrix": np.diag([1.0, 0, 1, 1]).tolist()}], 7: [{"shear": 2}]}, 5, ["#5[0].matrix", "singular"]),
    ({5: [{"rotate": {"axis": [0, 0, 0], "angle": 3}}], 7: [{"shear": 2}]}, 5, ["axis"]),
    ({7: [{"shear": 2}], 9: [{"scale": 0}]}, 7, ["#7[0]", "unknown operation 'shear'"])])
def test_the_first_malformed_transform_is_named(bad, first, words):
    """Among many operation lists of several sequences of operations, the error names the
    first bad entry, whichever batch it falls in (the batch of a later one may come first)
    and whether its numbers or its form are wrong."""
    rng = np.random.default_rng(32)
    values = [[_random_operation(rng) for _ in range(rng.integers(1, 3))] for _ in range(12)]
    for k, ops in bad.items():
        values[k] = ops
    with pytest.raises(SceneError) as err:
        parse_transforms(values, lambda i: f"#{i}")
    assert str(err.value).startswith(f"#{first}"), err.value
    for word in words:
        assert word in str(err.value), (word, err.value)


def test_operation_order_is_mitsuba_order():
    # translate then scale in written order: the scale acts first on points.
    t = parse_transform([{"translate": [1, 0, 0]}, {"scale": 2}])
    np.testing.assert_allclose(np.array(t.apply_point([1.0, 1.0, 1.0])), [3, 2, 2], atol=F64)
    t = parse_transform([{"scale": 2}, {"translate": [1, 0, 0]}])
    np.testing.assert_allclose(np.array(t.apply_point([1.0, 1.0, 1.0])), [4, 2, 2], atol=F64)


@pytest.mark.parametrize("axis, factors", [("x", [-1, 1, 1]), ("y", [1, -1, 1]), ("z", [1, 1, -1])])
def test_reflect_operation_is_negative_scale(axis, factors):
    m, _ = parse_transform([{"reflect": axis}]).to_numpy()
    np.testing.assert_array_equal(m, np.array(mi.ScalarTransform4f().scale(factors).matrix))


def test_matrix_to_world():
    rng = np.random.default_rng(20)
    m = random_affine(rng)
    desc = parse_scene(with_instance(to_world=m.tolist()))
    np.testing.assert_array_equal(desc.to_world[0], m)
    np.testing.assert_allclose(desc.from_world[0], np.linalg.inv(m), atol=F64 * np.linalg.cond(m))
    assert desc.instance_ids == ["a"]


def test_numpy_4x4_matrix_to_world():
    # A (4, 4) NumPy array in a Python dict is "a 4x4 row-major matrix" like the nested list.
    rng = np.random.default_rng(25)
    m = random_affine(rng)
    desc = parse_scene(with_instance(to_world=m))
    np.testing.assert_array_equal(desc.to_world[0], m)
    assert desc.instance_ids == ["a"]


def test_numpy_scalars_in_a_dict_scene_parse_as_python_numbers():
    """A scene dict built from NumPy values (film sizes, scales, angles, colours, light
    values) parses as the same dict of Python numbers does (NumPy integers and float32
    values were refused as 'not a number')."""
    def scene(num):
        return {"materials": {"paint": {"type": "diffuse", "reflectance": [num(0.25), 0.5, num(0.75)]}},
                "instances": [{"id": "a", "model": "sphere", "material": "paint",
                               "to_world": [{"translate": [num(1), 2, num(3)]},
                                            {"rotate": {"axis": [0, 0, num(1)], "angle": num(30)}},
                                            {"scale": num(2)}]}],
                "camera": {"type": "perspective", "fov": num(40), "width": num(16, int),
                           "height": num(12, int)},
                "lights": [{"type": "point", "position": [0, num(-4), 2], "intensity": num(5)}]}
    plain = instancing.load_scene(scene(lambda v, kind=float: kind(v)))
    wrapped = instancing.load_scene(scene(lambda v, kind=float: (np.int64 if kind is int
                                                                  else np.float32)(v)))
    np.testing.assert_array_equal(plain.to_world, wrapped.to_world)
    assert (wrapped.camera.width, wrapped.camera.height) == (16, 12)
    assert type(wrapped.camera.width) is int
    np.testing.assert_array_equal(np.asarray(instancing.render(plain, "direct", spp=1)),
                                  np.asarray(instancing.render(wrapped, "direct", spp=1)))
    scene_error(scene(lambda v, kind=float: np.bool_(True) if kind is int else v), "width must be an integer")


def test_op_list_to_world_and_default_identity():
    scene = minimal()
    scene["instances"] = [
        {"id": "moved", "model": "ball", "to_world": [{"translate": [1, 2, 3]}, {"scale": [1, 2, 4]}]},
        {"id": "plain", "model": "ball"},
    ]
    desc = parse_scene(scene)
    ref = np.diag([1.0, 2, 4, 1])
    ref[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(desc.to_world[0], ref, atol=F64)
    np.testing.assert_allclose(desc.from_world[0], np.linalg.inv(ref), atol=F64)
    np.testing.assert_array_equal(desc.to_world[1], np.eye(4))
    assert desc.instance_ids == ["moved", "plain"]
    assert desc.instance_material == ["default", "default"]
    assert desc.materials["default"]["reflectance"] == (0.5, 0.5, 0.5)


def _mixed_entries(rng, n):
    """``n`` random instance entries of every form (plain matrices as lists or arrays, named or
    not, with or without a material; operation lists; batches; no to_world; emitters), and
    what each stands for, worked out entry by entry: (ids, model, material, matrices,
    emitter radiance or None) per entry."""
    entries, expected = [], []
    for k in range(n):
        kind = rng.choice(["plain", "plain", "plain", "array", "ops", "batch", "none", "emitter"])
        entry = {"model": str(rng.choice(["ball", "cube", "disk"]))}
        if rng.random() < 0.5:
            entry["material"] = str(rng.choice(["red", "default"]))
        name = f"e{k}" if rng.random() < 0.4 else None
        if name is not None:
            entry["id"] = name
        radiance = None
        if kind in ("plain", "array"):
            m = random_affine(rng)
            entry["to_world"] = m.tolist() if kind == "plain" else m
            matrices = m[None]
        elif kind in ("ops", "emitter"):
            t = rng.uniform(-5, 5, 3)
            entry["to_world"] = [{"translate": t.tolist()}, {"scale": 2}]
            matrices = np.diag([2.0, 2, 2, 1])
            matrices[:3, 3] = t
            matrices = matrices[None]
            if kind == "emitter":
                radiance = float(rng.uniform(1, 5))
                entry["emitter"] = {"type": "area", "radiance": radiance}
        elif kind == "batch":
            matrices = random_batch(rng, int(rng.integers(1, 4)))
            entry["to_world"] = matrices
        else:
            matrices = np.eye(4)[None]
        start = sum(len(e[3]) for e in expected)
        if kind == "batch":
            prefix = name if name is not None else str(start)
            ids = [f"{prefix}[{i}]" for i in range(len(matrices))]
        else:
            ids = [name if name is not None else str(start)]
        expected.append((ids, entry["model"], entry.get("material", "default"), matrices, radiance))
        entries.append(entry)
    return entries, expected


@pytest.mark.parametrize("seed", range(4))
def test_entries_of_every_form_parse_as_each_entry_alone(seed):
    """Plain entries are read as columns and the rest one by one: the scene is what its
    entries stand for one by one, in order (ids, models, materials, matrices, emitters)."""
    rng = np.random.default_rng(seed)
    entries, expected = _mixed_entries(rng, 300)
    scene = minimal()
    scene["instances"] = entries
    desc = parse_scene(scene)
    ids = [i for e in expected for i in e[0]]
    assert list(desc.instance_ids) == ids and desc.instance_ids == ids
    for i, name in enumerate(ids):
        assert desc.instance_ids.index(name) == i and desc.instance_ids[i] == name
    models = [m.name for m in desc.models]
    assert [models[k] for k in desc.instance_model] == [e[1] for e in expected for _ in e[0]]
    assert desc.instance_material == [e[2] for e in expected for _ in e[0]]
    reference = np.concatenate([e[3] for e in expected])
    np.testing.assert_allclose(desc.to_world, reference, atol=F64 * 10)
    np.testing.assert_allclose(desc.from_world, np.linalg.inv(reference), atol=1e-10)
    radiance = {i: e[4] for i, e in zip(np.cumsum([0] + [len(e[0]) for e in expected]), expected)
                if e[4] is not None}
    assert {i: em.radiance[0] for i, em in desc.emitters.items()} == radiance


@pytest.mark.parametrize("plain", [True, False])
def test_the_first_bad_entry_is_named_among_many_plain_ones(plain):
    """A large scene of plain entries with two bad ones: the error names the first, whether
    it is a singular matrix or an operation list with a zero scale (read as batches too)."""
    rng = np.random.default_rng(7)
    entries = [{"model": "ball", "to_world": random_affine(rng).tolist()} for _ in range(500)]
    entries[123]["to_world"] = (np.diag([1.0, 0, 1, 1]).tolist() if plain
                                else [{"scale": [1, 0, 1]}])
    entries[400]["model"] = "nothing"
    scene_error(minimal(instances=entries), "instance #123")
    entries[123]["to_world"] = random_affine(rng).tolist()
    scene_error(minimal(instances=entries), "instance #400", "unknown model 'nothing'")


def test_an_id_that_is_an_unnamed_instance_index_is_taken_either_way():
    """An instance without an id is named by its index: an explicit id equal to it clashes,
    whichever entry comes first."""
    plain = {"model": "ball", "to_world": np.eye(4).tolist()}
    scene_error(minimal(instances=[plain, {**plain, "id": "0"}]), "'0' is used twice")
    scene_error(minimal(instances=[{**plain, "id": "2"}, plain, plain]), "'2' is used twice")
    desc = parse_scene(minimal(instances=[{**plain, "id": "02"}, plain, plain]))
    assert desc.instance_ids == ["02", "1", "2"]


def random_batch(rng, n):
    batch = np.stack([random_affine(rng) for _ in range(n)])
    return batch


def test_npy_file_expands_to_instances(tmp_path):
    rng = np.random.default_rng(21)
    batch = random_batch(rng, 5)
    (tmp_path / "data").mkdir()
    np.save(tmp_path / "data" / "forest.npy", batch)
    scene = minimal()
    scene["instances"] = [{"id": "solo", "model": "ball"},
                          {"id": "tree", "model": "ball", "material": "red",
                           "to_world": "data/forest.npy"}]
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    desc = parse_scene(path)
    assert desc.instance_ids == ["solo"] + [f"tree[{i}]" for i in range(5)]
    np.testing.assert_array_equal(desc.to_world[1:], batch)
    np.testing.assert_allclose(desc.from_world[1:], np.linalg.inv(batch), atol=1e-10)
    assert desc.instance_material == ["default"] + ["red"] * 5
    assert list(desc.instance_model) == [0] * 6


def test_numpy_array_in_dict_expands_to_instances():
    rng = np.random.default_rng(22)
    batch = random_batch(rng, 3)
    desc = parse_scene(with_instance(to_world=batch))
    assert desc.instance_ids == ["a[0]", "a[1]", "a[2]"]
    np.testing.assert_array_equal(desc.to_world, batch)
    np.testing.assert_allclose(desc.from_world, np.linalg.inv(batch), atol=1e-10)
    # A batch of one still gets an indexed id: it came from an array.
    desc = parse_scene(with_instance(to_world=batch[:1]))
    assert desc.instance_ids == ["a[0]"]


def test_json_file_with_relative_mesh_path(tmp_path, monkeypatch):
    (tmp_path / "sub").mkdir()
    shutil.copy(MESHES / "torus.obj", tmp_path / "sub" / "torus.obj")
    scene = {"models": {"donut": {"type": "obj", "filename": "sub/torus.obj"}},
             "instances": [{"id": "d", "model": "donut", "to_world": [{"translate": [0, 0, 2]}]}]}
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene, indent=2))
    # Relative paths resolve against the scene file's folder, not the working directory.
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    desc = parse_scene(str(path))
    assert desc.models[0].kind == "mesh"
    np.testing.assert_array_equal(desc.models[0].mesh.vertices,
                                  read_mesh(MESHES / "torus.obj").vertices)
    assert desc.base_dir == tmp_path


def test_textures_and_mesh_uvs_resolve_and_move_with_the_scene(tmp_path):
    """A bitmap texture's file resolves against the scene file's folder (a missing one names
    the resolved path); an OBJ's v is flipped by default and not with flip_tex_coords false;
    a scene written elsewhere with new transforms points at the same texture file."""
    from instancing.io.scene_file import write_scene_with_transforms
    (tmp_path / "sub").mkdir()
    shutil.copy(MESHES / "torus_uv.obj", tmp_path / "sub" / "torus_uv.obj")
    write_png(tmp_path / "sub" / "tex.png", np.full((2, 2, 3), 0.5, np.float32))
    material = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
        "type": "bitmap", "filename": "sub/tex.png"}}}
    scene = {"models": {"d": {"type": "obj", "filename": "sub/torus_uv.obj"},
                        "e": {"type": "obj", "filename": "sub/torus_uv.obj", "flip_tex_coords": False}},
             "materials": {"m": material},
             "instances": [{"id": "a", "model": "d", "material": "m"}, {"id": "b", "model": "e"}]}
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    desc = parse_scene(str(path))
    stored = read_mesh(MESHES / "torus_uv.obj").uvs
    np.testing.assert_array_equal(desc.models[0].mesh.uvs, stored * [1, -1] + [0, 1])
    np.testing.assert_array_equal(desc.models[1].mesh.uvs, stored)
    texture = desc.materials["m"].values["reflectance"]
    assert texture.filename == str((tmp_path / "sub" / "tex.png").resolve())
    (tmp_path / "out").mkdir()
    moved = tmp_path / "out" / "moved.json"
    write_scene_with_transforms(str(path), np.repeat(np.eye(4)[None], 2, 0) * [1, 1, 1, 1], moved)
    again = parse_scene(str(moved)).materials["m"].values["reflectance"]
    assert again.filename == texture.filename
    assert json.loads(moved.read_text())["materials"]["m"]["bsdf"]["reflectance"]["filename"] == \
        "../sub/tex.png"
    scene["materials"]["m"]["bsdf"]["reflectance"]["filename"] = "sub/none.png"
    path.write_text(json.dumps(scene))
    scene_error(path, "'sub/none.png'", str((tmp_path / "sub" / "none.png").resolve()))


def test_serialized_models_pick_their_mesh_by_index(tmp_path):
    from scene_helpers import write_serialized
    first = {"vertices": np.eye(3), "faces": [[0, 1, 2]]}
    second = {"vertices": np.eye(3) * 2, "faces": [[0, 2, 1]], "uvs": [[0, 0], [1, 0], [0, 1]]}
    write_serialized(tmp_path / "two.serialized", [first, second])

    def scene(**model):
        return {"models": {"m": {"type": "serialized", "filename": str(tmp_path / "two.serialized"),
                                 **model}},
                "instances": [{"model": "m"}]}

    desc = parse_scene(scene(shape_index=1))
    mesh = desc.models[0].mesh
    np.testing.assert_array_equal(mesh.vertices[mesh.faces], [np.eye(3)[[0, 2, 1]] * 2])
    np.testing.assert_array_equal(mesh.uvs, [[[0, 0], [0, 1], [1, 0]]])  # as stored: no v flip
    np.testing.assert_array_equal(parse_scene(scene()).models[0].mesh.vertices, np.eye(3))
    scene_error(scene(shape_index=-1), "'shape_index'", "must be an integer >= 0")
    scene_error(scene(shape_index=2), "out of range for 2 meshes", exc=MeshFileError)
    obj = {"models": {"m": {"type": "obj", "filename": str(MESHES / "torus.obj"), "shape_index": 0}},
           "instances": [{"model": "m"}]}
    scene_error(obj, "unknown keys ['shape_index']")


def test_computed_normals_to_world_is_a_transform_that_is_checked():
    """A mesh model's ``computed_normals_to_world``: a transform spec (a uniform scale of it
    computes the same normals), refused with the model's name where singular or malformed."""
    def scene(value):
        return {"models": {"m": {"type": "obj", "filename": str(MESHES / "torus.obj"),
                                 "computed_normals_to_world": value}}, "instances": [{"model": "m"}]}

    stretched = parse_scene(scene([{"scale": [1, 3, 1]}])).models[0].mesh.normals
    tripled = parse_scene(scene([{"scale": [3, 9, 3]}])).models[0].mesh.normals
    unit = lambda n: n / np.linalg.norm(n, axis=2, keepdims=True)  # noqa: E731
    np.testing.assert_allclose(unit(stretched), unit(tripled), atol=1e-12)
    plain = parse_scene({"models": {"m": {"type": "obj", "filename": str(MESHES / "torus.obj")}},
                         "instances": [{"model": "m"}]}).models[0].mesh.normals
    assert np.abs(unit(stretched) - unit(plain)).max() > 1e-2
    scene_error(scene([{"scale": [1, 0, 1]}]), "model 'm'", "computed_normals_to_world")
    scene_error(scene("twice"), "model 'm'", "computed_normals_to_world")


# --- malformed input --------------------------------------------------------------------------

def test_missing_scene_file(tmp_path):
    scene_error(tmp_path / "nope.json", "nope.json")


def test_malformed_json_names_line_and_column(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text('{\n  "instances": [\n    {"model": "sphere",}\n  ]\n}\n')
    message = scene_error(path, "broken.json", "line 3", "column")
    assert "JSON" in message


def test_top_level_not_an_object(tmp_path):
    path = tmp_path / "list.json"
    path.write_text("[1, 2, 3]")
    scene_error(path, "list.json", "object", "list")


def test_xml_source_with_unsupported_elements_names_them(tmp_path):
    path = tmp_path / "scene.xml"
    path.write_text('<scene version="3.0.0"><shape type="sphere"><bsdf type="bumpmap"/></shape></scene>')
    scene_error(path, "scene.xml", "bumpmap")


def test_unknown_top_level_key():
    scene_error(minimal(sampler={"type": "independent"}), "unknown top-level scene keys ['sampler']")


@pytest.mark.parametrize("instances", [{"id": "a"}, "a"], ids=["dict", "str"])
def test_instances_not_a_list(instances):
    scene = minimal()
    scene["instances"] = instances
    scene_error(scene, "'instances' must be a list")


@pytest.mark.parametrize("instances", [None, []], ids=["missing", "empty"])
def test_a_scene_without_instances_shows_its_environment(instances, tmp_path):
    """As Mitsuba renders a scene without shapes: every pixel sees the environment (here a
    constant one: exactly its radiance), and the same scene in Mitsuba's XML loads too."""
    scene = {"lights": [{"type": "constant", "radiance": [0.2, 0.3, 0.4]}],
             "camera": {"type": "perspective", "width": 8, "height": 6}}
    if instances is not None:
        scene["instances"] = instances
    path = tmp_path / "empty.xml"
    path.write_text('<scene version="3.0.0"><emitter type="constant"><rgb name="radiance" '
                    'value="0.2 0.3 0.4"/></emitter><sensor type="perspective"><film type="hdrfilm">'
                    '<integer name="width" value="8"/><integer name="height" value="6"/></film>'
                    '</sensor></scene>')
    for loaded in (instancing.load_scene(scene), instancing.load_scene(path)):
        assert len(loaded.instance_ids) == 0
        for integrator in ("direct", "path"):
            image = np.asarray(instancing.render(loaded, integrator, spp=2))
            np.testing.assert_allclose(image, np.broadcast_to([0.2, 0.3, 0.4], image.shape), rtol=1e-6)
        hits = loaded.intersect(np.zeros((4, 3)), np.tile([0.0, 0.0, 1.0], (4, 1)))
        assert np.isinf(hits.t).all() and (hits.instance == -1).all()


def test_instance_not_an_object():
    scene = minimal()
    scene["instances"].append(42)
    scene_error(scene, "instance #1", "42")


def test_unknown_instance_key():
    scene_error(with_instance(colour="red"), "'a'", "colour")


def test_unknown_model_type():
    scene = minimal()
    scene["models"]["pot"] = {"type": "teapot"}
    scene_error(scene, "'pot'", "teapot")


@pytest.mark.parametrize("spec, words", [
    ({"type": "sphere", "radius": 2}, ["'ball'", "radius", "to_world"]),
    ({"type": "cube", "flip_normals": "yes"}, ["'ball'", "flip_normals", "true or false", "yes"])])
def test_bad_analytic_model_keys_name_the_model(spec, words):
    scene = minimal()
    scene["models"]["ball"] = spec
    scene_error(scene, *words)


def test_an_analytic_model_turned_inside_out_faces_inward():
    """``flip_normals`` on an analytic model: its instances' hit normals point inward, under
    a mirror as without (a ray from outside meets a normal pointing along it, one from the
    centre a normal pointing back at it); the same model unflipped points outward."""
    scene = instancing.load_scene({
        "models": {"inside": {"type": "sphere", "flip_normals": True}, "out": {"type": "sphere"}},
        "instances": [{"model": "inside", "to_world": [{"translate": [0, 0, 0]}]},
                      {"model": "inside", "to_world": [{"translate": [5, 0, 0]}, {"scale": [-1, 1, 1]}]},
                      {"model": "out", "to_world": [{"translate": [10, 0, 0]}]}]})
    o = np.array([[0.0, -5.0, 0.0], [5.0, -5.0, 0.0], [10.0, -5.0, 0.0], [0.0, 0.0, 0.0]])
    d = np.array([[0.0, 1.0, 0.0]] * 4)
    hits = scene.intersect(o, d)
    np.testing.assert_array_equal(hits.instance, [0, 1, 2, 0])
    np.testing.assert_allclose(hits.n, [[0, 1, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0]], atol=1e-6)


def test_unknown_model_name():
    scene_error(with_instance(model="ballon"), "'a'", "ballon")


def test_unknown_material_name():
    scene_error(with_instance(material="blue"), "'a'", "blue")


def test_unknown_material_type():
    scene = minimal()
    scene["materials"]["velvet"] = {"type": "velvet"}
    scene_error(scene, "'velvet'", "unknown material type")


@pytest.mark.parametrize("reflectance", [1.5, -0.1, [0.1, 0.2], [0.1, 0.2, 0.3, 0.4], [math.nan, 0, 0],
                                         [0.1, math.inf, 0.2], "red", None, True, [0.5, False, 0.5]],
                         ids=["above1", "below0", "short", "long", "nan", "inf", "str", "null",
                              "bool", "bool-in-list"])
def test_bad_reflectance(reflectance):
    scene = minimal()
    scene["materials"]["red"]["reflectance"] = reflectance
    scene_error(scene, "'red'", "reflectance")


@pytest.mark.parametrize("extra, words", [
    ({"lights": [{"type": "point", "position": [0, 0, 5], "intensity": 1e39}]}, ["lights[0].intensity", "float32"]),
    ({"lights": [{"type": "constant", "radiance": [1, 1e39, 1]}]}, ["lights[0].radiance", "1e+39"]),
    ({"media": {"fog": {"type": "homogeneous", "sigma_t": 1e20, "scale": 1e20}}},
     ["medium 'fog'", "sigma_t times scale", "1e+40"])], ids=["intensity", "radiance", "extinction"])
def test_values_beyond_float32_are_refused(extra, words):
    """A light or medium value that float32 cannot hold (it rendered inf or NaN pixels)."""
    scene_error({**minimal(), **extra}, *words)


def test_an_environment_map_with_negative_or_non_finite_radiance_is_refused(tmp_path):
    from instancing.io.image import write_exr
    texels = np.full((8, 16, 3), 0.5, np.float32)
    texels[2, 3, 1] = -0.25
    write_exr(tmp_path / "sky.exr", texels)
    scene_error({**minimal(), "lights": [{"type": "envmap", "filename": str(tmp_path / "sky.exr")}]},
                "'sky.exr'", "non-negative", "1 texel values", "-0.25")
    texels[2, 3, 1] = 1e38
    write_exr(tmp_path / "sky.exr", texels)
    scene_error({**minimal(), "lights": [{"type": "envmap", "filename": str(tmp_path / "sky.exr"), "scale": 10}]},
                "'sky.exr'", "times scale", "1e+39")


def test_mesh_model_without_filename():
    scene = minimal()
    scene["models"]["m"] = {"type": "ply"}
    scene_error(scene, "'m'", "filename")


def test_missing_mesh_file(tmp_path):
    scene = minimal()
    scene["models"]["m"] = {"type": "obj", "filename": str(tmp_path / "gone.obj")}
    scene_error(scene, "gone.obj", exc=MeshFileError)


def test_malformed_mesh_file(tmp_path):
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1\nf 1 2 3\n")
    scene = minimal()
    scene["models"]["m"] = {"type": "obj", "filename": str(bad)}
    scene_error(scene, "bad.obj", "line 3", exc=MeshFileError)


def test_mesh_extension_type_mismatch(tmp_path):
    shutil.copy(MESHES / "torus.obj", tmp_path / "torus.obj")
    scene = minimal()
    scene["models"]["m"] = {"type": "ply", "filename": str(tmp_path / "torus.obj")}
    scene_error(scene, "'m'", "ply", ".obj")


@pytest.mark.parametrize("to_world, words", [
    ([{"scale": [1e-39, 1, 1]}], ["inverse's entries reach 1e+39"]),
    ([{"scale": 1e-45}], ["inverse's entries reach 1e+45"]),
    ([{"scale": [1, 1e39, 1]}], ["entries reach 1e+39"]),
    (np.diag([1, 1e-40, 1, 1.0]).tolist(), ["inverse's entries reach 1e+40"]),
    # Compositions that overflow float64 (inf times 0 leaves NaN entries).
    ([{"scale": 1e200}, {"scale": 1e200}, {"rotate": {"axis": [0, 0, 1], "angle": 30}}],
     ["entries overflow to NaN"]),
    ([{"scale": 1e-200}, {"scale": 1e-200}, {"rotate": {"axis": [0, 0, 1], "angle": 30}}],
     ["inverse's entries overflow to NaN"]),
    ([{"translate": [1e308, 0, 0]}, {"translate": [1e308, 0, 0]}], ["entries reach inf"])])
def test_transforms_float32_cannot_hold_are_refused_naming_the_instance(to_world, words):
    """A scale below float32's smallest normal number has an infinite float32 inverse (rays
    along that axis missed the instance), one past its largest an infinite matrix; refused
    without NumPy's overflow warnings."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene_error(with_instance(to_world=to_world), "instance #0 ('a')", "float32", *words)


def test_singular_matrix_in_to_world():
    m = np.eye(4)
    m[1, :3] = 0
    scene_error(with_instance(to_world=m.tolist()), "'a'", "singular")


def test_projective_matrix_in_to_world():
    m = np.eye(4)
    m[3, 0] = 0.5
    scene_error(with_instance(to_world=m.tolist()), "'a'", "affine")


def test_nan_in_translate_names_instance():
    scene_error(with_instance(to_world=[{"scale": 2}, {"translate": [math.nan, 0, 0]}]),
                "'a'", "translate", "non-finite")


def test_zero_scale_names_instance():
    scene_error(with_instance(to_world=[{"scale": [1, 0, 1]}]), "'a'", "scale")


def test_zero_rotation_axis_names_instance():
    scene_error(with_instance(to_world=[{"rotate": {"axis": [0, 0, 0], "angle": 30}}]),
                "'a'", "axis")


def test_unknown_operation():
    scene_error(with_instance(to_world=[{"shear": [1, 2, 3]}]), "'a'", "shear")


def test_operation_with_two_keys():
    scene_error(with_instance(to_world=[{"translate": [1, 2, 3], "scale": 2}]),
                "'a'", "to_world[0]", "one key")


def test_rotate_without_angle():
    scene_error(with_instance(to_world=[{"translate": [0, 0, 1]}, {"rotate": {"axis": [0, 0, 1]}}]),
                "'a'", "to_world[1]", "rotate", "angle")


@pytest.mark.parametrize("value", [{"translate": [1, 2, 3]}, 5, [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                                   [{"translate": [1, 2]}], [{"translate": [1, 2, "3"]}],
                                   [{"scale": True}], [{"rotate": {"axis": [0, 0, 1], "angle": "90"}}],
                                   [{"look_at": {"origin": [0, 0, 0], "target": [0, 0, 1]}}],
                                   [{"reflect": "w"}]],
                         ids=["dict", "number", "3x3", "short-translate", "str-component", "bool-scale",
                              "str-angle", "look_at-no-up", "reflect-w"])
def test_malformed_to_world(value):
    scene_error(with_instance(to_world=value), "'a'")


def test_bad_npy_wrong_shape(tmp_path):
    np.save(tmp_path / "m.npy", np.zeros((3, 3, 4)))
    path = tmp_path / "s.json"
    path.write_text(json.dumps(with_instance(to_world="m.npy")))
    scene_error(path, "'a'", "(N, 4, 4)", "(3, 3, 4)")


def test_bad_npy_missing_file(tmp_path):
    path = tmp_path / "s.json"
    path.write_text(json.dumps(with_instance(to_world="absent.npy")))
    scene_error(path, "'a'", "absent.npy")


def test_bad_npy_not_an_array(tmp_path):
    (tmp_path / "junk.npy").write_bytes(b"this is not numpy data")
    path = tmp_path / "s.json"
    path.write_text(json.dumps(with_instance(to_world="junk.npy")))
    scene_error(path, "'a'", "junk.npy")


@pytest.mark.parametrize("k", [0, 3, 6])
def test_bad_npy_singular_matrix_index(tmp_path, k):
    rng = np.random.default_rng(23)
    batch = random_batch(rng, 7)
    batch[k, :3, :3] = np.outer([1, 2, 3], [1, 0, 1])  # rank 1
    np.save(tmp_path / "m.npy", batch)
    path = tmp_path / "s.json"
    path.write_text(json.dumps(with_instance(to_world="m.npy")))
    scene_error(path, "'a'", f"#{k}", "singular")


def test_bad_array_nan_index():
    rng = np.random.default_rng(24)
    batch = random_batch(rng, 4)
    batch[2, 0, 3] = np.nan
    scene_error(with_instance(to_world=batch), "'a'", "#2", "non-finite")


# --- load_scene -------------------------------------------------------------------------------

def test_load_scene_ids_and_kinds_only_for_used_models():
    scene = {
        "models": {"ball": {"type": "sphere"}, "box": {"type": "cube"},
                   "donut": {"type": "obj", "filename": str(MESHES / "torus.obj")}},
        "materials": {"grey": {"type": "diffuse", "reflectance": 0.3}},
        "instances": [
            {"id": "b1", "model": "ball", "to_world": [{"translate": [0, 0, 0]}]},
            {"id": "plate", "model": "disk", "material": "grey",
             "to_world": [{"translate": [0, 0, -2]}, {"scale": 5}]},
            {"id": "b2", "model": "ball", "to_world": [{"translate": [3, 0, 0]}]},
        ],
    }
    s = instancing.load_scene(scene)
    assert isinstance(s, instancing.Scene)
    assert s.instance_ids == ["b1", "plate", "b2"]
    # Declared-but-unused models (cube, the torus mesh) are not in the scene's kinds;
    # the built-in "disk" is used without a declaration.
    assert s.kind_names == ["sphere", "disk"]
    assert s.materials["grey"]["reflectance"] == (0.3, 0.3, 0.3)


def test_load_scene_with_mesh_kind(tmp_path):
    shutil.copy(MESHES / "torus.obj", tmp_path / "torus.obj")
    batch = np.tile(np.eye(4), (3, 1, 1))
    batch[:, 0, 3] = [0, 3, 6]
    np.save(tmp_path / "row.npy", batch)
    scene = {"models": {"donut": {"type": "obj", "filename": "torus.obj"},
                        "unused": {"type": "cylinder"}},
             "instances": [{"id": "t", "model": "donut", "to_world": "row.npy"},
                           {"id": "c", "model": "cube"}]}
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    s = instancing.load_scene(path)
    assert s.instance_ids == ["t[0]", "t[1]", "t[2]", "c"]
    assert s.kind_names == ["cube", "mesh"]


def test_duplicate_instance_ids_are_rejected():
    with pytest.raises(SceneError, match="'a' is used twice"):
        parse_scene({"instances": [{"id": "a", "model": "sphere"}, {"id": "a", "model": "cube"}]})


def test_a_material_key_typo_names_the_key_and_the_closest_valid_name():
    """A misspelt key is an error, not a default grey."""
    scene = minimal(materials={"red": {"type": "diffuse", "reflectence": [0.8, 0.1, 0.1]}})
    scene_error(scene, "material 'red'", "'reflectence'", "did you mean 'reflectance'")
    scene = minimal(materials={"red": {"type": "diffuse", "roughness": 0.2}})
    scene_error(scene, "material 'red'", "'roughness'")


def test_dict_scene_file_names_resolve_against_base_dir(tmp_path, monkeypatch):
    """Relative mesh and .npy names in a dict resolve against ``base_dir`` (default: the
    current directory); the not-found error shows the resolved path."""
    (tmp_path / "assets").mkdir()
    shutil.copy(MESHES / "torus.obj", tmp_path / "assets" / "torus.obj")
    np.save(tmp_path / "assets" / "set.npy", np.eye(4)[None].repeat(2, axis=0))
    scene = {"models": {"ring": {"type": "obj", "filename": "assets/torus.obj"}},
             "instances": [{"model": "ring", "to_world": "assets/set.npy"}]}
    assert len(instancing.load_scene(scene, base_dir=tmp_path).instance_ids) == 2
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    scene_error(scene, str(elsewhere / "assets" / "torus.obj"), "not found", exc=MeshFileError)
    monkeypatch.chdir(tmp_path)
    assert len(instancing.load_scene(scene).instance_ids) == 2
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    with pytest.raises(SceneError, match="base_dir is for dict scenes"):
        instancing.load_scene(path, base_dir=tmp_path)


def test_changed_material_values_are_written_so_that_the_scene_reloads_with_them(tmp_path):
    """A named metal whose eta changed is written with its eta and k and without the name;
    a microfacet alpha given as alpha_u = alpha_v is written as the new alpha alone: the
    written scene loads and has the changed values."""
    from instancing.io.scene_file import write_scene_with_transforms
    scene = minimal(materials={
        "gold": {"type": "conductor", "material": "Au"},
        "rough": {"type": "roughconductor", "alpha_u": 0.2, "alpha_v": 0.2}})
    scene["instances"] = [{"id": "a", "model": "ball", "material": "gold"},
                          {"id": "b", "model": "ball", "material": "rough"}]
    built = instancing.load_scene(scene)
    params = instancing.traverse(built)
    params["gold.eta"] = [0.5, 0.6, 0.7]
    params["rough.alpha"] = 0.35
    params.update()
    changes = {name: built.materials[name].file_entries({key})
               for name, key in (("gold", "eta"), ("rough", "alpha"))}
    assert changes["gold"]["material"] is None and changes["rough"]["alpha_u"] is None
    path = tmp_path / "changed.json"
    write_scene_with_transforms(scene, built.to_world, path, materials=changes)
    written = json.loads(path.read_text())["materials"]
    assert "material" not in written["gold"] and "alpha_u" not in written["rough"]
    again = parse_scene(str(path)).materials
    np.testing.assert_allclose(again["gold"]["eta"], [0.5, 0.6, 0.7], rtol=1e-6)
    np.testing.assert_allclose(again["gold"]["k"], built.materials["gold"]["k"], rtol=1e-6)
    assert again["rough"]["alpha"] == pytest.approx(0.35) == again["rough"]["alpha_u"]


CAMERA = {"type": "perspective", "fov": 40, "width": 16, "height": 12,
          "to_world": [{"look_at": {"origin": [0, -9, 3], "target": [0, 0, 0], "up": [0, 0, 1]}}]}


def test_cameras_are_listed_in_order_with_their_ids():
    desc = parse_scene(minimal(cameras=[CAMERA, {**CAMERA, "id": "top", "width": 8},
                                        {**CAMERA, "id": "low"}]))
    assert [(c.id, c.width) for c in desc.cameras] == [("", 16), ("top", 8), ("low", 16)]
    assert desc.camera is desc.cameras[0]
    assert [c.key() for c in parse_scene(minimal(camera=CAMERA)).cameras] == [desc.camera.key()]
    assert parse_scene(minimal()).cameras == () and parse_scene(minimal()).camera is None


@pytest.mark.parametrize("extra, words", [
    ({"camera": CAMERA, "cameras": [CAMERA]}, ["either 'camera' or 'cameras'"]),
    ({"cameras": []}, ["'cameras' must be a non-empty list"]),
    ({"cameras": CAMERA}, ["'cameras' must be a non-empty list"]),
    ({"cameras": [CAMERA, {**CAMERA, "fov": 200}]}, ["cameras[1]", "fov"]),
    ({"cameras": [{**CAMERA, "id": "a"}, {**CAMERA, "id": "a"}]}, ["ids ['a']", "more than one"]),
    ({"cameras": [{**CAMERA, "id": 3}]}, ["cameras[0]", "id must be a string"]),
    ({"cameras": [{**CAMERA, "name": "x"}]}, ["cameras[0]", "unknown keys ['name']"]),
])
def test_bad_camera_lists_name_the_culprit(extra, words):
    with pytest.raises(SceneError) as err:
        parse_scene(minimal(**extra))
    for word in words:
        assert word in str(err.value), (word, str(err.value))


# -- fuzzed input -------------------------------------------------------------------------------

@fuzz.ci_settings(150)
@given(fuzz.mutated_scenes())
def test_fuzzed_scene_dicts_load_or_raise_documented_errors(scene):
    """A valid scene dict with random values, keys and items replaced, removed or added
    loads or raises an InstancingError (tests/fuzz_inputs.py)."""
    fuzz.load_scene_dict(scene)


@pytest.mark.parametrize("value", [10 ** 400, -10 ** 400, 3.4028235677973366e38, -1e300])
def test_every_number_of_a_scene_replaced_by_an_integer_beyond_float64_is_refused(value):
    """Each number of the fuzzer's valid scene in turn replaced by an integer that float64
    cannot hold (a JSON file may give one of any length), or by a float64 beyond float32's
    range: the scene loads or is refused with an InstancingError, without NumPy's overflow
    warnings (an OverflowError escaped from the light, material, medium and transform
    readers; a material's number overflowed to inf when stored in float32)."""
    places = [path for path, leaf in fuzz._places(fuzz.VALID_SCENE)
              if type(leaf) in (int, float)]
    assert len(places) > 60
    for path in places:
        scene = copy.deepcopy(fuzz.VALID_SCENE)
        parent = scene
        for step in path[:-1]:
            parent = parent[step]
        parent[path[-1]] = value
        fuzz.load_scene_dict(scene)


# -- bad input that was coerced or ignored --------------------------------------------------------

def test_a_huge_rotate_angle_loads_as_its_remainder_modulo_360():
    """1e12 + 30 degrees (exact in float64) is 310 degrees: the scene's matrix is the one of
    rotate 310, not the singular matrix sin and cos of the unreduced angle gave."""
    rng = np.random.default_rng(31)
    axis = rng.normal(size=3).tolist()
    huge, reduced = ([{"translate": [1, 2, 3]}, {"rotate": {"axis": axis, "angle": angle}}]
                     for angle in (1e12 + 30, 310))
    np.testing.assert_array_equal(parse_scene(with_instance(to_world=huge)).to_world,
                                  parse_scene(with_instance(to_world=reduced)).to_world)
    camera = {**CAMERA, "to_world": [{"translate": [0, -9, 3]}, {"rotate": {"axis": axis, "angle": 1e15}}]}
    assert len(parse_scene(minimal(camera=camera)).cameras) == 1


ROWS = np.eye(4).tolist()


@pytest.mark.parametrize("to_world, words", [
    ([[1, 0, 0, 0], [0, "1", 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], ["to_world[1][1]", "got '1'"]),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, True]], ["to_world[3][3]", "got True"]),
    ([[np.bool_(True), 0, 0, 0]] + ROWS[1:], ["to_world[0][0]", "got np.True_"]),
    ([[1 + 0j, 0, 0, 0]] + ROWS[1:], ["to_world[0][0]", "got (1+0j)"]),
    (np.array([["1", "0", "0", "0"]] + [[str(c) for c in row] for row in ROWS[1:]]), ["to_world", "<U"]),
    (np.eye(4, dtype=bool), ["to_world", "array of bool"]),
    (np.eye(4) + 0j, ["to_world", "array of complex128"]),
    (np.eye(4, dtype=bool)[None].repeat(3, axis=0), ["to_world", "array of bool"]),
    ([{"translate": [0, 0, 1]}, {"matrix": ROWS[:3] + [[0, 0, 0, "1"]]}], ["to_world[1].matrix[3][3]", "'1'"]),
], ids=["str", "bool", "numpy-bool", "complex", "str-array", "bool-array", "complex-array",
        "bool-batch", "matrix-op-str"])
def test_matrix_entries_that_are_not_numbers_are_refused_naming_the_entry(to_world, words):
    """Strings, booleans and complex numbers are not coerced to numbers ("1" and true were
    taken as 1.0), whether the entry is plain (read with many others) or not."""
    scene_error(with_instance(to_world=to_world), "instance #0 ('a')", "must be numbers", *words)
    rng = np.random.default_rng(32)
    plain = [{"model": "ball", "to_world": random_affine(rng).tolist()} for _ in range(50)]
    plain[37] = {"model": "ball", "to_world": to_world}
    scene_error(minimal(instances=plain), "instance #37", "must be numbers", *words)


def test_matrix_entries_from_json_files_are_refused_and_numpy_scalars_kept(tmp_path):
    for k, (entry, words) in enumerate((("true", "got True"), ('"1"', "got '1'"))):
        rows = "[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]"
        text = (f'{{"instances": [{{"model": "sphere", "to_world": [[1, 0, 0, 0], [0, 1, 0, 0], '
                f'[0, 0, 1, 0], [0, 0, 0, 1]]}}, {{"model": "sphere", "to_world": [{rows}, '
                f'[0, 0, 0, {entry}]]}}]}}')
        path = tmp_path / f"scene{k}.json"
        path.write_text(text)
        scene_error(path, "instance #1", "to_world[3][3]", words)
    # Numbers of NumPy's own types are numbers.
    rng = np.random.default_rng(33)
    m = random_affine(rng)
    mixed = [[np.float32(c) if (i + j) % 2 else np.int64(round(c)) if c == round(c) else c
              for j, c in enumerate(row)] for i, row in enumerate(m)]
    np.testing.assert_allclose(parse_scene(with_instance(to_world=mixed)).to_world[0],
                               np.array(mixed, np.float64), rtol=0, atol=0)


def test_null_to_world_and_null_camera_are_refused_missing_ones_are_not():
    scene_error(with_instance(to_world=None), "instance #0 ('a')", "to_world is null")
    plain = {"model": "ball", "to_world": np.eye(4).tolist()}
    scene_error(minimal(instances=[plain, plain, {"model": "ball", "to_world": None}]),
                "instance #2", "to_world is null")
    np.testing.assert_array_equal(parse_scene(minimal()).to_world[0], np.eye(4))
    scene_error(minimal(camera=None), "camera: null")
    assert parse_scene(minimal()).cameras == ()


@pytest.mark.parametrize("instance_id", [[1], {}, math.nan, True, "", 5, None],
                         ids=["list", "dict", "nan", "bool", "empty", "int", "null"])
@pytest.mark.parametrize("plain", [True, False])
def test_instance_ids_must_be_non_empty_strings_as_light_ids(instance_id, plain):
    """Ids of other types were turned into strings ('[1]', 'nan'), and '' gave parameter
    keys such as '.translation'; both plain and other entries are refused by their index."""
    entries = [{"model": "ball", "to_world": np.eye(4).tolist()} for _ in range(4)]
    entries[2]["id"] = instance_id
    if not plain:
        entries[2]["to_world"] = [{"translate": [0, 0, 1]}]
    scene_error(minimal(instances=entries), "instance #2", "'id' must be a non-empty string",
                f"got {instance_id!r}")


@pytest.mark.parametrize("size", [1e300, 1e-300, 1e-20, 1.0, 3e38])
def test_directional_light_directions_of_any_size_are_normalised(size):
    """[1e300, 1e300, 1e300] overflowed when squared (the light silently went black) and
    [1e-300, ...] vanished ('zero vector'): both are directions."""
    rng = np.random.default_rng(34)
    unit = rng.normal(size=3)
    unit /= np.linalg.norm(unit)
    light = {"type": "directional", "direction": (unit * size).tolist(), "irradiance": 1}
    (parsed,) = parse_scene(minimal(lights=[light])).lights
    np.testing.assert_allclose(parsed.direction, unit, rtol=0, atol=1e-15)
    scene_error(minimal(lights=[{**light, "direction": [0, 0, 0]}]), "lights[0].direction",
                "zero vector")


@pytest.mark.parametrize("to_world", [
    [{"scale": [1, 1, 2]}], [{"scale": 1e-30}], [{"translate": [1, 2, 3]}, {"scale": [1, 1, 1e-30]}],
    [[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]], ids=["scale", "tiny", "squash", "shear"])
def test_a_spot_light_frame_must_be_rigid_as_a_camera_frame(to_world):
    """A scaled or sheared spot frame dimmed the spot or made it black; it is refused with
    the camera's words. Rotations, reflections and translations stay."""
    spot = {"type": "spot", "to_world": to_world, "intensity": 3}
    scene_error(minimal(lights=[{"type": "point", "position": [0, 0, 1], "intensity": 1}, spot]),
                "lights[1].to_world must be rigid", "no scale or shear")
    camera = scene_error(minimal(camera={**CAMERA, "to_world": to_world}), "must be rigid")
    assert camera.split(" must be rigid")[1] == scene_error(
        minimal(lights=[spot]), "must be rigid").split(" must be rigid")[1]
    rigid = [{"translate": [1, 2, 3]}, {"rotate": {"axis": [1, 1, 0], "angle": 40}}, {"reflect": "x"}]
    (parsed,) = parse_scene(minimal(lights=[{**spot, "to_world": rigid}])).lights
    np.testing.assert_allclose(parsed.position, [1, 2, 3], atol=F64)


@pytest.mark.parametrize("source", [None, 5, [1, 2], b"scene.json", 2.5])
def test_load_scene_names_the_kinds_of_source_it_takes(source):
    with pytest.raises(TypeError) as err:
        instancing.load_scene(source)
    message = str(err.value)
    assert "source must be a scene dict or the path" in message and ".json or .xml" in message
    assert type(source).__name__ in message, message


@pytest.mark.parametrize("filename", [5, None, ["a.obj"], {"path": "a.obj"}])
def test_a_mesh_filename_that_is_not_a_string_names_the_model_and_key(filename):
    scene = minimal()
    scene["models"]["m"] = {"type": "obj", "filename": filename}
    scene_error(scene, "model 'm'", "'filename' must be a string", f"got {filename!r}")


@pytest.mark.parametrize("texture, words", [
    ([0.5, 0.5, 0.5], ["lights[0].texture", "bitmap or checkerboard"]),
    ({"type": "mesh_attribute", "name": "vertex_color"}, ["lights[0].texture", "bitmap or checkerboard"]),
    ({"type": "bitmap", "filename": "missing.png"}, ["lights[0]", "texture 'missing.png'"]),
    ({"type": "checkerboard", "color0": -1}, ["lights[0].texture.color0", "non-negative"]),
])
def test_a_spot_lights_texture_is_checked(tmp_path, texture, words):
    """A spot's texture is a bitmap or checkerboard (Mitsuba's asks for a spatially varying
    one); its file and values are checked, errors naming the light."""
    spec = {"lights": [{"type": "spot", "to_world": np.eye(4).tolist(), "texture": texture}],
            "instances": [{"model": "sphere"}]}
    with pytest.raises(SceneError) as err:
        instancing.load_scene(spec, base_dir=tmp_path)
    for word in words:
        assert word in str(err.value), str(err.value)


@pytest.mark.parametrize("extra, words", [
    ({"scale": -1}, ["lights[0].scale", "non-negative"]),
    ({"fov": 30, "fov_axis": "z"}, ["lights[0]", "fov_axis 'z'"]),
    ({"fov": 190}, ["lights[0]", "(0, 180)"]),
    ({"fov": "wide"}, ["lights[0]", "'fov' must be a number"]),
    ({"irradiance": {"type": "mesh_attribute", "name": "vertex_color"}},
     ["lights[0].irradiance", "bitmap or checkerboard"]),
    ({"irradiance": [1, -1, 1]}, ["lights[0].irradiance", "non-negative"]),
    ({"to_world": [{"scale": 2}]}, ["lights[0].to_world"]),
    ({"focal_length": "50mm"}, ["unknown keys ['focal_length']"]),
])
def test_a_projectors_values_are_checked(tmp_path, extra, words):
    """A projector's scale, field of view, irradiance and frame are checked, errors naming
    the light (a focal length is the XML importer's to convert: JSON takes fov)."""
    spec = {"lights": [{"type": "projector", "to_world": np.eye(4).tolist(), **extra}],
            "instances": [{"model": "sphere"}]}
    with pytest.raises(SceneError) as err:
        instancing.load_scene(spec, base_dir=tmp_path)
    for word in words:
        assert word in str(err.value), str(err.value)


def test_a_projectors_default_field_of_view_is_mitsubas():
    """Without a fov, a projector sees as Mitsuba's default 50 mm lens along the diagonal of
    its (square, for a constant) film: 2 atan(43.27 / 100 / sqrt 2) = 34.0 degrees across."""
    scene = instancing.load_scene({"lights": [{"type": "projector", "to_world": np.eye(4).tolist()}],
                                   "instances": [{"model": "sphere"}]})
    expected = 2 * np.degrees(np.arctan(np.hypot(36, 24) / 100 / np.sqrt(2)))
    assert scene.lights[0].fov == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("radiance, words", [
    ({"type": "mesh_attribute", "name": "vertex_color"}, ["emitter.radiance", "bitmap or checkerboard"]),
    ({"type": "bitmap", "filename": "missing.png"}, ["instance #0 ('lamp'): emitter", "'missing.png'"]),
    ({"type": "checkerboard", "color1": [1, -1, 1]}, ["emitter.radiance.color1", "non-negative"]),
])
def test_an_area_emitters_texture_is_checked(tmp_path, radiance, words):
    """An area emitter's radiance texture is a bitmap or checkerboard (as Mitsuba's
    spatially varying radiance), its file and colours checked, errors naming the instance."""
    spec = {"instances": [{"id": "lamp", "model": "rectangle",
                           "emitter": {"type": "area", "radiance": radiance}}]}
    with pytest.raises(SceneError) as err:
        instancing.load_scene(spec, base_dir=tmp_path)
    for word in words:
        assert word in str(err.value), str(err.value)


@pytest.mark.parametrize("suffix, text, culprit", [
    (".json", '{"instances": [{"model": "sphere"}], "camera": {"type": "perspective", "fovv": 3}}',
     "camera: unknown keys ['fovv']"),
    (".json", '{"instances": [{"model": "sphere", "to_world": [{"scale": 0}]}]}', "instance #0"),
    (".xml", '<scene version="3.0.0"><shape type="shapegroup" id="g"><shape type="sphere"/></shape>'
             '<shape type="instance" id="lamp"><ref id="g"/><transform name="to_world"><matrix '
             'value="1 0 0 0 0 1e-39 0 0 0 0 1 0 0 0 0 1"/></transform></shape></scene>',
     "cannot import this Mitsuba scene, 1 unsupported or invalid element(s):\n  {path}:1: <shape "
     "type=\"instance\" id=\"lamp\">: its to_world does not fit in float32")])
def test_a_scene_files_bad_values_are_reported_with_the_file_named_first(tmp_path, suffix, text, culprit):
    """A problem found in a scene file's values (a camera's key, an instance's transform, an
    XML shapegroup instance's transform, checked after the file is read, at its line) names
    the file, then the culprit; the same scene as a dict names the culprit alone."""
    path = tmp_path / f"scene{suffix}"
    path.write_text(text)
    culprit = culprit.replace("{path}", str(path))
    with pytest.raises(SceneError) as info:
        instancing.load_scene(path)
    assert str(info.value).startswith(f"{path}: {culprit}"), str(info.value)
    if suffix == ".json":
        with pytest.raises(SceneError) as info:
            instancing.load_scene(json.loads(text))
        assert str(info.value).startswith(culprit), str(info.value)
