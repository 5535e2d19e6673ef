"""Shared test fixtures: random affine instances, random rays, Mitsuba twins of our scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import instancing
from instancing.validation import reference
from instancing.core.backend import MITSUBA_VARIANT
from instancing.io.mesh_file import read_mesh

MESH_DIR = Path(__file__).resolve().parent.parent / "scenes" / "meshes"
KINDS = ["sphere", "cube", "rectangle", "disk", "cylinder", "mesh"]
#: The mesh used for the 'mesh' kind in tests.
MESH_FILE = MESH_DIR / "torus.obj"


def random_affine(rng: np.random.Generator, spread: float = 4.0, reflect: bool = False) -> np.ndarray:
    """A random invertible affine matrix: rotation, non-uniform scale, shear, translation."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    scale = np.diag(rng.uniform(0.3, 2.0, 3))
    shear = np.eye(3)
    shear[0, 1], shear[0, 2], shear[1, 2] = rng.uniform(-0.6, 0.6, 3)
    a = q @ shear @ scale
    if reflect != (np.linalg.det(a) < 0):
        a = a @ np.diag([-1.0, 1.0, 1.0])
    m = np.eye(4)
    m[:3, :3] = a
    m[:3, 3] = rng.uniform(-spread, spread, 3)
    return m


def float32_exact(x: np.ndarray) -> np.ndarray:
    """Round to float32 and back, so that both sides see exactly the same rays."""
    return np.asarray(x, np.float32).astype(np.float64)


def random_rays(rng: np.random.Generator, lo, hi, n: int):
    """Origins uniform in a box (many start inside shapes), isotropic unit directions."""
    o = rng.uniform(lo, hi, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float32_exact(o), float32_exact(d)


def scene_dict(kinds: list[str], matrices: list[np.ndarray]) -> dict:
    """Our scene: one instance per (kind, matrix)."""
    return {
        "models": {"torus": {"type": "obj", "filename": str(MESH_FILE)}},
        "instances": [{"model": "torus" if k == "mesh" else k, "to_world": m.tolist()}
                      for k, m in zip(kinds, matrices)],
    }


def reference_instances(kinds: list[str], matrices: list[np.ndarray], rounding=np.float64) -> list[dict]:
    """The same instances for instancing/reference.py, transforms and mesh vertices rounded
    to ``rounding`` (float32: the scene as the renderers store it)."""
    mesh = read_mesh(MESH_FILE)
    return reference.instance_list(kinds, matrices, (mesh.vertices, mesh.faces), rounding)


def mitsuba_instanced_scene(kinds: list[str], matrices: list[np.ndarray]):
    """Mitsuba twin: one shapegroup per kind, one ``instance`` per matrix."""
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    plugin = {"sphere": {"type": "sphere"}, "cube": {"type": "cube"},
              "rectangle": {"type": "rectangle"}, "disk": {"type": "disk"},
              "cylinder": {"type": "cylinder"},
              "mesh": {"type": "obj", "filename": str(MESH_FILE)}}
    scene = {"type": "scene"}
    for k in sorted(set(kinds)):
        scene[f"group_{k}"] = {"type": "shapegroup", "shape": plugin[k]}
    for i, (k, m) in enumerate(zip(kinds, matrices)):
        scene[f"inst_{i:05d}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": f"group_{k}"},
                                  "to_world": mi.ScalarTransform4f(m.tolist())}
    return mi, mi.load_dict(scene)


def mitsuba_intersect(kinds, matrices, o: np.ndarray, d: np.ndarray) -> dict:
    """Mitsuba's full ray_intersect on the instanced twin: t, n (NumPy), hit mask."""
    mi, scene = mitsuba_instanced_scene(kinds, matrices)
    ray = mi.Ray3f(mi.Point3f(*[np.ascontiguousarray(o[:, k], np.float32) for k in range(3)]),
                   mi.Vector3f(*[np.ascontiguousarray(d[:, k], np.float32) for k in range(3)]))
    si = scene.ray_intersect(ray)
    t = np.asarray(si.t, np.float64)
    return {"t": np.where(np.isfinite(t), t, np.inf), "n": np.asarray(si.n, np.float64).T,
            "p": np.asarray(si.p, np.float64).T}


def angle_deg(a: np.ndarray, b: np.ndarray, oriented: bool = True) -> np.ndarray:
    """Angle between vectors in degrees, via atan2(|a x b|, a.b) in float64 (exact near 0).

    ``oriented=False`` ignores the sign (for Mitsuba's mesh normals, which flip
    under reflections).
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    dot = np.sum(a * b, axis=1)
    dot = dot if oriented else np.abs(dot)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), dot))


def load(kinds, matrices, accel="auto") -> instancing.Scene:
    return instancing.load_scene(scene_dict(kinds, matrices), accel=accel)


def write_serialized(path: Path, meshes: list[dict], version: int = 4, double: bool = False) -> Path:
    """A serialized file as Mitsuba's format description defines it: per mesh a header
    (0x041C, version) and a zlib stream of flags, (v4) a name, counts, positions, optional
    normals, texture coordinates and colours, uint32 triangles; then the meshes' offsets
    (uint64 in v4, uint32 in v3) and their count."""
    import struct
    import zlib
    real = "<f8" if double else "<f4"
    blob, offsets = b"", []
    for k, mesh in enumerate(meshes):
        flags = (0x2000 if double else 0x1000) | (0x0001 if "normals" in mesh else 0) \
            | (0x0002 if "uvs" in mesh else 0) | (0x0008 if "colors" in mesh else 0)
        body = struct.pack("<I", flags)
        if version == 4:
            body += f"mesh{k}".encode() + b"\0"
        body += struct.pack("<QQ", len(mesh["vertices"]), len(mesh["faces"]))
        for key in ("vertices", "normals", "uvs", "colors"):
            if key in mesh:
                body += np.asarray(mesh[key], real).tobytes()
        body += np.asarray(mesh["faces"], "<u4").tobytes()
        offsets.append(len(blob))
        blob += struct.pack("<HH", 0x041C, version) + zlib.compress(body)
    table = np.array(offsets, "<u8" if version == 4 else "<u4").tobytes()
    path.write_bytes(blob + table + struct.pack("<I", len(meshes)))
    return path


def assert_textured_bsdf_is_mitsubas(table, bsdf, si, wi: np.ndarray, wo: np.ndarray, uv: np.ndarray,
                                     reach: float = 0.0) -> None:
    """Our material table's row 0 against Mitsuba's ``bsdf`` on the surface interaction ``si``
    (shading frame the identity, its uv and wi set): f cos at the directions ``wi``, ``wo``
    (N, 3) and surface coordinates ``uv`` (2, N) to float32 round-off, and the densities where
    both directions lie on one side (Mitsuba's roughplastic and blend give their lobes'
    formulas on opposite sides, where f is 0). More than ``reach`` of Mitsuba's values are
    non-zero (the directions reach the lobe) and they vary."""
    from instancing.core.backend import Array2f, Array3f, Float, UInt32, mitsuba_module
    mi = mitsuba_module()
    vectors = [Array3f(*w.T.astype(np.float32)) for w in (wi, wo)]
    ours_f = np.asarray(table.evaluate(UInt32(0), *vectors, Array2f(*uv)), np.float64)
    ours_pdf = np.asarray(table.pdf(UInt32(0), *vectors, Array2f(*uv)), np.float64)
    wo_mi = mi.Vector3f(*[Float(wo[:, k].astype(np.float32)) for k in range(3)])
    theirs_f = np.asarray(bsdf.eval(mi.BSDFContext(), si, wo_mi), np.float64)
    theirs_pdf = np.asarray(bsdf.pdf(mi.BSDFContext(), si, wo_mi), np.float64)
    assert (theirs_f > 0).mean() > reach and np.std(theirs_f) > 0
    np.testing.assert_allclose(ours_f, theirs_f, rtol=1e-4, atol=1e-5 * np.abs(theirs_f).max())
    same_side = wi[:, 2] * wo[:, 2] > 0
    np.testing.assert_allclose(ours_pdf[same_side], theirs_pdf[same_side], rtol=1e-4,
                               atol=1e-5 * theirs_pdf.max())


class GivenNumbers:
    """A sampler stand-in that hands out given arrays in order."""

    def __init__(self, *arrays):
        self.arrays = list(arrays)

    def next_float32(self):
        return self.arrays.pop(0)
