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
Eq. 1 (d = 3 H W) with diagonal Sigma. The paper writes the last term as ``2 sigma^2 f'(x)``;
here it is ``divergence_term = var_i * J_ii`` with ``J = dF/dx`` the Jacobian w.r.t. the colour
only.

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
high spp (measured: experiments/results/sure/sure-probe-noise.md). The signs are those of
the normal draws (``r = +1`` where ``n >= 0``), so tiles, chunks and black boxes see the
same probes for the same key. With a colour covariance the probes are ``L r`` (unbiased,
``E[L r r^T L^T] = Sigma``), and the diagonal term shrinks without vanishing.

Correlated colour channels (``Frame.covariance``)
------------------------------------------------
R, G and B of one Monte Carlo sample come from one path, so the noise of a pixel mean is
correlated across channels (strongly on jaxden's test scenes: docs/history.md, "Defaults of
the code"). With ``e ~ N(0, Sigma)`` per pixel, Sigma the 3 x 3 covariance of the mean,
Stein's lemma gives ``E[(y - x) . e] = tr(Sigma E[J]) - tr(Sigma)``, and the per-channel
split of the same derivation is ``E[(y_i - mu_i)^2] = E[(y_i - x_i)^2 - var_i + 2 (J
Sigma)_ii]``. Probes ``b = L n`` with ``L L^T = Sigma`` (:func:`colour_factor`) give
``E_b[b_i (J b)_i] = (J Sigma)_ii``, so the estimator above is unchanged but for the probes.
The diagonal form misses ``sum_{j != i} J_ij Sigma_ji``: nothing for a denoiser that filters
each channel on its own, but a network that mixes channels (a U-Net) is underestimated where
the cross-channel derivatives are positive (measured: docs/results.md, "SURE by
``jax.jvp``"). A frame with ``covariance`` uses it; one without keeps the diagonal.

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

Round-off in float32 makes the forward difference's error against the exact jvp smallest at
a step near 1e-3, not at the authors' 1e-4 (measured: docs/history.md, "Defaults of the
code"). Use ``"jvp"`` where the denoiser is differentiable. (Using the realised perturbation
fl(x + eps b) - x as the probe was tried: no measurable gain, since rounding of the outputs
dominates; not kept.)

``sure_buffers`` replaces the probe divergence by a covariance estimate from K independent
sub-buffers of the render (no Gaussian assumption, no derivative; see the derivation above
that function), for Monte Carlo noise that Stein's identity gets wrong.

``sure_blackbox`` does the ``"fd"`` method in NumPy (float64 arithmetic, float32 denoiser
inputs) for non-JAX denoisers such as OIDN through ``pyoidn``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame, NonFinitePolicy
from jaxden.sure.probes import (  # draw_probes, window_normal: jaxden.sure.stein's API too
    colour_factor,
    colour_probes,
    draw_probe,
    draw_probes,  # noqa: F401
    probe_normals,
    unit_probes,
    window_normal,  # noqa: F401
    window_normals,
)
from jaxden.sure.settings import (  # PROBE_DISTS, ProbeDist: jaxden.sure.stein's API too
    PROBE_DISTS,  # noqa: F401
    FdScheme,
    Method,
    ProbeDist,
    SureSettings,
    default_eps,
    resolve_settings,
)

_UNSET = object()

#: The authors' finite-difference step: what an unset ``eps`` is for :func:`sure` and
#: :func:`sure_blackbox` called directly (a denoiser's SURE, :func:`jaxden.sure.denoise_with_sure`,
#: takes the measured :func:`jaxden.sure.settings.default_eps`).
AUTHORS_EPS = 1e-4


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


def sure_input(frame: Frame, settings: SureSettings) -> Frame:
    """The frame SURE reads under ``settings``: without its colour covariance when
    ``settings.covariance`` is off (the per-channel form), else as given."""
    if settings.covariance is False and getattr(frame, "covariance", None) is not None:
        return frame.replace(covariance=None)
    return frame


def checked_frame(frame, where: str, nonfinite: NonFinitePolicy) -> Frame:
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


def check_output(out_shape, color_shape, where: str) -> None:
    """FrameError unless a denoiser's output shape is the colour's."""
    if tuple(out_shape) != tuple(color_shape):
        raise FrameError(
            f"{where}: the denoiser returned shape {tuple(out_shape)}, expected the colour's "
            f"shape {tuple(color_shape)}"
        )


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

    check_output(jax.eval_shape(f, x).shape, x.shape, "sure")

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
            return scale_normals(probe_normals(chunk_keys, x.shape, x.dtype, probe_dist))
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
    num_probes: int | None = None,
    method: Method | None = None,
    eps: float | None = None,
    *,
    settings: SureSettings | None = None,
    params: Any = _UNSET,
    fd_scheme: FdScheme | None = None,
    probe_batch: int | None = None,
    nonfinite: NonFinitePolicy = "error",
    probe_window: tuple | None = None,
    probe_dist: ProbeDist | None = None,
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
      settings: the :class:`~jaxden.sure.settings.SureSettings` (None: the defaults). The
        keywords below, where given (not None), override it field by field (the older form,
        ``sure(fn, frame, key, 4, "jvp")``, still works):
      num_probes: K, probes averaged per pixel (default 4; the authors use 1 or 4).
      method: ``"jvp"`` (exact J b by forward-mode AD; also what ``"auto"``, the default,
        means here) or ``"fd"`` (finite differences).
      eps: finite-difference step, relative to the probe (x + eps b); ignored for ``"jvp"``;
        unset: 1e-4 (the authors'). May be a traced scalar (a new value does not recompile;
        a tracer is accepted, unchecked).
      fd_scheme: ``"forward"`` (authors, K + 1 evaluations) or ``"central"`` (2K + 1).
      probe_batch: probes evaluated at once (default: all K). Peak memory scales with it;
        ``probe_batch=1`` makes K = 4 on 1280 x 720 cost one jvp's memory.
      probe_dist: ``"normal"`` or ``"rademacher"`` (the signs of the same draws: no diagonal
        term in the probe variance; see the module docstring).
      params: optional pytree passed as the denoiser's first argument; traced, so new values
        do not recompile.
      nonfinite: ``Frame.validated`` policy for concrete frames: ``"error"`` raises on NaN/inf
        or negative variance; ``"zero"`` applies the authors' repair (NaN -> 0, clip >= 0).
      probe_window: ``((H, W, C), (row, col))``: ``frame`` is the window at (row, col) of an
        (H, W, C) frame (one image), and its probes are that window of the whole frame's
        (:func:`window_normal`; ``row``/``col`` may be traced), so SURE over tiles equals
        SURE of the whole frame.

    Returns:
      :class:`SureResult` with fields of shape (..., H, W, 3) in the colour's dtype.

    Raises:
      FrameError: no variance, NaN or negative variance, shape mismatch, or a denoiser output
        of the wrong shape. ConfigError: invalid options.

    Frames holding tracers (``sure`` called inside the caller's ``jit``/``vmap``) get shape
    checks only: values cannot be inspected there. ``settings.seed`` is not used: ``key`` is
    the probes' key.
    """
    traced_eps = eps if isinstance(eps, jax.core.Tracer) else None
    if traced_eps is not None and np.shape(traced_eps) != ():
        raise ConfigError(f"sure: eps must be a scalar, got shape {np.shape(traced_eps)}")
    settings = resolve_settings(settings, num_probes=num_probes, method=method,
                                eps=None if traced_eps is not None else eps,
                                fd_scheme=fd_scheme, probe_batch=probe_batch,
                                probe_dist=probe_dist)
    if traced_eps is not None:
        eps = traced_eps
    else:
        eps = AUTHORS_EPS if settings.eps is None else settings.eps
    frame = checked_frame(sure_input(frame, settings), "sure", nonfinite)
    has_params = params is not _UNSET
    frame = jax.tree_util.tree_map(jnp.asarray, frame)
    return _sure_core(
        denoise_fn,
        params if has_params else None,
        frame,
        key,
        eps,
        has_params=has_params,
        num_probes=settings.probes,
        method="jvp" if settings.method == "auto" else settings.method,
        fd_scheme=settings.fd_scheme,
        probe_batch=min(settings.probe_batch or settings.probes, settings.probes),
        probe_frame=None if probe_window is None else tuple(int(n) for n in probe_window[0]),
        probe_origin=None if probe_window is None else jnp.asarray(probe_window[1], jnp.int32),
        probe_dist=settings.probe_dist,
    )


# ---------------------------------------------------------------------------------- NumPy


def sure_blackbox(
    denoise_np: Callable[[Frame], Any],
    frame: Frame,
    rng: int | np.random.Generator | None = 0,
    num_probes: int | None = None,
    eps: float | None = None,
    *,
    settings: SureSettings | None = None,
    fd_scheme: FdScheme | None = None,
    probes: np.ndarray | None = None,
    nonfinite: NonFinitePolicy = "error",
    probe_dist: ProbeDist | None = None,
) -> SureResult:
    """Finite-difference SURE of a black-box (NumPy in, NumPy out) denoiser, e.g. OIDN.

    ``denoise_np(frame)`` receives a Frame of float32 NumPy arrays whose colour is x or a
    perturbed x and returns (..., H, W, 3). It is called K + 1 times (forward) or 2K + 1
    times (central), one frame at a time. Probes and differences are float64; perturbed
    colours are rounded to float32 for the call.

    Args:
      rng: seed or ``np.random.Generator`` for the probes b_k = sqrt(var) * N(0, 1) (or the
        signs of those normals, ``probe_dist="rademacher"``); ``settings.seed`` is not used.
      probes: optional (K, ..., H, W, 3) probes to use instead of drawing them (for common
        random numbers with :func:`draw_probes` / :func:`sure`); overrides ``num_probes``.
      settings and the other keywords as in :func:`sure` (``method`` is ``fd``: ``auto`` means
        it here, ``jvp`` is refused).

    Returns:
      :class:`SureResult` of float32 NumPy arrays.
    """
    if probes is not None:
        probes = np.asarray(probes, dtype=np.float64)
        num_probes = int(probes.shape[0]) if probes.ndim >= 1 else 0
    settings = resolve_settings(settings, num_probes=num_probes, eps=eps, fd_scheme=fd_scheme,
                                probe_dist=probe_dist)
    _black_box_method(settings, "sure_blackbox")
    num_probes, fd_scheme = settings.probes, settings.fd_scheme
    eps = AUTHORS_EPS if settings.eps is None else settings.eps
    frame = checked_frame(sure_input(frame.numpy() if isinstance(frame, Frame) else frame,
                                     settings), "sure_blackbox", nonfinite)
    x32 = np.asarray(frame.color, dtype=np.float32)
    x = x32.astype(np.float64)
    var = np.asarray(frame.variance, dtype=np.float64)
    if probes is None:
        generator = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        normals = unit_probes(generator.standard_normal((num_probes,) + x.shape),
                              settings.probe_dist, xp=np)
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
        check_output(out.shape, x.shape, "sure_blackbox")
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


def _black_box_method(settings: SureSettings, where: str) -> None:
    if settings.method == "jvp":
        raise ConfigError(f"{where}: a black box has no derivatives: SURE needs method 'fd' "
                          f"(or 'auto')")


#: Rows per band of the float64 arithmetic in :func:`sure_blackbox_streamed` (memory only).
_BAND_ROWS = 256


def sure_blackbox_streamed(denoise_np, frame: Frame, key, settings: SureSettings | None = None,
                           **options) -> SureResult:
    """Forward-difference SURE of a black box, one probe at a time: the values of
    :func:`sure_blackbox` with the probes of :func:`draw_probes` for ``key`` (the same
    float64 arithmetic, per pixel), in a fraction of its memory. That form holds K probes and
    every intermediate in float64 (about 60 + 24 K bytes a pixel); this one holds one float32
    probe, the denoiser's output and a float64 sum (about 50 bytes a pixel beyond the frame),
    and does the float64 arithmetic in bands of rows. ``frame``: validated, one image or a
    batch (bands run over rows). ``settings`` (and the older keywords ``options``) as in
    :func:`sure`; the scheme is ``forward``; an unset ``eps`` is the measured black-box step
    (:func:`jaxden.sure.settings.default_eps`)."""
    settings = resolve_settings(settings, **options)
    _black_box_method(settings, "sure_blackbox")
    if settings.fd_scheme != "forward":
        raise ConfigError("sure_blackbox_streamed: only the forward scheme runs one probe at a "
                          "time (sure_blackbox takes central)")
    num_probes = settings.probes
    eps = default_eps("fd", False) if settings.eps is None else settings.eps
    frame = sure_input(frame, settings)
    x32 = np.asarray(frame.color, np.float32)
    var32 = np.asarray(frame.variance, np.float32)
    covariance = None if frame.covariance is None else np.asarray(frame.covariance, np.float32)
    rows = x32.shape[-3]
    bands = [(..., slice(r, min(r + _BAND_ROWS, rows)), slice(None), slice(None))
             for r in range(0, rows, _BAND_ROWS)]

    def call(color32: np.ndarray) -> np.ndarray:
        out = np.asarray(denoise_np(frame.replace(color=color32)), np.float32)
        check_output(out.shape, x32.shape, "sure_blackbox")
        return out

    y32 = call(x32)
    total = np.zeros(x32.shape, np.float64)
    plus = np.empty_like(x32)
    for probe_key in jax.random.split(key, num_probes):
        b32 = np.asarray(draw_probe(probe_key, var32, covariance, settings.probe_dist),
                         np.float32)
        for band in bands:
            plus[band] = (x32[band].astype(np.float64) + eps * b32[band].astype(np.float64))
        out32 = call(plus)
        for band in bands:
            jb = (out32[band].astype(np.float64) - y32[band]) / eps
            total[band] += b32[band] * jb
        del b32, out32
    del plus
    divergence = np.empty_like(x32)
    residual_sq = np.empty_like(x32)
    for band in bands:
        divergence[band] = total[band] / num_probes
        residual_sq[band] = np.square(y32[band].astype(np.float64) - x32[band])
    sure_map = total.astype(np.float32)  # reused as the float32 SURE (the float64 sum goes)
    for band in bands:
        sure_map[band] = (np.square(y32[band].astype(np.float64) - x32[band]) - var32[band]
                          + 2.0 * (total[band] / num_probes))
    del total
    return SureResult(sure=sure_map, residual_sq=residual_sq, divergence_term=divergence,
                      denoised=y32)
