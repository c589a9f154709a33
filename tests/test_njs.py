"""Neural James-Stein combiner (jaxden.denoise.njs, jaxden.denoise.nn.njs): the cross
regression and the James-Stein combination against slow NumPy references written from the
authors' CUDA kernels (``ops/js.cu.cc``: ``OlsKernel`` + ``OlsFinalizeKernel``,
``WeightAvgKernel``, ``CalcShrinkageKernel``, ``CombinerKernel``), their properties, the
network's shapes, ranges and size, the loss against its NumPy formula, and gradients through
network and combination.

The references loop over pixels and window positions in float64 with the kernels' mirrored
index ``getImgIdx`` (``2 W - 2 - x`` past the right edge, ``|x|`` past the left). Images are
9 x 8 with a 5 x 5 or 7 x 7 regression window and 5 x 5 or 15 x 15 combination windows.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.testing import assert_allclose

from jaxden.denoise import njs as N
from jaxden.denoise.nn.njs import NJSNet, njs_inputs
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame
from jaxden.train.losses import LOSSES, PER_IMAGE, get_loss

H, W = 9, 8


# ------------------------------------------------------------------------ NumPy references
def mirror(i: int, n: int) -> int:
    """The authors' getImgIdx along one axis."""
    return 2 * n - 2 - i if i >= n else abs(i)


def window(cy, cx, radius, height, width):
    """Row-major mirrored window positions of (cy, cx)."""
    return [(mirror(y, height), mirror(x, width))
            for y in range(cy - radius, cy + radius + 1)
            for x in range(cx - radius, cx + radius + 1)]


def np_ols(noisy, groups, v, size, ridge=0.1, min_weight=1e-5):
    """OlsKernel + OlsFinalizeKernel, one centre pixel at a time (float64)."""
    noisy = np.asarray(noisy, np.float64)
    features = np.concatenate([np.asarray(g, np.float64) for g in groups], -1)
    sizes = [g.shape[-1] for g in groups]
    bounds = np.cumsum([0, *sizes])
    v = np.broadcast_to(np.asarray(v, np.float64), (*noisy.shape[:2], 1))[..., 0]
    height, width, m = noisy.shape
    radius = size // 2
    total, weights = np.zeros((height, width, m)), np.zeros((height, width))
    for cy in range(height):
        for cx in range(width):
            qs = window(cy, cx, radius, height, width)
            centre = features[cy, cx]
            scale = []
            for g, n in enumerate(sizes):
                part = slice(bounds[g], bounds[g + 1])
                largest = max(np.linalg.norm(features[y, x, part] - centre[part]) for y, x in qs)
                scale += [1.0 / (largest + 0.1)] * n
            rows = np.array([np.concatenate([[1.0], (features[y, x] - centre) * scale])
                             for y, x in qs])
            guide = slice(0, sizes[0])
            w = np.array([np.exp(-np.sum((features[y, x, guide] - centre[guide]) ** 2)
                                 / (2 * v[cy, cx] + 0.01)) for y, x in qs])
            targets = np.array([noisy[y, x] for y, x in qs])
            matrix = rows.T @ (w[:, None] * rows) + ridge * np.eye(rows.shape[1])
            beta = np.linalg.solve(matrix, rows.T @ (w[:, None] * targets))
            for (y, x), row, wq in zip(qs, rows, w, strict=True):
                total[y, x] += wq * (row @ beta)
                weights[y, x] += wq
    guide_image = np.asarray(groups[0], np.float64)
    out = total / np.maximum(weights, 1e-300)[..., None]
    return np.where((weights < min_weight)[..., None], guide_image, out)


def np_weighted_variance(variance, weights, size):
    height, width, _ = variance.shape
    out = np.zeros(variance.shape)
    for y in range(height):
        for x in range(width):
            qs = window(y, x, size // 2, height, width)
            w = weights[y, x].astype(np.float64)
            out[y, x] = sum(w[n] * variance[q] for n, q in enumerate(qs)) / max(w.sum(), 1e-5)
    return out


def np_shrinkage(noisy, biased, var_hat, size):
    height, width, _ = noisy.shape
    rho = np.zeros(noisy.shape)
    for y in range(height):
        for x in range(width):
            sse = sum((noisy[q] - biased[q]) ** 2 for q in window(y, x, size // 2, height, width))
            rho[y, x] = np.maximum(0.0, 1.0 - (size * size - 2) * var_hat[y, x]
                                   / np.maximum(sse, 1e-5))
    return rho


def np_james_stein(noisy, biased, rho, size):
    height, width, _ = noisy.shape
    out = np.zeros(noisy.shape)
    for y in range(height):
        for x in range(width):
            mean_rho = np.mean([rho[q] for q in window(y, x, size // 2, height, width)], axis=0)
            out[y, x] = biased[y, x] + mean_rho * (noisy[y, x] - biased[y, x])
    return out


def half(rng, shape=(H, W), visibility=False) -> N.HalfBuffer:
    """A half buffer with smooth structure plus noise (features vary, weights spread)."""
    yy, xx = np.meshgrid(np.linspace(0, 1, shape[-2]), np.linspace(0, 1, shape[-1]),
                         indexing="ij")
    base = np.stack([yy, xx, yy * xx], -1)
    lead = shape[:-2]

    def noisy_image(channels, amplitude):
        return (np.broadcast_to(base[..., :channels], (*lead, *base.shape[:2], channels))
                + amplitude * rng.uniform(-1, 1, (*shape, channels))).astype(np.float32)

    return N.HalfBuffer(color=noisy_image(3, 0.3) + 0.5, denoised=noisy_image(3, 0.05) + 0.5,
                        albedo=noisy_image(3, 0.2), normal=noisy_image(3, 0.2),
                        depth=noisy_image(1, 0.1) + 1.0,
                        visibility=(rng.uniform(0, 1, (*shape, 1)).astype(np.float32)
                                    if visibility else None))


# ------------------------------------------------------------------------ cross regression
@pytest.mark.parametrize("size, block, visibility", [(5, 0, True), (7, 4, False)])
def test_collaborative_ols_matches_numpy(size, block, visibility):
    """Feature scaling, weights with a per-pixel bandwidth, ridge, mirrored borders and the
    collaborative average; 4 x 4 blocks (with a partial last block) give the same result."""
    rng = np.random.default_rng(0)
    a, b = half(rng, visibility=visibility), half(rng, visibility=visibility)
    v = rng.uniform(0.01, 0.2, (H, W, 1)).astype(np.float32)
    out = N.collaborative_ols(a.color, b.feature_groups(), v, window=size, block=block)
    expected = np_ols(a.color, b.feature_groups(), v, size)
    assert_allclose(np.asarray(out), expected, rtol=2e-4, atol=2e-5)


def test_collaborative_ols_ridge_and_batch():
    """Another ridge and a scalar bandwidth; a (2, H, W) batch equals each image alone."""
    rng = np.random.default_rng(1)
    a, b = half(rng, (2, H, W)), half(rng, (2, H, W))
    out = N.collaborative_ols(a.color, b.feature_groups(), 0.03, window=5, ridge=0.5)
    for i in range(2):
        expected = np_ols(a.color[i], [g[i] for g in b.feature_groups()], 0.03, 5, ridge=0.5)
        assert_allclose(np.asarray(out[i]), expected, rtol=2e-4, atol=2e-5)


def test_collaborative_ols_falls_back_to_the_guide():
    """Below ``min_weight`` total weight the denoised guide comes back, bit for bit (with the
    authors' 1e-5 it never happens for finite inputs: every pixel weighs itself by 1)."""
    rng = np.random.default_rng(2)
    a, b = half(rng), half(rng)
    out = N.collaborative_ols(a.color, b.feature_groups(), 0.05, window=5, min_weight=1e9)
    np.testing.assert_array_equal(np.asarray(out), b.denoised)
    expected = np_ols(a.color, b.feature_groups(), 0.05, 5, min_weight=1e9)
    np.testing.assert_array_equal(expected, b.denoised)


def test_constant_visibility_is_the_same_as_none():
    """A constant feature has zero differences: its column decouples (ridge only) and its
    coefficient is 0, so jaxden's 11-column design fits as the authors' 12 with a constant
    visibility."""
    rng = np.random.default_rng(3)
    a, b = half(rng), half(rng)
    v = rng.uniform(0.01, 0.2, (H, W, 1)).astype(np.float32)
    without = N.collaborative_ols(a.color, b.feature_groups(), v, window=5)
    constant = b._replace(visibility=np.full((H, W, 1), 0.7, np.float32))
    with_it = N.collaborative_ols(a.color, constant.feature_groups(), v, window=5)
    assert_allclose(np.asarray(with_it), np.asarray(without), rtol=1e-5, atol=1e-6)


def test_cross_regressions_and_bandwidth():
    rng = np.random.default_rng(4)
    a, b = half(rng), half(rng)
    grey = np.mean((a.denoised - b.denoised) ** 2 / 2, -1, keepdims=True)
    assert_allclose(np.asarray(N.bandwidth_variance(a.denoised, b.denoised, "pixel")), grey,
                    rtol=1e-6)
    image = np.asarray(N.bandwidth_variance(a.denoised, b.denoised, "image"))
    assert image.shape == (H, W, 1)
    assert_allclose(image, np.full((H, W, 1), grey.mean()), rtol=1e-5)
    ols_a, ols_b = N.cross_regressions(a, b, "image", window=5)
    # olsA: A's colour on B's features; olsB: B's on A's
    assert_allclose(np.asarray(ols_a), np_ols(a.color, b.feature_groups(), grey.mean(), 5),
                    rtol=2e-4, atol=2e-5)
    assert_allclose(np.asarray(ols_b), np_ols(b.color, a.feature_groups(), grey.mean(), 5),
                    rtol=2e-4, atol=2e-5)
    swapped = N.cross_regressions(b, a, "image", window=5)
    assert_allclose(np.asarray(swapped[0]), np.asarray(ols_b), rtol=1e-6)
    with pytest.raises(ConfigError, match="bandwidth"):
        N.bandwidth_variance(a.denoised, b.denoised, "frame")


def test_half_buffers_normalise_depth_by_the_largest():
    rng = np.random.default_rng(5)

    def frame(depth_max):
        return Frame(color=rng.uniform(size=(H, W, 3)).astype(np.float32),
                     albedo=rng.uniform(size=(H, W, 3)).astype(np.float32),
                     normal=rng.uniform(size=(H, W, 3)).astype(np.float32),
                     depth=rng.uniform(0, depth_max, (H, W, 1)).astype(np.float32))

    fa, fb = frame(3.0), frame(5.0)
    a, b = N.half_buffers(fa, fb, fa.color, fb.color)
    largest = max(fa.depth.max(), fb.depth.max())
    assert_allclose(np.asarray(a.depth), fa.depth / largest, rtol=1e-6)
    assert_allclose(np.asarray(b.depth), fb.depth / largest, rtol=1e-6)
    assert a.visibility is None
    with pytest.raises(FrameError, match="depth"):
        N.half_buffers(fa.replace(depth=None), fb, fa.color, fb.color)


def test_cross_regression_checks():
    rng = np.random.default_rng(6)
    a, b = half(rng), half(rng)
    with pytest.raises(FrameError, match="at least 9 x 9"):  # radius 8 > W - 1
        N.collaborative_ols(a.color, b.feature_groups(), 0.1, window=17)
    with pytest.raises(ConfigError, match="odd"):
        N.collaborative_ols(a.color, b.feature_groups(), 0.1, window=4)
    with pytest.raises(ConfigError, match="ridge"):
        N.collaborative_ols(a.color, b.feature_groups(), 0.1, window=5, ridge=0.0)
    with pytest.raises(FrameError, match="group 1"):
        N.collaborative_ols(a.color, (b.denoised, b.albedo[:4]), 0.1, window=5)
    with pytest.raises(FrameError, match="guide"):
        N.collaborative_ols(a.color, (b.depth, b.albedo), 0.1, window=5)
    with pytest.raises(FrameError, match="broadcast"):
        N.collaborative_ols(a.color, b.feature_groups(), np.zeros((H, 3, 1)), window=5)
    with pytest.raises(FrameError, match="both halves"):
        N.cross_regressions(a, b._replace(visibility=b.depth), window=5)


# ------------------------------------------------------------------------- the combination
def combination_inputs(rng, shape=(H, W), size=15):
    noisy = rng.uniform(0, 2, (*shape, 3)).astype(np.float32)
    variance = rng.uniform(0, 0.05, (*shape, 3)).astype(np.float32)
    ols_a = (noisy + rng.normal(0, 0.3, noisy.shape)).astype(np.float32)
    ols_b = (noisy + rng.normal(0, 0.3, noisy.shape)).astype(np.float32)
    weights = rng.uniform(1e-4, 1, (*shape, size * size)).astype(np.float32)
    alpha = rng.uniform(0, 1, (*shape, 1)).astype(np.float32)
    return noisy, variance, ols_a, ols_b, weights, alpha


@pytest.mark.parametrize("size", [5, 15])
def test_combination_matches_numpy(size):
    """Variance average, shrinkage and combination on a 9 x 8 image; 15 x 15 windows mirror
    across almost the whole image."""
    rng = np.random.default_rng(7)
    noisy, variance, ols_a, ols_b, weights, alpha = combination_inputs(rng, size=size)
    var_hat = np_weighted_variance(variance, weights, size)
    assert_allclose(np.asarray(N.weighted_variance(variance, weights, size)), var_hat,
                    rtol=1e-5, atol=1e-8)
    biased = alpha * ols_a + (1 - alpha) * ols_b
    # variances spread so that some rho are clipped at 0 and some are not
    var_hat = var_hat * rng.uniform(0, 5, var_hat.shape)
    rho = np_shrinkage(noisy, biased, var_hat, size)
    assert 0 < np.mean(rho == 0) < 1
    assert_allclose(np.asarray(N.shrinkage(noisy, biased, var_hat.astype(np.float32), size)),
                    rho, rtol=1e-4, atol=1e-5)
    expected = np_james_stein(noisy, biased, rho, size)
    assert_allclose(np.asarray(N.james_stein(noisy, biased, rho.astype(np.float32), size)),
                    expected, rtol=1e-5, atol=1e-6)
    whole = N.js_combine(noisy, variance, ols_a, ols_b, weights, alpha, size)
    rho = np_shrinkage(noisy, biased, np_weighted_variance(variance, weights, size), size)
    assert_allclose(np.asarray(whole), np_james_stein(noisy, biased, rho, size), rtol=1e-4,
                    atol=1e-5)


def test_variance_weights_are_row_major():
    """Weight channel n reads the offset (n // k - k // 2, n % k - k // 2)."""
    rng = np.random.default_rng(8)
    variance = rng.uniform(size=(20, 20, 3)).astype(np.float32)
    for n in (0, 7, 16, 112, 224):
        weights = np.zeros((20, 20, 225), np.float32)
        weights[..., n] = 2.0
        out = np.asarray(N.weighted_variance(variance, weights))
        dy, dx = n // 15 - 7, n % 15 - 7
        np.testing.assert_allclose(out[10, 10], variance[10 + dy, 10 + dx], rtol=1e-6)
    # all weights zero: the 1e-5 floor keeps it finite (0)
    assert not np.asarray(N.weighted_variance(variance, np.zeros((20, 20, 225)))).any()


def test_combination_properties():
    """rho and its mean lie in [0, 1], so the output lies between z and y per channel; a huge
    variance gives z; a zero variance gives y; z = y gives y; the clamp only cuts below 0."""
    rng = np.random.default_rng(9)
    noisy, variance, ols_a, ols_b, weights, alpha = combination_inputs(rng, (2, 12, 10))
    biased = alpha * ols_a + (1 - alpha) * ols_b
    var_hat = np.asarray(N.weighted_variance(variance, weights))
    rho = np.asarray(N.shrinkage(noisy, biased, var_hat))
    assert rho.min() >= 0 and rho.max() <= 1
    out = np.asarray(N.js_combine(noisy, variance, ols_a, ols_b, weights, alpha))
    low, high = np.minimum(noisy, biased), np.maximum(noisy, biased)
    assert np.all(out >= low - 1e-6) and np.all(out <= high + 1e-6)
    huge = N.js_combine(noisy, np.full_like(variance, 1e6), ols_a, ols_b, weights, alpha)
    assert_allclose(np.asarray(huge), biased, rtol=1e-6, atol=1e-7)
    zero = N.js_combine(noisy, np.zeros_like(variance), ols_a, ols_b, weights, alpha)
    assert_allclose(np.asarray(zero), noisy, rtol=1e-6, atol=1e-6)
    same = N.js_combine(noisy, variance, noisy, noisy, weights, alpha)
    assert_allclose(np.asarray(same), noisy, rtol=1e-6, atol=1e-7)
    negative = ols_a - 3.0
    unclamped = np.asarray(N.js_combine(noisy, variance, negative, negative, weights, alpha))
    clamped = np.asarray(N.js_combine(noisy, variance, negative, negative, weights, alpha,
                                      clamp=True))
    assert unclamped.min() < 0
    np.testing.assert_array_equal(clamped, np.maximum(unclamped, 0))


def test_combination_checks():
    rng = np.random.default_rng(10)
    noisy, variance, ols_a, ols_b, weights, alpha = combination_inputs(rng)
    with pytest.raises(FrameError, match="weights must have shape"):
        N.weighted_variance(variance, weights[..., :224])
    with pytest.raises(FrameError, match="alpha must have shape"):
        N.js_combine(noisy, variance, ols_a, ols_b, weights, alpha[..., :4, :])
    with pytest.raises(FrameError, match="at least 8 x 8"):
        N.shrinkage(noisy[:7], ols_a[:7], variance[:7])
    with pytest.raises(ConfigError, match="odd"):
        N.james_stein(noisy, ols_a, variance, kernel_size=4)


# ------------------------------------------------------------------------------ network
@pytest.fixture(scope="module")
def params():
    return jax.jit(N.njs_init)(jax.random.PRNGKey(0))


def test_network_shapes_ranges_and_size(params):
    """Odd sizes are padded to a multiple of 4 and cropped; weights > 0, alpha in (0, 1);
    the authors' 539426 parameters."""
    count = sum(np.size(p) for p in jax.tree_util.tree_leaves(params))
    assert count == N.parameter_count() == 539426
    rng = np.random.default_rng(11)
    x = rng.uniform(0, 2, (2, 13, 10, 12)).astype(np.float32)
    weights, alpha = jax.jit(NJSNet().apply)(params, x)
    assert weights.shape == (2, 13, 10, 225) and alpha.shape == (2, 13, 10, 1)
    assert weights.min() >= np.float32(1e-4) and 0 < float(alpha.min()) <= float(alpha.max()) < 1
    with pytest.raises(FrameError, match="ols_b"):
        njs_inputs(x[..., :3], x[..., :3], x[..., :3], x[..., :2])


def test_gradients_through_network_and_combination(params):
    """jax.grad of the loss with respect to the network parameters: finite everywhere and
    reaching the first and the last convolution."""
    rng = np.random.default_rng(12)
    noisy, variance, ols_a, ols_b, _, _ = combination_inputs(rng, (1, 16, 16))
    reference = np.clip(noisy + rng.normal(0, 0.1, noisy.shape), 0, None).astype(np.float32)
    loss = get_loss("relmse_njs")

    def objective(p):
        return loss(N.njs_apply(p, noisy, variance, ols_a, ols_b), reference)

    grads = jax.jit(jax.grad(objective))(params)["params"]
    for leaf in jax.tree_util.tree_leaves(grads):
        assert np.all(np.isfinite(leaf))
    assert float(jnp.abs(grads["out"]["kernel"]).max()) > 0
    assert float(jnp.abs(grads["enc1a"]["kernel"]).max()) > 0


def test_whole_combiner_from_half_buffers(params):
    """Cross regressions (small window), network and combination: clamped output, as the
    parts compose."""
    rng = np.random.default_rng(13)
    a, b = half(rng, (12, 12)), half(rng, (12, 12))
    variance = rng.uniform(0, 0.02, (12, 12, 3)).astype(np.float32)
    config = N.NJSConfig(ols_window=5)
    out = np.asarray(jax.jit(N.njs_combiner, static_argnums=4)(params, a, b, variance, config))
    ols_a, ols_b = N.cross_regressions(a, b, "image", window=5)
    noisy = (a.color + b.color) / 2
    apply = jax.jit(N.njs_apply, static_argnames=("config", "clamp"))
    expected = np.maximum(np.asarray(apply(params, noisy, variance, ols_a, ols_b)), 0)
    assert out.shape == (12, 12, 3)
    assert_allclose(out, expected, rtol=1e-5, atol=1e-6)
    with pytest.raises(ConfigError, match="odd"):
        N.NJSConfig(ols_window=50)


# ---------------------------------------------------------------------------------- loss
def test_relmse_njs_loss_matches_numpy():
    rng = np.random.default_rng(14)
    x = rng.normal(0.5, 2.0, (2, 5, 6, 3)).astype(np.float32)
    y = rng.normal(0.5, 2.0, (2, 5, 6, 3)).astype(np.float32)
    tx, ty = np.sign(x) * np.log1p(np.abs(x)), np.sign(y) * np.log1p(np.abs(y))
    per_pixel = (tx - ty) ** 2 / (ty.mean(-1, keepdims=True) ** 2 + 0.01)
    assert "relmse_njs" in LOSSES
    assert_allclose(float(get_loss("relmse_njs")(x, y)), per_pixel.mean(), rtol=1e-5)
    assert_allclose(np.asarray(PER_IMAGE["relmse_njs"](x, y)), per_pixel.mean(axis=(1, 2, 3)),
                    rtol=1e-5)
    grad = jax.grad(get_loss("relmse_njs"))(x, y)
    # d/dx: 2 (x' - y') / (1 + |x|) / (mean_c(y')^2 + 0.01) / n
    expected = 2 * (tx - ty) / (1 + np.abs(x)) / (ty.mean(-1, keepdims=True) ** 2 + 0.01) / x.size
    assert_allclose(np.asarray(grad), expected, rtol=1e-4, atol=1e-9)
