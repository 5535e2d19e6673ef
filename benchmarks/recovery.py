"""Recovery of instance transforms: the bundled scenes, and the effect of coarse to fine.

    python -m benchmarks.recovery [--part bundled,coarse,shadow] [--iterations 300] [--spp 8]

1. bundled: ``scenes/recover_init.json`` -> ``scenes/recover_target.json`` (box,
   card, elliptic torus mesh; translations off by 15-20 % of their
   size, rotations by 18-22 degrees, scales by 20 %), 128x128: iterations, time
   per iteration, and the final errors against the targets (1 % of the size,
   1 degree, 1 %). Writes ``docs/recover_convergence.png`` and ``docs/recover.png``
   (target | before | after).
2. coarse: the box alone moved by 1.5 times its size, so that it no longer
   overlaps its target: plain descent against blurred-loss descent (blur from
   16 px down to 0 over the first half), same iterations and seeds.
3. shadow: the bundled scenes with the lamp moved off the camera
   (SHADOW_LIGHT), so that every instance's shadow on the ground is in view:
   recovery with the shadow-boundary term (sppi) and, for comparison, without it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import instancing
from instancing.ad.recovery import recover, recover_files, write_convergence_plot

ROOT = Path(__file__).resolve().parents[1]
TARGET = ROOT / "scenes" / "recover_target.json"
INIT = ROOT / "scenes" / "recover_init.json"
#: Where the shadow part puts the lamp (the bundled scenes have it at the camera).
SHADOW_LIGHT = [3.0, -2.0, 5.0]


def shadowed_copies(folder: Path, light=SHADOW_LIGHT) -> tuple[Path, Path]:
    """The bundled target and init scenes with the lamp at ``light``, written to ``folder``
    (mesh paths made absolute): (target, init)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for source in (TARGET, INIT):
        scene = json.loads(source.read_text())
        for model in scene["models"].values():
            if "filename" in model:
                model["filename"] = str((source.parent / model["filename"]).resolve())
        scene["lights"][0]["position"] = list(light)
        paths.append(folder / source.name)
        paths[-1].write_text(json.dumps(scene, indent=1))
    return paths[0], paths[1]


def _summary(run, iterations: int, spp: int) -> dict:
    final = run.history.errors[-1]
    return {"iterations": iterations, "spp": spp,
            "seconds_per_iteration": float(np.median(run.history.seconds)),
            "initial": run.history.errors[0], "final": final,
            "met": {name: bool(e[0] < 0.01 and e[1] < 1.0 and e[2] < 0.01) for name, e in final.items()}}


def bundled(iterations: int, spp: int, out: Path) -> dict:
    run = recover_files(str(TARGET), str(INIT), str(out), iterations=iterations, spp=spp)
    print(run.table(), flush=True)
    docs = ROOT / "docs"
    write_convergence_plot(run.history, str(docs / "recover_convergence.png"))
    import mitsuba as mi
    strip = np.concatenate([np.array(mi.Bitmap(str(out / f"{n}.png"))) for n in ("target", "before", "after")], 1)
    mi.Bitmap(strip).write(str(docs / "recover.png"))
    return _summary(run, iterations, spp)


def shadow(iterations: int, spp: int, out: Path) -> dict:
    """The bundled recovery with shadows in view, with and without the shadow term."""
    target, init = shadowed_copies(out / "scenes")
    results = {"light": SHADOW_LIGHT}
    for label, sppi in (("with the shadow term", None), ("without (sppi 0)", 0)):
        run = recover_files(str(target), str(init), str(out / f"sppi_{sppi}"), iterations=iterations,
                            spp=spp, sppi=sppi)
        print(f"-- {label}\n{run.table()}", flush=True)
        results[label] = _summary(run, iterations, spp)
    return results


def coarse_to_fine(iterations: int, spp: int) -> dict:
    target_scene = instancing.load_scene(TARGET)
    target = instancing.render(target_scene, "direct", spp=256, seed=5)
    results = {}
    for blur_start in (0.0, 16.0):
        scene = instancing.load_scene(TARGET)
        params = instancing.traverse(scene)
        box = scene.instance_ids.index("box")
        size = 2.0 * np.linalg.svd(scene.to_world[box][:3, :3], compute_uv=False)[0]
        t = np.array(params["box.translation"]).ravel()
        params["box.translation"] = (t + 1.5 * size * np.array([0.8, 0.0, 0.6])).tolist()
        params.update()
        history = recover(params, target, ["box.translation"], iterations=iterations, spp=spp,
                          blur_start=blur_start, target_to_world=target_scene.to_world)
        start, end = history.errors[0]["box"][0], history.errors[-1]["box"][0]
        label = "blurred loss" if blur_start else "plain loss"
        print(f"{label:<13} translation error / size: {start:.3f} -> {end:.4f}", flush=True)
        results[label] = {"initial": start, "final": end}
    return results


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--part", default="bundled,coarse,shadow")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--out", default=str(ROOT / "recover_out"))
    args = parser.parse_args(argv)
    path = ROOT / "benchmarks" / "results_recovery.json"
    # Parts run separately update their entry and keep the others.
    results = json.loads(path.read_text()) if path.is_file() else {}
    parts = args.part.split(",")
    if "bundled" in parts:
        print("== bundled recovery scenes, 128x128 ==")
        results["bundled"] = bundled(args.iterations, args.spp, Path(args.out))
    if "coarse" in parts:
        print("== coarse to fine: the box moved by 1.5 times its size ==")
        results["coarse"] = coarse_to_fine(min(args.iterations, 150), args.spp)
    if "shadow" in parts:
        print(f"== the bundled scenes with the lamp at {SHADOW_LIGHT}: shadows in view ==")
        results["shadow"] = shadow(args.iterations, args.spp, Path(args.out) / "shadow")
    path.write_text(json.dumps(results, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
