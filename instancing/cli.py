"""Command line: ``instancing render SCENE``, ``intersect SCENE``, ``crosscheck SCENE``,
``recover TARGET --init SCENE`` and ``stress`` (also ``python -m instancing``).

Bad arguments and bad scenes print one clear line and exit with status 2;
no traceback.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from typing import Callable

import numpy as np

from pathlib import Path

from tqdm import tqdm

from .ad.recovery import CHECKPOINT, LR, REFERENCE_SPP, recover_files, resume_files
from .core.backend import dr
from .core.errors import InstancingError, SceneError
from .core.memory import require_memory
from .io.image import ImageDataError, ImageFileError, write_exr, write_png
from .io.scene_file import load_scene
from .rendering.film import INTEGRATORS, channel_names, render, render_settings
from .validation.crosscheck import crosscheck
from .validation.stress import SIZES as STRESS_SIZES
from .validation.stress import format_table, run_suite

#: Characters from dark to bright for the terminal preview.
_SHADES = " .:-=+*#%@"


def _int_at_least(least: int) -> Callable[[str], int]:
    """An argparse type: integers >= ``least`` (1: positive, 0: non-negative)."""
    what = "positive" if least == 1 else "non-negative" if least == 0 else f">= {least}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {what} integer, got {text!r}") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"expected a {what} integer, got {value}")
        return value

    return parse


_positive_int, _non_negative_int = _int_at_least(1), _int_at_least(0)


def build_parser() -> argparse.ArgumentParser:
    # No prefix abbreviations: '--sp' must not silently mean '--spp' (or '--sppi').
    parser = argparse.ArgumentParser(prog="instancing", description="Instanced ray tracing on Dr.Jit.",
                                     allow_abbrev=False)
    commands = parser.add_subparsers(dest="command", required=True)
    cross = commands.add_parser("crosscheck", allow_abbrev=False,
                                help="compare rays and images with Mitsuba 3 on the same scene")
    cross.add_argument("scene", help="scene file (.json or Mitsuba .xml)")
    cross.add_argument("--rays", type=_positive_int, default=1 << 20, help="random rays (default 1048576)")
    cross.add_argument("--reference-rays", type=_positive_int, default=20000,
                       help="rays also traced by the float64 reference (default 20000)")
    cross.add_argument("--spp", type=_positive_int, default=1024, help="our samples per pixel")
    cross.add_argument("--reference-spp", type=_positive_int, default=4096, help="Mitsuba's samples per pixel")
    cross.add_argument("--integrators", default="aov,direct,path",
                       help="comma-separated images to compare ('' for rays only)")
    cross.add_argument("--width", type=_positive_int, help="film width for the images")
    cross.add_argument("--height", type=_positive_int, help="film height for the images")
    cross.add_argument("--out", default="crosscheck_out", help="folder for disagreements and difference images")
    cross.add_argument("--seed", type=_non_negative_int, default=0)
    cross.add_argument("--repeats", type=_positive_int, default=1,
                       help="renders per renderer at --spp, image errors as their RMS (default 1; "
                            "4 keeps a firefly or a bright edge from deciding the verdict)")
    rend = commands.add_parser("render", allow_abbrev=False, help="render a scene to EXR (and a PNG preview)")
    rend.add_argument("scene", help="scene file (.json or .xml)")
    rend.add_argument("-o", "--output", help="output .exr (with a .png preview beside it) or .png only "
                                             "(default: the scene's name in the current folder, .exr)")
    rend.add_argument("--spp", type=_positive_int, default=None,
                      help="samples per pixel (default: the camera's sample count in the file, else 64)")
    rend.add_argument("--integrator", choices=list(INTEGRATORS), default=None,
                      help="default: the file's integrator (Mitsuba's <integrator>), else direct")
    rend.add_argument("--width", type=_positive_int, help="film width (default: the camera's)")
    rend.add_argument("--height", type=_positive_int, help="film height (default: the camera's)")
    rend.add_argument("--seed", type=_non_negative_int, default=0)
    rend.add_argument("--camera", help="the camera to render, by index or id (default: every "
                                       "camera; several are written as NAME_<id or index>.exr)")
    rend.add_argument("--max-depth", type=int, default=None,
                      help="longest path for 'path' and 'volpath' (1: emitters only, 2: direct light, -1: "
                           "unbounded, the default)")
    rend.add_argument("--rr-depth", type=_positive_int, default=None,
                      help="depth from which Russian roulette may stop a 'path' or 'volpath' path "
                           "(default: the file's, else 5)")
    rend.add_argument("--hide-emitters", action=argparse.BooleanOptionalAction, default=None,
                      help="hide the emitters seen directly, as Mitsuba's hide_emitters (default: the "
                           "file's, else shown)")
    for strategy in ("emitter", "bsdf"):
        rend.add_argument(f"--{strategy}-samples", type=_non_negative_int, default=None,
                          help=f"{strategy} samples per camera hit of 'direct', as Mitsuba's "
                               f"{strategy}_samples (default: the file's, else 1)")
    rec = commands.add_parser(
        "recover", allow_abbrev=False,
        help="recover instance transforms and material parameters from a target scene or "
             "image by gradient descent")
    rec.add_argument("target", nargs="?",
                     help="target scene (.json/.xml, rendered through every camera) or target "
                          "image (.exr, a one-camera scene)")
    rec.add_argument("--target-images", nargs="+", metavar="EXR",
                     help="target images instead of TARGET, one per camera in camera order")
    rec.add_argument("--init", help="scene with the perturbed transforms to start from (required "
                                    "unless --resume)")
    rec.add_argument("--out", default="recover_out", help="folder for the images, plot and recovered scene")
    rec.add_argument("--iterations", type=_positive_int, default=300)
    rec.add_argument("--spp", type=_positive_int, default=8, help="samples per pixel per iteration")
    rec.add_argument("--sppc", type=_non_negative_int, default=None,
                     help="samples per pixel of the interior derivative, apart from the image's "
                          "(default: half of --spp, at least 1)")
    rec.add_argument("--sppi", type=_non_negative_int, default=None,
                     help="shadow-boundary samples per pixel per iteration (default: --spp; 0: off)")
    rec.add_argument("--reference-spp", type=_positive_int, default=REFERENCE_SPP,
                     help="samples per pixel of the target images rendered from a target scene, "
                          f"and of the PNGs (default {REFERENCE_SPP})")
    rec.add_argument("--lr", type=float, default=LR, help=f"base learning rate (default {LR})")
    rec.add_argument("--blur", type=float, default=0.0,
                     help="coarse to fine: initial blur of the loss in pixels, shrinking to 0 (default 0: off)")
    rec.add_argument("--restarts", type=_non_negative_int, default=0,
                     help="random restarts: this many random starts besides the given one, each "
                          "probed for a fifth of the iterations; the best goes on (default 0)")
    rec.add_argument("--instances", help="comma-separated ids to optimise (default: those that differ)")
    rec.add_argument("--parameters", default="translation,rotation,scale",
                     help="comma-separated subset of translation,rotation,scale")
    rec.add_argument("--materials",
                     help="comma-separated material parameters to optimise, e.g. "
                          "paint.reflectance,gold.alpha (default: those that differ)")
    rec.add_argument("--seed", type=_non_negative_int, default=0)
    rec.add_argument("--checkpoint-every", type=_non_negative_int, default=25, metavar="N",
                     help="save the run's state to OUT/checkpoint.npz every N iterations "
                          "(default 25; 0: never)")
    rec.add_argument("--resume", metavar="OUT",
                     help="continue the interrupted run in the output folder OUT from its last "
                          "checkpoint, with the arguments it was started with (give no others)")
    inter = commands.add_parser(
        "intersect", allow_abbrev=False,
        help="intersect camera and random rays with a scene and report the hits")
    inter.add_argument("scene", help="scene file (.json or Mitsuba .xml)")
    inter.add_argument("--rays", type=_positive_int, default=1 << 20,
                       help="random rays through the scene bounds (default 1048576)")
    inter.add_argument("--accel", choices=["auto", "grid", "bvh", "unrolled", "brute"], default="auto")
    inter.add_argument("--seed", type=_non_negative_int, default=0)
    inter.add_argument("--width", type=_positive_int, default=72, help="preview columns")
    stress = commands.add_parser("stress", allow_abbrev=False,
                                 help="numerical stress suite against float64, beside Mitsuba 3")
    stress.add_argument("--size", choices=["full", "ci"], default="full",
                        help=f"rays per model kind and case: full {STRESS_SIZES['full']}, "
                             f"ci {STRESS_SIZES['ci']} (default full)")
    stress.add_argument("--seed", type=_non_negative_int, default=0)
    return parser


def run_stress(args: argparse.Namespace) -> int:
    """Print the stress table; exit status 1 when a target is missed."""
    with tqdm(desc="stress", unit="case", leave=False) as bar:
        rows = run_suite(args.size, args.seed, progress=lambda name: (bar.set_postfix_str(name), bar.update()))
    print(format_table(rows))
    return 1 if any(r.met is False for r in rows) else 0


def _preview(scene, width: int) -> str:
    """Terminal picture through the scene camera: Lambert shading with a head light."""
    if scene.camera is None:
        return "(no camera in the scene: no preview)"
    camera = scene.camera
    # Terminal cells are about twice as tall as wide.
    height = max(1, round(width * camera.height / camera.width / 2))
    camera = camera.with_size(width, height)
    o, d = camera.pixel_centre_rays()
    hit = scene.intersect(o, d)
    shade = dr.select(hit.valid, 0.15 + 0.85 * dr.abs(dr.dot(hit.n, d)), 0.0)
    levels = np.clip((np.asarray(shade) * (len(_SHADES) - 1)).round().astype(int), 0, len(_SHADES) - 1)
    rows = levels.reshape(height, width)
    return "\n".join("".join(_SHADES[v] for v in row) for row in rows)


#: Bytes per random ray that intersect and crosscheck hold at once (float64 rays, the
#: hit record, float32 copies and NumPy temporaries), checked before allocating.
RAY_BYTES = 256


def run_intersect(args: argparse.Namespace) -> None:
    require_memory(args.rays * RAY_BYTES, f"--rays {args.rays}")
    start = time.perf_counter()
    scene = load_scene(args.scene, accel=args.accel)
    build = time.perf_counter() - start
    rng = np.random.default_rng(args.seed)
    lo, hi = scene.bounds
    o = rng.uniform(lo, hi, (args.rays, 3))
    d = rng.normal(size=(args.rays, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    scene.intersect(o[:1024], d[:1024])  # compile the kernels once
    start = time.perf_counter()
    hits = scene.intersect(o, d)
    elapsed = time.perf_counter() - start
    print(_preview(scene, args.width))
    print(f"scene {args.scene}: {len(scene.instance_ids)} instances, models "
          f"{', '.join(scene.kind_names)}, {scene.accel} built in {build:.2f} s")
    hit = hits.instance >= 0
    print(f"{args.rays} random rays: {hit.mean():.1%} hit, {args.rays / elapsed / 1e6:.2f} Mrays/s "
          f"(full hit record, including NumPy transfer)")
    counts = np.bincount(hits.instance[hit], minlength=len(scene.instance_ids))
    for name, count in sorted(zip(scene.instance_ids, counts), key=lambda x: -x[1])[:10]:
        print(f"  {name:<24} {count:>9} hits")


def _check_writable_folder(output: Path) -> None:
    """Refuse, before rendering, an output whose folder is missing or takes no files."""
    folder = output.parent
    if not folder.is_dir():
        raise ImageFileError(f"output {str(output)!r}: the folder {str(folder)!r} does not exist")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise ImageFileError(f"output {str(output)!r}: cannot write in {str(folder)!r}: "
                             f"{err.strerror or err}") from None


def run_render(args: argparse.Namespace) -> None:
    if args.output and Path(args.output).suffix.lower() not in (".exr", ".png"):
        raise ImageDataError(f"output {args.output!r}: expected a .exr or .png file name")
    if args.output and Path(args.output).suffix.lower() == ".png" and args.integrator == "aov":
        raise ImageDataError(f"output {args.output!r}: a PNG holds colour, not the aov channels; "
                             "write a .exr")
    start = time.perf_counter()
    scene = load_scene(args.scene)
    output = Path(args.output) if args.output else Path(Path(args.scene).stem + ".exr")
    _check_writable_folder(output)
    if args.camera is None:
        views = list(range(len(scene.cameras))) or [0]  # (none: render names the problem)
    else:
        by_id = args.camera in [camera.id for camera in scene.cameras]
        which = int(args.camera) if args.camera.isdigit() and not by_id else args.camera
        views = [scene.camera_index(which)]
    for k in views:
        name = output
        if len(scene.cameras) > 1 and args.camera is None:
            name = output.with_name(f"{output.stem}_{scene.camera_name(k)}{output.suffix}")
        _render_view(args, scene, k, name, start)
        start = time.perf_counter()


def _render_view(args: argparse.Namespace, scene, camera: int, output: Path, start: float) -> None:
    """Render camera ``camera`` of ``scene`` to ``output`` (and its PNG preview), with the
    integrator and spp given, else the scene file's
    (:func:`~instancing.rendering.film.render_settings`)."""
    options = {"max_depth": args.max_depth, "rr_depth": args.rr_depth, "hide_emitters": args.hide_emitters,
               "emitter_samples": args.emitter_samples, "bsdf_samples": args.bsdf_samples}
    integrator, spp, _ = render_settings(scene, args.integrator, args.spp, camera=camera, **options)
    if output.suffix.lower() == ".png" and integrator in ("aov", "moment"):
        raise ImageDataError(f"output {str(output)!r}: the scene's integrator is {integrator!r}, whose "
                             "channels a PNG does not hold; write a .exr (or name another --integrator)")
    with tqdm(total=spp, unit="spp", desc="render", leave=False) as bar:
        image = render(scene, args.integrator, spp=spp, seed=args.seed, camera=camera,
                       width=args.width, height=args.height, **options,
                       progress=lambda done: bar.update(done - bar.n))
        dr.sync_thread()
    elapsed = time.perf_counter() - start
    height, width, _ = image.shape
    written = []
    if output.suffix.lower() == ".exr":
        write_exr(output, image, channel_names(args.integrator, scene=scene, camera=camera))
        written.append(str(output))
    if integrator != "aov":
        # (A moment render's preview: the RGB, and alpha, of the integrator nested first.)
        preview = output.with_suffix(".png")
        alpha = scene.cameras[camera].alpha
        write_png(preview, image[:, :, :4 if alpha else 3], premultiplied=alpha)
        written.append(str(preview))
    samples = width * height * spp
    print(f"rendered {width}x{height} at {spp} spp ({integrator}) in {elapsed:.2f} s, "
          f"{samples / elapsed / 1e6:.2f} Msamples/s -> {', '.join(written)}")


def run_crosscheck(args: argparse.Namespace) -> int:
    require_memory((args.rays + args.reference_rays) * RAY_BYTES,
                   f"--rays {args.rays} and --reference-rays {args.reference_rays}")
    integrators = [i for i in args.integrators.split(",") if i]
    unknown = [i for i in integrators if i not in INTEGRATORS]
    if unknown:
        raise SceneError(f"--integrators: unknown {unknown}; available: {list(INTEGRATORS)}")
    scene = load_scene(args.scene)
    if scene.camera is not None and (args.width or args.height):
        scene.set_camera(scene.camera.with_size(args.width or scene.camera.width,
                                                args.height or scene.camera.height))
    report = crosscheck(scene, random_rays=args.rays, reference_rays=args.reference_rays,
                        integrators=integrators, spp=args.spp, reference_spp=args.reference_spp,
                        out_dir=args.out, seed=args.seed, source=args.scene, repeats=args.repeats)
    print(report.table())
    return 1 if report.failures else 0


def run_recover(args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
    if args.resume is not None:
        return _resume_recover(args, parser)
    if args.init is None:
        raise SceneError("recover: --init is required (or --resume OUT to continue a run)")
    if (args.target is None) == (args.target_images is None):
        raise SceneError("recover: give either TARGET (a scene or an image) or --target-images")
    if not np.isfinite(args.lr) or args.lr <= 0:
        raise SceneError(f"--lr must be a positive number, got {args.lr}")
    if not np.isfinite(args.blur) or args.blur < 0:
        raise SceneError(f"--blur must be a non-negative number of pixels, got {args.blur}")
    instances = [i for i in args.instances.split(",") if i] if args.instances else None
    parameters = tuple(p for p in args.parameters.split(",") if p)
    materials = [m for m in args.materials.split(",") if m] if args.materials is not None else None
    _report(args.out, args.iterations, lambda progress: recover_files(
        args.target_images or args.target, args.init, args.out, iterations=args.iterations,
        spp=args.spp, sppc=args.sppc, sppi=args.sppi, lr=args.lr, blur_start=args.blur, instances=instances,
        parameters=parameters, materials=materials, reference_spp=args.reference_spp,
        seed=args.seed, restarts=args.restarts, progress=progress,
        checkpoint_every=args.checkpoint_every))


def _resume_recover(args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
    """``recover --resume OUT``: the run's own arguments come from OUT/run.json."""
    defaults = vars(parser.parse_args(["recover", "--resume", args.resume]))
    others = sorted(name for name, value in vars(args).items() if value != defaults[name])
    if others:
        raise SceneError(f"recover --resume continues a run with its own arguments; remove "
                         f"{', '.join(('--' + name.replace('_', '-')) if name != 'target' else 'TARGET' for name in others)}")
    _report(args.resume, None, lambda progress: resume_files(args.resume, progress))


def _report(out: str, iterations: int | None, run: Callable) -> None:
    """Run a recovery with a progress bar; print its table and files. Interrupted, say how
    to continue from its checkpoint."""
    try:
        with tqdm(total=iterations, unit="it", desc="recover", leave=False) as bar:
            def progress(iteration: int, loss: float) -> None:
                bar.set_postfix(loss=f"{loss:.3e}")
                bar.n = iteration + 1
                bar.refresh()
            result = run(progress)
    except KeyboardInterrupt:
        if (Path(out) / CHECKPOINT).is_file():
            print(f"instancing: continue with: instancing recover --resume {out}", file=sys.stderr)
        raise
    print(result.table())
    print("wrote " + ", ".join(result.written))


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "intersect":
            run_intersect(args)
        elif args.command == "render":
            run_render(args)
        elif args.command == "crosscheck":
            return run_crosscheck(args)
        elif args.command == "stress":
            return run_stress(args)
        elif args.command == "recover":
            run_recover(args, parser)
    except InstancingError as err:
        print(f"instancing: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # (Outputs are written whole or not at all: io.output_file.)
        print(f"instancing: {args.command} interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
