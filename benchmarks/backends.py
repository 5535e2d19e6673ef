"""The same code on two Dr.Jit backends: LLVM (CPU) against CUDA (GPU).

The renderer picks its backend once, at import, from ``INSTANCING_BACKEND``
(:mod:`instancing.core.backend`); nothing else in the code path depends on it. This
script checks that claim on the bundled scenes: run it with ``--save DIR`` on
one backend, then with ``--against DIR`` on the other, and it prints, per scene,

* hits of the same random rays: hit/miss and instance agreement, the 99.9th
  percentile of the relative t difference and of the normal angle difference;
* images (``aov``, ``direct``, ``path``; same seed, so the same sample
  sequences): relative RMSE of one backend's image against the other's, beside
  the image's own Monte Carlo noise (relative RMSE between two seeds);
* the median time of a later render (compiled kernels cached) on each backend.

Usage:
    INSTANCING_BACKEND=llvm python -m benchmarks.backends --save out/llvm
    INSTANCING_BACKEND=cuda python -m benchmarks.backends --against out/llvm
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

import instancing
from instancing.core.backend import BACKEND_NAME, dr

ROOT = Path(__file__).resolve().parent.parent
INTEGRATORS = ("aov", "direct", "path")


def bundled_scenes() -> list[Path]:
    """Every bundled scene file with a camera (read from the JSON, not loaded)."""
    return [p for p in sorted((ROOT / "scenes").glob("*.json"))
            if "camera" in json.loads(p.read_text())]


def scene_rays(scene, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Origins uniform in the scene's bounds (grown by 10 %), isotropic directions."""
    lo, hi = scene.bounds
    pad = 0.1 * (hi - lo)
    rng = np.random.default_rng(seed)
    o = rng.uniform(lo - pad, hi + pad, (count, 3)).astype(np.float32)
    d = rng.normal(size=(count, 3))
    return o, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def measure(path: Path, args) -> dict[str, np.ndarray]:
    """Hits, images (two seeds) and later-render times of one scene on this backend."""
    scene = instancing.load_scene(path)
    o, d = scene_rays(scene, args.rays, seed=1)
    hits = scene.intersect(o, d)
    record = {"t": hits.t, "n": hits.n, "instance": hits.instance}
    for integrator in INTEGRATORS:
        def run(seed: int) -> np.ndarray:
            return np.asarray(instancing.render(scene, integrator, spp=args.spp, seed=seed,
                                                width=args.width, height=args.height))
        record[f"{integrator}_image"] = run(0)
        record[f"{integrator}_noise"] = run(1)  # a second seed: the image's own noise
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            run(0)
            dr.sync_thread()
            times.append(time.perf_counter() - start)
        record[f"{integrator}_seconds"] = np.array(statistics.median(times))
    return record


def rel_rmse(a: np.ndarray, b: np.ndarray) -> float:
    """RMSE of a - b over the RMS of b (0 when both are 0)."""
    scale = np.sqrt(np.mean(np.square(b, dtype=np.float64)))
    return float(np.sqrt(np.mean(np.square(a - b, dtype=np.float64))) / scale) if scale else 0.0


def compare(ours: dict, theirs: dict) -> dict[str, float]:
    """Agreement figures of this backend's record against the saved one."""
    hit_a, hit_b = ours["instance"] >= 0, theirs["instance"] >= 0
    both = hit_a & hit_b
    rel_t = np.abs(ours["t"][both].astype(np.float64) - theirs["t"][both]) / theirs["t"][both]
    a, b = ours["n"][both].astype(np.float64), theirs["n"][both].astype(np.float64)
    # atan2(|a x b|, a . b): exact near 0, where arccos of a float32 dot product is not.
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))
    same = both & (ours["instance"] == theirs["instance"])
    row = {"hit/miss agree %": 100.0 * np.mean(hit_a == hit_b),
           "instance agree %": 100.0 * np.sum(same) / max(np.sum(both), 1),
           "t rel 99.9%": float(np.percentile(rel_t, 99.9)) if rel_t.size else 0.0,
           "normal deg 99.9%": float(np.percentile(angle, 99.9)) if angle.size else 0.0}
    for integrator in INTEGRATORS:
        image = f"{integrator}_image"
        row[f"{integrator} rel RMSE"] = rel_rmse(ours[image], theirs[image])
        row[f"{integrator} noise"] = rel_rmse(ours[f"{integrator}_noise"], ours[image])
        row[f"{integrator} s (this/saved)"] = (float(ours[f"{integrator}_seconds"]),
                                               float(theirs[f"{integrator}_seconds"]))
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--save", type=Path, help="write this backend's records to this folder")
    where.add_argument("--against", type=Path, help="compare with the records in this folder")
    parser.add_argument("--rays", type=int, default=200_000)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--width", type=int, default=96)
    parser.add_argument("--height", type=int, default=72)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    print(f"backend: {BACKEND_NAME}")
    for path in bundled_scenes():
        record = measure(path, args)
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(args.save / f"{path.stem}.npz", **record)
            print(f"{path.stem}: saved")
            continue
        saved = dict(np.load(args.against / f"{path.stem}.npz"))
        row = compare(record, saved)
        print(f"{path.stem}: " + ", ".join(
            f"{k} {v[0]:.3g}/{v[1]:.3g}" if isinstance(v, tuple) else f"{k} {v:.3g}"
            for k, v in row.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
