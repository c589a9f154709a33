"""progressive_denoise: denoise a frame, take SURE, mix and scale by the t-statistic; the shipped
mixers, their denoisers' twins, and the warning when a mixer mixes another denoiser.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError, JaxdenError
from jaxden.progressive.checks import check_spp
from jaxden.progressive.guard import guard_sample_count
from jaxden.progressive.heads import mix_unchecked
from jaxden.progressive.mixer_checkpoints import load_mixer
from jaxden.progressive.mixer_config import MixerConfig
from jaxden.progressive.network import inference_alpha
from jaxden.progressive.tstat import TStatConfig, consistent_alpha
from jaxden.sure.denoiser import resolve_denoiser
from jaxden.sure.settings import SureSettings, resolve_settings

# ------------------------------------------------------------------------------ inference

_FROM_CONFIG = object()


def progressive_denoise(
    frame,
    denoiser,
    mixer_params,
    mixer_config: MixerConfig,
    key,
    *,
    sure: SureSettings | None = None,
    tstat=_FROM_CONFIG,
    nonfinite: str = "error",
    swap_average: bool | None = None,
    **options,
):
    """The whole progressive-denoising pipeline on one frame (paper Fig. 6).

    y = D(x); SURE of y (jvp for JAX denoisers, finite differences for black boxes such as
    OIDN; :func:`jaxden.sure.denoise_with_sure`); alpha = mixer; alpha' = t-statistic
    scaling, then the error guard (:mod:`jaxden.progressive.guard`, ``tstat.guard``);
    z' = x + alpha' (y - x).

    Args:
      frame: :class:`jaxden.frame.Frame` (H, W, 3) (leading batch dims if the denoiser takes
        them) with colour and ``variance`` (the variance of the pixel mean; required) plus
        the features the denoiser uses.
      denoiser: a :class:`jaxden.denoise.Denoiser` or a spec for
        :func:`jaxden.denoise.load_denoiser` (``"oidn"``, a checkpoint folder, ...). One
        other than the mixer's ``denoiser`` (and not its twin, :data:`TWINS`) is mixed with
        a :class:`MixerDenoiserWarning`, once per process and pair.
      mixer_params, mixer_config: from :func:`load_mixer` (or :func:`mixer_init`).
      key: PRNG key of the SURE probes.
      sure: :class:`~jaxden.sure.settings.SureSettings`; its unset fields are the mixer's
        (``mixer_config.sure``, the SURE it was trained with). The older keywords
        ``options`` (``num_probes=``, ``method=``, ``eps=``, ``probe_batch=``,
        ``probe_dist=``; None: not given) override it field by field.
      tstat: :class:`TStatConfig`; default the mixer config's; None skips the scaling
        (the paper's "w/o t-test" ablation).
      nonfinite: ``"error"`` or ``"zero"`` (the authors' repair of NaN / negative variance).
      swap_average: average alpha with 1 - alpha of the swapped inputs (see
        :class:`MixerConfig`); None: the mixer config's ``swap_average``.

    Returns:
      ``(z_prime, alpha_prime, extras)``: output colour and the scaled alpha, (..., H, W, 3)
      float32 JAX arrays, and a dict with ``denoised``, ``sure``, ``divergence`` (var dy/dx),
      ``alpha`` (before scaling) and ``mixed`` (x + alpha (y - x), before scaling).

    Raises:
      FrameError: no variance (SURE needs it), negative or non-finite values, missing
        denoiser features. ConfigError: bad options.
    """
    from jaxden.sure.denoiser import denoise_with_sure

    settings = resolve_settings(sure, mixer_config.sure, **options)
    if tstat is _FROM_CONFIG:
        tstat = mixer_config.tstat
    if tstat is not None and not isinstance(tstat, TStatConfig):
        raise ConfigError(
            f"progressive_denoise: tstat must be a TStatConfig or None, got {tstat!r}"
        )
    spec, denoiser = denoiser, resolve_denoiser(denoiser)
    warn_if_other_denoiser(mixer_config, denoiser, spec)
    result, frame = denoise_with_sure(denoiser, frame, key, sure=settings, nonfinite=nonfinite,
                                      where="progressive_denoise")
    y = jnp.asarray(result.denoised, jnp.float32)
    sure_map = jnp.asarray(result.sure, jnp.float32)
    z_prime, alpha_prime, alpha, mixed = mix_given_sure(
        frame.color, y, frame.variance, sure_map, mixer_params, mixer_config, tstat=tstat,
        swap_average=swap_average, spp=frame.spp, variance_dof=frame.variance_dof)
    extras = {
        "denoised": y,
        "sure": sure_map,
        "divergence": jnp.asarray(result.divergence_term, jnp.float32),
        "alpha": alpha,
        "mixed": mixed,
    }
    return z_prime, alpha_prime, extras


def mix_given_sure(x, y, var, sure, mixer_params, mixer_config: MixerConfig, *,
                   tstat=_FROM_CONFIG, swap_average: bool | None = None, spp=None,
                   sigma=None, variance_dof=None):
    """The part of :func:`progressive_denoise` after SURE: alpha from the mixer (swap-averaged
    per ``swap_average``, None: the config's), the t-statistic scaling (``tstat`` as there) and
    the mix. ``sure`` may be any map in SURE's place (the PD report feeds the true error;
    ``jaxden progressive --buffers`` sub-buffer SURE). ``spp``: the sample count ``var`` was
    estimated from, for the error guard (None: unknown). ``variance_dof``: the degrees of
    freedom of ``var`` (``Frame.variance_dof``), which the guard's bound uses in place of
    spp - 1 where given (:mod:`jaxden.progressive.guard`). ``sigma``: the t-statistic's width
    (None: from ``var``; tiles pass their frame's).
    Returns ``(z_prime, alpha_prime, alpha, mixed)``, float32 JAX arrays."""
    if tstat is _FROM_CONFIG:
        tstat = mixer_config.tstat
    if swap_average is None:
        swap_average = mixer_config.swap_average
    x, y, var, sure = (jnp.asarray(a, jnp.float32) for a in (x, y, var, sure))
    alpha = inference_alpha(mixer_params, x, y, var, sure, mixer_config, bool(swap_average))
    mixed = mix_unchecked(x, y, alpha)
    if tstat is None:
        return mixed, alpha, alpha, mixed
    if tstat.guard:
        if variance_dof is not None:
            dof = np.asarray(variance_dof, np.float64)
            if not np.all(np.isfinite(dof)) or np.any(dof <= 0):
                raise FrameError(f"progressive_denoise: variance_dof (the variance's degrees of "
                                 f"freedom) must be finite and > 0, got {dof}")
        spp = check_spp(guard_sample_count(spp, variance_dof), tuple(x.shape[:-3]),
                        "progressive_denoise")
    alpha_prime = consistent_alpha(alpha, x, y, var, mixed, tstat, spp, sigma)
    return mix_unchecked(x, y, alpha_prime), alpha_prime, alpha, mixed


#: Denoisers that give, to float32 rounding, the output of the one a shipped mixer was
#: trained on: ``{denoiser: the mixer's denoiser}`` (the mixer is theirs as much). OIDN in
#: JAX (``oidn-jax``) is OIDN with Intel's weights.
TWINS: dict[str, str] = {"oidn-jax": "oidn"}

#: Mixers shipped in ``jaxden/weights/`` per denoiser name: ``{denoiser: weights name}``; a
#: twin (:data:`TWINS`) takes its original's.
SHIPPED_MIXERS: dict[str, str] = {"oidn": "oidn-pd", "wskp-6": "wskp-6-pd"}
SHIPPED_MIXERS.update({twin: SHIPPED_MIXERS[original] for twin, original in TWINS.items()})

#: The SURE a twin feeds its original's shipped mixer, over the mixer's training settings
#: (:meth:`SureSettings.over`): OIDN in JAX takes one Rademacher probe by ``jax.jvp``, which
#: scores as ``oidn-pd``'s own four finite-difference probes of the C++ OIDN on both held-out
#: sets, for one jvp pass instead of four more OIDN calls (measured: docs/results.md, "OIDN
#: in JAX with Intel's weights").
TWIN_SURE: dict[str, SureSettings] = {
    "oidn-jax": SureSettings(probes=1, method="jvp", probe_dist="rademacher")}


class MixerDenoiserWarning(UserWarning):
    """A trained mixer mixes the output of a denoiser other than the one it was trained on."""


_WARNED: set[tuple[str, str]] = set()
_SAME: dict[tuple, bool] = {}


def _trained_on(trained: str, denoiser, spec) -> bool:
    """Whether ``denoiser`` (given as ``spec``) is the mixer's ``trained`` one or its twin."""
    if trained in (denoiser.name, TWINS.get(denoiser.name)):
        return True
    if isinstance(spec, (str, os.PathLike)) and Path(spec).name == Path(trained).name:
        return True
    memo = (trained, denoiser.name, id(denoiser.params))
    if memo not in _SAME:  # shipped or trained weights: the same network and parameters?
        from jaxden.data.item_cache import params_sha256

        try:
            original = resolve_denoiser(trained)
        except JaxdenError:
            _SAME[memo] = False
        else:
            _SAME[memo] = (original.name == denoiser.name
                           and params_sha256(original.params) == params_sha256(denoiser.params))
    return _SAME[memo]


def warn_if_other_denoiser(mixer_config: MixerConfig, denoiser, spec=None) -> str | None:
    """Warn (:class:`MixerDenoiserWarning`, once per process and pair) when a trained mixer
    is applied to a denoiser other than its ``mixer_config.denoiser``: not that name, not its
    twin (:data:`TWINS`), not the same network with the same parameters, and (``spec``: how
    the caller named ``denoiser``) not a spec of the same name. Returns the message when it
    warns, else None. The closed form was trained on nothing: never."""
    if mixer_config.kind != "network" or _trained_on(mixer_config.denoiser, denoiser, spec):
        return None
    pair = (mixer_config.denoiser, denoiser.name)
    if pair in _WARNED:
        return None
    _WARNED.add(pair)
    message = (f"the mixer was trained on the output of denoiser {mixer_config.denoiser!r}; "
               f"mixing {denoiser.name!r} instead")
    warnings.warn(message, MixerDenoiserWarning, stacklevel=3)
    return message


def shipped_mixer_path(denoiser: str = "oidn"):
    """Path of the shipped mixer's .msgpack for ``denoiser``, or None if none ships."""
    from jaxden.paths import shipped_weights_file

    name = SHIPPED_MIXERS.get(denoiser)
    return None if name is None else shipped_weights_file(name)


def load_shipped_mixer(denoiser: str = "oidn"):
    """``(params, config)`` of the mixer shipped for ``denoiser`` (:data:`SHIPPED_MIXERS`), a
    twin's with its SURE settings (:data:`TWIN_SURE`); None when none ships."""
    path = shipped_mixer_path(denoiser)
    if path is None:
        return None
    params, config = load_mixer(str(path))
    twin = TWIN_SURE.get(denoiser)
    if twin is not None:
        config = dataclasses.replace(config, sure=twin.over(config.sure))
    return params, config


def shipped_progressive_denoiser(denoiser: str = "oidn", *, seed: int = 0,
                                 num_probes: int | None = None,
                                 sure: SureSettings | None = None):
    """PD(denoiser) with the mixer shipped in the package, or None when none ships.

    Returns a function ``frame -> (z_prime, alpha_prime)`` (NumPy float32, (H, W, 3) each):
    :func:`progressive_denoise` with the shipped mixer (``jaxden/weights/oidn-pd.msgpack`` for
    OIDN and OIDN in JAX; see its model card ``oidn-pd.md``; :func:`load_shipped_mixer`), its
    t-statistic config and its SURE settings (the twin's, :data:`TWIN_SURE`) under ``sure``
    (and ``num_probes``, where given), probes drawn from ``PRNGKey(seed)``.
    """
    shipped = load_shipped_mixer(denoiser)
    if shipped is None:
        return None
    from jaxden.denoise.registry import load_denoiser

    params, config = shipped
    model = load_denoiser(denoiser)
    key = jax.random.PRNGKey(seed)

    def run(frame):
        z, alpha, _ = progressive_denoise(frame, model, params, config, key, sure=sure,
                                          num_probes=num_probes)
        return np.asarray(z), np.asarray(alpha)

    return run
