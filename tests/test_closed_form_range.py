"""The range-aware closed form (``closed_form_stops``): Eq. 9's local means restricted to
neighbours of similar brightness.

- against a literal NumPy reference (explicit windows and strata, float64);
- the property it exists for: a bright, badly denoised spot beside a dim surface no longer
  sets the surface's alpha;
- the closed form's guarantees kept: exact swap symmetry, consistency as the variance
  vanishes, batching; the spec, config errors, the network head built on it.
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

from jaxden import progressive as P
from jaxden.errors import ConfigError
from jaxden.progressive.closed_form import (
    CLOSED_FORM_PROXY_SIGMA,
    CLOSED_FORM_RANGE_CEIL,
    CLOSED_FORM_RANGE_FLOOR,
)


def _blur_reference(image: np.ndarray, sigma: float) -> np.ndarray:
    """Zero-padded Gaussian correlation of (H, W, C), truncated at ceil(3 sigma), float64."""
    radius = max(1, math.ceil(3 * sigma))
    height, width = image.shape[:2]
    out = np.zeros(image.shape, np.float64)
    for di in range(-radius, radius + 1):
        for dj in range(-radius, radius + 1):
            w = math.exp(-(di * di + dj * dj) / (2 * sigma * sigma))
            src = image[max(0, di):height + min(0, di), max(0, dj):width + min(0, dj)]
            out[max(0, -di):height + min(0, -di), max(0, -dj):width + min(0, -dj)] += w * src
    return out


def reference_range_alpha(x, y, var, sure_map, sigma, per_channel, stops) -> np.ndarray:
    """Literal definition, one image, float64: alpha(p) = sum_q g(p - q) k(p, q) num(q) /
    sum_q g(p - q) k(p, q) den(q) with k(p, q) = sum_b s_b(p) s_b(q), s_b the tent
    memberships of log2(proxy) / stops in the integer bins, proxy = blur_2px(mean_c (x+y)/2)
    clamped to [FLOOR, CEIL]."""
    x, y, var, sure_map = (np.asarray(a, np.float64) for a in (x, y, var, sure_map))
    height, width, _ = x.shape
    numerator = (y - x) ** 2 + var - sure_map
    denominator = 2 * (y - x) ** 2
    if not per_channel:
        numerator = numerator.sum(-1, keepdims=True)
        denominator = denominator.sum(-1, keepdims=True)
    proxy = _blur_reference(((x + y) / 2).mean(-1, keepdims=True), CLOSED_FORM_PROXY_SIGMA)
    proxy = np.clip(proxy[..., 0], CLOSED_FORM_RANGE_FLOOR, CLOSED_FORM_RANGE_CEIL)
    level = np.log2(proxy) / stops
    radius = max(1, math.ceil(3 * sigma))
    alpha = np.empty(numerator.shape)
    for i in range(height):
        for j in range(width):
            num = np.zeros(numerator.shape[-1])
            den = np.zeros(numerator.shape[-1])
            for ii in range(max(0, i - radius), min(height, i + radius + 1)):
                for jj in range(max(0, j - radius), min(width, j + radius + 1)):
                    g = math.exp(-((ii - i) ** 2 + (jj - j) ** 2) / (2 * sigma * sigma))
                    bins = np.arange(math.floor(min(level[i, j], level[ii, jj])) - 1,
                                     math.ceil(max(level[i, j], level[ii, jj])) + 2)
                    s_p = np.clip(1 - np.abs(level[i, j] - bins), 0, 1)
                    s_q = np.clip(1 - np.abs(level[ii, jj] - bins), 0, 1)
                    k = float(np.sum(s_p * s_q))
                    num += g * k * numerator[ii, jj]
                    den += g * k * denominator[ii, jj]
            alpha[i, j] = np.where(den > 0, num / np.where(den > 0, den, 1), 1.0)
    return np.broadcast_to(np.clip(alpha, 0, 1), x.shape)


def _inputs(seed: int, shape=(10, 12, 3)):
    """Radiance over ~8 stops (log-uniform), a noisy render and a biased denoiser."""
    rng = np.random.default_rng(seed)
    mu = np.exp2(rng.uniform(-6, 2, shape[:2] + (1,))) * rng.uniform(0.7, 1.0, shape)
    x = (mu * (1 + rng.normal(0, 0.3, shape))).astype(np.float32)
    y = (mu * (1 + rng.normal(0, 0.1, shape)) + 0.02).astype(np.float32)
    var = (0.09 * mu ** 2).astype(np.float32)
    sure_map = ((y - x) ** 2 - var + 2 * var * rng.uniform(0, 0.5, shape)).astype(np.float32)
    return x, y, var, sure_map


@pytest.mark.parametrize("sigma, per_channel, stops", [
    (1.5, False, 1.0), (1.0, True, 0.5), (2.0, False, 2.5),
])
def test_range_closed_form_matches_numpy_reference(sigma, per_channel, stops):
    x, y, var, sure_map = _inputs(0)
    got = np.asarray(P.closed_form_alpha(x, y, var, sure_map, sigma=sigma,
                                         per_channel=per_channel, stops=stops))
    want = reference_range_alpha(x, y, var, sure_map, sigma, per_channel, stops)
    # float32 against float64 through log2, tents and sums of <= 169 terms.
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert 0.05 < float(np.mean((want > 0) & (want < 1)))  # not all clipped
    plain = np.asarray(P.closed_form_alpha(x, y, var, sure_map, sigma=sigma,
                                           per_channel=per_channel))
    assert float(np.max(np.abs(plain - want))) > 0.05  # the strata change the answer here


def _wall_and_lamp(seed: int, lamp: bool, size: int = 48):
    """A dim wall (0.05, noise var 1e-4, OIDN-like output with a small bias: the best alpha
    is near 1) and, optionally, a 10 x 10 lamp (radiance 100, var 1, a denoiser 5 too high:
    the best alpha there is near 0) in its corner."""
    rng = np.random.default_rng(seed)
    shape = (size, size, 3)
    mu = np.full(shape, 0.05)
    var = np.full(shape, 1e-4)
    bias = np.full(shape, 0.002)
    if lamp:
        mu[:10, :10], var[:10, :10], bias[:10, :10] = 100.0, 1.0, 5.0
    x = mu + np.sqrt(var) * rng.normal(size=shape)
    y = mu + bias + 0.1 * np.sqrt(var) * rng.normal(size=shape)
    sure_map = (y - x) ** 2 - var + 2 * var * 0.1  # a denoiser that passes 10 % of the noise
    return [a.astype(np.float32) for a in (x, y, var, sure_map)]


def test_range_closed_form_keeps_a_lamp_from_setting_the_walls_alpha():
    """The property behind the option (the demo's Cornell box in miniature): with plain local
    means the lamp's errors, ~1e4 x the wall's, rule every window that reaches it and drag the
    wall's alpha from ~0.87 down to ~0.2 in reach of the lamp; with strata 1 stop wide the wall
    (pixels more than 3 proxy widths from the lamp) keeps its alpha: mean change 0.0007, at
    most 0.022 (seed 1; the pixels whose proxy the lamp's blur raises change weight in the
    wall's windows, so the change is not exactly 0), and the lamp keeps its own."""
    without = _wall_and_lamp(1, lamp=False)
    with_lamp = _wall_and_lamp(1, lamp=True)
    wall = np.ones((48, 48), bool)
    wall[:16, :16] = False
    base = np.asarray(P.closed_form_alpha(*without, sigma=6.0, stops=1.0))[..., 0]
    ranged = np.asarray(P.closed_form_alpha(*with_lamp, sigma=6.0, stops=1.0))[..., 0]
    plain = np.asarray(P.closed_form_alpha(*with_lamp, sigma=6.0))[..., 0]
    assert float(base[wall].mean()) > 0.8
    change = np.abs(ranged[wall] - base[wall])
    assert float(change.mean()) < 0.005 and float(change.max()) < 0.05
    assert float(np.abs(plain[wall] - base[wall]).mean()) > 0.15
    near = wall.copy()
    near[30:, :] = near[:, 30:] = False  # wall pixels within reach of the lamp's windows
    assert float(plain[near].mean()) < 0.3
    assert float(ranged[:10, :10].max()) < 0.1  # the lamp still takes x


def test_range_closed_form_is_exactly_swap_symmetric_and_batches():
    x, y, var, sure_map = _inputs(3)
    params, config = P.load_mixer("closed-form:sigma=2,stops=1")
    assert config.closed_form_stops == 1.0
    alpha = np.asarray(P.mixer_alpha(params, config, x, y, var, sure_map))
    swapped = np.asarray(P.mixer_alpha(params, config, y, x, sure_map, var))
    unclipped = (alpha > 1e-3) & (alpha < 1 - 1e-3)
    assert unclipped.mean() > 0.2
    np.testing.assert_allclose(alpha[unclipped], 1 - swapped[unclipped], atol=3e-6)
    images = [_inputs(seed) for seed in (4, 5)]
    stacked = [np.stack(parts) for parts in zip(*images)]
    batched = np.asarray(P.closed_form_alpha(*stacked, sigma=2.0, stops=1.0))
    for b, parts in enumerate(images):
        np.testing.assert_allclose(
            batched[b], np.asarray(P.closed_form_alpha(*parts, sigma=2.0, stops=1.0)), atol=1e-6)


def test_range_closed_form_alpha_vanishes_as_the_variance_shrinks():
    """As in the plain closed form: a fixed bias and var -> 0 give alpha -> 0."""
    rng = np.random.default_rng(6)
    mu = np.exp2(rng.uniform(-5, 3, (32, 32, 1))) * np.ones((1, 1, 3))
    for s2, bound in [(1e-4, 0.05), (1e-6, 5e-4)]:
        x = (mu + math.sqrt(s2) * rng.normal(size=mu.shape)).astype(np.float32)
        y = (mu + 0.1).astype(np.float32)
        var = np.full(mu.shape, s2, np.float32)
        alpha = np.asarray(P.closed_form_alpha(x, y, var, (y - x) ** 2 - var, stops=1.0))
        assert float(alpha.max()) <= bound, (s2, float(alpha.max()))


def test_range_closed_form_config_and_network_head():
    for spec, message in [("closed-form:stops=0", r"closed_form_stops: 0.0 is outside the valid range \[0.0625, 64\]"),
                          ("closed-form:stops=-1", "closed_form_stops"),
                          ("closed-form:stop=1", "KEY one of sigma, per_channel, stops")]:
        with pytest.raises(ConfigError, match=message):
            P.load_mixer(spec)
    with pytest.raises(ConfigError, match="closed_form_stops"):
        P.MixerConfig(closed_form_stops=True)
    assert P.MixerConfig().closed_form_stops is None  # off by default: old mixers unchanged
    # The closed_form_logit head starts from the range-aware closed form when asked to.
    x, y, var, sure_map = _inputs(7)
    config = P.MixerConfig(head="closed_form_logit", width=8, closed_form_sigma=2.0,
                           closed_form_stops=1.0, logit_bound=4.0)
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    params = jax.tree_util.tree_map(np.zeros_like, params)
    alpha = np.asarray(P.mixer_alpha(params, config, x, y, var, sure_map))
    want = np.clip(np.asarray(P.closed_form_alpha(x, y, var, sure_map, sigma=2.0, stops=1.0)),
                   config.logit_eps, 1 - config.logit_eps)
    np.testing.assert_allclose(alpha, want, atol=1e-5)
