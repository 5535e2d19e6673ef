"""Intersect rays with many instances of one shared model (lecture: "Instancing").

Builds a ring of torus instances from a single mesh model, each placed by its
own affine transform (rotation, non-uniform scale, one reflected), shoots a
fan of rays from the centre, and prints which instance each ray hits, where,
and with which outward normal.

Usage: python examples/intersect_instances.py [--count N] [--rays R]
"""

import argparse
from pathlib import Path

import numpy as np

import instancing as ins

MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"


def ring_of_tori(count: int) -> dict:
    """A scene dict: `count` instances of one torus model around the z axis."""
    instances = []
    for k in range(count):
        angle = 360.0 * k / count
        # world_from_object = rotate about z, move out to radius 5, stand the torus up, squash it.
        world_from_object = (ins.rotate_z(angle) @ ins.translate([5.0, 0.0, 0.0])
                             @ ins.rotate_x(90.0) @ ins.scale([1.0, 1.0, 0.5]))
        if k == 0:
            world_from_object = world_from_object @ ins.reflect("x")  # a mirrored copy
        matrix, _ = world_from_object.to_numpy()
        instances.append({"id": f"torus{k}", "model": "torus", "material": "gold",
                          "to_world": matrix.tolist()})
    return {"models": {"torus": {"type": "obj", "filename": str(MESHES / "torus.obj")}},
            "materials": {"gold": {"type": "diffuse", "reflectance": [0.9, 0.7, 0.2]}},
            "instances": instances}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--count", type=int, default=12)
    parser.add_argument("--rays", type=int, default=16)
    args = parser.parse_args(argv)
    scene = ins.load_scene(ring_of_tori(args.count))
    print(f"{len(scene.instance_ids)} instances of one mesh, acceleration: {scene.accel}")
    angles = np.linspace(0.0, 2 * np.pi, args.rays, endpoint=False)
    directions = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])
    origins = np.zeros_like(directions)
    hits = scene.intersect(origins, directions)
    for k in range(args.rays):
        if hits.instance[k] < 0:
            print(f"ray {k:2d}: miss")
            continue
        p, n = hits.p[k], hits.n[k]
        print(f"ray {k:2d}: {scene.instance_ids[hits.instance[k]]:<8} triangle {hits.prim[k]:4d} "
              f"t={hits.t[k]:.4f} p=({p[0]:+.3f}, {p[1]:+.3f}, {p[2]:+.3f}) "
              f"n=({n[0]:+.3f}, {n[1]:+.3f}, {n[2]:+.3f})")


if __name__ == "__main__":
    main()
