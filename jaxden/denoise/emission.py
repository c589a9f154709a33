"""Emission kept out of the filter: denoise the rest of the radiance, add the emission back.

A kernel-predicting denoiser spreads a directly visible lamp onto the dark pixels beside it
(docs/results.md, "Emitters bleed"). Real-time pipelines keep directly seen emission out of the
filter; with ``Frame.emission`` (the radiance emitted by the first hit, averaged over the
colour's own samples, :mod:`jaxden.render.integrators`) any denoiser D becomes::

    F(frame) = D(frame with colour max(colour - emission, 0)) + emission      (..., H, W, 3)

Selected by the denoiser spec option ``emission=separate`` (``wskp-6:emission=separate``,
:func:`jaxden.denoise.registry.load_denoiser`); ``emission=filter`` is D itself, the default.

Decisions:

- **Clamp at 0.** In jaxden's renders ``colour - emission`` is the mean of ``L - Le`` over the
  same samples and never negative (float addition is monotone), so the clamp does nothing. For
  other renderers it can be: a clamped or differently filtered combined pass, float16 files.
  The rest of the radiance cannot be negative, and the denoisers assume non-negative input
  (OIDN and WSKP clip or tone-map it at 0). The clamp is written so that its derivative is 1
  where ``colour - emission >= 0``: where it never acts, F is exactly D(colour - emission) +
  emission and its Jacobian w.r.t. the colour is D's at that input.
- **Variance unchanged.** Denoisers that take the variance (the U-Net's ``var``, SURE, the
  mixers) get the colour's variance (and covariance). Where no sample saw an emitter
  (``emission == 0``) it *is* the variance of the rest; on and beside an emitter it
  overestimates it (it holds the emitter's hit-or-miss variance, Var(L) ~ Var(Le) there): the
  renderer does not record the moments of ``L - Le``, and such pixels are few.
- **The albedo beside it is a reflectance.** The filter demodulates the rest by the albedo
  (WSKP) and multiplies it back, so a lamp pixel whose albedo holds the lamp's emission (Blender
  Cycles' Denoising Albedo: the Emission pass plus the surface's albedo, up to the lamp's
  strength) gets its neighbours' light times that emission: 30 % too bright on
  tests/data/cycles/passes-seed1.exr's lamp. ``--from cycles`` reads that albedo clipped to
  [0, 1] (:mod:`jaxden.io.conventions`), which gives the lamp its colour back within 2 %;
  measured over two Cycles scenes and two spp levels in
  ``experiments/results/renderers/cycles-emission.md``. Nothing here repairs an albedo above 1
  (reading a file warns about one).
- **The emission is a fixed feature.** SURE perturbs the colour only (``frame.replace(color=)``,
  :mod:`jaxden.sure`), so its divergence is D's at ``colour - emission``. The emission is not
  independent of the colour's noise (the same samples): where an emitter covers part of a pixel
  its noise passes through F unfiltered, and SURE, which sees it as fixed, misjudges those
  pixels' error; elsewhere (emission 0 on every sample) nothing changes.

Pure functions: the same code serves JAX denoisers (traced, jvp-able) and black boxes (NumPy).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxden.errors import FrameError
from jaxden.frame import CHANNELS, Frame

#: Values of the denoiser spec option ``emission``: ``filter`` (D as it is, the default) or
#: ``separate`` (the emission kept out of the filter).
EMISSION_MODES: tuple[str, ...] = ("filter", "separate")


def require_emission(frame: Frame, who: str) -> None:
    """FrameError naming the missing channels unless ``frame`` carries ``emission``."""
    if getattr(frame, "emission", None) is None:
        have = ", ".join(frame.features()) if isinstance(frame, Frame) else type(frame).__name__
        raise FrameError(
            f"{who} keeps the emission out of the filter and needs the frame feature emission "
            f"(EXR channels {'/'.join(CHANNELS['emission'])}: the radiance emitted by the "
            f"first hit, written by `jaxden render`; Blender Cycles' Emission pass, View Layer "
            f"Properties > Passes > Light > Emission, read by --from cycles; another name with "
            f"--channels emission=NAME.R,NAME.G,NAME.B), but the frame has only {have}")


def rest_of_radiance(color, emission, xp=jnp):
    """``max(color - emission, 0)`` per pixel and channel, (..., H, W, 3), with derivative 1
    w.r.t. ``color`` wherever ``color >= emission`` (0 only where the clamp acts). ``xp``:
    ``jnp`` (traced) or ``np``."""
    rest = color - emission
    return xp.where(rest < 0, xp.zeros_like(rest), rest)


def separate_emission(frame: Frame, denoise: Callable[[Frame], Any], *, xp=jnp,
                      who: str = "this denoiser"):
    """``denoise(frame with colour max(colour - emission, 0)) + emission``, (..., H, W, 3).

    ``denoise``: frame -> image (the variance, covariance and every other feature are passed
    unchanged; see the module docstring). ``xp``: ``jnp`` for JAX denoisers, ``np`` for black
    boxes (float32 out). Raises FrameError when the frame has no emission.
    """
    require_emission(frame, who)
    if xp is np:
        color = np.asarray(frame.color, np.float32)
        emission = np.asarray(frame.emission, np.float32)
        rest = rest_of_radiance(color, emission, np)
        return (np.asarray(denoise(frame.replace(color=rest)), np.float32) + emission)
    color = jnp.asarray(frame.color, jnp.float32)
    emission = jnp.asarray(frame.emission, jnp.float32)
    rest = rest_of_radiance(color, emission, jnp)
    return jnp.asarray(denoise(frame.replace(color=rest)), jnp.float32) + emission


def separated_apply(apply: Callable, name: str, differentiable: bool) -> Callable:
    """A denoiser definition's ``apply(params, config, frame)`` with the emission kept out of
    the filter (:func:`separate_emission`); ``name`` for error messages."""
    xp = jnp if differentiable else np

    def apply_separated(params, config, frame: Frame):
        return separate_emission(frame, lambda rest: apply(params, config, rest), xp=xp,
                                 who=f"denoiser '{name}'")

    return apply_separated


def separated_step(step: Callable) -> Callable:
    """A temporal form ``step(params, config, state, frame) -> (image, state)`` with the
    emission kept out of the filter: the history holds the rest of the radiance, and each
    frame's emission is added to its image (JAX denoisers)."""

    def step_separated(params, config, state, frame: Frame):
        require_emission(frame, "this temporal denoiser")
        emission = jnp.asarray(frame.emission, jnp.float32)
        rest = rest_of_radiance(jnp.asarray(frame.color, jnp.float32), emission, jnp)
        image, state = step(params, config, state, frame.replace(color=rest))
        return jnp.asarray(image, jnp.float32) + emission, state

    return step_separated
