"""StatMC (jaxden.denoise.statmc) against slow NumPy references written from BASELINES.md 7.

The references loop over pixels and the disk window with the authors' formulas (Johnson's
skewness correction, the discriminator, the all-channel test, replicate clamping, the Gaussian
weights) in float64; the jitted functions must agree to float32 round-off. Inputs are drawn so
that no pair of pixels lies within round-off of the test's threshold, and so that the test
accepts some neighbours and rejects others. Frames are about 11 x 9, so the file runs in
seconds.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.stats import t as student_t

from jaxden.denoise import load_denoiser, make_denoiser
from jaxden.denoise import statmc as S
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

EPS32 = float(np.finfo(np.float32).eps)
#: Test settings with wide feature weights, so that accepted neighbours weigh visibly.
WIDE = S.StatMCConfig(radius=3, sigma_spatial=2.0, sigma_albedo=0.5, sigma_normal=1.0)
WIDE_MOON = S.MoonCIConfig(radius=3, sigma_spatial=2.0, sigma_albedo=0.5, sigma_normal=1.0)


# ------------------------------------------------------------------------ NumPy references
def np_t(significance, df):
    """The authors' LUT read: df clipped to [1, 1024]."""
    return student_t.ppf(1.0 - significance / 2.0, min(max(round(float(df)), 1), 1024))


def np_statistics(boxcox, n, significance):
    """(mu', D) per pixel from the Box-Cox statistics, float64, as stat_denoiser.cu."""
    boxcox = np.asarray(boxcox, np.float64)
    mean, m2, m3 = boxcox[..., 0:3] * 1.0, boxcox[..., 3:6] * n, boxcox[..., 6:9] * n
    s2 = m2 / (n - 1)
    corrected = mean + np.where(s2 > EPS32, (m3 / n) / (6.0 * np.where(s2 > EPS32, s2, 1) * n),
                                0.0)
    t = np_t(significance, 2 * n - 2)
    return corrected, corrected ** 2 - t * t * m2 / (n * (n - 1))


def np_filter(color, albedo, normal, accept, cfg):
    """sum w colour / sum w over the disk, replicate clamping, the centre weighing 1;
    ``accept(y, x, qy, qx) -> bool``."""
    h, w = color.shape[:2]
    r = cfg.radius
    out = np.zeros((h, w, 3))
    for y in range(h):
        for x in range(w):
            num, den = np.array(color[y, x], np.float64), 1.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if dy * dy + dx * dx > r * r or (dy, dx) == (0, 0):
                        continue
                    qy, qx = min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)
                    if not accept(y, x, qy, qx):
                        continue
                    e = -(dy * dy + dx * dx) / (2 * cfg.sigma_spatial ** 2)
                    if albedo is not None:
                        e -= np.sum((albedo[y, x] - albedo[qy, qx]) ** 2) / (
                            2 * cfg.sigma_albedo ** 2)
                    if normal is not None:
                        e -= np.sum((normal[y, x] - normal[qy, qx]) ** 2) / (
                            2 * cfg.sigma_normal ** 2)
                    num += np.exp(e) * color[qy, qx]
                    den += np.exp(e)
            out[y, x] = num / den
    return out


def np_statmc(frame, n, cfg):
    corrected, disc = np_statistics(frame.boxcox, n, cfg.significance)
    accept = lambda y, x, qy, qx: bool(np.all(
        disc[y, x] + disc[qy, qx] <= 2 * corrected[y, x] * corrected[qy, qx]))
    return np_filter(np.float64(frame.color), frame.albedo, frame.normal, accept, cfg)


def np_moon(frame, n, cfg):
    t = np_t(cfg.significance, n - 1)
    half = t * np.sqrt(np.float64(frame.variance))
    color = np.float64(frame.color)
    accept = lambda y, x, qy, qx: bool(np.all(np.abs(color[qy, qx] - color[y, x])
                                              <= half[y, x]))
    return np_filter(color, frame.albedo, frame.normal, accept, cfg)


def window_margins(frame, n, cfg, moon=False):
    """(smallest relative distance of any window pair from the test's threshold, share of
    the pairs accepted)."""
    h, w = frame.color.shape[:2]
    if moon:
        t = np_t(cfg.significance, n - 1)
        left = lambda y, x, qy, qx: np.abs(np.float64(frame.color[qy, qx])
                                           - frame.color[y, x])
        right = lambda y, x, qy, qx: t * np.sqrt(np.float64(frame.variance[y, x]))
    else:
        corrected, disc = np_statistics(frame.boxcox, n, cfg.significance)
        left = lambda y, x, qy, qx: disc[y, x] + disc[qy, qx]
        right = lambda y, x, qy, qx: 2 * corrected[y, x] * corrected[qy, qx]
    smallest, accepted, total = np.inf, 0, 0
    r = cfg.radius
    for y in range(h):
        for x in range(w):
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if dy * dy + dx * dx > r * r or (dy, dx) == (0, 0):
                        continue
                    qy, qx = min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)
                    a, b = left(y, x, qy, qx), right(y, x, qy, qx)
                    if (qy, qx) != (y, x):  # a clamped copy of the centre ties exactly
                        smallest = min(smallest, float(np.min(
                            np.abs(a - b) / (np.abs(a) + np.abs(b) + 1e-12))))
                    accepted += bool(np.all(a <= b))
                    total += 1
    return smallest, accepted / total


# ------------------------------------------------------------------------ inputs
def random_frame(seed=0, height=11, width=9, n=8.0, features=("albedo", "normal")):
    """A small frame whose Box-Cox statistics make the test accept about half the pairs:
    two levels of transformed means, noise, positive M2, signed M3."""
    rng = np.random.default_rng(seed)
    shape = (height, width, 3)
    level = np.where(rng.random((height, width, 1)) < 0.5, 0.0, 0.6)
    mean_b = level + 0.15 * rng.standard_normal(shape)
    m2 = rng.uniform(0.01, 0.04, shape)  # M2 / n
    m3 = rng.uniform(-0.01, 0.01, shape)  # M3 / n
    boxcox = np.concatenate([mean_b, m2, m3], axis=-1).astype(np.float32)
    color = rng.gamma(2.0, 0.5, shape).astype(np.float32)
    variance = (0.05 * color ** 2 + 0.01).astype(np.float32)
    extra = {}
    if "albedo" in features:
        extra["albedo"] = rng.uniform(0.2, 0.8, shape).astype(np.float32)
    if "normal" in features:
        normal = rng.standard_normal(shape)
        extra["normal"] = (normal / np.linalg.norm(normal, axis=-1, keepdims=True)
                           ).astype(np.float32)
    return Frame(color=color, variance=variance, boxcox=boxcox, spp=np.float32(n), **extra)


@pytest.fixture(scope="module")
def jitted():
    """One compiled function per (variant, config) for the whole file."""
    cache = {}

    def get(name, config):
        key = (name, config)
        if key not in cache:
            function = S.statmc if name == "statmc" else S.statmc_moon
            cache[key] = jax.jit(lambda frame, f=function: f(frame, config))
        return cache[key]

    return get


# ------------------------------------------------------------------------ statistics
@pytest.mark.parametrize("significance", [0.005, 0.002])
def test_t_table_matches_scipy(significance):
    table = S.t_quantile_table(significance)
    assert table.shape == (1024,) and table.dtype == np.float32
    for df in (1, 2, 3, 7, 30, 255, 1024):
        assert_allclose(table[df - 1], student_t.ppf(1 - significance / 2, df), rtol=1e-6)
    assert S.t_quantile_table(significance) is table  # computed once
    # Read as the authors: df - 1, the last entry beyond the table, the first below it.
    df = jnp.asarray([1.0, 6.0, 1024.0, 5000.0, 0.0])
    assert_allclose(S.t_quantile(significance, df), table[[0, 5, 1023, 1023, 0]])


def test_skewness_correction_and_discriminator_are_welchs_test():
    rng = np.random.default_rng(3)
    n = 12.0
    shape = (200, 2, 3)
    boxcox = np.concatenate([rng.normal(0, 1, shape), rng.uniform(0.01, 1, shape),
                             rng.uniform(-0.5, 0.5, shape)], axis=-1).astype(np.float32)
    boxcox[0, 0, 3:6] = 0.0  # s^2 = 0: no correction
    corrected = np.asarray(S.skewness_corrected_mean(boxcox, n), np.float64)
    b = np.float64(boxcox)
    s2 = b[..., 3:6] * n / (n - 1)
    expected = b[..., 0:3] + (b[..., 6:9] * n / n) / (6 * np.maximum(s2, 1e-30) * n)
    expected[0, 0] = b[0, 0, 0:3]
    assert_allclose(corrected, expected, rtol=1e-5, atol=1e-6)
    t = S.t_quantile(0.005, 2 * n - 2)
    assert_allclose(t, student_t.ppf(1 - 0.005 / 2, 2 * n - 2), rtol=1e-6)
    disc = np.asarray(S.discriminator(jnp.asarray(corrected, jnp.float32), boxcox, n, t),
                      np.float64)
    # D_p + D_q <= 2 mu'_p mu'_q  <=>  (mu'_p - mu'_q)^2 <= t^2 (s_p^2 / n + s_q^2 / n)
    p, q = corrected[:, 0], corrected[:, 1]
    welch = (p - q) ** 2 - float(t) ** 2 * (s2[:, 0] / n + s2[:, 1] / n)
    discriminated = disc[:, 0] + disc[:, 1] - 2 * p * q
    assert_allclose(discriminated, welch, rtol=1e-4, atol=1e-5)
    assert 0.1 < np.mean(welch <= 0) < 0.9  # both outcomes occur


# ------------------------------------------------------------------------ the filter
@pytest.mark.parametrize("features", [("albedo", "normal"), ("normal",), ()])
def test_statmc_matches_numpy(features, jitted):
    frame = random_frame(seed=1, features=features)
    smallest, accepted = window_margins(frame, 8.0, WIDE)
    assert smallest > 1e-5 and 0.2 < accepted < 0.8, (smallest, accepted)
    out = jitted("statmc", WIDE)(frame)
    assert out.shape == frame.color.shape and out.dtype == jnp.float32
    assert_allclose(out, np_statmc(frame, 8.0, WIDE), rtol=2e-5, atol=2e-6)


def test_statmc_default_weights_match_numpy(jitted):
    frame = random_frame(seed=2)
    frame = frame.replace(albedo=0.5 + 0.01 * (frame.albedo - 0.5),
                          normal=frame.normal * 0.0 + np.float32([0, 0, 1])
                          + 0.03 * frame.normal)
    config = S.StatMCConfig(radius=3)
    assert window_margins(frame, 8.0, config)[0] > 1e-5
    assert_allclose(jitted("statmc", config)(frame), np_statmc(frame, 8.0, config),
                    rtol=2e-5, atol=2e-6)


@pytest.mark.parametrize("features", [("albedo", "normal"), ()])
def test_moon_matches_numpy(features, jitted):
    frame = random_frame(seed=4, features=features)
    smallest, accepted = window_margins(frame, 8.0, WIDE_MOON, moon=True)
    assert smallest > 1e-5 and 0.2 < accepted < 0.8, (smallest, accepted)
    assert_allclose(jitted("moon", WIDE_MOON)(frame), np_moon(frame, 8.0, WIDE_MOON),
                    rtol=2e-5, atol=2e-6)


def test_constant_image_comes_back_unchanged(jitted):
    frame = random_frame(seed=5)
    constant = frame.replace(
        color=np.full_like(frame.color, 0.7),
        boxcox=np.broadcast_to(np.float32([0.2, 0.3, 0.4, 0.1, 0.1, 0.1, 0.01, 0, -0.01]),
                               frame.boxcox.shape).copy(),
        variance=np.full_like(frame.variance, 0.01))
    for name, config in (("statmc", WIDE), ("moon", WIDE_MOON)):
        assert_allclose(jitted(name, config)(constant), constant.color, rtol=1e-6)


def test_huge_n_with_distinct_means_accepts_nothing(jitted):
    frame = random_frame(seed=6).replace(spp=np.float32(1e6))
    distinct = np.float32(np.arange(99 * 3).reshape(11, 9, 3) * 0.01)
    frame = frame.replace(boxcox=np.concatenate([distinct, frame.boxcox[..., 3:]], axis=-1),
                          color=frame.color + distinct,
                          variance=np.full_like(frame.variance, 1e-8))
    assert_allclose(jitted("statmc", WIDE)(frame), frame.color, rtol=1e-6)
    assert_allclose(jitted("moon", WIDE_MOON)(frame), frame.color, rtol=1e-6)


def test_fewer_than_two_samples_return_the_colour(jitted):
    frame = random_frame(seed=7).replace(spp=np.float32(1.0))
    assert_allclose(jitted("statmc", WIDE)(frame), frame.color)
    assert_allclose(jitted("moon", WIDE_MOON)(frame), frame.color)
    # n from variance_dof + 1 where it is set: dof 0 is one render, nothing to test
    merged = frame.replace(spp=np.float32(64.0), variance_dof=np.float32(0.5))
    assert_allclose(jitted("statmc", WIDE)(merged), frame.color)


def test_batch_dimensions_with_their_own_n(jitted):
    a, b = random_frame(seed=8, n=8.0), random_frame(seed=9, n=3.0)
    batch = jax.tree_util.tree_map(lambda *x: np.stack(x), a, b)
    assert batch.color.shape == (2, 11, 9, 3) and batch.spp.shape == (2,)
    for name, config in (("statmc", WIDE), ("moon", WIDE_MOON)):
        function = jitted(name, config)
        out = function(batch)
        assert out.shape == (2, 11, 9, 3)
        assert_allclose(out[0], function(a), rtol=1e-6, atol=1e-7)
        assert_allclose(out[1], function(b), rtol=1e-6, atol=1e-7)
    assert not np.allclose(jitted("statmc", WIDE)(b), jitted("statmc", WIDE)(
        b.replace(spp=np.float32(8.0))))  # n matters


def test_bands_and_unrolling_reproduce_the_whole_frame(monkeypatch, jitted):
    frame = random_frame(seed=10)
    whole = jitted("statmc", WIDE)(frame)
    monkeypatch.setattr(S, "BAND_PIXELS", 20)  # 5 bands of 3 rows for 11 rows: a ragged end
    monkeypatch.setattr(S, "UNROLL_FROM", 0)  # and the unrolled loop of large frames
    assert_allclose(jax.jit(lambda f: S.statmc(f, WIDE))(frame), whole, rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------------ statistics of samples
def sample_statistics(samples):
    """Frame fields of per-pixel samples ``(n, H, W, 3)``: mean colour, variance of the mean,
    and boxcox (mean of b, M2 / n, M3 / n of b = (sqrt(L) - 1) / 0.5)."""
    n = samples.shape[0]
    b = S.boxcox_transform(samples)
    mean_b = b.mean(axis=0)
    centred = b - mean_b
    boxcox = np.concatenate([mean_b, (centred ** 2).mean(0), (centred ** 3).mean(0)], -1)
    return Frame(color=samples.mean(0).astype(np.float32),
                 variance=(samples.var(0, ddof=1) / n).astype(np.float32),
                 boxcox=boxcox.astype(np.float32), spp=np.float32(n))


def test_filter_averages_within_regions_not_across():
    """Two regions of gamma-distributed samples (means 1 and 1.6, 256 per pixel): StatMC
    accepts no neighbour across the edge (a colour replaced by the region's label comes back
    as the label: the test reads only the statistics) and averages within each region."""
    rng = np.random.default_rng(11)
    height, width, n = 10, 16, 256
    right = np.arange(width)[None, :, None] >= width // 2
    means = np.where(right, 1.6, 1.0) * np.ones((height, width, 3))
    shape = 4.0
    samples = rng.gamma(shape, means / shape, (n, height, width, 3))
    frame = sample_statistics(samples)
    config = S.StatMCConfig(radius=4)
    statmc = jax.jit(lambda f: S.statmc(f, config))
    label = np.broadcast_to(right, frame.color.shape).astype(np.float32)
    assert_allclose(statmc(frame.replace(color=label)), label, atol=1e-6)
    out = np.asarray(statmc(frame))
    error_in, error_out = (np.sqrt(np.mean((image - means) ** 2)) for image in (frame.color,
                                                                                 out))
    assert error_out < 0.35 * error_in, (error_out, error_in)
    moon = np.asarray(jax.jit(lambda f: S.statmc_moon(f, S.MoonCIConfig(radius=4)))(frame))
    assert np.sqrt(np.mean((moon - means) ** 2)) < 0.5 * error_in
    assert np.max(np.abs(moon - means)) < 0.2  # nothing of the other region


def test_approximate_boxcox_is_close_for_mild_noise():
    rng = np.random.default_rng(12)
    n, shape = 4000, 20.0
    means = rng.uniform(0.5, 2.0, (2, 3, 3))
    frame = sample_statistics(rng.gamma(shape, means / shape, (n, 2, 3, 3)))
    approx = S.approximate_boxcox(frame.color, frame.variance, n)
    assert approx.shape == (2, 3, 9) and approx.dtype == np.float32
    assert_allclose(approx[..., :3], frame.boxcox[..., :3], atol=0.01)
    assert_allclose(approx[..., 3:6], frame.boxcox[..., 3:6], rtol=0.1)


# ------------------------------------------------------------------------ registry and errors
def test_registered_denoisers():
    frame = random_frame(seed=13)
    den = make_denoiser("statmc", S.StatMCConfig(radius=2))
    assert den.fields_read() == ("boxcox", "albedo", "normal")
    assert den.tile_spec().radius == 2
    out = den(frame)
    assert out.shape == frame.color.shape and np.isfinite(out).all()
    assert load_denoiser("statmc").config == S.STATMC_PAPER
    moon = load_denoiser("statmc-moon")
    assert moon.config == S.MOON_CI_PAPER and moon.config.significance == 0.002
    assert moon.fields_read() == ("variance", "albedo", "normal")
    without = frame.replace(boxcox=None, albedo=None)  # the Moon test needs no statistics
    assert_allclose(make_denoiser("statmc-moon", WIDE_MOON)(without),
                    np_moon(without, 8.0, WIDE_MOON), rtol=2e-5, atol=2e-6)
    # SURE differentiates through the colour: StatMC's weights do not depend on it, so the
    # filter is linear in the colour and its jvp is the filter of the tangent.
    tangent = np.random.default_rng(13).standard_normal(frame.color.shape).astype(np.float32)
    function = den.function()
    _, jvp = jax.jvp(lambda c: function(frame.replace(color=c)), (frame.color,), (tangent,))
    assert_allclose(jvp, function(frame.replace(color=tangent)), rtol=1e-4, atol=1e-5)


def test_missing_fields_are_named():
    frame = random_frame(seed=14)
    # The registry's check names the field and its EXR channels; the function says too how
    # to render them.
    with pytest.raises(FrameError, match=r"statmc.*boxcox.*boxcox\.mean\.R"):
        make_denoiser("statmc")(frame.replace(boxcox=None))
    with pytest.raises(FrameError, match=r"boxcox.*boxcox\.mean\.R.*statistics=True.*"
                                         r"statistics = true"):
        S.statmc(frame.replace(boxcox=None))
    with pytest.raises(FrameError, match="sample count n.*neither spp nor variance_dof"):
        S.statmc(frame.replace(spp=None))
    with pytest.raises(FrameError, match=r"shape \(\.\.\., H, W, 9\)"):
        S.statmc(frame.replace(boxcox=frame.boxcox[..., :6]))
    with pytest.raises(FrameError, match=r"statmc-moon.*variance.*variance\.R"):
        make_denoiser("statmc-moon")(frame.replace(variance=None))
    with pytest.raises(FrameError, match="neither spp nor variance_dof"):
        S.statmc_moon(frame.replace(spp=None))


@pytest.mark.parametrize("field, value, expected", [
    ("radius", -1, "radius"), ("significance", 0.0, "significance"),
    ("significance", 1.0, "significance"), ("significance", 1.5, "significance"),
    ("sigma_spatial", 0.0, "sigma_spatial"), ("sigma_albedo", -1.0, "sigma_albedo"),
    ("sigma_normal", 0.0, "sigma_normal"), ("radius", 2.5, "radius")])
def test_config_errors_name_the_field(field, value, expected):
    for cls in (S.StatMCConfig, S.MoonCIConfig):
        with pytest.raises(ConfigError, match=expected):
            cls(**{field: value})
    assert dataclasses.replace(S.StatMCConfig(), radius=0).radius == 0


# ------------------------------------------------------------------------ the benchmark's input
def test_bench_gives_statmc_statistics_and_the_others_their_file(tmp_path, monkeypatch):
    """``jaxden bench denoisers``: StatMC gets Box-Cox statistics (approximated: the bench
    frame has none), every other command the file it had."""
    import sys

    from jaxden.bench import BENCH_FRAME_ENV, denoisers, frames
    from jaxden.io.exr import read_frame, write_frame
    from jaxden.render.synthetic import synthetic_render

    frame = synthetic_render("bench", 4, seed=1, size=(16, 12))
    with_statistics = denoisers.with_statistics(frame)
    assert_allclose(with_statistics.boxcox,
                    S.approximate_boxcox(frame.color, frame.variance, 4))
    assert denoisers.with_statistics(with_statistics) is with_statistics
    assert "statmc" in denoisers.BASELINES and "statmc_moon" in denoisers.BASELINES
    write_frame(tmp_path / "frame.exr", frame)
    monkeypatch.setenv(BENCH_FRAME_ENV, str(tmp_path / "frame.exr"))

    def copy_to(target):  # a stand-in command: keeps the file it is given
        code = "import shutil, sys; shutil.copy(sys.argv[1], sys.argv[2])"
        return lambda source, out: [sys.executable, "-c", code, source, str(target)]

    monkeypatch.setitem(frames.COMMANDS, "denoisers", {"oidn": copy_to(tmp_path / "oidn.exr"),
                                                       "statmc": copy_to(tmp_path / "s.exr")})
    result = frames.frame_bench("denoisers", True, [(16, 12)])
    assert result["statmc_16x12_status"] == 0 and result["oidn_16x12_status"] == 0
    assert read_frame(tmp_path / "oidn.exr").boxcox is None
    seen = read_frame(tmp_path / "s.exr")
    assert_allclose(seen.boxcox, with_statistics.boxcox, rtol=1e-6)
    assert_allclose(seen.color, frame.color)
