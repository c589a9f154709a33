"""The progressive-denoising mixer network ("PDNet", Firmino, Frisvad, Jensen 2022, Sec. 4.3)
and the mixer as pure functions of (params, config, x, y, var, SURE): :func:`mixer_init`,
:func:`mixer_alpha`, :func:`mixer_apply`, :func:`inference_alpha`, :func:`swap_symmetry`.

Architecture (paper Fig. 6 and the reference notes)::

    in (..., H, W, C_in)                          C_in = 18 (all features) or 12 (w/o SURE)
    conv_in   5x5, C_in -> width, ReLU            width = 48
    block_0   h = ReLU(conv_a 3x3(x)); out = ReLU(x + conv_b 3x3(h))
    block_1   the same
    conv_out  3x3, width -> C_out                 C_out = 9 (f_act) or 3 (alpha directly)

Six convolutions, 'SAME' zero padding, biases, no normalisation layers; ReLU after every
convolution but the last. The raw output goes to :func:`jaxden.progressive.alpha_from_head`.

Choices the paper leaves open (recorded here, and options where they are research knobs):

- Residual block form: the standard ResNet block of He et al. 2016 (the paper's [HZRS16]),
  ``ReLU(x + conv_b(ReLU(conv_a(x))))``, so a ReLU still follows every convolution but the
  last, as the paper says.
- Initialisation: :func:`mixer_init` (what jaxden uses) draws LeCun-normal
  kernels N(0, 1 / fan_in) from one chunked normal sequence (fast to compile), scales the
  output kernel by ``MixerConfig.init_output_scale`` (0.1) and sets zero biases, except the
  output bias, which :func:`head_bias` sets so that the untrained network starts inside the
  region where alpha has a gradient. With f_act and zero biases half the pixels
  have ``x3 < eps`` and ``alpha = clip((x1 - x2) / 1e-6, 0, 1)`` saturates at 0 or 1 with zero
  gradient; the bias ``x1 = 0.5, x2 = 0, x3 = 1`` with the small output kernel starts every
  pixel near ``alpha = 0.5``. Both choices lowered the validation SMAPE after short
  trainings (measured: docs/history.md, "Defaults of the code").
  The paper does not say how it initialised (the authors' PyTorch default gives zero-mean
  biases); ``centred_head=False`` gives zero biases. ``PDNet.init`` itself uses the flax
  defaults (truncated LeCun-normal) with the same output bias.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.checks import check_same
from jaxden.progressive.closed_form import closed_form_alpha_unchecked
from jaxden.progressive.heads import closed_form_logit_alpha, f_act_unchecked, mix_unchecked
from jaxden.progressive.inputs import mixer_inputs_unchecked
from jaxden.progressive.mixer_config import MixerConfig
from jaxden.registry import Registry


def head_bias(out_channels: int, head: str) -> np.ndarray:
    """Initial bias of the output convolution that puts alpha near 0.5 at every pixel.

    ``f_act`` (9 outputs, grouped by role as in :func:`jaxden.progressive.f_act`):
    x1 = 0.5, x2 = 0, x3 = 1, so alpha = (x1 - x2) / x3 = 0.5 with non-zero gradients in all
    three. ``clip`` (3 outputs): 0.5. ``sigmoid`` (3 outputs): 0 (sigmoid(0) = 0.5).
    """
    bias = np.zeros(out_channels, np.float32)
    if head == "f_act" and out_channels == 9:
        bias[0:3] = 0.5
        bias[6:9] = 1.0
    elif head == "clip":
        bias[:] = 0.5
    return bias


class ResidualBlock(nn.Module):
    """``ReLU(x + conv_b(ReLU(conv_a(x))))`` with two 3x3 convolutions of ``width`` filters."""

    width: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        h = nn.relu(nn.Conv(self.width, (3, 3), padding="SAME", name="conv_a")(x))
        h = nn.Conv(self.width, (3, 3), padding="SAME", name="conv_b")(h)
        return nn.relu(x + h)


class PDNet(nn.Module):
    """The mixer network: (..., H, W, C_in) -> raw outputs (..., H, W, out_channels).

    Attributes:
      width: feature channels of every hidden layer (48 in the paper).
      out_channels: 9 for the f_act head, 3 for the direct-alpha ablation.
      head: the alpha head the output feeds (only used for the initial output bias).
      centred_head: initialise the output bias with :func:`head_bias` (else zeros).
      num_blocks: residual blocks (2 in the paper).

    Parameter names are fixed (``conv_in``, ``block_0``, ``block_1``, ``conv_out``) so that
    checkpoints and released weights keep one layout.
    """

    width: int = 48
    out_channels: int = 9
    head: str = "f_act"
    centred_head: bool = True
    num_blocks: int = 2

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        h = nn.relu(nn.Conv(self.width, (5, 5), padding="SAME", name="conv_in")(x))
        for index in range(self.num_blocks):
            h = ResidualBlock(self.width, name=f"block_{index}")(h)
        if self.centred_head:
            bias = head_bias(self.out_channels, self.head)
            bias_init = lambda key, shape, dtype=jnp.float32: jnp.asarray(bias, dtype)
        else:
            bias_init = nn.initializers.zeros
        return nn.Conv(
            self.out_channels, (3, 3), padding="SAME", bias_init=bias_init, name="conv_out"
        )(h)


# ------------------------------------------------------------------ the mixer networks
@dataclasses.dataclass(frozen=True)
class MixerNetwork:
    """A mixer network, by name (``MixerConfig.network``).

    ``build(config) -> flax module`` mapping the mixer inputs (..., H, W,
    ``config.in_channels``) to raw outputs (..., H, W, ``config.out_channels``), which the
    config's head turns into alpha; ``radius``: the pixels each side that one output reads
    (so frames can run over tiles). Everything around it (input features, head, SURE cache,
    training task, checkpoints, t-statistic) is the mixer's own."""

    name: str
    build: Callable[[MixerConfig], nn.Module]
    radius: int
    description: str = ""


#: Every mixer network by name: the paper's PDNet and those of plugins.
MIXER_NETWORKS: Registry = Registry("mixer network")
_REGISTER_PLUMBING = True  # registrations through this module belong to their caller


def register_mixer_network(network: MixerNetwork, *, owner: str | None = None) -> MixerNetwork:
    """Add a mixer network (then ``model_config.network = NAME`` in a mixer's config); a
    name that jaxden or another module holds is refused in one line."""
    from jaxden.registry import caller_module

    if not isinstance(network, MixerNetwork) or not (
            isinstance(network.radius, int) and network.radius >= 0):
        raise ConfigError(f"register_mixer_network() takes a MixerNetwork with an int radius "
                          f">= 0, got {network!r}")
    return MIXER_NETWORKS.add(network.name, network, owner or caller_module())


def get_mixer_network(name: str) -> MixerNetwork:
    """The mixer network ``name`` (plugins named by ``JAXDEN_PLUGINS`` or entry points are
    imported first); ConfigError naming the registered ones otherwise."""
    if MIXER_NETWORKS.find(name) is None:
        raise ConfigError(f"MixerConfig.network: unknown mixer network {name!r}; registered: "
                          f"{', '.join(MIXER_NETWORKS)} (a network of your own: "
                          f"register_mixer_network in a plugin module, docs/your-denoiser.md)")
    return MIXER_NETWORKS[name]


def _pdnet(config: MixerConfig) -> PDNet:
    return PDNet(width=config.width, out_channels=config.out_channels, head=config.head,
                 centred_head=config.centred_head)


#: conv_in 5x5, two residual blocks of two 3x3 convolutions, conv_out 3x3
PDNET_RADIUS = 2 + 2 * 2 + 1
register_mixer_network(MixerNetwork("pdnet", _pdnet, PDNET_RADIUS,
                                    "the paper's PDNet (Fig. 6)"), owner=__name__)


# ------------------------------------------------------------------------------ the mixer

def mixer_module(config: MixerConfig):
    """The flax module of ``config.network`` (:class:`PDNet` by default) for ``config``."""
    return get_mixer_network(config.network).build(config)


_INIT_CHUNK = 1 << 16


@jax.jit
def _normal_chunk(key, index):
    # One fixed shape: XLA:CPU compiles a threefry draw in ~1.5 s, once per shape; a flax
    # init compiles one per parameter shape (seconds for PDNet).
    return jax.random.normal(jax.random.fold_in(key, index), (_INIT_CHUNK,), jnp.float32)


def mixer_init(key, config: MixerConfig | None = None):
    """Fresh mixer parameters (a pytree) for ``config`` (None: ``MixerConfig()``).

    Kernels are LeCun-normal, ``N(0, 1 / fan_in)`` (fan_in = k * k * C_in; flax's default is a
    truncated variant), the output kernel times ``config.init_output_scale``; biases zero
    except the output bias (:func:`jaxden.progressive.network.head_bias` when ``centred_head``). The
    values come from one flat standard-normal sequence drawn in fixed-size chunks of ``key``
    (so initialising any config reuses one compiled draw) and are assigned to the kernels in
    parameter-path order. Same structure as ``PDNet.init``.
    """
    config = MixerConfig() if config is None else config
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
    """:func:`mixer_alpha` of checked float32 arrays, averaged with 1 - alpha of the swapped
    call when ``swap_average`` (see :class:`MixerConfig`)."""
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
