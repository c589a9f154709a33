"""The mixer ("PDNet") as pure functions: MixerConfig, init, alpha and apply, swap symmetry, and
mixer checkpoints (save_mixer, load_mixer).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Literal

import jax
import jax.numpy as jnp

from jaxden.config import bounded
from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.checks import check_same
from jaxden.progressive.closed_form import closed_form_alpha_unchecked
from jaxden.progressive.heads import (
    ALPHA_HEADS,
    CLOSED_FORM_LOGIT_EPS,
    closed_form_logit_alpha,
    f_act_unchecked,
    mix_unchecked,
)
from jaxden.progressive.inputs import (
    CHANNELS_PER_FEATURE,
    MIXER_FEATURES,
    SURE_BASED_FEATURES,
    check_mixer_features,
    mixer_channel_slices,
    mixer_inputs_unchecked,
)
from jaxden.progressive.tstat import TStatConfig
from jaxden.sure.stein import ProbeDist

# ------------------------------------------------------------------------ closed-form mixer

#: Mixer spec (``--mixer``, :func:`load_mixer`) of the closed-form mixer; options as
#: ``closed-form:sigma=4,per_channel=true``; ``covariance=true`` takes SURE from the colour
#: covariance of frames that carry one (``Frame.covariance``; the stronger PD over JAX bases
#: that mix channels, docs/results.md).
CLOSED_FORM_SPEC = "closed-form"
#: Option names of the closed-form spec -> :class:`MixerConfig` fields.
CLOSED_FORM_OPTIONS = {"sigma": "closed_form_sigma", "per_channel": "closed_form_per_channel",
                       "stops": "closed_form_stops", "covariance": "sure_covariance"}


def closed_form_alpha(x, y, var, sure, *, sigma: float = 12.0, per_channel: bool = False,
                      stops: float | None = None):
    """The paper's Eq. 9 with Gaussian local means: a mixer without a network (our addition).

    For z = x + alpha (y - x), the alpha that minimises E[(z - mu)^2] is (paper Eq. 9)
    ``alpha = (var - var E f'(x)) / E[(y - x)^2]``; with SURE = (y - x)^2 - var + 2 var f'(x)
    its numerator is ``((y - x)^2 + var - SURE) / 2``. Per pixel these estimates are far too
    noisy to use (paper Sec. 4.1; measured: at sigma 2 the mix is already worse than OIDN
    alone, experiments/results/closed-form-sigma.md at commit 72ae049), so both
    numerator and denominator are replaced by local means, Gaussian weights of standard
    deviation ``sigma`` pixels (truncated at 3 sigma, only in-image pixels), summed over the
    colour channels unless ``per_channel``, and the ratio is clipped to [0, 1].

    Properties: swap-symmetric by construction (exchanging (x, var) with (y, SURE) gives
    1 - alpha before clipping); consistent on its own (as var -> 0 with y's bias fixed, the
    numerator -> 0 and the denominator -> 2 bias^2, so alpha -> 0), and the t-statistic
    scaling still applies on top in :func:`progressive_denoise`. Where y == x on a whole
    window alpha is 1 (any value gives the same z).

    ``stops`` (None: off) makes the local means range-aware (our addition): only neighbours of
    similar brightness count, through tent bins ``stops`` wide in log2 of the channel mean of
    (x + y) / 2 (blurred by :data:`CLOSED_FORM_PROXY_SIGMA` px; see
    :func:`_range_local_means`). Without it, a window holding an emitter or a bright
    highlight is ruled by that spot's errors, which are orders of magnitude larger than those
    of the dim surfaces around it, and its alpha is forced on them (measured on the demo's
    Cornell box: relMSE 2.4x OIDN's at 64 spp; with stops = 1, 0.6x). The proxy is symmetric
    in x and y, so swap symmetry and consistency hold as above.

    Inputs (..., H, W, 3) as in :func:`mixer_alpha`; returns alpha (..., H, W, 3) in [0, 1].
    Pure and jitted (``sigma``, ``per_channel`` and ``stops`` static).
    """
    config = MixerConfig(kind="closed_form", closed_form_sigma=sigma,
                         closed_form_per_channel=per_channel, closed_form_stops=stops)
    x, y, var, sure = _mixer_arrays("closed_form_alpha", config, x, y, var, sure)
    return closed_form_alpha_unchecked(x, y, var, sure, float(sigma), per_channel,
                                       None if stops is None else float(stops))


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


# ==================================================================================== mixer
# The mixer network, its config, training task, checkpoints and the inference pipeline.
# (The network module is jaxden.progressive.network.PDNet.)

MIXER_KIND = "mixer"
MIXER_MODEL = "mixer"
#: MixerConfig.kind: the paper's network, or Eq. 9 with local means (:func:`closed_form_alpha`).
MIXER_KINDS = ("network", "closed_form")


@dataclasses.dataclass(frozen=True)
class MixerConfig:
    """The progressive-denoising mixer ("PDNet") and the data it is trained on.

    Network:
      features: mixer inputs (:data:`MIXER_FEATURES`, 18 channels; :data:`MIXER_FEATURES_NO_SURE`
        for the "w/o SURE" ablation, 12 channels).
      head: ``"f_act"`` (paper Eq. 19, 9 outputs) or ``"sigmoid"`` / ``"clip"`` (the "w/o f_act"
        ablation: alpha predicted directly, 3 outputs), or ``"closed_form_logit"`` (our
        addition, 3 outputs: a logit-space correction of the closed-form alpha with this
        config's ``closed_form_sigma`` / ``closed_form_per_channel``; an untrained network
        starts at the closed form). See :data:`ALPHA_HEADS`.
      width: hidden channels (48). centred_head: start alpha near 0.5 (see
        :func:`jaxden.progressive.network.head_bias`; our choice, the paper does not say).
      init_output_scale: factor on the initial output-layer kernel (0.1): with the full
        LeCun scale the untrained f_act mixer has a third of its alphas saturated at 0 or 1
        (zero gradient) on the tiny dataset, mean 0.15; at 0.1 none, 0.46 +- 0.03.
      f_act_eps: the eps of f_act (1e-6).
      input_transform: ``"atan"`` (the authors') or ``"log"`` (a signed log; our addition) for
        the var, SURE, residual and divergence inputs; see :data:`INPUT_TRANSFORMS`.
      logit_bound: with the ``closed_form_logit`` head, None (the correction is the raw
        output) or B > 0: the correction is B tanh(raw / B), so alpha's logit stays within B
        of Eq. 9's whatever the inputs (see :func:`closed_form_logit_alpha`).
      logit_eps: with the ``closed_form_logit`` head, alpha_cf is clipped to [eps, 1 - eps]
        before its logit (default :data:`CLOSED_FORM_LOGIT_EPS`).

    Closed-form mixer (no network; our addition, see :func:`closed_form_alpha`):
      kind: ``"network"`` (the paper's PDNet) or ``"closed_form"`` (the paper's Eq. 9 with
        Gaussian local means of the per-pixel estimates; no parameters, works for any
        denoiser without training; load it with the spec :data:`CLOSED_FORM_SPEC`).
      closed_form_sigma: standard deviation in pixels of the Gaussian local means (also of
        the network's optional ``closed_form`` input feature; 12: the
        best geometric-mean RMSE ratio over OIDN on the 480 inputs of data/default-chain, flat
        within 0.3 % from 8 to 16; experiments/results/closed-form-sigma.md at commit 72ae049).
      closed_form_per_channel: one alpha per colour channel instead of one for all three.
      closed_form_stops: None (plain Gaussian local means) or the width in stops (log2) of
        the brightness strata of range-aware local means (see :func:`closed_form_alpha`);
        also used by the ``closed_form_logit`` head and the ``closed_form`` feature.
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
        Measured with the shipped OIDN mixer (with the t-statistic scaling), PD(OIDN) / OIDN
        mean over spp went from 0.928 / 0.893 to 0.923 / 0.887 (RMSE / relMSE, test set,
        2..1024 spp) and from 0.807 / 0.788 to 0.806 / 0.780 (test-high, 32..4096 spp;
        experiments/results/pd-oidn*.md at commit 72ae049). Default off, so a mixer trained and evaluated
        before this option behaves as it did; the shipped ``oidn-pd`` turns it on.

    SURE cache (the denoised images and SURE maps the mixer is trained on, computed once per
    dataset item by :func:`jaxden.progressive.cache_build.build_sure_cache`):
      denoiser: denoiser spec (``oidn``, a checkpoint folder or a .msgpack file; paths may
        use ``~`` and ``$JAXDEN_HOME``).
      cache: cache folder; empty = ``DATASET/derived/<denoiser>`` (see
        :func:`jaxden.progressive.cache.default_cache_dir`).
      sure_probes, sure_method (``auto``: jvp for JAX denoisers, fd for black boxes),
      sure_eps (None: the measured default of :func:`jaxden.sure.denoiser.default_eps`), sure_seed.
      sure_covariance: draw SURE's probes from the colour covariance of frames that carry one
        (``Frame.covariance``; :mod:`jaxden.sure.stein`), in training and at inference. Off by
        default: a mixer learns the SURE it was trained with, and mixers trained before
        frames had a covariance saw the per-channel form, which inference then keeps.
      sure_probe_dist: ``normal`` or ``rademacher`` probes (:mod:`jaxden.sure.stein`), in
        training and, unless told otherwise, at inference.
      build_cache: build (or finish) the cache when training starts if it is missing or
        incomplete; else a missing cache is an error.
    """

    features: tuple[str, ...] = MIXER_FEATURES
    kind: Literal["network", "closed_form"] = "network"
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
    sure_probes: int = bounded(4, low=1, high=1024)
    sure_method: Literal["auto", "jvp", "fd"] = "auto"
    sure_eps: float | None = bounded(None, low=0, low_open=True, high=1)
    sure_seed: int = bounded(0, low=0, high=4294967295)
    sure_covariance: bool = False
    sure_probe_dist: ProbeDist = "normal"
    build_cache: bool = True

    def __post_init__(self):
        from jaxden.config import check_fields
        from jaxden.paths import expand_path

        if isinstance(self.features, list):  # a list from Python code; jit needs it hashable
            object.__setattr__(self, "features", tuple(self.features))
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


def mixer_module(config: MixerConfig):
    """The flax module (:class:`jaxden.progressive.network.PDNet`) for ``config``."""
    from jaxden.progressive.network import PDNet

    return PDNet(
        width=config.width,
        out_channels=config.out_channels,
        head=config.head,
        centred_head=config.centred_head,
    )


_INIT_CHUNK = 1 << 16


@jax.jit
def _normal_chunk(key, index):
    # One fixed shape: XLA:CPU compiles a threefry draw in ~1.5 s, once per shape; a flax
    # init compiles one per parameter shape (~9 s for PDNet on the project machine).
    return jax.random.normal(jax.random.fold_in(key, index), (_INIT_CHUNK,), jnp.float32)


def mixer_init(key, config: MixerConfig = MixerConfig()):
    """Fresh mixer parameters (a pytree) for ``config``.

    Kernels are LeCun-normal, ``N(0, 1 / fan_in)`` (fan_in = k * k * C_in; flax's default is a
    truncated variant), the output kernel times ``config.init_output_scale``; biases zero
    except the output bias (:func:`jaxden.progressive.network.head_bias` when ``centred_head``). The
    values come from one flat standard-normal sequence drawn in fixed-size chunks of ``key``
    (so initialising any config reuses one compiled draw) and are assigned to the kernels in
    parameter-path order. Same structure as ``PDNet.init``.
    """
    from jaxden.progressive.network import head_bias

    if config.kind == "closed_form":
        return {}
    sample = jax.ShapeDtypeStruct((1, 8, 8, config.in_channels), jnp.float32)
    shapes = jax.eval_shape(mixer_module(config).init, jax.random.PRNGKey(0), sample)
    leaves, tree = jax.tree_util.tree_flatten_with_path(shapes)
    kernels = [(i, leaf.shape) for i, (path, leaf) in enumerate(leaves)
               if jax.tree_util.keystr(path).endswith("['kernel']")]
    total = sum(math.prod(shape) for _, shape in kernels)
    chunks = [_normal_chunk(key, i) for i in range(-(-total // _INIT_CHUNK))]
    flat = jnp.concatenate(chunks) if len(chunks) > 1 else chunks[0]
    values = [jnp.zeros(leaf.shape, leaf.dtype) for _, leaf in leaves]
    offset = 0
    for index, shape in kernels:
        size = math.prod(shape)
        fan_in = math.prod(shape[:-1])
        values[index] = flat[offset : offset + size].reshape(shape) / math.sqrt(fan_in)
        offset += size
    for index, (path, leaf) in enumerate(leaves):
        name = jax.tree_util.keystr(path)
        if "conv_out" not in name:
            continue
        if name.endswith("['kernel']"):
            values[index] = values[index] * config.init_output_scale
        elif config.centred_head:
            values[index] = jnp.asarray(head_bias(config.out_channels, config.head))
    return jax.tree_util.tree_unflatten(tree, values)


def _mixer_swap_args(config: MixerConfig, x, y, var, sure):
    """Arguments of the mixer with the roles of x and y exchanged (see MixerConfig)."""
    if config.uses_sure:
        return y, x, sure, var
    return y, x, var, sure


@functools.partial(jax.jit, static_argnames=("config",))
def _mixer_alpha(params, x, y, var, sure, config: MixerConfig):
    stops = None if config.closed_form_stops is None else float(config.closed_form_stops)
    if config.kind == "closed_form":
        return closed_form_alpha_unchecked(x, y, var, sure, float(config.closed_form_sigma),
                                           config.closed_form_per_channel, stops)
    inputs = mixer_inputs_unchecked(x, y, var, sure, tuple(config.features), config.input_transform,
                                    float(config.closed_form_sigma), stops)
    raw = mixer_module(config).apply(params, inputs)
    if config.head == "f_act":
        return f_act_unchecked(raw, config.f_act_eps, "by_role")
    if config.head == "closed_form_logit":
        alpha_cf = closed_form_alpha_unchecked(x, y, var, sure, float(config.closed_form_sigma),
                                               config.closed_form_per_channel, stops)
        return closed_form_logit_alpha(raw, alpha_cf, config.logit_bound, config.logit_eps)
    if config.head == "sigmoid":
        return jax.nn.sigmoid(raw)
    return jnp.clip(raw, 0.0, 1.0)


def _mixer_arrays(where: str, config: MixerConfig, x, y, var, sure):
    if config.uses_sure and sure is None:
        raise FrameError(f"{where}: the mixer's features {list(config.features)} need 'sure'")
    arrays = {"x": x, "y": y, "var": var}
    if sure is not None:
        arrays["sure"] = sure
    check_same(where, **arrays)
    x, y, var = (jnp.asarray(a, jnp.float32) for a in (x, y, var))
    sure = jnp.zeros_like(x) if sure is None else jnp.asarray(sure, jnp.float32)
    return x, y, var, sure


def mixer_alpha(params, config: MixerConfig, x, y, var, sure=None):
    """alpha = head(PDNet(mixer_inputs(x, y, var, sure))), (..., H, W, 3) in [0, 1].

    x: noisy colour, y: denoised colour, var: variance of the pixel mean of x, sure: SURE of
    y; all (..., H, W, 3) linear radiance (radiance^2 for var and sure). Pure and jitted
    (``config`` is static), differentiable in ``params``. No t-statistic scaling.
    """
    x, y, var, sure = _mixer_arrays("mixer_alpha", config, x, y, var, sure)
    return _mixer_alpha(params, x, y, var, sure, config)


def mixer_apply(params, config: MixerConfig, x, y, var, sure=None):
    """The training-time mixer: ``(z, alpha)`` with ``z = x + alpha (y - x)``; shapes as in
    :func:`mixer_alpha`. No t-statistic scaling (the paper applies it only at inference)."""
    x, y, var, sure = _mixer_arrays("mixer_apply", config, x, y, var, sure)
    alpha = _mixer_alpha(params, x, y, var, sure, config)
    return mix_unchecked(x, y, alpha), alpha


def inference_alpha(params, x, y, var, sure, config: MixerConfig, swap_average: bool):
    alpha = _mixer_alpha(params, x, y, var, sure, config)
    if not swap_average:
        return alpha
    swapped = _mixer_alpha(params, *_mixer_swap_args(config, x, y, var, sure), config)
    return 0.5 * (alpha + (1.0 - swapped))


def swap_symmetry(params, config: MixerConfig, x, y, var, sure=None, *, per_pixel: bool = False):
    """How far a mixer is from swap symmetry: mean |alpha(x, y, var, sure) - (1 - alpha(y, x,
    sure, var))|.

    A mixer that learned the paper's swap invariance (Sec. 4.3, 7: swapping the inputs turns
    alpha into beta = 1 - alpha) gives 0; the training swap only encourages it, so expect a
    small positive number for a trained mixer. Inputs (..., H, W, 3). Returns a float (mean over
    everything), or the per-pixel map (..., H, W, 3) with ``per_pixel=True``. With the
    "w/o SURE" features the swapped call is alpha(y, x, var) (see :class:`MixerConfig`).
    """
    x, y, var, sure = _mixer_arrays("swap_symmetry", config, x, y, var, sure)
    alpha = _mixer_alpha(params, x, y, var, sure, config)
    swapped = _mixer_alpha(params, *_mixer_swap_args(config, x, y, var, sure), config)
    gap = jnp.abs(alpha - (1.0 - swapped))
    return gap if per_pixel else float(jnp.mean(gap))


# ------------------------------------------------------------------------------ checkpoints

def mixer_meta(config: MixerConfig) -> dict:
    from jaxden.config import config_to_dict

    return {
        "kind": MIXER_KIND,
        "model": MIXER_MODEL,
        "model_config": config_to_dict(config),
        "layout": mixer_layout(config),
    }


def save_mixer(path, params, config: MixerConfig, **extra_meta) -> None:
    """Write released mixer weights: ``path`` (.msgpack) and its .json meta record (atomic).

    ``extra_meta``: anything worth recording (training steps, dataset, measured metrics).
    """
    from jaxden.checkpoint import save_weights

    save_weights(path, params, {**extra_meta, **mixer_meta(config)})


def load_mixer(spec, *, expect_features: tuple[str, ...] | None = None):
    """``(params, config)`` of a trained mixer.

    ``spec``: a training workdir or checkpoint folder of ``jaxden train`` with ``model =
    "mixer"``, a released ``.msgpack`` file (with its .json), the name of weights shipped in
    ``jaxden/weights/<name>.msgpack``, or ``closed-form[:KEY=VALUE,...]`` for the mixer
    without weights (:func:`closed_form_mixer`; params ``{}``). ``expect_features``: the input layout the caller needs.

    Raises CheckpointError naming the difference when the checkpoint is not a mixer (e.g. a
    denoiser checkpoint), its config is not a valid :class:`MixerConfig`, its recorded input
    layout differs from what this jaxden builds for that config, its features differ from
    ``expect_features``, or a parameter's shape does not fit the config.
    """
    from pathlib import Path

    from jaxden.checkpoint import load_trained_params, read_checkpoint_meta
    from jaxden.config import config_diff, load_config
    from jaxden.errors import CheckpointError

    if isinstance(spec, str) and spec.partition(":")[0] == CLOSED_FORM_SPEC:
        return closed_form_mixer(spec)
    path = Path(spec)
    if not path.exists() and isinstance(spec, str):
        from jaxden.denoise.registry import WEIGHTS_DIR

        shipped = WEIGHTS_DIR / f"{spec}.msgpack"
        if shipped.is_file():
            path = shipped
    if not path.exists():
        raise CheckpointError(
            f"mixer {spec}: no such checkpoint folder or weights file (train one with "
            f"`jaxden train` and a config with model = \"mixer\")"
        )
    meta = read_checkpoint_meta(path)
    if meta.get("kind") != MIXER_KIND:
        raise CheckpointError(
            f"{path}: holds a {meta.get('kind', 'unknown')!r} checkpoint (model "
            f"{meta.get('model')!r}), not a mixer; a denoiser goes to --denoiser"
        )
    try:
        config = load_config(dict(meta.get("model_config", {})), MixerConfig)
    except ConfigError as error:
        raise CheckpointError(
            f"{path}: its model_config is not a valid mixer config: {error}"
        ) from None
    layout = mixer_layout(config)
    stored = meta.get("layout")
    if stored is not None:
        differences = config_diff(stored, layout)
        if differences:
            raise CheckpointError(
                f"{path}: the recorded mixer input layout differs from the one this jaxden "
                f"builds for its config (stored -> built): {'; '.join(differences)}"
            )
    if expect_features is not None and tuple(expect_features) != tuple(config.features):
        raise CheckpointError(
            f"{path}: the mixer was trained on features {list(config.features)}, expected "
            f"{list(expect_features)}"
        )
    # Shapes only: the loader checks names and shapes against it and fills in the values.
    target = jax.eval_shape(lambda: mixer_init(jax.random.PRNGKey(0), config))
    expect = {"kind": MIXER_KIND, "model": MIXER_MODEL}
    params, _ = load_trained_params(path, target, expect=expect)
    return params, config
