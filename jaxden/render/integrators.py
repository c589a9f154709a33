"""Mitsuba integrators for denoising data: RGB moments in one render, and feature AOVs.

``jaxden_moment`` (:func:`moment_integrator`) wraps an inner sampling integrator (``path`` by
default) and returns its radiance L as the colour plus L_R^2, L_G^2, L_B^2 and the cross
products L_R L_G, L_G L_B, L_B L_R as six AOVs. With a box pixel filter every sample lands in
exactly one pixel with weight 1, so the film's averages are the exact per-pixel first and
second moments m1 = mean(L), m2 = mean(L^2), m11 = mean(L_a L_b) of the n = spp samples, and

    variance of the pixel mean   = (m2 - m1^2) / (n - 1),            clipped at 0,
    covariance of the pixel mean = (m11 - m1_a m1_b) / (n - 1),      clipped to Cauchy-Schwarz,

i.e. the unbiased sample (co)variance divided by n. Mitsuba's built-in ``moment`` integrator
is not used: it stores CIE XYZ moments, from which per-channel RGB variance cannot be
recovered.

Three more AOVs hold the **emission** Le of each sample: the radiance emitted towards the
camera by the surface its camera ray hits first (``emitter.eval`` at that hit, 0 where the
surface is no emitter), i.e. the directly visible emitters, exactly the term the path
integrator adds at depth 0 (throughput 1, MIS weight 1: a camera ray is a delta "bounce").
The film averages it over the same samples as the colour, so per pixel ``m1 - emission`` is the
mean of ``L - Le``, the rest of the radiance, with no rim where a separate render would have
hit the emitter on other samples; float addition is monotone, so ``emission <= m1`` holds
exactly in every channel. Decisions: the environment seen on camera-ray misses is *not*
emission (as Blender Cycles' ``Emit`` pass, where the background is its own pass; it is low in
variance and mostly what a denoiser is trained to see); an inner integrator with
``hide_emitters`` gives emission 0 (its colour holds no directly visible emitter). The hit is
found by one more ``ray_intersect`` of the camera ray, which draws no random numbers, so the
colour, moments and cross moments are bit for bit those of a render without emission (the
film already had 3+ extra channels; measured in tests/test_emission.py). Its cost is one more
intersection per sample (``jaxden bench render`` reports it as ``ratio_emission``; measured:
docs/results.md, "Data"). Assumptions: the camera ray weight is 1 (perspective and thin-lens
cameras in RGB variants) and no participating medium lies between the camera and the first
surface (volpath would attenuate Le there).

The wrapper calls the inner integrator's ``sample`` with the same sampler and nothing else, so
it draws exactly the same random numbers: with the same seed and spp its colour equals a plain
render of the inner integrator. In ``llvm_ad_rgb`` it is equal to float32 round-off, not bit
for bit (measured: docs/results.md, "Data"): a film with 3+ extra channels accumulates in a
different order; a 1-channel AOV or no AOV gives bit-identical colour, which shows the samples
themselves are identical. In ``scalar_rgb`` it is bit-identical (but a Python integrator is
slow in scalar mode: every sample calls into Python).

``jaxden_features`` (:func:`aov_integrator`) is Mitsuba's built-in ``aov`` integrator with
albedo, shading normal, depth and position of the first hit (0 on misses). Two separate renders
(moments, then AOVs) are faster than ``aov`` wrapping ``path`` (docs/results.md, "Data"), and
give the same result.

``jaxden_features_chain`` (:func:`chain_features_integrator`, ``aux = "specular-chain"``) gives
the same 10 channels, but takes albedo and normal from the first *non-delta* surface: where a
camera ray meets a perfect mirror or smooth glass (a BSDF with only delta lobes), it follows
the reflected or refracted ray, chosen by sampling the BSDF (so the pixel average is the
Fresnel blend of the two), up to ``max_specular`` delta bounces, and stores the albedo of the
surface it reaches times the delta lobes' weights, and that surface's normal. This is what
Intel Open Image Denoise's documentation recommends for delta surfaces; the first-hit albedo
of a mirror or of glass is 0 in Mitsuba, which tells OIDN nothing about what is seen in it.
Depth and position stay those of the first hit. A chain that ends in a miss, or is still on
delta surfaces after ``max_specular`` bounces, stores 0 (as a camera ray's miss does).
"""

from __future__ import annotations

from typing import Any

from jaxden.render.variant import ensure_variant

MOMENT_PLUGIN = "jaxden_moment"
#: Film channel order of a moment render: R, G, B, then these AOVs (``e.*``: the emission).
MOMENT_AOVS: tuple[str, ...] = ("m2.R", "m2.G", "m2.B", "m11.RG", "m11.GB", "m11.BR",
                                "e.R", "e.G", "e.B")
#: Channels of a moment render: m1 (3), m2 (3), m11 (3), emission (3).
MOMENT_CHANNELS = 3 + len(MOMENT_AOVS)
#: The AOVs a moment render adds with ``statistics=True``, after MOMENT_AOVS: the first three
#: raw moments of s = 2 sqrt(L) per channel (s = b + 2 for StatMC's Box-Cox(0.5) value
#: b = (sqrt(L) - 1) / 0.5; see :func:`boxcox_statistics`).
STATISTICS_AOVS: tuple[str, ...] = tuple(f"s{k}.{c}" for k in (1, 2, 3) for c in "RGB")
#: Built-in ``aov`` integrator spec; output channels in this order (10 in all).
FEATURE_AOVS: str = "albedo:albedo,nn:sh_normal,dd:depth,pp:position"
FEATURE_CHANNELS: dict[str, slice] = {
    "albedo": slice(0, 3),
    "normal": slice(3, 6),
    "depth": slice(6, 7),
    "position": slice(7, 10),
}
DEFAULT_MAX_DEPTH = 8
CHAIN_PLUGIN = "jaxden_features_chain"
DEFAULT_MAX_SPECULAR = 4
#: How the albedo and normal features are taken (``render_frame(aux=...)``).
AUX_MODES: tuple[str, ...] = ("first-hit", "specular-chain")

_classes: dict[str, type] = {}  # variant -> MomentIntegrator class of that variant


def _moment_class() -> type:
    """The MomentIntegrator class for the current variant (mi classes are per variant)."""
    import drjit as dr
    import mitsuba as mi

    variant = ensure_variant()
    if variant in _classes:
        return _classes[variant]

    class MomentIntegrator(mi.SamplingIntegrator):
        """Radiance of an inner integrator plus its channel squares and cross products as
        6 AOVs.

        Properties: ``inner`` (a nested sampling integrator) or ``max_depth`` (for the default
        ``path`` inner integrator; -1 is unbounded); ``emission`` (default True: the last 3
        AOVs are the emission Le of the first hit, see the module docstring; False: without
        them, the integrator before the emission existed, kept for tests and benchmarks);
        ``statistics`` (default False: True adds STATISTICS_AOVS after the emission, the raw
        moments StatMC's per-pixel statistics come from; needs ``emission``).
        """

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            inner = props.get("inner", None) if "inner" in props.keys() else None
            max_depth = props.get("max_depth", DEFAULT_MAX_DEPTH)
            if inner is None:
                inner = mi.load_dict({"type": "path", "max_depth": int(max_depth)})
            self.inner = inner
            self.emission = bool(props.get("emission", True))
            self.statistics = bool(props.get("statistics", False)) and self.emission

        def sample(self, scene, sampler, ray, medium=None, active=True):
            # Only the inner integrator touches the sampler: no extra random numbers.
            radiance, valid, _ = self.inner.sample(scene, sampler, ray, medium, active)
            moments = [radiance[0] * radiance[0], radiance[1] * radiance[1],
                       radiance[2] * radiance[2], radiance[0] * radiance[1],
                       radiance[1] * radiance[2], radiance[2] * radiance[0]]
            if not self.emission:
                return radiance, valid, moments
            emitted = first_hit_emission(scene, ray, active, self.inner)
            aovs = moments + [emitted[0], emitted[1], emitted[2]]
            if self.statistics:
                # s = 2 sqrt(L), the Box-Cox(0.5) value shifted by 2: central moments do not
                # see the shift, and dark pixels (b near -2) keep their digits in float32.
                s = [2.0 * mi.Float(dr.sqrt(dr.maximum(radiance[c], 0.0))) for c in range(3)]
                aovs += s + [v * v for v in s] + [v * v * v for v in s]
            return radiance, valid, aovs

        def aov_names(self):
            names = list(MOMENT_AOVS if self.emission else MOMENT_AOVS[:6])
            return names + list(STATISTICS_AOVS) if self.statistics else names

        def to_string(self):
            return f"MomentIntegrator[inner={self.inner}]"

    mi.register_integrator(MOMENT_PLUGIN, lambda props: MomentIntegrator(props))
    _classes[variant] = MomentIntegrator
    return MomentIntegrator


def first_hit_emission(scene, ray, active, inner=None):
    """Le of each camera ray: the radiance emitted towards the camera by the surface the ray
    hits first (an ``mi.Color3f``, 0 on misses and on surfaces that emit nothing, and 0
    everywhere when ``inner`` hides emitters). Draws no random numbers."""
    import mitsuba as mi

    if getattr(inner, "hide_emitters", False):
        return mi.Color3f(0.0)
    si = scene.ray_intersect(ray, active)
    emitter = si.emitter(scene)
    if emitter is None:  # scalar variants: one ray, which hit no emitter (or nothing)
        return mi.Color3f(0.0)
    if isinstance(active, bool):  # scalar variants: one ray, which hit an emitter
        return mi.Color3f(emitter.eval(si)) if active else mi.Color3f(0.0)
    return mi.Color3f(emitter.eval(si, active & si.is_valid()))


def register() -> None:
    """Register ``jaxden_moment`` with Mitsuba for the current jaxden variant (idempotent)."""
    _moment_class()


def path_integrator(max_depth: int = DEFAULT_MAX_DEPTH):
    """A plain Mitsuba ``path`` integrator (the peer of the moment render)."""
    import mitsuba as mi

    ensure_variant()
    return mi.load_dict({"type": "path", "max_depth": int(max_depth)})


def _construct(cls: type, **properties: Any):
    """An instance of one of jaxden's Python integrator classes from Mitsuba properties."""
    import mitsuba as mi

    props = mi.Properties()
    for key, value in properties.items():
        props[key] = value
    logger = mi.logger()
    level = logger.log_level()
    if mi.variant().startswith("scalar"):
        # Mitsuba warns that Python integrators are slow in scalar mode; jaxden's variant
        # notice has already said so once.
        logger.set_log_level(mi.LogLevel.Error)
    try:
        return cls(props)
    finally:
        logger.set_log_level(level)


def moment_integrator(inner=None, max_depth: int = DEFAULT_MAX_DEPTH, emission: bool = True,
                      statistics: bool = False):
    """A ``jaxden_moment`` integrator wrapping ``inner`` (an mi.SamplingIntegrator).

    With ``inner=None`` it wraps ``path`` with ``max_depth``. Rendered with a box filter, the
    image has 12 channels (MOMENT_CHANNELS): m1 (R, G, B), m2 (R, G, B), m11 (RG, GB, BR),
    then the emission (R, G, B), see the module docstring; 9 with ``emission=False``; 21 with
    ``statistics=True`` (STATISTICS_AOVS follow the emission).
    """
    integrator = _construct(_moment_class(), max_depth=int(max_depth), emission=bool(emission),
                            statistics=bool(statistics))
    if inner is not None:
        integrator.inner = inner
    return integrator


def aov_integrator():
    """Mitsuba's ``aov`` integrator returning the 10 feature channels of FEATURE_CHANNELS.

    albedo: diffuse reflectance of the first hit; normal: world-space shading normal; depth:
    distance along the ray; position: world-space hit point. All are 0 on misses.
    """
    import mitsuba as mi

    ensure_variant()
    return mi.load_dict({"type": "aov", "aovs": FEATURE_AOVS})


_chain_classes: dict[str, type] = {}  # variant -> ChainFeatures class of that variant


def _and_not(a, b):
    """``a & ~b`` for Dr.Jit masks and for the Python bools of scalar variants."""
    return (a and not b) if isinstance(b, bool) else a & ~b


def _chain_class() -> type:
    """The ChainFeatures class for the current variant (see the module docstring)."""
    import drjit as dr
    import mitsuba as mi

    variant = ensure_variant()
    if variant in _chain_classes:
        return _chain_classes[variant]

    class ChainFeatures(mi.SamplingIntegrator):
        """First-hit depth and position; albedo and normal of the first non-delta hit.

        Output: the albedo as the film's RGB, then normal (3), depth (1), position (3) as
        AOVs: the channel order of FEATURE_CHANNELS. Property: ``max_specular``.
        """

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.max_specular = int(props.get("max_specular", DEFAULT_MAX_SPECULAR))
            # Mitsuba's own aov integrator gives albedo and shading normal at the first hit
            # of each ray of the chain: its shading normal includes bump and normal maps
            # (a BSDF's perturbed frame, not reachable from Python).
            self.first_hit = mi.load_dict({"type": "aov", "aovs": FEATURE_AOVS})

        def sample(self, scene, sampler, ray, medium=None, active=True):
            # Importance mode: no radiance scaling (1 / eta^2) on refraction, so a chain
            # through clear glass keeps weight 1.
            context = mi.BSDFContext(mi.TransportMode.Importance)
            ray = mi.RayDifferential3f(ray)
            si = scene.ray_intersect(ray, active)
            alive = mi.Bool(active) & si.is_valid()
            albedo = mi.Spectrum(0.0)
            normal = mi.Vector3f(0.0)
            weight = mi.Spectrum(1.0)
            # dr.select and _and_not rather than masked assignment and ~: the same code runs
            # on lanes (llvm) and on one sample with Python bools (scalar variants).
            for bounce in range(self.max_specular + 1):
                _, _, hit = self.first_hit.sample(scene, sampler, ray, medium, alive)
                if bounce == 0:
                    depth, position = hit[6], hit[7:10]
                if isinstance(alive, bool) and not alive:
                    break  # scalar variants: one sample, and no surface left to query
                bsdf = si.bsdf(ray)
                flags = bsdf.flags()
                delta_only = _and_not(mi.has_flag(flags, mi.BSDFFlags.Delta),
                                      mi.has_flag(flags, mi.BSDFFlags.Smooth))
                stop = _and_not(alive, delta_only)
                albedo = dr.select(stop, weight * mi.Spectrum(hit[0], hit[1], hit[2]), albedo)
                normal = dr.select(stop, mi.Vector3f(hit[3], hit[4], hit[5]), normal)
                alive = alive & delta_only
                if bounce == self.max_specular:
                    break
                sample, lobe_weight = bsdf.sample(context, si, sampler.next_1d(alive),
                                                  sampler.next_2d(alive), alive)
                alive = alive & dr.any(lobe_weight > 0.0)
                weight = dr.select(alive, weight * lobe_weight, weight)
                ray = mi.RayDifferential3f(si.spawn_ray(si.to_world(sample.wo)))
                si = scene.ray_intersect(ray, alive)
                alive = alive & si.is_valid()
            aovs = [normal.x, normal.y, normal.z, depth, *position]
            return albedo, mi.Bool(True), aovs

        def aov_names(self):
            return ["nn.X", "nn.Y", "nn.Z", "dd.Y", "pp.X", "pp.Y", "pp.Z"]

        def to_string(self):
            return f"ChainFeatures[max_specular={self.max_specular}]"

    mi.register_integrator(CHAIN_PLUGIN, lambda props: ChainFeatures(props))
    _chain_classes[variant] = ChainFeatures
    return ChainFeatures


def chain_features_integrator(max_specular: int = DEFAULT_MAX_SPECULAR):
    """The ``jaxden_features_chain`` integrator: FEATURE_CHANNELS with albedo and normal of
    the first non-delta hit (see the module docstring)."""
    return _construct(_chain_class(), max_specular=int(max_specular))


def features_integrator(aux: str = "first-hit"):
    """The feature integrator of an ``aux`` mode (one of AUX_MODES)."""
    if aux == "first-hit":
        return aov_integrator()
    if aux == "specular-chain":
        return chain_features_integrator()
    raise ValueError(f"aux must be one of {', '.join(AUX_MODES)}, got {aux!r}")


def covariance_of_mean(m1, m11, variance, spp: int):
    """Covariance of the pixel mean between channels (R, G), (G, B), (B, R) from the first
    moments m1 (..., 3), the cross moments m11 = mean(L_R L_G), mean(L_G L_B), mean(L_B L_R)
    and the variance of the mean (:func:`variance_of_mean`): ``(m11 - m1_a m1_b) / (spp - 1)``
    in float64, clipped to ``|cov| <= sqrt(var_a var_b)`` (round-off, and the variance's own
    clipping at 0, can otherwise break it by a few ulp)."""
    import numpy as np

    from jaxden.frame import covariance_bound

    if spp < 2:
        raise ValueError(f"covariance of the mean needs spp >= 2, got {spp}")
    m1 = np.asarray(m1, dtype=np.float64)
    cross = (np.asarray(m11, dtype=np.float64) - m1 * np.roll(m1, -1, axis=-1)) / (spp - 1)
    bound = covariance_bound(variance)
    return np.clip(cross, -bound, bound)


#: Relative round-off of a float32 film's per-pixel average of one raw moment (a sum of up to
#: MAX_SPP_PER_PASS samples: ~sqrt(1024) x 2^-24 ~ 2e-6, with a margin).
RAW_MOMENT_ROUNDOFF = 2e-5


def boxcox_statistics(s1, s2, s3, count):
    """``Frame.boxcox`` (..., 9) from the raw moments mean(s^k), k = 1, 2, 3, of the
    ``count`` samples' s = 2 sqrt(L) (STATISTICS_AOVS, averaged over the passes in float64):
    the mean of the Box-Cox(0.5) value b = s - 2, and its central moments
    m2 = mean((b - mean b)^2) = s2 - s1^2 and m3 = mean((b - mean b)^3)
    = s3 - 3 s1 s2 + 2 s1^3 (M2 / n and M3 / n of Welford's online form).

    Round-off: the raw moments come from float32 films, each good to RAW_MOMENT_ROUNDOFF of
    its size; m2 is clipped at 0, and m3 is set to 0 where it is below what the cancellation
    can leave (RAW_MOMENT_ROUNDOFF x (|s3| + 3 |s1 s2| + 2 |s1|^3)) and clipped to the largest
    skewness ``count`` samples can have, (n - 2) / sqrt(n - 1) (their exact bound), so round-off
    never makes StatMC's skewness correction large. All in float64; returns float32."""
    import numpy as np

    s1, s2, s3 = (np.asarray(v, np.float64) for v in (s1, s2, s3))
    n = np.asarray(count, np.float64)
    second = np.maximum(s2 - s1 * s1, 0.0)
    third = s3 - 3.0 * s1 * s2 + 2.0 * s1 ** 3
    noise = RAW_MOMENT_ROUNDOFF * (np.abs(s3) + 3.0 * np.abs(s1 * s2) + 2.0 * np.abs(s1) ** 3)
    third = np.where(np.abs(third) <= noise, 0.0, third)
    largest = np.maximum(n - 2.0, 0.0) / np.sqrt(np.maximum(n - 1.0, 1.0)) * second ** 1.5
    third = np.clip(third, -largest, largest)
    return np.concatenate([s1 - 2.0, second, third], axis=-1).astype(np.float32)


def boxcox_of_samples(samples, axis: int = 0):
    """``Frame.boxcox`` (..., 9) of explicit samples of L (..., 3) along ``axis``, in float64:
    the slow, obvious form (tests, and the statistics of K renders' means, whose samples are
    the K means: :func:`jaxden.data.merge.merge_renders`)."""
    import numpy as np

    b = 2.0 * np.sqrt(np.maximum(np.asarray(samples, np.float64), 0.0)) - 2.0
    mean = b.mean(axis=axis)
    deviation = b - np.expand_dims(mean, axis)
    return np.concatenate([mean, np.square(deviation).mean(axis=axis),
                           (deviation ** 3).mean(axis=axis)], axis=-1).astype(np.float32)


def variance_of_mean(m1, m2, spp: int):
    """Variance of the pixel mean from first and second moments of ``spp`` samples.

    ``(m2 - m1^2) / (spp - 1)`` clipped at 0 (float round-off can make it slightly negative),
    computed in float64. Shapes: any, m1 and m2 alike. Needs spp >= 2.
    """
    import numpy as np

    if spp < 2:
        raise ValueError(f"variance of the mean needs spp >= 2, got {spp}")
    m1 = np.asarray(m1, dtype=np.float64)
    m2 = np.asarray(m2, dtype=np.float64)
    return np.maximum(m2 - m1 * m1, 0.0) / (spp - 1)
