"""RepVGG-style blocks (Ding et al. 2021) as used by WSKP's ImportanceNet (Fan et al. 2021, 4.1).

Training time, :class:`RepVGGBlock`::

    y = act(conv5x5(x) + conv3x3(x) + conv1x1(x) [+ x])

with zero ("SAME") padding, no bias and no batch norm (as in the WSKP authors' code; the original
RepVGG has a batch norm per branch), the identity branch only when input and output widths are
equal, and ``act`` a LeakyReLU with slope 0.1 (the authors' code; the paper's text says ReLU).
The activation can be switched off for a network's last layer.

Deploy time, :class:`RepVGGDeployBlock`: ``y = act(conv5x5'(x))`` with the single kernel from
:func:`reparameterize_block`: the 3x3 and 1x1 kernels zero-padded to 5x5 and added to the 5x5
kernel, and the identity added as a centre tap ``K[2, 2, i, i] += 1``. With zero padding this is
exactly the same linear map (an out-of-image tap of the padded kernels is zero in both), so the
two blocks agree to float round-off.

Parameter trees: a training block holds ``{"branch_5x5": {"kernel": (5, 5, in, out)},
"branch_3x3": {"kernel": (3, 3, in, out)}, "branch_1x1": {"kernel": (1, 1, in, out)}}``; a deploy
block ``{"conv_5x5": {"kernel": (5, 5, in, out)}}``. :func:`reparameterize` maps a whole model's
params by replacing every training-block subtree; for the result to fit the deploy model, the
parent module must give each block the same explicit ``name`` in both modes (linen's automatic
names contain the class name, which differs).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import flax.linen as nn
import jax.numpy as jnp

from jaxden.errors import ConfigError

BRANCHES: dict[str, int] = {"branch_5x5": 5, "branch_3x3": 3, "branch_1x1": 1}
DEPLOY_CONV = "conv_5x5"


def _identity_enabled(use_identity: bool | None, in_features: int, out_features: int,
                      where: str) -> bool:
    if use_identity is None:
        return in_features == out_features
    if use_identity and in_features != out_features:
        raise ConfigError(
            f"{where}: use_identity=True needs equal input and output widths, got "
            f"{in_features} -> {out_features}"
        )
    return bool(use_identity)


class RepVGGBlock(nn.Module):
    """Training-time multi-branch block. Input (..., H, W, C_in) -> output (..., H, W, features).

    Attributes:
      features: output channels.
      use_identity: add the input (identity branch); ``None`` = exactly when C_in == features.
      negative_slope: LeakyReLU slope (0.1 in the authors' code).
      activation: apply the LeakyReLU (switch off for a network's last layer).
      kernel_init: initialiser of each branch's kernel.
    """

    features: int
    use_identity: bool | None = None
    negative_slope: float = 0.1
    activation: bool = True
    kernel_init: Callable[..., Any] = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(self, x):
        y = None
        for name, size in BRANCHES.items():
            branch = nn.Conv(
                self.features, (size, size), padding="SAME", use_bias=False,
                kernel_init=self.kernel_init, name=name,
            )(x)
            y = branch if y is None else y + branch
        if _identity_enabled(self.use_identity, x.shape[-1], self.features, "RepVGGBlock"):
            y = y + x
        return nn.leaky_relu(y, self.negative_slope) if self.activation else y


class RepVGGDeployBlock(nn.Module):
    """Deploy-time block: one 5x5 conv (no bias) + optional LeakyReLU; see module docstring."""

    features: int
    negative_slope: float = 0.1
    activation: bool = True
    kernel_init: Callable[..., Any] = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(self, x):
        y = nn.Conv(
            self.features, (5, 5), padding="SAME", use_bias=False,
            kernel_init=self.kernel_init, name=DEPLOY_CONV,
        )(x)
        return nn.leaky_relu(y, self.negative_slope) if self.activation else y


def _is_training_block(tree: Any) -> bool:
    return isinstance(tree, Mapping) and set(BRANCHES) <= set(tree)


def reparameterize_block(block_params: Mapping, use_identity: bool | None = None) -> dict:
    """Merge one :class:`RepVGGBlock`'s params into :class:`RepVGGDeployBlock` params.

    Pure (jit-able). ``block_params`` is the block's subtree ``{"branch_5x5": ..., ...}``, or
    ``{"params": {...}}`` as returned by ``RepVGGBlock.init`` (the result then has the same
    wrapping). ``use_identity`` must match the block's attribute (``None`` = C_in == C_out).
    """
    if set(block_params) == {"params"}:
        return {"params": reparameterize_block(block_params["params"], use_identity)}
    if not _is_training_block(block_params):
        raise ConfigError(
            f"reparameterize_block: expected a RepVGGBlock param tree with keys "
            f"{sorted(BRANCHES)}, got keys {sorted(block_params)}"
        )
    kernel = None
    for name, size in BRANCHES.items():
        branch = jnp.asarray(block_params[name]["kernel"])
        if branch.shape[:2] != (size, size):
            raise ConfigError(
                f"reparameterize_block: {name} kernel must be ({size}, {size}, in, out), got "
                f"{branch.shape}"
            )
        pad = (5 - size) // 2  # centre the smaller kernel in the 5x5 one
        branch = jnp.pad(branch, [(pad, pad), (pad, pad), (0, 0), (0, 0)])
        if kernel is not None and branch.shape != kernel.shape:
            raise ConfigError(
                f"reparameterize_block: branch widths differ: {name} is {branch.shape[2:]}, "
                f"expected {kernel.shape[2:]}"
            )
        kernel = branch if kernel is None else kernel + branch
    in_features, out_features = kernel.shape[2], kernel.shape[3]
    if _identity_enabled(use_identity, in_features, out_features, "reparameterize_block"):
        kernel = kernel.at[2, 2].add(jnp.eye(in_features, dtype=kernel.dtype))
    return {DEPLOY_CONV: {"kernel": kernel}}


def reparameterize(
    params: Mapping, use_identity: bool | None | Mapping[str, bool | None] = None
) -> dict:
    """Replace every :class:`RepVGGBlock` subtree of a model's params by deploy params.

    Pure: params -> params (any other leaves are passed through unchanged).

    Args:
      params: a params tree (e.g. ``model.init(...)``), possibly nested modules.
      use_identity: ``None`` (each block's default: identity iff C_in == C_out), one bool for
        all blocks, or a mapping from a block's path (module names joined by ``/``, without the
        ``params`` collection, e.g. ``"encoder/block_2"``) to its setting; blocks not in the
        mapping use ``None``. It must match how the training model was built.

    Returns:
      The params tree for the same model built with :class:`RepVGGDeployBlock` (same names).
    """

    def setting(path: tuple[str, ...]):
        if isinstance(use_identity, Mapping):
            return use_identity.get("/".join(p for p in path if p != "params"))
        return use_identity

    def walk(tree, path):
        if _is_training_block(tree):
            return reparameterize_block(tree, setting(path))
        if isinstance(tree, Mapping):
            return {key: walk(value, path + (str(key),)) for key, value in tree.items()}
        return tree

    return walk(params, ())


__all__ = [
    "RepVGGBlock",
    "RepVGGDeployBlock",
    "reparameterize",
    "reparameterize_block",
]
