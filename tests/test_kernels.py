"""Tests for jaxden.denoise.kernels: the WSKP filter (unfold and box forms), fusion and decoder."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxden.denoise import kernels
from jaxden.errors import ConfigError, FrameError


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def _inputs(rng, shape, importance_scale=2.0):
    """Colour (shape + (3,)) of either sign and importance (shape) ~ N(0, scale^2)."""
    color = rng.normal(0.5, 1.0, shape + (3,)).astype(np.float32)
    importance = (importance_scale * rng.standard_normal(shape)).astype(np.float32)
    return color, importance


def _numpy_filter(color, importance, k):
    """Float64 brute force, pixel by pixel, straight from the paper's Eqs. 3-4."""
    color = np.asarray(color, np.float64)
    importance = np.asarray(importance, np.float64)
    height, width, _ = color.shape
    out = np.zeros_like(color)
    r = k // 2
    for y in range(height):
        for x in range(width):
            ys = slice(max(y - r, 0), min(y + r + 1, height))
            xs = slice(max(x - r, 0), min(x + r + 1, width))
            logits = importance[ys, xs]
            weights = np.exp(logits - logits.max())
            weights /= weights.sum()
            out[y, x] = np.einsum("ij,ijc->c", weights, color[ys, xs])
    return out


# --------------------------------------------------------------------------- the filters
@pytest.mark.parametrize("k", [1, 3, 5, 9, 13])
def test_both_forms_match_brute_force(rng, k):
    # 7 x 10 with k = 9 and 13: windows larger than the image, clipped on every side.
    color, importance = _inputs(rng, (7, 10))
    expected = _numpy_filter(color, importance, k)
    for form in (kernels.filter_box, kernels.filter_unfold):
        np.testing.assert_allclose(form(color, importance, k), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("k", [7])
def test_forms_agree_with_batch_dims(rng, k):
    color, importance = _inputs(rng, (2, 3, 16, 19), importance_scale=4.0)
    box = kernels.filter_box(color, importance, k)
    unfold = kernels.filter_unfold(color, importance, k)
    assert box.shape == (2, 3, 16, 19, 3)
    np.testing.assert_allclose(box, unfold, rtol=1e-5, atol=1e-6)
    # Leading dims are independent images: equal to filtering each one alone.
    np.testing.assert_allclose(
        box[1, 2], kernels.filter_box(color[1, 2], importance[1, 2], k), rtol=1e-6, atol=1e-7
    )


def _check_grads64(rng, k, order):
    # check_grads compares autodiff with finite differences; float64 makes it a tight check.
    color, importance = _inputs(rng, (6, 7))
    with jax.enable_x64(True):
        color64, importance64 = color.astype(np.float64), importance.astype(np.float64)
        for form in (kernels.filter_box, kernels.filter_unfold):
            check_grads(
                lambda c, i, f=form: f(c, i, k),
                (color64, importance64),
                order=order,
                modes=("rev", "fwd"),  # fwd matters: SURE takes jvps through the decoder
                atol=1e-6,
                rtol=1e-6,
            )


def test_gradients_numerically_correct(rng):
    _check_grads64(rng, 3, order=1)


@pytest.mark.slow
@pytest.mark.parametrize("k", [3, 5])
def test_second_derivatives_numerically_correct(rng, k):
    _check_grads64(rng, k, order=2)


@pytest.mark.parametrize("k", [3, 9])
def test_forms_have_equal_gradients(rng, k):
    color, importance = _inputs(rng, (12, 15), importance_scale=3.0)
    cotangent = rng.standard_normal(color.shape).astype(np.float32)

    def grads(form):
        loss = lambda c, i: jnp.sum(form(c, i, k) * cotangent)  # noqa: E731
        return jax.jit(jax.grad(loss, argnums=(0, 1)))(color, importance)

    box_dc, box_di = grads(kernels.filter_box)
    unfold_dc, unfold_di = grads(kernels.filter_unfold)
    np.testing.assert_allclose(box_dc, unfold_dc, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(box_di, unfold_di, rtol=1e-5, atol=1e-5 * np.abs(unfold_di).max())


@pytest.mark.parametrize("form", [kernels.filter_box, kernels.filter_unfold])
def test_invariant_to_constant_importance_shift(rng, form):
    color, importance = _inputs(rng, (10, 12), importance_scale=3.0)
    # A 1/256 grid keeps importance + 64 exact in float32: only the algorithm is tested.
    importance = np.round(importance * 256) / 256
    for shift in (64.0, -64.0):
        np.testing.assert_allclose(
            form(color, importance + shift, 7), form(color, importance, 7), rtol=1e-6, atol=1e-6
        )


@pytest.mark.parametrize("form", [kernels.filter_box, kernels.filter_unfold])
def test_constant_colour_is_preserved(rng, form):
    _, importance = _inputs(rng, (9, 14), importance_scale=10.0)
    color = np.full((9, 14, 3), [0.25, 3.0, 1e3], np.float32)
    out = form(color, importance, 5)
    np.testing.assert_allclose(out, color, rtol=1e-6)


@pytest.mark.parametrize("form", [kernels.filter_box, kernels.filter_unfold])
def test_kernel_size_one_is_identity(rng, form):
    color, importance = _inputs(rng, (2, 5, 6))
    np.testing.assert_array_equal(form(color, importance, 1), color)


def test_output_is_a_convex_combination_of_the_window(rng):
    color, importance = _inputs(rng, (11, 13), importance_scale=5.0)
    out = np.asarray(kernels.filter_box(color, importance, 3))
    padded_max = np.pad(color, [(1, 1), (1, 1), (0, 0)], constant_values=-np.inf)
    padded_min = np.pad(color, [(1, 1), (1, 1), (0, 0)], constant_values=np.inf)
    window_max = np.max([padded_max[dy : dy + 11, dx : dx + 13] for dy in range(3)
                         for dx in range(3)], axis=0)
    window_min = np.min([padded_min[dy : dy + 11, dx : dx + 13] for dy in range(3)
                         for dx in range(3)], axis=0)
    assert np.all(out <= window_max + 1e-5) and np.all(out >= window_min - 1e-5)


def test_large_importance_is_stable(rng):
    # A ramp from -80 to +80 plus noise: with a global max shift exp(I - max I) underflows to
    # 0/0 over the left half; the per-window stabilisation must stay exact.
    height, width = 10, 40
    ramp = np.linspace(-80.0, 80.0, width, dtype=np.float32)[None, :]
    importance = (ramp + 3.0 * rng.standard_normal((height, width))).astype(np.float32)
    color = rng.uniform(0.0, 2.0, (height, width, 3)).astype(np.float32)
    expected = _numpy_filter(color, importance, 7)
    cotangent = rng.standard_normal(color.shape).astype(np.float32)
    for form in (kernels.filter_box, kernels.filter_unfold):
        out = form(color, importance, 7)
        assert np.all(np.isfinite(out))
        np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)
        grads = jax.grad(lambda c, i, f=form: jnp.sum(f(c, i, 7) * cotangent), argnums=(0, 1))(
            color, importance
        )
        assert all(np.all(np.isfinite(g)) for g in grads)
    # Far beyond exp's float32 range: still finite and a convex combination.
    huge = 1e3 * rng.standard_normal((height, width)).astype(np.float32)
    out = kernels.filter_box(color, huge, 5)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out, _numpy_filter(color, huge, 5), rtol=1e-5, atol=1e-6)


def test_half_precision_inputs_are_promoted(rng):
    color, importance = _inputs(rng, (6, 6))
    out = kernels.filter_box(color.astype(np.float16), importance.astype(np.float16), 3)
    assert out.dtype == jnp.float32


# ------------------------------------------------------------------------------- fusion
def test_fuse_matches_numpy(rng):
    filtered = rng.standard_normal((2, 4, 5, 6, 3)).astype(np.float32)  # (B, M, H, W, C)
    logits = (3 * rng.standard_normal((2, 5, 6, 4))).astype(np.float32)
    weights = np.exp(logits - logits.max(-1, keepdims=True))
    weights /= weights.sum(-1, keepdims=True)
    expected = np.einsum("bmhwc,bhwm->bhwc", filtered, weights)
    np.testing.assert_allclose(kernels.fuse(filtered, logits), expected, rtol=1e-5, atol=1e-6)
    as_list = [filtered[:, m] for m in range(4)]
    np.testing.assert_allclose(kernels.fuse(as_list, logits), expected, rtol=1e-5, atol=1e-6)


def test_fuse_equal_logits_is_the_mean(rng):
    filtered = rng.standard_normal((3, 4, 4, 3)).astype(np.float32)
    out = kernels.fuse(filtered, np.full((4, 4, 3), 7.0, np.float32))
    np.testing.assert_allclose(out, filtered.mean(0), rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------ decoder
def test_decode_is_filter_then_fuse(rng):
    sizes = (3, 5, 7)
    color, _ = _inputs(rng, (2, 9, 10))
    importance = (2 * rng.standard_normal((2, 9, 10, 3))).astype(np.float32)
    logits = rng.standard_normal((2, 9, 10, 3)).astype(np.float32)
    manual = kernels.fuse(
        [kernels.filter_unfold(color, importance[..., i], k) for i, k in enumerate(sizes)],
        logits,
    )
    for form in ("box", "unfold"):
        out = kernels.decode(color, importance, logits, kernel_sizes=sizes, form=form)
        np.testing.assert_allclose(out, manual, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    "sizes", [(3, 5, 9), pytest.param(kernels.DEFAULT_KERNEL_SIZES, marks=pytest.mark.slow)]
)
def test_decode_forms_agree_in_value_and_gradient(rng, sizes):
    color, _ = _inputs(rng, (14, 16))
    importance = (2 * rng.standard_normal((14, 16, len(sizes)))).astype(np.float32)
    logits = rng.standard_normal((14, 16, len(sizes))).astype(np.float32)
    cotangent = rng.standard_normal(color.shape).astype(np.float32)

    def value_and_grads(form):
        decode = jax.jit(lambda c, i, a: kernels.decode(c, i, a, sizes, form))
        value, vjp = jax.vjp(decode, color, importance, logits)
        return value, vjp(cotangent)

    box_value, box_grads = value_and_grads("box")
    unfold_value, unfold_grads = value_and_grads("unfold")
    np.testing.assert_allclose(box_value, unfold_value, rtol=1e-5, atol=1e-6)
    for box_g, unfold_g in zip(box_grads, unfold_grads, strict=True):
        np.testing.assert_allclose(box_g, unfold_g, rtol=1e-5, atol=1e-5 * np.abs(unfold_g).max())


def test_decode_under_jit_and_vmap(rng):
    color, _ = _inputs(rng, (3, 8, 8))
    importance = rng.standard_normal((3, 8, 8, 2)).astype(np.float32)
    logits = rng.standard_normal((3, 8, 8, 2)).astype(np.float32)
    batched = kernels.decode(color, importance, logits, (3, 5))
    mapped = jax.jit(jax.vmap(lambda c, i, a: kernels.decode(c, i, a, [3, 5])))(
        color, importance, logits
    )
    np.testing.assert_allclose(mapped, batched, rtol=1e-6, atol=1e-7)


# ------------------------------------------------- the decoder's two paths (box form)
def _three_map_inputs(rng, spread, shape=(2, 12, 15)):
    """Colour and three importance maps whose range (max - min) over each image is ``spread``."""
    color, _ = _inputs(rng, shape)
    # A ramp along W plus noise: the windows at the low end hold only small weights.
    maps = np.linspace(0.0, 1.0, shape[-1])[:, None] + 0.05 * rng.uniform(0, 1, shape + (3,))
    maps = (maps - maps.min(axis=(-3, -2), keepdims=True))
    maps = spread * maps / maps.max(axis=(-3, -2), keepdims=True) - spread / 2
    logits = rng.standard_normal(shape + (3,)).astype(np.float32)
    return color, maps.astype(np.float32), logits


def test_path_choice_follows_the_importance_range(rng):
    _, maps, _ = _three_map_inputs(rng, 63.0)
    assert bool(kernels._global_shift_ok(maps))
    _, wide, _ = _three_map_inputs(rng, 65.0)
    assert not bool(kernels._global_shift_ok(wide))
    # One wide map in one batch item sends the whole call to the per-window path.
    mixed = maps.copy()
    mixed[1, ..., 2] = wide[1, ..., 2]
    assert not bool(kernels._global_shift_ok(mixed))
    for bad in (np.nan, np.inf, -np.inf):
        broken = maps.copy()
        broken[0, 3, 4, 1] = bad
        assert not bool(kernels._global_shift_ok(broken))


@pytest.mark.parametrize("spread", [1.0, 20.0, 63.5, 64.5, 150.0])
def test_both_paths_match_brute_force_near_the_threshold(rng, spread):
    # Either side of GLOBAL_SHIFT_RANGE = 64: the global-shift path at 63.5 keeps every
    # window's weights exact (its smallest window maximum is e^-63.5 of the image's), and the
    # per-window path takes over at 64.5; both agree with the float64 per-pixel softmax.
    sizes = (1, 3, 7, 13)
    color, _ = _inputs(rng, (12, 15))
    ramp = np.linspace(-spread / 2, spread / 2, 15)[None, :, None]
    maps = (ramp + 0.2 * rng.standard_normal((12, 15, 4))).clip(-spread / 2, spread / 2)
    maps = maps.astype(np.float32)
    logits = rng.standard_normal((12, 15, 4)).astype(np.float32)
    assert bool(kernels._global_shift_ok(maps)) == (spread < kernels.GLOBAL_SHIFT_RANGE)
    alpha = np.exp(logits - logits.max(-1, keepdims=True))
    alpha /= alpha.sum(-1, keepdims=True)
    expected = sum(alpha[..., i : i + 1] * _numpy_filter(color, maps[..., i], k)
                   for i, k in enumerate(sizes))
    out = kernels.decode(color, maps, logits, sizes)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("spread", [30.0, 63.5])
def test_the_two_paths_agree_in_value_and_gradient(rng, spread):
    # The same inputs through each path directly (the production call picks one of them). At
    # the threshold a window's weight sum is as small as e^-63.5: its square's inverse, which
    # reverse mode forms for a quotient, would overflow float32 without the normalisation.
    sizes = (3, 5, 9)
    color, maps, logits = _three_map_inputs(rng, spread)
    cotangent = rng.standard_normal(color.shape).astype(np.float32)
    results = []
    for path in (kernels._decode_shifted, kernels._decode_windowed):
        fn = jax.jit(lambda c, i, a, path=path: path(c, i, a, kernel_sizes=sizes))
        value, vjp = jax.vjp(fn, color, maps, logits)
        results.append((value, vjp(cotangent)))
    (v1, g1), (v2, g2) = results
    np.testing.assert_allclose(v1, v2, rtol=1e-5, atol=1e-6)
    for a, b in zip(g1, g2, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * np.abs(b).max())


@pytest.mark.slow  # ~15 s idle; test_decode_forms_agree_in_value_and_gradient covers the gradients
def test_decode_jvp_through_the_path_choice(rng):
    # SURE's divergence is a jvp of the denoiser: the choice depends on the primal only, and
    # the tangent of the global-shift path equals the per-window path's.
    sizes = (3, 5, 9)
    color, maps, logits = _three_map_inputs(rng, 10.0)
    tangent = rng.standard_normal(color.shape).astype(np.float32)
    outs = [jax.jvp(lambda c, p=path: p(c, maps, logits, kernel_sizes=sizes), (color,),
                    (tangent,))[1] for path in (kernels._decode_shifted, kernels._decode_windowed)]
    np.testing.assert_allclose(outs[0], outs[1], rtol=1e-5, atol=1e-6)
    production = jax.jvp(lambda c: kernels.decode(c, maps, logits, sizes), (color,), (tangent,))
    np.testing.assert_allclose(production[1], outs[1], rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------- bad input
def test_shape_and_option_errors(rng):
    color, importance = _inputs(rng, (6, 7))
    with pytest.raises(FrameError, match=r"importance must have shape \(\.\.\., H, W\) = \(6, 7\)"):
        kernels.filter_box(color, importance[:, :5], 3)
    with pytest.raises(FrameError, match="importance must have shape"):
        kernels.filter_unfold(color, importance[..., None], 3)
    with pytest.raises(FrameError, match=r"colour must have shape \(\.\.\., H, W, C\)"):
        kernels.filter_box(color[0], importance[0], 3)
    with pytest.raises(FrameError, match="must be floating point"):
        kernels.filter_box(color.astype(np.int32), importance, 3)
    for bad in (4, 0, -3, 2.0, True):
        with pytest.raises(ConfigError, match="kernel size must be"):
            kernels.filter_box(color, importance, bad)
    with pytest.raises(ConfigError, match="form must be one of"):
        kernels.decode(color, np.zeros((6, 7, 1)), np.zeros((6, 7, 1)), (3,), form="fft")
    with pytest.raises(FrameError, match=r"importance_maps must have shape .* 2 kernel sizes"):
        kernels.decode(color, np.zeros((6, 7, 3)), np.zeros((6, 7, 2)), (3, 5))
    with pytest.raises(FrameError, match="fusion_logits must have shape"):
        kernels.decode(color, np.zeros((6, 7, 2)), np.zeros((6, 8, 2)), (3, 5))
    with pytest.raises(ConfigError, match="kernel size must be odd"):
        kernels.decode(color, np.zeros((6, 7, 2)), np.zeros((6, 7, 2)), (3, 6))
    with pytest.raises(FrameError, match=r"logits must have shape \(\.\.\., H, W, M\)"):
        kernels.fuse(np.zeros((3, 6, 7, 3)), np.zeros((6, 7, 2)))
    with pytest.raises(FrameError, match="different shapes"):
        kernels.fuse([np.zeros((6, 7, 3)), np.zeros((6, 6, 3))], np.zeros((6, 7, 2)))
    # FrameError and ConfigError are ValueErrors, for callers that catch the builtin.
    with pytest.raises(ValueError):
        kernels.filter_box(color, importance[:1], 3)
