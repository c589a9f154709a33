"""MixerConfig: the progressive-denoising mixer and the data it is trained on, as one frozen value;
its input/output layout (:func:`mixer_layout`), the closed-form mixer's spec
(:func:`closed_form_mixer`) and the one map from the older flat keys of stored configs
(:func:`upgrade_mixer_config`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Literal

from jaxden.config import bounded
from jaxden.errors import ConfigError
from jaxden.progressive.heads import ALPHA_HEADS, CLOSED_FORM_LOGIT_EPS
from jaxden.progressive.inputs import (
    CHANNELS_PER_FEATURE,
    MIXER_FEATURES,
    SURE_BASED_FEATURES,
    check_mixer_features,
    mixer_channel_slices,
)
from jaxden.progressive.tstat import TStatConfig
from jaxden.sure.settings import SureSettings

#: MixerConfig.kind: the paper's network, or Eq. 9 with local means
#: (:func:`jaxden.progressive.closed_form.closed_form_alpha`).
MIXER_KINDS = ("network", "closed_form")

#: A mixer's SURE settings where its config leaves them unset: the defaults
#: (:data:`jaxden.sure.settings.DEFAULTS`) but per-channel probes (``covariance`` off: a mixer
#: learns the SURE it was trained with, and mixers trained before frames had a covariance saw
#: the per-channel form).
MIXER_SURE = SureSettings(covariance=False).resolved()


@dataclasses.dataclass(frozen=True)
class MixerConfig:
    """The progressive-denoising mixer ("PDNet") and the data it is trained on.

    Network:
      features: mixer inputs (:data:`~jaxden.progressive.inputs.MIXER_FEATURES`, 18 channels;
        :data:`~jaxden.progressive.inputs.MIXER_FEATURES_NO_SURE` for the "w/o SURE" ablation,
        12 channels).
      head: ``"f_act"`` (paper Eq. 19, 9 outputs) or ``"sigmoid"`` / ``"clip"`` (the "w/o f_act"
        ablation: alpha predicted directly, 3 outputs), or ``"closed_form_logit"`` (our
        addition, 3 outputs: a logit-space correction of the closed-form alpha with this
        config's ``closed_form_sigma`` / ``closed_form_per_channel``; an untrained network
        starts at the closed form). See :data:`~jaxden.progressive.heads.ALPHA_HEADS`.
      network: the registered mixer network (:func:`jaxden.progressive.network.
        register_mixer_network`): ``"pdnet"``, the paper's, or a plugin's; every other field
        (inputs, head, SURE, training, t-statistic) applies to it unchanged. Checked where
        the network is built (a ConfigError naming the registered ones).
      width: hidden channels (48). centred_head: start alpha near 0.5 (see
        :func:`jaxden.progressive.network.head_bias`; our choice, the paper does not say).
      init_output_scale: factor on the initial output-layer kernel (0.1: no alpha of the
        untrained mixer saturated at 0 or 1, where it has no gradient; measured:
        docs/history.md, "Defaults of the code").
      f_act_eps: the eps of f_act (1e-6).
      input_transform: ``"atan"`` (the authors') or ``"log"`` (a signed log; our addition) for
        the var, SURE, residual and divergence inputs; see
        :data:`~jaxden.progressive.inputs.INPUT_TRANSFORMS`.
      logit_bound: with the ``closed_form_logit`` head, None (the correction is the raw
        output) or B > 0: the correction is B tanh(raw / B), so alpha's logit stays within B
        of Eq. 9's whatever the inputs (see
        :func:`~jaxden.progressive.heads.closed_form_logit_alpha`).
      logit_eps: with the ``closed_form_logit`` head, alpha_cf is clipped to [eps, 1 - eps]
        before its logit (default :data:`~jaxden.progressive.heads.CLOSED_FORM_LOGIT_EPS`).

    Closed-form mixer (no network; our addition, see
    :func:`~jaxden.progressive.closed_form.closed_form_alpha`):
      kind: ``"network"`` (the paper's PDNet) or ``"closed_form"`` (the paper's Eq. 9 with
        Gaussian local means of the per-pixel estimates; no parameters, works for any
        denoiser without training; load it with the spec :data:`CLOSED_FORM_SPEC`).
      closed_form_sigma: standard deviation in pixels of the Gaussian local means (also of
        the network's optional ``closed_form`` input feature); 12 (measured:
        docs/history.md, "Defaults of the code").
      closed_form_per_channel: one alpha per colour channel instead of one for all three.
      closed_form_stops: None (plain Gaussian local means) or the width in stops (log2) of
        the brightness strata of range-aware local means; also used by the
        ``closed_form_logit`` head and the ``closed_form`` feature.
      With ``kind = "closed_form"`` the network fields (features, head, width, ...) are unused.

    Training:
      swap_probability: probability of swapping (x, var) with (y, SURE) per training sample
        (0.5, paper Sec. 4.3). With the "w/o SURE" features the swap exchanges x and y only
        (there is no error estimate of y to exchange var with; our choice).

    Inference:
      tstat: the t-statistic scaling (:class:`TStatConfig`), applied only at inference.
      swap_average: use (alpha(x, y, var, SURE) + 1 - alpha(y, x, SURE, var)) / 2, the mean
        of the mixer and its swapped call (test-time symmetrisation of the swap invariance the
        training encourages; our addition, not in the paper; costs a second mixer call).
        Default off, so a mixer trained and evaluated before this option behaves as it did;
        the shipped ``oidn-pd`` turns it on (measured: docs/history.md, "Defaults of the
        code").

    SURE (the mixer's input, and its cache: the denoised images and SURE maps it is trained
    on, computed once per dataset item by
    :func:`jaxden.progressive.cache_build.build_sure_cache`):
      denoiser: denoiser spec (``oidn``, a checkpoint folder or a .msgpack file; paths may
        use ``~`` and ``$JAXDEN_HOME``).
      cache: cache folder; empty = ``DATASET/derived/<denoiser>`` (see
        :func:`jaxden.progressive.cache.default_cache_dir`).
      sure: the :class:`~jaxden.sure.settings.SureSettings` of the SURE the mixer is trained
        on and, unless told otherwise, fed at inference (the TOML table
        ``[model_config.sure]``); fields left unset are :data:`MIXER_SURE`'s: 4 normal
        probes, method ``auto``, the measured step, seed 0, per-channel (``covariance``
        off).
      build_cache: build (or finish) the cache when training starts if it is missing or
        incomplete; else a missing cache is an error.

    Configs and checkpoints written before ``sure`` was one table hold flat keys
    (``sure_probes``, ``sure_method``, ``sure_eps``, ``sure_seed``, ``sure_covariance``,
    ``sure_probe_dist``): :meth:`upgrade_config` maps them.
    """

    features: tuple[str, ...] = MIXER_FEATURES
    kind: Literal["network", "closed_form"] = "network"
    network: str = "pdnet"
    closed_form_sigma: float = bounded(12.0, low=0, low_open=True, high=256, unit='pixels')
    closed_form_per_channel: bool = False
    closed_form_stops: float | None = bounded(None, low=0.0625, high=64,
                                              unit='stops')  # >= 1/16 stop
    head: Literal["f_act", "sigmoid", "clip", "closed_form_logit"] = "f_act"
    width: int = bounded(48, low=1, high=1024)
    centred_head: bool = True
    init_output_scale: float = bounded(0.1, low=0, high=100)
    f_act_eps: float = bounded(1e-6, low=0, low_open=True, high=1)
    input_transform: Literal["atan", "log"] = "atan"
    logit_bound: float | None = bounded(None, low=0, low_open=True, high=100)
    logit_eps: float = bounded(CLOSED_FORM_LOGIT_EPS, low=0, low_open=True, high=0.5,
                               high_open=True)
    swap_probability: float = bounded(0.5, low=0, high=1)
    tstat: TStatConfig = TStatConfig()
    swap_average: bool = False
    denoiser: str = "oidn"
    cache: str = ""
    sure: SureSettings = MIXER_SURE
    build_cache: bool = True

    def __post_init__(self):
        from jaxden.config import check_fields
        from jaxden.paths import expand_path

        if isinstance(self.features, list):  # a list from Python code; jit needs it hashable
            object.__setattr__(self, "features", tuple(self.features))
        if isinstance(self.sure, SureSettings):  # a partial one: the rest is the mixer's
            object.__setattr__(self, "sure", self.sure.over(MIXER_SURE))
        # Types, choices and the bounded ranges, as declared above.
        check_fields(self)
        check_mixer_features(self.features)
        if self.head != "closed_form_logit" and (
                self.logit_bound is not None or self.logit_eps != CLOSED_FORM_LOGIT_EPS):
            raise ConfigError(
                f"MixerConfig.logit_bound / logit_eps apply only to head = 'closed_form_logit' "
                f"(head is {self.head!r})"
            )
        if not self.denoiser:
            raise ConfigError("MixerConfig.denoiser: name the denoiser whose output is mixed")
        # a trained base under "$JAXDEN_HOME/runs/..." or "~/...", as data.dataset allows
        for name in ("denoiser", "cache"):
            object.__setattr__(self, name, expand_path(getattr(self, name)))

    @classmethod
    def upgrade_config(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """A stored MixerConfig table (TOML, a checkpoint's meta record) in today's keys: the
        flat SURE keys of older configs moved into the ``sure`` table
        (:func:`upgrade_mixer_config`)."""
        return upgrade_mixer_config(data)

    @property
    def in_channels(self) -> int:
        return CHANNELS_PER_FEATURE * len(self.features)

    @property
    def out_channels(self) -> int:
        return ALPHA_HEADS[self.head]

    @property
    def uses_sure(self) -> bool:
        return (self.kind == "closed_form" or self.head == "closed_form_logit"
                or any(f in SURE_BASED_FEATURES for f in self.features))


#: The flat keys of a MixerConfig from before its SURE settings were one table -> the field
#: of ``sure`` each one is.
LEGACY_SURE_KEYS = {"sure_probes": "probes", "sure_method": "method", "sure_eps": "eps",
                    "sure_seed": "seed", "sure_covariance": "covariance",
                    "sure_probe_dist": "probe_dist"}


def upgrade_mixer_config(data: Mapping[str, Any]) -> dict[str, Any]:
    """``data`` (a MixerConfig table as stored) with the flat keys of older configs
    (:data:`LEGACY_SURE_KEYS`) moved into its ``sure`` table; a legacy ``sure_covariance``
    that is absent is off, as it was. The one place that knows the old keys: shipped weights,
    checkpoints and users' configs from before keep loading. A key given both ways is a
    ConfigError naming it."""
    data = dict(data)
    flat = {LEGACY_SURE_KEYS[key]: data.pop(key) for key in list(data) if key in LEGACY_SURE_KEYS}
    if not flat:
        return data
    table = data.get("sure", {})
    if not isinstance(table, Mapping):
        return data  # the loader names the wrong type
    both = sorted(set(flat) & set(table))
    if both:
        raise ConfigError(f"MixerConfig: {', '.join(f'sure_{k} and sure.{k}' for k in both)} "
                          f"both given; keep the table [model_config.sure] only (as an "
                          f"override: {', '.join(f'sure.{k}=VALUE' for k in both)})")
    data["sure"] = {**flat, **table}
    return data


def mixer_layout(config: MixerConfig) -> dict:
    """The input/output layout a mixer's parameters belong to (stored in checkpoints).

    ``{"features": [...], "in_channels": 18, "out_channels": 9, "head": "f_act",
    "channels": {"hdr": [0, 3], ...}}`` (JSON-able).
    """
    slices = mixer_channel_slices(tuple(config.features))
    return {
        "features": list(config.features),
        "in_channels": config.in_channels,
        "out_channels": config.out_channels,
        "head": config.head,
        "channels": {name: [s.start, s.stop] for name, s in slices.items()},
    }


# ------------------------------------------------------------------------ closed-form mixer

#: Mixer spec (``--mixer``, :func:`jaxden.progressive.load_mixer`) of the closed-form mixer;
#: options as ``closed-form:sigma=4,per_channel=true``; ``covariance=true`` takes SURE from
#: the colour covariance of frames that carry one (``Frame.covariance``; the stronger PD over
#: JAX bases that mix channels, docs/results.md).
CLOSED_FORM_SPEC = "closed-form"
#: Option names of the closed-form spec -> :class:`MixerConfig` fields (dotted: nested).
CLOSED_FORM_OPTIONS = {"sigma": "closed_form_sigma", "per_channel": "closed_form_per_channel",
                       "stops": "closed_form_stops", "covariance": "sure.covariance"}


def with_tstat_overrides(config: MixerConfig, words) -> MixerConfig:
    """``config`` with ``KEY=VALUE`` words applied to its :class:`TStatConfig` (checked:
    ConfigError naming a wrong key or value); ``config`` itself without words."""
    if not words:
        return config
    from jaxden.config import load_config

    return dataclasses.replace(config, tstat=load_config(config.tstat, TStatConfig,
                                                         overrides=list(words)))


def closed_form_mixer(spec: str = CLOSED_FORM_SPEC):
    """``({}, MixerConfig)`` of the closed-form mixer for a spec ``closed-form`` or
    ``closed-form:KEY=VALUE,...`` (keys: :data:`CLOSED_FORM_OPTIONS`)."""
    from jaxden.config import load_config

    name, _, options = spec.partition(":")
    if name != CLOSED_FORM_SPEC:
        raise ConfigError(f"mixer {spec!r}: not a closed-form mixer spec ({CLOSED_FORM_SPEC})")
    overrides = []
    for option in filter(None, (o.strip() for o in options.split(","))):
        key, equals, value = option.partition("=")
        if not equals or key.strip() not in CLOSED_FORM_OPTIONS:
            raise ConfigError(
                f"mixer {spec!r}: expected options KEY=VALUE with KEY one of "
                f"{', '.join(CLOSED_FORM_OPTIONS)}, got {option!r}"
            )
        overrides.append(f"{CLOSED_FORM_OPTIONS[key.strip()]}={value.strip()}")
    try:
        config = load_config(MixerConfig(kind="closed_form"), MixerConfig, overrides=overrides)
    except ConfigError as error:
        raise ConfigError(f"mixer {spec!r}: {error}") from None
    return {}, config
