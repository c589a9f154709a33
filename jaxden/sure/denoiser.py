"""SURE of a denoiser: denoise a frame and estimate the per-pixel SURE of the result, by jvp for
JAX denoisers and by finite differences for black boxes.

Finite-difference step (``eps=None`` picks :func:`default_eps`): the authors use 1e-4, which
in float32 is dominated by round-off. Measured on OIDN (pyoidn 2.5, 'high', Cornell box 64 x 64,
4 common probes, relative L2 error of the divergence term against the mean of central
differences at 3e-3 and 1e-2): forward eps = 1e-4: 5 % (4 spp), 12 % (64 spp), 30 % (1024 spp);
1e-3: 2 %, 2 %, 5 %; 1e-2: 1.9 %, 0.9 %, 1.1 %; 3e-2: 4 %, 2 %, 1 %. So black boxes get
1e-2 (the error floor is OIDN's own float32 output). JAX denoisers use jvp (exact) unless
``method='fd'``, for which 1e-3 (the float32 optimum measured in tests/test_sure_properties.py).
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError
from jaxden.frame import Frame

#: Finite-difference steps chosen from measurements (module docstring).
FD_EPS_BLACKBOX = 1e-2
FD_EPS_JAX = 1e-3


# ------------------------------------------------------------------------------- denoisers
def resolve_denoiser(denoiser):
    """A :class:`jaxden.denoise.Denoiser` from a Denoiser or a spec for ``load_denoiser``."""
    from jaxden.denoise.registry import Denoiser, load_denoiser

    if isinstance(denoiser, Denoiser):
        return denoiser
    if isinstance(denoiser, (str, os.PathLike)):
        return load_denoiser(denoiser)
    raise ConfigError(
        f"denoiser must be a name, a checkpoint path or a Denoiser, got {type(denoiser).__name__}"
    )


def default_eps(method: str, differentiable: bool) -> float | None:
    """The finite-difference step used when none is given (see the module docstring):
    None for ``jvp``; 1e-2 for black boxes, 1e-3 for JAX denoisers with ``fd``."""
    if method == "jvp":
        return None
    return FD_EPS_JAX if differentiable else FD_EPS_BLACKBOX


def resolve_method(method: str, denoiser) -> str:
    if method not in ("auto", "jvp", "fd"):
        raise ConfigError(f"SURE method must be 'auto', 'jvp' or 'fd', got {method!r}")
    if method == "auto":
        return "jvp" if denoiser.differentiable else "fd"
    if method == "jvp" and not denoiser.differentiable:
        raise ConfigError(
            f"denoiser '{denoiser.name}' is a black box (no derivatives): SURE needs method 'fd' "
            f"(or 'auto')"
        )
    return method


@functools.partial(jax.jit, static_argnames=("num_probes", "dist"))
def _draw_probes(key, variance, num_probes: int, covariance=None, dist="normal"):
    """:func:`jaxden.sure.draw_probes` compiled once per shape (called eagerly it retraces
    its ``lax.map`` on every call, ~0.7 s each on the project machine); the same values."""
    from jaxden.sure.stein import draw_probes

    return draw_probes(key, variance, num_probes, covariance, dist)


@functools.lru_cache(maxsize=64)
def _apply_fn(definition, config):
    """A stable ``(params, frame) -> image`` per (definition, config): :func:`jaxden.sure.sure`
    compiles per function object, so the same object must come back every call."""
    return lambda params, frame: definition.apply(params, config, frame)


def denoise_with_sure(
    denoiser,
    frame: Frame,
    key,
    *,
    num_probes: int = 4,
    method: str = "auto",
    eps: float | None = None,
    fd_scheme: str = "forward",
    probe_batch: int | None = None,
    nonfinite: str = "error",
    where: str = "sure",
    probe_dist: str = "normal",
):
    """Denoise ``frame`` and estimate the per-pixel SURE of the result.

    ``method``: ``auto`` = ``jvp`` for JAX denoisers (exact J b, :func:`jaxden.sure.sure`) and
    ``fd`` for black boxes (:func:`jaxden.sure.sure_blackbox` with the probes of
    :func:`jaxden.sure.draw_probes`, so both paths use the same probes for the same key).
    ``eps`` None: :func:`default_eps`. ``probe_batch``: probes per jvp pass (memory; JAX only).
    ``probe_dist``: ``normal`` or ``rademacher`` (:func:`jaxden.sure.stein.unit_probes`).

    Returns ``(SureResult, frame)``: fields (..., H, W, 3) (JAX arrays for JAX denoisers, NumPy
    for black boxes) and the validated frame: as given when it holds JAX arrays that pass
    every check (a frame on the GPU is not copied to the host), else a NumPy copy (possibly
    repaired, ``nonfinite='zero'``).
    Raises FrameError when the frame has no variance (naming SURE and the variance), bad
    values, or lacks a feature the denoiser needs.
    """
    from jaxden.sure.stein import check_probe_dist, require_variance, sure, sure_blackbox

    check_probe_dist(probe_dist, where)
    denoiser = resolve_denoiser(denoiser)
    require_variance(frame, where, held_in="EXR channels variance.R/G/B")
    if nonfinite not in ("error", "zero"):
        raise ConfigError(f"{where}: nonfinite must be 'error' or 'zero', got {nonfinite!r}")
    if not frame.is_valid_on_device():  # a frame on the device stays there (no host copy)
        frame = frame.numpy().validated(where=where, nonfinite=nonfinite)
    denoiser.check_frame(frame)
    method = resolve_method(method, denoiser)
    if eps is None:
        eps = default_eps(method, denoiser.differentiable) or 1e-4  # ignored by jvp
    if denoiser.differentiable:
        result = sure(
            _apply_fn(denoiser.definition, denoiser.config), frame, key, num_probes, method, eps,
            params=denoiser.params, fd_scheme=fd_scheme, probe_batch=probe_batch,
            probe_dist=probe_dist,
        )
    elif fd_scheme == "forward":
        result = sure_blackbox_streamed(denoiser.function(), frame, key, num_probes, eps,
                                        probe_dist)
    else:
        probes = np.asarray(_draw_probes(key, frame.variance, num_probes, frame.covariance,
                                         probe_dist), np.float64)
        result = sure_blackbox(
            denoiser.function(), frame, probes=probes, eps=eps, fd_scheme=fd_scheme
        )
    return result, frame


@functools.partial(jax.jit, static_argnames=("dist",))
def _draw_probe(key, variance, covariance=None, dist="normal"):
    """Probe k of :func:`_draw_probes` alone (``key`` = ``split(key, K)[k]``): the same values."""
    from jaxden.sure.stein import _probe_normal, colour_factor, colour_probes, unit_probes

    normals = unit_probes(_probe_normal(key, variance.shape, variance.dtype), dist)
    if covariance is None:
        return jnp.sqrt(variance) * normals
    return colour_probes(normals, colour_factor(variance, jnp.asarray(covariance,
                                                                      variance.dtype)))


#: Rows per band of the float64 arithmetic in :func:`sure_blackbox_streamed` (memory only).
_BAND_ROWS = 256


def sure_blackbox_streamed(denoise_np, frame: Frame, key, num_probes: int, eps: float,
                           probe_dist: str = "normal"):
    """Forward-difference SURE of a black box, one probe at a time: the values of
    :func:`jaxden.sure.sure_blackbox` with the probes of :func:`_draw_probes` (the same
    float64 arithmetic, per pixel), in a fraction of its memory. That form holds K probes and
    every intermediate in float64 (about 60 + 24 K bytes a pixel: 3.2 GB of probes alone for
    K = 4 at 7680 x 4320); this one holds one float32 probe, the denoiser's output and a
    float64 sum (about 50 bytes a pixel beyond the frame), and does the float64 arithmetic in
    bands of rows. ``frame``: validated, one image or a batch (bands run over rows)."""
    from jaxden.sure.stein import SureResult, _check_options, _check_output

    _check_options(num_probes, "fd", eps, "forward", None)
    x32 = np.asarray(frame.color, np.float32)
    var32 = np.asarray(frame.variance, np.float32)
    covariance = None if frame.covariance is None else np.asarray(frame.covariance, np.float32)
    rows = x32.shape[-3]
    bands = [(..., slice(r, min(r + _BAND_ROWS, rows)), slice(None), slice(None))
             for r in range(0, rows, _BAND_ROWS)]

    def call(color32: np.ndarray) -> np.ndarray:
        out = np.asarray(denoise_np(frame.replace(color=color32)), np.float32)
        _check_output(out.shape, x32.shape, "sure_blackbox")
        return out

    y32 = call(x32)
    total = np.zeros(x32.shape, np.float64)
    plus = np.empty_like(x32)
    for probe_key in jax.random.split(key, num_probes):
        b32 = np.asarray(_draw_probe(probe_key, var32, covariance, probe_dist), np.float32)
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
