"""Tests of jaxden.progressive: mixer inputs, f_act, mix, t-statistic scaling.

The t-statistic is compared against a slow, literal NumPy reference (explicit windows and
loops, float64, blur(z) - blur(x) as two separate sums, first-maximum M_p search) on a
non-square 10 x 12 image, so the 11 x 11 window crosses the borders everywhere.
Tolerances: t to rtol 2e-5 plus atol 2e-5 * max(t) (float32 sums of <= 121 terms vs float64);
alpha' to atol 1e-5 (|d alpha'/d t| <= a * phi(0) = 0.8, times the t tolerance).
"""

from __future__ import annotations

import math
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.stats import norm

from jaxden import progressive as P
from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.heads import ALPHA_HEADS, alpha_direct
from jaxden.progressive.inputs import (
    MIXER_FEATURES,
    MIXER_FEATURES_NO_SURE,
    MIXER_LAYOUT,
    mixer_channel_slices,
)

# ------------------------------------------------------------------------ NumPy reference


def reference_t(x, z, var, cfg: P.TStatConfig) -> np.ndarray:
    """Literal, slow t-statistic for one image (H, W, 3) -> (H, W, 1 or 3), float64."""
    x, z, var = (np.asarray(a, np.float64) for a in (x, z, var))
    height, width, channels = x.shape
    if cfg.sigma_rule == "fixed":
        s = cfg.sigma_fixed
    else:
        mean_var = var.mean()
        if cfg.sigma_rule == "image_mean_variance":
            mean_var /= var.size
        s = cfg.sigma_scale * math.sqrt(min(max(mean_var, 0.0), cfg.sigma_variance_cap))
    s = max(s, cfg.sigma_min)
    r = cfg.window // 2
    out_channels = 3 if cfg.per_channel else 1
    t = np.zeros((height, width, out_channels))
    for py in range(height):
        for px in range(width):
            blur_z = [0.0] * channels
            blur_x = [0.0] * channels
            blur_v = [0.0] * channels
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    qy, qx = py + dy, px + dx
                    if not (0 <= qy < height and 0 <= qx < width):
                        continue
                    kappa = math.exp(-(dy * dy + dx * dx) / (2 * s * s))
                    kappa /= s * math.sqrt(2 * math.pi)
                    for c in range(channels):
                        blur_z[c] += kappa * z[qy, qx, c]
                        blur_x[c] += kappa * x[qy, qx, c]
                        blur_v[c] += kappa * kappa * var[qy, qx, c]
            if cfg.use_max_variance_neighbour:
                w = cfg.neighbour_weight
                for c in range(channels):
                    best, best_q = -math.inf, None
                    for dy in range(-r, r + 1):  # row-major: first maximum wins
                        for dx in range(-r, r + 1):
                            qy, qx = py + dy, px + dx
                            if 0 <= qy < height and 0 <= qx < width and var[qy, qx, c] > best:
                                best, best_q = var[qy, qx, c], (qy, qx)
                    blur_z[c] += w * z[best_q + (c,)]
                    blur_x[c] += w * x[best_q + (c,)]
                    blur_v[c] += w * w * best
            if cfg.per_channel:
                for c in range(channels):
                    t[py, px, c] = abs(blur_z[c] - blur_x[c]) / (math.sqrt(blur_v[c]) + cfg.eps)
            else:
                t[py, px, 0] = abs(sum(blur_z) - sum(blur_x)) / (math.sqrt(sum(blur_v)) + cfg.eps)
    return t


def reference_scaling(alpha, t, cfg: P.TStatConfig) -> np.ndarray:
    u = cfg.a * (t - cfg.c)
    keep = norm.sf(u) if cfg.squash == "normal_cdf" else 1.0 / (1.0 + np.exp(u))
    return np.asarray(alpha, np.float64) * keep


def make_scene(seed, height=10, width=12, mean_var=1e-3, bias=4.0, tie_var=False):
    """x, y, var, alpha, z with t spread over ~0..10 (bias in units of the local std)."""
    rng = np.random.default_rng(seed)
    clean = rng.uniform(0.0, 2.0, (height, width, 3))
    if tie_var:
        var = np.full((height, width, 3), mean_var)
    else:
        var = rng.uniform(0.1, 1.9, (height, width, 3)) * mean_var
    x = clean + np.sqrt(var) * rng.standard_normal((height, width, 3))
    # A smooth bias field (so window sums do not cancel) of a few standard deviations.
    yy, xx = np.meshgrid(np.linspace(-1, 1, height), np.linspace(-1, 1, width), indexing="ij")
    field = np.sin(2.5 * yy + 1.0) * np.cos(1.7 * xx)
    y = clean + bias * math.sqrt(mean_var) * field[..., None] * rng.uniform(0.5, 1.0, 3)
    alpha = rng.uniform(0.0, 1.0, (height, width, 3))
    z = x + alpha * (y - x)
    return tuple(a.astype(np.float32) for a in (x, y, var, alpha, z))


T_CASES = {
    # s ~ 0.03: the centre pixel and M_p only
    "default_small_s": (P.TStatConfig(), dict(mean_var=1e-7, bias=8.0)),
    "default_mid_s": (P.TStatConfig(), dict(mean_var=4e-4)),  # s ~ 2
    "default_large_s": (P.TStatConfig(), dict(mean_var=0.3, bias=32.0)),  # s ~ 55
    "default_capped_s": (P.TStatConfig(), dict(mean_var=3.0, bias=32.0)),  # s = 100 (cap)
    "tied_variance": (P.TStatConfig(), dict(mean_var=4e-4, tie_var=True)),
    "per_channel": (P.TStatConfig(per_channel=True), dict(mean_var=4e-4)),
    "no_max_neighbour": (P.TStatConfig(use_max_variance_neighbour=False), dict(mean_var=4e-4)),
    "window5_fixed_logistic": (
        P.TStatConfig(window=5, sigma_rule="fixed", sigma_fixed=1.5, squash="logistic", a=1.5,
                      c=3.0, neighbour_weight=1.0),
        dict(mean_var=1e-2),
    ),
    "paper_literal_sigma": (P.TStatConfig(sigma_rule="image_mean_variance"),
                            dict(mean_var=2e-3, bias=8.0)),
}


@pytest.mark.parametrize("name", sorted(T_CASES))
def test_t_statistic_matches_numpy_reference(name):
    cfg, scene = T_CASES[name]
    x, y, var, alpha, z = make_scene(seed=zlib.crc32(name.encode()) % 1000, **scene)
    expected_t = reference_t(x, z, var, cfg)
    t = np.asarray(P.t_statistic(x, z, var, cfg))
    assert t.shape == expected_t.shape
    np.testing.assert_allclose(t, expected_t, rtol=2e-5, atol=2e-5 * expected_t.max())
    # The cases must exercise the scaling's transition region (c - 3/a < t < c + 3/a, about
    # 2.7..5.7 with the defaults), not only its flat ends.
    transition = np.mean((expected_t > 2.0) & (expected_t < 6.0))
    assert transition >= 0.1, transition
    alpha_prime = np.asarray(P.t_statistic_scaling(alpha, x, z, var, cfg))
    np.testing.assert_allclose(alpha_prime, reference_scaling(alpha, expected_t, cfg), atol=1e-5)


def test_t_statistic_keyword_overrides_equal_config():
    x, y, var, alpha, z = make_scene(seed=3)
    cfg = P.TStatConfig(window=7, a=3.0, c=3.5, per_channel=True)
    a = P.t_statistic_scaling(alpha, x, z, var, window=7, a=3.0, c=3.5, per_channel=True)
    b = P.t_statistic_scaling(alpha, x, z, var, cfg)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_t_statistic_batched_equals_per_image():
    """Leading dims: each image has its own s (from its own mean variance)."""
    scenes = [make_scene(seed=s, mean_var=m) for s, m in ((1, 1e-4), (2, 5e-2))]
    x, y, var, alpha, z = (np.stack(parts) for parts in zip(*scenes))
    batched = np.asarray(P.t_statistic_scaling(alpha, x, z, var))
    for i in range(2):
        single = np.asarray(P.t_statistic_scaling(alpha[i], x[i], z[i], var[i]))
        np.testing.assert_allclose(batched[i], single, rtol=1e-6, atol=1e-7)


def test_scaling_is_tiny_change_without_difference_and_shrinks_alpha():
    x, y, var, alpha, z = make_scene(seed=5)
    # z == x: t = 0, keep = Phi(a c) = Phi(8.4) = 1 - 2e-17.
    same = np.asarray(P.t_statistic_scaling(alpha, x, x, var))
    np.testing.assert_allclose(same, alpha, rtol=1e-6)
    scaled = np.asarray(P.t_statistic_scaling(alpha, x, z, var))
    assert np.all(scaled <= alpha) and np.all(scaled >= 0)
    # ... and it does shrink: alpha' = alpha (1 - Phi(a (|t| - c))), so where |t| >= c + 3 / a
    # alpha' <= (1 - Phi(3)) alpha = 0.00135 alpha, and where |t| <= c - 3 / a alpha is kept
    # to 0.14 %.
    config = P.TStatConfig()
    t = np.broadcast_to(np.abs(np.asarray(P.t_statistic(x, z, var))), alpha.shape)
    large, small = t >= config.c + 3 / config.a, t <= config.c - 3 / config.a
    assert large.any() and small.any()  # the scene spreads t over both regimes
    assert np.all(scaled[large] <= 0.002 * alpha[large])
    np.testing.assert_allclose(scaled[small], alpha[small], rtol=2e-3)


def test_consistent_mix_composes_mix_scaling_and_guard():
    x, y, var, alpha, _ = make_scene(seed=6)
    z = np.asarray(P.mix(x, y, alpha))
    scaled = np.asarray(P.t_statistic_scaling(alpha, x, z, var))
    _, alpha_paper = P.consistent_mix(x, y, alpha, var, guard=False)
    np.testing.assert_allclose(np.asarray(alpha_paper), scaled, rtol=1e-6)
    z_prime, alpha_prime = P.consistent_mix(x, y, alpha, var)
    np.testing.assert_allclose(np.asarray(alpha_prime),
                               np.asarray(P.error_guard(scaled, x, y, var)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(z_prime), x + np.asarray(alpha_prime) * (y - x),
                               rtol=1e-6, atol=1e-6)


# ------------------------------------------------------------------------ consistency


def _shrink(x_clean, base_var, noise, k):
    var = (base_var * 4.0**-k).astype(np.float32)
    x = (x_clean + np.sqrt(var) * noise).astype(np.float32)
    return x, var


@settings(max_examples=15, deadline=None, derandomize=True)
@given(
    alpha=hnp.arrays(np.float32, (6, 7, 3), elements=st.floats(0, 1, width=32)),
    bias=hnp.arrays(np.float32, (6, 7, 3), elements=st.floats(0.0625, 1.0, width=32)),
    sign=st.sampled_from([-1.0, 1.0]),
    base_var=hnp.arrays(np.float32, (6, 7, 3), elements=st.floats(2**-10, 1.0, width=32)),
    seed=st.integers(0, 2**16),
    per_channel=st.booleans(),
)
def test_consistency_alpha_vanishes_as_variance_shrinks(alpha, bias, sign, base_var, seed,
                                                        per_channel):
    """Theory (see t_statistic_scaling): y = mu + b held fixed, var = base * 4^-k, x = mu +
    sqrt(var) n. With b of one sign everywhere (so the window sums cannot cancel) t_p -> inf
    wherever alpha_p > 0, hence alpha' -> 0 and z' -> x -> mu.

    Criterion at k = 20 (sqrt(var) <= 2^-20 ~ 1e-6, |bias| >= 1/16): alpha' <= 1e-3 everywhere
    (pixels with alpha <= 1e-3 pass trivially since alpha' <= alpha; for alpha >= 1e-3 the
    bound t >= alpha b / (sqrt(3) 2^-20) ~ 29 gives alpha' ~ Phi(-50)), and
    |z' - x| <= 1e-3 |y - x|. Also alpha' <= alpha at every k.
    """
    rng = np.random.default_rng(seed)
    clean = rng.uniform(0.0, 2.0, alpha.shape).astype(np.float32)
    noise = rng.standard_normal(alpha.shape).astype(np.float32)
    y = clean + sign * bias
    for k in (0, 5, 10, 20):
        x, var = _shrink(clean, base_var, noise, k)
        z_prime, alpha_prime = P.consistent_mix(x, y, alpha, var, per_channel=per_channel)
        alpha_prime = np.asarray(alpha_prime)
        assert np.all(alpha_prime <= alpha) and np.all(alpha_prime >= 0)
    assert alpha_prime.max() <= 1e-3
    assert np.all(np.abs(np.asarray(z_prime) - x) <= 1e-3 * np.abs(y - x) + 1e-7)


def test_channel_summed_t_misses_hue_shift_bias_but_per_channel_catches_it():
    """A documented limitation of the authors' channel-summed t: a bias (+beta, -beta, 0)
    with the same alpha in every channel cancels in the sum over R, G, B, so t stays O(1)
    (it only sees the noise) and alpha' ~ alpha even as var -> 0: z' does not converge.
    ``per_channel=True`` sees it in R and G: t ~ alpha beta / sqrt(var) ~ 500 here (B has no
    bias, so alpha'_B ~ alpha_B is right there and z'_B - x_B = alpha_B sqrt(var) n -> 0).
    The error guard (on by default) sums squares over the channels, so it catches the shift
    with the channel-summed t too."""
    rng = np.random.default_rng(11)
    shape = (8, 9, 3)
    clean = rng.uniform(0.2, 0.8, shape).astype(np.float32)
    noise = rng.standard_normal(shape).astype(np.float32)
    y = clean + np.array([0.1, -0.1, 0.0], np.float32)
    alpha = np.full(shape, 0.5, np.float32)
    x, var = _shrink(clean, np.full(shape, 1e-2, np.float32), noise, 10)  # std 1e-4
    _, summed = P.consistent_mix(x, y, alpha, var, guard=False)
    _, per_channel = P.consistent_mix(x, y, alpha, var, per_channel=True, guard=False)
    assert np.asarray(summed).min() > 0.45  # keep >= 0.9: nothing detected
    assert np.asarray(per_channel)[..., :2].max() < 1e-6
    assert np.asarray(per_channel)[..., 2].min() > 0.45
    _, guarded = P.consistent_mix(x, y, alpha, var)
    assert np.asarray(guarded).max() < 1e-6


# ------------------------------------------------------------------------ mixer inputs


def test_mixer_inputs_layout():
    rng = np.random.default_rng(0)
    x, y, sure = (rng.normal(1.0, 0.5, (2, 4, 5, 3)).astype(np.float32) for _ in range(3))
    var = rng.uniform(0, 0.2, (2, 4, 5, 3)).astype(np.float32)
    features = np.asarray(P.mixer_inputs(x, y, var, sure))
    assert features.shape == (2, 4, 5, 18)
    r2 = (x - y) ** 2
    expected = {
        "hdr": x,
        "den": y,
        "var": np.arctan(var),
        "sure": np.arctan(sure),
        "residual": np.arctan(r2),
        "divergence": np.arctan(sure + var - r2),
    }
    assert MIXER_LAYOUT == mixer_channel_slices()
    expected_slices = [slice(i, i + 3) for i in range(0, 18, 3)]
    assert [MIXER_LAYOUT[n] for n in MIXER_FEATURES] == expected_slices
    for name, value in expected.items():
        np.testing.assert_allclose(features[..., MIXER_LAYOUT[name]], value, rtol=1e-6, atol=1e-7)


def test_log_input_transform_is_a_signed_log_and_scale_free():
    """transform="log": 0.1 sign(v) log(1 + |v| / 1e-8) for var, SURE, residual and divergence;
    radiance stays linear. Values are O(1) from 1e-7 to 1e4 (arctan is ~0 below 1e-3), and
    scaling var and SURE together by k shifts both by ~0.1 log k (a log-ratio input)."""
    rng = np.random.default_rng(3)
    x, y = (rng.uniform(0.1, 1.0, (4, 5, 3)).astype(np.float32) for _ in range(2))
    var = np.full((4, 5, 3), 1e-6, np.float32)
    sure = np.full((4, 5, 3), -4e-6, np.float32)
    f = np.asarray(P.mixer_inputs(x, y, var, sure, transform="log"))
    L = MIXER_LAYOUT
    np.testing.assert_allclose(f[..., L["hdr"]], x)
    np.testing.assert_allclose(f[..., L["var"]], 0.1 * np.log1p(100.0), rtol=1e-5)
    np.testing.assert_allclose(f[..., L["sure"]], -0.1 * np.log1p(400.0), rtol=1e-5)
    r2 = (x.astype(np.float64) - y) ** 2
    np.testing.assert_allclose(f[..., L["residual"]], 0.1 * np.log1p(r2 / 1e-8), rtol=1e-5)
    d = sure.astype(np.float64) + var - r2
    np.testing.assert_allclose(f[..., L["divergence"]], 0.1 * np.sign(d) * np.log1p(np.abs(d) / 1e-8),
                               rtol=1e-4)
    g = np.asarray(P.mixer_inputs(x, y, 1e4 * var, 1e4 * sure, transform="log"))
    shift = g[..., L["var"]] - f[..., L["var"]]
    np.testing.assert_allclose(shift, 0.1 * np.log(1e4), rtol=2e-3)  # the floor: 0.1 %
    np.testing.assert_allclose(-(g[..., L["sure"]] - f[..., L["sure"]]), shift, rtol=2e-3)
    assert np.abs(np.asarray(P.mixer_inputs(x, y, var, sure))[..., L["var"]]).max() < 2e-6
    with pytest.raises(ConfigError, match="unknown transform 'sqrt'"):
        P.mixer_inputs(x, y, var, sure, transform="sqrt")
    with pytest.raises(ConfigError, match="input_transform: expected one of 'atan', 'log', found 'sqrt'"):
        P.MixerConfig(input_transform="sqrt")


def test_mixer_inputs_without_sure_for_ablation():
    rng = np.random.default_rng(1)
    x, y = (rng.normal(1.0, 0.5, (4, 5, 3)).astype(np.float32) for _ in range(2))
    var = rng.uniform(0, 0.2, (4, 5, 3)).astype(np.float32)
    features = np.asarray(P.mixer_inputs(x, y, var, None, features=MIXER_FEATURES_NO_SURE))
    assert MIXER_FEATURES_NO_SURE == ("hdr", "den", "var", "residual")
    assert features.shape == (4, 5, 12)
    slices = mixer_channel_slices(MIXER_FEATURES_NO_SURE)
    np.testing.assert_allclose(features[..., slices["residual"]], np.arctan((x - y) ** 2),
                               rtol=1e-6)
    with pytest.raises(FrameError, match="need 'sure'"):
        P.mixer_inputs(x, y, var, None)
    with pytest.raises(ConfigError, match="unknown mixer feature"):
        P.mixer_inputs(x, y, var, None, features=("hdr", "albedo"))


def test_mixer_inputs_shape_errors():
    a = np.zeros((4, 5, 3), np.float32)
    with pytest.raises(FrameError, match="'var' has shape"):
        P.mixer_inputs(a, a, np.zeros((4, 6, 3), np.float32), a)
    with pytest.raises(FrameError, match=r"\(\.\.\., H, W, 3\)"):
        P.mixer_inputs(a, a, a, np.zeros((4, 5, 1), np.float32))


def test_swap_inputs_swaps_whole_images():
    rng = np.random.default_rng(2)
    x, y, var, sure = (rng.normal(size=(64, 2, 2, 3)).astype(np.float32) for _ in range(4))
    x2, y2, var2, sure2, swapped = P.swap_inputs(jax.random.key(0), x, y, var, sure)
    swapped = np.asarray(swapped)
    s = swapped[:, None, None, None]
    np.testing.assert_array_equal(np.asarray(x2), np.where(s, y, x))
    np.testing.assert_array_equal(np.asarray(y2), np.where(s, x, y))
    np.testing.assert_array_equal(np.asarray(var2), np.where(s, sure, var))
    np.testing.assert_array_equal(np.asarray(sure2), np.where(s, var, sure))
    assert 16 < swapped.sum() < 48  # Binomial(64, 0.5): 4.0 sigma either side
    never = P.swap_inputs(jax.random.key(0), x, y, var, sure, probability=0.0)[4]
    assert not np.asarray(never).any()


# ------------------------------------------------------------------------ f_act, mix


def test_f_act_values_by_hand():
    # by_role: [x1 R G B, x2 R G B, x3 R G B]
    raw = np.array([0.5, 1.0, 0.2,   0.25, 0.0, 0.7,   0.5, 0.5, 1.0], np.float32)
    alpha = np.asarray(P.f_act(raw.reshape(1, 1, 9)))[0, 0]
    # R: 0.25 / 0.5 = 0.5; G: 1 / 0.5 = 2 -> clip 1; B: -0.5 / 1 -> clip 0
    np.testing.assert_allclose(alpha, [0.5, 1.0, 0.0], rtol=1e-6)
    # x3 <= eps -> divide by eps: tiny positive numerator saturates at 1
    raw2 = np.array([1e-7, 0.0, 0.0, 0.0, 0.0, 0.0, -3.0, 0.0, 1e-9], np.float32)
    np.testing.assert_allclose(np.asarray(P.f_act(raw2.reshape(1, 1, 9)))[0, 0], [0.1, 0, 0],
                               rtol=1e-5)
    by_channel = raw.reshape(3, 3).T.reshape(1, 1, 9)  # [x1R x2R x3R, x1G ...]
    np.testing.assert_allclose(np.asarray(P.f_act(by_channel, grouping="by_channel"))[0, 0],
                               [0.5, 1.0, 0.0], rtol=1e-6)


def test_alpha_heads_and_mix():
    raw = np.array([[[-2.0, 0.0, 0.3]]], np.float32)
    np.testing.assert_allclose(np.asarray(alpha_direct(raw)), 1 / (1 + np.exp(-raw)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(alpha_direct(raw, "clip")), [[[0.0, 0.0, 0.3]]])
    assert ALPHA_HEADS == {"f_act": 9, "sigmoid": 3, "clip": 3, "closed_form_logit": 3}
    with pytest.raises(ConfigError, match="unknown alpha head"):
        P.alpha_from_head(raw, "softmax")
    x = np.array([[[1.0, 2.0, 3.0]]], np.float32)
    y = np.array([[[3.0, 2.0, 1.0]]], np.float32)
    np.testing.assert_allclose(np.asarray(P.mix(x, y, np.array([[[0.0, 0.5, 1.0]]]))),
                               [[[1.0, 2.0, 1.0]]])
    np.testing.assert_allclose(np.asarray(P.mix(x, y, np.array([[[0.25]]]))), [[[1.5, 2.0, 2.5]]])
    with pytest.raises(FrameError, match="'alpha' has shape"):
        P.mix(x, y, np.zeros((2, 1, 3), np.float32))
    with pytest.raises(FrameError, match=r"'raw' must have shape \(\.\.\., H, W, 9\)"):
        P.f_act(np.zeros((2, 2, 3)))
    with pytest.raises(ConfigError, match="grouping"):
        P.f_act(np.zeros((2, 2, 9)), grouping="rgb")


# ------------------------------------------------------------------------ errors


def test_tstat_config_and_input_errors():
    with pytest.raises(ConfigError, match="window"):
        P.TStatConfig(window=10)
    with pytest.raises(ConfigError, match=r"TStatConfig\.a"):
        P.TStatConfig(a=-1.0)
    with pytest.raises(ConfigError, match="squash"):
        P.TStatConfig(squash="tanh")
    x, y, var, alpha, z = make_scene(seed=0)
    with pytest.raises(ConfigError, match="unknown t-statistic option.*allowed"):
        P.t_statistic_scaling(alpha, x, z, var, windw=11)
    bad = var.copy()
    bad[2, 3, 1] = -1.0
    with pytest.raises(FrameError, match=r"variance must be finite and >= 0.*\(2, 3, 1\)"):
        P.t_statistic_scaling(alpha, x, z, bad)
    bad[2, 3, 1] = np.nan
    with pytest.raises(FrameError, match="variance"):
        P.t_statistic(x, z, bad)
    with pytest.raises(FrameError, match="'z' has shape"):
        P.t_statistic_scaling(alpha, x, z[:, :5], var)
    with pytest.raises(FrameError, match="'alpha' has shape"):
        P.t_statistic_scaling(alpha[:5], x, z, var)


def test_t_statistic_scaling_jits_inside_caller():
    x, y, var, alpha, z = make_scene(seed=4)
    jitted = jax.jit(lambda *a: P.consistent_mix(*a)[1])(x, y, alpha, var)
    eager = P.consistent_mix(x, y, alpha, var)[1]
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=1e-6, atol=1e-7)
    assert jnp.asarray(jitted).dtype == jnp.float32


def test_consistent_mix_is_differentiable_in_alpha():
    """Not used in training by the authors, but a pure function should differentiate: the
    gradient of sum(z') w.r.t. alpha is finite, and matches a central difference."""
    x, y, var, alpha, _ = make_scene(seed=8, mean_var=4e-4)

    def total(a):
        return jnp.sum(P.consistent_mix(x, y, a, var)[0])

    grad = np.asarray(jax.grad(total)(jnp.asarray(alpha)))
    assert np.isfinite(grad).all()
    direction = np.random.default_rng(0).normal(size=alpha.shape).astype(np.float32)
    with jax.enable_x64(True):
        args = [a.astype(np.float64) for a in (x, y, var, alpha, direction)]
        h = 1e-6

        def total64(a):
            return float(jnp.sum(P.consistent_mix(args[0], args[1], a, args[2])[0]))

        numeric = (total64(args[3] + h * args[4]) - total64(args[3] - h * args[4])) / (2 * h)
    np.testing.assert_allclose(np.sum(grad * direction), numeric, rtol=1e-3)
