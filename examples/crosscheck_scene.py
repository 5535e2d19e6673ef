"""Cross-check a scene against Mitsuba 3: same rays, same images, measured agreement.

Prints the table of `instancing crosscheck` (hit/miss disagreement, t, position
and normal differences, instance agreement, errors of both renderers against a
float64 reference, image relative RMSE and timings) for a bundled scene.

Usage: python examples/crosscheck_scene.py [--scene scenes/light_point.json] [--rays N] [--spp S]
"""

import argparse
from pathlib import Path

import instancing as ins
from instancing.validation.crosscheck import crosscheck

ROOT = Path(__file__).resolve().parent.parent


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default=str(ROOT / "scenes" / "light_point.json"))
    parser.add_argument("--rays", type=int, default=1 << 18)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--size", type=int, default=96, help="image width (height follows 4:3)")
    args = parser.parse_args(argv)
    scene = ins.load_scene(args.scene)
    scene.set_camera(scene.camera.with_size(args.size, args.size * 3 // 4))
    report = crosscheck(scene, random_rays=args.rays, reference_rays=min(args.rays, 20000),
                        spp=args.spp, reference_spp=4 * args.spp, integrators=("aov", "direct"),
                        source=args.scene)
    print(report.table())


if __name__ == "__main__":
    main()
