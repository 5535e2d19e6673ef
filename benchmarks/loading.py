"""Loading at scale: seconds for ``load_scene`` (parse and build) of N sphere instances given
as 4x4 matrices, in each form a user hands them over, beside Mitsuba's ``load_file`` of the
same XML.

* ``dict``: a Python dict, one instance entry per sphere with its ``to_world`` matrix (nested
  lists);
* ``ops``: the same dict with each sphere placed by a list of operations instead (translate,
  rotate about z, scale: the same matrix);
* ``JSON``: the same dict as a ``.json`` file;
* ``npy``: one entry whose ``to_world`` names an ``.npy`` file of (N, 4, 4) matrices;
* ``XML``: Mitsuba XML, one ``shapegroup`` holding the sphere and N ``instance`` shapes with a
  ``<matrix>`` each; Mitsuba loads the same file.

The spheres are the intersection benchmark's uniform field. Medians of ``--repeats`` loads per
form (after a first, untimed one), ours and Mitsuba alternating on the XML. Targets (the performance issue): under 1 s for a
dict or JSON scene of 100 000 instances and for Mitsuba XML with 10 000.

Meshes: one binary PLY heightfield (the terrain scene's hills, ``scenes/meshes/generate.py``) of
about ``--triangles`` triangles, loaded as a scene of one shape by both renderers (reading the
file and building the acceleration: our SAH BVH, Mitsuba's Embree scene), alternating.

Usage: python -m benchmarks.loading [--counts 10000 100000] [--triangles 100000 1000000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import instancing
from instancing.core.backend import MITSUBA_VARIANT

from .intersect import sphere_field, timed

#: Targets: form -> (instances, seconds).
TARGETS = {"dict": (100_000, 1.0), "JSON": (100_000, 1.0), "XML": (10_000, 1.0)}


def _xml(matrices: np.ndarray) -> str:
    """Mitsuba XML: one shapegroup with a unit sphere, one instance per matrix."""
    lines = ['<scene version="3.0.0">', '  <shape type="shapegroup" id="ball">',
             '    <shape type="sphere"/>', '  </shape>']
    for m in matrices:
        values = " ".join(f"{v:.9g}" for v in m.ravel())
        lines.append(f'  <shape type="instance"><ref id="ball"/>'
                     f'<transform name="to_world"><matrix value="{values}"/></transform></shape>')
    lines.append("</scene>")
    return "\n".join(lines)


def _operations(matrix: np.ndarray, angle: float) -> list[dict]:
    """A sphere's placement (translation times uniform scale) as an operation list, with a
    rotation about z (which leaves the sphere where it is)."""
    return [{"translate": matrix[:3, 3].tolist()}, {"rotate": {"axis": [0, 0, 1], "angle": float(angle)}},
            {"scale": float(matrix[0, 0])}]


def measure(counts: list[int], repeats: int) -> list[dict]:
    """Rows (form, instances, ours s, Mitsuba s or None) for every form and count."""
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANT)
    rows = []
    folder = Path(tempfile.mkdtemp(prefix="loading_"))
    instancing.load_scene({"instances": [{"model": "sphere"}]})  # (imports and first kernels)
    for n in counts:
        matrices = sphere_field(n)
        entries = [{"model": "sphere", "to_world": m.tolist()} for m in matrices]
        json_path, npy_path, xml_path = (folder / f"field_{n}{ext}" for ext in (".json", ".npy", ".xml"))
        json_path.write_text(json.dumps({"instances": entries}))
        np.save(npy_path, matrices)
        npy_scene = folder / f"field_{n}_npy.json"
        npy_scene.write_text(json.dumps({"instances": [{"model": "sphere", "to_world": npy_path.name}]}))
        xml_path.write_text(_xml(matrices))
        rows.append({"form": "dict", "instances": n, "ours": timed(
            lambda: instancing.load_scene({"instances": entries}), repeats), "mitsuba": None})
        placed = [{"model": "sphere", "to_world": _operations(m, angle)}
                  for m, angle in zip(matrices, np.random.default_rng(n).uniform(0, 360, n))]
        rows.append({"form": "ops", "instances": n, "ours": timed(
            lambda: instancing.load_scene({"instances": placed}), repeats), "mitsuba": None})
        rows.append({"form": "JSON", "instances": n, "ours": timed(
            lambda: instancing.load_scene(json_path), repeats), "mitsuba": None})
        rows.append({"form": "npy", "instances": n, "ours": timed(
            lambda: instancing.load_scene(npy_scene), repeats), "mitsuba": None})
        # The XML loads alternate between the renderers (each load timed once).
        seconds = {"ours": [], "mitsuba": []}
        for _ in range(repeats):
            for name, load in (("ours", lambda: instancing.load_scene(xml_path)),
                               ("mitsuba", lambda: mi.load_file(str(xml_path)))):
                start = time.perf_counter()
                load()
                seconds[name].append(time.perf_counter() - start)
        rows.append({"form": "XML", "instances": n,
                     **{name: statistics.median(s) for name, s in seconds.items()}})
        for row in rows[-5:]:
            print(_line(row), flush=True)
    return rows


def measure_meshes(triangles: list[int], repeats: int) -> list[dict]:
    """Rows (triangles, ours s, Mitsuba s) for a heightfield PLY of about each count."""
    import mitsuba as mi
    from scenes.meshes.generate import terrain, write_ply
    mi.set_variant(MITSUBA_VARIANT)
    folder = Path(tempfile.mkdtemp(prefix="loading_mesh_"))
    rows = []
    for n in triangles:
        cells = max(1, round((n / 2) ** 0.5))
        path = folder / f"terrain_{cells}.ply"
        write_ply(path, *terrain(cells))
        ours = {"models": {"hills": {"type": "ply", "filename": str(path)}}, "instances": [{"model": "hills"}]}
        theirs = {"type": "scene", "hills": {"type": "ply", "filename": str(path)}}
        loads = (("ours", lambda: instancing.load_scene(ours)), ("mitsuba", lambda: mi.load_dict(theirs)))
        for _, load in loads:  # (first kernels and file cache)
            load()
        seconds = {"ours": [], "mitsuba": []}
        for _ in range(repeats):
            for name, load in loads:
                start = time.perf_counter()
                load()
                seconds[name].append(time.perf_counter() - start)
        rows.append({"triangles": 2 * cells * cells, **{k: statistics.median(v) for k, v in seconds.items()}})
        r = rows[-1]
        print(f"PLY    {r['triangles']:>8} triangles {r['ours']:>9.2f} {r['mitsuba']:>9.2f}  "
              f"{r['ours'] / r['mitsuba']:.1f}x Mitsuba's time", flush=True)
    return rows


def _line(row: dict) -> str:
    target = TARGETS.get(row["form"])
    verdict = ""
    if target is not None and row["instances"] == target[0]:
        verdict = f"target < {target[1]:g} s: {'met' if row['ours'] < target[1] else 'MISSED'}"
    theirs = "-" if row["mitsuba"] is None else f"{row['mitsuba']:.2f}"
    return f"{row['form']:<6} {row['instances']:>8} {row['ours']:>9.2f} {theirs:>9}  {verdict}"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--triangles", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    print(f"{'form':<6} {'instances':>8} {'ours s':>9} {'Mitsuba s':>9}")
    rows = measure(args.counts, args.repeats)
    meshes = measure_meshes(args.triangles, args.repeats)
    return {"counts": args.counts, "repeats": args.repeats, "rows": rows, "meshes": meshes}


if __name__ == "__main__":
    main()
