"""Monte Carlo SURE: a per-pixel, per-channel estimate of a denoiser's squared error.

Stein's unbiased risk estimate (Stein 1981) for a denoiser ``y = F(x)`` of a Monte Carlo image
``x = mu + e``, ``e ~ N(0, diag(var))``, with ``var`` the variance of the pixel *mean*
(``Frame.variance``).

Derivation (per pixel and channel ``i``)
----------------------------------------
Write ``(y_i - mu_i)^2 = (y_i - x_i)^2 + 2 (y_i - x_i) e_i + e_i^2``. Then ``E[e_i^2] = var_i``
and, by Stein's lemma for the independent Gaussian coordinate ``e_i`` (``F`` weakly
differentiable, ``E|d F_i / d x_i| < inf``), ``E[y_i e_i] = var_i E[d y_i / d x_i]``, so
``E[(y_i - x_i) e_i] = var_i E[d y_i/d x_i] - var_i`` and::

    E[(y_i - mu_i)^2] = E[ (y_i - x_i)^2 - var_i + 2 var_i d y_i / d x_i ]      (per pixel/channel)

The summand is the per-pixel SURE; summed over pixels and channels it is d times the paper's
Eq. 1 (d = 3 H W) with diagonal Sigma. The paper writes the last term as ``2 sigma^2 f'(x)``; here it is
``divergence_term = var_i * J_ii`` with ``J = dF/dx`` the Jacobian w.r.t. the colour only.

Probe estimator of ``var_i J_ii`` (Ramani et al. 2008, the paper's Eq. 2)
------------------------------------------------------------------------
Draw ``b ~ N(0, diag(var))`` on the colour channels only (albedo, normal, ... stay fixed).
``E_b[b_i (J b)_i] = sum_j J_ij E[b_i b_j] = var_i J_ii``, so::

    divergence_term_i = (1/K) sum_k b_{k,i} (J b_k)_i

is unbiased for ``var_i J_ii`` given ``x``; hence the per-pixel SURE built from it is unbiased
for ``E[(y_i - mu_i)^2]`` in expectation over the probes AND the noise (tower property). Its
probe variance, given ``x``, is::

    Var_b = (2 var_i^2 J_ii^2 + var_i sum_{j != i} var_j J_ij^2) / K

(``E[b_i^3 b_j] = 0`` and ``E[b_i^2 b_j b_l] = 0`` for ``j != l`` kill the cross terms), so
pixels whose output depends on many neighbours (a blurring denoiser) get noisy per-pixel
estimates; sums over regions average the noise away. This is on top of the intrinsic noise of
SURE over ``x`` (the paper's Fig. 3: per-pixel SURE is too noisy to use alone).

Rademacher probes (``probe_dist="rademacher"``; Hutchinson 1990): ``b = sqrt(var) r`` with
``r_i = +-1`` equally likely. ``E[r r^T] = I`` as for normals, so the estimator stays
unbiased, but ``r_i^2 = 1`` removes the diagonal term of the probe variance::

    Var_b = var_i sum_{j != i} var_j J_ij^2 / K

(the ``2 var_i^2 J_ii^2 / K`` of normal probes is gone), never more than the normal probes'
and far less where the output follows its own pixel (``J_ii`` large), as a denoiser does at
high spp: one Rademacher probe through OIDN is less noisy per pixel than four normal ones
from 256 spp on (``experiments/results/sure/sure-probe-noise.md``). The signs are those of
the normal draws (``r = +1`` where ``n >= 0``), so tiles, chunks and black boxes see the
same probes for the same key. With a colour covariance the probes are ``L r`` (unbiased,
``E[L r r^T L^T] = Sigma``), and the diagonal term shrinks without vanishing.

Correlated colour channels (``Frame.covariance``)
------------------------------------------------
R, G and B of one Monte Carlo sample come from one path, so the noise of a pixel mean is
correlated across channels (a median correlation of 0.85-0.99 per crop on jaxden's procedural
test scenes). With ``e ~ N(0, Sigma)`` per pixel, Sigma the 3 x 3 covariance of the mean,
Stein's lemma gives ``E[(y - x) . e] = tr(Sigma E[J]) - tr(Sigma)``, and the per-channel
split of the same derivation is ``E[(y_i - mu_i)^2] = E[(y_i - x_i)^2 - var_i + 2 (J
Sigma)_ii]``. Probes ``b = L n`` with ``L L^T = Sigma`` (:func:`colour_factor`) give
``E_b[b_i (J b)_i] = (J Sigma)_ii``, so the estimator above is unchanged but for the probes.
The diagonal form misses ``sum_{j != i} J_ij Sigma_ji``: nothing for a denoiser that filters
each channel on its own, but a network that mixes channels (a U-Net) is underestimated where
the cross-channel derivatives are positive (measured: the median crop's SURE of a U-Net at
64 spp is 0.45 of the true MSE with the diagonal and 0.97 with the covariance,
``docs/results.md``). A frame with ``covariance`` uses it; one without keeps the diagonal.

Assumptions, and where they fail: x Gaussian (Monte Carlo means are only asymptotically
Gaussian); R, G, B independent unless the frame carries ``covariance`` (the paper, Sec. 3.2,
ignores the correlation); ``var`` the true variance (a per-pixel sample estimate in practice); F
weakly differentiable, i.e. continuous (ReLU kinks and clamps are fine: ``jax.jvp`` gives the
a.e. derivative). A denoiser with jumps (hard thresholds, argmax routing) breaks Stein's
lemma; the jvp then misses the jump contributions and SURE is biased.

Methods
-------
``"jvp"``: ``J b`` exactly from ``jax.jvp`` (no epsilon, no bias beyond float round-off);
probes batched with ``vmap`` in chunks of ``probe_batch`` (a ``lax.scan`` over the chunks), so
memory grows with ``probe_batch``, not with ``num_probes``. Within a chunk the primal pass runs
once (only tangents are batched); each chunk reruns the primal.

``"fd"``: finite differences, for denoisers with no usable derivative. ``forward`` is the
authors' form ``(F(x + eps b) - F(x)) / eps``; ``central`` is ``(F(x + eps b) - F(x - eps b))
/ (2 eps)`` (one more evaluation per probe). By Taylor, with ``H`` and ``T`` the second and
third derivatives of ``F``, forward gives ``J b + (eps/2) H[b, b] + (eps^2/6) T[b, b, b] + ...``
and central ``J b + (eps^2/6) T[b, b, b] + O(eps^4)``: the error of a single estimate is
``O(eps)`` (curvature) for forward and ``O(eps^2)`` for central. Averaged over the probes,
forward's ``O(eps)`` term cancels (``b_i H_i[b, b]`` is odd in ``b`` and the Gaussian probes
are symmetric; it only adds probe variance). In fact the two schemes have exactly the same
expectation: ``E[b_i F_i(x)] = 0`` and ``E[b_i F_i(x - eps b)] = -E[b_i F_i(x + eps b)]``, so
both equal ``E[b_i F_i(x + eps b)] / eps = var_i E[J_ii(x + eps b)]`` (Stein's lemma): the
Jacobian diagonal averaged over ``N(0, eps^2 diag(var))``. The bias of the estimate's
expectation is therefore ``O(eps^2)`` for both, ``(eps^2/2) var_i sum_j var_j
d^3 F_i / (dx_i dx_j^2) + O(eps^4)`` for smooth ``F``; central's gain is the smaller
per-probe error (less probe variance), not a smaller bias. Both add round-off of order
``u |F(x)| / (eps |b|)`` (``u`` the float epsilon)
relative to ``J b``: in float32 with the authors' ``eps = 1e-4``, ``|F| ~ 1`` and
``|b| = sqrt(var) ~ 1e-2`` (high spp) that bound is ~10%; bright pixels are worse.

Round-off in float32 (measured, tests/test_sure_properties.py): on an 8 x 8 tanh net with
x in [0, 2] and var in [1e-3, 0.1], the relative L2 error of the forward difference vs the
exact jvp is 3.5e-3 at eps = 1e-2, 7e-4 at 1e-3 (best), 5e-3 at 1e-4 (authors' default) and
5e-2 at 1e-5; in float64 it falls as eps (central: eps^2) down to 1e-6. Use ``"jvp"`` where
the denoiser is differentiable. (Using the realised perturbation fl(x + eps b) - x as the
probe was tried: no measurable gain, since rounding of the outputs dominates; not kept.)

``sure_buffers`` replaces the probe divergence by a covariance estimate from K independent
sub-buffers of the render (no Gaussian assumption, no derivative; see the derivation above
that function), for Monte Carlo noise that Stein's identity gets wrong.

``sure_blackbox`` does the ``"fd"`` method in NumPy (float64 arithmetic, float32 denoiser
inputs) for non-JAX denoisers such as OIDN through ``pyoidn``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame, NonFinitePolicy

Method = Literal["jvp", "fd"]
FdScheme = Literal["forward", "central"]
ProbeDist = Literal["normal", "rademacher"]
PROBE_DISTS = ("normal", "rademacher")

_UNSET = object()


class SureResult(NamedTuple):
    """Per-pixel SURE and its parts; every field has the colour's shape (..., H, W, 3).

    ``sure = residual_sq - variance + 2 * divergence_term`` exactly.

    - ``sure``: estimate of the squared error (y - mu)^2 of the denoised image, radiance^2.
    - ``residual_sq``: (y - x)^2.
    - ``divergence_term``: var * dy_c/dx_c (the paper's sigma^2 f'(x)), probe estimate.
    - ``denoised``: y = F(x).
    """

    sure: Any
    residual_sq: Any
    divergence_term: Any
    denoised: Any

    def mse(self) -> Any:
        """Image-level SURE: mean over (H, W, 3), shape (...)."""
        return jnp.mean(self.sure, axis=(-3, -2, -1))


def sure_from_parts(noisy, denoised, variance, divergence_term) -> jax.Array:
    """SURE = (y - x)^2 - var + 2 * var * dy/dx, per pixel and channel (shapes broadcast)."""
    return jnp.square(denoised - noisy) - variance + 2.0 * divergence_term


# ---------------------------------------------------------------------------------- checks


def _is_concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def _is_positive_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1


def _check_options(num_probes, method, eps, fd_scheme, probe_batch) -> int:
    """Validate the options; return the effective probe batch."""
    if not _is_positive_int(num_probes):
        raise ConfigError(f"sure: num_probes must be an integer >= 1, got {num_probes!r}")
    if method not in ("jvp", "fd"):
        raise ConfigError(f"sure: method must be 'jvp' or 'fd', got {method!r}")
    if fd_scheme not in ("forward", "central"):
        raise ConfigError(f"sure: fd_scheme must be 'forward' or 'central', got {fd_scheme!r}")
    if isinstance(eps, jax.core.Tracer):
        if np.shape(eps) != ():
            raise ConfigError(f"sure: eps must be a scalar, got shape {np.shape(eps)}")
    elif (not isinstance(eps, (int, float, np.floating)) or isinstance(eps, bool)
          or not math.isfinite(eps) or eps <= 0):
        raise ConfigError(f"sure: eps must be a finite float > 0, got {eps!r}")
    if probe_batch is None:
        return int(num_probes)
    if not _is_positive_int(probe_batch):
        raise ConfigError(f"sure: probe_batch must be None or an integer >= 1, got {probe_batch!r}")
    return int(min(probe_batch, num_probes))


def require_variance(frame, where: str, held_in: str = "Frame.variance") -> None:
    """FrameError unless ``frame`` is a Frame with the variance of the pixel mean, which SURE
    needs; ``held_in`` names where the caller's user keeps it (a Frame field, EXR channels)."""
    if not isinstance(frame, Frame):
        raise FrameError(f"{where}: expected a jaxden Frame, got {type(frame).__name__}")
    if frame.variance is None:
        raise FrameError(
            f"{where}: SURE needs the variance of the pixel mean ({held_in}: sample "
            f"variance / spp), but the frame has only {', '.join(frame.features())}"
        )


def _checked_frame(frame, where: str, nonfinite: NonFinitePolicy) -> Frame:
    """Structural checks always; value checks (NaN, negative variance) on concrete arrays."""
    require_variance(frame, where)
    leaves = jax.tree_util.tree_leaves(frame)
    if _is_concrete(*leaves):
        return frame.validated(where=where, nonfinite=nonfinite)
    # Under a transformation (jit/vmap of the caller): shapes only; values cannot be read.
    color_shape, var_shape = np.shape(frame.color), np.shape(frame.variance)
    if len(color_shape) < 3 or color_shape[-1] != 3:
        raise FrameError(f"{where}: colour must have shape (..., H, W, 3), got {color_shape}")
    if var_shape != color_shape:
        raise FrameError(
            f"{where}: variance has shape {var_shape} but the colour has {color_shape}"
        )
    if frame.covariance is not None and np.shape(frame.covariance) != color_shape:
        raise FrameError(f"{where}: covariance has shape {np.shape(frame.covariance)} but the "
                         f"colour has {color_shape}")
    return frame


def _check_output(out_shape, color_shape, where: str) -> None:
    if tuple(out_shape) != tuple(color_shape):
        raise FrameError(
            f"{where}: the denoiser returned shape {tuple(out_shape)}, expected the colour's "
            f"shape {tuple(color_shape)}"
        )


# ---------------------------------------------------------------------------------- probes


def _probe_normal(key, shape, dtype):
    # Drawn flat and reshaped: the same values as normal(key, shape) (counter-based threefry
    # indexes the flat array), but XLA:CPU compiles the flat draw several times faster.
    return jax.random.normal(key, (math.prod(shape),), dtype).reshape(shape)


def check_probe_dist(dist, where: str = "sure") -> str:
    """``dist`` if it names a probe distribution (:data:`PROBE_DISTS`), else ConfigError."""
    if dist not in PROBE_DISTS:
        raise ConfigError(f"{where}: the probe distribution must be one of "
                          f"{', '.join(PROBE_DISTS)}, got {dist!r}")
    return dist


def unit_probes(normals, dist: ProbeDist, xp=jnp):
    """Standard normal draws as probes of ``dist`` (zero mean, identity covariance): the
    normals themselves, or their signs (+1 where ``n >= 0``, -1 elsewhere: never 0)."""
    if dist == "normal":
        return normals
    return xp.where(normals >= 0, 1.0, -1.0).astype(normals.dtype)


def _normals(keys, shape, dtype, dist: ProbeDist = "normal"):
    # lax.map, not vmap: a sequential draw per key equals the unbatched draw for every key
    # implementation (vmap of rbg keys does not), so probe k is the same at any probe_batch.
    return jax.lax.map(lambda k: unit_probes(_probe_normal(k, shape, dtype), dist), keys)


def window_normal(key, frame_shape, origin, shape):
    """The (rows, cols, C) window at ``origin`` (row, column; traced) of
    ``_probe_normal(key, frame_shape, float32)`` for a frame of ``frame_shape`` (H, W, C),
    computed without drawing the rest: with JAX's partitionable threefry (the default) the
    value at flat index i is threefry2x32(key, (0, i)), turned into a normal as
    ``jax.random.normal`` does (a uniform in (-1, 1) from the top 23 bits, then
    sqrt(2) erfinv). Equal bit for bit to the slice of the whole draw (tested), so a tile's
    SURE probes are the whole frame's."""
    from jax.extend.random import threefry2x32_p

    height, width, channels = frame_shape
    if height * width * channels >= 2**32:
        raise FrameError(f"SURE probes over tiles: a {height}x{width} frame is too large "
                         f"(2^32 values at most)")
    origin = jnp.asarray(origin, jnp.uint32)
    rows = origin[0] + jnp.arange(shape[0], dtype=jnp.uint32)
    cols = origin[1] + jnp.arange(shape[1], dtype=jnp.uint32)
    chans = jnp.arange(channels, dtype=jnp.uint32)
    low = (rows[:, None, None] * jnp.uint32(width) + cols[None, :, None]) * jnp.uint32(
        channels) + chans[None, None, :]
    data = jax.random.key_data(key) if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key) \
        else key
    bits1, bits2 = threefry2x32_p.bind(jnp.broadcast_to(data[0], low.shape),
                                       jnp.broadcast_to(data[1], low.shape),
                                       jnp.zeros_like(low), low)
    mantissa = jax.lax.shift_right_logical(bits1 ^ bits2, jnp.uint32(32 - 23))
    one = jnp.uint32(np.array(1.0, np.float32).view(np.uint32))
    floats = jax.lax.bitcast_convert_type(mantissa | one, jnp.float32) - jnp.float32(1.0)
    low_value = np.nextafter(np.float32(-1.0), np.float32(0.0), dtype=np.float32)
    uniform = jnp.maximum(low_value, floats * (np.float32(1.0) - low_value) + low_value)
    return np.float32(np.sqrt(2.0)) * jax.lax.erf_inv(uniform)


def window_normals(keys, frame_shape, origin, shape, dist: ProbeDist = "normal"):
    """:func:`window_normal` for each of ``keys`` (K, ...), as probes of ``dist``
    (:func:`unit_probes`): (K, rows, cols, C)."""
    return jax.lax.map(
        lambda k: unit_probes(window_normal(k, frame_shape, origin, shape), dist), keys)


def colour_factor(variance, covariance, xp=jnp):
    """Per pixel, the lower-triangular L with L L^T = Sigma, the 3 x 3 covariance of the pixel
    mean (``variance`` on the diagonal, ``covariance`` = (R, G), (G, B), (B, R) off it), as
    its six entries (l00, l10, l11, l20, l21, l22), each (..., H, W).

    A closed-form Cholesky that tolerates singular and round-off-indefinite Sigma: a zero
    pivot zeroes its column (a channel without variance gets no noise) and negative Schur
    complements are clipped at 0. With zero covariance L = diag(sqrt(var)), so the probes
    ``L n`` equal ``sqrt(var) * n`` exactly. ``xp``: ``jnp`` (traced) or ``np`` (float64)."""
    v = xp.maximum(variance, 0.0)
    c_rg, c_gb, c_br = covariance[..., 0], covariance[..., 1], covariance[..., 2]

    def over(a, pivot):
        return xp.where(pivot > 0, a / xp.where(pivot > 0, pivot, 1.0), 0.0)

    l00 = xp.sqrt(v[..., 0])
    l10, l20 = over(c_rg, l00), over(c_br, l00)
    l11 = xp.sqrt(xp.maximum(v[..., 1] - l10 * l10, 0.0))
    l21 = over(c_gb - l20 * l10, l11)
    l22 = xp.sqrt(xp.maximum(v[..., 2] - l20 * l20 - l21 * l21, 0.0))
    return l00, l10, l11, l20, l21, l22


def colour_probes(normals, factor, xp=jnp):
    """``L n`` per pixel for standard normals (..., H, W, 3) and :func:`colour_factor`'s L."""
    l00, l10, l11, l20, l21, l22 = factor
    n0, n1, n2 = normals[..., 0], normals[..., 1], normals[..., 2]
    return xp.stack([l00 * n0, l10 * n0 + l11 * n1, l20 * n0 + l21 * n1 + l22 * n2], axis=-1)


def draw_probes(key, variance, num_probes: int, covariance=None,
                dist: ProbeDist = "normal") -> jax.Array:
    """The probes ``sure(..., key, num_probes)`` uses: shape (num_probes, *variance.shape).

    ``b_k = sqrt(var) * n_k`` with ``n_k = normal(split(key, num_probes)[k])``, so the draw of
    probe k does not depend on the chunking (``probe_batch``), for any key implementation
    (threefry, rbg). With ``covariance`` (``Frame.covariance``) ``b_k = L n_k``, L the
    per-pixel Cholesky factor of the colour covariance (:func:`colour_factor`): the same
    ``n_k``, so zero covariance gives the same probes. ``dist="rademacher"``: ``n_k``
    replaced by its signs (:func:`unit_probes`). Exposed so that tests and experiments can
    reproduce the exact probes (common random numbers).
    """
    variance = jnp.asarray(variance)
    keys = jax.random.split(key, num_probes)
    normals = _normals(keys, variance.shape, variance.dtype, check_probe_dist(dist))
    if covariance is None:
        return jnp.sqrt(variance) * normals
    return colour_probes(normals, colour_factor(variance, jnp.asarray(covariance, variance.dtype)))


# ---------------------------------------------------------------------------------- core


@functools.partial(
    jax.jit,
    static_argnames=("denoise_fn", "has_params", "num_probes", "method", "fd_scheme",
                     "probe_batch", "probe_frame", "probe_dist"),
)
def _sure_core(denoise_fn, params, frame, key, eps, *, has_params, num_probes, method,
               fd_scheme, probe_batch, probe_frame=None, probe_origin=None,
               probe_dist="normal"):
    """The traced computation; ``eps`` is a traced scalar (changing it does not recompile)."""
    x = frame.color
    var = frame.variance
    factor = None if frame.covariance is None else colour_factor(var, frame.covariance)
    sqrt_var = jnp.sqrt(var)

    def scale_normals(normals):
        return sqrt_var * normals if factor is None else colour_probes(normals, factor)

    def f(color):
        perturbed = frame.replace(color=color)
        out = denoise_fn(params, perturbed) if has_params else denoise_fn(perturbed)
        return jnp.asarray(out, dtype=x.dtype)

    _check_output(jax.eval_shape(f, x).shape, x.shape, "sure")

    # Per-probe keys, padded to whole chunks; padded probes get weight 0.
    num_chunks = -(-num_probes // probe_batch)
    padded = num_chunks * probe_batch
    keys = jax.random.split(key, num_probes)
    if padded > num_probes:
        keys = jnp.concatenate([keys, keys[: padded - num_probes]], axis=0)
    keys = keys.reshape((num_chunks, probe_batch) + keys.shape[1:])
    weights = (jnp.arange(padded) < num_probes).astype(x.dtype).reshape(num_chunks, probe_batch)

    def probes_of(chunk_keys):
        if probe_frame is None:
            return scale_normals(_normals(chunk_keys, x.shape, x.dtype, probe_dist))
        return scale_normals(window_normals(chunk_keys, probe_frame, probe_origin,
                                            x.shape[-3:-1], probe_dist).astype(x.dtype))

    if method == "jvp":

        def chunk_products(chunk_keys):
            b = probes_of(chunk_keys)
            # Only the tangent is batched, so the primal pass runs once per chunk.
            y, jb = jax.vmap(lambda t: jax.jvp(f, (x,), (t,)), out_axes=(None, 0))(b)
            return y, b * jb

    else:
        y_fixed = f(x)
        scale = jnp.asarray(eps).astype(x.dtype)

        def chunk_products(chunk_keys):
            b = probes_of(chunk_keys)
            plus = x + scale * b
            if fd_scheme == "forward":
                jb = (jax.vmap(f)(plus) - y_fixed) / scale
            else:
                jb = (jax.vmap(f)(plus) - jax.vmap(f)(x - scale * b)) / (2 * scale)
            return y_fixed, b * jb

    def step(carry, inputs):
        total, _ = carry
        chunk_keys, chunk_weights = inputs
        y, products = chunk_products(chunk_keys)
        w = chunk_weights.reshape((-1,) + (1,) * x.ndim)
        return (total + jnp.sum(w * products, axis=0), y), None

    init = (jnp.zeros_like(x), jnp.zeros_like(x))
    (total, y), _ = jax.lax.scan(step, init, (keys, weights))
    divergence_term = total / num_probes
    residual_sq = jnp.square(y - x)
    return SureResult(
        sure=residual_sq - var + 2.0 * divergence_term,
        residual_sq=residual_sq,
        divergence_term=divergence_term,
        denoised=y,
    )


def sure(
    denoise_fn: Callable,
    frame: Frame,
    key: jax.Array,
    num_probes: int = 4,
    method: Method = "jvp",
    eps: float = 1e-4,
    *,
    params: Any = _UNSET,
    fd_scheme: FdScheme = "forward",
    probe_batch: int | None = None,
    nonfinite: NonFinitePolicy = "error",
    probe_window: tuple | None = None,
    probe_dist: ProbeDist = "normal",
) -> SureResult:
    """Per-pixel Monte Carlo SURE of a JAX denoiser (see the module docstring for the math).

    Args:
      denoise_fn: ``denoise_fn(frame) -> (..., H, W, 3)``, or ``denoise_fn(params, frame)``
        when ``params`` is given. It must be a JAX-traceable function of ``frame.color``
        (``vmap``-able for ``method="fd"``). It is a static argument of the compiled core:
        pass the same function object each call (e.g. a module-level function with
        ``params=``, not a fresh lambda/partial) to avoid recompiling.
      frame: the noisy input; ``color`` is x and ``variance`` the variance of the pixel mean
        (required). Other features are passed through unchanged and are not perturbed.
        Leading batch dimensions are allowed if the denoiser accepts them.
      key: PRNG key for the probes (see :func:`draw_probes`).
      num_probes: K, probes averaged per pixel (the authors use 1 or 4).
      method: ``"jvp"`` (exact J b by forward-mode AD) or ``"fd"`` (finite differences).
      eps: finite-difference step, relative to the probe (x + eps b); ignored for ``"jvp"``.
        Traced (a new value does not recompile; a tracer is accepted, unchecked).
      params: optional pytree passed as the denoiser's first argument; traced, so new values
        do not recompile.
      fd_scheme: ``"forward"`` (authors, K + 1 evaluations) or ``"central"`` (2K + 1).
      probe_batch: probes evaluated at once (default: all K). Peak memory scales with it;
        ``probe_batch=1`` makes K = 4 on 1280 x 720 cost one jvp's memory.
      nonfinite: ``Frame.validated`` policy for concrete frames: ``"error"`` raises on NaN/inf
        or negative variance; ``"zero"`` applies the authors' repair (NaN -> 0, clip >= 0).
      probe_window: ``((H, W, C), (row, col))``: ``frame`` is the window at (row, col) of an
        (H, W, C) frame (one image), and its probes are that window of the whole frame's
        (:func:`window_normal`; ``row``/``col`` may be traced), so SURE over tiles equals
        SURE of the whole frame.
      probe_dist: ``"normal"`` or ``"rademacher"`` (the signs of the same draws: no diagonal
        term in the probe variance; see the module docstring).

    Returns:
      :class:`SureResult` with fields of shape (..., H, W, 3) in the colour's dtype.

    Raises:
      FrameError: no variance, NaN or negative variance, shape mismatch, or a denoiser output
        of the wrong shape. ConfigError: invalid options.

    Frames holding tracers (``sure`` called inside the caller's ``jit``/``vmap``) get shape
    checks only: values cannot be inspected there.
    """
    batch = _check_options(num_probes, method, eps, fd_scheme, probe_batch)
    check_probe_dist(probe_dist)
    frame = _checked_frame(frame, "sure", nonfinite)
    has_params = params is not _UNSET
    frame = jax.tree_util.tree_map(jnp.asarray, frame)
    return _sure_core(
        denoise_fn,
        params if has_params else None,
        frame,
        key,
        eps if isinstance(eps, jax.core.Tracer) else float(eps),
        has_params=has_params,
        num_probes=int(num_probes),
        method=method,
        fd_scheme=fd_scheme,
        probe_batch=batch,
        probe_frame=None if probe_window is None else tuple(int(n) for n in probe_window[0]),
        probe_origin=None if probe_window is None else jnp.asarray(probe_window[1], jnp.int32),
        probe_dist=probe_dist,
    )


# ---------------------------------------------------------------------------------- NumPy


def sure_blackbox(
    denoise_np: Callable[[Frame], Any],
    frame: Frame,
    rng: int | np.random.Generator | None = 0,
    num_probes: int = 4,
    eps: float = 1e-4,
    *,
    fd_scheme: FdScheme = "forward",
    probes: np.ndarray | None = None,
    nonfinite: NonFinitePolicy = "error",
    probe_dist: ProbeDist = "normal",
) -> SureResult:
    """Finite-difference SURE of a black-box (NumPy in, NumPy out) denoiser, e.g. OIDN.

    ``denoise_np(frame)`` receives a Frame of float32 NumPy arrays whose colour is x or a
    perturbed x and returns (..., H, W, 3). It is called K + 1 times (forward) or 2K + 1
    times (central), one frame at a time. Probes and differences are float64; perturbed
    colours are rounded to float32 for the call.

    Args:
      rng: seed or ``np.random.Generator`` for the probes b_k = sqrt(var) * N(0, 1) (or the
        signs of those normals, ``probe_dist="rademacher"``).
      probes: optional (K, ..., H, W, 3) probes to use instead of drawing them (for common
        random numbers with :func:`draw_probes` / :func:`sure`); overrides ``num_probes``.
      Other arguments as in :func:`sure`.

    Returns:
      :class:`SureResult` of float32 NumPy arrays.
    """
    if probes is not None:
        probes = np.asarray(probes, dtype=np.float64)
        num_probes = int(probes.shape[0]) if probes.ndim >= 1 else 0
    _check_options(num_probes, "fd", eps, fd_scheme, None)
    check_probe_dist(probe_dist, "sure_blackbox")
    frame = _checked_frame(frame.numpy() if isinstance(frame, Frame) else frame, "sure_blackbox",
                           nonfinite)
    x32 = np.asarray(frame.color, dtype=np.float32)
    x = x32.astype(np.float64)
    var = np.asarray(frame.variance, dtype=np.float64)
    if probes is None:
        generator = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        normals = unit_probes(generator.standard_normal((num_probes,) + x.shape), probe_dist,
                              xp=np)
        if frame.covariance is None:
            probes = np.sqrt(var) * normals
        else:
            factor = colour_factor(var, np.asarray(frame.covariance, np.float64), xp=np)
            probes = colour_probes(normals, factor, xp=np)
    elif probes.shape[1:] != x.shape:
        raise FrameError(
            f"sure_blackbox: probes have shape {probes.shape}, expected (K, *{x.shape})"
        )

    def call(color32: np.ndarray) -> np.ndarray:
        out = np.asarray(denoise_np(frame.replace(color=color32)), dtype=np.float64)
        _check_output(out.shape, x.shape, "sure_blackbox")
        return out

    y = call(x32)
    total = np.zeros_like(x)
    for b in probes:
        plus = (x + eps * b).astype(np.float32)
        if fd_scheme == "forward":
            jb = (call(plus) - y) / eps
        else:
            jb = (call(plus) - call((x - eps * b).astype(np.float32))) / (2 * eps)
        total += b * jb
    divergence_term = total / num_probes
    residual_sq = np.square(y - x)
    result = SureResult(
        sure=residual_sq - var + 2.0 * divergence_term,
        residual_sq=residual_sq,
        divergence_term=divergence_term,
        denoised=y,
    )
    return SureResult(*(np.asarray(a, dtype=np.float32) for a in result))
