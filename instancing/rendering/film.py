"""``instancing.render``: camera samples -> integrator -> film -> (H, W, C) image.

Pixel sampling: each pixel gets ``spp`` camera rays through film positions uniform in the
pixel (:mod:`instancing.rendering.pixel_filter`). With a box every sample has weight 1 and
the pixel value is the sample mean; with a wide filter they are splatted as Mitsuba's film
does (:func:`_splat`): each pixel is the filter-weighted sum of the samples it reaches over
the weights' sum. Random numbers come from one PCG32 stream per sample, or, where the
camera's sampler stratifies, from a :class:`~instancing.core.rng.PixelSampler` per sample,
stratified over the pixel's samples (:mod:`instancing.core.rng`); both are keyed by the
sample's pixel and index and by ``seed``: the same scene, spp and seed give a
bit-identical image, however the samples are split into passes.
"""

from __future__ import annotations

import warnings
from typing import Callable, NamedTuple

from ..core.arguments import integer
from ..core.backend import Array3f, Float, Int32, TensorXf, UInt32, dr
from ..core.errors import SceneError
from ..core.memory import require_entries, require_memory
from ..core.rng import pixel_samplers, sample_streams
from ..materials.texture import SRGB_TO_XYZ
from ..scene.camera import Camera, CameraBatch
from ..scene.description import IntegratorChoice
from ..scene.scene import Scene, require_scene
from .boundary_term import (BoundarySampler, boundary_sampler, boundary_term, contact_samplers,
                            mirror_sampler, shadow_lights, shadow_samplers, terminator_sampler)
from .integrators.aov import (AOV_CHANNELS, DEFAULT_AOVS, MITSUBA_AOVS, aov_channel_names, integrate_aov,
                              mitsuba_aov_channel_names)
from .integrators.direct import integrate_direct, past_emitters, strategy_samples
from .integrators.path import RR_DEPTH, integrate_path
from .integrators.volpath import camera_medium, check_volpath, integrate_volpath
from .pixel_filter import PixelFilter
from .recording import replay
from .secondary_boundary import occluder_set, secondary_boundary, secondary_term_needed

INTEGRATORS = ("aov", "direct", "path", "volpath")
#: The integrators that follow paths of several bounces (and take a max_depth).
PATH_INTEGRATORS = ("path", "volpath")
#: Rays traced at once at most (bounds memory; larger renders run in passes).
MAX_LANES = 1 << 22
#: Bytes that a splat's per-pixel sums may take for all of the filter's row offsets at once
#: even where that is more than the pass's samples take (:func:`splat_rows`).
SPLAT_SUMS_BYTES = 1 << 28
#: Samples per view and term at most (pixels times spp): a sample's random stream is
#: chosen by a 32-bit index, pixel * spp + sample (:func:`~instancing.core.rng.sample_streams`).
MAX_SAMPLES = 1 << 32
#: Seed offset of the camera samples that estimate the secondary boundary term.
SECONDARY_STREAM_SEED = 0x5BD1E995
#: Seed offset per view between the camera batches of one optimisation step (an odd
#: constant far from the small offsets of the render's own streams and of consecutive
#: steps).
VIEW_SEED_STRIDE = 0x9E3779B1


#: Longest path a 'path' render takes as a bound (its depth counter is a 32-bit integer).
MAX_DEPTH = (1 << 32) - 1
#: The integrator and samples per pixel of a render that names neither, where the scene's
#: file does not either.
DEFAULT_INTEGRATOR = "direct"
DEFAULT_SPP = 64


class RenderSettings(NamedTuple):
    """What a render traces, checked (see :func:`render`): also the key of its recordings."""

    integrator: str
    aovs: tuple | None
    max_depth: int
    rr_depth: int
    hide_emitters: bool
    spp: int
    sppc: int
    sppp: int
    sppi: int
    #: The direct integrator's (emitter samples, BSDF samples) per camera hit.
    strategies: tuple[int, int] = (1, 1)
    #: Whether each sample also gives its XYZ and their squares (Mitsuba's ``moment``).
    moments: bool = False


def render_settings(scene: Scene, integrator: str | None = None, spp: int | None = None,
                    max_depth: int | None = None, camera: int | str = 0,
                    rr_depth: int | None = None, hide_emitters: bool | None = None,
                    emitter_samples: int | None = None, bsdf_samples: int | None = None
                    ) -> tuple[str, int, dict]:
    """(integrator, spp, its options) of a render: those given; else the scene file's (its
    integrator, with that integrator's ``max_depth``, ``rr_depth``, ``hide_emitters``,
    ``emitter_samples`` and ``bsdf_samples``, and the camera's sample count, as Mitsuba
    renders a file); else :data:`DEFAULT_INTEGRATOR` and :data:`DEFAULT_SPP`. The options are
    :func:`render`'s keyword arguments of those names (None: the default).

    Raises:
        SceneError: no integrator is given, and the file names one that none of ours
            renders as it asks (:func:`instancing.io.scene_file.parse_integrator`).
    """
    options = {"max_depth": max_depth, "rr_depth": rr_depth, "hide_emitters": hide_emitters,
               "emitter_samples": emitter_samples, "bsdf_samples": bsdf_samples}
    choice = scene.description.integrator
    if integrator is None and choice is not None:
        if choice.name is None:
            raise SceneError(f"the scene's integrator {choice.refusal}; name the render's "
                             f"integrator, one of {list(INTEGRATORS)}")
        integrator = choice.name
        options = {name: getattr(choice, name) if value is None else value
                   for name, value in options.items()}
    if spp is None:
        own = scene.cameras[scene.camera_index(camera)].spp if scene.camera is not None else None
        spp = DEFAULT_SPP if own is None else own
    return DEFAULT_INTEGRATOR if integrator is None else integrator, spp, options


def channel_names(integrator: str | None, aovs: list[str] | None = None,
                  scene: Scene | None = None, camera: int | str = 0) -> list[str]:
    """Names of the channels that :func:`render` returns for these settings (integrator
    None: the one ``scene``'s file names, as :func:`render` renders it) through ``scene``'s
    camera ``camera`` (whose film may add alpha, ``A``, after RGB)."""
    alpha = False
    if scene is not None:
        require_scene(scene, "channel_names")
        alpha = scene.camera is not None and scene.cameras[scene.camera_index(camera)].alpha
    if integrator is None and scene is not None:
        composite = _file_composite(scene)
        if composite is not None:
            labels = [label for label, _ in composite.nested]
            if composite.name == "moment":
                return moment_channel_names(labels, alpha)
            return mitsuba_aov_channel_names(composite.aovs, labels, alpha)
        integrator = render_settings(scene)[0]
    _check_integrator(integrator, aovs)
    if integrator == "aov":
        return aov_channel_names(_check_aovs(aovs))
    return ["R", "G", "B", "A"] if alpha else ["R", "G", "B"]


def moment_channel_names(labels: list[str], alpha: bool = False) -> list[str]:
    """Channel names of Mitsuba's ``moment`` integrator around integrators labelled
    ``labels``, as Mitsuba's ``mi.render`` gives them: the first one's RGB (and alpha, with
    ``alpha``), each one's XYZ (``label.X``), then their second moments (``m2_label.X``)."""
    first = [f"{label}.{c}" for label in labels for c in "XYZ"]
    return ["R", "G", "B"] + (["A"] if alpha else []) + first + [f"m2_{name}" for name in first]


def _file_composite(scene: Scene) -> IntegratorChoice | None:
    """The scene file's integrator where it is Mitsuba's ``aov`` or ``moment`` (integrators
    nested in another), else None."""
    choice = scene.description.integrator
    return choice if choice is not None and choice.name in ("aov", "moment") else None


def _render_file_composite(scene: Scene, choice: IntegratorChoice, spp: int | None, seed: int,
                           given: dict, common: dict) -> TensorXf:
    """Mitsuba's ``aov`` or ``moment`` of a scene file, as channels of one image (as
    Mitsuba's ``mi.render``): for ``aov`` each nested integrator's RGB with its own settings,
    then the AOVs; for ``moment`` the first nested integrator's RGB, then each one's XYZ, then
    their second moments (:func:`moment_channel_names`)."""
    if given:
        raise SceneError(f"{sorted(given)} set with the scene file's {choice.name!r} integrator, which "
                         "renders the integrators nested in it with their own settings; name the "
                         "render's integrator to set them")
    moments = choice.name == "moment"
    if moments and scene.differentiable:
        raise SceneError("the scene file's 'moment' integrator renders no derivatives; name the "
                         "render's integrator to differentiate it")
    parts = [_render(scene, c.name, spp, seed, max_depth=c.max_depth, rr_depth=c.rr_depth,
                     hide_emitters=c.hide_emitters, emitter_samples=c.emitter_samples,
                     bsdf_samples=c.bsdf_samples, moments=moments, **common) for _, c in choice.nested]
    if moments:
        # Each part: R, G, B, (A,) X, Y, Z, X^2, Y^2, Z^2.
        k = 4 if scene.view(common["camera"]).alpha else 3
        parts = ([parts[0][:, :, :k]] + [p[:, :, k:k + 3] for p in parts] + [p[:, :, k + 3:] for p in parts])
    elif choice.aovs:
        aovs = [MITSUBA_AOVS[kind][0] for _, kind in choice.aovs]
        parts.append(render(scene, "aov", spp, seed, aovs=aovs, **common))
    return parts[0] if len(parts) == 1 else dr.concat(parts, axis=2)


def _check_integrator(integrator: str, aovs: list[str] | None = None,
                      max_depth: int | None = None, rr_depth: int | None = None,
                      hide_emitters: bool | None = None, emitter_samples: int | None = None,
                      bsdf_samples: int | None = None) -> None:
    """Refuse an unknown integrator, and settings that only another integrator reads (they
    would be ignored)."""
    if integrator not in INTEGRATORS:
        raise SceneError(f"unknown integrator {integrator!r}; available: {list(INTEGRATORS)}")
    if aovs is not None and integrator != "aov":
        raise SceneError(f"aovs are the 'aov' integrator's channels; {integrator!r} renders RGB")
    for name, value in (("max_depth", max_depth), ("rr_depth", rr_depth)):
        if value is not None and integrator not in PATH_INTEGRATORS:
            raise SceneError(f"{name} is the 'path' and 'volpath' integrators'; {integrator!r} has none")
    for name, value in (("emitter_samples", emitter_samples), ("bsdf_samples", bsdf_samples)):
        if value is not None and integrator != "direct":
            raise SceneError(f"{name} is the 'direct' integrator's; {integrator!r} samples the light "
                             "once per vertex")
    if hide_emitters is not None and not isinstance(hide_emitters, bool):
        raise SceneError(f"hide_emitters must be True or False, got {hide_emitters!r}")
    if hide_emitters and integrator == "aov":
        raise SceneError("hide_emitters is the shading integrators'; 'aov' shows no emitters")


def _check_aovs(aovs: list[str] | None) -> list[str]:
    if isinstance(aovs, str) or not (aovs is None or isinstance(aovs, (list, tuple))):
        raise SceneError(f"aovs must be a list of AOV names (available: {list(AOV_CHANNELS)}), "
                         f"got {aovs!r}")
    aovs = DEFAULT_AOVS if aovs is None else list(aovs)
    unknown = [a for a in aovs if not isinstance(a, str) or a not in AOV_CHANNELS]
    if unknown or not aovs:
        raise SceneError(f"unknown AOVs {unknown}; available: {list(AOV_CHANNELS)}")
    if len(set(aovs)) != len(aovs):
        raise SceneError(f"aovs names an AOV twice: {aovs}")
    return aovs


def seed_value(seed: int) -> UInt32:
    """The render seed as an opaque 32-bit value (other seeds replay the same kernels).

    Raises:
        SceneError: ``seed`` is not an integer.
    """
    return dr.opaque(UInt32, integer("seed", seed) & 0xFFFFFFFF)


def render(scene: Scene, integrator: str | None = None, spp: int | None = None, seed: int = 0, *,
           aovs: list[str] | None = None, max_depth: int | None = None,
           rr_depth: int | None = None, hide_emitters: bool | None = None,
           emitter_samples: int | None = None, bsdf_samples: int | None = None,
           width: int | None = None, height: int | None = None,
           sppc: int | None = None, sppp: int | None = None, sppi: int | None = None,
           progress: Callable[[int], None] | None = None, frozen: bool = True,
           camera: int | str = 0) -> TensorXf:
    """Render the scene through one of its cameras.

    Args:
        scene: a loaded scene with a ``"camera"`` (or ``"cameras"``).
        integrator: 'aov', 'direct', 'path' or 'volpath' (participating media; no
            derivatives); default: the scene file's integrator, with its ``max_depth``
            (Mitsuba's ``<integrator>``: :func:`render_settings`; Mitsuba's ``aov``: the RGB
            of each integrator nested in it, then its AOVs, named by :func:`channel_names`
            with the scene), else 'direct'.
        spp: samples per pixel (>= 1); default: the camera's sample count (Mitsuba's
            sensor's sampler), else 64. They draw their random numbers as the camera's
            ``sampler`` says: independent, or stratified over the pixel's samples.
        seed: random seed in [0, 2^32); equal inputs give bit-identical images.
        aovs: for 'aov' (only): any of depth, position, normal, shading_normal, instance, albedo
            (the default), uv, roughness.
        max_depth: longest path for 'path' and 'volpath' (only), as Mitsuba (1: emitters seen directly,
            2: direct light, -1: unbounded; default -1).
        rr_depth: for 'path' and 'volpath' (only), the depth from which Russian roulette
            may stop a path, as Mitsuba's (>= 1; default: the scene file's, else 5). A
            depth past the longest paths turns roulette off: no path is cut short, less
            noise per sample at a higher cost per sample (e.g. in dense glass).
        hide_emitters: as Mitsuba's: the emitters that camera rays see directly (the
            environment behind everything, area emitters, which they pass through) give
            no light (default: the scene file's, else False); light they cast stays.
        emitter_samples, bsdf_samples: for 'direct' (only), as Mitsuba's: the samples of
            the lights and of the BSDF at each camera hit, weighted against each other by
            the power heuristic (0 to 64 each, not both 0; 0 emitter samples: no light
            sampled at all, point lights included; default: the scene file's, else 1 and 1).
        width, height: override the camera's film size.
        sppc: samples per pixel of the interior derivative term (AD through the
            re-attached intersection and shading); default ``spp`` (the same
            samples as the image), 0 switches the term off. Any other count draws samples
            of its own: a loss that multiplies the image by its derivative (a squared
            error) then has an unbiased gradient (:func:`instancing.ad.recovery.recover`).
        sppp: samples per pixel of the boundary derivative term (edge sampling of
            moving instances' silhouettes seen by the camera,
            :mod:`instancing.rendering.boundary_term`); default ``spp``, 0 switches it off.
        sppi: samples per pixel of the secondary boundary terms: the shadow boundaries
            that moving instances cast from point and directional lights onto the
            surfaces the camera sees (:func:`~instancing.rendering.boundary_term.shadow_samplers`),
            and the visibility changes seen from those surfaces: area lights' and the
            environment's penumbrae and, in ``path``, indirect light, at every bounce
            (:mod:`instancing.rendering.secondary_boundary`); default ``spp``, 0 switches
            them off. ``sppc``, ``sppp`` and ``sppi`` set on a render without derivatives
            (no grad-enabled scene parameter) are warned about: they sample nothing there.
        progress: called with the number of samples per pixel finished after each pass.
        camera: which of the scene's cameras: an index into ``scene.cameras`` or a
            camera's ``id`` (default: the first).
        frozen: record the first call per setting with ``dr.freeze`` and replay the
            recording for later calls with the same settings (any seed) instead of
            tracing the integrator again (:mod:`instancing.rendering.recording`): saves the 5 - 50 ms
            of tracing per render (measured on the bundled scenes at 128x96: 1-spp frames
            1.4 - 7x faster, the kernels as fast). Recording costs 1 - 4 ms more than
            tracing, once per setting and scene revision (``set_transforms`` starts a new
            one). ``False`` traces every call. Renders with derivatives or a
            ``progress`` callback are traced every call; whole optimisation steps
            are recorded by :class:`instancing.OptimisationStep`.

    Returns:
        TensorXf of shape (H, W, C); :func:`channel_names` gives the channel names (RGB,
        then alpha where the camera's ``pixel_format`` is ``rgba``: docs/rendering.md#alpha).
        When scene parameters are grad-enabled (:func:`instancing.traverse`), the
        image carries their derivatives: ``dr.forward`` gives gradient images,
        ``dr.backward`` on a loss gives parameter gradients. The derivative terms
        add 0 to the image's value.

    Raises:
        TypeError: ``scene`` is not a loaded :class:`~instancing.Scene`.
        SceneError: a bad argument (named), or more than MAX_SAMPLES (2^32) pixels times
            ``spp`` (``sppc``, ``sppp``, ``sppi``).

    Limitations: samples are traced in passes of at most MAX_LANES rays; every pass
    reuses the same compiled kernels (per-pass values are opaque). Visibility changes
    are differentiated as seen from the camera (``sppp``) and from the path's vertices
    (``sppi``); what is left is listed in docs/differentiable-rendering.md.
    """
    require_scene(scene, "render")
    composite = _file_composite(scene) if integrator is None else None
    common = dict(width=width, height=height, sppc=sppc, sppp=sppp, sppi=sppi, progress=progress,
                  frozen=frozen, camera=camera)
    if composite is not None:
        given = {name: value for name, value in (
            ("aovs", aovs), ("max_depth", max_depth), ("rr_depth", rr_depth), ("hide_emitters", hide_emitters),
            ("emitter_samples", emitter_samples), ("bsdf_samples", bsdf_samples)) if value is not None}
        return _render_file_composite(scene, composite, spp, seed, given, common)
    return _render(scene, integrator, spp, seed, aovs=aovs, max_depth=max_depth, rr_depth=rr_depth,
                   hide_emitters=hide_emitters, emitter_samples=emitter_samples, bsdf_samples=bsdf_samples,
                   **common)


def _render(scene: Scene, integrator: str | None, spp: int | None, seed: int, *,
            aovs: list[str] | None = None, max_depth: int | None = None, rr_depth: int | None = None,
            hide_emitters: bool | None = None, emitter_samples: int | None = None,
            bsdf_samples: int | None = None, width: int | None = None, height: int | None = None,
            sppc: int | None = None, sppp: int | None = None, sppi: int | None = None,
            progress: Callable[[int], None] | None = None, frozen: bool = True,
            camera: int | str = 0, moments: bool = False) -> TensorXf:
    """:func:`render` of one integrator (``moments``: with each sample's XYZ and their
    squares after its RGB, for Mitsuba's ``moment``)."""
    integrator, spp, options = render_settings(scene, integrator, spp, max_depth, camera, rr_depth,
                                               hide_emitters, emitter_samples, bsdf_samples)
    _check_integrator(integrator, aovs, **options)
    max_depth, rr_depth, hide_emitters = options["max_depth"], options["rr_depth"], options["hide_emitters"]
    strategies = strategy_samples(*(1 if options[name] is None else options[name]
                                    for name in ("emitter_samples", "bsdf_samples")))
    if integrator == "volpath":
        check_volpath(scene)
    elif scene.media is not None and integrator != "aov":
        warnings.warn(f"the scene's participating media are left out by {integrator!r} (as by "
                      "Mitsuba's); render with 'volpath' to include them", UserWarning, stacklevel=2)
    if not isinstance(frozen, bool):
        raise SceneError(f"frozen must be True or False, got {frozen!r}")
    if progress is not None and not callable(progress):
        raise SceneError(f"progress must be a function of the samples per pixel done, got {progress!r}")
    spp = integer("spp", spp, 1)
    # (A 32-bit seed, as Mitsuba's: a larger one would silently repeat a smaller one's image.)
    seed = seed_value(integer("seed", seed, 0, 2 ** 32 - 1))
    max_depth = integer("max_depth", -1 if max_depth is None else max_depth, -1, MAX_DEPTH)
    rr_depth = integer("rr_depth", RR_DEPTH if rr_depth is None else rr_depth, 1, MAX_DEPTH)
    if scene.camera is None:
        raise SceneError("the scene has no 'camera'; add one to render it")
    view = scene.view(camera)
    given = [name for name, value in (("sppc", sppc), ("sppp", sppp), ("sppi", sppi)) if value is not None]
    if given and not scene.differentiable:
        warnings.warn(f"{', '.join(given)} set on a render without derivatives (no scene parameter is "
                      "grad-enabled): the derivative terms they sample are not computed",
                      UserWarning, stacklevel=3)
    sppc, sppp, sppi = (spp if value is None else integer(name, value, 0)
                        for name, value in (("sppc", sppc), ("sppp", sppp), ("sppi", sppi)))
    if width is not None or height is not None:
        view = view.with_size(view.width if width is None else width,
                              view.height if height is None else height)
    pixels = view.width * view.height
    for name, value in (("spp", spp), ("sppc", sppc), ("sppp", sppp), ("sppi", sppi)):
        if pixels * value > MAX_SAMPLES:
            raise SceneError(f"{name}={value} is too many samples for a {view.width}x{view.height} "
                             f"film: pixels times {name} may be at most 2^32 (each sample's random "
                             f"stream has a 32-bit index), {name} <= {MAX_SAMPLES // pixels} here; "
                             "average renders with other seeds for more")
    aovs = _check_aovs(aovs) if integrator == "aov" else None
    alpha = view.alpha and integrator != "aov"
    _require_film_memory(view, (9 if moments else len(channel_names(integrator, aovs))) + alpha, spp)
    # Built before any recording: a recording may not upload host data.
    lights = scene.light_set() if integrator != "aov" else None
    settings = RenderSettings(integrator, None if aovs is None else tuple(aovs), max_depth, rr_depth,
                              bool(hide_emitters), spp, sppc, sppp, sppi, strategies, moments)
    if not frozen or progress is not None or scene.differentiable:
        # (Derivatives and progress reports call back into Python between kernels.) The
        # boundary term has value 0: only a render with derivatives samples it.
        curves = None
        if scene.differentiable:
            warn_omitted_terms(scene, view, settings)
            curves = boundary_samplers(scene, [CameraBatch((view,))], settings)[0]
        return _image(scene, view, lights, settings, seed, progress, curves)
    # Later renders with these settings replay one recording (instancing.rendering.recording).
    key = settings + (view.key(),)
    return replay(scene, key, _image, view, lights, settings, seed)


def _require_film_memory(camera: Camera, channels: int, spp: int) -> None:
    """Refuse a render whose passes and film would not fit in memory (estimated before
    anything is allocated): each pass's samples (one Float per channel, and their
    per-pixel sums, or a splat's), and the film's running total, interleaved image and NumPy
    copy."""
    pixels = camera.width * camera.height
    pixel_filter = PixelFilter.of(camera)
    sampled = _sampled_pixels(camera, pixel_filter)
    count = max(1, min(spp, MAX_LANES // sampled))
    lanes = sampled * count
    what = f"a {camera.width}x{camera.height} render with {channels} channels"
    require_entries(pixels * channels, what)
    splat = _splat_bytes(pixel_filter, channels, sampled, count) if pixel_filter.splats else 0
    require_memory(4 * channels * (2 * lanes + 3 * pixels) + splat, what)


def omitted_terms(scene: Scene, camera: Camera, settings: RenderSettings) -> list[str]:
    """The derivative terms that a render of ``scene`` with ``settings`` leaves out although
    its moving instances need them: switched off by the caller."""
    integrator, sppp, sppi = settings.integrator, settings.sppp, settings.sppi
    instances, lights = len(scene.moving_instances) > 0, len(scene.moving_lights) > 0
    if not instances and not lights:
        return []
    omitted = [] if sppp or not instances else [
        "sppp=0: the moving instances' silhouettes seen by the camera"]
    if integrator == "aov":
        return omitted
    if shadow_lights(scene, camera) and not sppi:
        omitted.append("sppi=0: the shadows that moving instances cast from point and "
                       "directional lights, and that moving lights cast")
    if not sppi and secondary_term_needed(scene, integrator):
        omitted.append("sppi=0: the visibility changes seen from the shading points (area "
                       "lights' and the environment's penumbrae, indirect light)")
    return omitted


def warn_omitted_terms(scene: Scene, camera: Camera, settings: RenderSettings,
                       stacklevel: int = 3) -> None:
    """A UserWarning naming :func:`omitted_terms`, if any."""
    omitted = omitted_terms(scene, camera, settings)
    if omitted:
        warnings.warn("the gradients leave out visibility changes the scene has: "
                      + "; ".join(omitted), UserWarning, stacklevel=stacklevel)


def boundary_samplers(scene: Scene, batches: list[CameraBatch], settings: RenderSettings
                      ) -> list[tuple]:
    """Per camera batch, the frame's curves for the boundary terms of ``settings`` (host
    work): the moving instances' silhouettes, contact curves, terminator arcs and
    silhouettes seen in flat mirrors (when ``sppp``) and their shadow curves (when ``sppi``,
    for the integrators that shade), each
    kind one table over the batch's views (:meth:`BoundarySampler.joined`), with the
    occluders of the secondary term (when ``sppi``; one set, built once and shared by every
    batch)."""
    _refuse_curveless_boundaries(scene, settings)
    occluders = occluder_set(scene, settings.integrator) if settings.sppi else None
    return [_batch_samplers(scene, list(batch.cameras), settings) + (occluders,)
            for batch in batches]


def _refuse_curveless_boundaries(scene: Scene, settings: RenderSettings) -> None:
    """A SceneError where boundary terms are asked for while something moves in a scene
    with an SDF grid or a linear curve: such a model has no curves to sample (its
    silhouettes, its shadows' edges, the curves where it touches another instance)."""
    names = scene.curveless_model_names
    if names and (settings.sppp or settings.sppi) and (len(scene.moving_instances)
                                                       or len(scene.moving_lights)):
        kind = scene.description.models[[m.name for m in scene.description.models].index(names[0])].type
        raise SceneError(f"{kind} model {names[0]!r}: gradients cannot sample its silhouettes, "
                         "its shadows' edges nor where it touches other instances (the boundary "
                         "terms, sppp and sppi); render with sppp=0 and sppi=0 for the interior "
                         "terms alone")


def _batch_samplers(scene: Scene, cameras: list[Camera], settings: RenderSettings) -> tuple:
    """The curves of :func:`boundary_samplers` seen by the cameras of one batch."""
    integrator, sppp, sppi = settings.integrator, settings.sppp, settings.sppi
    for camera in cameras:
        if camera.viewpoint() is not None:
            continue
        # Silhouettes and shadow edges are sampled as curves seen from one viewpoint.
        moving = len(scene.moving_instances) > 0
        needed = (["the moving instances' silhouettes (sppp)"] if sppp and moving else []) + (
            ["shadow edges from point and directional lights (sppi)"]
            if sppi and integrator != "aov" and shadow_lights(scene, camera)
            and (moving or len(scene.moving_lights)) else [])
        if needed:
            raise SceneError(f"a {camera.type!r} camera has no single viewpoint: gradients "
                             f"cannot sample {' and '.join(needed)} on its film; render with "
                             "sppp=0 and sppi=0 to leave them out, or use a 'perspective' or "
                             "'orthographic' camera")
    none = [None] * len(cameras)
    shading = integrator != "aov"
    return tuple(BoundarySampler.joined(per_view) for per_view in (
        [boundary_sampler(scene, camera) for camera in cameras] if sppp else none,
        contact_samplers(scene, cameras) if sppp else none,
        [terminator_sampler(scene, camera) for camera in cameras] if sppp and shading else none,
        [mirror_sampler(scene, camera) for camera in cameras] if sppp and shading else none,
        shadow_samplers(scene, cameras) if sppi and shading else none))


def _image(scene: Scene, camera: Camera, lights, settings: RenderSettings, seed: UInt32,
           progress: Callable[[int], None] | None = None,
           curves: tuple | None = None) -> TensorXf:
    """The rendered (H, W, C) tensor for ``settings`` (see :func:`render`); ``curves``:
    the moving instances' silhouettes and shadow curves for the boundary terms
    (:func:`boundary_samplers`)."""
    return images(scene, CameraBatch((camera,)), lights, settings, seed, progress, curves)[0]


def images(scene: Scene, batch: CameraBatch, lights, settings: RenderSettings, seed: UInt32,
           progress: Callable[[int], None] | None = None,
           curves: tuple | None = None) -> list[TensorXf]:
    """The (H, W, C) tensors of the views of ``batch`` for ``settings``: their samples traced
    as one wavefront per pass, and so is each boundary term; ``curves``: the batch's
    :func:`boundary_samplers` (None: no boundary terms)."""
    if lights is None:
        return _images(scene, batch, lights, settings, seed, progress, curves)
    # Emitter sampling by cones where no derivative is taken (see LightSet.sphere_cones).
    with lights.spheres_by_cone(not scene.differentiable):
        return _images(scene, batch, lights, settings, seed, progress, curves)


def _images(scene: Scene, batch: CameraBatch, lights, settings: RenderSettings, seed: UInt32,
            progress: Callable[[int], None] | None, curves: tuple | None) -> list[TensorXf]:
    """:func:`images` with the light set's sampling chosen."""
    integrator, max_depth, spp, sppc, sppp, sppi = (settings.integrator, settings.max_depth, settings.spp,
                                                    settings.sppc, settings.sppp, settings.sppi)

    medium = camera_medium(scene, batch.camera.medium) if integrator == "volpath" else 0
    if batch.camera.seed:
        # The cameras' own seed (Mitsuba's sampler's), added to the render's.
        seed = seed + batch.camera.seed
    alpha = batch.camera.alpha and integrator != "aov"

    def radiance(o, d, sampler) -> list[Float]:
        return _radiance(scene, settings, lights, o, d, sampler, medium, alpha)

    # The image, with the interior derivative carried by the same samples when sppc == spp.
    with dr.suspend_grad(when=sppc != spp):
        channels = _film(batch, radiance, spp, seed, progress)
    if sppc not in (0, spp):
        # A separate estimate of the interior derivative: value 0, derivative from sppc samples.
        interior = _film(batch, radiance, sppc, seed + 1, None)
        channels = [c + (i - dr.detach(i)) for c, i in zip(channels, interior)]
    silhouettes, contacts, terminators, mirrors, shadows, occluders = (None,) * 6 if curves is None else curves
    pixel_filter = PixelFilter.of(batch.camera)
    for sampler, count in ((silhouettes, sppp), (contacts, sppp), (terminators, sppp), (mirrors, sppp),
                           (shadows, sppi)):
        boundary = boundary_term(sampler, scene, batch, radiance, len(channels), count,
                                 seed, MAX_LANES, pixel_filter, lights)
        if boundary is not None:
            channels = [c + b for c, b in zip(channels, boundary)]
    per_view = _views(batch, channels)
    if occluders is not None and sppi:
        # Visibility seen from the shading points: camera samples of their own stream.

        def secondary(o, d, sampler) -> list[Float]:
            o = _past_hidden_emitters(scene, settings, lights, o, d)
            rgb = secondary_boundary(scene, lights, occluders, integrator, max_depth, o, d, sampler)
            # (Alpha does not depend on what the shading points see.)
            return [rgb.x, rgb.y, rgb.z] + ([dr.zeros(Float, dr.width(rgb.x))] if alpha else [])

        boundary = _views(batch, _film(batch, secondary, sppi, seed + SECONDARY_STREAM_SEED, None))
        per_view = [[c + b for c, b in zip(view, extra)] for view, extra in zip(per_view, boundary)]
    # Film: channels interleaved per pixel.
    camera = batch.camera
    pixels = camera.width * camera.height
    tensors = []
    for view in per_view:
        flat = dr.zeros(Float, pixels * len(view))
        slot = dr.arange(UInt32, pixels) * len(view)
        for c, values in enumerate(view):
            dr.scatter(flat, values, slot + c)
        tensors.append(TensorXf(flat, shape=(camera.height, camera.width, len(view))))
    return tensors


def _views(batch: CameraBatch, channels: list[Float]) -> list[list[Float]]:
    """Per view of ``batch``, its pixels' part of the batch's (view-major) ``channels``."""
    if len(batch) == 1:
        return [channels]
    pixels = batch.camera.width * batch.camera.height
    index = dr.arange(UInt32, pixels)
    return [[dr.gather(Float, values, index + k * pixels) for values in channels]
            for k in range(len(batch))]


def _film(batch: CameraBatch, radiance: Callable, spp: int, seed: UInt32,
          progress: Callable[[int], None] | None) -> list[Float]:
    """Per-pixel means of ``spp`` filtered samples of ``radiance`` in every view of ``batch``,
    one Float per channel (view-major pixels)."""
    pixel_filter = PixelFilter.of(batch.camera)
    per_pass = max(1, min(spp, MAX_LANES // (_sampled_pixels(batch.camera, pixel_filter) * len(batch))))
    total = None
    for first in range(0, spp, per_pass):
        count = min(per_pass, spp - first)
        channels, px, py = _render_pass(batch, radiance, spp, first, count, seed, pixel_filter)
        # One kernel traces the pass and writes every channel (and the film points a
        # splat reads); then per-pixel sums.
        dr.eval(channels, *((px, py) if pixel_filter.splats else ()))
        if pixel_filter.splats:
            sums = _splat(batch, channels, px, py, count, pixel_filter)
        else:
            sums = [dr.block_sum(values, count) for values in channels]
        total = sums if total is None else [t + s for t, s in zip(total, sums)]
        dr.eval(total)
        if progress is not None:
            dr.sync_thread()  # kernels run asynchronously: report work that is done
            progress(first + count)
    if pixel_filter.splats:
        # Each pixel: its weighted sum over its weights' sum (the last entry).
        return [values / total[-1] for values in total[:-1]]
    # The pixel value is the mean of its samples (all weights are 1).
    # spp stays opaque: renders at other sample counts reuse the compiled kernels.
    return [values / dr.opaque(Float, spp) for values in total]


def _sampled_pixels(camera: Camera, pixel_filter: PixelFilter) -> int:
    """Pixels whose samples a render of one view draws: the film's, and its border's where
    the film samples it (:attr:`PixelFilter.border`)."""
    border = pixel_filter.border
    return (camera.width + 2 * border) * (camera.height + 2 * border)


def _splat(batch: CameraBatch, channels: list[Float], px: Float, py: Float, count: int,
           pixel_filter: PixelFilter) -> list[Float]:
    """Per pixel of every view of ``batch``, the filter-weighted sums of the pass's samples
    (``count`` per sampled pixel, the film's and its border's, at film points (px, py)) of
    the pixels around it that the filter reaches, one Float per channel, then the weights'
    sum. In a fixed order (no atomic additions: the sums are deterministic), in two steps:
    each sampled pixel sums its own samples' weighted values towards every pixel the filter
    reaches (:func:`_moments`), then each film pixel gathers what its neighbours hold
    towards it. The first step covers all row offsets at once where their sums fit, else
    one row offset at a time (:func:`splat_rows`)."""
    camera = batch.camera
    width, height, border = camera.width, camera.height, pixel_filter.border
    # The sampled grid: the film and its border.
    wide, high = width + 2 * border, height + 2 * border
    pixel = dr.arange(UInt32, width * height * len(batch))
    view = pixel // dr.opaque(UInt32, width * height)
    view_first = view * dr.opaque(UInt32, wide * high)
    x = Int32(pixel % dr.opaque(UInt32, width)) + border
    y = Int32((pixel - view * dr.opaque(UInt32, width * height)) // dr.opaque(UInt32, width)) + border
    sums = [dr.zeros(Float, dr.width(pixel)) for _ in range(len(channels) + 1)]
    reach = pixel_filter.reach
    offsets = range(-reach, reach + 1)
    sampled = wide * high * len(batch)
    group = splat_rows(pixel_filter, len(channels), sampled, count)
    for rows in (offsets[k:k + group] for k in range(0, len(offsets), group)):
        moments = _moments(channels, px, py, count, sampled, pixel_filter, rows)
        for dy in rows:
            for dx in offsets:
                qx, qy = x + dx, y + dy
                inside = (qx >= 0) & (qx < wide) & (qy >= 0) & (qy < high)
                neighbour = view_first + UInt32(dr.select(inside, qy * wide + qx, 0))
                # The neighbour lies dx columns and dy rows away: its moment towards the
                # pixel dx columns and dy rows before it.
                for c, held in enumerate(moments[dy, dx]):
                    sums[c] += dr.gather(Float, held, neighbour, inside)
        # Evaluated per group: one group's moments are held at a time.
        dr.eval(sums)
    return sums


def splat_rows(pixel_filter: PixelFilter, channels: int, pixels: int, count: int) -> int:
    """Row offsets whose moments a splat of ``count`` samples per pixel of ``pixels`` computes
    at once: all of them where their sums (per pixel, (channels + 1) per offset) take no
    more memory than the samples (channels and film point) or :data:`SPLAT_SUMS_BYTES`,
    else one."""
    side = 2 * pixel_filter.reach + 1
    return side if (_splat_bytes(pixel_filter, channels, pixels, count, side)
                    <= max(4 * pixels * count * (channels + 2), SPLAT_SUMS_BYTES)) else 1


def _splat_bytes(pixel_filter: PixelFilter, channels: int, pixels: int, count: int,
                 rows: int | None = None) -> int:
    """Bytes of the moments a splat holds at a time: ``rows`` row offsets' (default: those of
    :func:`splat_rows`), (channels + 1) per offset and pixel."""
    side = 2 * pixel_filter.reach + 1
    rows = splat_rows(pixel_filter, channels, pixels, count) if rows is None else rows
    return 4 * pixels * rows * side * (channels + 1)


def _moments(channels: list[Float], px: Float, py: Float, count: int, pixels: int,
             pixel_filter: PixelFilter, rows: range) -> dict[tuple[int, int], list[Float]]:
    """Per pixel and offset (dy, dx), dy in ``rows`` and dx across the filter's reach, the
    sums over the pixel's ``count`` samples of their channel values (and 1) weighted towards
    the pixel dx columns and dy rows before it: one loop over each pixel's samples, in
    their order."""
    reach = pixel_filter.reach
    offsets = [(dy, dx) for dy in rows for dx in range(-reach, reach + 1)]
    first = dr.arange(UInt32, pixels) * dr.opaque(UInt32, count)
    n = len(channels) + 1

    def body(s, sums):
        index = first + s
        values = [dr.gather(Float, c, index) for c in channels] + [Float(1.0)]
        x, y = dr.gather(Float, px, index), dr.gather(Float, py, index)
        fx, fy = x - dr.floor(x) - 0.5, y - dr.floor(y) - 0.5
        towards_x = {dx: pixel_filter.weight(fx + dx) for dx in range(-reach, reach + 1)}
        towards_y = {dy: pixel_filter.weight(fy + dy) for dy in rows}
        out = list(sums)
        for k, (dy, dx) in enumerate(offsets):
            weight = towards_x[dx] * towards_y[dy]
            for c, value in enumerate(values):
                out[k * n + c] = dr.fma(weight, value, out[k * n + c])
        return s + 1, out

    zero = [dr.zeros(Float, pixels) for _ in range(len(offsets) * n)]
    _, sums = dr.while_loop((dr.zeros(UInt32, pixels), zero),
                            lambda s, sums: s < dr.opaque(UInt32, count), body)
    # One kernel for all of them (a gather from a pending one would launch its own loop).
    dr.eval(sums)
    return {offset: sums[k * n:(k + 1) * n] for k, offset in enumerate(offsets)}


def _render_pass(batch, radiance, spp, first, count, seed, pixel_filter: PixelFilter
                 ) -> tuple[list[Float], Float, Float]:
    """Channel values of samples first .. first+count-1 of every sampled pixel (the film's,
    and its border's where it samples it) of every view (view-major, then pixel-major
    lanes), and their film points (pixels)."""
    camera = batch.camera
    sampled = _sampled_pixels(camera, pixel_filter)
    lane = dr.arange(UInt32, sampled * len(batch) * count)
    pixel = lane // dr.opaque(UInt32, count)
    # Each sample's random numbers depend on (seed, view, pixel, sample index) only.
    index = lane % dr.opaque(UInt32, count) + dr.opaque(UInt32, first)
    sampler = (pixel_samplers(pixel, index, spp, seed, camera.jitter) if camera.stratified
               else sample_streams(pixel * dr.opaque(UInt32, spp) + index, seed))
    view = None
    if len(batch) > 1:
        view = pixel // dr.opaque(UInt32, sampled)
        pixel = pixel - view * dr.opaque(UInt32, sampled)
    # The film size is opaque too: other resolutions reuse the compiled kernels.
    border = dr.opaque(Float, pixel_filter.border)
    wide = dr.opaque(UInt32, camera.width + 2 * pixel_filter.border)
    cx, cy = Float(pixel % wide) - border, Float(pixel // wide) - border
    # The film point: uniform in the pixel.
    ux, uy = sampler.next_pair()
    px, py = cx + ux, cy + uy
    w, h = dr.opaque(Float, camera.width), dr.opaque(Float, camera.height)
    aperture = sampler.next_pair() if camera.aperture_samples else None
    o, d = camera.rays(px / w, py / h, aperture, batch.lanes(view))
    return radiance(o, d, sampler), px, py


def _past_hidden_emitters(scene, settings: RenderSettings, lights, o, d):
    """Camera ray origins past the area emitters they see first, where the render hides
    emitters (volpath passes them in its own loop)."""
    if settings.hide_emitters and settings.integrator in ("direct", "path"):
        return past_emitters(scene, lights, o, d)
    return o


def _radiance(scene, settings: RenderSettings, lights, o, d, sampler, medium, alpha: bool = False
              ) -> list[Float]:
    """The integrator's channel values along camera rays (o, d) (that start in the medium
    ``medium`` for volpath); with ``alpha``, each sample's alpha after its RGB."""
    integrator, max_depth, rr_depth = settings.integrator, settings.max_depth, settings.rr_depth
    hide = settings.hide_emitters
    if integrator == "aov":
        return integrate_aov(scene, o, d, settings.aovs)
    o = _past_hidden_emitters(scene, settings, lights, o, d)
    if integrator == "direct":
        out = integrate_direct(scene, lights, o, d, sampler, hide, settings.strategies, alpha)
    elif integrator == "path":
        out = integrate_path(scene, lights, o, d, sampler, max_depth, rr_depth=rr_depth, hide_emitters=hide,
                             alpha=alpha)
    else:
        out = integrate_volpath(scene, lights, o, d, sampler, max_depth, medium, rr_depth, hide, alpha)
    rgb, coverage = out if alpha else (out, None)
    channels = [rgb.x, rgb.y, rgb.z] + ([coverage] if alpha else [])
    if not settings.moments:
        return channels
    xyz = [dr.dot(Array3f(*row), rgb) for row in SRGB_TO_XYZ]
    return channels + xyz + [dr.square(v) for v in xyz]
