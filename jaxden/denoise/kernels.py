"""Weight-sharing kernel decoder (Fan et al. 2021, Sec. 3 and 4.2): filtering and fusion.

Given a colour image ``c`` (in WSKP the demodulated irradiance) and one importance map ``I``
per kernel size ``k``, the kernel of pixel ``p`` over its ``k x k`` window ``Omega_p`` is

    w_p(q) = exp(I(q)) / sum_{q' in Omega_p} exp(I(q')),        (paper Eq. 3; "splatting":
                                                                  q's weight is q's importance)
    R_k(p) = sum_{q in Omega_p} w_p(q) c(q)                      (Eq. 4)

Neighbours outside the image have no weight (the window is renormalised over its in-image
part), which equals ``box_k(exp(I) * c) / box_k(exp(I))`` with ``box_k`` a zero-padded ``k x k``
sum. ``M`` filtered images are fused by a per-pixel softmax over ``M`` logits (Eq. 5).

Two implementations of the filter, which agree to float32 round-off (tests assert it):

* :func:`filter_unfold` (reference) materialises the ``(..., H, W, k*k)`` kernel map exactly as
  the paper describes (unfold, softmax over the window, weighted sum). Clear, slow, and memory
  hungry (``k = 13`` at 1280 x 720 is 0.6 GB for the weights alone).
* :func:`filter_box` (production) never forms anything larger than ``(..., H, W, C + 1)``. It
  computes the two box sums separably (a pass along W, then a pass along H), each pass as a sum
  of ``k`` shifted terms, carrying a *per-pixel log-scale*: after the W pass each pixel holds
  ``(m1, S1)`` with ``S1 = sum_dx exp(I - m1) [c, 1]`` and ``m1`` the max of ``I`` over its row
  window; the H pass rescales the neighbours' ``S1`` by ``exp(m1(q) - m2(p))`` with ``m2`` the
  max of ``m1`` over the column window (= the 2-D max-pool of ``I``). Every exponent is <= 0 and
  the denominator is >= 1 (the window's maximum contributes exp(0)), so there is no overflow,
  no 0/0, and underflow only drops terms below e^-87 of the window's largest weight.

Why this form and not the alternatives (max relative error against a float64 brute force on a
320 x 180 crop, k = 3 and 13; see the report of the issue for timings):

* A *global* max shift, ``exp(I - max I)``, underflows to 0/0 (NaN) wherever a whole window lies
  more than ~87-104 below the image maximum: with importance ~ N(0, 20^2) every global-shift
  variant returned NaN, this form 5e-7. Importance maps from a network are not bounded.
* A per-pixel local max ``m(q)`` used *inside* ``box_k(exp(I - m) c) / box_k(exp(I - m))`` is
  simply wrong: the weights ``exp(I(q) - m(q))`` are no longer proportional to ``exp(I(q))``.
  A stabiliser must be constant over each output window, hence the per-pass rescaling above.
* Summed-area tables / cumulative sums cost O(1) per pixel independently of ``k`` but lose
  float32 accuracy by cancellation (a window sum is the difference of two prefix sums carrying
  the whole row's or image's mass of ``exp(I)``): importance ~ N(0, 1): 6e-3 (2-D table) and
  1e-4 (separable cumsums); N(0, 5^2): 14 % and 4 % at k = 13, inf/NaN at k = 3. They also
  cannot take a window-local stabiliser.
* ``lax.reduce_window`` sums or plain shifted sums with the global shift are accurate (2e-6)
  while they do not underflow. Timings, six kernels 3..13 at 1280 x 720 x 3, CPU seconds on
  the 2-core machine: this form 1.08, global shift + shifted sums 0.44, + separable cumsums
  0.74, + 2-D table 0.82, + reduce_window 1.42; unfold 17.9. So robustness costs ~2.4x against
  the fastest unsafe form (one exponential per pixel instead of 2 k per pass).

The production decoder (:func:`decode` with ``form="box"``, and :func:`filter_box`) takes a
faster exact path whenever it can: if every importance map's range (max - min over the image)
is below ``GLOBAL_SHIFT_RANGE`` = 64, one shift per map (its maximum) keeps every window's
largest weight above e^-64, so nothing that matters underflows. The weights ``exp(I - max I)``
are then computed once per pixel and map, the two box sums are power-of-two partial sums
(k = 13 in 5 additions instead of 12) on channel-first planes (contiguous along W), and the
quotient is normalised so that reverse mode never squares a tiny denominator. Otherwise (a
wider range, NaN, inf) the call takes the per-window form above. The choice is one
``lax.cond`` on the primal (jvp and grad keep it; a ``vmap`` over importance maps evaluates
both paths). The trained WSKP-6 produces ranges of 4-47 on the held-out crops. Six kernels at
1280 x 720: 2.2x faster than the per-window form alone forward, 1.3x forward+backward
(``jaxden bench decoder`` reports both paths).

Both filters are jitted, differentiable in ``color`` and ``importance``, accept leading batch
dimensions, and are float32 throughout (inputs are promoted to at least float32).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError

DEFAULT_KERNEL_SIZES: tuple[int, ...] = (3, 5, 7, 9, 11, 13)
FORMS: tuple[str, ...] = ("box", "unfold")


# --------------------------------------------------------------------------------- checks
def _check_kernel_size(kernel_size, where: str) -> int:
    if isinstance(kernel_size, bool) or not isinstance(kernel_size, (int, np.integer)):
        raise ConfigError(f"{where}: kernel size must be an odd int >= 1, got {kernel_size!r}")
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ConfigError(
            f"{where}: kernel size must be odd and >= 1 (a window centred on the pixel), "
            f"got {kernel_size}"
        )
    return int(kernel_size)


def _check_color_importance(color, importance, where: str) -> None:
    if color.ndim < 3:
        raise FrameError(f"{where}: colour must have shape (..., H, W, C), got {color.shape}")
    if importance.shape != color.shape[:-1]:
        raise FrameError(
            f"{where}: importance must have shape (..., H, W) = {color.shape[:-1]} to match the "
            f"colour of shape (..., H, W, C) = {color.shape}, got {importance.shape}"
        )
    for name, array in (("colour", color), ("importance", importance)):
        if not jnp.issubdtype(array.dtype, jnp.floating):
            raise FrameError(f"{where}: {name} must be floating point, got {array.dtype}")


def _as_float(x):
    x = jnp.asarray(x)
    # Promote half precision (and leave float64 alone under x64): exp(I) sums need float32.
    if jnp.issubdtype(x.dtype, jnp.floating) and jnp.finfo(x.dtype).bits < 32:
        x = x.astype(jnp.float32)
    return x


# ------------------------------------------------------------------------ reference form
def _unfold(x, kernel_size: int):
    """(..., H, W, C) -> (..., H, W, k*k, C): zero-padded k x k windows, row-major offsets.

    One gather with a static index table (compiles in well under a second for k = 13, where
    k*k separate slices take tens of seconds).
    """
    radius = kernel_size // 2
    height, width = x.shape[-3], x.shape[-2]
    pad = [(0, 0)] * (x.ndim - 3) + [(radius, radius), (radius, radius), (0, 0)]
    padded = jnp.pad(x, pad)
    dy, dx = np.divmod(np.arange(kernel_size * kernel_size), kernel_size)
    rows = np.arange(height)[:, None, None] + dy[None, None, :]  # (H, 1, k*k)
    cols = np.arange(width)[None, :, None] + dx[None, None, :]  # (1, W, k*k)
    return padded[..., rows, cols, :]


def _inside_mask(height: int, width: int, kernel_size: int) -> np.ndarray:
    """(H, W, k*k) bool: which window offsets of each pixel fall inside the image."""
    ones = np.ones((height, width, 1), np.float32)
    radius = kernel_size // 2
    padded = np.pad(ones, [(radius, radius), (radius, radius), (0, 0)])
    windows = [
        padded[dy : dy + height, dx : dx + width, 0]
        for dy in range(kernel_size)
        for dx in range(kernel_size)
    ]
    return np.stack(windows, axis=-1) > 0


@functools.partial(jax.jit, static_argnames=("kernel_size",))
def _filter_unfold(color, importance, kernel_size: int):
    height, width = color.shape[-3], color.shape[-2]
    logits = _unfold(importance[..., None], kernel_size)[..., 0]  # (..., H, W, k*k)
    inside = _inside_mask(height, width, kernel_size)
    weights = jax.nn.softmax(logits, axis=-1, where=inside)  # Eq. 3, 0 outside the image
    return jnp.einsum("...q,...qc->...c", weights, _unfold(color, kernel_size))  # Eq. 4


def filter_unfold(color, importance, kernel_size: int):
    """Reference WSKP filter: unfold k x k windows, softmax of importance, weighted sum.

    Args:
      color: (..., H, W, C) image to filter (linear values; WSKP passes irradiance).
      importance: (..., H, W) importance map ``I`` (log-weights, unitless, any real value).
      kernel_size: odd window size ``k`` >= 1 (static).

    Returns:
      (..., H, W, C): ``sum_q softmax_{q in window}(I(q)) c(q)``; out-of-image neighbours get
      no weight. Materialises (..., H, W, k*k, C): use for tests and small images only.

    Raises:
      FrameError: wrong shapes or non-float dtypes. ConfigError: bad kernel size.
    """
    kernel_size = _check_kernel_size(kernel_size, "filter_unfold")
    color, importance = _as_float(color), _as_float(importance)
    _check_color_importance(color, importance, "filter_unfold")
    return _filter_unfold(color, importance, kernel_size)


# ----------------------------------------------------------------------- production form
def _scaled_window_sum(log_scale, values, kernel_size: int, axis: int):
    """One separable pass of a k-window sum of ``exp(log_scale) * values`` along one axis.

    ``log_scale`` is (..., H, W) and ``values`` (..., H, W, C); ``axis`` indexes ``log_scale``
    (-2 for H, -1 for W). Returns ``(new_scale, sums)`` with
    ``new_scale(p) = max_{q in window(p)} log_scale(q)`` (gradient stopped: the final ratio does
    not depend on it) and ``sums(p) = sum_q exp(log_scale(q) - new_scale(p)) values(q)``.
    Out-of-image neighbours enter as log-scale -inf and value 0, i.e. with zero weight; every
    exponent is <= 0 so nothing overflows.

    The k terms are added in a ``fori_loop`` over the offset: each step is one fused loop
    (slice, exp, multiply-add into the accumulator), so no k shifted copies are materialised;
    measured at 1280 x 720, k = 13 against the unrolled sum: 0.6x the time, 0.4x the
    temporary memory, 0.4x the compile time. The loop body is ``jax.checkpoint``-ed, so
    reverse mode recomputes each step's exponential from the loop-invariant padded inputs
    instead of storing k residual images: decode's forward+backward temporaries at 1280 x 720
    with six kernels drop from 1.8 GB to 0.68 GB, and it runs faster.
    """
    ndim = log_scale.ndim
    axis = axis % ndim
    radius = kernel_size // 2
    size = log_scale.shape[axis]
    pad = [(0, 0)] * (ndim + 1)
    pad[axis] = (radius, radius)
    padded_scale = jnp.pad(log_scale, pad[:ndim], constant_values=-jnp.inf)
    padded_values = jnp.pad(values, pad)
    window = tuple(kernel_size if a == axis else 1 for a in range(ndim))
    new_scale = jax.lax.stop_gradient(
        jax.lax.reduce_window(padded_scale, -jnp.inf, jax.lax.max, window, (1,) * ndim, "VALID")
    )

    def add_offset(offset, total):
        scale = jax.lax.dynamic_slice_in_dim(padded_scale, offset, size, axis=axis)
        value = jax.lax.dynamic_slice_in_dim(padded_values, offset, size, axis=axis)
        return total + jnp.exp(scale - new_scale)[..., None] * value

    step = jax.checkpoint(add_offset)
    total = jax.lax.fori_loop(0, kernel_size, step, jnp.zeros_like(values))
    return new_scale, total


def _filter_box_windowed(color, importance, kernel_size: int):
    """The per-window-stabilised filter (any importance range); see the module docstring."""
    if kernel_size == 1:
        return color  # a 1 x 1 window: the weight is exactly 1
    ones = jnp.ones(color.shape[:-1] + (1,), color.dtype)
    values = jnp.concatenate([color, ones], axis=-1)  # numerator channels and the denominator
    scale, sums = _scaled_window_sum(importance, values, kernel_size, axis=-1)  # along W
    _, sums = _scaled_window_sum(scale, sums, kernel_size, axis=-2)  # along H
    return sums[..., :-1] / sums[..., -1:]  # denominator >= 1 by construction


#: Largest importance range (max - min over each map) that takes the global-shift path: every
#: window's largest weight is then > e^-64 (a normal float32) and the terms that underflow
#: (below e^-87.3) are < e^-23 of it, a relative error below 169 e^-23 = 2e-8.
GLOBAL_SHIFT_RANGE = 64.0


def _box_sum(values, kernel_size: int, axis: int):
    """Zero-padded centred k-window sum along ``axis`` from power-of-two partial sums.

    ``S_2m(i) = S_m(i) + S_m(i + m)`` builds windows of 1, 2, 4, 8 ... samples; the k-window is
    the sum of the ones in k's binary expansion at consecutive offsets: k = 13 takes 3 doublings
    and 2 additions instead of 12 shifted additions. All slices are static and the sum is
    linear, so its transpose (the gradient) is the same shape of program.
    """
    radius = kernel_size // 2
    size = values.shape[axis]
    pad = [(0, 0)] * values.ndim
    pad[axis] = (radius, radius)
    partial = {1: jnp.pad(values, pad)}  # length size + k - 1
    width = 1
    while 2 * width <= kernel_size:
        prev = partial[width]
        length = prev.shape[axis] - width
        partial[2 * width] = (jax.lax.slice_in_dim(prev, 0, length, axis=axis)
                              + jax.lax.slice_in_dim(prev, width, width + length, axis=axis))
        width *= 2
    total, offset = None, 0
    for width in sorted(partial, reverse=True):
        if kernel_size & width:
            part = jax.lax.slice_in_dim(partial[width], offset, offset + size, axis=axis)
            total = part if total is None else total + part
            offset += width
    return total


def _global_shift_ok(importance_maps):
    """Scalar bool: every map's range (over H, W; all batch items) is below the threshold.

    False for NaN or infinite importance, which then take the per-window path as before.
    """
    spread = jnp.max(importance_maps, axis=(-3, -2)) - jnp.min(importance_maps, axis=(-3, -2))
    return jnp.all(spread < GLOBAL_SHIFT_RANGE)


def _decode_shifted(color, importance_maps, fusion_logits, kernel_sizes):
    """Filter and fuse with one shift per map (its maximum), channel-first: see the docstring.

    Planes are (..., C, H, W) so that the window sums run along the contiguous W axis on
    full-width vectors (channel-last (H, W, 4) vectorises badly on the CPU: 2x slower).
    """
    maps = jnp.moveaxis(importance_maps, -1, -3)  # (..., M, H, W)
    shift = jax.lax.stop_gradient(jnp.max(maps, axis=(-2, -1), keepdims=True))
    weights = jnp.exp(maps - shift)  # (..., M, H, W), in (e^-60, 1]
    planes = jnp.moveaxis(color, -1, -3)  # (..., C, H, W)
    alpha = jax.nn.softmax(jnp.moveaxis(fusion_logits, -1, -3), axis=-3)  # Eq. 5
    out = jnp.zeros_like(planes)
    for i, k in enumerate(kernel_sizes):
        a = alpha[..., i : i + 1, :, :]
        if k == 1:
            out = out + a * planes
            continue
        w = weights[..., i : i + 1, :, :]
        sums = jnp.concatenate([w * planes, w], axis=-3)
        sums = _box_sum(_box_sum(sums, k, axis=-1), k, axis=-2)
        # The weight sum lies in (e^-64, k^2]. Reverse mode of a quotient forms the inverse
        # square of its denominator (e^128: inf in float32), so divide both by the sum (as a
        # constant) first: the quotient's denominator is then 1 up to round-off.
        norm = jax.lax.stop_gradient(1.0 / sums[..., -1:, :, :])
        out = out + (sums[..., :-1, :, :] * norm) * (a / (sums[..., -1:, :, :] * norm))
    return jnp.moveaxis(out, -3, -1)


def _decode_windowed(color, importance_maps, fusion_logits, kernel_sizes):
    filtered = [_filter_box_windowed(color, importance_maps[..., i], k)
                for i, k in enumerate(kernel_sizes)]
    return _fuse(jnp.stack(filtered, axis=-4), fusion_logits)


def _decode_box(color, importance_maps, fusion_logits, kernel_sizes):
    """The production decoder: the fast global-shift path when it is exact, else per window."""
    return jax.lax.cond(
        _global_shift_ok(importance_maps),
        functools.partial(_decode_shifted, kernel_sizes=kernel_sizes),
        functools.partial(_decode_windowed, kernel_sizes=kernel_sizes),
        color, importance_maps, fusion_logits,
    )


@functools.partial(jax.jit, static_argnames=("kernel_size",))
def _filter_box(color, importance, kernel_size: int):
    if kernel_size == 1:
        return color
    # One kernel size is a decode with a single map and a fusion weight of 1.
    logits = jnp.zeros(importance.shape + (1,), color.dtype)
    return _decode_box(color, importance[..., None], logits, (kernel_size,))


def filter_box(color, importance, kernel_size: int):
    """Production WSKP filter: ``box_k(exp(I) c) / box_k(exp(I))`` without a k*k tensor.

    Same contract and result as :func:`filter_unfold` (see the module docstring for the
    separable, per-window-stabilised evaluation). Cost: ``2 k`` exponentials and ``2 k (C+1)``
    multiply-adds per pixel, memory O(H W (C + 1)).

    Args:
      color: (..., H, W, C) image to filter.
      importance: (..., H, W) importance map (any real values; +-1e3 is fine, +-inf is not).
      kernel_size: odd window size ``k`` >= 1 (static).

    Returns:
      (..., H, W, C) filtered image, dtype of the (float32-promoted) inputs.

    Raises:
      FrameError: wrong shapes or non-float dtypes. ConfigError: bad kernel size.
    """
    kernel_size = _check_kernel_size(kernel_size, "filter_box")
    color, importance = _as_float(color), _as_float(importance)
    _check_color_importance(color, importance, "filter_box")
    return _filter_box(color, importance, kernel_size)


# ---------------------------------------------------------------------------- fusion
@jax.jit
def _fuse(filtered, logits):
    weights = jax.nn.softmax(logits, axis=-1)  # (..., H, W, M), Eq. 5's alpha
    return jnp.einsum("...mhwc,...hwm->...hwc", filtered, weights)


def fuse(filtered, logits):
    """Fuse M filtered images with a per-pixel softmax over M logits (paper Eq. 5).

    Args:
      filtered: a sequence of M arrays (..., H, W, C), or one array (..., M, H, W, C).
      logits: (..., H, W, M) fusion logits (unnormalised).

    Returns:
      (..., H, W, C): ``sum_i softmax(logits)_i * filtered_i``.

    Raises:
      FrameError: M or the image shapes disagree.
    """
    if isinstance(filtered, Sequence) and not hasattr(filtered, "shape"):
        if not filtered:
            raise FrameError("fuse: got an empty list of filtered images")
        shapes = {jnp.shape(f) for f in filtered}
        if len(shapes) != 1:
            raise FrameError(f"fuse: filtered images have different shapes {sorted(shapes)}")
        filtered = jnp.stack([_as_float(f) for f in filtered], axis=-4)
    filtered, logits = _as_float(filtered), _as_float(logits)
    if filtered.ndim < 4:
        raise FrameError(
            f"fuse: filtered must be (..., M, H, W, C) or a list of (..., H, W, C), got "
            f"{filtered.shape}"
        )
    batch, count, image = filtered.shape[:-4], filtered.shape[-4], filtered.shape[-3:-1]
    if logits.shape != batch + image + (count,):
        raise FrameError(
            f"fuse: logits must have shape (..., H, W, M) = {batch + image + (count,)} for "
            f"{count} filtered images of shape (..., H, W, C) = {batch + filtered.shape[-3:]}, "
            f"got {logits.shape}"
        )
    return _fuse(filtered, logits)


# ---------------------------------------------------------------------------- decoder
@functools.partial(jax.jit, static_argnames=("kernel_sizes", "form"))
def _decode(color, importance_maps, fusion_logits, kernel_sizes, form):
    if form == "box":
        return _decode_box(color, importance_maps, fusion_logits, kernel_sizes)
    filtered = [
        _filter_unfold(color, importance_maps[..., i], k) for i, k in enumerate(kernel_sizes)
    ]
    return _fuse(jnp.stack(filtered, axis=-4), fusion_logits)


def decode(
    color,
    importance_maps,
    fusion_logits,
    kernel_sizes: Sequence[int] = DEFAULT_KERNEL_SIZES,
    form: str = "box",
):
    """The WSKP reconstruction phase: filter with M kernel sizes, then fuse (Eqs. 3-5).

    Args:
      color: (..., H, W, C) image to filter. WSKP filters the demodulated irradiance
        (radiance / albedo) and multiplies the albedo back afterwards; that is the caller's job.
      importance_maps: (..., H, W, M) one importance map per kernel size.
      fusion_logits: (..., H, W, M) per-pixel fusion logits (softmax over M).
      kernel_sizes: M odd window sizes, default (3, 5, 7, 9, 11, 13) as in the paper.
      form: ``'box'`` (production, memory-light) or ``'unfold'`` (reference).

    Returns:
      (..., H, W, C) reconstructed image.

    Raises:
      FrameError: shapes disagree. ConfigError: bad kernel sizes or form.
    """
    if form not in FORMS:
        raise ConfigError(f"decode: form must be one of {FORMS}, got {form!r}")
    if isinstance(kernel_sizes, (int, np.integer)) or not len(kernel_sizes):
        raise ConfigError(
            f"decode: kernel_sizes must be a non-empty sequence, got {kernel_sizes!r}"
        )
    kernel_sizes = tuple(_check_kernel_size(k, "decode") for k in kernel_sizes)
    color = _as_float(color)
    importance_maps, fusion_logits = _as_float(importance_maps), _as_float(fusion_logits)
    if color.ndim < 3:
        raise FrameError(f"decode: colour must have shape (..., H, W, C), got {color.shape}")
    expected = color.shape[:-1] + (len(kernel_sizes),)
    for name, array in (("importance_maps", importance_maps), ("fusion_logits", fusion_logits)):
        if array.shape != expected:
            raise FrameError(
                f"decode: {name} must have shape (..., H, W, M) = {expected} for colour "
                f"{color.shape} and {len(kernel_sizes)} kernel sizes {kernel_sizes}, "
                f"got {array.shape}"
            )
    for name, array in (("colour", color), ("importance_maps", importance_maps),
                        ("fusion_logits", fusion_logits)):
        if not jnp.issubdtype(array.dtype, jnp.floating):
            raise FrameError(f"decode: {name} must be floating point, got {array.dtype}")
    return _decode(color, importance_maps, fusion_logits, kernel_sizes, form)
