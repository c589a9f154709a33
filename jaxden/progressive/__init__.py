"""Progressive denoising (Firmino, Frisvad, Jensen 2022) as pure functions, in data-flow order:

- :mod:`~jaxden.progressive.inputs`: the mixer's input features from x, y, var and SURE;
- :mod:`~jaxden.progressive.heads`: raw network outputs -> alpha (f_act, sigmoid, closed-form logit), the mix;
- :mod:`~jaxden.progressive.tstat`: the t-statistic scaling that makes the mix consistent;
- :mod:`~jaxden.progressive.closed_form`: Eq. 9 with local means (a mixer without a network);
- :mod:`~jaxden.progressive.network`: the PDNet flax module;
- :mod:`~jaxden.progressive.mixer`: MixerConfig, init / alpha / apply, mixer checkpoints;
- :mod:`~jaxden.progressive.pipeline`: progressive_denoise and the shipped mixers;
- :mod:`~jaxden.progressive.cache`, :mod:`~jaxden.progressive.cache_build`: SURE caches for
  mixer training (data derived from a dataset; kept here, beside their reader, because
  building one runs SURE, a later floor than :mod:`jaxden.data`);
- :mod:`~jaxden.progressive.checks`: the argument checks these functions share.

The mixer's training task, and its entry in the table of trainable models, live with the
other tasks in :mod:`jaxden.train.tasks`.
"""

from jaxden.progressive.closed_form import (
    CLOSED_FORM_PROXY_SIGMA,
    CLOSED_FORM_RANGE_CEIL,
    CLOSED_FORM_RANGE_FLOOR,
)
from jaxden.progressive.heads import (
    ALPHA_HEADS,
    CLOSED_FORM_LOGIT_EPS,
    alpha_direct,
    alpha_from_head,
    closed_form_logit_alpha,
    f_act,
    mix,
)
from jaxden.progressive.inputs import (
    CHANNELS_PER_FEATURE,
    EXTRA_MIXER_FEATURES,
    INPUT_TRANSFORMS,
    LOG_FLOOR,
    LOG_SCALE,
    MIXER_FEATURES,
    MIXER_FEATURES_NO_SURE,
    MIXER_LAYOUT,
    SURE_BASED_FEATURES,
    mixer_channel_slices,
    mixer_inputs,
    swap_inputs,
)
from jaxden.progressive.mixer import (
    CLOSED_FORM_OPTIONS,
    CLOSED_FORM_SPEC,
    MIXER_KIND,
    MIXER_KINDS,
    MIXER_MODEL,
    MixerConfig,
    closed_form_alpha,
    closed_form_mixer,
    load_mixer,
    mixer_alpha,
    mixer_apply,
    mixer_init,
    mixer_layout,
    mixer_module,
    save_mixer,
    swap_symmetry,
)
from jaxden.progressive.pipeline import (
    SHIPPED_MIXERS,
    TWIN_SURE,
    load_shipped_mixer,
    progressive_denoise,
    shipped_mixer_path,
    shipped_progressive_denoiser,
)
from jaxden.progressive.tstat import (
    TStatConfig,
    consistent_mix,
    error_guard,
    t_statistic,
    t_statistic_scaling,
)

__all__ = [
    "ALPHA_HEADS",
    "CHANNELS_PER_FEATURE",
    "CLOSED_FORM_LOGIT_EPS",
    "CLOSED_FORM_OPTIONS",
    "CLOSED_FORM_PROXY_SIGMA",
    "CLOSED_FORM_RANGE_CEIL",
    "CLOSED_FORM_RANGE_FLOOR",
    "CLOSED_FORM_SPEC",
    "EXTRA_MIXER_FEATURES",
    "INPUT_TRANSFORMS",
    "LOG_FLOOR",
    "LOG_SCALE",
    "MIXER_FEATURES",
    "MIXER_FEATURES_NO_SURE",
    "MIXER_KIND",
    "MIXER_KINDS",
    "MIXER_LAYOUT",
    "MIXER_MODEL",
    "MixerConfig",
    "SHIPPED_MIXERS",
    "TWIN_SURE",
    "SURE_BASED_FEATURES",
    "TStatConfig",
    "alpha_direct",
    "alpha_from_head",
    "closed_form_alpha",
    "closed_form_logit_alpha",
    "closed_form_mixer",
    "consistent_mix",
    "error_guard",
    "f_act",
    "load_mixer",
    "load_shipped_mixer",
    "mix",
    "mixer_alpha",
    "mixer_apply",
    "mixer_channel_slices",
    "mixer_init",
    "mixer_inputs",
    "mixer_layout",
    "mixer_module",
    "progressive_denoise",
    "save_mixer",
    "shipped_mixer_path",
    "shipped_progressive_denoiser",
    "swap_inputs",
    "swap_symmetry",
    "t_statistic",
    "t_statistic_scaling",
]
