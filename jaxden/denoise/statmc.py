"""StatMC: "A Statistical Approach to Monte Carlo Denoising" (Sakai et al., SIGGRAPH Asia
2024), in pure JAX, and its "Moon CI" variant.

A training-free cross-bilateral filter whose neighbours must pass a pairwise statistical test
first, as the authors' CUDA denoiser (``stat_denoiser.cu``; BASELINES.md section 7;
docs/departures.md, "StatMC", lists where jaxden departs from it):

1. **Statistics.** Per pixel the frame carries ``boxcox`` (:class:`jaxden.frame.Frame`): the
   mean of the Box-Cox(0.5) transformed samples ``b = (sqrt(L) - 1) / 0.5`` and its central
   moments ``M2 / n``, ``M3 / n``, per channel; ``n = frame.statistics_count()``.
2. **Skewness-corrected mean** (Johnson): ``mu' = mean + mu3 / (6 s^2 n)`` with ``mu3 = M3 / n``
   and ``s^2 = M2 / (n - 1)``; no correction where ``s^2 <= FLT_EPSILON``.
3. **Discriminator** ``D = mu'^2 - t^2 M2 / (n (n - 1))``, ``t`` the two-sided Student-t
   quantile at ``significance`` (0.005) with ``2n - 2`` degrees of freedom, read from a
   1024-entry table (:func:`t_quantile_table`) as the authors do.
4. **Test.** A neighbour ``q`` of ``p`` is accepted iff ``D_p + D_q <= 2 mu'_p mu'_q`` in all
   three channels: ``(mu'_p - mu'_q)^2 <= t^2 (s_p^2 / n + s_q^2 / n)``, Welch's test that
   the two pixels' (transformed) means are equal.
5. **Filter.** Over the disk ``dx^2 + dy^2 <= radius^2`` (20 px; borders clamped), an accepted
   neighbour weighs ``exp(-d^2 / (2 sigma_s^2) - |albedo_p - albedo_q|^2 / (2 sigma_albedo^2)
   - |normal_p - normal_q|^2 / (2 sigma_normal^2))``, the centre 1, and the output is
   ``sum w colour_q / sum w`` of the frame's (untransformed) mean colour. A frame without
   albedo or without normal drops that term (the authors' list of G-buffers is a setting).

The Moon CI variant (the authors' ``-DMEMFNC=1``, after Moon et al. 2013's confidence
interval) skips steps 1-4: ``q`` is accepted iff ``|colour_q - colour_p| <= t sqrt(variance_p)``
in all three channels (``frame.variance``, the variance of the mean ``M2 / (n (n - 1))``;
``t`` at ``n - 1`` degrees of freedom and significance 0.002); it runs on any frame with a
variance.

Registered: ``statmc`` (:class:`StatMCConfig`) and ``statmc-moon`` (:class:`MoonCIConfig`),
pure, jitted by the registry, differentiable in the colour (the tests are hard thresholds:
their derivative is 0 almost everywhere). ``statmc(frame, config)`` and
``statmc_moon(frame, config)`` are the functions.

Shapes: images ``(..., H, W, C)`` (leading batch dimensions allowed); ``n`` a scalar or of
shape ``(...)``, may be traced. Units: linear radiance, pixels. With ``n < 2`` there is no
variance, no neighbour passes and the colour comes back as it is. The filter loops over the
window's offsets (``lax.scan``), accumulating numerator and denominator: its memory is a few
copies of the frame, whatever the radius.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.config import bounded, check_fields
from jaxden.denoise.registry import DenoiserDef, register
from jaxden.errors import FrameError
from jaxden.frame import BOXCOX_LAMBDA, Frame
from jaxden.tiling import TileSpec

#: Entries of the t-quantile table; entry i holds df = i + 1 (the authors' LUT).
T_TABLE_SIZE = 1024
#: float32's machine epsilon (C's FLT_EPSILON): below it s^2 counts as 0 (no skew correction).
FLT_EPSILON = float(np.finfo(np.float32).eps)
#: How to give a frame its statistics (named in the errors of a frame without them).
HOW_TO_RENDER = ("render them with render_frame(..., statistics=True) or a dataset config "
                 "with statistics = true")


@dataclasses.dataclass(frozen=True)
class StatMCConfig:
    """StatMC's parameters; the defaults are the authors' (``scenes/render-denoise.pbrt``,
    BASELINES.md 7.2-7.3).

    ``radius``: the filter window, the disk ``dx^2 + dy^2 <= radius^2`` (pixels; 0: no
    filtering); ``significance``: the two-sided significance level of the pairwise test (its
    t quantile); ``sigma_spatial`` (pixels), ``sigma_albedo``, ``sigma_normal``: the widths of
    the Gaussian weights on the distance and on the albedo and normal differences.
    """

    radius: int = bounded(20, low=0, unit="pixels")
    significance: float = bounded(0.005, low=0, low_open=True, high=1, high_open=True)
    sigma_spatial: float = bounded(10.0, low=0, low_open=True, unit="pixels")
    sigma_albedo: float = bounded(0.02, low=0, low_open=True)
    sigma_normal: float = bounded(0.1, low=0, low_open=True)

    def __post_init__(self) -> None:
        check_fields(self)


@dataclasses.dataclass(frozen=True)
class MoonCIConfig(StatMCConfig):
    """The Moon CI variant's parameters: StatMC's, with the significance the paper uses for
    it (0.002, BASELINES.md 7.2)."""

    significance: float = bounded(0.002, low=0, low_open=True, high=1, high_open=True)


#: The authors' settings of the two tests.
STATMC_PAPER = StatMCConfig()
MOON_CI_PAPER = MoonCIConfig()


# ------------------------------------------------------------------------------ statistics
@functools.cache
def _t_table(significance: float) -> np.ndarray:
    from scipy.stats import t as student_t

    df = np.arange(1, T_TABLE_SIZE + 1, dtype=np.float64)
    table = student_t.ppf(1.0 - significance / 2.0, df).astype(np.float32)
    table.setflags(write=False)
    return table


def t_quantile_table(significance: float) -> np.ndarray:
    """The two-sided Student-t quantiles ``t_{1 - significance / 2}(df)`` for df = 1 ... 1024,
    float32 ``(1024,)``, entry ``i`` at ``df = i + 1`` (the authors' 1024-entry LUT; computed
    once per significance with SciPy, read-only)."""
    return _t_table(float(significance))


def t_quantile(significance: float, df) -> jax.Array:
    """The table's quantile at ``df`` degrees of freedom (any shape, may be traced): entry
    ``df - 1``, the last entry (df = 1024) beyond the table and the first below it, as the
    authors index it. ``df`` is rounded to the nearest integer."""
    index = jnp.clip(jnp.round(jnp.asarray(df, jnp.float32)).astype(jnp.int32) - 1, 0,
                     T_TABLE_SIZE - 1)
    return jnp.asarray(t_quantile_table(significance))[index]


def _count(n, ndim: int) -> jax.Array:
    """``n`` (scalar or ``(...)``) as float32 broadcastable against ``(..., H, W, C)``."""
    n = jnp.asarray(n, jnp.float32)
    return jnp.reshape(n, n.shape + (1,) * (ndim - n.ndim)) if n.ndim else n


def skewness_corrected_mean(boxcox: jax.Array, n) -> jax.Array:
    """Johnson's skewness-corrected mean of the transformed samples,
    ``mu' = mean + mu3 / (6 s^2 n)`` with ``mu3 = M3 / n`` (``boxcox[..., 6:9]``) and
    ``s^2 = M2 / (n - 1)`` (``M2 / n = boxcox[..., 3:6]``); 0 correction where ``s^2 <=
    FLT_EPSILON``. ``boxcox (..., H, W, 9)``, ``n`` scalar or ``(...)`` (>= 2) ->
    ``(..., H, W, 3)``."""
    boxcox = jnp.asarray(boxcox, jnp.float32)
    n = _count(n, boxcox.ndim)
    mean, second, third = boxcox[..., 0:3], boxcox[..., 3:6], boxcox[..., 6:9]
    s2 = second * n / (n - 1.0)
    usable = s2 > FLT_EPSILON
    correction = third / (6.0 * jnp.where(usable, s2, 1.0) * n)
    return mean + jnp.where(usable, correction, 0.0)


def discriminator(corrected_mean: jax.Array, boxcox: jax.Array, n, t) -> jax.Array:
    """``D = mu'^2 - t^2 M2 / (n (n - 1))`` per channel: ``corrected_mean (..., H, W, 3)``
    (:func:`skewness_corrected_mean`), ``boxcox (..., H, W, 9)``, ``n`` and ``t`` scalar or
    ``(...)`` -> ``(..., H, W, 3)``. Two pixels pass Welch's test where ``D_p + D_q <=
    2 mu'_p mu'_q``."""
    boxcox = jnp.asarray(boxcox, jnp.float32)
    n, t = _count(n, boxcox.ndim), _count(t, boxcox.ndim)
    variance_of_mean = boxcox[..., 3:6] / (n - 1.0)  # (M2 / n) / (n - 1)
    return corrected_mean * corrected_mean - t * t * variance_of_mean


def boxcox_transform(radiance):
    """The Box-Cox(0.5) transform of radiance samples, ``(sqrt(L) - 1) / 0.5`` (NumPy or
    JAX arrays; L >= 0)."""
    return (radiance ** BOXCOX_LAMBDA - 1.0) / BOXCOX_LAMBDA


def approximate_boxcox(color, variance, n) -> np.ndarray:
    """Box-Cox statistics ``(..., H, W, 9)`` (the layout of ``Frame.boxcox``) that a frame
    with mean ``color`` and variance of the mean ``variance`` (``(..., H, W, 3)``) would have
    on average, to second order in the noise (the delta method), were its ``n`` samples per
    pixel (scalar or ``(...)``) gamma-distributed: for benchmarks and smoke runs of frames
    rendered without statistics. Not what a renderer measures (a few path-traced samples are
    nothing like gamma-distributed), and never used by the denoisers. NumPy, float32."""
    color = np.maximum(np.asarray(color, np.float64), 0.0)
    n = np.asarray(n, np.float64)
    n = np.reshape(n, n.shape + (1,) * (color.ndim - n.ndim))
    sample_variance = np.maximum(np.asarray(variance, np.float64), 0.0) * n  # of one sample
    mean = np.maximum(color, 1e-3)  # the expansion's centre: keeps dark pixels finite
    # b(L) = 2 sqrt(L) - 2: b' = L^-1/2, b'' = -L^-3/2 / 2; a gamma sample has mu3 = 2 s^4 / m,
    # so b's third central moment is b'^3 mu3 + 3 b'^2 b'' s^4 = s^4 m^-5/2 / 2.
    mean_b = np.maximum(2.0 * np.sqrt(color) - 2.0 - sample_variance / (4.0 * mean ** 1.5),
                        -2.0)
    variance_b = sample_variance / mean
    third_b = np.minimum(0.5 * sample_variance ** 2 / mean ** 2.5,
                         2.0 * variance_b ** 1.5)  # a guard: skewness at most 2
    # The expected sample moments about the sample mean: M2 / n and M3 / n are biased low.
    statistics = np.concatenate([mean_b, variance_b * (n - 1) / n,
                                 third_b * (n - 1) * (n - 2) / (n * n)], axis=-1)
    return statistics.astype(np.float32)


# ------------------------------------------------------------------------------ the filter
def disk_offsets(radius: int) -> list[tuple[int, int]]:
    """The window's offsets ``(dy, dx)`` with ``dy^2 + dx^2 <= radius^2``, the centre left out
    (it enters with weight 1), row by row."""
    return [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)
            if dy * dy + dx * dx <= radius * radius and (dy, dx) != (0, 0)]


#: Pixels per band of the window loop (:func:`disk_filter`), so that a band's planes stay in
#: a CPU's cache (1280 x 720, radius 20, 2 cores: the whole frame at once 3.6 CPU s, bands of
#: 2^17 pixels 2.0 CPU s, of 2^15 2.5 CPU s).
BAND_PIXELS = 1 << 17
#: Offsets per iteration of the window loop (``lax.scan``'s unroll): XLA then fuses several
#: offsets' updates of the accumulators into one pass over the band (on a CPU, 320 x 180,
#: radius 20: unroll 1 0.36 s, 4 0.15 s, 8 0.12 s). Bands under UNROLL_FROM pixels are not
#: unrolled: they run in milliseconds either way and compile twice as fast.
UNROLL, UNROLL_FROM = 8, 1 << 14


def _planes(image) -> list[jax.Array]:
    """``(..., H, W, C)`` -> C planes ``(..., H, W)`` float32: the window loop works plane by
    plane, every operation elementwise over whole planes (on a CPU ~3x faster than the
    channels-last layout, whose 3-channel minor axis does not vectorise)."""
    image = jnp.asarray(image, jnp.float32)
    return [image[..., c] for c in range(image.shape[-1])]


def _guides(frame: Frame, config: StatMCConfig) -> list[jax.Array]:
    """The albedo and normal planes scaled by ``1 / (sqrt(2) sigma)``, so that the squared
    differences of two pixels' planes, summed, are the weight's exponent: 0, 3 or 6 planes
    ``(..., H, W)`` by what the frame has."""
    planes = []
    for image, sigma in ((frame.albedo, config.sigma_albedo),
                         (frame.normal, config.sigma_normal)):
        if image is not None:
            planes += [plane * float(1.0 / (np.sqrt(2.0) * sigma)) for plane in _planes(image)]
    return planes


def disk_filter(color: list[jax.Array], guides: list[jax.Array], tests: list[jax.Array],
                accept: Callable[[list[jax.Array], list[jax.Array], list[jax.Array]], jax.Array],
                radius: int, sigma_spatial: float) -> list[jax.Array]:
    """The tested cross-bilateral filter over the disk of ``radius``, on planes ``(..., H, W)``.

    ``color``: the 3 colour planes averaged; ``guides``: scaled feature planes (the weight is
    ``exp(-d^2 / (2 sigma_spatial^2) - sum_g (g_p - g_q)^2)``); ``tests``: the planes that the
    test reads: ``accept(tests_p, tests_q, color_q) -> bool (..., h, W)`` with the centre's
    and the neighbour's tests and the neighbour's colour. Neighbours outside the image are the
    nearest border pixel (replicate clamping). The centre weighs 1. Returns the 3 filtered
    planes.

    How: the frame is cut into bands of rows (about :data:`BAND_PIXELS` pixels each, so that a
    band's planes stay in the CPU's cache), ``lax.map`` over the bands; in each, one
    ``lax.scan`` over the offsets of :func:`disk_offsets` (unrolled :data:`UNROLL` times in
    bands of :data:`UNROLL_FROM` pixels or more)
    carries the numerator and the denominator. Nothing of the window's size is stored."""
    offsets = disk_offsets(radius)
    if not offsets:
        return color
    planes = [*color, *guides, *tests]
    n_guides = len(guides)
    shape = planes[0].shape
    lead, (height, width) = shape[:-2], shape[-2:]
    bands = max(1, min(height, -(-math.prod(shape) // BAND_PIXELS)))
    band = -(-height // bands)
    # Rows past the bottom (up to bands * band) repeat the last row, as the clamp does.
    pad = [(0, 0)] * len(lead) + [(radius, radius + bands * band - height), (radius, radius)]
    padded = jnp.stack([jnp.pad(plane, pad, mode="edge") for plane in planes])
    dys = jnp.asarray([dy for dy, _ in offsets], jnp.int32)
    dxs = jnp.asarray([dx for _, dx in offsets], jnp.int32)
    spatial = jnp.asarray([-(dy * dy + dx * dx) / (2.0 * sigma_spatial ** 2)
                           for dy, dx in offsets], jnp.float32)
    zero = jnp.zeros((), jnp.int32)
    zeros = (zero,) * len(lead)

    def filter_band(top):
        slab = jax.lax.dynamic_slice(
            padded, (zero, *zeros, top, zero),
            (len(planes), *lead, band + 2 * radius, width + 2 * radius))
        slab = [slab[k] for k in range(len(planes))]
        centre = [jax.lax.dynamic_slice(plane, (*zeros, radius, radius),
                                        (*lead, band, width)) for plane in slab]
        color_p = centre[:3]
        guides_p = centre[3:3 + n_guides]
        tests_p = centre[3 + n_guides:]

        def body(carry, xs):
            numerator, denominator = carry
            dy, dx, log_spatial = xs
            q = [jax.lax.dynamic_slice(plane, (*zeros, radius + dy, radius + dx),
                                       (*lead, band, width)) for plane in slab]
            color_q, guides_q, tests_q = q[:3], q[3:3 + n_guides], q[3 + n_guides:]
            exponent = log_spatial
            for guide_p, guide_q in zip(guides_p, guides_q, strict=True):
                exponent = exponent - jnp.square(guide_p - guide_q)
            passed = accept(tests_p, tests_q, color_q)
            weight = jnp.where(passed, jnp.exp(exponent), 0.0)
            numerator = tuple(total + weight * c
                              for total, c in zip(numerator, color_q, strict=True))
            return (numerator, denominator + weight), None

        init = (tuple(color_p), jnp.ones_like(color_p[0]))
        unroll = UNROLL if math.prod(shape[:-2]) * band * width >= UNROLL_FROM else 1
        (numerator, denominator), _ = jax.lax.scan(body, init, (dys, dxs, spatial),
                                                   unroll=unroll)
        return jnp.stack([total / denominator for total in numerator])

    out = jax.lax.map(filter_band, jnp.arange(bands, dtype=jnp.int32) * band)
    # (bands, 3, ..., band, W) -> 3 planes (..., H, W)
    out = jnp.moveaxis(out, 0, -3)
    out = jnp.reshape(out, (3, *lead, bands * band, width))[..., :height, :]
    return [out[c] for c in range(3)]


def _statistics_count(frame: Frame, who: str):
    n = frame.statistics_count()
    if n is None:
        raise FrameError(f"{who} needs the statistics' sample count n, but the frame has "
                         f"neither spp nor variance_dof")
    return n


def require_statistics(frame: Frame, who: str = "denoiser 'statmc'") -> None:
    """FrameError when the frame lacks ``boxcox`` (naming its EXR channels and how to render
    them), has it in the wrong shape, or lacks its sample count."""
    try:
        frame.require("boxcox", who=who)
    except FrameError as error:
        raise FrameError(f"{error}: StatMC's test reads the per-pixel statistics of the "
                         f"Box-Cox-transformed samples; {HOW_TO_RENDER}") from None
    if np.shape(frame.boxcox)[-1:] != (9,) or np.shape(frame.boxcox)[:-1] != frame.shape:
        raise FrameError(f"{who}: boxcox must have shape (..., H, W, 9) beside a colour of "
                         f"{np.shape(frame.color)}, got {np.shape(frame.boxcox)}")
    _statistics_count(frame, who)


def _filtered(frame: Frame, config: StatMCConfig, tests, accept, n) -> jax.Array:
    """The filter on ``frame``'s colour, returned as ``(..., H, W, 3)``; the colour itself
    where ``n < 2``."""
    color = jnp.asarray(frame.color, jnp.float32)
    out = jnp.stack(disk_filter(_planes(color), _guides(frame, config), tests, accept,
                                config.radius, config.sigma_spatial), axis=-1)
    return jnp.where(_count(n, out.ndim) >= 2.0, out, color)


def _all_channels(passed: list[jax.Array]) -> jax.Array:
    return passed[0] & passed[1] & passed[2]


def statmc(frame: Frame, config: StatMCConfig = STATMC_PAPER) -> jax.Array:
    """StatMC (module docstring): ``frame`` with colour and ``boxcox`` ``(..., H, W, C)``,
    ``spp`` or ``variance_dof`` (n), and, used when present, albedo and normal -> the filtered
    colour ``(..., H, W, 3)``, linear radiance. Pure; jit it with ``config`` static."""
    require_statistics(frame)
    n = _statistics_count(frame, "denoiser 'statmc'")
    safe_n = jnp.maximum(jnp.asarray(n, jnp.float32), 2.0)  # n < 2: see _filtered
    t = t_quantile(config.significance, 2.0 * safe_n - 2.0)
    corrected = skewness_corrected_mean(frame.boxcox, safe_n)
    disc = discriminator(corrected, frame.boxcox, safe_n, t)

    def accept(tests_p, tests_q, color_q):
        (corrected_p, disc_p), (corrected_q, disc_q) = (
            (tests[:3], tests[3:]) for tests in (tests_p, tests_q))
        return _all_channels([dp + dq <= 2.0 * cp * cq for dp, dq, cp, cq in
                              zip(disc_p, disc_q, corrected_p, corrected_q, strict=True)])

    return _filtered(frame, config, [*_planes(corrected), *_planes(disc)], accept, n)


def statmc_moon(frame: Frame, config: MoonCIConfig = MOON_CI_PAPER) -> jax.Array:
    """StatMC's Moon CI variant (module docstring): ``frame`` with colour and variance
    ``(..., H, W, 3)``, ``spp`` or ``variance_dof`` (n), and, used when present, albedo and
    normal -> ``(..., H, W, 3)``. Needs no ``boxcox``. Pure; jit it with ``config`` static."""
    who = "denoiser 'statmc-moon'"
    frame.require("variance", who=f"{who} (its test is the confidence interval of the "
                                   f"pixel mean)")
    n = _statistics_count(frame, who)
    safe_n = jnp.maximum(jnp.asarray(n, jnp.float32), 2.0)
    t = _count(t_quantile(config.significance, safe_n - 1.0), frame.color.ndim)
    variance = jnp.maximum(jnp.asarray(frame.variance, jnp.float32), 0.0)
    # The centre's colour and half-width; the neighbour's colour is the filter's own.
    tests = [*_planes(frame.color), *_planes(t * jnp.sqrt(variance))]

    def accept(tests_p, tests_q, color_q):
        color_p, half_width = tests_p[:3], tests_p[3:]
        return _all_channels([jnp.abs(cq - cp) <= h for cq, cp, h in
                              zip(color_q, color_p, half_width, strict=True)])

    return _filtered(frame, config, tests, accept, n)


# ------------------------------------------------------------------------------ registration
register(DenoiserDef(
    name="statmc",
    description="StatMC (Sakai et al. 2024): cross-bilateral filter over neighbours that pass "
                "Welch's test on Box-Cox sample statistics (JAX, no training; needs boxcox)",
    config_cls=StatMCConfig,
    required=lambda config: ("boxcox",),
    optional=lambda config: ("albedo", "normal"),
    apply=lambda params, config, frame: statmc(frame, config),
    tiling=lambda config: TileSpec(radius=config.radius),
))

register(DenoiserDef(
    name="statmc-moon",
    description="StatMC's Moon CI variant: cross-bilateral filter over neighbours inside the "
                "pixel mean's confidence interval (JAX, no training)",
    config_cls=MoonCIConfig,
    required=lambda config: ("variance",),
    optional=lambda config: ("albedo", "normal"),
    apply=lambda params, config, frame: statmc_moon(frame, config),
    tiling=lambda config: TileSpec(radius=config.radius),
))
