"""From the mixer network's raw outputs to the mixing weight alpha: the paper's f_act (Eq. 19),
the direct sigmoid/clip heads of the "w/o f_act" ablation, the bounded closed-form-logit head,
and the mix z = x + alpha (y - x).
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.checks import check_image, check_same

# ---------------------------------------------------------------------------------- alpha

#: Raw output channels per alpha head: the paper's f_act (3 values per colour channel), the
#: "w/o f_act" ablation where the network predicts alpha directly, and ``closed_form_logit``
#: (our addition): a correction to the closed-form alpha in logit space,
#: alpha = sigmoid(logit(alpha_cf) + raw), so an output of 0 is Eq. 9 with local means.
ALPHA_HEADS: dict[str, int] = {"f_act": 9, "sigmoid": 3, "clip": 3, "closed_form_logit": 3}

#: alpha_cf is clipped to [eps, 1 - eps] before its logit in the ``closed_form_logit`` head.
CLOSED_FORM_LOGIT_EPS = 1e-3


@functools.partial(jax.jit, static_argnames=("grouping",))
def f_act_unchecked(raw, eps, grouping):
    if grouping == "by_role":
        x1, x2, x3 = raw[..., 0:3], raw[..., 3:6], raw[..., 6:9]
    else:
        x1, x2, x3 = raw[..., 0::3], raw[..., 1::3], raw[..., 2::3]
    return jnp.clip((x1 - x2) / jnp.maximum(x3, eps), 0.0, 1.0)


def f_act(raw, eps: float = 1e-6, *, grouping: Literal["by_role", "by_channel"] = "by_role"):
    """Paper Eq. 19 with the authors' clip: alpha = clip((x1 - x2) / max(x3, eps), 0, 1).

    ``raw``: (..., H, W, 9) network outputs; returns alpha (..., H, W, 3), one per colour
    channel. Grouping of the 9 channels (our choice; for a trained network it only permutes
    the last layer's filters, it matters when importing foreign weights):

    - ``"by_role"`` (default): [x1_R, x1_G, x1_B, x2_R, x2_G, x2_B, x3_R, x3_G, x3_B];
    - ``"by_channel"``: [x1_R, x2_R, x3_R, x1_G, x2_G, x3_G, x1_B, x2_B, x3_B].

    Mirrors Eqs. 9-10: alpha is a difference of two quantities over a third. Note
    ``max(x3, eps)`` has zero gradient w.r.t. x3 below eps and the clip zero gradient outside
    [0, 1] (as in the authors' code).
    """
    check_image("raw", raw, "f_act", channels=(9,))
    if grouping not in ("by_role", "by_channel"):
        raise ConfigError(f"f_act: grouping must be 'by_role' or 'by_channel', got {grouping!r}")
    if not (isinstance(eps, (int, float, np.floating)) and math.isfinite(eps) and eps > 0):
        raise ConfigError(f"f_act: eps must be > 0, got {eps!r}")
    return f_act_unchecked(jnp.asarray(raw), eps, grouping)


def alpha_direct(raw, kind: Literal["sigmoid", "clip"] = "sigmoid"):
    """"w/o f_act" ablation (paper Table 4): alpha from 3 raw outputs, (..., H, W, 3).

    ``"sigmoid"``: alpha = sigmoid(raw); ``"clip"``: alpha = clip(raw, 0, 1). The paper does
    not say which squashing its ablation used; sigmoid is the default (nonzero gradient).
    """
    check_image("raw", raw, "alpha_direct")
    raw = jnp.asarray(raw)
    if kind == "sigmoid":
        return jax.nn.sigmoid(raw)
    if kind == "clip":
        return jnp.clip(raw, 0.0, 1.0)
    raise ConfigError(f"alpha_direct: kind must be 'sigmoid' or 'clip', got {kind!r}")


def alpha_from_head(raw, head: str = "f_act", eps: float = 1e-6):
    """alpha from the network's raw output for a head of :data:`ALPHA_HEADS`."""
    if head == "f_act":
        return f_act(raw, eps)
    if head in ("sigmoid", "clip"):
        return alpha_direct(raw, head)
    if head == "closed_form_logit":
        raise ConfigError("the closed_form_logit head needs the closed-form alpha of the "
                          "inputs: use mixer_alpha (or closed_form_logit_alpha)")
    raise ConfigError(f"unknown alpha head {head!r}; allowed: {', '.join(ALPHA_HEADS)}")


def closed_form_logit_alpha(raw, alpha_cf, bound: float | None = None,
                            eps: float = CLOSED_FORM_LOGIT_EPS):
    """The ``closed_form_logit`` head: sigmoid(logit(clip(alpha_cf, eps, 1 - eps)) + c).

    ``raw`` (..., H, W, 3) network outputs, ``alpha_cf`` (..., H, W, 1 or 3) from
    :func:`closed_form_alpha`; returns (..., H, W, 3) in (0, 1). The correction is c = raw,
    or with a ``bound`` B, c = B tanh(raw / B): the logit then never moves more than B from
    Eq. 9's (a trust region around the closed form; slope 1 at raw = 0). Swap-consistent:
    logit(1 - a) = -logit(a) and the bound is odd, so the swapped inputs (whose closed form is
    exactly 1 - alpha_cf) see the same correction problem with the sign flipped.
    """
    a = jnp.clip(jnp.asarray(alpha_cf), eps, 1.0 - eps)
    correction = jnp.asarray(raw)
    if bound is not None:
        correction = bound * jnp.tanh(correction / bound)
    return jax.nn.sigmoid(jnp.log(a) - jnp.log1p(-a) + correction)


@jax.jit
def mix_unchecked(x, y, alpha):
    return x + alpha * (y - x)


def mix(x, y, alpha):
    """z = x + alpha * (y - x); x, y (..., H, W, 3), alpha broadcastable (..., H, W, 1 or 3)."""
    shape = check_same("mix", x=x, y=y)
    alpha_shape = check_image("alpha", alpha, "mix", channels=(1, 3))
    if alpha_shape[:-1] != shape[:-1]:
        raise FrameError(f"mix: 'alpha' has shape {alpha_shape} but x has {shape}")
    return mix_unchecked(jnp.asarray(x), jnp.asarray(y), jnp.asarray(alpha))
