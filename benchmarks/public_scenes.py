"""Mitsuba's public example scenes, loaded unmodified by both renderers.

Mitsuba's data and tutorial repositories carry no licence that lets this project copy their
scenes (the tutorials' LEGO scene is CC-BY-NC), so they are not bundled; this script runs
on a local checkout of them instead. For every Mitsuba XML file found under the given
folders it reports whether ``instancing.load_scene`` reads it (or the first problem of the
error, which names what is refused; "both refuse" where Mitsuba refuses the file too, as it
does files whose meshes lie in folders Mitsuba's documentation build adds), and for those that load, the 8x8-block error of our
render against a high-spp Mitsuba reference of the file beside Mitsuba's own at the same
spp (``instancing.validation.measures.block_error``, root mean square over ``--repeats``
renders of each, so that one firefly does not decide), the verdict being "match" when ours
is within 1.5x of Mitsuba's (the acceptance of the real-scenes issue). Each such line also
gives the median wall time of one render at ``--spp`` by each renderer, the two rendering in
turns after a warm-up render each (at the reduced film size, so fixed costs per render weigh
more than in full-size frames), each renderer's noise (:func:`pixel_noise`: the variance of a
pixel's value, from one more render of each with every sample's luminance and its square,
Mitsuba's ``moment``) and from the ratios our time at equal error (:func:`equal_error_time`).
The noise, not the block error, scales the time: a few pixels (a light's edge, a highlight)
make most of a small image's error, and over a few renders the block errors of two renderers
with the same noise differ by up to 1.8x (Mitsuba's `integrator_depth_1.xml` at 256 spp, three sets of
four renders: 1.80x, 1.10x and 1.04x), where each pixel's spp samples estimate its variance.
A file whose sampler stratifies a pixel's samples (each renderer draws them as its sampler
type says) has its noise measured across the ``--repeats`` renders instead
(:func:`render_noise`): its samples' spread overstates the variance of their mean.

``--integrator file`` (the default) renders each file as a user would without naming an
integrator: ours takes the file's integrator with its ``max_depth`` and Russian roulette
(:func:`instancing.rendering.film.render_settings`; files naming none: ``direct``), Mitsuba
the integrator object it built from the same file (files naming none: ``direct`` as well,
where Mitsuba's own default would be ``path``); a file whose integrator ours do not render
as asked is reported as refused, naming it. ``direct``, ``path`` or ``volpath`` renders
every file with that integrator instead.

Both renderers read the file itself; only the film is made small: Mitsuba renders through
the sensor that ``to_mitsuba`` writes for our camera at the reduced size (the same sensor:
``tests/test_camera.py``), on the scene Mitsuba loaded from the file. Files that are
fragments (no sensor, or included by another file) are reported as such. Every file is
loaded with the parameter ``spp`` set (``--param``), as Mitsuba's documentation builds them:
some of its scenes take their sample count as an undeclared ``$spp``.

``--json PATH`` also writes every file's verdict and figures, with the run's settings, as
JSON: ``docs/performance.md`` summarises them (``python -m benchmarks.performance_page``).

Usage: python -m benchmarks.public_scenes FOLDER [FOLDER ...] [--size 64 48] [--spp 256]
           [--reference-spp 4096] [--integrator file] [--repeats 4] [--param name=value ...]
           [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

import instancing
from benchmarks.machine import describe
from instancing.core.backend import MITSUBA_VARIANT, mitsuba_module
# (The film's own entry points for one integrator with moments and for a file's composite one.)
from instancing.materials.texture import LUMINANCE
from instancing.rendering.film import _file_composite, _render, render_settings
from instancing.scene.description import DirectionalLight, PointLight
from instancing.validation.measures import block_error, root_mean_square

#: Ours may be this multiple of Mitsuba's own block error (the real-scenes acceptance).
MATCH_RATIO = 1.5


def compare(path: Path, size: tuple[int, int], spp: int, reference_spp: int,
            integrator: str, parameters: dict[str, str], repeats: int = 4
            ) -> tuple[str, str, dict | None]:
    """(verdict, detail, figures) for one scene file, loaded with ``parameters`` ($name
    values). The figures, for a file both renderers rendered (None otherwise): the block
    errors ``ours_error`` and ``mitsuba_error`` (root mean squares over ``repeats`` renders
    of each renderer), the median seconds per render ``ours_s`` and ``mitsuba_s``, and
    ``equal_error``, our time at equal error over Mitsuba's (None unless the file matches)."""
    mi = mitsuba_module()
    mi.set_variant(MITSUBA_VARIANT)
    theirs_scene, their_refusal = _mitsuba_scene(mi, path, parameters)
    try:
        scene = _our_scene(path, parameters)
    except instancing.InstancingError as err:
        # The first problem, not only the count of them, with the file named by its name
        # alone (its path, twice in the message, would fill the reason's length).
        ours = str(err).replace(str(path), path.name).splitlines()
        reason = " ".join(line.strip() for line in ours[:2])[:300]
        if their_refusal is not None:
            return "both refuse", f"ours: {reason}; Mitsuba: {their_refusal}", None
        return "refused", reason, None
    if scene.camera is None:
        return "no sensor", "loads (a fragment or a scene without a camera)", None
    if their_refusal is not None:
        return "mitsuba refuses", their_refusal, None
    ours_integrator = None if integrator == "file" else integrator
    if integrator == "file":
        try:
            named = render_settings(scene, spp=spp)[0]
        except instancing.InstancingError as err:
            return "refused", f"its integrator: {err}", None
        mintegrator = (theirs_scene.integrator() if scene.description.integrator is not None
                       else mi.load_dict({"type": named}))
    else:
        mintegrator = mi.load_dict({"type": integrator})
    small = scene.camera.with_size(*size)
    scene.set_camera(small)
    sensor = mi.load_dict(instancing.to_mitsuba(scene, spp=spp)["sensor"])
    # The first three channels: the RGB (of an aov integrator, its first nested integrator's).
    reference = np.asarray(mi.render(theirs_scene, sensor=sensor, integrator=mintegrator,
                                     spp=reference_spp, seed=11))[..., :3]
    renderers = (lambda seed: np.asarray(instancing.render(scene, ours_integrator, spp=spp,
                                                           seed=seed))[..., :3],
                 lambda seed: np.asarray(mi.render(theirs_scene, sensor=sensor, integrator=mintegrator,
                                                   spp=spp, seed=seed))[..., :3])
    (ours, ours_s), (theirs, theirs_s) = _renders(renderers, repeats)
    if not reference.any():
        # No light reaches the film (a fragment without emitters): there is no error to scale.
        dark = not any(image.any() for image in ours)
        return (("dark" if dark else "MISS"),
                "Mitsuba's reference is black" + ("; so are ours" if dark else
                                                  f"; ours is not (mean {np.mean(ours):.4g})"), None)
    ours_error, theirs_error = (root_mean_square([block_error(image, reference) for image in images])
                                for images in (ours, theirs))
    if scene.camera.stratified:
        # A pixel's stratified samples spread more than their mean varies: the variance
        # across the renders is the measure.
        ours_noise, theirs_noise = (render_noise(images) for images in (ours, theirs))
    else:
        ours_noise, theirs_noise = _noises(mi, scene, theirs_scene, sensor, mintegrator, ours_integrator, spp)
    verdict = "match" if ours_error <= MATCH_RATIO * theirs_error else "MISS"
    detail = (f"block error ours {ours_error:.4f}, Mitsuba's {theirs_error:.4f} "
              f"({ours_error / theirs_error:.2f}x); means {np.mean(ours):.4f} / {reference.mean():.4f}; "
              f"render ours {ours_s:.3f} s, Mitsuba's {theirs_s:.3f} s ({ours_s / theirs_s:.2f}x)")
    detail += (f"; noise ours {ours_noise:.4g}, Mitsuba's {theirs_noise:.4g} "
               f"({ours_noise / theirs_noise:.2f}x)" if ours_noise is not None
               else "; no noise measure (the file's aov integrator)")
    # Our time at equal error, where the images agree (a biased reference makes it meaningless).
    equal_error = (equal_error_time(ours_s / theirs_s, ours_noise / theirs_noise)
                   if verdict == "match" and ours_noise is not None else None)
    if equal_error is not None:
        detail += f"; at equal error about {equal_error:.2f}x"
    if verdict == "MISS" and _blends_a_delta_lobe(scene):
        detail += ("; Mitsuba 3.9.1's blendbsdf with a delta part is biased, and so is this "
                   "reference (tests/test_materials.py::"
                   "test_a_blend_with_a_delta_part_reflects_the_mixture_of_its_parts)")
    if verdict == "MISS" and _counts_delta_lights_per_sample(scene, mintegrator):
        detail += ("; Mitsuba 3.9.1's direct counts each point, spot or directional light once "
                   "per emitter sample, so its images with several are that many times too "
                   "bright, and so is this reference (tests/test_mitsuba_render.py::"
                   "test_delta_lights_count_once_whatever_the_emitter_samples)")
    figures = {"ours_error": float(ours_error), "mitsuba_error": float(theirs_error), "ours_s": ours_s,
               "mitsuba_s": theirs_s, "ours_noise": ours_noise, "mitsuba_noise": theirs_noise,
               "equal_error": equal_error}
    return verdict, detail, figures


def equal_error_time(time_ratio: float, noise_ratio: float) -> float:
    """Our time over Mitsuba's at equal error, from the ratios at equal spp of the time and
    of the noise (:func:`pixel_noise`, a variance): an unbiased renderer's variance falls as
    1 / spp, so ours reaches Mitsuba's at noise_ratio times the spp."""
    return time_ratio * noise_ratio


def pixel_noise(image: np.ndarray, nested: int, spp: int) -> float:
    """The mean over pixels of the variance of a pixel's luminance (Y) at ``spp`` samples,
    from a render with Mitsuba's ``moment`` channels (R, G, B, then each of the ``nested``
    integrators' X, Y, Z, then their squares: the first one's Y and Y^2 are read): each
    pixel's spread of its samples, E[Y^2] - E[Y]^2, over spp - 1 (the unbiased estimate of
    the variance of their mean, for spp >= 2)."""
    if spp < 2:
        raise ValueError(f"pixel_noise: one sample per pixel has no spread to read, spp = {spp}")
    mean, square = image[..., 4].astype(np.float64), image[..., 4 + 3 * nested].astype(np.float64)
    return float(np.mean(np.maximum(square - mean ** 2, 0.0)) / (spp - 1))


def render_noise(images: list[np.ndarray]) -> float | None:
    """The mean over pixels of the variance of a pixel's luminance (Y of linear sRGB) across
    ``images``, renders of one setting with different seeds (None for fewer than two): the
    noise of renders whose samples are stratified, for which :func:`pixel_noise` (each
    pixel's samples' spread over spp - 1) overstates it."""
    if len(images) < 2:
        return None
    luminance = np.stack([np.asarray(image, np.float64)[..., :3] @ np.asarray(LUMINANCE) for image in images])
    return float(np.var(luminance, axis=0, ddof=1).mean())


def _noises(mi, scene, theirs_scene, sensor, mintegrator, ours_integrator: str | None,
            spp: int) -> tuple[float | None, float | None]:
    """(ours, Mitsuba's) :func:`pixel_noise` of the rendered integrator, each from one render
    with moments (seed 1, apart from the timed ones); (None, None) for a file's ``aov``
    integrator, whose channels are not one estimate."""
    composite = _file_composite(scene) if ours_integrator is None else None
    if composite is not None and composite.name != "moment":
        return None, None
    if composite is not None:
        # The file's own moment integrator, in both renderers.
        nested = len(composite.nested)
        ours = instancing.render(scene, None, spp=spp, seed=1)
        theirs_integrator = mintegrator
    else:
        nested = 1
        ours = _render(scene, ours_integrator, spp, 1, moments=True)
        theirs_integrator = mi.load_dict({"type": "moment", "nested": mintegrator})
    theirs = mi.render(theirs_scene, sensor=sensor, integrator=theirs_integrator, spp=spp, seed=1)
    return pixel_noise(np.asarray(ours), nested, spp), pixel_noise(np.asarray(theirs), nested, spp)


def _renders(renderers: tuple, repeats: int) -> list[tuple[list, float]]:
    """Per renderer (a function of the seed), its ``repeats`` images (seeds 3, 4, ...) and
    the median wall time of one: the renderers take turns, after a warm-up render each
    (tracing and compilation), so that load from other jobs hits them alike."""
    for render in renderers:
        render(2)
    images, seconds = [[] for _ in renderers], [[] for _ in renderers]
    for k in range(repeats):
        for render, done, spent in zip(renderers, images, seconds):
            start = time.perf_counter()
            done.append(render(3 + k))
            spent.append(time.perf_counter() - start)
    return [(done, float(np.median(spent))) for done, spent in zip(images, seconds)]


def _mitsuba_scene(mi, path: Path, parameters: dict[str, str]) -> tuple:
    """(Mitsuba's scene of the file, None) or (None, its refusal in its words). A file that
    takes none of ``parameters`` is loaded without them (Mitsuba refuses unused ones)."""
    for given in (parameters, {}):
        try:
            return mi.load_file(str(path), **given), None
        except Exception as err:  # Mitsuba raises RuntimeError naming the problem
            refusal = str(err)
            if "unused parameters" not in refusal:
                break
    return None, refusal.splitlines()[-1][:150]


def _our_scene(path: Path, parameters: dict[str, str]):
    """Our scene of the file, loaded as :func:`_mitsuba_scene` loads Mitsuba's (without the
    parameters where the file takes some of them not)."""
    try:
        return instancing.load_scene(path, **parameters)
    except instancing.SceneError as err:
        if "not used by the file" not in str(err):
            raise
        return instancing.load_scene(path)


def _blends_a_delta_lobe(scene) -> bool:
    """Whether some material of the scene is a blendbsdf with a part that has a delta lobe."""
    return any(material.type == "blendbsdf" and any(
        getattr(part.lobe, "delta_only", False) or getattr(part.lobe, "samples_delta", False)
        for part in material.parts) for material in scene.materials.values())


def _counts_delta_lights_per_sample(scene, mintegrator) -> bool:
    """Whether Mitsuba's integrator is its ``direct`` with more than one emitter sample and
    the scene has a delta light (point, spot, projector or directional)."""
    return (_direct_emitter_samples(mintegrator) > 1
            and any(isinstance(light, (PointLight, DirectionalLight)) for light in scene.lights))


def _direct_emitter_samples(mintegrator) -> int:
    """The emitter samples of Mitsuba's ``direct`` integrator object (0 for other types),
    from its description (Mitsuba keeps the count out of its parameters)."""
    text = str(mintegrator)
    if not text.startswith("DirectIntegrator"):
        return 0
    match = re.search(r"emitter_samples\s*=\s*(\d+)", text)
    return int(match.group(1)) if match else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--size", type=int, nargs=2, default=(64, 48))
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--integrator", choices=("file", "direct", "path", "volpath"), default="file",
                        help="'file': each file's own (see the module docstring)")
    parser.add_argument("--repeats", type=int, default=4,
                        help="renders per renderer at --spp (block errors: their RMS)")
    parser.add_argument("--param", action="append", default=["spp=16"],
                        help="a $name value for every file, name=value (default spp=16)")
    parser.add_argument("--json", type=Path, help="also write the verdicts and figures to this file")
    args = parser.parse_args(argv)
    if any(n <= 0 or n % 8 for n in args.size):
        parser.error(f"--size takes a width and height that are positive multiples of 8 (the block "
                     f"error's blocks), got {args.size}")
    if not all("=" in p for p in args.param):
        parser.error(f"--param takes name=value, got {args.param}")
    parameters = dict(p.split("=", 1) for p in args.param)
    files = sorted(f for folder in args.folders for f in folder.rglob("*.xml"))
    if not files:
        parser.error(f"no .xml files under {[str(f) for f in args.folders]}")
    counts: dict[str, int] = {}
    records = []
    for path in files:
        start = time.perf_counter()
        verdict, detail, figures = compare(path, tuple(args.size), args.spp, args.reference_spp,
                                           args.integrator, parameters, args.repeats)
        counts[verdict] = counts.get(verdict, 0) + 1
        records.append({"file": path.as_posix(), "verdict": verdict, "detail": detail, **(figures or {})})
        print(f"{verdict:<16} {path}  {detail}  [{time.perf_counter() - start:.1f} s]", flush=True)
    print("summary: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) + f" of {len(files)}")
    equal_error_times = [r["equal_error"] for r in records if r.get("equal_error") is not None]
    if equal_error_times:
        ratios = np.array(equal_error_times)
        print(f"our time at equal error over Mitsuba's, {len(ratios)} matches: geometric mean "
              f"{np.exp(np.log(ratios).mean()):.2f}x, range {ratios.min():.2f} - {ratios.max():.2f}x; "
              f"ours faster on {(ratios < 1).sum()}")
    if args.json is not None:
        settings = {"size": list(args.size), "spp": args.spp, "reference_spp": args.reference_spp,
                    "integrator": args.integrator, "repeats": args.repeats, "parameters": parameters,
                    "folders": [f.as_posix() for f in args.folders]}
        args.json.write_text(json.dumps({"settings": settings, "machine": describe(), "files": records},
                                        indent=1) + "\n")
        print(f"results written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
