"""SURE and the true squared error of a denoiser over many noisy frames around a known clean
image: the draws that :func:`jaxden.testing.check_sure_unbiased` tests, for tests of one's own.

For a clean frame (colour mu, variance of the mean var) draw ``x_i = mu + e_i``, ``e_i ~ N(0,
diag var)`` (``N(0, Sigma)`` per pixel with the frame's ``covariance``), ``i = 1 .. n``, and
let ``y_i = F(x_i)``. Over the pixels and channels P of the image (or of a region)::

    S_i = mean_P SURE(x_i)          (jaxden.sure.sure: K probes, jvp or finite differences)
    T_i = mean_P (y_i - mu)^2       (the true squared error: mu is known)
    V_i = mean_P var dy/dx          (SURE's divergence term, the probe estimate)
    R_i = mean_P (y_i - x_i)^2

SURE is unbiased for ``E (y - mu)^2`` over the noise and the probes (:mod:`jaxden.sure.stein`),
so ``E[S_i - T_i] = 0``; ``S = R - mean_P var + 2 V``, so a mutated estimator can be
recomposed from the parts.

Compiled once: a JAX denoiser runs in batches of ``batch`` draws, all the draws of a batch in
one ``vmap`` of :func:`jaxden.sure.sure` inside one jitted function, which every batch reuses
(the denoiser is traced when it compiles, not per draw or per batch). A black box (OIDN) runs
draw by draw through :func:`jaxden.sure.denoise_with_sure` by finite differences.

Seeds: the noise and the probes of batch ``b`` come from ``jax.random.fold_in(jax.random.key(
seed), b)``, so the draws are reproducible from ``seed`` and the other arguments, and the
first batches do not change when more draws are asked for.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

#: ``params`` not given: the denoiser is called as ``denoiser(frame)``.
NO_PARAMS = object()


class SureDraws(NamedTuple):
    """Per draw (and region), means over the pixels and channels, float64 NumPy arrays of shape
    (draws,), or (draws, 1 + regions) with regions (column 0: the whole image).

    - ``sure``: mean SURE (with the variance the frame gives SURE);
    - ``truth``: mean true squared error (y - mu)^2;
    - ``divergence``: mean divergence term var * dy/dx (the probe estimate);
    - ``residual``: mean (y - x)^2.
    """

    sure: np.ndarray
    truth: np.ndarray
    divergence: np.ndarray
    residual: np.ndarray


# ------------------------------------------------------------------------------ denoisers


@functools.lru_cache(maxsize=64)
def _bound_apply(definition, config):
    """One ``(params, frame) -> image`` per (definition, config): the jitted draws compile per
    function object, so the same object must come back every call."""
    return lambda params, frame: definition.apply(params, config, frame)


class _Resolved(NamedTuple):
    fn: Callable
    params: Any  # NO_PARAMS: fn(frame)
    differentiable: bool
    name: str
    denoiser: Any  # the Denoiser, or None for a plain function


def _resolve(denoiser, params) -> _Resolved:
    from jaxden.denoise.registry import Denoiser
    from jaxden.sure.denoiser import resolve_denoiser

    if isinstance(denoiser, (str, os.PathLike, Denoiser)):
        model = resolve_denoiser(denoiser)
        if params is not NO_PARAMS:
            raise ConfigError("params= is for a plain function denoiser(params, frame); a "
                              "Denoiser carries its own parameters")
        name = str(denoiser) if isinstance(denoiser, (str, os.PathLike)) else model.name
        if not model.differentiable:
            return _Resolved(model.function(), NO_PARAMS, False, name, model)
        try:
            fn = _bound_apply(model.definition, model.config)
        except TypeError:  # an unhashable config: compiles per call, still correct
            definition, config = model.definition, model.config
            fn = lambda p, frame: definition.apply(p, config, frame)
        return _Resolved(fn, model.params, True, name, model)
    if not callable(denoiser):
        raise ConfigError(f"denoiser must be a Denoiser, a registered name or checkpoint, or a "
                          f"JAX function frame -> image, got {type(denoiser).__name__}")
    name = getattr(denoiser, "__name__", None) or type(denoiser).__name__
    return _Resolved(denoiser, params, True, name, None)


def _method(method: str, differentiable: bool, name: str) -> str:
    if method not in ("auto", "jvp", "fd"):
        raise ConfigError(f"method must be 'auto', 'jvp' or 'fd', got {method!r}")
    if method == "auto":
        return "jvp" if differentiable else "fd"
    if method == "jvp" and not differentiable:
        raise ConfigError(f"denoiser '{name}' is a black box (no derivatives): use method='fd' "
                          f"(or 'auto')")
    return method


# --------------------------------------------------------------------------------- regions


def region_weights(regions, height: int, width: int) -> tuple[np.ndarray, tuple[str, ...]]:
    """``(weights (H * W, m), names)``: column 0 averages the whole image, column j > 0 the
    pixels of region j; each column sums to 1 / 3 (the three channels are summed first).

    ``regions``: None (the image only); an integer n (an n x n grid of blocks, named by their
    rows and columns); or an integer label map (H, W) with labels 0 .. R - 1 (-1: in no
    region), regions named "label k".
    """
    pixels = height * width
    columns = [np.ones(pixels)]
    names = ["image"]
    if regions is None:
        pass
    elif isinstance(regions, (int, np.integer)) and not isinstance(regions, bool):
        if not 1 <= regions <= min(height, width):
            raise ConfigError(f"regions: a grid of n x n blocks needs 1 <= n <= "
                              f"{min(height, width)} for a {height}x{width} frame, got {regions}")
        rows = np.array_split(np.arange(height), regions)
        cols = np.array_split(np.arange(width), regions)
        for r in rows:
            for c in cols:
                mask = np.zeros((height, width))
                mask[r[0]:r[-1] + 1, c[0]:c[-1] + 1] = 1.0
                columns.append(mask.reshape(-1))
                names.append(f"rows {r[0]}:{r[-1] + 1}, cols {c[0]}:{c[-1] + 1}")
    else:
        labels = np.asarray(regions)
        if labels.shape != (height, width) or not np.issubdtype(labels.dtype, np.integer):
            raise ConfigError(f"regions: expected None, a grid size or an integer label map of "
                              f"shape {(height, width)}, got {labels.dtype} {labels.shape}")
        for label in sorted(int(v) for v in np.unique(labels) if v >= 0):
            columns.append((labels == label).reshape(-1).astype(np.float64))
            names.append(f"label {label}")
    weights = np.stack(columns, axis=1)
    return (weights / (3.0 * weights.sum(axis=0))).astype(np.float32), tuple(names)


# ----------------------------------------------------------------------------------- draws


@functools.partial(jax.jit, static_argnames=("batch",))
def _noise(key, variance, covariance, *, batch: int):
    """(noise (batch, H, W, 3), probe keys (batch,)) of one batch, from ``key``."""
    from jaxden.sure.stein import colour_factor, colour_probes

    noise_key, probe_key = jax.random.split(key)
    # Drawn flat: XLA:CPU compiles multi-dimensional threefry draws much more slowly.
    normals = jax.random.normal(noise_key, (batch * variance.size,), variance.dtype).reshape(
        (batch,) + variance.shape)
    if covariance is None:
        noise = jnp.sqrt(variance) * normals
    else:
        noise = colour_probes(normals, colour_factor(variance, covariance))
    return noise, jax.random.split(probe_key, batch)


def _reduce(xp, weights, sure, truth, divergence, residual):
    """(4, m): the weighted means of the four per-pixel maps (H, W, 3)."""
    maps = xp.stack([sure, truth, divergence, residual]).sum(axis=-1).reshape(4, -1)
    if xp is np:
        return maps @ weights
    # Full float32: a GPU's default (TF32) would round SURE and the truth apart by ~1e-3.
    return jnp.matmul(maps, weights, precision=jax.lax.Precision.HIGHEST)


@functools.partial(jax.jit, static_argnames=("denoise_fn", "has_params", "batch", "num_probes",
                                             "method"))
def _sure_batch(denoise_fn, params, clean, noise_variance, weights, key, eps, *,
                has_params: bool, batch: int, num_probes: int, method: str):
    """(batch, 4, m) for one batch of draws: one compiled function for every batch."""
    from jaxden.sure import sure

    noise, probe_keys = _noise(key, noise_variance, clean.covariance, batch=batch)
    mu = clean.color

    def one(e, probe_key):
        frame = clean.replace(color=mu + e)
        options = {"num_probes": num_probes, "method": method, "eps": eps}
        if has_params:
            r = sure(denoise_fn, frame, probe_key, params=params, **options)
        else:
            r = sure(denoise_fn, frame, probe_key, **options)
        return _reduce(jnp, weights, r.sure, jnp.square(r.denoised - mu), r.divergence_term,
                       r.residual_sq)

    return jax.vmap(one)(noise, probe_keys)


def _blackbox_batch(model, clean, noise_variance, weights, key, eps, *, batch, num_probes):
    """The same as :func:`_sure_batch` for a black box (NumPy denoiser), one draw at a time
    through :func:`jaxden.sure.denoise_with_sure` (finite differences)."""
    from jaxden.sure import denoise_with_sure

    covariance = None if clean.covariance is None else jnp.asarray(clean.covariance)
    noise, probe_keys = _noise(key, jnp.asarray(noise_variance), covariance, batch=batch)
    noise = np.asarray(noise)
    mu = np.asarray(clean.color, np.float64)
    rows = []
    for e, probe_key in zip(noise, probe_keys):
        frame = clean.replace(color=(mu + e).astype(np.float32))
        r, _ = denoise_with_sure(model, frame, probe_key, num_probes=num_probes, method="fd",
                                 eps=eps, where="check_sure_unbiased")
        parts = [np.asarray(a, np.float64) for a in (r.sure, r.denoised, r.divergence_term,
                                                     r.residual_sq)]
        parts[1] = np.square(parts[1] - mu)
        rows.append(_reduce(np, weights.astype(np.float64), *parts))
    return np.stack(rows)


def _checked_clean(frame, where: str, model) -> Frame:
    from jaxden.sure.stein import require_variance

    require_variance(frame, where)
    frame = frame.numpy().validated(where=where)
    if np.ndim(frame.color) != 3:
        raise FrameError(f"{where}: expected one clean image (H, W, 3), got a colour of shape "
                         f"{np.shape(frame.color)}")
    if model is not None:
        model.check_frame(frame)
    return frame


class SureSampler:
    """Draws :class:`SureDraws` of one denoiser around one clean frame, batch by batch (one
    compiled function for every batch): :meth:`run` adds batches, :meth:`draws` returns all
    so far. Arguments as in :func:`sure_draws`; ``where`` names the caller in errors.

    Attributes: ``name`` (the denoiser's), ``method`` (resolved: jvp or fd), ``probes``,
    ``batch``, ``names`` (of the image and the regions, :func:`region_weights`), ``count``
    (draws so far).
    """

    def __init__(self, denoiser, frame: Frame, *, probes: int = 1, method: str = "auto",
                 eps: float | None = None, seed=0, params=NO_PARAMS, regions=None,
                 noise_variance=None, batch: int = 64, where: str = "sure_draws"):
        from jaxden.sure.denoiser import default_eps

        if not (isinstance(probes, (int, np.integer)) and probes >= 1):
            raise ConfigError(f"{where}: probes must be an integer >= 1, got {probes!r}")
        if not (isinstance(batch, (int, np.integer)) and batch >= 2):
            raise ConfigError(f"{where}: batch must be an integer >= 2, got {batch!r}")
        self._resolved = _resolve(denoiser, params)
        self.name = self._resolved.name
        self.method = _method(method, self._resolved.differentiable, self.name)
        if eps is None:
            eps = default_eps(self.method, self._resolved.differentiable) or 1e-4
        self._eps = float(eps)
        self._clean = _checked_clean(frame, where, self._resolved.denoiser)
        height, width = np.shape(self._clean.color)[:2]
        self._weights, self.names = region_weights(regions, height, width)
        variance = self._clean.variance if noise_variance is None else noise_variance
        self._noise_variance = np.asarray(variance, np.float32)
        if self._noise_variance.shape != np.shape(self._clean.color):
            raise FrameError(f"{where}: noise_variance has shape {self._noise_variance.shape}, "
                             f"expected the colour's {np.shape(self._clean.color)}")
        self._key = jax.random.key(seed) if isinstance(seed, (int, np.integer)) else seed
        self._device_clean = jax.tree_util.tree_map(jnp.asarray, self._clean)
        self.probes = int(probes)
        self.batch = int(batch)
        self._rows: list[np.ndarray] = []

    @property
    def count(self) -> int:
        return self.batch * len(self._rows)

    def run(self, batches: int) -> None:
        """Draw ``batches`` more batches."""
        r = self._resolved
        for _ in range(batches):
            key = jax.random.fold_in(self._key, len(self._rows))
            if r.differentiable:
                has_params = r.params is not NO_PARAMS
                rows = _sure_batch(
                    r.fn, r.params if has_params else None, self._device_clean,
                    jnp.asarray(self._noise_variance), jnp.asarray(self._weights), key,
                    jnp.float32(self._eps), has_params=has_params, batch=self.batch,
                    num_probes=self.probes, method=self.method)
            else:
                rows = _blackbox_batch(r.denoiser, self._clean, self._noise_variance,
                                       self._weights, key, self._eps, batch=self.batch,
                                       num_probes=self.probes)
            self._rows.append(np.asarray(rows, np.float64))

    def draws(self, squeeze: bool = False) -> SureDraws:
        """Every draw so far: columns (image, regions...), or the image's alone with
        ``squeeze``."""
        if not self._rows:
            raise ConfigError("SureSampler.draws: no draws yet (call run first)")
        rows = np.concatenate(self._rows)  # (draws, 4, m)
        return SureDraws(*(rows[:, i, 0] if squeeze else rows[:, i, :] for i in range(4)))


def sure_draws(denoiser, frame: Frame, *, draws: int, probes: int = 1, method: str = "auto",
               eps: float | None = None, seed=0, params=NO_PARAMS, regions=None,
               noise_variance=None, batch: int = 64) -> SureDraws:
    """SURE and the true error of ``denoiser`` on ``draws`` noisy frames around the clean
    ``frame`` (module docstring): the per-draw statistics
    :func:`jaxden.testing.check_sure_unbiased` tests, for tests of one's own (e.g. a mutated
    estimator recomposed from the parts).

    Args:
      denoiser: a :class:`jaxden.denoise.Denoiser`, a name or checkpoint for
        :func:`jaxden.denoise.load_denoiser`, or a JAX function ``frame -> (H, W, 3)``
        (``denoiser(params, frame)`` with ``params``, which are traced: new values do not
        recompile). Black boxes (OIDN) run one draw at a time by finite differences.
      frame: the clean frame: ``color`` is mu (H, W, 3), ``variance`` the variance of the
        noise and the one SURE is told; its other fields (albedo, ...) pass to the denoiser.
      draws: rounded up to whole batches of ``batch`` (``batch`` is lowered to ``draws``
        when fewer are asked for).
      probes, method (``auto``: jvp for JAX denoisers, fd for black boxes), eps (None: the
        measured default, :func:`jaxden.sure.denoiser.default_eps`): SURE's options.
      seed: an integer or a JAX PRNG key (module docstring).
      regions: see :func:`region_weights`.
      noise_variance: (H, W, 3) variance the noise is drawn with when it differs from the
        one SURE is told (``frame.variance``), to test a mis-told variance.

    Returns:
      :class:`SureDraws`, one row per draw.
    """
    if not (isinstance(draws, (int, np.integer)) and draws >= 2):
        raise ConfigError(f"sure_draws: draws must be an integer >= 2, got {draws!r}")
    batch = min(int(batch), int(draws))
    sampler = SureSampler(denoiser, frame, probes=probes, method=method, eps=eps, seed=seed,
                          params=params, regions=regions, noise_variance=noise_variance,
                          batch=batch)
    sampler.run(-(-int(draws) // batch))
    return sampler.draws(squeeze=regions is None)
