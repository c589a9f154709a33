"""SURE of a denoiser: denoise a frame and estimate the per-pixel SURE of the result, by jvp for
JAX denoisers and by finite differences for black boxes (:func:`denoise_with_sure`).

An unset method (``auto``) is chosen by the denoiser's kind (:func:`resolve_method`), an
unset finite-difference step by :func:`jaxden.sure.settings.default_eps` (1e-2 for black boxes,
1e-3 for JAX denoisers; the authors' 1e-4 is dominated by float32 round-off; measured:
docs/history.md, "Defaults of the code").
"""

from __future__ import annotations

import functools

from jaxden.errors import ConfigError
from jaxden.frame import Frame
from jaxden.sure.settings import (  # FD_EPS_*, default_eps: jaxden.sure.denoiser's API too
    FD_EPS_BLACKBOX,  # noqa: F401
    FD_EPS_JAX,  # noqa: F401
    SureSettings,
    default_eps,
    resolve_settings,
)


# ------------------------------------------------------------------------------- denoisers
def resolve_denoiser(denoiser):
    """A :class:`jaxden.denoise.Denoiser` from a Denoiser, a spec for ``load_denoiser`` or a
    plain JAX function ``frame -> image`` (:func:`jaxden.denoise.registry.as_denoiser`)."""
    from jaxden.denoise.registry import as_denoiser

    return as_denoiser(denoiser)


def resolve_method(method: str, denoiser) -> str:
    """The method ``method`` (a valid :class:`SureSettings` method) means for ``denoiser``:
    ``auto`` is ``jvp`` for JAX denoisers and ``fd`` for black boxes; ``jvp`` on a black box
    is a ConfigError."""
    if method == "auto":
        return "jvp" if denoiser.differentiable else "fd"
    if method == "jvp" and not denoiser.differentiable:
        raise ConfigError(
            f"denoiser '{denoiser.name}' is a black box (no derivatives): SURE needs method 'fd' "
            f"(or 'auto')"
        )
    return method


def for_denoiser(settings: SureSettings, denoiser) -> SureSettings:
    """Resolved ``settings`` with the method and step they mean for ``denoiser``
    (:func:`resolve_method`, :func:`jaxden.sure.settings.default_eps`; the step stays unset
    for ``jvp``, which uses none)."""
    method = resolve_method(settings.method, denoiser)
    eps = settings.eps if settings.eps is not None else default_eps(method,
                                                                     denoiser.differentiable)
    return settings.replace(method=method, eps=None if method == "jvp" else eps)


@functools.lru_cache(maxsize=64)
def _apply_fn(definition, config):
    """A stable ``(params, frame) -> image`` per (definition, config): :func:`jaxden.sure.sure`
    compiles per function object, so the same object must come back every call."""
    return lambda params, frame: definition.apply(params, config, frame)


def denoise_with_sure(denoiser, frame: Frame, key, *, sure: SureSettings | None = None,
                      nonfinite: str = "error", where: str = "sure", **options):
    """Denoise ``frame`` and estimate the per-pixel SURE of the result.

    ``sure``: the :class:`~jaxden.sure.settings.SureSettings` (None: the defaults); the older
    keywords ``options`` (``num_probes=``, ``method=``, ``eps=``, ``fd_scheme=``,
    ``probe_batch=``, ``probe_dist=``, ``covariance=``) override it where given. ``method``
    ``auto`` = ``jvp`` for JAX denoisers (exact J b, :func:`jaxden.sure.sure`) and ``fd`` for
    black boxes (:func:`jaxden.sure.stein.sure_blackbox_streamed`, or
    :func:`jaxden.sure.sure_blackbox` for the central scheme, with the probes of
    :func:`jaxden.sure.draw_probes`, so both paths use the same probes for the same key).
    ``probe_batch``: probes per jvp pass (memory; JAX only). ``key`` is the probes' key
    (``sure.seed`` is not used).

    Returns ``(SureResult, frame)``: fields (..., H, W, 3) (JAX arrays for JAX denoisers, NumPy
    for black boxes) and the validated frame: as given when it holds JAX arrays that pass
    every check (a frame on the GPU is not copied to the host), else a NumPy copy (possibly
    repaired, ``nonfinite='zero'``); without its covariance when ``sure.covariance`` is off.
    Raises FrameError when the frame has no variance (naming SURE and the variance), bad
    values, or lacks a feature the denoiser needs.
    """
    import numpy as np

    from jaxden.sure.probes import draw_probes_compiled
    from jaxden.sure.stein import (
        require_variance,
        sure_blackbox,
        sure_blackbox_streamed,
        sure_input,
    )
    from jaxden.sure.stein import sure as stein_sure

    settings = resolve_settings(sure, **options)
    denoiser = resolve_denoiser(denoiser)
    require_variance(frame, where, held_in="EXR channels variance.R/G/B")
    if nonfinite not in ("error", "zero"):
        raise ConfigError(f"{where}: nonfinite must be 'error' or 'zero', got {nonfinite!r}")
    frame = sure_input(frame, settings)  # an unused covariance is not even checked
    if not frame.is_valid_on_device():  # a frame on the device stays there (no host copy)
        frame = frame.numpy().validated(where=where, nonfinite=nonfinite)
    denoiser.check_frame(frame)
    settings = for_denoiser(settings, denoiser)
    if denoiser.differentiable:
        result = stein_sure(_apply_fn(denoiser.definition, denoiser.config), frame, key,
                            settings=settings, params=denoiser.params)
    elif settings.fd_scheme == "forward":
        result = sure_blackbox_streamed(denoiser.function(), frame, key, settings)
    else:
        probes = np.asarray(draw_probes_compiled(key, frame.variance, settings.probes,
                                                 frame.covariance, settings.probe_dist),
                            np.float64)
        result = sure_blackbox(denoiser.function(), frame, probes=probes, settings=settings)
    return result, frame
