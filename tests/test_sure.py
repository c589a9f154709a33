"""Tests of jaxden.sure: exact identities, method agreement, options, errors.

Statistical (unbiasedness) tests are in test_sure_properties.py. Here every check is exact
or deterministic: divergence terms are compared with analytic J b for the very probes
``draw_probes`` reproduces. Tolerances: float32 jvp vs analytic rtol 1e-5; finite differences
in float32 at eps = 1e-2 on linear denoisers rtol 2e-3 (the realised probe differs from the
drawn one by <= ulp(x) / eps ~ 1e-5 |x|, and differences of outputs round at ~1e-7 / 1e-2).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame
from jaxden.sure.stein import SureResult, draw_probes, sure, sure_blackbox, sure_from_parts

DN = ("NHWC", "HWIO", "NHWC")


def key(seed: int):
    """rbg keys: XLA:CPU compiles threefry draws several times slower, and each distinct
    configuration here is a new compilation. ``sure`` takes any key type; the threefry
    default is exercised in test_sure_works_inside_jit_and_vmap."""
    return jax.random.key(seed, impl="rbg")


def conv(image, kernel):
    """'SAME' zero-padded convolution of (..., H, W, C) with an HWIO kernel."""
    lead = image.shape[:-3]
    flat = image.reshape((-1,) + image.shape[-3:])
    out = jax.lax.conv_general_dilated(flat, kernel, (1, 1), "SAME", dimension_numbers=DN,
                                       precision=jax.lax.Precision.HIGHEST)
    return out.reshape(lead + out.shape[-3:])


def linear_filter(kernel, frame):
    return conv(frame.color, kernel)


def small_net(params, frame):
    w1, w2 = params
    return conv(jnp.tanh(conv(frame.color, w1)), w2) + 0.5 * frame.color


def pixelwise_with_albedo(scale, frame):
    """y = scale * albedo * x + albedo^2: J is diagonal, scale * albedo (albedo not perturbed)."""
    return scale * frame.albedo * frame.color + frame.albedo**2


@pytest.fixture
def frame():
    rng = np.random.default_rng(0)
    return Frame(
        color=rng.uniform(0.0, 2.0, (6, 7, 3)).astype(np.float32),
        variance=rng.uniform(1e-3, 5e-2, (6, 7, 3)).astype(np.float32),
        albedo=rng.uniform(0.1, 0.9, (6, 7, 3)).astype(np.float32),
    )


@pytest.fixture
def kernel():
    return jnp.asarray(np.random.default_rng(1).normal(0, 0.3, (3, 3, 3, 3)).astype(np.float32))


@pytest.fixture
def net_params():
    rng = np.random.default_rng(2)
    return (jnp.asarray(rng.normal(0, 0.4, (3, 3, 3, 6)).astype(np.float32)),
            jnp.asarray(rng.normal(0, 0.3, (3, 3, 6, 3)).astype(np.float32)))


def test_result_parts_are_consistent(frame, net_params):
    result = sure(small_net, frame, key(0), params=net_params)
    assert isinstance(result, SureResult)
    for field in result:
        assert field.shape == (6, 7, 3) and field.dtype == jnp.float32
    y = small_net(net_params, frame)
    np.testing.assert_allclose(result.denoised, y, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(result.residual_sq, (y - frame.color) ** 2, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(
        result.sure,
        sure_from_parts(frame.color, result.denoised, frame.variance, result.divergence_term),
        rtol=1e-6, atol=1e-7,
    )
    np.testing.assert_allclose(result.mse(), result.sure.mean(), rtol=1e-6)


def test_jvp_divergence_is_exact_for_pixelwise_linear_and_ignores_albedo(frame):
    probe_key = key(3)
    result = sure(pixelwise_with_albedo, frame, probe_key, params=jnp.float32(1.5))
    b = draw_probes(probe_key, frame.variance, 4)
    expected = jnp.mean(b * b, axis=0) * 1.5 * frame.albedo
    np.testing.assert_allclose(result.divergence_term, expected, rtol=1e-5)


def test_jvp_divergence_is_exact_for_a_convolution(frame, kernel):
    probe_key = key(4)
    result = sure(linear_filter, frame, probe_key, params=kernel)
    b = draw_probes(probe_key, frame.variance, 4)
    expected = jnp.mean(b * conv(b, kernel), axis=0)
    np.testing.assert_allclose(result.divergence_term, expected, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("method, batches", [("jvp", (None, 1, 3, 64)), ("fd", (None, 3))])
def test_probe_batch_does_not_change_the_result(frame, net_params, method, batches):
    """Same probes whatever the chunking (3 does not divide K = 4: a padded, masked chunk).
    fd tolerance: XLA rounds a batched conv differently, and fd divides that by eps = 1e-2."""
    results = [
        sure(small_net, frame, key(5), method=method, eps=1e-2,
             params=net_params, probe_batch=batch)
        for batch in batches
    ]
    rtol = 1e-5 if method == "jvp" else 1e-3
    for other in results[1:]:
        for a, b in zip(results[0], other):
            np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * np.abs(a).max())


@pytest.mark.parametrize("scheme", ["forward", "central"])
def test_fd_matches_jvp_for_linear_denoisers(frame, kernel, scheme):
    probe_key = key(6)
    exact = sure(linear_filter, frame, probe_key, params=kernel)
    fd = sure(linear_filter, frame, probe_key, method="fd", eps=1e-2, fd_scheme=scheme,
              params=kernel)
    scale = np.abs(exact.divergence_term).max()
    np.testing.assert_allclose(fd.divergence_term, exact.divergence_term, rtol=2e-3,
                               atol=2e-3 * scale)
    np.testing.assert_allclose(fd.denoised, exact.denoised, rtol=1e-6, atol=1e-6)


def test_fd_on_albedo_denoiser_ignores_albedo(frame):
    probe_key = key(7)
    fd = sure(pixelwise_with_albedo, frame, probe_key, method="fd", eps=1e-2,
              params=jnp.float32(1.5))
    b = draw_probes(probe_key, frame.variance, 4)
    expected = jnp.mean(b * b, axis=0) * 1.5 * frame.albedo
    np.testing.assert_allclose(fd.divergence_term, expected, rtol=2e-3, atol=1e-7)


def test_blackbox_matches_jax_with_common_probes(frame, kernel):
    probe_key = key(8)
    probes = np.asarray(draw_probes(probe_key, frame.variance, 4))
    kernel_np = np.asarray(kernel)
    calls = []

    def denoise_np(f):
        assert isinstance(f.color, np.ndarray) and f.color.dtype == np.float32
        calls.append(1)
        return np.asarray(conv(jnp.asarray(f.color), kernel_np))

    exact = sure(linear_filter, frame, probe_key, params=kernel)
    for scheme, expected_calls in (("forward", 5), ("central", 9)):
        calls.clear()
        bb = sure_blackbox(denoise_np, frame, probes=probes, eps=1e-2, fd_scheme=scheme)
        assert len(calls) == expected_calls
        assert all(isinstance(a, np.ndarray) and a.dtype == np.float32 for a in bb)
        scale = np.abs(exact.divergence_term).max()
        np.testing.assert_allclose(bb.divergence_term, exact.divergence_term, rtol=2e-3,
                                   atol=2e-3 * scale)
        np.testing.assert_allclose(bb.sure, exact.sure, rtol=2e-3, atol=4e-3 * scale)


def test_blackbox_seed_is_reproducible(frame):
    def den(f):
        return np.tanh(f.color)

    a = sure_blackbox(den, frame, rng=3, eps=1e-3)
    b = sure_blackbox(den, frame, rng=np.random.default_rng(3), eps=1e-3)
    c = sure_blackbox(den, frame, rng=4, eps=1e-3)
    np.testing.assert_array_equal(a.sure, b.sure)
    assert not np.array_equal(a.sure, c.sure)


def test_sure_works_inside_jit_and_vmap(frame, net_params):
    key = jax.random.key(9)
    eager = sure(small_net, frame, key, params=net_params)
    jitted = jax.jit(lambda f, p: sure(small_net, f, key, params=p).sure)(frame, net_params)
    np.testing.assert_allclose(jitted, eager.sure, rtol=1e-5, atol=1e-7)
    colors = jnp.stack([frame.color, frame.color + 0.1])
    batched = jax.vmap(
        lambda c: sure(small_net, frame.replace(color=c), key, params=net_params).sure
    )(colors)
    np.testing.assert_allclose(batched[0], eager.sure, rtol=1e-5, atol=1e-7)


def test_batched_frame_with_leading_dimension(kernel):
    rng = np.random.default_rng(10)
    frame = Frame(color=rng.uniform(0, 1, (2, 5, 6, 3)).astype(np.float32),
                  variance=np.full((2, 5, 6, 3), 0.01, np.float32))
    probe_key = key(11)
    result = sure(linear_filter, frame, probe_key, params=kernel)
    assert result.sure.shape == (2, 5, 6, 3) and result.mse().shape == (2,)
    b = draw_probes(probe_key, frame.variance, 4)
    np.testing.assert_allclose(result.divergence_term, jnp.mean(b * conv(b, kernel), axis=0),
                               rtol=1e-5, atol=1e-8)


def test_probe_batch_bounds_jvp_memory(net_params):
    """Compiled temp memory (XLA's own accounting, not a timing): chunked jvp probes must
    need clearly less than all probes at once. A 3-layer ReLU net, 32 channels, 256 x 256,
    K = 4 (only compiled, never run): measured 75 MiB at probe_batch=4, 22 MiB at 1.
    (XLA's accounting depends on the net: for the 2-layer tanh net above chunking saves
    nothing; the bound is a property of ReLU-style nets, which the denoisers are.)"""
    from jaxden.sure.stein import _sure_core

    def deep_net(params, frame):
        w1, w2, w3 = params
        hidden = jax.nn.relu(conv(jax.nn.relu(conv(frame.color, w1)), w2))
        return conv(hidden, w3)

    frame = Frame(color=jnp.zeros((256, 256, 3)), variance=jnp.ones((256, 256, 3)))
    wide = (jnp.zeros((3, 3, 3, 32)), jnp.zeros((3, 3, 32, 32)), jnp.zeros((3, 3, 32, 3)))

    def temp_bytes(batch):
        lowered = _sure_core.lower(deep_net, wide, frame, key(0), 1e-4,
                                   has_params=True, num_probes=4, method="jvp",
                                   fd_scheme="forward",
                                   probe_batch=batch)
        return lowered.compile().memory_analysis().temp_size_in_bytes

    assert temp_bytes(4) > 2.0 * temp_bytes(1)


# ------------------------------------------------------------------------ errors


def test_missing_variance_is_a_clear_error(frame):
    no_var = frame.replace(variance=None)
    with pytest.raises(FrameError, match="SURE needs the variance of the pixel mean"):
        sure(lambda f: f.color, no_var, key(0))
    with pytest.raises(FrameError, match="SURE needs the variance of the pixel mean"):
        sure_blackbox(lambda f: f.color, no_var)


def test_bad_variance_values_are_clear_errors(frame):
    bad = np.array(frame.variance)
    bad[1, 2, 0] = -0.5
    with pytest.raises(FrameError, match=r"sure: variance must be >= 0.*\(1, 2, 0\)"):
        sure(lambda f: f.color, frame.replace(variance=bad), key(0))
    bad[1, 2, 0] = np.nan
    with pytest.raises(FrameError, match="sure: field 'variance' has 1 non-finite"):
        sure(lambda f: f.color, frame.replace(variance=bad), key(0))
    with pytest.raises(FrameError, match="sure_blackbox: field 'variance'"):
        sure_blackbox(lambda f: f.color, frame.replace(variance=bad))
    # The authors' repair policy: NaN variance -> 0 (that pixel then has no noise term).
    repaired = sure(lambda f: f.color, frame.replace(variance=bad), key(0),
                    nonfinite="zero")
    assert np.isfinite(np.asarray(repaired.sure)).all()
    assert float(repaired.divergence_term[1, 2, 0]) == 0.0


def test_shape_and_option_errors(frame):
    with pytest.raises(FrameError, match=r"denoiser returned shape \(6, 7, 1\)"):
        sure(lambda f: f.color[..., :1], frame, key(0))
    with pytest.raises(FrameError, match="sure_blackbox: the denoiser returned shape"):
        sure_blackbox(lambda f: f.color[:3], frame)
    with pytest.raises(FrameError, match="expected a jaxden Frame"):
        sure(lambda f: f.color, frame.color, key(0))
    with pytest.raises(FrameError, match="variance"):
        sure(lambda f: f.color, frame.replace(variance=frame.variance[:3]), key(0))
    with pytest.raises(FrameError, match="probes have shape"):
        sure_blackbox(lambda f: f.color, frame, probes=np.zeros((2, 3, 3, 3)))
    for kwargs, match in (
        (dict(method="adjoint"), "method"),
        (dict(num_probes=0), "num_probes"),
        (dict(eps=0.0), "eps"),
        (dict(probe_batch=0), "probe_batch"),
        (dict(fd_scheme="backward"), "fd_scheme"),
    ):
        with pytest.raises(ConfigError, match=match):
            sure(lambda f: f.color, frame, key(0), **kwargs)


@pytest.mark.parametrize("tonemap", ["reinhard_gamma", "gamma"])
def test_jvp_sure_of_wskp_is_finite_on_black_pixels_with_zero_variance(tonemap):
    """Low-spp renders have pixels whose samples are all 0 (colour 0, variance 0). The WSKP
    input tone map t ** (1/2.2) has an infinite slope at 0; jvp then gave inf * 0 = NaN there
    (seen on the test set at 2-64 spp). With the floor the SURE map is finite everywhere and
    equals (y - x)^2 at pixels whose variance is 0 (no probe moves them)."""
    from jaxden.denoise.registry import make_denoiser
    from jaxden.denoise.nn.wskp import WSKPConfig
    from jaxden.sure.denoiser import denoise_with_sure

    rng = np.random.default_rng(0)
    h, w = 16, 16
    color = rng.gamma(1.0, 0.5, (h, w, 3)).astype(np.float32)
    variance = (0.05 * color).astype(np.float32)
    color[4:8, 4:8] = 0.0
    variance[4:8, 4:8] = 0.0
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1.0
    frame = Frame(color=color, variance=variance, albedo=np.full((h, w, 3), 0.5, np.float32),
                  normal=normal, depth=np.ones((h, w, 1), np.float32), spp=2)
    config = WSKPConfig(num_layers=2, width=4, kernel_sizes=(3, 5), tonemap=tonemap)
    model = make_denoiser("wskp", config, key=jax.random.PRNGKey(0))
    result, _ = denoise_with_sure(model, frame, jax.random.PRNGKey(1), num_probes=2)
    sure_map = np.asarray(result.sure)
    assert np.all(np.isfinite(sure_map))
    residual = (np.asarray(result.denoised) - color) ** 2
    np.testing.assert_allclose(sure_map[4:8, 4:8], residual[4:8, 4:8], rtol=1e-5, atol=1e-9)


# ------------------------------------------------------------------ colour covariance


def _random_covariance(rng, shape, correlation=0.9):
    """Per-pixel PSD 3 x 3 covariances: a shared brightness term plus independent noise, as
    Monte Carlo colour has; returns (variance, covariance (RG, GB, BR))."""
    scale = rng.uniform(0.05, 0.3, shape + (3,))
    shared = np.sqrt(correlation) * scale
    own = np.sqrt(1 - correlation) * scale
    sigma = shared[..., :, None] * shared[..., None, :] + np.eye(3) * own[..., None, :] ** 2
    variance = np.stack([sigma[..., i, i] for i in range(3)], axis=-1)
    covariance = np.stack([sigma[..., 0, 1], sigma[..., 1, 2], sigma[..., 2, 0]], axis=-1)
    return variance, covariance, sigma


def test_colour_factor_reproduces_the_covariance_and_tolerates_singular_pixels():
    """L L^T = Sigma per pixel; a channel without variance gets a zero column (no NaN); zero
    covariance gives diag(sqrt(var)), so the probes equal the per-channel ones exactly."""
    from jaxden.sure.stein import colour_factor

    rng = np.random.default_rng(0)
    variance, covariance, sigma = _random_covariance(rng, (5, 4))
    variance[0, 0, 1] = 0.0  # a black channel: its row and column of Sigma vanish
    covariance[0, 0, 0] = covariance[0, 0, 1] = 0.0
    sigma[0, 0, 1, :] = sigma[0, 0, :, 1] = 0.0
    l00, l10, l11, l20, l21, l22 = colour_factor(variance, covariance, xp=np)
    zero = np.zeros_like(l00)
    factor = np.stack([np.stack([l00, zero, zero], -1), np.stack([l10, l11, zero], -1),
                       np.stack([l20, l21, l22], -1)], axis=-2)
    assert np.isfinite(factor).all()
    np.testing.assert_allclose(factor @ np.swapaxes(factor, -1, -2), sigma, rtol=1e-10,
                               atol=1e-15)
    var32 = jnp.asarray(variance, jnp.float32)
    plain = draw_probes(key(2), var32, 4)
    assert np.array_equal(np.asarray(draw_probes(key(2), var32, 4, jnp.zeros_like(var32))),
                          np.asarray(plain))


def test_covariance_probes_make_sure_unbiased_for_a_channel_mixing_denoiser():
    """F(x) = A x per pixel with A mixing the channels, correlated colour noise: the
    divergence term estimates (A Sigma)_ii with covariance probes. Pixel-and-probe means over
    64 x 64 pixels and 64 probes (seed 3) are within 2 % of the analytic value (standard error
    about 0.3 %); the per-channel probes miss sum_{j != i} A_ij Sigma_ji, here over 30 % of
    it, and are rejected by the same check."""
    rng = np.random.default_rng(3)
    variance, covariance, sigma = _random_covariance(rng, (64, 64))
    mix = jnp.asarray([[0.5, 0.3, 0.2], [0.25, 0.5, 0.25], [0.2, 0.3, 0.5]], jnp.float32)

    def denoise(frame):
        return jnp.einsum("ij,...j->...i", mix, frame.color)

    color = rng.uniform(0.5, 2.0, (64, 64, 3)).astype(np.float32)
    expected = np.einsum("ij,...ji->...i", np.asarray(mix, np.float64), sigma).mean(axis=(0, 1))
    frame = Frame(color=color, variance=variance.astype(np.float32),
                  covariance=covariance.astype(np.float32))
    full = sure(denoise, frame, key(4), num_probes=64).divergence_term
    diag = sure(denoise, frame.replace(covariance=None), key(4), num_probes=64).divergence_term
    full_mean = np.asarray(full, np.float64).mean(axis=(0, 1))
    diag_mean = np.asarray(diag, np.float64).mean(axis=(0, 1))
    np.testing.assert_allclose(full_mean, expected, rtol=0.02)
    assert (np.abs(diag_mean / expected - 1) > 0.3).all()
    # the black-box path draws its probes from the same factor (float64, NumPy generator)
    box = sure_blackbox(lambda f: np.einsum("ij,...j->...i", np.asarray(mix), f.color), frame,
                        num_probes=64, rng=5, eps=1e-2).divergence_term
    np.testing.assert_allclose(np.asarray(box, np.float64).mean(axis=(0, 1)), expected,
                               rtol=0.02)
