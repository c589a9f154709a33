"""The Denoiser protocol and registry.

Every denoiser is ``denoise(params, frame) -> (..., H, W, 3)`` linear radiance, chosen by name
and a frozen config dataclass. JAX denoisers are pure and differentiable (SURE takes their jvp);
black-box denoisers (OIDN through pyoidn) are NumPy in, NumPy out, and SURE uses finite
differences for them.

>>> den = make_denoiser("oidn")               # ready to call: den(frame) -> image
>>> den = make_denoiser("unet", key=key)      # freshly initialised parameters
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
import os
from pathlib import Path
from typing import Any, Literal

import jax
import numpy as np

from jaxden.errors import CheckpointError, ConfigError, FrameError
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
    _load_builtin_models()
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
        from jaxden.nn.layers import reparameterize

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


# ------------------------------------------------------------------------------------- OIDN
@dataclasses.dataclass(frozen=True)
class OIDNConfig:
    """Intel Open Image Denoise (pyoidn, CPU, built-in weights).

    ``use_albedo`` / ``use_normal`` pass the auxiliary features when the frame has them.
    ``clean_aux`` is OIDN's ``cleanAux`` flag (the features are noise-free): ``"yes"``
    (default), ``"no"``, or ``"auto"``: yes for frames of at least ``clean_aux_min_spp``
    samples per pixel (or of unknown spp), no below. Features average min(spp, feature_spp)
    samples, so at 2-4 spp they are noisy, but telling OIDN so is no reliable gain: on the 8
    crops of data/test "no" lowers OIDN's RMSE by 18 % at 2 spp and 9 % at 4 spp, while on
    the built-in scenes at 2-8 spp it ranges from 0.63x to 4.6x in relMSE (small-lights:
    far worse); from 16 spp up "yes" wins (docs/results.md, "OIDN's auxiliary features").
    """

    quality: Literal["high", "balanced", "fast"] = "high"
    use_albedo: bool = True
    use_normal: bool = True
    clean_aux: Literal["auto", "yes", "no"] = "yes"
    clean_aux_min_spp: int = 8

    def __post_init__(self) -> None:
        if self.clean_aux not in ("auto", "yes", "no"):
            raise ConfigError(f"OIDN clean_aux must be auto, yes or no, got {self.clean_aux!r}")
        if self.clean_aux_min_spp < 1:
            raise ConfigError(f"OIDN clean_aux_min_spp must be >= 1, got "
                              f"{self.clean_aux_min_spp}")

    def features_are_clean(self, spp) -> bool:
        """Whether to pass cleanAux for a frame of ``spp`` samples per pixel (None: unknown)."""
        if self.clean_aux != "auto":
            return self.clean_aux == "yes"
        return spp is None or float(spp) >= self.clean_aux_min_spp


def _oidn_one(config: OIDNConfig, color, albedo, normal, clean: bool) -> np.ndarray:
    import pyoidn

    color = np.ascontiguousarray(np.maximum(np.asarray(color, np.float32), 0.0))
    if normal is not None and albedo is None:
        # OIDN's RT filter accepts normals only together with albedo.
        normal = None
    return pyoidn.denoise(
        color,
        None if albedo is None else np.ascontiguousarray(np.clip(albedo, 0, 1), np.float32),
        None if normal is None else np.ascontiguousarray(np.clip(normal, -1, 1), np.float32),
        hdr=True,
        clean_aux=clean and albedo is not None,
        quality=config.quality,
    )


def oidn_apply(params: None, config: OIDNConfig, frame: Frame) -> np.ndarray:
    """Denoise with OIDN; NumPy in and out; batch dimensions are looped over."""
    color = np.asarray(frame.color, np.float32)
    if color.ndim < 3 or color.shape[-1] != 3:
        raise FrameError(f"OIDN needs colour of shape (..., H, W, 3), got {color.shape}")
    albedo = frame.albedo if config.use_albedo else None
    normal = frame.normal if config.use_normal else None
    batch = color.shape[:-3]
    flat = color.reshape((-1,) + color.shape[-3:])
    out = np.empty_like(flat)

    def flat_aux(aux):
        return None if aux is None else np.asarray(aux, np.float32).reshape(flat.shape)

    albedo, normal = flat_aux(albedo), flat_aux(normal)
    spp = (None,) * flat.shape[0] if frame.spp is None else np.broadcast_to(
        np.asarray(frame.spp, np.float64), batch).reshape(-1)
    for i in range(flat.shape[0]):
        out[i] = _oidn_one(
            config, flat[i], None if albedo is None else albedo[i],
            None if normal is None else normal[i], config.features_are_clean(spp[i]),
        )
    return out.reshape(batch + color.shape[-3:])


register(
    DenoiserDef(
        name="oidn",
        description="Intel Open Image Denoise 2 (pyoidn, CPU, pretrained; black box)",
        config_cls=OIDNConfig,
        required=lambda config: ("color",),
        apply=oidn_apply,
        differentiable=False,
    )
)


# ------------------------------------------------------------------------------------ U-Net
@dataclasses.dataclass(frozen=True)
class UNetConfig:
    """The progressive-denoising paper's U-Net; ``features`` from hdr, var, alb, nrm."""

    features: tuple[str, ...] = ("hdr", "alb", "nrm", "var")
    encoder_widths: tuple[int, ...] = (32, 48, 64, 80, 96)
    decoder_widths: tuple[int, ...] = (112, 96, 64, 64, 32)


def _unet_module(config: UNetConfig):
    from jaxden.nn.unet import UNet

    return UNet(tuple(config.encoder_widths), tuple(config.decoder_widths))


def _unet_init(key, config: UNetConfig):
    from jaxden.nn.unet import check_features

    features = check_features(config.features)
    sample = jax.numpy.zeros((1, 16, 16, 3 * len(features)), jax.numpy.float32)
    return _unet_module(config).init(key, sample)


def _unet_apply(params, config: UNetConfig, frame: Frame):
    from jaxden.nn.unet import unet_denoise

    return unet_denoise(_unet_module(config), params, frame, config.features)


def _unet_required(config: UNetConfig) -> tuple[str, ...]:
    from jaxden.nn.unet import FEATURE_FIELDS, check_features

    return tuple(FEATURE_FIELDS[f] for f in check_features(config.features))


register(
    DenoiserDef(
        name="unet",
        description="U-Net of OIDN / the progressive-denoising paper (trainable, JAX)",
        config_cls=UNetConfig,
        required=_unet_required,
        apply=_unet_apply,
        init=_unet_init,
    )
)


WEIGHTS_DIR = Path(__file__).parent / "weights"


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


def _load_builtin_models() -> None:
    """Import modules that register further denoisers (kept lazy to keep imports light)."""
    import importlib

    for module in ("jaxden.models",):
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as error:
            if error.name != module:
                raise
