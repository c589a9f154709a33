"""The Denoiser protocol and registry.

Every denoiser is ``denoise(params, frame) -> (..., H, W, 3)`` linear radiance, chosen by name
and a frozen config dataclass. JAX denoisers are pure and differentiable (SURE takes their jvp);
black-box denoisers (OIDN through pyoidn) are NumPy in, NumPy out, and SURE uses finite
differences for them.

>>> den = make_denoiser("oidn")               # ready to call: den(frame) -> image
>>> den = make_denoiser("unet", key=key)      # freshly initialised parameters

The registered denoisers live beside this module (:mod:`jaxden.denoise.oidn`,
:mod:`jaxden.denoise.models`); the package imports them, so any import of
``jaxden.denoise...`` sees every name.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from jaxden.errors import CheckpointError, ConfigError
from jaxden.frame import Frame


@dataclasses.dataclass(frozen=True)
class DenoiserDef:
    """A registry entry.

    ``init(key, config) -> params`` (None for black boxes);
    ``apply(params, config, frame) -> image`` (pure JAX unless ``differentiable`` is False);
    ``required(config) -> field names`` the frame must carry.
    """

    name: str
    description: str
    config_cls: type
    required: Callable[[Any], tuple[str, ...]]
    apply: Callable[[Any, Any, Frame], Any]
    init: Callable[[jax.Array, Any], Any] | None = None
    differentiable: bool = True


REGISTRY: dict[str, DenoiserDef] = {}


def register(definition: DenoiserDef) -> DenoiserDef:
    REGISTRY[definition.name] = definition
    return definition


def get_definition(name: str) -> DenoiserDef:
    if name not in REGISTRY:
        raise ConfigError(
            f"unknown denoiser {name!r}; registered denoisers: {', '.join(sorted(REGISTRY))}"
        )
    return REGISTRY[name]


@dataclasses.dataclass
class Denoiser:
    """A definition with its config and parameters: call it on a Frame."""

    definition: DenoiserDef
    config: Any
    params: Any = None

    @property
    def name(self) -> str:
        return self.definition.name

    @property
    def differentiable(self) -> bool:
        return self.definition.differentiable

    def check_frame(self, frame: Frame) -> None:
        frame.require(*self.definition.required(self.config), who=f"denoiser '{self.name}'")

    @functools.cached_property
    def _jitted(self):
        definition, config = self.definition, self.config
        return jax.jit(lambda params, frame: definition.apply(params, config, frame))

    def function(self) -> Callable[[Frame], Any]:
        """``frame -> image`` with parameters bound (what SURE and the mixer pipeline take)."""
        if not self.differentiable:
            return lambda frame: self.definition.apply(self.params, self.config, frame)
        return functools.partial(self._jitted, self.params)

    def __call__(self, frame: Frame):
        self.check_frame(frame)
        return self.function()(frame)

    def deployed(self) -> Denoiser:
        """The inference form: RepVGG blocks folded into single 5x5 convolutions (same outputs
        to float round-off, fewer operations). Models without RepVGG blocks are returned as is."""
        if getattr(self.config, "deploy", None) is not False:
            return self  # no RepVGG blocks, or already deployed
        from jaxden.denoise.nn.layers import reparameterize

        return Denoiser(self.definition, dataclasses.replace(self.config, deploy=True),
                        reparameterize(self.params))


def make_denoiser(
    name: str, config: Any = None, params: Any = None, *, key: jax.Array | None = None
) -> Denoiser:
    """Build a registered denoiser; initialise parameters from ``key`` when none are given."""
    definition = get_definition(name)
    if config is None:
        config = definition.config_cls()
    elif not isinstance(config, definition.config_cls):
        raise ConfigError(
            f"denoiser '{name}' takes a {definition.config_cls.__name__}, got "
            f"{type(config).__name__}"
        )
    if params is None and definition.init is not None:
        params = definition.init(key if key is not None else jax.random.PRNGKey(0), config)
    return Denoiser(definition, config, params)


WEIGHTS_DIR = Path(__file__).parent.parent / "weights"


def load_denoiser(spec: str | os.PathLike) -> Denoiser:
    """A ready denoiser from a name or trained weights.

    ``spec``: a registered black-box name (``oidn``); a name with weights shipped in the
    package (``jaxden/weights/<name>.msgpack``); a training workdir or checkpoint folder from
    ``jaxden train``; or a released ``.msgpack`` weights file. The checkpoint's meta record
    says which model and config it holds; a mixer checkpoint or an unknown model is a
    CheckpointError.
    """
    from jaxden.checkpoint import load_trained_params, read_checkpoint_meta
    from jaxden.config import load_config

    path = Path(spec)
    shipped = WEIGHTS_DIR / f"{spec}.msgpack"
    if not path.exists() and isinstance(spec, str) and shipped.is_file():
        path = shipped
    if not path.exists():
        definition = get_definition(str(spec))
        if definition.init is not None:
            raise CheckpointError(
                f"denoiser '{spec}' needs trained weights: pass a checkpoint folder from "
                f"`jaxden train` (or a .msgpack weights file) instead of its name"
            )
        return make_denoiser(str(spec))
    meta = read_checkpoint_meta(path)
    if meta.get("kind") != "denoiser":
        raise CheckpointError(
            f"{path}: holds a {meta.get('kind', 'unknown')!r} checkpoint "
            f"(model {meta.get('model')!r}), not a denoiser"
        )
    try:
        definition = get_definition(meta.get("model", "?"))
    except ConfigError as error:
        raise CheckpointError(f"{path}: its meta record names model {meta.get('model')!r}: "
                              f"{error}") from None
    try:
        config = load_config(meta.get("model_config", {}), definition.config_cls)
    except ConfigError as error:
        raise CheckpointError(f"{path}: its model_config does not fit '{definition.name}': {error}") from None
    # Only structure and shapes are needed: eval_shape skips the (seconds-long) init.
    target = jax.eval_shape(lambda: definition.init(jax.random.PRNGKey(0), config))
    params, _ = load_trained_params(path, target, expect={"model": definition.name})
    return Denoiser(definition, config, params)
