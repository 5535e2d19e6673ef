"""Recover three instances' transforms (a box, a card, a torus mesh) from a target image.

Starts from ``scenes/recover_init.json``, whose instances are moved by 15-20 % of
their size, turned by 18-22 degrees and scaled by +-20 %, and optimises their
translation, rotation and scale with Adam until the render matches
``scenes/recover_target.json``. Writes before/after images, the convergence plot
and the recovered scene to the output folder and prints the errors.

Usage: python examples/recover_transforms.py [--iterations 300] [--spp 8] [--out recover_out]
"""

import argparse
from pathlib import Path

from tqdm import tqdm

from instancing.ad.recovery import recover_files

ROOT = Path(__file__).resolve().parent.parent


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--reference-spp", type=int, default=256)
    parser.add_argument("--out", default="recover_out")
    args = parser.parse_args(argv)
    with tqdm(total=args.iterations, unit="it", leave=False) as bar:
        run = recover_files(str(ROOT / "scenes" / "recover_target.json"),
                            str(ROOT / "scenes" / "recover_init.json"), args.out,
                            iterations=args.iterations, spp=args.spp,
                            reference_spp=args.reference_spp,
                            progress=lambda it, loss: (bar.set_postfix(loss=f"{loss:.2e}"), bar.update(1)))
    print(run.table())
    print("wrote " + ", ".join(run.written))


if __name__ == "__main__":
    main()
