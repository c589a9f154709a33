"""Progressive denoising (Firmino, Frisvad, Jensen 2022) as pure functions, in data-flow order:

- :mod:`~jaxden.progressive.inputs`: the mixer's input features from x, y, var and SURE;
- :mod:`~jaxden.progressive.heads`: raw network outputs -> alpha (f_act, sigmoid, closed-form
  logit), the mix;
- :mod:`~jaxden.progressive.tstat`, :mod:`~jaxden.progressive.guard`: the t-statistic scaling
  that makes the mix consistent, and the error guard after it;
- :mod:`~jaxden.progressive.closed_form`: Eq. 9 with local means (a mixer without a network);
- :mod:`~jaxden.progressive.mixer_config`: MixerConfig (with its SURE settings), the
  closed-form spec, the map from the older flat keys;
- :mod:`~jaxden.progressive.network`: PDNet and the mixer as pure functions (init, alpha,
  apply, swap symmetry);
- :mod:`~jaxden.progressive.mixer_checkpoints`: save_mixer, load_mixer;
- :mod:`~jaxden.progressive.pipeline`: progressive_denoise, the shipped mixers and their
  twins; :mod:`~jaxden.progressive.tiled`: the pipeline over tiles (progressive_frame);
- :mod:`~jaxden.progressive.cache`, :mod:`~jaxden.progressive.cache_build`: SURE caches for
  mixer training (data derived from a dataset; kept here, beside their reader, because
  building one runs SURE, a later floor than :mod:`jaxden.data`);
- :mod:`~jaxden.progressive.checks`: the argument checks these functions share.

(:mod:`~jaxden.progressive.mixer` keeps the mixer's names under their older import path.)
The constants (feature lists, heads, the closed form's bounds, the shipped mixers' table) are
imported from their modules. The mixer's training task, and its entry in the table of
trainable models, live with the other tasks in :mod:`jaxden.train.tasks`.
"""

from jaxden.progressive.closed_form import closed_form_alpha
from jaxden.progressive.heads import alpha_from_head, f_act, mix
from jaxden.progressive.inputs import mixer_inputs, swap_inputs
from jaxden.progressive.mixer_checkpoints import load_mixer, save_mixer
from jaxden.progressive.mixer_config import MixerConfig, closed_form_mixer, mixer_layout
from jaxden.progressive.network import mixer_alpha, mixer_apply, mixer_init, swap_symmetry
from jaxden.progressive.pipeline import (
    MixerDenoiserWarning,
    load_shipped_mixer,
    mix_given_sure,
    progressive_denoise,
    shipped_mixer_path,
    shipped_progressive_denoiser,
)
from jaxden.progressive.tiled import progressive_denoise_tiled, progressive_frame
from jaxden.progressive.tstat import (
    TStatConfig,
    consistent_mix,
    error_guard,
    t_statistic,
    t_statistic_scaling,
)

__all__ = [
    "MixerConfig",
    "MixerDenoiserWarning",
    "TStatConfig",
    "alpha_from_head",
    "closed_form_alpha",
    "closed_form_mixer",
    "consistent_mix",
    "error_guard",
    "f_act",
    "load_mixer",
    "load_shipped_mixer",
    "mix",
    "mix_given_sure",
    "mixer_alpha",
    "mixer_apply",
    "mixer_init",
    "mixer_inputs",
    "mixer_layout",
    "progressive_denoise",
    "progressive_denoise_tiled",
    "progressive_frame",
    "save_mixer",
    "shipped_mixer_path",
    "shipped_progressive_denoiser",
    "swap_inputs",
    "swap_symmetry",
    "t_statistic",
    "t_statistic_scaling",
]
