"""The mixer's names under their older import path, ``jaxden.progressive.mixer``: each lives in
the module of its concept, and jaxden's own code imports it from there.

- the value: :mod:`~jaxden.progressive.mixer_config` (:class:`MixerConfig`, the closed-form
  spec :func:`closed_form_mixer`, :func:`mixer_layout`);
- the network as pure functions: :mod:`~jaxden.progressive.network` (:func:`mixer_init`,
  :func:`mixer_alpha`, :func:`mixer_apply`, :func:`inference_alpha`, :func:`swap_symmetry`);
- the closed form: :mod:`~jaxden.progressive.closed_form` (:func:`closed_form_alpha`);
- checkpoints: :mod:`~jaxden.progressive.mixer_checkpoints` (:func:`save_mixer`,
  :func:`load_mixer`, :func:`mixer_meta`).
"""

from jaxden.progressive.closed_form import closed_form_alpha
from jaxden.progressive.mixer_checkpoints import (
    MIXER_KIND,
    MIXER_MODEL,
    load_mixer,
    mixer_meta,
    save_mixer,
)
from jaxden.progressive.mixer_config import (
    CLOSED_FORM_OPTIONS,
    CLOSED_FORM_SPEC,
    MIXER_KINDS,
    MixerConfig,
    closed_form_mixer,
    mixer_layout,
)
from jaxden.progressive.network import (
    inference_alpha,
    mixer_alpha,
    mixer_apply,
    mixer_init,
    mixer_module,
    swap_symmetry,
)

__all__ = [
    "CLOSED_FORM_OPTIONS",
    "CLOSED_FORM_SPEC",
    "MIXER_KIND",
    "MIXER_KINDS",
    "MIXER_MODEL",
    "MixerConfig",
    "closed_form_alpha",
    "closed_form_mixer",
    "inference_alpha",
    "load_mixer",
    "mixer_alpha",
    "mixer_apply",
    "mixer_init",
    "mixer_layout",
    "mixer_meta",
    "mixer_module",
    "save_mixer",
    "swap_symmetry",
]
