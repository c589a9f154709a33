"""Statistical properties of jaxden.sure: unbiasedness, divergence expectation, eps -> 0.

Setup: 8 x 8 x 3 images; clean image mu and per-pixel variance drawn by hypothesis; noisy
x = mu + sqrt(var) n, n ~ N(0, I), with fresh probes per draw. Everything is seeded
(hypothesis ``derandomize=True``; JAX keys from hypothesis-drawn integers), so every run
does the same thing and a failure reproduces. The Monte Carlo loops use ``rbg`` keys
(``key(seed, impl="rbg")``): vmapped threefry draws compile ~3x slower on XLA:CPU, and
``sure`` takes any key type.

The target. Per noise draw i, D_i = mean_pixels SURE(x_i) - mean_pixels (F(x_i) - mu)^2 (the
draws and the statistic are jaxden.testing's: ``sure_draws``, ``z_score``). SURE is unbiased
for E_x ||F(x) - mu||^2 (over the noise AND the probes), so E[D] = 0. Comparing the mean of
D with 0, rather than mean SURE with a separately estimated mean squared error, uses common
random numbers: D has much lower variance than either term. z-test: |mean D| <= 4.5 stderr
(stderr = sample std / sqrt(N)), N = DRAWS = 512 draws per example; a correct estimator
fails one example with probability 7e-6 (normal approximation; D is a mean of 192 weakly
dependent terms). The same test must reject a broken estimator: dropping the divergence
term (bias -2 mean var J_ii) gives |z| > 10.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jaxden.frame import Frame
from jaxden.sure.stein import draw_probes, sure, sure_blackbox
from jaxden.testing import sure_draws, z_score

SHAPE = (8, 8, 3)
DRAWS = 512
Z_LIMIT = 4.5
DN = ("NHWC", "HWIO", "NHWC")
SETTINGS = settings(max_examples=8, deadline=None, derandomize=True)


def conv(image, kernel):
    out = jax.lax.conv_general_dilated(image[None], kernel, (1, 1), "SAME", dimension_numbers=DN,
                                       precision=jax.lax.Precision.HIGHEST)
    return out[0]


# ------------------------------------------------------------------ denoisers (params, frame)


def linear_filter(kernel, frame):
    """y = K * x, K an HWIO 3x3 kernel mixing channels; J_ii = K[1, 1, c, c]."""
    return conv(frame.color, kernel)


# The identity and zero denoisers as kernels of linear_filter (one compiled function for all
# three: each new denoise_fn costs a compilation of the whole Monte Carlo loop).
IDENTITY = jnp.zeros((3, 3, 3, 3), jnp.float32).at[1, 1].set(jnp.eye(3))
ZERO = jnp.zeros((3, 3, 3, 3), jnp.float32)
BOX = jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32) / 9.0, (3, 3, 3, 3))


def soft_threshold(tau, frame):
    """Shrink x towards its 3x3 box mean m by tau: m + sign(d) max(|d| - tau, 0), d = x - m.
    Non-linear, not pixelwise, only weakly differentiable (kinks at |d| = tau)."""
    mean = conv(frame.color, BOX.astype(frame.color.dtype))
    d = frame.color - mean
    return mean + jnp.sign(d) * jnp.maximum(jnp.abs(d) - tau, 0.0)


def relu_net(params, frame):
    """A small random conv net: 3 -> 8 (ReLU) -> 3, plus a skip; piecewise linear."""
    w1, w2 = params
    return conv(jax.nn.relu(conv(frame.color, w1)), w2) + 0.5 * frame.color


def tanh_net(params, frame):
    """Smooth (for the eps -> 0 test)."""
    w1, w2 = params
    return conv(jnp.tanh(conv(frame.color, w1)), w2) + 0.5 * frame.color


def net_params(seed: int, dtype=np.float32, hidden: int = 8):
    rng = np.random.default_rng(seed)
    return (jnp.asarray(rng.normal(0, 0.5, (3, 3, 3, hidden)).astype(dtype)),
            jnp.asarray(rng.normal(0, 0.3, (3, 3, hidden, 3)).astype(dtype)))


# ------------------------------------------------------------------ Monte Carlo machinery


def draw_statistics(denoise_fn, params, clean, var, seed: int, eps, *, method="jvp",
                    num_probes=4):
    """jaxden.testing.sure_draws over DRAWS noisy frames around ``clean`` (one batch: one
    compiled function per denoiser, whatever the example's arrays)."""
    return sure_draws(denoise_fn, Frame(color=np.asarray(clean), variance=np.asarray(var)),
                      draws=DRAWS, batch=DRAWS, probes=num_probes, method=method, eps=eps,
                      seed=mc_key(seed), params=params)


def mc_key(seed: int):
    """Key for the Monte Carlo loops (see the module docstring for why rbg)."""
    return jax.random.key(seed, impl="rbg")


images = hnp.arrays(np.float32, SHAPE, elements=st.floats(0.0, 2.0, width=32))
variances = hnp.arrays(np.float32, SHAPE, elements=st.floats(2.0**-10, 0.25, width=32))
kernels = hnp.arrays(np.float32, (3, 3, 3, 3), elements=st.floats(-0.5, 0.5, width=32))
seeds = st.integers(0, 2**31 - 1)


# ------------------------------------------------------------------ unbiasedness


def _assert_unbiased(denoise_fn, params, clean, var, seed, method="jvp", eps=1e-4,
                     num_probes=4):
    draws = draw_statistics(denoise_fn, params, clean, var, seed, eps, method=method,
                            num_probes=num_probes)
    z = z_score(draws.sure, draws.truth)
    assert abs(z) <= Z_LIMIT, (z, np.mean(draws.sure - draws.truth), np.mean(draws.truth))


@SETTINGS
@given(clean=images, var=variances, seed=seeds)
def test_sure_unbiased_identity_and_zero(clean, var, seed):
    _assert_unbiased(linear_filter, IDENTITY, clean, var, seed)
    _assert_unbiased(linear_filter, ZERO, clean, var, seed)


@SETTINGS
@given(clean=images, var=variances, kernel=kernels, seed=seeds,
       method_probes=st.sampled_from([("jvp", 4), ("jvp", 1), ("fd", 4)]))
def test_sure_unbiased_linear_filter(clean, var, kernel, seed, method_probes):
    """fd at eps = 1e-2 is exact for a linear filter up to float32 round-off."""
    method, num_probes = method_probes
    _assert_unbiased(linear_filter, jnp.asarray(kernel), clean, var, seed, method=method,
                     eps=1e-2, num_probes=num_probes)


@SETTINGS
@given(clean=images, var=variances, tau=st.floats(0.0, 0.5, width=32), seed=seeds)
def test_sure_unbiased_soft_threshold(clean, var, tau, seed):
    _assert_unbiased(soft_threshold, jnp.float32(tau), clean, var, seed)


@SETTINGS
@given(clean=images, var=variances, net_seed=st.integers(0, 10_000), seed=seeds)
def test_sure_unbiased_relu_net(clean, var, net_seed, seed):
    _assert_unbiased(relu_net, net_params(net_seed), clean, var, seed)


def test_z_test_rejects_sure_without_divergence_term():
    """Power check, seeded: the same test applied to (y - x)^2 - var (no 2 var J_ii term)
    must reject, for the identity (J = I) and a 3x3 box blur (J_ii = 1/9)."""
    rng = np.random.default_rng(123)
    clean = jnp.asarray(rng.uniform(0, 2, SHAPE).astype(np.float32))
    var = jnp.asarray(rng.uniform(1e-3, 0.1, SHAPE).astype(np.float32))
    for kernel in (IDENTITY, BOX):
        draws = draw_statistics(linear_filter, kernel, clean, var, 7, 1e-4)
        broken = draws.residual - float(np.mean(np.asarray(var, np.float64)))
        assert abs(z_score(draws.sure, draws.truth)) <= Z_LIMIT
        assert z_score(broken, draws.truth) < -10.0, z_score(broken, draws.truth)


# ------------------------------------------------------------------ divergence


@functools.partial(jax.jit, static_argnames=("count",))
def single_probe_divergences(kernel, frame, key, count):
    """Image sums of the K = 1 divergence estimate for ``count`` independent probe keys."""
    def one(k):
        return jnp.sum(sure(linear_filter, frame, k, 1, params=kernel).divergence_term)

    return jax.vmap(one)(jax.random.split(key, count))


@SETTINGS
@given(clean=images, var=variances, kernel=kernels, seed=seeds)
def test_divergence_expectation_is_the_analytic_trace(clean, var, kernel, seed):
    """E_b[sum_i b_i (J b)_i] = sum_i var_i J_ii, J_ii = K[1, 1, c, c] at every pixel (zero
    padding keeps the centre tap). z-test over 2048 single-probe estimates, |z| <= 4.5."""
    frame = Frame(color=jnp.asarray(clean), variance=jnp.asarray(var))
    estimates = np.asarray(single_probe_divergences(jnp.asarray(kernel), frame,
                                                    mc_key(seed), 2048), np.float64)
    trace = float(np.sum(var.astype(np.float64) * np.diag(kernel[1, 1]).astype(np.float64)))
    assert abs(z_score(estimates, trace)) <= Z_LIMIT


@SETTINGS
@given(clean=images, var=variances, kernel=kernels, seed=seeds)
def test_jvp_probe_products_are_exact_for_linear_filters(clean, var, kernel, seed):
    """No randomness in the check: the jvp J b equals the analytic K * b for the same probes
    (float32, rtol 1e-5 relative to the largest term)."""
    frame = Frame(color=jnp.asarray(clean), variance=jnp.asarray(var))
    key = mc_key(seed)
    result = sure(linear_filter, frame, key, 4, params=jnp.asarray(kernel))
    b = draw_probes(key, frame.variance, 4)
    expected = np.asarray(jnp.mean(b * jax.vmap(lambda p: conv(p, jnp.asarray(kernel)))(b),
                                   axis=0))
    np.testing.assert_allclose(result.divergence_term, expected, rtol=1e-5,
                               atol=1e-5 * np.abs(expected).max() + 1e-12)


# ------------------------------------------------------------------ eps -> 0


def _fd_errors(dtype, scheme, epsilons):
    rng = np.random.default_rng(5)
    frame = Frame(color=jnp.asarray(rng.uniform(0, 2, SHAPE).astype(dtype)),
                  variance=jnp.asarray(rng.uniform(1e-3, 1e-1, SHAPE).astype(dtype)))
    params = net_params(6, dtype)
    key = jax.random.key(8)
    exact = np.asarray(sure(tanh_net, frame, key, params=params).divergence_term, np.float64)
    errors = []
    for eps in epsilons:
        fd = sure(tanh_net, frame, key, method="fd", eps=eps, fd_scheme=scheme, params=params)
        errors.append(np.linalg.norm(np.asarray(fd.divergence_term, np.float64) - exact)
                      / np.linalg.norm(exact))
    return np.array(errors)


def test_fd_converges_to_jvp_as_eps_shrinks_float64():
    """Same probes (same key). Relative L2 error of fd vs jvp in float64 on a smooth net:
    forward error ~ C eps (ratio per decade in [7, 13]), central ~ C eps^2 (ratio in
    [70, 130]) over eps = 1e-1 .. 1e-4; measured ratios ~10.0 and ~100."""
    epsilons = [1e-1, 1e-2, 1e-3, 1e-4]
    with jax.enable_x64(True):
        forward = _fd_errors(np.float64, "forward", epsilons)
        central = _fd_errors(np.float64, "central", epsilons)
    assert np.all((forward[:-1] / forward[1:] > 7) & (forward[:-1] / forward[1:] < 13)), forward
    assert np.all((central[:-1] / central[1:] > 70) & (central[:-1] / central[1:] < 130)), central
    assert forward[-1] < 1e-4 and central[-1] < 1e-7


def test_fd_float32_round_off_floor():
    """float32: truncation shrinks with eps until round-off (~u |F| / (eps |b|)) takes over.
    Measured: forward 3.5e-2, 3.5e-3, 7e-4, 5e-3, 5e-2 at eps = 1e-1 .. 1e-5. Asserts the
    shape (a minimum in the middle), not the exact values: fd at 1e-2..1e-3 within 1%, and
    at 1e-5 worse than at 1e-3 by > 10x (why the jvp method exists)."""
    forward = _fd_errors(np.float32, "forward", [1e-1, 1e-2, 1e-3, 1e-4, 1e-5])
    assert forward[1] < 1e-2 and forward[2] < 1e-2, forward
    assert forward[4] > 10 * forward[2], forward


# ------------------------------------------------------------------ NumPy black box


@pytest.mark.parametrize("scheme", ["forward", "central"])
def test_blackbox_sure_unbiased_for_numpy_soft_threshold(scheme):
    """sure_blackbox with a NumPy denoiser (pixelwise soft threshold around 1, tau = 0.2),
    seeded: 400 noise draws, K = 2 probes, eps = 1e-3; same z-test, |z| <= 4.5."""
    rng = np.random.default_rng(99)
    clean = rng.uniform(0.5, 1.5, SHAPE).astype(np.float32)
    var = rng.uniform(1e-3, 0.05, SHAPE).astype(np.float32)

    def denoise_np(frame):
        d = frame.color - 1.0
        return (1.0 + np.sign(d) * np.maximum(np.abs(d) - 0.2, 0.0)).astype(np.float32)

    differences = []
    for _ in range(400):
        x = (clean + np.sqrt(var) * rng.standard_normal(SHAPE)).astype(np.float32)
        result = sure_blackbox(denoise_np, Frame(color=x, variance=var), rng, num_probes=2,
                               eps=1e-3, fd_scheme=scheme)
        true_sq = np.sum((result.denoised.astype(np.float64) - clean) ** 2)
        differences.append(float(np.sum(result.sure, dtype=np.float64)) - true_sq)
    assert abs(z_score(differences)) <= Z_LIMIT
