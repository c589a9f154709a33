"""Neural James-Stein combiner (Gu, Iglesias-Guitian, Moon, SIGGRAPH Asia 2022), in pure JAX:
the cross-regressed biased inputs, the James-Stein combination, and the whole combiner.

Follows the authors' code (``CGLab-GIST/NeuralJS_combiner`` @d876212: ``ops/js.cu.cc``,
``model.py``, ``main.py``, ``loader.py``; BASELINES.md section 8); docs/departures.md, "Neural
James-Stein combiner", lists where jaxden departs from it. NJS needs two independent half
buffers A and B of one image, and a biased denoiser's output for each half.

**Cross regression** (the authors' ``ols`` op; :func:`collaborative_ols`,
:func:`cross_regressions`). ``olsA`` regresses the noisy colour of half A on features of the
*other* half: B's denoised image, albedo, normal, depth (and visibility, which jaxden frames do
not have: see :class:`HalfBuffer`); ``olsB`` the other way round. For each pixel ``p``, over the
``51 x 51`` window ``q`` (image borders mirrored without repeating the edge pixel):

    x_pq  = [1, s_1 (f_1(q) - f_1(p)), ..., s_G (f_G(q) - f_G(p))]       (d = 1 + channels)
    s_g   = 1 / (max_q |f_g(q) - f_g(p)| + 0.1)          (Euclidean norm over the group)
    w_pq  = exp(-|z(q) - z(p)|^2 / (2 v(p) + 0.01))      (z = the denoised image, group 1)
    beta_p = (X^T W X + 0.1 I)^-1 X^T W y                (Cholesky; the ridge on every
                                                          coefficient, the intercept too)

and the fits are *collaborative*: every ``p`` evaluates its fit at each ``q`` of its window
and adds ``w_pq x_pq . beta_p`` and ``w_pq`` there (at the mirrored pixel for a ``q`` outside
the image); the output is the ratio, or the denoised ``z`` where the weights sum to less
than 1e-5 (never, for finite inputs: ``w_pp = 1``). ``v`` is the *bandwidth variance*
(:func:`bandwidth_variance`): at test time one value per image, the mean over pixels and
channels of ``(z_A - z_B)^2 / 2``; in training that value per pixel (grey).

Memory and time: per block of centre pixels, a ``lax.scan`` over the window's offsets
accumulates each pixel's normal equations (``d^2 + 3 d`` numbers, d = 11 or 12) and the
groups' largest differences, the block's systems are solved, and a second scan adds the
block's fits into its sums over the block's window-wide surroundings; nothing of size pixels
x window exists. The blocks are 64 x 64 on the CPU (``lax.map``, accumulators in cache) and
the whole image on accelerators (:func:`block_side`); the result does not depend on the
block. Compiled working set at 1280 x 720, window 51: 0.2 GiB in 64 x 64 blocks, 1.2 GiB as
one block. One call at 256 x 256 takes about 10 CPU-seconds on the 2-core machine
(single-threaded; ~55 ns per pixel and window offset for both passes).

**James-Stein combination** (the authors' ``weight_avg``, ``calc_shrinkage``, ``combiner``
ops; :func:`js_combine`), over a ``k x k`` window (k = 15, borders mirrored the same way):

    var_hat(p) = sum_n w_pn Var(q_n) / max(sum_n w_pn, 1e-5)   (n row-major over the window)
    z         = alpha olsA + (1 - alpha) olsB
    rho(p)    = max(0, 1 - (k^2 - 2) var_hat(p) / max(sum_q (y(q) - z(q))^2, 1e-5))
    out(p)    = z(p) + mean_q rho(q) (y(p) - z(p))                (per channel)

with ``y`` the noisy colour of the whole image, ``Var`` its variance of the mean, and ``w``,
``alpha`` from the network (:mod:`jaxden.denoise.nn.njs`). ``rho`` and its box mean lie in
[0, 1], so the output lies between ``z`` and ``y`` channel by channel. At test time the output
is clamped at 0 (``clamp``).

Gradients are JAX's exact derivatives; the authors' hand-written ones differ (see the
departures). The cross regression is input preparation (computed once per image, as the
authors' loader does), not meant to be differentiated.

API: :class:`HalfBuffer`, :func:`bandwidth_variance`, :func:`collaborative_ols`,
:func:`cross_regressions`, :func:`half_buffers`; :func:`weighted_variance`,
:func:`shrinkage`, :func:`james_stein`, :func:`js_combine`; :class:`NJSConfig`,
:func:`njs_init`, :func:`njs_apply` (network and combination on precomputed olsA / olsB),
:func:`njs_combiner` (everything, from two half buffers). Shapes ``(..., H, W, C)`` with any
leading batch dimensions; linear radiance; pixels.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.config import bounded, check_fields
from jaxden.denoise.james_stein import (
    JS_EPS,
    check_mirror,
    check_window,
    james_stein,
    js_combine,
    mirror_pad,
    shrinkage,
    weighted_variance,
)
from jaxden.denoise.nn.njs import INPUT_CHANNELS, KERNEL_SIZE, WIDTHS, NJSNet, njs_inputs
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

#: The authors' regression window (``olsKernelSize``).
OLS_WINDOW = 51
#: Added to the diagonal of every normal matrix (``OLS_EP``).
OLS_RIDGE = 0.1
#: In each feature group's scale ``1 / (max |difference| + 0.1)`` (``OLS_EP`` again).
OLS_SCALE_EPS = 0.1
#: In the weights' denominator ``2 v + 0.01`` (``OLS_WGT_EP``).
OLS_WEIGHT_EPS = 0.01
#: Below this total weight a pixel keeps the denoised value (``OlsFinalizeKernel``).
OLS_MIN_WEIGHT = 1e-5
#: What ``bandwidth`` may name: one value per image (test time) or per pixel (training).
BANDWIDTHS = ("image", "pixel")


# ------------------------------------------------------------------------------- borders
def mirror_index(size: int, radius: int) -> np.ndarray:
    """The image index of each of the ``size + 2 radius`` positions of a mirrored padding."""
    return np.pad(np.arange(size), radius, mode="reflect")


def block_side(block: int) -> int:
    """The block side the regressions work in: ``block``, or for 0 64 pixels on the CPU and
    the whole image on accelerators."""
    if block:
        return block
    return 64 if jax.default_backend() == "cpu" else 1 << 30


def _grid(size: int, block: int) -> tuple[int, int]:
    """``(side, overshoot)``: the block side along an axis of ``size`` pixels and how far the
    last block reaches past it."""
    side = min(block_side(block), size)
    return side, -(-size // side) * side - size


# ------------------------------------------------------------------------ cross regression
class HalfBuffer(NamedTuple):
    """One half buffer of an image and what its cross regression reads, ``(..., H, W, C)``:
    ``color`` (3), the noisy mean of the half's samples; ``denoised`` (3), the biased
    denoiser's output on this half alone; ``albedo`` (3), ``normal`` (3), ``depth`` (1, as the
    authors: divided by the image's largest depth, :func:`half_buffers`); ``visibility`` (1) or
    None (jaxden frames have none: the design then has 11 columns, which gives the same fit as a
    constant visibility)."""

    color: jax.Array
    denoised: jax.Array
    albedo: jax.Array
    normal: jax.Array
    depth: jax.Array
    visibility: jax.Array | None = None

    def feature_groups(self) -> tuple[jax.Array, ...]:
        """The regression's feature groups, the guide first: denoised, albedo, normal, depth
        (, visibility)."""
        groups = (self.denoised, self.albedo, self.normal, self.depth)
        return groups if self.visibility is None else (*groups, self.visibility)


def bandwidth_variance(denoised_a, denoised_b, bandwidth: str = "image") -> jax.Array:
    """``v`` of the regression weights from the two halves' denoised images ``(..., H, W,
    3)``: the grey ``mean_c (z_A - z_B)^2 / 2`` per pixel (``bandwidth = "pixel"``, training)
    or its mean over the image, broadcast (``"image"``, test time). Returns (..., H, W, 1)."""
    if bandwidth not in BANDWIDTHS:
        raise ConfigError(f"bandwidth_variance: bandwidth must be one of "
                          f"{', '.join(BANDWIDTHS)}, got {bandwidth!r}")
    a, b = jnp.asarray(denoised_a, jnp.float32), jnp.asarray(denoised_b, jnp.float32)
    if a.shape != b.shape or a.ndim < 3:
        raise FrameError(f"bandwidth_variance: the denoised halves must have one shape "
                         f"(..., H, W, C), got {a.shape} and {b.shape}")
    grey = jnp.mean(jnp.square(a - b) / 2.0, axis=-1, keepdims=True)
    if bandwidth == "pixel":
        return grey
    return jnp.broadcast_to(jnp.mean(grey, axis=(-3, -2, -1), keepdims=True), grey.shape)


def _solve(gram: jax.Array, rhs: jax.Array, scale: jax.Array, ridge: float) -> jax.Array:
    """Coefficients of the *unscaled* differences: ``S (S G S + ridge I)^-1 S rhs`` for the
    normal matrices ``gram (..., d, d)`` and ``rhs (..., d, m)`` of the unscaled design and
    its column scales ``scale (..., d)``; batched Cholesky."""
    d = rhs.shape[-2]
    matrix = gram * scale[..., :, None] * scale[..., None, :]
    matrix = matrix + ridge * jnp.eye(d, dtype=matrix.dtype)
    factor = jnp.linalg.cholesky(matrix)
    beta = jax.scipy.linalg.cho_solve((factor, True), rhs * scale[..., :, None])
    return beta * scale[..., :, None]


def _ols_image(noisy, features, variance, sizes: tuple[int, ...], radius: int, ridge: float,
               min_weight: float, block: int):
    """:func:`collaborative_ols` of one image: ``noisy (H, W, m)``, ``features (H, W, D)``
    (the groups of ``sizes`` side by side, the guide first), ``variance (H, W, 1)``.

    Per block of centre pixels: pass 1 (a scan over the window) accumulates the normal
    equations and the groups' largest differences, the block's systems are solved, and pass 2
    (a second scan) adds each centre's weighted fit at every window position into the block's
    sums over its mirrored surroundings; the blocks' sums are added on the mirrored grid
    (``H + 2 r`` x ``W + 2 r``) and folded onto the pixels they mirror.

    Arrays are channel-major ``(C, H, W)`` inside, so that every per-offset operation is a
    plane over the block's pixels; the hot loops avoid sums over a channel axis and
    concatenations, which XLA's CPU code makes several times slower."""
    height, width, channels = features.shape
    m = noisy.shape[-1]
    d = 1 + channels
    bounds = np.cumsum((0, *sizes))
    guide = sizes[0]
    span = 2 * radius + 1
    iys, ixs = np.meshgrid(np.arange(span), np.arange(span), indexing="ij")
    offsets = (jnp.asarray(iys.ravel(), jnp.int32), jnp.asarray(ixs.ravel(), jnp.int32))
    side_y, over_y = _grid(height, block)
    side_x, over_x = _grid(width, block)
    area = (side_y + 2 * radius, side_x + 2 * radius)
    planes = lambda a: jnp.pad(jnp.moveaxis(a, -1, 0), ((0, 0), (0, over_y), (0, over_x)))
    features_m = planes(mirror_pad(features, radius))
    noisy_m = planes(mirror_pad(noisy, radius))
    variance_e = planes(variance)
    inside_e = planes(jnp.ones((height, width, 1), features.dtype))

    def plane_sum(parts):
        total = parts[0]
        for part in parts[1:]:
            total = total + part
        return total

    def block_sums(y0, x0):
        feats = jax.lax.dynamic_slice(features_m, (0, y0, x0), (channels, *area))
        colors = jax.lax.dynamic_slice(noisy_m, (0, y0, x0), (m, *area))
        centre = feats[:, radius:radius + side_y, radius:radius + side_x]
        denominator = 2.0 * jax.lax.dynamic_slice(variance_e, (0, y0, x0),
                                                  (1, side_y, side_x))[0] + OLS_WEIGHT_EPS
        inside = jax.lax.dynamic_slice(inside_e, (0, y0, x0), (1, side_y, side_x))[0]
        ones = jnp.ones((1, side_y, side_x), features.dtype)

        def differences(iy, ix):
            delta = jax.lax.dynamic_slice(feats, (0, iy, ix), (channels, side_y, side_x)) - centre
            square = delta * delta
            norms = [plane_sum([square[i] for i in range(a, b)])
                     for a, b in itertools.pairwise(bounds)]
            return delta, norms, jnp.exp(-norms[0] / denominator)

        def system_tap(carry, offset):
            iy, ix = offset
            delta, norms, weight = differences(iy, ix)
            color = jax.lax.dynamic_slice(colors, (0, iy, ix), (m, side_y, side_x))
            design = jnp.concatenate([ones, delta], 0)
            weighted = weight * design
            largest, gram, rhs = carry
            return (jnp.maximum(largest, jnp.stack(norms, 0)),
                    gram + weighted[:, None] * design[None],
                    rhs + weighted[:, None] * color[None]), None

        init = (jnp.zeros((len(sizes), side_y, side_x), features.dtype),
                jnp.zeros((d, d, side_y, side_x), features.dtype),
                jnp.zeros((d, m, side_y, side_x), features.dtype))
        (largest, gram, rhs), _ = jax.lax.scan(system_tap, init, offsets)
        group_scale = 1.0 / (jnp.sqrt(largest) + OLS_SCALE_EPS)
        scale = jnp.concatenate([ones] + [jnp.repeat(group_scale[g:g + 1], n, 0)
                                          for g, n in enumerate(sizes)], 0)
        pixel_major = lambda a: jnp.moveaxis(a, (-2, -1), (0, 1))
        beta = _solve(pixel_major(gram), pixel_major(rhs), pixel_major(scale), ridge)
        beta = jnp.moveaxis(beta, (0, 1), (-2, -1))  # (d, m, side_y, side_x)

        def collaborate_tap(sums, offset):
            iy, ix = offset
            delta, _, weight = differences(iy, ix)
            weight = weight * inside
            fitted = plane_sum([beta[0]] + [delta[i][None] * beta[1 + i]
                                             for i in range(channels)])
            here = jax.lax.dynamic_slice(sums, (0, iy, ix), (m + 1, side_y, side_x))
            here = here + jnp.concatenate([weight[None] * fitted, weight[None]], 0)
            return jax.lax.dynamic_update_slice(sums, here, (0, iy, ix)), None

        sums, _ = jax.lax.scan(collaborate_tap, jnp.zeros((m + 1, *area), features.dtype),
                               offsets)
        return sums

    count_y, count_x = -(-height // side_y), -(-width // side_x)
    ys, xs = np.meshgrid(np.arange(count_y) * side_y, np.arange(count_x) * side_x,
                         indexing="ij")
    ys, xs = ys.ravel(), xs.ravel()
    sums = jax.lax.map(lambda origin: block_sums(*origin),
                       (jnp.asarray(ys, jnp.int32), jnp.asarray(xs, jnp.int32)))
    # the blocks' sums on the mirrored grid, then onto the pixels each position mirrors
    rows = (ys[:, None] + np.arange(area[0]))[:, :, None]
    cols = (xs[:, None] + np.arange(area[1]))[:, None, :]
    grid = jnp.zeros((m + 1, count_y * side_y + 2 * radius, count_x * side_x + 2 * radius),
                     sums.dtype).at[:, rows, cols].add(jnp.moveaxis(sums, 0, 1))
    grid = grid[:, :height + 2 * radius, :width + 2 * radius]
    mirrored_rows, mirrored_cols = mirror_index(height, radius), mirror_index(width, radius)
    sums = jnp.zeros((m + 1, height, width), sums.dtype).at[
        :, mirrored_rows[:, None], mirrored_cols[None, :]].add(grid)
    total, weights = jnp.moveaxis(sums[:m], 0, -1), sums[m][..., None]
    return jnp.where(weights < min_weight, features[..., :guide],
                     total / jnp.maximum(weights, min_weight))


@functools.partial(jax.jit, static_argnames=("sizes", "radius", "ridge", "min_weight", "block"))
def _ols_batch(noisy, features, variance, sizes, radius, ridge, min_weight, block):
    one = functools.partial(_ols_image, sizes=sizes, radius=radius, ridge=ridge,
                            min_weight=min_weight, block=block)
    return jax.lax.map(lambda args: one(*args), (noisy, features, variance))


def collaborative_ols(noisy, groups, bandwidth, *, window: int = OLS_WINDOW,
                      ridge: float = OLS_RIDGE, min_weight: float = OLS_MIN_WEIGHT,
                      block: int = 0) -> jax.Array:
    """The authors' ``ols`` op: the collaborative weighted least-squares fit of ``noisy`` on
    the feature ``groups`` (module docstring).

    Args:
      noisy: (..., H, W, m) the image regressed (a half buffer's noisy colour).
      groups: feature groups, each (..., H, W, c_g); the first is the guide ``z`` of the
        weights and the fallback (the other half's denoised image, m channels). Each group is
        scaled by ``1 / (max |difference| in the window + 0.1)``.
      bandwidth: ``v``, broadcastable to (..., H, W, 1) (:func:`bandwidth_variance`).
      window: odd side of the window (51); it must fit the image mirrored once.
      ridge: added to the diagonal of every normal matrix (0.1), > 0.
      min_weight: below this total weight the output is the guide (1e-5).
      block: the side of the blocks the scans sweep (0: :func:`block_side`); speed and memory
        only.

    Returns:
      (..., H, W, m). Jitted; ``lax.map`` over the leading dimensions.

    Raises:
      FrameError: mismatched shapes, an image smaller than the window's reach.
      ConfigError: an even window, a ridge <= 0.
    """
    radius = check_window(window, "collaborative_ols")
    if not ridge > 0:
        raise ConfigError(f"collaborative_ols: ridge must be > 0, got {ridge!r}")
    noisy = jnp.asarray(noisy, jnp.float32)
    groups = tuple(jnp.asarray(g, jnp.float32) for g in groups)
    if noisy.ndim < 3 or not groups:
        raise FrameError(f"collaborative_ols: noisy must be (..., H, W, C) and at least one "
                         f"feature group given, got {noisy.shape} and {len(groups)} group(s)")
    lead, (height, width) = noisy.shape[:-3], noisy.shape[-3:-1]
    for index, group in enumerate(groups):
        if group.shape[:-1] != noisy.shape[:-1]:
            raise FrameError(f"collaborative_ols: feature group {index} has shape "
                             f"{group.shape}, expected (..., H, W, C) = "
                             f"{(*noisy.shape[:-1], 'C')}")
    if groups[0].shape[-1] != noisy.shape[-1]:
        raise FrameError(f"collaborative_ols: the guide (group 0) must have the channels of "
                         f"noisy ({noisy.shape[-1]}), got {groups[0].shape[-1]}")
    try:
        variance = jnp.broadcast_to(jnp.asarray(bandwidth, jnp.float32), (*lead, height, width, 1))
    except ValueError:
        raise FrameError(f"collaborative_ols: bandwidth of shape {jnp.shape(bandwidth)} does "
                         f"not broadcast to {(*lead, height, width, 1)}") from None
    check_mirror(height, width, radius, "collaborative_ols")
    sizes = tuple(int(g.shape[-1]) for g in groups)
    features = jnp.concatenate(groups, -1)
    flat = lambda a: a.reshape(-1, *a.shape[-3:])
    out = _ols_batch(flat(noisy), flat(features), flat(variance), sizes, radius, float(ridge),
                     float(min_weight), int(block))
    return out.reshape(noisy.shape)


def cross_regressions(half_a: HalfBuffer, half_b: HalfBuffer, bandwidth="image", *,
                      window: int = OLS_WINDOW, ridge: float = OLS_RIDGE,
                      block: int = 0) -> tuple[jax.Array, jax.Array]:
    """``(olsA, olsB)``, each (..., H, W, 3): A's noisy colour regressed on B's features
    (:meth:`HalfBuffer.feature_groups`), B's on A's. ``bandwidth``: ``"image"`` (test time),
    ``"pixel"`` (training), or ``v`` itself (broadcastable to (..., H, W, 1)); the names use
    :func:`bandwidth_variance` of the two denoised halves. One compiled program for both."""
    if (half_a.visibility is None) != (half_b.visibility is None):
        raise FrameError("cross_regressions: give visibility for both halves or for neither")
    if isinstance(bandwidth, str):
        bandwidth = bandwidth_variance(half_a.denoised, half_b.denoised, bandwidth)
    shape = jnp.shape(half_a.color)
    for half in (half_a, half_b):
        if jnp.shape(half.color) != shape:
            raise FrameError(f"cross_regressions: the halves' colours must have one shape, got "
                             f"{shape} and {jnp.shape(half.color)}")
    variance = jnp.broadcast_to(jnp.asarray(bandwidth, jnp.float32), (*shape[:-1], 1))
    stacked = [jnp.stack([jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32)])
               for a, b in zip(half_b.feature_groups(), half_a.feature_groups(), strict=True)]
    both = collaborative_ols(jnp.stack([half_a.color, half_b.color]), stacked,
                             jnp.stack([variance, variance]), window=window, ridge=ridge,
                             block=block)
    return both[0], both[1]


def half_buffers(frame_a: Frame, frame_b: Frame, denoised_a, denoised_b,
                 visibility_a=None, visibility_b=None) -> tuple[HalfBuffer, HalfBuffer]:
    """:class:`HalfBuffer` s from two half-buffer Frames (colour, albedo, normal, depth) and
    the denoiser's output on each: depth divided by the largest depth of the two halves over
    the image (the authors divide by the image's largest depth; 1 where all is 0)."""
    for name, frame in (("A", frame_a), ("B", frame_b)):
        frame.require("color", "albedo", "normal", "depth", who=f"NJS (half buffer {name})")
    depth_a = jnp.asarray(frame_a.depth, jnp.float32)
    depth_b = jnp.asarray(frame_b.depth, jnp.float32)
    largest = jnp.maximum(jnp.max(depth_a, axis=(-3, -2, -1), keepdims=True),
                          jnp.max(depth_b, axis=(-3, -2, -1), keepdims=True))
    largest = jnp.where(largest > 0, largest, 1.0)

    def half(frame, denoised, depth, visibility):
        return HalfBuffer(color=jnp.asarray(frame.color, jnp.float32),
                          denoised=jnp.asarray(denoised, jnp.float32),
                          albedo=jnp.asarray(frame.albedo, jnp.float32),
                          normal=jnp.asarray(frame.normal, jnp.float32),
                          depth=depth / largest, visibility=visibility)

    return (half(frame_a, denoised_a, depth_a, visibility_a),
            half(frame_b, denoised_b, depth_b, visibility_b))


# ------------------------------------------------------------------------- the combiner
@dataclasses.dataclass(frozen=True)
class NJSConfig:
    """The Neural James-Stein combiner: ``widths`` of the network's three levels (32, 64,
    128), ``kernel_size`` of the combination window (15), ``ols_window`` of the cross
    regressions (51), ``ols_ridge`` (0.1), ``bandwidth`` of the cross regressions when the
    combiner computes them (:func:`njs_combiner`): ``image`` (the authors' test time) or
    ``pixel`` (their training inputs)."""

    widths: tuple[int, ...] = WIDTHS
    kernel_size: int = bounded(KERNEL_SIZE, low=3, high=63, unit="pixels")
    ols_window: int = bounded(OLS_WINDOW, low=1, high=255, unit="pixels")
    ols_ridge: float = bounded(OLS_RIDGE, low=0, low_open=True)
    bandwidth: Literal["image", "pixel"] = "image"

    def __post_init__(self):
        check_fields(self)
        object.__setattr__(self, "widths", tuple(self.widths))
        if len(self.widths) != 3 or any(w < 1 for w in self.widths):
            raise ConfigError(f"NJSConfig.widths: three widths >= 1, got {list(self.widths)}")
        check_window(self.kernel_size, "NJSConfig.kernel_size")
        check_window(self.ols_window, "NJSConfig.ols_window")


def njs_net(config: NJSConfig) -> NJSNet:
    return NJSNet(config.widths, config.kernel_size)


def njs_init(key: jax.Array, config: NJSConfig = NJSConfig()):
    """The network's parameters (flax variables ``{"params": ...}``)."""
    return njs_net(config).init(key, jnp.zeros((1, 16, 16, INPUT_CHANNELS), jnp.float32))


def njs_apply(params, noisy, variance, ols_a, ols_b, config: NJSConfig = NJSConfig(), *,
              clamp: bool = False) -> jax.Array:
    """Network and combination on precomputed cross regressions: ``noisy`` (the whole image's
    noisy colour), ``variance`` (its variance of the mean), ``ols_a``, ``ols_b``, each
    (..., H, W, 3) -> (..., H, W, 3). ``clamp``: at 0 (test time; the authors train
    unclamped). Pure, differentiable in ``params`` and the arrays."""
    weights, alpha = njs_net(config).apply(params, njs_inputs(noisy, variance, ols_a, ols_b))
    return js_combine(noisy, variance, ols_a, ols_b, weights, alpha, config.kernel_size, clamp)


def njs_combiner(params, half_a: HalfBuffer, half_b: HalfBuffer, variance,
                 config: NJSConfig = NJSConfig(), *, clamp: bool = True) -> jax.Array:
    """Everything from two half buffers: the cross regressions (``config.bandwidth``), then
    :func:`njs_apply` on the halves' mean colour ``(A + B) / 2`` with ``variance``, the
    variance of that mean, (..., H, W, 3). Returns (..., H, W, 3), clamped at 0 by default
    (test time)."""
    ols_a, ols_b = cross_regressions(half_a, half_b, config.bandwidth, window=config.ols_window,
                                     ridge=config.ols_ridge)
    noisy = 0.5 * (jnp.asarray(half_a.color, jnp.float32) + jnp.asarray(half_b.color,
                                                                        jnp.float32))
    return njs_apply(params, noisy, variance, ols_a, ols_b, config, clamp=clamp)


def parameter_count(config: NJSConfig = NJSConfig()) -> int:
    """The network's number of parameters (539426 for the authors')."""
    w1, w2, w3 = config.widths
    taps = config.kernel_size ** 2 + 1
    convs = [(INPUT_CHANNELS, w1), (w1, w1), (w1, w2), (w2, w2), (w2, w3), (w3, w3),
             (w3 + w2, w2), (w2, w2), (w2 + w1, w1), (w1, w1), (w1, taps)]
    return sum(9 * cin * cout + cout for cin, cout in convs)


__all__ = [
    "BANDWIDTHS",
    "JS_EPS",
    "OLS_MIN_WEIGHT",
    "OLS_RIDGE",
    "OLS_SCALE_EPS",
    "OLS_WEIGHT_EPS",
    "OLS_WINDOW",
    "HalfBuffer",
    "NJSConfig",
    "bandwidth_variance",
    "block_side",
    "collaborative_ols",
    "cross_regressions",
    "half_buffers",
    "james_stein",
    "js_combine",
    "mirror_index",
    "njs_apply",
    "njs_combiner",
    "njs_init",
    "njs_net",
    "parameter_count",
    "shrinkage",
    "weighted_variance",
]
