"""NFOR (jaxden.denoise.nfor, on jaxden.denoise.nl_means) against slow NumPy references
written from BASELINES.md 6.x.

The references loop over pixels, offsets and patch pixels with Tungsten's formulas
(``nlMeansWeights``, ``nlMeans``, ``collaborativeRegression``, ``nforDenoiser``) in float64;
the regressions are ``np.linalg.lstsq`` on the square-root-weighted design with the ridge
rows. Frames are 10 x 12 with small windows for the references, 32 x 32 with Tungsten's
parameters for the end-to-end properties.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.testing import assert_allclose

from jaxden.denoise import nfor as N
from jaxden.denoise import nl_means as L
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

#: Small windows for the NumPy references (patch 1, windows 2, final feature window 1).
SMALL = N.NFORConfig(prefilter_patch=1, prefilter_window=2, regression_patch=1,
                     regression_window=2, selection_patch=1, selection_window=2,
                     final_feature_patch=1, final_feature_window=1, ridge=1e-4)


# ------------------------------------------------------------------------ NumPy references
def inside(shape, y, x):
    return 0 <= y < shape[0] and 0 <= x < shape[1]


def np_weights(guide, var, dy, dx, patch, k, scale):
    """Tungsten's nlMeansWeights, one pixel, one patch pixel at a time: (H, W, C)."""
    h, w, c = guide.shape
    out = np.zeros((h, w, c))
    for y in range(h):
        for x in range(w):
            if not inside(guide.shape, y + dy, x + dx):
                continue
            distances = []
            for ry in range(y - patch, y + patch + 1):
                for rx in range(x - patch, x + patch + 1):
                    if not (inside(guide.shape, ry, rx)
                            and inside(guide.shape, ry + dy, rx + dx)):
                        continue
                    vp, vq = var[ry, rx] * scale, var[ry + dy, rx + dx] * scale
                    diff = (guide[ry, rx] - guide[ry + dy, rx + dx]) ** 2
                    d = (diff - (vp + np.minimum(vp, vq))) / (1e-7 + k * k * (vp + vq))
                    distances.append(np.minimum(d, 1e4))
            out[y, x] = np.exp(-np.maximum(np.mean(distances, axis=0), 0.0))
            if dy == 0 and dx == 0:
                out[y, x] = np.maximum(out[y, x], 1e-4)
    return out


def np_nl_means(image, guide, var, patch, window, k, scale=1.0):
    """Tungsten's nlMeans: per-channel weights, sum over the window inside the image."""
    h, w, _ = guide.shape
    total, weights = np.zeros(image.shape), np.zeros(guide.shape)
    for dy in range(-window, window + 1):
        for dx in range(-window, window + 1):
            wt = np_weights(guide, var, dy, dx, patch, k, scale)
            for y in range(h):
                for x in range(w):
                    if inside(guide.shape, y + dy, x + dx):
                        total[..., y, x, :] += wt[y, x] * image[..., y + dy, x + dx, :]
                        weights[y, x] += wt[y, x]
    return total / weights


def np_window_weights(guide, var, patch, window, k, scale):
    """{(dy, dx): scalar weight map (H, W)}: the least channel's, as convertWeight."""
    return {(dy, dx): np_weights(guide, var, dy, dx, patch, k, scale).min(axis=-1)
            for dy in range(-window, window + 1) for dx in range(-window, window + 1)}


def np_fit(y, x, image, features, weights, window, ridge):
    """One pixel's weighted first-order fit by lstsq: beta (d, 3) and its rows."""
    rows, targets, w = [], [], []
    for dy in range(-window, window + 1):
        for dx in range(-window, window + 1):
            qy, qx = y + dy, x + dx
            if not inside(image.shape, qy, qx):
                continue
            rows.append([1.0, dx, dy, *(features[qy, qx] - features[y, x])])
            targets.append(image[qy, qx])
            w.append(weights[dy, dx][y, x])
    design, targets, w = np.array(rows), np.array(targets), np.array(w)
    gram_diagonal = np.einsum("n,ni,ni->i", w, design, design)
    penalty = np.diag(np.sqrt(ridge * gram_diagonal))[1:]
    stacked = np.concatenate([np.sqrt(w)[:, None] * design, penalty])
    rhs = np.concatenate([np.sqrt(w)[:, None] * targets, np.zeros((len(penalty), 3))])
    return np.linalg.lstsq(stacked, rhs, rcond=None)[0]


def np_collaborative(image, guide, features, var, patch, window, k, scale, ridge):
    """Tungsten's collaborativeRegression with lstsq fits."""
    h, w, _ = image.shape
    weights = np_window_weights(guide, var, patch, window, k, scale)
    total, norm = np.zeros((h, w, 3)), np.zeros((h, w, 1))
    for y in range(h):
        for x in range(w):
            beta = np_fit(y, x, image, features, weights, window, ridge)
            for dy in range(-window, window + 1):
                for dx in range(-window, window + 1):
                    qy, qx = y + dy, x + dx
                    if not inside(image.shape, qy, qx):
                        continue
                    row = np.array([1.0, dx, dy, *(features[qy, qx] - features[y, x])])
                    total[qy, qx] += weights[dy, dx][y, x] * (row @ beta)
                    norm[qy, qx] += weights[dy, dx][y, x]
    return total / norm


def np_select(ca, cb, var, filtered_a, filtered_b, cfg):
    """Tungsten's MSE estimate, its filtering, the binary map 'mse0 < mse1 ? 0 : 1', its
    filtering and the lerp (two bandwidths)."""
    mean = 0.5 * (ca + cb)
    filt = lambda image: np_nl_means(image, mean, var, cfg.selection_patch,
                                     cfg.selection_window, cfg.selection_bandwidth)
    mses = []
    for fa, fb in zip(filtered_a, filtered_b, strict=True):
        mse_a = (cb - fa) ** 2 - 2 * var
        mse_b = (ca - fb) ** 2 - 2 * var
        mses.append(filt((mse_a + mse_b) * 0.5 - (fb - fa) ** 2 * 0.25))
    selection = filt(np.where(mses[0] < mses[1], 0.0, 1.0))
    lerp = lambda f: f[0] + selection * (f[1] - f[0])
    return lerp(filtered_a), lerp(filtered_b)


def np_nfor(inputs: N.NFORInputs, cfg: N.NFORConfig):
    """nforDenoiser, composed of the references above."""
    ca, cb, var, fa, fb, fvar = (np.asarray(a, np.float64) for a in inputs)
    pf = lambda image, guide: np_nl_means(image, guide, fvar, cfg.prefilter_patch,
                                          cfg.prefilter_window, cfg.prefilter_bandwidth,
                                          cfg.prefilter_variance_scale)
    pfa, pfb = pf(fa, fb), pf(fb, fa)
    reg = lambda image, guide, feats, v, k: np_collaborative(
        image, guide, feats, v, cfg.regression_patch, cfg.regression_window, k,
        cfg.regression_variance_scale, cfg.ridge)
    filtered_a = [reg(ca, cb, pfb, var, k) for k in cfg.bandwidths]
    filtered_b = [reg(cb, ca, pfa, var, k) for k in cfg.bandwidths]
    ra, rb = np_select(ca, cb, var, filtered_a, filtered_b, cfg)
    feats = 0.5 * (pfa + pfb)
    feats = np_nl_means(feats, feats, 0.25 * (pfb - pfa) ** 2, cfg.final_feature_patch,
                        cfg.final_feature_window, cfg.final_feature_bandwidth)
    color = 0.5 * (ra + rb)
    return reg(color, color, feats, 0.25 * (rb - ra) ** 2, cfg.final_bandwidth)


# ------------------------------------------------------------------------ data
def random_inputs(seed, h=10, w=12, features=4):
    rng = np.random.default_rng(seed)
    smooth = rng.normal(size=(h, w, 3)).cumsum(0).cumsum(1) * 0.05 + 1.0
    color_a = (smooth + rng.normal(0, 0.1, (h, w, 3))).astype(np.float32)
    color_b = (smooth + rng.normal(0, 0.1, (h, w, 3))).astype(np.float32)
    feats = rng.normal(size=(h, w, features)).cumsum(1) * 0.3
    feats_a = (feats + rng.normal(0, 0.05, feats.shape)).astype(np.float32)
    feats_b = (feats + rng.normal(0, 0.05, feats.shape)).astype(np.float32)
    var = rng.uniform(0.002, 0.008, (h, w, 3)).astype(np.float32)
    fvar = (0.25 * (feats_a - feats_b) ** 2).astype(np.float32)
    return N.NFORInputs(color_a, color_b, var, feats_a, feats_b, fvar)


def scene(size=32, sigma=0.1, seed=0, own_variance=True, noise=True):
    """A seeded synthetic scene: piecewise-smooth colour over two regions with different
    depth / albedo / normal (feature edges) and a texture edge, and two halves with
    independent Gaussian noise of variance sigma^2 (each half's variance of its mean)."""
    y, x = np.mgrid[0:size, 0:size] / size
    left = x < 0.45
    depth = np.where(left, 2 + x, 5 - 2 * y)[..., None]
    albedo = np.stack([np.where(left, 0.8, 0.3), np.where(y > 0.6, 0.5, 0.7),
                       np.full_like(x, 0.4)], -1)
    normal = np.stack([np.where(left, 0.0, 0.6), 0 * x, np.where(left, 1.0, 0.8)], -1)
    color = albedo * (0.5 + 0.5 * np.sin(3 * x + 2 * y)[..., None]) + 0.1 * depth
    rng = np.random.default_rng(seed)

    def half():
        noisy = color + (rng.normal(0, sigma, color.shape) if noise else 0)
        return Frame(color=noisy.astype(np.float32), albedo=albedo.astype(np.float32),
                     normal=normal.astype(np.float32), depth=depth.astype(np.float32),
                     variance=np.full(color.shape, sigma**2, np.float32)
                     if own_variance else None)

    return color, half(), half()


@functools.partial(jax.jit, static_argnames=("patch", "window", "scale", "block"))
def jit_nl_means(image, guide, var, k, patch, window, scale=1.0, block=0):
    return L.nl_means(image, guide, var, patch, window, k, scale, block)


@functools.partial(jax.jit, static_argnames=("patch", "window", "ridge", "block"))
def jit_regression(image, guide, feats, var, k, patch, window, ridge, block=0):
    beta = L.regression_coefficients(image, guide, feats, var, patch, window, k, 2.0, ridge,
                                     block)
    out = L.collaborate(beta, guide, feats, var, patch, window, k, 2.0, block)
    return beta, out


jit_core = jax.jit(N.nfor_core, static_argnames="config")
jit_weights = jax.jit(L.nl_means_weights, static_argnames=("dy", "dx", "patch",
                                                            "variance_scale"))
jit_inputs = jax.jit(N.nfor_inputs, static_argnames="config")


# ------------------------------------------------------------------------ NL-means
@pytest.mark.parametrize(("dy", "dx", "patch", "scale"),
                         [(0, 0, 1, 2.0), (1, -2, 1, 2.0), (-3, 2, 2, 1.0), (2, 5, 0, 1.0)])
def test_nl_means_weights_match_numpy(dy, dx, patch, scale):
    inputs = random_inputs(1)
    guide = inputs.color_b
    var = inputs.color_variance.copy()
    var[:3, :4] = 0.0  # zero variance: only (near-)equal values keep a weight
    got = jit_weights(guide, var, dy=dy, dx=dx, patch=patch, k=0.7, variance_scale=scale)
    want = np_weights(guide.astype(np.float64), var.astype(np.float64), dy, dx, patch, 0.7,
                      scale)
    assert_allclose(np.asarray(got), want, rtol=2e-4, atol=1e-6)
    assert (np.asarray(got) > 0).any()


def test_nl_means_matches_numpy_and_shares_weights_over_a_stack():
    inputs = random_inputs(2)
    feats, guide, var = inputs.features_a, inputs.features_b, inputs.feature_variance
    got = jit_nl_means(feats, guide, var, 0.5, patch=1, window=2, scale=2.0)
    want = np_nl_means(feats.astype(np.float64), guide.astype(np.float64),
                       var.astype(np.float64), 1, 2, 0.5, 2.0)
    assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-5)
    stack = np.stack([feats, 2 * feats + 1])
    got_stack = jit_nl_means(stack, guide, var, 0.5, patch=1, window=2, scale=2.0)
    assert_allclose(np.asarray(got_stack[1]), 2 * np.asarray(got) + 1, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------ regression
def test_regression_at_one_pixel_matches_lstsq():
    inputs = random_inputs(3)
    image, guide, feats, var = (inputs.color_a, inputs.color_b, inputs.features_b,
                                inputs.color_variance)
    beta, _ = jit_regression(image, guide, feats, var, 1.0, patch=1, window=2, ridge=1e-4)
    weights = np_window_weights(guide.astype(np.float64), var.astype(np.float64), 1, 2, 1.0,
                                2.0)
    for y, x in [(5, 6), (0, 0), (9, 3), (4, 11)]:
        want = np_fit(y, x, image.astype(np.float64), feats.astype(np.float64), weights, 2,
                      1e-4)
        # the fitted values over the window, not the coefficients (collinear directions)
        rows = np.array([[1.0, dx, dy, *(feats[y + dy, x + dx] - feats[y, x])]
                         for dy in range(-2, 3) for dx in range(-2, 3)
                         if inside(image.shape, y + dy, x + dx)])
        assert_allclose(rows @ np.asarray(beta[y, x]), rows @ want, rtol=1e-3, atol=1e-3)
        assert_allclose(np.asarray(beta[y, x, 0]), want[0], rtol=1e-3, atol=1e-4)


def test_solve_regression_ridge_and_empty_columns():
    rng = np.random.default_rng(4)
    design = np.concatenate([np.ones((30, 1)), rng.normal(size=(30, 3)), np.zeros((30, 1))], 1)
    w = rng.uniform(0.1, 1.0, 30)
    y = rng.normal(size=(30, 3))
    gram = np.einsum("n,ni,nj->ij", w, design, design)
    upper = gram[np.triu_indices(5)]
    solve = jax.jit(L.solve_regression, static_argnames="ridge")
    beta = np.asarray(solve(jnp.asarray(upper, jnp.float32),
                            jnp.asarray(design.T @ (w[:, None] * y), jnp.float32), ridge=1e-3))
    penalty = np.diag(np.sqrt(1e-3 * np.diag(gram)))[1:]
    want = np.linalg.lstsq(np.concatenate([np.sqrt(w)[:, None] * design, penalty]),
                           np.concatenate([np.sqrt(w)[:, None] * y, np.zeros((4, 3))]),
                           rcond=None)[0]
    assert_allclose(beta, want, rtol=1e-4, atol=1e-5)
    assert np.all(beta[4] == 0)  # the empty column


def test_collaborative_regression_matches_numpy():
    inputs = random_inputs(5)
    image, guide, feats, var = (inputs.color_a, inputs.color_b, inputs.features_b,
                                inputs.color_variance)
    _, got = jit_regression(image, guide, feats, var, 0.5, patch=1, window=2, ridge=1e-4)
    want = np_collaborative(*(a.astype(np.float64) for a in (image, guide, feats, var)),
                            1, 2, 0.5, 2.0, 1e-4)
    assert_allclose(np.asarray(got), want, rtol=1e-3, atol=1e-3)


def test_blocks_do_not_change_the_result():
    """Blocks of 4 x 4 (not dividing 10 x 12; block origins, the padding past the image and
    the reassembly) against the whole image in one block (the CPU default at this size)."""
    inputs = random_inputs(6)
    args = (inputs.color_a, inputs.color_b, inputs.features_b, inputs.color_variance, 1.0)
    assert L.block_side(0) >= 12 or jax.default_backend() != "cpu"
    whole_beta, whole = jit_regression(*args, patch=1, window=2, ridge=1e-4)
    beta, blocks = jit_regression(*args, patch=1, window=2, ridge=1e-4, block=4)
    assert_allclose(np.asarray(blocks), np.asarray(whole), rtol=1e-4, atol=1e-4)
    assert_allclose(np.asarray(beta[..., 0, :]), np.asarray(whole_beta[..., 0, :]), rtol=1e-4,
                    atol=1e-4)


# ------------------------------------------------------------------------ selection + pipeline
def test_selection_matches_numpy_loop():
    inputs = random_inputs(7)
    rng = np.random.default_rng(7)
    filtered_a = np.stack([inputs.color_a + rng.normal(0, 0.05, inputs.color_a.shape)
                           for _ in range(2)]).astype(np.float32)
    filtered_b = np.stack([inputs.color_b + rng.normal(0, 0.05, inputs.color_b.shape)
                           for _ in range(2)]).astype(np.float32)
    select = jax.jit(N.select_bandwidths, static_argnames="config")
    got_a, got_b, selection = select(inputs, filtered_a, filtered_b, config=SMALL)
    f64 = lambda a: np.asarray(a, np.float64)
    want_a, want_b = np_select(f64(inputs.color_a), f64(inputs.color_b),
                               f64(inputs.color_variance), f64(filtered_a), f64(filtered_b),
                               SMALL)
    assert_allclose(np.asarray(got_a), want_a, rtol=1e-4, atol=1e-5)
    assert_allclose(np.asarray(got_b), want_b, rtol=1e-4, atol=1e-5)
    assert_allclose(np.asarray(selection).sum(0), 1.0, atol=1e-5)
    assert 0 < float(np.asarray(selection[1]).mean()) < 1


def test_pipeline_matches_numpy():
    """Cross-prefiltering, the cross regressions at both bandwidths, selection and the second
    pass, end to end."""
    inputs = random_inputs(8)
    got = jit_core(inputs, config=SMALL)
    want = np_nfor(inputs, SMALL)
    assert_allclose(np.asarray(got), want, rtol=2e-3, atol=2e-3)


def test_exact_on_colour_linear_in_the_features():
    """Noise-free halves whose colour is an affine function of the features and the pixel
    position: every regression fits it exactly, so NFOR returns it (up to the ridge's 1e-5
    shrinkage; the claimed variance 0.01 makes the first pass's weights wide, so its fits use
    whole windows and a wrong fit would show)."""
    size = 32
    _, half, _ = scene(size, noise=False)
    rng = np.random.default_rng(9)
    feats = np.concatenate([half.depth, half.albedo, half.normal], -1).astype(np.float64)
    y, x = np.mgrid[0:size, 0:size]
    color = (1.0 + feats @ rng.normal(0, 0.3, (7, 3)) + 0.01 * x[..., None]
             - 0.02 * y[..., None])
    frame = half.replace(color=color.astype(np.float32))
    frame = frame.replace(variance=np.full(color.shape, 0.01, np.float32))
    out = np.asarray(N.nfor(frame, frame))
    assert_allclose(out, color, atol=2e-4 * np.abs(color).max())


def test_noisy_scene_mse_well_below_the_halves_mean():
    """Seeded scene (seed 0, sigma 0.1 per half, 32 x 32, Tungsten's parameters): the output's
    MSE is below a fifth of the halves' mean's (measured: about 1/30)."""
    color, a, b = scene(32, sigma=0.1, seed=0)
    out = np.asarray(N.nfor(a, b))
    noisy = 0.5 * (a.color + b.color)
    mse_out = np.mean((out - color) ** 2)
    mse_noisy = np.mean((noisy - color) ** 2)
    assert np.isfinite(out).all()
    assert mse_out < 0.2 * mse_noisy, (mse_out, mse_noisy)


@pytest.mark.slow
def test_noisy_scene_larger_and_without_own_variance():
    """64 x 64, sigma 0.2 (seed 3), variance from the halves' difference: still below a fifth
    (measured: about 1/70)."""
    color, a, b = scene(64, sigma=0.2, seed=3, own_variance=False)
    out = np.asarray(N.nfor(a, b))
    mse_out = np.mean((out - color) ** 2)
    mse_noisy = np.mean((0.5 * (a.color + b.color) - color) ** 2)
    assert mse_out < 0.2 * mse_noisy, (mse_out, mse_noisy)


# ------------------------------------------------------------------------ inputs, buffers
def test_inputs_variances_and_halves():
    _, a, b = scene(8, sigma=0.1, seed=1)
    inputs = jit_inputs([a, b])
    assert_allclose(np.asarray(inputs.color_variance), 0.25 * (0.01 + 0.01), rtol=1e-6)
    feats = lambda f: np.concatenate([f.depth, f.albedo, f.normal], -1)
    assert_allclose(np.asarray(inputs.feature_variance),
                    0.25 * (feats(a) - feats(b)) ** 2, atol=1e-7)
    no_var = jit_inputs([a.replace(variance=None), b])  # not all carry one: the spread
    assert_allclose(np.asarray(no_var.color_variance), 0.25 * (a.color - b.color) ** 2,
                    rtol=1e-5, atol=1e-9)
    # four buffers: halves 0, 2 and 1, 3; colour variance pooled sum var_k / 16
    _, c, d = scene(8, sigma=0.1, seed=2)
    four = jit_inputs([a, b, c, d])
    assert_allclose(np.asarray(four.color_a), 0.5 * (a.color + c.color), rtol=1e-6)
    assert_allclose(np.asarray(four.color_b), 0.5 * (b.color + d.color), rtol=1e-6)
    assert_allclose(np.asarray(four.color_variance), 4 * 0.01 / 16, rtol=1e-6)
    stack = np.stack([a.color, b.color, c.color, d.color])
    spread = np.sum((stack - stack.mean(0)) ** 2, 0) / 12
    bare = [f.replace(variance=None) for f in (a, b, c, d)]
    assert_allclose(np.asarray(jit_inputs(bare).color_variance), spread, rtol=1e-4,
                    atol=1e-9)


def four_buffers_and_halves():
    """Four 10 x 12 buffers without own variances (noise-free features) and the two half
    Frames that give NFOR the same inputs: the halves' colours, and a variance whose
    (vA + vB) / 4 is the spread of the four."""
    buffers = [scene(16, sigma=0.1, seed=seed, own_variance=False)[1].crop(0, 0, 10, 12)
               for seed in range(4)]
    stack = np.stack([f.color for f in buffers])
    spread = np.sum((stack - stack.mean(0)) ** 2, 0) / 12
    halves = [buffers[i].replace(color=0.5 * (buffers[i].color + buffers[i + 2].color),
                                 variance=(2 * spread).astype(np.float32)) for i in (0, 1)]
    return buffers, halves


def test_nfor_frames_of_four_buffers_is_nfor_of_their_halves():
    buffers, halves = four_buffers_and_halves()
    four, two = jit_inputs(buffers, config=SMALL), jit_inputs(halves, config=SMALL)
    for name, got, want in zip(four._fields, four, two, strict=True):
        assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-8, err_msg=name)
    out = np.asarray(N.nfor(*halves, SMALL))
    assert_allclose(out, np.asarray(jit_core(two, config=SMALL)), rtol=1e-6, atol=1e-6)
    assert_allclose(np.asarray(N.nfor_frames(halves, SMALL)), out)


def test_errors():
    _, a, b = scene(8)
    with pytest.raises(FrameError, match="at least 2"):
        N.nfor_frames([a])
    with pytest.raises(FrameError, match="albedo"):
        N.nfor(a.replace(albedo=None), b)
    with pytest.raises(FrameError, match="buffer 1"):
        N.nfor(a, b.crop(0, 0, 4, 4))
    with pytest.raises(FrameError, match="single"):
        N.nfor(a.map(lambda v: v[None]), b.map(lambda v: v[None]))
    with pytest.raises(ConfigError, match="features"):
        N.NFORConfig(features=("depth", "texture"))
    with pytest.raises(ConfigError, match="bandwidths"):
        N.NFORConfig(bandwidths=())
    with pytest.raises(ConfigError, match="ridge"):
        N.NFORConfig(ridge=0.0)


# ------------------------------------------------------------------------ tiling, hook
def test_radius():
    assert N.nfor_radius(N.NFOR_TUNGSTEN) == 65
    assert N.nfor_radius(SMALL) == 16
    assert N.nfor_radius(dataclasses.replace(SMALL, second_pass=False)) == 11


@pytest.mark.slow
def test_tiles_equal_the_whole_frame_and_the_radius_bounds_the_field():
    _, a, b = scene(56, sigma=0.1, seed=6)
    whole = N.BUFFER_DENOISERS["nfor"].denoise([a, b], SMALL, tile=0)
    tiled = N.denoise_buffers([a, b], SMALL, tile=16)
    assert_allclose(tiled, whole, rtol=1e-4, atol=1e-4)
    radius = N.nfor_radius(SMALL)
    changed = a.replace(color=a.color.copy())
    changed.color[28, 28] += 5.0
    moved = N.denoise_buffers([changed, b], SMALL, tile=0)
    ys, xs = np.nonzero(np.abs(moved - whole).max(-1) > 0)
    assert 0 < max(np.abs(ys - 28).max(), np.abs(xs - 28).max()) <= radius  # measured: 14


def test_buffer_denoiser_hook():
    hook = N.BUFFER_DENOISERS["nfor"]
    assert hook.required(N.NFOR_TUNGSTEN) == ("color", "depth", "albedo", "normal")
    assert hook.radius(SMALL) == N.nfor_radius(SMALL)
    _, halves = four_buffers_and_halves()
    out = hook.denoise(halves, SMALL, tile=0)
    assert out.dtype == np.float32 and out.shape == (10, 12, 3)
    assert_allclose(out, np.asarray(N.nfor(*halves, SMALL)), rtol=1e-6, atol=1e-6)


def test_jaxden_denoise_runs_nfor_on_the_buffers_of_a_render(tmp_path, capsys):
    """`jaxden render --buffers 2` then `jaxden denoise IN --model nfor --buffers B0 B1`: the
    image equals nfor_frames of the buffers as read, and its error against a 512-spp render
    is below the input's (the Cornell box, 40 x 32, 16 spp, seed 3); nfor without buffers,
    and a single-frame denoiser with them, are one error line each."""
    from helpers import assert_one_error_line, run_cli

    from jaxden.io.exr import read_frame, read_image

    noisy = tmp_path / "box.exr"
    assert run_cli(["render", "cornell-box", "--spp", "16", "--size", "40x32", "--seed", "3",
                    "--buffers", "2", "--out", noisy], capsys)[0] == 0
    reference = tmp_path / "ref.exr"
    assert run_cli(["render", "cornell-box", "--spp", "512", "--size", "40x32", "--seed", "99",
                    "--out", reference], capsys)[0] == 0
    buffers = [tmp_path / "box.b0.exr", tmp_path / "box.b1.exr"]
    out = tmp_path / "nfor.exr"
    code, lines, _ = run_cli(["denoise", noisy, "--model", "nfor", "--buffers", *buffers,
                              "--out", out], capsys)
    assert code == 0, lines
    image = read_image(out)
    frames = [read_frame(b) for b in buffers]
    assert_allclose(image, np.asarray(N.nfor_frames(frames)), rtol=1e-5, atol=1e-6)
    truth = read_image(reference)
    mse = float(np.mean((image - truth) ** 2))
    mse_in = float(np.mean((read_image(noisy) - truth) ** 2))
    assert mse < 0.7 * mse_in, (mse, mse_in)
    code, lines, _ = run_cli(["denoise", noisy, "--model", "nfor", "--out", out], capsys)
    assert_one_error_line(code, lines, "nfor", "--buffers")
    code, lines, _ = run_cli(["denoise", noisy, "--model", "wskp-6", "--buffers", *buffers,
                              "--out", out], capsys)
    assert_one_error_line(code, lines, "wskp-6", "single frame")
