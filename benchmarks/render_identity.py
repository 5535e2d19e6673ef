"""Renders of the bundled scenes as SHA-256 digests: are two versions bit-identical?

Renders every ``scenes/*.json`` scene with ``aov``, ``direct`` and ``path`` at a small
size and fixed seed, and intersects seeded random rays with it, through the public API
only (``instancing.load_scene``, ``instancing.render``, ``Scene.intersect``), so the same
script runs on any version of the package::

    python -m benchmarks.render_identity --save before.json      # on one version
    python -m benchmarks.render_identity --compare before.json   # on another

``--compare`` prints one line per render and exits with status 1 when any differs.
Digests depend on the CPU (vector width) and the LLVM version: compare on one machine.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

import instancing

SCENES = Path(__file__).resolve().parent.parent / "scenes"
INTEGRATORS = ("aov", "direct", "path")


def digests(width: int = 48, height: int = 36, spp: int = 4) -> dict[str, str]:
    """``{"<scene>/<integrator>": sha256 of the float32 image}`` for every bundled scene,
    and ``"<scene>/intersect"``: sha256 of the hit records of 4096 random rays."""
    out = {}
    rng = np.random.default_rng(3)
    for path in sorted(SCENES.glob("*.json")):
        scene = instancing.load_scene(path)
        # Ray origins in the scene's box rounded to quarter units and widened (the same rays
        # whatever the last bits of the bounds).
        lo, hi = np.round(scene.bounds[0] * 4) / 4 - 0.5, np.round(scene.bounds[1] * 4) / 4 + 0.5
        d = rng.normal(size=(4096, 3))
        hits = scene.intersect(rng.uniform(lo, hi, (4096, 3)), d / np.linalg.norm(d, axis=1)[:, None])
        record = b"".join(np.ascontiguousarray(a).tobytes()
                          for a in (hits.t, hits.p, hits.n, hits.instance, hits.prim))
        out[f"{path.stem}/intersect"] = hashlib.sha256(record).hexdigest()
        for integrator in INTEGRATORS:
            image = instancing.render(scene, integrator, spp=spp, seed=7, width=width, height=height,
                                      max_depth=4 if integrator == "path" else None)
            data = np.ascontiguousarray(np.asarray(image, np.float32))
            out[f"{path.stem}/{integrator}"] = hashlib.sha256(data.tobytes()).hexdigest()
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--save", help="write the digests to this JSON file")
    group.add_argument("--compare", help="compare against digests saved with --save")
    args = parser.parse_args(argv)
    current = digests()
    if args.save:
        Path(args.save).write_text(json.dumps(current, indent=1) + "\n")
        print(f"{len(current)} renders -> {args.save}")
        return 0
    saved = json.loads(Path(args.compare).read_text())
    differ = 0
    for key in sorted(set(saved) | set(current)):
        same = saved.get(key) == current.get(key)
        differ += not same
        print(f"{key:<28} {'identical' if same else 'DIFFERS'}")
    print(f"{len(current) - differ} of {len(current)} renders bit-identical")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
