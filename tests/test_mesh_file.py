"""Tests of the OBJ and PLY triangle mesh readers and the example meshes."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import plyfile
import pytest
from hypothesis import given

from instancing.core.errors import MeshFileError
from instancing.io import mesh_file
from instancing.io.mesh_file import MeshData, read_mesh, read_obj, read_ply
from instancing.validation.stress import MESH_FILE as STRESS_MESH
from scene_helpers import write_serialized
import fuzz_inputs as fuzz

MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"

# A unit square (quad) plus a fifth vertex, used by several tests.
SQUARE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 1.5, 0]],
                  dtype=np.float64)


def write(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` and return the path."""
    path.write_text(text)
    return path


def write_ply(path: Path, vertices: np.ndarray, polygons: list[list[int]],
              text: bool, face_property: str = "vertex_indices") -> Path:
    """Write vertices and polygons as an ASCII or binary PLY file."""
    vertex = np.empty(len(vertices), dtype=[("x", "f8"), ("y", "f8"),
                                            ("z", "f8")])
    vertex["x"], vertex["y"], vertex["z"] = np.asarray(vertices, float).T
    face = np.empty(len(polygons), dtype=[(face_property, "O")])
    for i, polygon in enumerate(polygons):
        face[i] = (np.array(polygon, dtype="i4"),)
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"),
                     plyfile.PlyElement.describe(face, "face")],
                    text=text).write(str(path))
    return path


def obj_text(vertices: np.ndarray, face_lines: list[str]) -> str:
    """OBJ text with ``v`` lines for ``vertices`` and the given face lines."""
    return "".join(f"v {x} {y} {z}\n" for x, y, z in vertices) + \
        "".join(line + "\n" for line in face_lines)


# --- OBJ ------------------------------------------------------------------

def test_obj_triangles(tmp_path):
    path = write(tmp_path / "tri.obj", obj_text(SQUARE[:4], ["f 1 2 3",
                                                             "f 1 3 4"]))
    mesh = read_obj(path)
    assert isinstance(mesh, MeshData)
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.shape == (4, 3)
    assert mesh.faces.dtype == np.int64
    np.testing.assert_array_equal(mesh.vertices, SQUARE[:4])
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])


def test_obj_polygons_are_fan_triangulated_in_file_order(tmp_path):
    path = write(tmp_path / "poly.obj", obj_text(SQUARE, [
        "f 2 3 4 1",    # quad
        "f 1 2 5",      # triangle
        "f 1 2 3 4 5",  # pentagon
    ]))
    np.testing.assert_array_equal(read_obj(path).faces, [
        [1, 2, 3], [1, 3, 0],
        [0, 1, 4],
        [0, 1, 2], [0, 2, 3], [0, 3, 4],
    ])


def test_obj_index_forms_and_negative_indices(tmp_path):
    path = write(tmp_path / "forms.obj", obj_text(SQUARE[:4], [
        "vt 0 0", "vt 1 0", "vt 1 1", "vn 0 0 1",
        "f 1 2 3",
        "f 1/1 2/2 3/3",
        "f 1//1 2//1 3//1",
        "f 1/1/1 2/2/1 3/3/1",
        "f -4 -3 -2",
        "f -4/1 2//1 -1/3/1",
    ]))
    faces = read_obj(path).faces
    np.testing.assert_array_equal(faces[:5], [[0, 1, 2]] * 5)
    np.testing.assert_array_equal(faces[5], [0, 1, 3])


def test_obj_negative_index_is_relative_to_vertices_above(tmp_path):
    path = write(tmp_path / "relative.obj", "\n".join([
        "v 0 0 0", "v 1 0 0", "v 0 1 0",
        "f -3 -2 -1",
        "v 0 0 1",
        "f -3 -2 -1",
    ]))
    np.testing.assert_array_equal(read_obj(path).faces,
                                  [[0, 1, 2], [1, 2, 3]])


def test_obj_skips_comments_and_other_statements(tmp_path):
    path = write(tmp_path / "misc.obj", "\n".join([
        "# a comment", "", "mtllib scene.mtl", "o thing", "g group",
        "s 1", "usemtl red", "v 0 0 0 1.0", "v 1 0 0  # trailing comment",
        "v 0 1 0", "vp 0.5", "l 1 2", "p 1", "f 1 2 3",
    ]))
    mesh = read_obj(path)
    np.testing.assert_array_equal(mesh.vertices, SQUARE[[0, 1, 3]])
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2]])


def test_obj_vertices_are_not_deduplicated(tmp_path):
    path = write(tmp_path / "dup.obj", obj_text(
        np.concatenate([SQUARE[:3], SQUARE[:3]]), ["f 1 2 3", "f 4 5 6"]))
    mesh = read_obj(path)
    assert len(mesh.vertices) == 6
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [3, 4, 5]])


# --- PLY ------------------------------------------------------------------

def test_ply_ascii_and_binary_agree(tmp_path):
    triangles = [[0, 1, 2], [0, 2, 3], [1, 4, 2]]
    ascii_mesh = read_ply(write_ply(tmp_path / "a.ply", SQUARE, triangles,
                                    text=True))
    binary_mesh = read_ply(write_ply(tmp_path / "b.ply", SQUARE, triangles,
                                     text=False))
    for mesh in (ascii_mesh, binary_mesh):
        assert mesh.vertices.dtype == np.float64
        assert mesh.faces.dtype == np.int64
        np.testing.assert_array_equal(mesh.vertices, SQUARE)
        np.testing.assert_array_equal(mesh.faces, triangles)


@pytest.mark.parametrize("text", [True, False])
def test_ply_mixed_polygons_are_fan_triangulated(tmp_path, text):
    path = write_ply(tmp_path / "mixed.ply", SQUARE,
                     [[1, 2, 3, 0], [0, 1, 4], [0, 1, 2, 3, 4], [2, 3, 4]],
                     text=text)
    np.testing.assert_array_equal(read_ply(path).faces, [
        [1, 2, 3], [1, 3, 0],
        [0, 1, 4],
        [0, 1, 2], [0, 2, 3], [0, 3, 4],
        [2, 3, 4],
    ])


@pytest.mark.parametrize("byte_order", ["<", ">"])
@pytest.mark.parametrize("face_property", ["vertex_indices", "vertex_index"])
def test_binary_ply_triangles_are_read_in_one_piece(tmp_path, monkeypatch, byte_order, face_property):
    # Triangles only: the faces come from plyfile's fixed-length reader, never from its
    # element-by-element one, and agree with the ASCII file's.
    triangles = [[0, 1, 2], [0, 2, 3], [1, 4, 2]]
    ascii_mesh = read_ply(write_ply(tmp_path / "a.ply", SQUARE, triangles, text=True,
                                    face_property=face_property))
    path = write_ply(tmp_path / "b.ply", SQUARE, triangles, text=False, face_property=face_property)
    data = plyfile.PlyData.read(str(path), mmap=False)
    data.byte_order = byte_order
    data.write(str(path))

    def per_element(*args):
        raise AssertionError("read element by element")
    monkeypatch.setattr(plyfile.PlyElement, "_read_bin", per_element)
    mesh = read_ply(path)
    np.testing.assert_array_equal(mesh.vertices, ascii_mesh.vertices)
    np.testing.assert_array_equal(mesh.faces, ascii_mesh.faces)


def test_binary_ply_with_a_truncated_triangle_is_corrupt(tmp_path):
    path = write_ply(tmp_path / "cut.ply", SQUARE, [[0, 1, 2], [0, 2, 3]], text=False)
    path.write_bytes(path.read_bytes()[:-5])
    assert_mesh_error(path, "corrupt PLY file")


def test_ply_vertex_index_property(tmp_path):
    path = write_ply(tmp_path / "vi.ply", SQUARE, [[0, 1, 2, 3]], text=True,
                     face_property="vertex_index")
    np.testing.assert_array_equal(read_ply(path).faces,
                                  [[0, 1, 2], [0, 2, 3]])


def test_read_mesh_dispatches_case_insensitively(tmp_path):
    obj = write(tmp_path / "UPPER.OBJ", obj_text(SQUARE[:3], ["f 1 2 3"]))
    ply = write_ply(tmp_path / "UPPER.Ply", SQUARE[:3], [[0, 1, 2]],
                    text=False)
    for path in (obj, ply, str(obj)):
        np.testing.assert_array_equal(read_mesh(path).faces, [[0, 1, 2]])


# --- Errors ---------------------------------------------------------------

def assert_mesh_error(path: Path, *fragments: str) -> None:
    """read_mesh(path) raises MeshFileError naming the file and fragments."""
    with pytest.raises(MeshFileError) as info:
        read_mesh(path)
    message = str(info.value)
    assert path.name in message
    for fragment in fragments:
        assert fragment in message, message


def test_error_is_a_value_error():
    assert issubclass(MeshFileError, ValueError)


def test_missing_file(tmp_path):
    assert_mesh_error(tmp_path / "missing.obj", "not found")
    assert_mesh_error(tmp_path / "missing.ply", "not found")


def test_unknown_extension(tmp_path):
    assert_mesh_error(write(tmp_path / "mesh.stl", "solid"), ".stl")
    assert_mesh_error(write(tmp_path / "mesh", "v 0 0 0"), "extension")


def test_directory_is_unreadable(tmp_path):
    (tmp_path / "dir.obj").mkdir()
    assert_mesh_error(tmp_path / "dir.obj", "cannot be read")


@pytest.mark.parametrize("bad_line", [
    "v 1 2",           # too few coordinates
    "v 1 2 x",         # not a number
    "f 1 2 x",         # not an index
    "f 1/2/3/4 2 3",   # too many slashes
    "f 1/x 2 3",       # texture index not an integer
    "f 1.5 2 3",       # fractional index
    "curv 0 1 1 2",    # unsupported statement
    "\x00\x01binary",  # garbage
])
def test_obj_unparsable_line(tmp_path, bad_line):
    path = write(tmp_path / "bad.obj",
                 obj_text(SQUARE[:3], ["f 1 2 3", bad_line]))
    assert_mesh_error(path, "line 5", repr(bad_line.strip()))


def test_obj_invalid_utf8_reports_the_line(tmp_path):
    path = tmp_path / "latin.obj"
    path.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 \xe9\n")
    assert_mesh_error(path, "line 4")


@pytest.mark.parametrize("face, index, count", [
    ("f 1 2 4", "4", "3"),
    ("f 0 1 2", "0", "3"),
    ("f -4 1 2", "-4", "3"),
])
def test_obj_index_out_of_range(tmp_path, face, index, count):
    path = write(tmp_path / "range.obj", obj_text(SQUARE[:3], [face]))
    assert_mesh_error(path, "line 4", f"index {index}", f"{count} vertices")


def test_obj_index_may_not_refer_to_a_later_vertex(tmp_path):
    path = write(tmp_path / "forward.obj",
                 "v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n")
    assert_mesh_error(path, "line 3", "index 3", "2 vertices")


def test_obj_face_with_fewer_than_three_vertices(tmp_path):
    path = write(tmp_path / "short.obj", obj_text(SQUARE[:3], ["f 1 2"]))
    assert_mesh_error(path, "line 4", "2 vertices")


@pytest.mark.parametrize("coordinate", ["nan", "inf", "-inf"])
def test_obj_non_finite_vertex(tmp_path, coordinate):
    path = write(tmp_path / "nan.obj",
                 f"v 0 0 0\nv 1 {coordinate} 0\nv 0 1 0\nf 1 2 3\n")
    assert_mesh_error(path, "line 2", "non-finite")


def test_obj_without_vertices_or_faces(tmp_path):
    assert_mesh_error(write(tmp_path / "empty.obj", "# nothing\n"),
                      "no vertices")
    assert_mesh_error(write(tmp_path / "points.obj", obj_text(SQUARE, [])),
                      "no faces")


@pytest.mark.parametrize("text", [True, False])
def test_mesh_whose_triangles_all_have_zero_area_is_refused_without_numpy_warnings(tmp_path, text):
    """Collinear and repeated corners only: our error naming the file, not a NumPy
    RuntimeWarning from the area sampling that a scene would build from it; one triangle
    with an area is enough to load."""
    line = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]])
    degenerate = [[0, 1, 2], [0, 0, 1], [3, 3, 3]]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        faces = [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in degenerate]
        assert_mesh_error(write(tmp_path / "flat.obj", obj_text(line, faces)),
                          "all 3 triangles have zero area")
        assert_mesh_error(write_ply(tmp_path / "flat.ply", line, degenerate, text=text),
                          "all 3 triangles have zero area")
        assert read_mesh(write(tmp_path / "one.obj", obj_text(line, faces + ["f 1 2 4"]))).faces.shape == (4, 3)


def test_zero_area_check_runs_on_to_the_first_triangle_with_an_area(tmp_path, monkeypatch):
    # The check goes a run of triangles at a time: here runs of 2, the area in the third run
    # (loads) or in none (refused).
    monkeypatch.setattr(mesh_file, "_AREA_CHECK_RUN", 2)
    line = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]])
    flat = ["f 1 2 3"] * 5
    assert read_mesh(write(tmp_path / "late.obj", obj_text(line, flat + ["f 1 2 4"]))).faces.shape == (6, 3)
    assert_mesh_error(write(tmp_path / "none.obj", obj_text(line, flat + ["f 1 1 4"])),
                      "all 6 triangles have zero area")


def test_ply_index_out_of_range(tmp_path):
    path = write_ply(tmp_path / "range.ply", SQUARE,
                     [[0, 1, 2], [0, 1, 2, 3, 5]], text=True)
    assert_mesh_error(path, "face 1", "index 5", "5 vertices")
    path = write_ply(tmp_path / "negative.ply", SQUARE, [[0, -1, 2]],
                     text=False)
    assert_mesh_error(path, "face 0", "index -1", "5 vertices")


def test_ply_face_with_fewer_than_three_vertices(tmp_path):
    path = write_ply(tmp_path / "short.ply", SQUARE, [[0, 1, 2], [0, 1]],
                     text=False)
    assert_mesh_error(path, "face 1", "2 vertices")


def test_ply_non_finite_vertex(tmp_path):
    vertices = SQUARE.copy()
    vertices[3, 2] = np.nan
    path = write_ply(tmp_path / "nan.ply", vertices, [[0, 1, 2]], text=False)
    assert_mesh_error(path, "vertex 3", "non-finite")


def test_ply_without_vertices_or_faces(tmp_path):
    assert_mesh_error(write_ply(tmp_path / "novertex.ply", SQUARE[:0], [],
                                text=True), "no vertices")
    assert_mesh_error(write_ply(tmp_path / "noface.ply", SQUARE, [],
                                text=True), "no faces")


def ply_header(elements: str) -> str:
    """An ASCII PLY header declaring ``elements``."""
    return f"ply\nformat ascii 1.0\n{elements}end_header\n"


def test_ply_without_required_elements_or_properties(tmp_path):
    xyz = "property float x\nproperty float y\nproperty float z\n"
    face = "element face 1\nproperty list uchar int vertex_indices\n"
    cases = {
        "noelement.ply": (ply_header(face) + "3 0 1 2\n",
                          "no 'vertex' element"),
        "noface.ply": (ply_header("element vertex 3\n" + xyz)
                       + "0 0 0\n1 0 0\n0 1 0\n", "no 'face' element"),
        "noz.ply": (ply_header("element vertex 3\nproperty float x\n"
                               "property float y\n" + face)
                    + "0 0\n1 0\n0 1\n3 0 1 2\n", "property 'z'"),
        "nolist.ply": (ply_header("element vertex 3\n" + xyz
                                  + "element face 1\nproperty int a\n")
                       + "0 0 0\n1 0 0\n0 1 0\n0\n", "vertex_indices"),
        "floatindex.ply": (ply_header("element vertex 3\n" + xyz
                                      + "element face 1\nproperty list "
                                        "uchar float vertex_indices\n")
                           + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "non-integer"),
    }
    for name, (text, fragment) in cases.items():
        assert_mesh_error(write(tmp_path / name, text), fragment)


def test_corrupt_ply(tmp_path):
    good = write_ply(tmp_path / "good.ply", SQUARE, [[0, 1, 2]],
                     text=False).read_bytes()
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(good[:-5])
    assert_mesh_error(truncated, "corrupt PLY", "end-of-file")
    no_magic = tmp_path / "nomagic.ply"
    no_magic.write_bytes(b"PLY?" + good[3:])
    assert_mesh_error(no_magic, "corrupt PLY")
    negative_count = write(tmp_path / "negative.ply", ply_header(
        "element vertex -3\nproperty float x\n"))
    assert_mesh_error(negative_count, "corrupt PLY")
    malformed = write(tmp_path / "malformed.ply", ply_header(
        "element vertex 1\nproperty float x\nproperty float y\n"
        "property float z\n") + "0 zero 0\n")
    assert_mesh_error(malformed, "corrupt PLY", "malformed")


# --- Vertex normals -------------------------------------------------------

def test_obj_normals_become_corner_normals(tmp_path):
    """Faces referring to vn get those normals at their corners (as written, not
    normalized); corners without one take the smooth normal; relative indices count
    back from the normals above."""
    path = write(tmp_path / "normals.obj", obj_text(SQUARE, [
        "vn 0 0 2", "vn 0.5 0 1", "vn 0 0.5 1", "vt 0 0",
        "f 1//1 2//2 3//3", "f 1/1/-1 3//-2 4",
    ]))
    mesh = read_obj(path)
    assert mesh.normals.shape == (2, 3, 3)
    np.testing.assert_array_equal(mesh.normals[0], [[0, 0, 2], [0.5, 0, 1], [0, 0.5, 1]])
    np.testing.assert_array_equal(mesh.normals[1, :2], [[0, 0.5, 1], [0.5, 0, 1]])
    np.testing.assert_allclose(mesh.normals[1, 2], [0, 0, 1])  # computed: a flat square


def test_obj_and_ply_without_normals_have_none(tmp_path):
    assert read_obj(write(tmp_path / "plain.obj", obj_text(SQUARE, ["f 1 2 3"]))).normals is None
    assert read_ply(write_ply(tmp_path / "plain.ply", SQUARE, [[0, 1, 2]], True)).normals is None


@pytest.mark.parametrize("lines, words", [
    (["vn 0 0 1", "f 1//2 2//1 3//1"], ["line 7", "face index 2", "1 normals"]),
    (["f 1//1 2 3"], ["face index 1", "0 normals"]),
    (["vn 0 nan 1", "f 1//1 2//1 3//1"], ["line 6", "non-finite normal"]),
    (["vn 0 1", "f 1 2 3"], ["line 6", "normal 'vn x y z'"]),
])
def test_obj_normal_errors(tmp_path, lines, words):
    assert_mesh_error(write(tmp_path / "bad.obj", obj_text(SQUARE, lines)), *words)


def write_ply_normals(path: Path, vertices: np.ndarray, normals: np.ndarray,
                      triangles: list[list[int]], names=("nx", "ny", "nz")) -> Path:
    """A binary PLY with x y z and the given normal properties per vertex (or any other
    per-vertex properties: ``names`` for the columns of ``normals``)."""
    vertex = np.empty(len(vertices), dtype=[(c, "f4") for c in ("x", "y", "z") + tuple(names)])
    for k, c in enumerate("xyz"):
        vertex[c] = vertices[:, k]
    for k, c in enumerate(names):
        vertex[c] = normals[:, k]
    face = np.empty(len(triangles), dtype=[("vertex_indices", "O")])
    for i, triangle in enumerate(triangles):
        face[i] = (np.array(triangle, dtype="i4"),)
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"),
                     plyfile.PlyElement.describe(face, "face")]).write(str(path))
    return path


def test_ply_normals_become_corner_normals(tmp_path):
    normals = np.arange(15, dtype=np.float64).reshape(5, 3) / 4 + 0.25
    mesh = read_ply(write_ply_normals(tmp_path / "n.ply", SQUARE, normals, [[0, 1, 2], [4, 2, 3]]))
    np.testing.assert_array_equal(mesh.normals, normals.astype(np.float32)[[[0, 1, 2], [4, 2, 3]]])
    partial = write_ply_normals(tmp_path / "p.ply", SQUARE, normals, [[0, 1, 2]], names=("nx", "ny"))
    assert_mesh_error(partial, "some but not all", "'nz'")
    normals[3, 1] = np.inf
    assert_mesh_error(write_ply_normals(tmp_path / "inf.ply", SQUARE, normals, [[0, 1, 2]]),
                      "vertex 3", "non-finite normal")


def test_zero_normals_that_faces_use_are_refused_in_every_format(tmp_path):
    """A zero normal gives a NaN shading normal: refused naming the file and how many faces
    use; an unused one, or one only some corners skip, is harmless and loads."""
    rng = np.random.default_rng(12)
    normals = rng.normal(size=(5, 3))
    normals[[1, 3]] = 0.0
    obj_normals = [f"vn {x} {y} {z}" for x, y, z in normals]
    assert_mesh_error(write(tmp_path / "zero.obj", obj_text(SQUARE, obj_normals + [
        "f 1//1 2//2 3//3", "f 1//1 3//4 4//5"])), "2 of the 5 vertex normals", "zero length",
        "normal 1")
    assert_mesh_error(write_ply_normals(tmp_path / "zero.ply", SQUARE, normals, [[0, 1, 2]]),
                      "1 of the 3 vertex normals", "zero length")
    mesh = _random_mesh(rng, normals=1)
    mesh["normals"][[0, 2, 4]] = 0.0
    assert_mesh_error(write_serialized(tmp_path / "zero.serialized", [mesh]),
                      "3 of the 6 vertex normals", "zero length")
    unused = read_obj(write(tmp_path / "unused.obj", obj_text(SQUARE, obj_normals + [
        "f 1//1 3//3 4//5", "f 2 3 4"])))
    assert np.isfinite(unused.normals).all() and np.abs(unused.normals).sum(axis=2).all()


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".serialized"])
def test_coordinates_beyond_float32_are_refused_without_numpy_warnings(tmp_path, suffix):
    """Meshes are stored in float32: a vertex (or normal) beyond its range, finite in
    float64, is refused naming the file and the vertex; 1e10 loads without a warning."""
    rng = np.random.default_rng(13)
    for size, fine in ((1e10, True), (1e39, False)):
        vertices = rng.uniform(-1, 1, (6, 3))
        vertices[4] *= size
        mesh = {"vertices": vertices, "faces": [[0, 1, 2], [2, 3, 4], [4, 5, 0]]}
        path = tmp_path / f"big{size:g}{suffix}"
        if suffix == ".obj":
            write(path, obj_text(vertices, [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh["faces"]]))
        elif suffix == ".ply":
            write_ply(path, vertices, mesh["faces"], text=False)
        else:
            write_serialized(path, [mesh], double=True)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            if fine:
                np.testing.assert_array_equal(read_mesh(path).vertices, vertices)
            else:
                assert_mesh_error(path, "vertex 4", "beyond float32's range")
    normals = rng.normal(size=(5, 3))
    normals[2, 0] = -1e39
    assert_mesh_error(write(tmp_path / "normal.obj", obj_text(SQUARE, [
        f"vn {x} {y} {z}" for x, y, z in normals] + ["f 1//1 2//2 3//4"])),
        "normal 2", "beyond float32's range")


# --- Texture coordinates ---------------------------------------------------

def test_obj_texture_coordinates_become_corner_uvs(tmp_path):
    """Faces referring to vt get those (u, v) at their corners as stored (v is flipped by
    the scene, not the reader); corners without one take (0, 0); a missing v is 0."""
    path = write(tmp_path / "uv.obj", obj_text(SQUARE, [
        "vt 0.25 0.5", "vt 1 0.75 0.3", "vt 0.5",
        "f 1/1 2/2 3/3", "f 1/-1/ 3 4/-3",
    ]))
    mesh = read_obj(path)
    np.testing.assert_array_equal(mesh.uvs, [[[0.25, 0.5], [1, 0.75], [0.5, 0]],
                                             [[0.5, 0], [0, 0], [0.25, 0.5]]])
    assert read_obj(write(tmp_path / "plain.obj", obj_text(SQUARE, ["f 1 2 3"]))).uvs is None


@pytest.mark.parametrize("lines, words", [
    (["vt 0 0", "f 1/2 2/1 3/1"], ["line 7", "face index 2", "1 texture coordinates"]),
    (["vt nan 0", "f 1/1 2/1 3/1"], ["line 6", "non-finite texture coordinate"]),
    (["vt", "f 1 2 3"], ["line 6", "'vt u [v [w]]'"]),
])
def test_obj_texture_coordinate_errors(tmp_path, lines, words):
    assert_mesh_error(write(tmp_path / "bad.obj", obj_text(SQUARE, lines)), *words)


def write_ply_uvs(path: Path, uvs: np.ndarray, triangles: list[list[int]], names=("u", "v")) -> Path:
    """A binary PLY of SQUARE with the given texture-coordinate properties per vertex."""
    return write_ply_normals(path, SQUARE, uvs, triangles, names)


@pytest.mark.parametrize("names", [("u", "v"), ("s", "t"), ("texture_u", "texture_v")])
def test_ply_texture_coordinates_become_corner_uvs(tmp_path, names):
    uvs = np.arange(10, dtype=np.float64).reshape(5, 2) / 8
    mesh = read_ply(write_ply_uvs(tmp_path / "uv.ply", uvs, [[0, 1, 2], [4, 2, 3]], names))
    np.testing.assert_array_equal(mesh.uvs, uvs.astype(np.float32)[[[0, 1, 2], [4, 2, 3]]])
    uvs[2, 0] = np.nan
    assert_mesh_error(write_ply_uvs(tmp_path / "nan.ply", uvs, [[0, 1, 2]], names),
                      "vertex 2", "non-finite texture coordinates")


def mitsuba_corner_uvs(path: Path, **props) -> np.ndarray:
    """(F, 3, 2) texture coordinates at the triangles' corners as Mitsuba loads them."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    params = mi.traverse(mi.load_dict({"type": path.suffix[1:], "filename": str(path), **props}))
    uvs = np.array(params["vertex_texcoords"]).reshape(-1, 2)
    return uvs[np.array(params["faces"]).reshape(-1, 3)]


@pytest.mark.parametrize("flip", [None, True, False])
def test_texture_coordinates_agree_with_mitsuba(tmp_path, flip):
    """Mitsuba's uvs at each triangle corner are ours after the scene's v flip, which is
    on by default for OBJ files and off for PLY files (as Mitsuba's plugins)."""
    from instancing.io.scene_file import _FLIP_TEX_COORDS, shaded_mesh
    rng = np.random.default_rng(2)
    uvs = rng.uniform(-1, 2, size=(5, 2))
    obj = write(tmp_path / "uv.obj", obj_text(SQUARE, [f"vt {u} {v}" for u, v in uvs] + [
        "f 1/1 2/2 3/3", "f 1/4 3/5 4/2"]))
    ply = write_ply_uvs(tmp_path / "uv.ply", uvs, [[0, 1, 2], [4, 2, 3]])
    for path in (obj, MESHES / "torus_uv.obj", ply):
        props = {} if flip is None else {"flip_tex_coords": flip}
        on = _FLIP_TEX_COORDS[path.suffix[1:]] if flip is None else flip
        ours = shaded_mesh(read_mesh(path), flip_tex_coords=on).uvs
        np.testing.assert_allclose(ours, mitsuba_corner_uvs(path, **props), rtol=0, atol=1e-6)


# --- Mitsuba's serialized format ---------------------------------------------

def _random_mesh(rng, count=6, **extra) -> dict:
    mesh = {"vertices": rng.uniform(-1, 1, (count, 3)),
            "faces": [[0, 1, 2], [2, 3, 4], [4, 5, 0], [1, 3, 5]]}
    if "normals" in extra:
        mesh["normals"] = rng.normal(size=(count, 3))
    if "uvs" in extra:
        mesh["uvs"] = rng.uniform(0, 1, (count, 2))
    if "colors" in extra:
        mesh["colors"] = rng.uniform(0, 1, (count, 3))
    return mesh


@pytest.mark.parametrize("version, double", [(4, False), (4, True), (3, False)])
def test_serialized_meshes_agree_with_mitsuba(tmp_path, version, double):
    """Every mesh of a multi-mesh file, with and without normals, uvs and colours, single
    and double precision, format 3 and 4: Mitsuba's serialized plugin reads the same
    triangles, corner normals and corner uvs."""
    from instancing.io.mesh_file import read_serialized
    rng = np.random.default_rng(version + double)
    meshes = [_random_mesh(rng), _random_mesh(rng, normals=1, uvs=1),
              _random_mesh(rng, 7, uvs=1, colors=1), _random_mesh(rng, normals=1, colors=1)]
    path = write_serialized(tmp_path / "m.serialized", meshes, version, double)
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    for index, written in enumerate(meshes):
        ours = read_serialized(path, index)
        params = mi.traverse(mi.load_dict({"type": "serialized", "filename": str(path),
                                           "shape_index": index}))
        faces = np.array(params["faces"]).reshape(-1, 3)
        corners = np.array(params["vertex_positions"]).reshape(-1, 3)[faces]
        np.testing.assert_allclose(ours.vertices[ours.faces], corners, rtol=0, atol=1e-6)
        assert (ours.normals is None) == ("normals" not in written)
        if ours.normals is not None:
            unit = ours.normals / np.linalg.norm(ours.normals, axis=2, keepdims=True)
            theirs = np.array(params["vertex_normals"]).reshape(-1, 3)[faces]
            np.testing.assert_allclose(unit, theirs / np.linalg.norm(theirs, axis=2, keepdims=True),
                                       atol=1e-6)
        assert (ours.uvs is None) == ("uvs" not in written)
        if ours.uvs is not None:
            np.testing.assert_allclose(ours.uvs, np.array(params["vertex_texcoords"]).reshape(-1, 2)[faces],
                                       atol=1e-7)


def test_serialized_errors(tmp_path):
    import struct
    import zlib
    from instancing.io.mesh_file import read_serialized
    rng = np.random.default_rng(0)
    good = write_serialized(tmp_path / "good.serialized", [_random_mesh(rng)])
    assert_mesh_error(tmp_path / "none.serialized", "not found")
    with pytest.raises(MeshFileError, match="out of range for 1 meshes"):
        read_serialized(good, 1)
    with pytest.raises(MeshFileError, match="shape_index must be an integer >= 0"):
        read_serialized(good, -1)
    data = good.read_bytes()
    (tmp_path / "magic.serialized").write_bytes(struct.pack("<H", 0x1234) + data[2:])
    assert_mesh_error(tmp_path / "magic.serialized", "not a Mitsuba serialized mesh")
    (tmp_path / "v9.serialized").write_bytes(data[:2] + struct.pack("<H", 9) + data[4:])
    assert_mesh_error(tmp_path / "v9.serialized", "version 9")
    (tmp_path / "zlib.serialized").write_bytes(data[:4] + b"garbage" * 10)
    assert_mesh_error(tmp_path / "zlib.serialized", "corrupt compressed")
    body = struct.pack("<I", 0x1000) + b"m\0" + struct.pack("<QQ", 10**9, 1)
    (tmp_path / "short.serialized").write_bytes(struct.pack("<HH", 0x041C, 4) + zlib.compress(body))
    assert_mesh_error(tmp_path / "short.serialized", "truncated")
    bad = _random_mesh(rng)
    bad["faces"] = [[0, 1, 9]]
    assert_mesh_error(write_serialized(tmp_path / "index.serialized", [bad]), "vertex index 9")
    assert_mesh_error(write_serialized(tmp_path / "empty.serialized", [{"vertices": np.zeros((3, 3)),
                                                                        "faces": np.zeros((0, 3))}]),
                      "no faces")
    with pytest.raises(MeshFileError, match="serialized files only"):
        read_mesh(write(tmp_path / "t.obj", obj_text(SQUARE, ["f 1 2 3"])), shape_index=1)


# --- Cross-check with Mitsuba's loaders -----------------------------------

def mitsuba_triangles(path: Path) -> np.ndarray:
    """(F, 3, 3) corner positions of the triangles Mitsuba loads from path."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    shape = mi.load_dict({"type": path.suffix[1:], "filename": str(path)})
    params = mi.traverse(shape)
    vertices = np.array(params["vertex_positions"]).reshape(-1, 3)
    faces = np.array(params["faces"]).reshape(-1, 3)
    return vertices[faces]


def test_obj_agrees_with_mitsuba_including_polygons(tmp_path):
    # Mitsuba deduplicates vertices by (v, vt, vn) and rejects negative
    # indices, so compare the triangles' corner positions, face by face.
    path = write(tmp_path / "mixed.obj", obj_text(SQUARE, [
        "vt 0 0", "vn 0 0 1",
        "f 2 3 4 1", "f 1/1 2/1 5/1", "f 1 2 3 4 5", "f 3//1 4//1 5//1",
    ]))
    mesh = read_obj(path)
    np.testing.assert_allclose(mesh.vertices[mesh.faces],
                               mitsuba_triangles(path))


def test_generated_meshes_agree_with_mitsuba():
    for path in (MESHES / "torus.obj", STRESS_MESH, MESHES / "tree.ply"):
        mesh = read_mesh(path)
        np.testing.assert_allclose(mesh.vertices[mesh.faces],
                                   mitsuba_triangles(path),
                                   rtol=0, atol=1e-6)


def test_triangle_ply_agrees_with_mitsuba(tmp_path):
    # Mitsuba's ply plugin accepts triangle-only files (no polygons).
    path = write_ply(tmp_path / "tri.ply", SQUARE,
                     [[0, 1, 2], [0, 2, 3], [3, 2, 4]], text=False)
    mesh = read_ply(path)
    np.testing.assert_allclose(mesh.vertices[mesh.faces],
                               mitsuba_triangles(path))


# --- Generated example meshes ----------------------------------------------

def closed_and_outward(mesh: MeshData) -> tuple[bool, float]:
    """Whether every edge joins two oppositely wound triangles; the volume."""
    faces = mesh.faces
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]],
                               faces[:, [2, 0]]])
    unique, counts = np.unique(directed, axis=0, return_counts=True)
    forward = {tuple(edge) for edge in unique}
    closed = bool((counts == 1).all()) and all(
        (b, a) in forward for a, b in forward)
    v0, v1, v2 = (mesh.vertices[faces[:, k]] for k in range(3))
    volume = float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6)
    return closed, volume


def components(mesh: MeshData) -> list[MeshData]:
    """Split a mesh into its vertex-connected pieces."""
    parent = list(range(len(mesh.vertices)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for a, b, c in mesh.faces:
        parent[root(b)] = root(a)
        parent[root(c)] = root(a)
    labels = np.array([root(int(f[0])) for f in mesh.faces])
    return [MeshData(mesh.vertices, mesh.faces[labels == label])
            for label in np.unique(labels)]


@pytest.mark.parametrize("name, triangles, pieces", [
    ("tree.ply", 232, 4),
    ("torus.obj", 2 * 24 * 12, 1),
    ("icosphere.obj", 320, 1),
])
def test_generated_meshes_are_closed_and_outward(name, triangles, pieces):
    path = STRESS_MESH if name == "icosphere.obj" else MESHES / name
    assert path.stat().st_size < 100_000
    mesh = read_mesh(path)
    assert mesh.faces.shape == (triangles, 3)
    parts = components(mesh)
    assert len(parts) == pieces
    for part in parts:
        closed, volume = closed_and_outward(part)
        assert closed and volume > 0


def test_generated_mesh_shapes():
    tree = read_mesh(MESHES / "tree.ply").vertices
    assert tree[:, 2].min() == 0 and tree[:, 2].max() == pytest.approx(2)
    assert np.abs(tree[:, :2]).max() <= 1
    sphere = read_mesh(STRESS_MESH)
    np.testing.assert_allclose(np.linalg.norm(sphere.vertices, axis=1), 1,
                               atol=1e-8)
    # Inscribed polyhedra fall a little short of the analytic volumes.
    assert closed_and_outward(sphere)[1] == pytest.approx(4 / 3 * np.pi,
                                                          rel=0.04)
    torus = read_mesh(MESHES / "torus.obj")
    assert closed_and_outward(torus)[1] == pytest.approx(
        2 * np.pi ** 2 * 0.7 * 0.3 ** 2, rel=0.08)


def test_closedness_check_detects_holes_and_inward_winding():
    sphere = read_mesh(STRESS_MESH)
    holed = MeshData(sphere.vertices, sphere.faces[1:])
    assert not closed_and_outward(holed)[0]
    flipped = MeshData(sphere.vertices, sphere.faces[:, ::-1])
    closed, volume = closed_and_outward(flipped)
    assert closed and volume < 0
    mixed = MeshData(sphere.vertices,
                     np.concatenate([flipped.faces[:1], sphere.faces[1:]]))
    assert not closed_and_outward(mixed)[0]


def mitsuba_corner_normals(path: Path) -> np.ndarray:
    """(F, 3, 3) unit normals at the triangles' corners as Mitsuba loads them from path."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    params = mi.traverse(mi.load_dict({"type": path.suffix[1:], "filename": str(path)}))
    normals = np.array(params["vertex_normals"]).reshape(-1, 3)
    faces = np.array(params["faces"]).reshape(-1, 3)
    return normals[faces] / np.linalg.norm(normals[faces], axis=2, keepdims=True)


def test_file_normals_agree_with_mitsuba(tmp_path):
    """OBJ vn (several per position, as for hard edges) and PLY normals: Mitsuba's normals
    at each triangle corner are ours."""
    rng = np.random.default_rng(5)
    normals = rng.normal(size=(6, 3))
    lines = [f"vn {x} {y} {z}" for x, y, z in normals] + [
        "f 1//1 2//2 3//3", "f 1//4 3//5 4//6", "f 3//1 4//2 5//3"]
    obj = write(tmp_path / "hard.obj", obj_text(SQUARE, lines))
    ply = write_ply_normals(tmp_path / "n.ply", SQUARE, normals[:5], [[0, 1, 2], [4, 2, 3]])
    for path in (obj, ply):
        ours = read_mesh(path).normals
        ours = ours / np.linalg.norm(ours, axis=2, keepdims=True)
        np.testing.assert_allclose(ours, mitsuba_corner_normals(path), rtol=0, atol=1e-6)


def test_computed_normals_break_along_texture_seams_as_mitsubas(tmp_path):
    """An OBJ without vn whose faces give a position different vt indices (a cube with four
    texture corners per face; a strip of quads with one seam across it, and one corner
    without vt): Mitsuba welds vertices by position and texture index, so the smooth normals
    it computes are not shared across a seam. Ours, at every triangle corner, are Mitsuba's;
    the cube comes out flat."""
    from instancing.io.scene_file import shaded_mesh
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
    quads = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]
    lines = [f"vt {u} {v}" for _ in quads for u, v in ((0, 0), (1, 0), (1, 1), (0, 1))]
    lines += ["f " + " ".join(f"{p}/{4 * k + c + 1}" for c, p in enumerate(q)) for k, q in enumerate(quads)]
    strip = np.array([[x, y, 0.3 * x * x] for y in (0, 1) for x in (0, 1, 2, 3)], np.float64)
    strip_lines = [f"vt {u} {v}" for u, v in ((0, 0), (0.3, 0), (0.6, 0), (0.9, 0), (0, 1), (0.3, 1),
                                               (0.6, 1), (0.9, 1), (0.1, 0), (0.1, 1))]
    # The quads 1-2 and 2-3 meet at x = 1 with the same vt, 2-3 and 3-4 at x = 2 with others.
    strip_lines += ["f 1/1 2/2 6/6 5/5", "f 2/2 3/3 7/7 6/6", "f 3/9 4/4 8/8 7/10", "f 2 3 7"]
    for name, vertices, faces in (("cube.obj", cube, lines), ("strip.obj", strip, strip_lines)):
        path = write(tmp_path / name, obj_text(vertices, faces))
        mesh = read_mesh(path)
        assert mesh.weld is not None
        ours = shaded_mesh(mesh).normals
        np.testing.assert_allclose(ours, mitsuba_corner_normals(path), rtol=0, atol=1e-6)
    v = cube[read_mesh(tmp_path / "cube.obj").faces]
    flat = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    cube_normals = shaded_mesh(read_mesh(tmp_path / "cube.obj")).normals
    np.testing.assert_allclose(cube_normals, np.repeat(flat[:, None], 3, axis=1), atol=1e-12)
    # Without the texture indices: one smooth normal per position, and no welding keys.
    plain = read_mesh(write(tmp_path / "plain.obj", obj_text(cube, [
        "f " + " ".join(map(str, q)) for q in quads])))
    assert plain.weld is None
    assert not np.allclose(shaded_mesh(plain).normals, np.repeat(flat[:, None], 3, axis=1))


# -- fuzzed files -------------------------------------------------------------------------------

@pytest.mark.parametrize("suffix, valid", [(".obj", lambda: fuzz.VALID_OBJ),
                                           (".ply", lambda: fuzz.ply_bytes(False)),
                                           (".ply", lambda: fuzz.ply_bytes(True)),
                                           (".serialized", fuzz.serialized_bytes)],
                         ids=["obj", "ply-ascii", "ply-binary", "serialized"])
def test_fuzzed_mesh_files_load_or_raise_documented_errors(suffix, valid):
    """Valid mesh files with bytes replaced, deleted, inserted or cut off: each loads or
    raises a MeshFileError (an InstancingError), without NumPy warnings
    (tests/fuzz_inputs.py)."""
    @fuzz.ci_settings(100)
    @given(fuzz.mutated_bytes(valid()))
    def check(data):
        fuzz.load_scene_text(data, suffix)

    check()


# --- PLY mesh attributes -----------------------------------------------------

def write_ply_properties(path: Path, vertex: dict, face: dict, polygons) -> Path:
    """A binary PLY of SQUARE's vertices with the ``vertex`` properties ``vertex`` (name:
    (values, dtype)) after x y z, and the ``face`` properties ``face`` after the indices."""
    v = np.empty(len(SQUARE), dtype=[(n, "f4") for n in "xyz"] + [(n, t) for n, (_, t) in vertex.items()])
    v["x"], v["y"], v["z"] = SQUARE.T
    for name, (values, _) in vertex.items():
        v[name] = values
    f = np.empty(len(polygons), dtype=[("vertex_indices", "O")] + [(n, t) for n, (_, t) in face.items()])
    f["vertex_indices"] = [np.array(p, "i4") for p in polygons]
    for name, (values, _) in face.items():
        f[name] = values
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"),
                     plyfile.PlyElement.describe(f, "face")], text=False).write(str(path))
    return path


def mitsuba_attributes(path: Path) -> dict[str, np.ndarray]:
    """The mesh attributes Mitsuba's ``ply`` plugin reads from ``path``, at the triangles'
    corners (F, 3, dim), as ``MeshData.attribute_corners`` gives ours."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    with warnings.catch_warnings():
        params = mi.traverse(mi.load_dict({"type": "ply", "filename": str(path)}))
    faces = np.array(params["faces"]).reshape(-1, 3)
    out = {}
    for key in params.keys():
        if not key.startswith(("vertex_", "face_")) or key in ("vertex_positions", "vertex_normals",
                                                                "vertex_texcoords"):
            continue
        values = np.array(params[key], np.float64)
        if key.startswith("vertex_"):
            out[key] = values.reshape(len(SQUARE), -1)[faces]
        else:
            out[key] = np.repeat(values.reshape(len(faces), 1, -1), 3, axis=1)
    return out


def test_ply_attributes_are_grouped_as_mitsubas(tmp_path):
    """Every naming rule of Mitsuba's ``ply`` plugin, on one file: the prefix-free colour
    (``red green blue``), runs of ``_x _y _z``, ``_r _g _b`` (``..._color``), ``_0 _1 _2``,
    ``_1 _2 _3`` and single values, integer values taken unscaled; skipped (with a warning):
    a property without a one-letter postfix, a run of 2 or 4, a broken run, a prefix seen
    before, a texture coordinate pair. Ours are Mitsuba's names and values."""
    rng = np.random.default_rng(4)

    def column(dtype="f4"):
        values = rng.uniform(0, 1, len(SQUARE)) if dtype == "f4" else rng.integers(0, 256, len(SQUARE))
        return values, dtype

    vertex = {"red": column(), "green": column(), "blue": column(),
              "s": column(), "t": column(),
              "dir_x": column(), "dir_y": column(), "dir_z": column(),
              "albedo_r": column("u1"), "albedo_g": column("u1"), "albedo_b": column("u1"),
              "weight_0": column(),
              "pair_x": column(), "pair_y": column(),
              "quad_1": column(), "quad_2": column(), "quad_3": column(), "quad_4": column(),
              "mass": column(), "long_xy": column(),
              "spin_1": column(), "spin_2": column(), "spin_3": column(),
              "weight_x": column(),
              # Last: after a broken run, Mitsuba 3.9.1 also drops the next property and
              # miscounts the run after it (ours reads that run).
              "bad_x": column(), "bad_z": column(), "bad_y": column()}
    face = {"tint_0": (rng.uniform(0, 1, 2), "f4"), "tint_1": (rng.uniform(0, 1, 2), "f4"),
            "tint_2": (rng.uniform(0, 1, 2), "f4"), "id_x": (np.array([3, 7]), "f4")}
    path = write_ply_properties(tmp_path / "attributes.ply", vertex, face, [[0, 1, 2], [4, 2, 3]])
    with pytest.warns(UserWarning) as caught:
        mesh = read_ply(path)
    theirs = mitsuba_attributes(path)
    ours = {name: mesh.attribute_corners(name) for name in mesh.attributes}
    assert sorted(ours) == sorted(theirs) == sorted([
        "vertex_color", "vertex_dir", "vertex_albedo_color", "vertex_weight", "vertex_spin",
        "face_tint", "face_id"])
    for name in theirs:
        np.testing.assert_allclose(ours[name], theirs[name], rtol=1e-7, err_msg=name)
    message = " ".join(str(w.message) for w in caught)
    for skipped in ("'pair_x'", "'quad_4'", "'bad_z'", "'mass'", "'long_xy'", "'weight_x'",
                    "'vertex_albedo_color' has integer values"):
        assert skipped in message, skipped
    assert "'s'" not in message  # read as texture coordinates


def test_ply_face_attributes_hold_on_each_fan_triangle(tmp_path):
    """A polygon's attribute is each of its fan triangles' (Mitsuba's plugin takes triangles
    only), and a vertex attribute follows the fan's corners."""
    colour = np.arange(15, dtype=np.float64).reshape(5, 3) / 15
    vertex = {f"c_{k}": (colour[:, k], "f4") for k in range(3)}
    face = {"tag_x": (np.array([0.25, 0.75]), "f4")}
    path = write_ply_properties(tmp_path / "fan.ply", vertex, face, [[0, 1, 2, 3], [1, 4, 2]])
    mesh = read_ply(path)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    np.testing.assert_array_equal(mesh.attribute_corners("face_tag")[..., 0], [[0.25] * 3, [0.25] * 3, [0.75] * 3])
    np.testing.assert_allclose(mesh.attribute_corners("vertex_c"), colour.astype(np.float32)[mesh.faces])
    # Integer face values are taken as they are (Mitsuba 3.9.1 reads an int32 3 as 1.1e-10).
    tagged = write_ply_properties(tmp_path / "int.ply", {}, {"id_x": (np.array([3, 7]), "i4")},
                                  [[0, 1, 2, 3], [1, 4, 2]])
    np.testing.assert_array_equal(read_ply(tagged).attributes["face_id"][:, 0], [3, 3, 7])
    flipped = mesh.flipped()
    np.testing.assert_array_equal(flipped.attribute_corners("vertex_c"), mesh.attribute_corners("vertex_c")[:, ::-1])


def test_ply_attribute_names_must_be_unique(tmp_path):
    """``r g b`` and ``color_x color_y color_z`` would both be ``vertex_color``: refused, as
    Mitsuba refuses the file."""
    ones = (np.ones(len(SQUARE)), "f4")
    vertex = {"r": ones, "g": ones, "b": ones, "color_x": ones, "color_y": ones, "color_z": ones}
    path = write_ply_properties(tmp_path / "twice.ply", vertex, {}, [[0, 1, 2]])
    assert_mesh_error(path, "two mesh attributes are named 'vertex_color'")
