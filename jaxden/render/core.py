"""render_frame: one Mitsuba render -> a jaxden Frame (colour, variance of the mean, features).

Two renders per frame, with the same sensor:

1. **Colour pass(es)**: the ``jaxden_moment`` integrator (see
   :mod:`jaxden.render.integrators`) gives the exact per-pixel RGB first and second sample
   moments in one render, and the emission of the first hit averaged over the same samples. Large jobs (spp x pixels > ``MAX_SAMPLES_PER_PASS``, or spp >
   ``MAX_SPP_PER_PASS``) are split into passes with their own derived seeds; the passes'
   moments are combined exactly (weighted by their spp, in float64). Passes keep the Dr.Jit
   wavefront far below its 2^32 limit and bound the float32 round-off of the film's per-pixel
   sums (the sum of 1024 samples loses at most ~1e-4 relative; the variance needs m2 - m1^2).
2. **Feature pass**: ``min(spp, feature_spp)`` samples per pixel (default 1024; datasets
   built before the option used ``AOV_SPP`` = 16), box filter, with Mitsuba's ``aov``
   integrator (``aux="first-hit"``) or jaxden's specular-chain one (the default). The features are therefore *averages over that many samples inside the pixel*
   (anti-aliased, as in the authors' data and as OIDN expects): at an object's silhouette the
   albedo, depth and position blend the hit and the miss (misses count as 0). Normals are the
   averaged shading normal rescaled to unit length (0 where no sample hit), so ``normal`` is
   unit length wherever anything was hit. ``albedo`` is Mitsuba's ``albedo`` AOV (the BSDF's
   diffuse reflectance) clipped to [0, 1]: for glossy lobes Mitsuba evaluates the BSDF at
   normal incidence, which exceeds 1 (a rough gold sphere gives ~16); smooth dielectrics and
   conductors get 0. With ``aux="specular-chain"`` the albedo and normal come instead from
   the first non-delta surface along the mirror / refraction chain (the integrator
   ``jaxden_features_chain``, as OIDN's documentation recommends; see
   :mod:`jaxden.render.integrators`); depth and position stay first-hit.

Seeds: the colour passes and the feature pass use seeds derived from ``seed`` by hashing
(:func:`derive_seed`), so they are distinct, deterministic, and unrelated across user seeds.

With ``spp == 1`` the sample variance cannot be estimated: the Frame's ``variance`` is None.

Speed: Dr.Jit compiles kernels per scene object, film (or crop) size and spp, and caches them
(about 0.3-2 s each on two cores, more when they are busy). To render many frames of one scene, load it once with
:func:`jaxden.render.load_scene` and pass the ``mi.Scene``; crops of one size at any position,
seeds and camera poses then reuse the compiled kernels. render_frame also reuses the scene of
a recent identical name/``procedural:SEED``/XML spec (see :func:`_load_cached`).
"""

from __future__ import annotations

import collections
import hashlib
import math
import os

import numpy as np

from jaxden.errors import SceneError
from jaxden.frame import Frame
from jaxden.render import integrators, load, scenes
from jaxden.render.variant import ensure_variant

AOV_SPP = 16  # the feature samples of every jaxden dataset built before feature_spp existed
#: render_frame's defaults: the features OIDN does best with (docs/results.md, "OIDN's auxiliary
#: features"); datasets keep the legacy first-hit / AOV_SPP unless their config says otherwise.
DEFAULT_AUX = "specular-chain"
DEFAULT_FEATURE_SPP = 1024
MAX_SAMPLES_PER_PASS = 1 << 28  # samples (pixels x spp) per colour pass; wavefront < 2^32
MAX_SPP_PER_PASS = 1024
MAX_SPP = 1 << 24


def derive_seed(seed: int, purpose: str, index: int = 0) -> int:
    """A 32-bit Mitsuba seed for one pass: hash of (seed, purpose, pass index).

    purpose is 'color' (index = pass number) or 'aov'. Hashing keeps seeds of different
    frames and passes unrelated even when users number their frames 0, 1, 2, ...
    """
    digest = hashlib.blake2b(f"jaxden:{int(seed)}:{purpose}:{int(index)}".encode(),
                             digest_size=4).digest()
    return int.from_bytes(digest, "little")


def feature_attributes(spp: int, aux: str = DEFAULT_AUX,
                       feature_spp: int = DEFAULT_FEATURE_SPP) -> dict[str, str | int]:
    """The EXR header attributes that record how a render's features were made, for
    ``write_frame(..., attributes=...)`` (written as ``jaxden.aux`` and ``jaxden.feature_spp``):
    ``aux`` and the samples the feature pass averaged, ``min(spp, feature_spp)``. A denoiser
    run on the file compares them with the features it was trained on
    (:mod:`jaxden.data.features`)."""
    return {"aux": str(aux), "feature_spp": min(int(spp), int(feature_spp))}


def split_passes(spp: int, pixels: int, max_samples: int = MAX_SAMPLES_PER_PASS,
                 max_spp: int = MAX_SPP_PER_PASS) -> list[int]:
    """spp of each colour pass: as few passes as the budgets allow, spp split evenly."""
    passes = max(math.ceil(spp * pixels / max_samples), math.ceil(spp / max_spp), 1)
    passes = min(passes, spp)
    base, extra = divmod(spp, passes)
    return [base + (1 if i < extra else 0) for i in range(passes)]


def _check_int(value, name: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise SceneError(f"render_frame: {name} must be an integer, got {value!r}")
    value = int(value)
    if not low <= value <= high:
        raise SceneError(f"render_frame: {name} must be in [{low}, {high}], got {value}")
    return value


def _check_crop(crop, size: tuple[int, int]) -> tuple[int, int, int, int]:
    try:
        top, left, height, width = crop
    except (TypeError, ValueError):
        raise SceneError(
            f"render_frame: crop must be (top, left, height, width), got {crop!r}"
        ) from None
    values = (top, left, height, width)
    if any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in values):
        raise SceneError(f"render_frame: crop must be four integers, got {crop!r}")
    top, left, height, width = (int(v) for v in values)
    film_width, film_height = size
    if top < 0 or left < 0 or height < 1 or width < 1 or top + height > film_height \
            or left + width > film_width:
        raise SceneError(
            f"render_frame: crop (top={top}, left={left}, height={height}, width={width}) does "
            f"not fit in the {film_width}x{film_height} (width x height) film"
        )
    return top, left, height, width


# Only the last spec's scene: every other live scene would be traced into each render's kernels.
SPEC_MEMORY = 1
_spec_scenes: collections.OrderedDict = collections.OrderedDict()


def _load_cached(spec, size, parameters=None):
    """load_scene for render_frame, reusing the scene of a recent identical spec.

    Dr.Jit compiles kernels per scene *object* (and film size and spp), so loading the same
    spec again would recompile. Only specs that name immutable sources are reused: built-in
    names, ``procedural:SEED``, and XML files (keyed by path and modification time). Scene
    dicts are always loaded afresh. The scenes never leave render_frame, so nobody can
    modify a shared one.
    """
    key = None
    if isinstance(spec, (str, os.PathLike)):
        if load._is_path_like(spec):
            try:
                path = os.path.realpath(os.fspath(spec))
                key = ("xml", path, os.stat(path).st_mtime_ns, size,
                       tuple(sorted((parameters or {}).items())))
            except OSError:
                key = None  # load_scene reports the missing file
        else:
            key = ("name", spec, size)
    if key is not None and key in _spec_scenes:
        _spec_scenes.move_to_end(key)
        return _spec_scenes[key]
    scene = load.load_scene(spec, size, parameters)
    if key is not None:
        _spec_scenes[key] = scene
        while len(_spec_scenes) > SPEC_MEMORY:
            _spec_scenes.popitem(last=False)
    return scene


def _scene_and_sensor(scene, size, crop, sensor, parameters=None):
    """(mi.Scene, mi.Sensor, (height, width) of the output) for render_frame's arguments."""
    import mitsuba as mi

    if size is not None:
        size = scenes.check_size(size, "render_frame: size")
    if not isinstance(scene, mi.Scene):
        scene = _load_cached(scene, size, parameters)
    source = load.sensor_source(scene)
    if sensor is not None:
        if not isinstance(sensor, dict):
            raise SceneError(
                f"render_frame: sensor must be a Mitsuba sensor dict, got {type(sensor).__name__}"
            )
        film = sensor.get("film") if isinstance(sensor.get("film"), dict) else {}
        if size is None and "width" in film and "height" in film:
            size = scenes.check_size((film["width"], film["height"]), "render_frame: sensor film")
        elif size is None:
            size = source.size if source is not None else tuple(
                int(v) for v in scene.sensors()[0].film().size())
        crop = None if crop is None else _check_crop(crop, size)
        load.patch_sensor_dict(sensor, size, "render_frame: sensor")  # errors before loading
        built = load.SensorSource(name="render_frame: sensor", size=size,
                                    sensor_dict=sensor).build(size, crop)
    elif source is not None:
        size = size or source.size
        crop = None if crop is None else _check_crop(crop, size)
        built = source.build(size, crop)
    else:
        # A scene jaxden did not load (or forgot): only its own sensor, checked as it is.
        if not scene.sensors():
            raise SceneError("render_frame: the scene has no sensor")
        built = scene.sensors()[0]
        own = tuple(int(v) for v in built.film().size())
        if (size is not None and tuple(size) != own) or crop is not None:
            raise SceneError(
                "render_frame: this mi.Scene was not loaded by jaxden.render.load_scene (or is "
                f"older than its last {scenes.SCENE_MEMORY} scenes), so its {own[0]}x{own[1]} "
                "film cannot be resized or cropped; pass the scene spec instead"
            )
        if not str(built.film().rfilter()).startswith("BoxFilter") or \
                not str(built.sampler()).startswith("IndependentSampler"):
            raise SceneError(
                "render_frame: the mi.Scene's sensor must use a box filter and the independent "
                "sampler (others correlate pixels); load it with jaxden.render.load_scene"
            )
        size = own
    if crop is not None:
        return scene, built, (crop[2], crop[3])
    return scene, built, (size[1], size[0])


_integrator_cache: dict = {}


def _integrators(scene, max_depth, statistics: bool = False):
    """(inner colour integrator, its moment wrapper) for a scene, cached."""
    import mitsuba as mi

    inner = None
    if max_depth is None:
        own = scene.integrator()
        if own is not None and isinstance(own, mi.SamplingIntegrator) and not own.aov_names():
            inner = own  # the scene's own integrator (e.g. volpath of an XML scene)
    if inner is None:
        depth = integrators.DEFAULT_MAX_DEPTH if max_depth is None else max_depth
        key = ("path", mi.variant(), depth)
        if key not in _integrator_cache:
            _integrator_cache[key] = integrators.path_integrator(depth)
        inner = _integrator_cache[key]
    key = ("moment", mi.variant(), id(inner), statistics)
    entry = _integrator_cache.get(key)
    if entry is None or entry[0] is not inner:
        entry = (inner, integrators.moment_integrator(inner, statistics=statistics))
        _integrator_cache[key] = entry
        while len(_integrator_cache) > 32:
            _integrator_cache.pop(next(iter(_integrator_cache)))
    return inner, entry[1]


def _features_integrator(aux: str = "first-hit"):
    import mitsuba as mi

    key = ("features", aux, mi.variant())
    if key not in _integrator_cache:
        _integrator_cache[key] = integrators.features_integrator(aux)
    return _integrator_cache[key]


def _render(scene, sensor, integrator, seed: int, spp: int, channels: int) -> np.ndarray:
    import mitsuba as mi

    try:
        image = np.array(mi.render(scene, sensor=sensor, integrator=integrator, seed=seed,
                                   spp=spp), dtype=np.float32)
    except Exception as error:  # noqa: BLE001 - Mitsuba raises RuntimeError and others
        # A scene Mitsuba loads but cannot render (e.g. a texture that a plugin cannot
        # differentiate); the innermost message names the plugin.
        while error.__cause__ is not None:
            error = error.__cause__
        message = " ".join(line.strip() for line in str(error).splitlines() if line.strip())
        source = load.sensor_source(scene)
        name = source.name if source is not None else "the scene"
        raise SceneError(f"{name}: Mitsuba could not render it: {message}") from None
    if image.ndim != 3 or image.shape[-1] != channels:
        raise RuntimeError(f"expected a render with {channels} channels, got shape {image.shape}")
    return image


def _render_colour(mi_scene, mi_sensor, max_depth, seed: int, spp: int,
                   shape: tuple[int, int], budget: int, statistics: bool = False):
    """Colour passes: (pixel mean, variance of the mean, covariance of the mean between
    channels, emission of the first hit averaged over the same samples, Box-Cox statistics or
    None), float32; variance and covariance None at 1 spp."""
    _, moment = _integrators(mi_scene, max_depth, statistics)
    channels = integrators.MOMENT_CHANNELS + (len(integrators.STATISTICS_AOVS) if statistics
                                              else 0)
    sums = np.zeros(shape + (channels,), np.float64)
    for index, pass_spp in enumerate(split_passes(spp, shape[0] * shape[1], budget)):
        sums += pass_spp * _render(mi_scene, mi_sensor, moment, derive_seed(seed, "color", index),
                                   pass_spp, channels).astype(np.float64)
    moments = sums / spp
    m1 = moments[..., 0:3]
    emission = moments[..., 9:12].astype(np.float32)
    boxcox = None if not statistics else integrators.boxcox_statistics(
        moments[..., 12:15], moments[..., 15:18], moments[..., 18:21], spp)
    if spp == 1:
        return m1.astype(np.float32), None, None, emission, boxcox
    variance = integrators.variance_of_mean(m1, moments[..., 3:6], spp)
    covariance = integrators.covariance_of_mean(m1, moments[..., 6:9], variance, spp)
    return (m1.astype(np.float32), variance.astype(np.float32), covariance.astype(np.float32),
            emission, boxcox)


def _check_colour(colour: Frame, spp: int, shape: tuple[int, int]):
    """The colour, variance, covariance and emission of a given render, checked against the
    frame to be made."""
    color = np.asarray(colour.color, np.float32)
    if color.shape != shape + (3,):
        raise SceneError(f"render_frame: colour= has shape {color.shape}, the render is "
                         f"{shape + (3,)}")
    if colour.spp is not None and float(colour.spp) != spp:
        raise SceneError(f"render_frame: colour= is a {float(colour.spp):g}-spp render, "
                         f"not {spp} spp")
    variance = None if colour.variance is None else np.asarray(colour.variance, np.float32)
    if variance is None and spp > 1:
        raise SceneError("render_frame: colour= has no variance")
    covariance = None if colour.covariance is None else np.asarray(colour.covariance, np.float32)
    emission = None if colour.emission is None else np.asarray(colour.emission, np.float32)
    boxcox = None if colour.boxcox is None else np.asarray(colour.boxcox, np.float32)
    return color, variance, covariance, emission, boxcox


def _render_features(scene, sensor, integrator, seed: int, spp: int, pixels: int,
                     budget: int) -> np.ndarray:
    """The 10 feature channels at ``spp`` samples: in one pass when it fits the sample budget
    (always, at the legacy 16 spp), else in passes with derived seeds, averaged by spp."""
    plan = split_passes(spp, pixels, budget)
    if len(plan) == 1:
        return _render(scene, sensor, integrator, seed, spp, 10)
    total = None
    for index, pass_spp in enumerate(plan):
        image = _render(scene, sensor, integrator, derive_seed(seed, "aov-pass", index),
                        pass_spp, 10).astype(np.float64)
        total = pass_spp * image if total is None else total + pass_spp * image
    return (total / spp).astype(np.float32)


def render_frame(
    scene,
    spp: int,
    seed: int = 0,
    size: tuple[int, int] | None = None,
    *,
    crop: tuple[int, int, int, int] | None = None,
    sensor: dict | None = None,
    max_depth: int | None = None,
    max_samples_per_pass: int | None = None,
    aux: str = DEFAULT_AUX,
    feature_spp: int = DEFAULT_FEATURE_SPP,
    colour: Frame | None = None,
    parameters: dict[str, str] | None = None,
    statistics: bool = False,
) -> Frame:
    """Render a Frame: colour, variance of the mean, emission, albedo, normal, depth, position.

    Args:
      scene: anything :func:`jaxden.render.load_scene` accepts (built-in name,
        ``procedural:SEED``, XML path, scene dict), or an ``mi.Scene`` (from ``load_scene``,
        which remembers how to resize and crop it; other mi.Scenes render only as they are and
        must already use a box filter and the independent sampler).
      spp: samples per pixel, >= 1.
      seed: any integer >= 0; the frame is a deterministic function of it.
      size: (width, height) in pixels of the full film; default the scene's (or the sensor's).
      crop: (top, left, height, width) in pixels of the full film; only the crop is rendered
        and returned (for perspective cameras by an equivalent off-centre camera, which
        reuses compiled kernels across crop positions; else by Mitsuba's film crop).
      sensor: a Mitsuba sensor dict (e.g. a camera of a path) used instead of the scene's
        own; it also gets hdrfilm + box filter + independent sampler and ``size``.
      max_depth: path length of the ``path`` integrator used for colour; default: the
        scene's own sampling integrator if it has one, else ``path`` with max_depth 8.
      max_samples_per_pass: samples (pixels x spp) per colour pass, default
        MAX_SAMPLES_PER_PASS; smaller means more passes (see the module docstring).
      aux: how albedo and normal are taken: ``"specular-chain"`` (default: from the first
        non-delta surface behind mirrors and smooth glass, as OIDN recommends; see the module
        docstring) or ``"first-hit"`` (Mitsuba's ``aov`` integrator; datasets built before
        this option).
      feature_spp: the feature pass averages ``min(spp, feature_spp)`` samples per pixel
        (default 1024). The 16 of older datasets leaves sampling noise in textured albedo and
        at edges, which OIDN keeps when told its features are clean: 10-25 % more RMSE at
        256-4096 spp (docs/results.md, "OIDN's auxiliary features").
      colour: a Frame whose colour, variance, covariance and emission to keep instead of
        rendering them (only the feature pass runs): a render of the same scene, crop and spp, e.g. a dataset item
        whose features are re-rendered (``jaxden dataset refeature``). With the seed it was
        rendered with, the result equals a full render_frame call.
      parameters: ``{name: value}`` for ``$name`` in an XML scene (Mitsuba's ``-D``).
      statistics: also the per-pixel sample statistics StatMC tests with (``Frame.boxcox``:
        mean, second and third central moments of each sample's Box-Cox(0.5) value, from the
        same samples as the colour, which stays as without them but for float32 round-off;
        :func:`jaxden.render.integrators.boxcox_statistics`). 9 more film channels.

    Returns:
      A Frame of float32 NumPy arrays without batch dimension: color (H, W, 3) (linear
      radiance, mean of spp samples), variance (H, W, 3) variance of that mean and
      covariance (H, W, 3) its covariance between channels (R, G), (G, B), (B, R), both None
      when spp == 1; emission (H, W, 3) the radiance emitted by the first hit (directly
      visible emitters; not the environment on misses), averaged over the colour's own
      samples, so 0 <= emission <= color (see :mod:`jaxden.render.integrators`; None with a
      ``colour`` frame that has none); albedo (H, W, 3); normal (H, W, 3), unit length, 0
      where no feature sample hit;
      depth (H, W, 1) distance along the camera ray, 0 on misses; position (H, W, 3) world
      space, 0 on misses; spp = np.float32(spp). Features average min(spp, feature_spp)
      samples.

    Raises SceneError for a bad scene, size, crop, spp, seed, max_depth, aux or feature_spp.
    """
    ensure_variant()
    if aux not in integrators.AUX_MODES:
        raise SceneError(f"render_frame: aux must be one of {', '.join(integrators.AUX_MODES)}, "
                         f"got {aux!r}")
    spp = _check_int(spp, "spp", 1, MAX_SPP)
    seed = _check_int(seed, "seed", 0, 2**63 - 1)
    if max_depth is not None:
        max_depth = _check_int(max_depth, "max_depth", -1, 1024)
        if max_depth == 0:
            raise SceneError("render_frame: max_depth must be >= 1 (or -1 for unbounded), got 0")
    feature_spp = _check_int(feature_spp, "feature_spp", 1, MAX_SPP)
    budget = MAX_SAMPLES_PER_PASS if max_samples_per_pass is None else _check_int(
        max_samples_per_pass, "max_samples_per_pass", 1, 1 << 31)
    mi_scene, mi_sensor, (height, width) = _scene_and_sensor(scene, size, crop, sensor,
                                                             parameters)
    if colour is None:
        color, variance, covariance, emission, boxcox = _render_colour(
            mi_scene, mi_sensor, max_depth, seed, spp, (height, width), budget,
            bool(statistics))
    else:
        color, variance, covariance, emission, boxcox = _check_colour(colour, spp,
                                                                      (height, width))

    features = _render_features(mi_scene, mi_sensor, _features_integrator(aux),
                                derive_seed(seed, "aov"), min(spp, feature_spp), height * width,
                                budget)
    channels = integrators.FEATURE_CHANNELS
    normal = features[..., channels["normal"]]
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.where(length > 1e-6, normal / np.maximum(length, 1e-6), 0.0)
    return Frame(
        color=color,
        variance=variance,
        # Mitsuba's albedo AOV evaluates non-diffuse lobes at normal incidence (a rough gold
        # sphere gives ~16): clip to the physical range.
        albedo=np.clip(features[..., channels["albedo"]], 0.0, 1.0),
        normal=normal.astype(np.float32),
        depth=np.ascontiguousarray(features[..., channels["depth"]]),
        position=np.ascontiguousarray(features[..., channels["position"]]),
        spp=np.float32(spp),
        covariance=covariance,
        emission=emission,
        boxcox=boxcox,
    )
