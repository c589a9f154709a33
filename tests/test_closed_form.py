"""The closed-form mixer: the paper's Eq. 9 with Gaussian local means (no network).

- against a literal NumPy reference (explicit windows, float64, in-image pixels only);
- against the analytic MSE-optimal alpha of a known linear denoiser under Gaussian noise;
- exact swap symmetry, consistency as the variance vanishes, and the spec / config errors;
- the whole pipeline (progressive_denoise, `jaxden progressive --mixer closed-form`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pytest

from jaxden import progressive as P
from jaxden.errors import CheckpointError, ConfigError, FrameError
from jaxden.progressive.heads import ALPHA_HEADS, CLOSED_FORM_LOGIT_EPS, closed_form_logit_alpha
from jaxden.progressive.inputs import MIXER_FEATURES, MIXER_FEATURES_NO_SURE, mixer_channel_slices
from jaxden.progressive.network import inference_alpha
from jaxden.sure.stein import sure


def reference_alpha(x, y, var, sure_map, sigma: float, per_channel: bool) -> np.ndarray:
    """Literal Eq. 9 with Gaussian local means, one image (H, W, 3), float64."""
    x, y, var, sure_map = (np.asarray(a, np.float64) for a in (x, y, var, sure_map))
    height, width, _ = x.shape
    radius = max(1, math.ceil(3 * sigma))
    numerator = (y - x) ** 2 + var - sure_map
    denominator = 2 * (y - x) ** 2
    if not per_channel:
        numerator = numerator.sum(-1, keepdims=True)
        denominator = denominator.sum(-1, keepdims=True)
    alpha = np.empty(numerator.shape)
    for i in range(height):
        for j in range(width):
            num = np.zeros(numerator.shape[-1])
            den = np.zeros(numerator.shape[-1])
            for di in range(-radius, radius + 1):
                for dj in range(-radius, radius + 1):
                    ii, jj = i + di, j + dj
                    if 0 <= ii < height and 0 <= jj < width:
                        w = math.exp(-(di * di + dj * dj) / (2 * sigma * sigma))
                        num += w * numerator[ii, jj]
                        den += w * denominator[ii, jj]
            alpha[i, j] = np.where(den > 0, num / np.where(den > 0, den, 1), 1.0)
    return np.broadcast_to(np.clip(alpha, 0, 1), x.shape)


def _inputs(seed: int, shape=(9, 13, 3)):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 1, shape).astype(np.float32)
    y = (x + rng.normal(0, 0.2, shape)).astype(np.float32)
    var = rng.uniform(0, 0.05, shape).astype(np.float32)
    sure_map = rng.normal(0.02, 0.05, shape).astype(np.float32)
    return x, y, var, sure_map


@pytest.mark.parametrize("sigma, per_channel", [(1.0, False), (1.5, True), (0.5, False)])
def test_closed_form_matches_numpy_reference(sigma, per_channel):
    x, y, var, sure_map = _inputs(0)
    got = P.closed_form_alpha(x, y, var, sure_map, sigma=sigma, per_channel=per_channel)
    want = reference_alpha(x, y, var, sure_map, sigma, per_channel)
    # float32 sums of <= 169 terms against float64: 1e-5 absolute on alpha in [0, 1].
    np.testing.assert_allclose(np.asarray(got), want, atol=1e-5)
    assert 0.05 < float(np.mean((want > 0) & (want < 1)))  # not all clipped: a real test


def test_closed_form_batched_equals_per_image():
    images = [_inputs(seed) for seed in (1, 2)]
    stacked = [np.stack(parts) for parts in zip(*images)]
    batched = np.asarray(P.closed_form_alpha(*stacked, sigma=2.0))
    for b, parts in enumerate(images):
        np.testing.assert_allclose(batched[b], np.asarray(P.closed_form_alpha(*parts, sigma=2.0)),
                                   atol=1e-6)


def test_closed_form_recovers_the_optimal_alpha_of_a_linear_denoiser():
    """y = (1 - w) x + w c (shrink towards c) on a constant image mu with noise N(0, s2):
    E[(z - mu)^2] for z = x + alpha (y - x) is minimal at alpha* = s2 / (w (s2 + (c - mu)^2))
    (here 0.4). SURE by jvp (4 probes). Seed 0, 128 x 128; the local means at sigma 8 average
    ~800 pixels x 3 channels, so the image-mean alpha is within 0.03 of alpha* (the measured
    spread over seeds is ~0.004)."""
    mu, c, w, s2 = 1.0, 3.0, 0.5, 1.0
    alpha_star = s2 / (w * (s2 + (c - mu) ** 2))
    shape = (128, 128, 3)
    key_noise, key_probe = jax.random.split(jax.random.PRNGKey(0))
    var = np.full(shape, s2, np.float32)
    x = mu + np.sqrt(s2) * np.asarray(jax.random.normal(key_noise, shape), np.float32)
    from jaxden.frame import Frame

    frame = Frame(color=x, variance=var)
    result = sure(lambda f: (1 - w) * f.color + w * c, frame, key_probe, num_probes=4)
    y = np.asarray(result.denoised)
    alpha = np.asarray(P.closed_form_alpha(x, y, var, np.asarray(result.sure), sigma=8.0))
    assert abs(float(alpha.mean()) - alpha_star) < 0.03
    z = x + alpha * (y - x)
    mse = lambda image: float(np.mean((image - mu) ** 2))
    optimum = (1 - alpha_star * w) ** 2 * s2 + (alpha_star * w * (c - mu)) ** 2  # 0.8
    # Both inputs are worse (x: 1.0, y: 1.25); z is within 2 % of the analytic optimum.
    assert mse(z) < 1.02 * optimum < min(mse(x), mse(y))


def test_closed_form_is_exactly_swap_symmetric():
    x, y, var, sure_map = _inputs(3)
    params, config = P.load_mixer("closed-form:sigma=2")
    alpha = np.asarray(P.mixer_alpha(params, config, x, y, var, sure_map))
    swapped = np.asarray(P.mixer_alpha(params, config, y, x, sure_map, var))
    np.testing.assert_allclose(alpha, 1 - swapped, atol=2e-6)
    assert P.swap_symmetry(params, config, x, y, var, sure_map) < 2e-6


def test_closed_form_alpha_vanishes_as_the_variance_shrinks():
    """A denoiser with a fixed bias b: SURE's expectation is b^2 and (y - x)^2 -> b^2, so the
    numerator (y - x)^2 + var - SURE -> var -> 0 and alpha -> 0 (no t-test involved)."""
    rng = np.random.default_rng(4)
    mu = rng.uniform(0.5, 1.5, (32, 32, 3)).astype(np.float32)
    bias = 0.1
    for s2, bound in [(1e-2, 1.0), (1e-4, 0.05), (1e-6, 5e-4)]:
        x = (mu + math.sqrt(s2) * rng.normal(size=mu.shape)).astype(np.float32)
        y = mu + bias  # the denoiser ignores the noise: f' = 0, SURE = (y - x)^2 - var
        var = np.full(mu.shape, s2, np.float32)
        alpha = np.asarray(P.closed_form_alpha(x, y, var, (y - x) ** 2 - var))
        assert float(alpha.max()) <= bound, (s2, float(alpha.max()))


def test_closed_form_spec_config_and_errors(tmp_path):
    params, config = P.load_mixer("closed-form")
    assert params == {} and config.kind == "closed_form" and config.closed_form_sigma == 12.0
    _, config = P.load_mixer("closed-form:sigma=3, per_channel=true")
    assert (config.closed_form_sigma, config.closed_form_per_channel) == (3.0, True)
    assert not config.sure.covariance
    assert P.load_mixer("closed-form:covariance=true")[1].sure.covariance
    assert P.mixer_init(jax.random.PRNGKey(0), config) == {}
    for spec, message in [("closed-form:width=3", "KEY one of sigma, per_channel"),
                          ("closed-form:sigma", "KEY=VALUE"),
                          ("closed-form:sigma=0", r"closed_form_sigma: 0.0 is outside the valid range \(0, 256\]"),
                          ("closed-form:per_channel=2", "closed_form_per_channel")]:
        with pytest.raises(ConfigError, match=message):
            P.load_mixer(spec)
    with pytest.raises(ConfigError, match="kind: expected one of 'network', 'closed_form', found 'tree'"):
        P.MixerConfig(kind="tree")
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        P.load_mixer(str(tmp_path / "closed-form"))  # a path is not the spec
    x, y, var, _ = _inputs(5)
    with pytest.raises(FrameError, match="need 'sure'"):
        P.closed_form_alpha(x, y, var, None)
    with pytest.raises(FrameError, match="shape"):
        P.closed_form_alpha(x, y[:4], var, var)


def test_closed_form_as_a_network_input_feature():
    """The optional ``closed_form`` feature is closed_form_alpha at the config's width, turns
    into 1 - alpha when the inputs are swapped, and a network with it initialises and runs."""
    x, y, var, sure_map = _inputs(6)
    features = (*MIXER_FEATURES, "closed_form")
    inputs = np.asarray(P.mixer_inputs(x, y, var, sure_map, features=features,
                                       closed_form_sigma=2.0))
    assert inputs.shape == (*x.shape[:-1], 21)
    part = mixer_channel_slices(features)["closed_form"]
    want = np.asarray(P.closed_form_alpha(x, y, var, sure_map, sigma=2.0))
    np.testing.assert_allclose(inputs[..., part], want, atol=1e-6)
    swapped = np.asarray(P.mixer_inputs(y, x, sure_map, var, features=features,
                                        closed_form_sigma=2.0))
    np.testing.assert_allclose(swapped[..., part], 1 - want, atol=2e-6)
    config = P.MixerConfig(features=features, closed_form_sigma=2.0, width=8)
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    alpha = np.asarray(P.mixer_alpha(params, config, x, y, var, sure_map))
    assert alpha.shape == x.shape and np.all((alpha >= 0) & (alpha <= 1))
    with pytest.raises(ConfigError, match="unknown mixer feature"):
        P.MixerConfig(features=(*MIXER_FEATURES, "oracle"))
    assert "closed_form" not in MIXER_FEATURES_NO_SURE


def test_closed_form_logit_head_starts_at_the_closed_form_and_corrects_it():
    """head = closed_form_logit: alpha = sigmoid(logit(alpha_cf) + raw). With a zero output
    layer it is the closed form (clipped to [eps, 1 - eps]), swap averaging included; a raw
    output r moves the logit by exactly r; it needs SURE whatever the features."""
    x, y, var, sure_map = _inputs(8)
    config = P.MixerConfig(head="closed_form_logit", closed_form_sigma=2.0, width=8,
                           features=MIXER_FEATURES_NO_SURE)
    assert config.uses_sure and ALPHA_HEADS["closed_form_logit"] == 3
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    out = params["params"]["conv_out"]
    zero = jax.tree_util.tree_map(np.zeros_like, out)
    flat = {"params": {**params["params"], "conv_out": zero}}
    want = np.clip(np.asarray(P.closed_form_alpha(x, y, var, sure_map, sigma=2.0)),
                   CLOSED_FORM_LOGIT_EPS, 1 - CLOSED_FORM_LOGIT_EPS)
    got = np.asarray(P.mixer_alpha(flat, config, x, y, var, sure_map))
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=2e-6)
    averaged = dataclasses.replace(config, swap_average=True)
    got = np.asarray(inference_alpha(flat, x, y, var, sure_map, averaged, True))
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=4e-6)
    shifted = {"params": {**params["params"],
                          "conv_out": {"kernel": zero["kernel"],
                                       "bias": np.array([0.5, -1.0, 2.0], np.float32)}}}
    got = np.asarray(P.mixer_alpha(shifted, config, x, y, var, sure_map), np.float64)
    logit = np.log(got) - np.log1p(-got)
    np.testing.assert_allclose(logit - (np.log(want) - np.log1p(-want)),
                               np.broadcast_to([0.5, -1.0, 2.0], got.shape), atol=2e-3)
    with pytest.raises(FrameError, match="need 'sure'"):
        P.mixer_alpha(params, config, x, y, var)
    with pytest.raises(ConfigError, match="closed_form_logit head needs"):
        P.alpha_from_head(np.zeros((2, 2, 3), np.float32), "closed_form_logit")


def test_closed_form_logit_bound_is_a_trust_region_around_the_closed_form():
    """logit_bound = B: the correction is B tanh(raw / B). Whatever the raw output (here up to
    +-1e4, as a firefly's linear radiance input can drive a ReLU network), alpha's logit stays
    within B of the closed form's; near raw = 0 it is the unbounded head (slope 1); the bound
    is odd, so swap averaging of a zero network is still the closed form."""
    a = np.array([0.001, 0.02, 0.3, 0.5, 0.97, 0.999], np.float32)[:, None, None] * np.ones(
        (1, 2, 3), np.float32)
    logit_a = np.log(a.astype(np.float64)) - np.log1p(-a.astype(np.float64))
    for bound in (0.5, 2.0, 3.0):
        for raw in (-1e4, -40.0, -1.0, 1.0, 40.0, 1e4):
            got = np.asarray(closed_form_logit_alpha(np.full(a.shape, raw, np.float32), a,
                                                       bound), np.float64)
            shift = np.log(got) - np.log1p(-got) - logit_a
            want = bound * np.tanh(raw / bound)
            np.testing.assert_allclose(shift, want, atol=2e-3 * max(1.0, abs(want)))
            assert np.all(np.abs(shift) <= bound + 1e-3)
        small = np.full(a.shape, 1e-3, np.float32)
        np.testing.assert_allclose(closed_form_logit_alpha(small, a, bound),
                                   closed_form_logit_alpha(small, a), atol=1e-6)
    # Unbounded, a huge raw output overrides the closed form completely.
    assert float(np.max(closed_form_logit_alpha(np.full(a.shape, -40.0, np.float32), a))) < 1e-3
    # eps: alpha_cf = 1 is clipped to 1 - eps before the logit.
    one = np.ones((2, 2, 3), np.float32)
    zero_raw = np.zeros_like(one)
    np.testing.assert_allclose(closed_form_logit_alpha(zero_raw, one, None, 1e-4), 1 - 1e-4,
                               atol=1e-6)
    x, y, var, sure_map = _inputs(8)
    config = P.MixerConfig(head="closed_form_logit", closed_form_sigma=2.0, width=8,
                           logit_bound=2.0, logit_eps=1e-4)
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    zero = jax.tree_util.tree_map(np.zeros_like, params["params"]["conv_out"])
    flat = {"params": {**params["params"], "conv_out": zero}}
    want = np.clip(np.asarray(P.closed_form_alpha(x, y, var, sure_map, sigma=2.0)), 1e-4,
                   1 - 1e-4)
    got = np.asarray(inference_alpha(flat, x, y, var, sure_map, config, True))
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=4e-6)
    loud = {"params": {**params["params"], "conv_out": {
        "kernel": zero["kernel"], "bias": np.array([1e3, -1e3, 0.0], np.float32)}}}
    got = np.asarray(P.mixer_alpha(loud, config, x, y, var, sure_map), np.float64)
    shift = np.log(got) - np.log1p(-got) - (np.log(want) - np.log1p(-want))
    np.testing.assert_allclose(shift, np.broadcast_to([2.0, -2.0, 0.0], got.shape), atol=5e-3)


@pytest.mark.parametrize("fields, match", [
    ({"head": "closed_form_logit", "logit_bound": 0.0}, r"logit_bound: 0.0 is outside the valid range \(0, 100\]"),
    ({"head": "closed_form_logit", "logit_bound": float("nan")}, "logit_bound"),
    ({"head": "closed_form_logit", "logit_bound": True}, "logit_bound"),
    ({"head": "closed_form_logit", "logit_eps": 0.5}, r"logit_eps: 0.5 is outside the valid range \(0, 0.5\)"),
    ({"head": "closed_form_logit", "logit_eps": 0}, "logit_eps"),
    ({"logit_bound": 2.0}, "apply only to head = 'closed_form_logit'"),
    ({"head": "sigmoid", "logit_eps": 1e-4}, "apply only to head"),
])
def test_closed_form_logit_bound_config_errors(fields, match):
    with pytest.raises(ConfigError, match=match):
        P.MixerConfig(**fields)


def test_closed_form_logit_bound_loads_from_toml_overrides(tmp_path):
    from jaxden.config import load_config

    config = load_config(P.MixerConfig(), P.MixerConfig, overrides=[
        "head=closed_form_logit", "logit_bound=3", "logit_eps=1e-4"])
    assert config.logit_bound == 3 and config.logit_eps == 1e-4
    with pytest.raises(ConfigError, match="logit_bound"):
        load_config(P.MixerConfig(), P.MixerConfig, overrides=["logit_bound=3"])
