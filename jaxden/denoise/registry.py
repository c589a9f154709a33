"""The Denoiser protocol and registry.

Every denoiser is ``denoise(params, frame) -> (..., H, W, 3)`` linear radiance, chosen by name
and a frozen config dataclass. JAX denoisers are pure and differentiable (SURE takes their jvp);
black-box denoisers (OIDN through pyoidn) are NumPy in, NumPy out, and SURE uses finite
differences for them.

>>> den = make_denoiser("oidn")               # ready to call: den(frame) -> image
>>> den = make_denoiser("unet", key=key)      # freshly initialised parameters
>>> den = load_denoiser("wskp-6:emission=separate")   # a spec with options

A spec ``SPEC:KEY=VALUE,...`` takes options after the last colon: those of
:data:`DENOISER_OPTIONS`, for every denoiser: ``emission=separate`` keeps the directly visible
emission (``Frame.emission``) out of the filter, ``D(colour - emission) + emission``
(:mod:`jaxden.denoise.emission`); ``emission=filter`` is the default; and a registered
denoiser's own (``DenoiserDef.options``), e.g. OIDN's inputs, quality and precision:
``oidn-jax:aux=albedo,quality=balanced,precision=bfloat16``, ``oidn:quality=fast``.

The registered denoisers live beside this module (:mod:`jaxden.denoise.oidn`,
:mod:`jaxden.denoise.models`); the package imports them, so any import of
``jaxden.denoise...`` sees every name. Training sees them, beside the mixer, through the table
of trainable models (:func:`jaxden.train.tasks.trainables`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from jaxden.denoise.emission import EMISSION_MODES, separated_apply, separated_step
from jaxden.errors import CheckpointError, ConfigError
from jaxden.frame import Frame
from jaxden.paths import WEIGHTS_DIR, resolve_weights, shipped_weights_file
from jaxden.registry import Registry

#: Options of a denoiser spec ``SPEC:KEY=VALUE,...`` -> their values (the first: the default).
DENOISER_OPTIONS: dict[str, tuple[str, ...]] = {"emission": EMISSION_MODES}


@dataclasses.dataclass(frozen=True)
class DenoiserDef:
    """A registry entry.

    ``init(key, config) -> params`` (None for black boxes);
    ``apply(params, config, frame) -> image`` (pure JAX unless ``differentiable`` is False);
    ``required(config) -> field names`` the frame must carry; ``pretrained``: ``init``
    returns trained weights (OIDN in JAX reads Intel's), so the name alone loads it;
    ``tiling(config) -> TileSpec | None``: its receptive field and alignment, so frames can
    run over tiles (:mod:`jaxden.tiling`); None: whole frames only; ``optional(config)``: the
    fields it uses when a frame has them (OIDN's albedo and normal); ``options``: its own
    spec options ``((KEY, (VALUE, ...)), ...)``, the first value the default, and
    ``configure(config, {KEY: VALUE}) -> config`` applies them (:func:`with_options`).
    ``step(params, config, state, frame) -> (image, state)``: a temporal method's form over a
    sequence (``state`` None before the first frame; the frames of one sequence share their
    size): SVGF, BMFR; ``apply`` is then its single-frame (spatial) part. None: frames are
    independent (:meth:`Denoiser.sequence` runs ``apply`` on each).
    """

    name: str
    description: str
    config_cls: type
    required: Callable[[Any], tuple[str, ...]]
    apply: Callable[[Any, Any, Frame], Any]
    init: Callable[[jax.Array, Any], Any] | None = None
    differentiable: bool = True
    pretrained: bool = False  # init gives trained weights (read, not drawn): usable by name
    tiling: Callable[[Any], Any] | None = None
    optional: Callable[[Any], tuple[str, ...]] | None = None  # fields used when present
    options: tuple[tuple[str, tuple[str, ...]], ...] = ()
    configure: Callable[[Any, dict[str, str]], Any] | None = None
    step: Callable[[Any, Any, Any, Frame], tuple[Any, Any]] | None = None


#: Every denoiser by name: jaxden's own and those of plugins (:mod:`jaxden.plugins`).
REGISTRY: Registry = Registry("denoiser")
_REGISTER_PLUMBING = True  # registrations through this module belong to their caller


def register(definition: DenoiserDef, *, owner: str | None = None) -> DenoiserDef:
    """Add ``definition`` to the registry under its name; ``owner``: the registering module
    (default: the caller's). A name that jaxden or another module already holds is refused
    (:class:`jaxden.registry.PluginClashError`)."""
    from jaxden.registry import caller_module

    if not isinstance(definition, DenoiserDef):
        raise ConfigError(f"register() takes a DenoiserDef (or use Denoiser.from_function), "
                          f"got {type(definition).__name__}")
    owner = owner or caller_module()
    if shipped_weights_file(definition.name) is not None:
        from jaxden.registry import PluginClashError

        raise PluginClashError(f"denoiser name {definition.name!r} from module '{owner}' "
                               f"clashes with jaxden's shipped weights {definition.name!r}; "
                               f"register it under another name")
    return REGISTRY.add(definition.name, definition, owner)


def get_definition(name: str) -> DenoiserDef:
    """The registered denoiser ``name`` (plugins named by ``JAXDEN_PLUGINS`` or entry points
    are imported first); ConfigError listing the names if there is none."""
    if REGISTRY.find(name) is None:
        raise ConfigError(
            f"unknown denoiser {name!r}; registered denoisers: {', '.join(sorted(REGISTRY))}"
            + ("" if REGISTRY.from_plugins() else
               " (a denoiser of your own: name its module with --plugin or JAXDEN_PLUGINS, "
               "docs/your-denoiser.md)")
        )
    return REGISTRY[name]


@dataclasses.dataclass(frozen=True)
class FunctionConfig:
    """The config of a denoiser made from a function (:meth:`Denoiser.from_function`): none."""


def _function_name(fn) -> str:
    name = getattr(fn, "__name__", "") or type(fn).__name__
    return "function" if name == "<lambda>" else name.replace("_", "-")


@dataclasses.dataclass
class Denoiser:
    """A definition with its config and parameters: call it on a Frame."""

    definition: DenoiserDef
    config: Any
    params: Any = None
    #: the features its training data had (:class:`jaxden.data.features.FeatureRecord`,
    #: from its checkpoint's meta record); None: not recorded
    trained_features: Any = None

    @classmethod
    def from_function(
        cls,
        fn: Callable[..., Any],
        *,
        name: str | None = None,
        needs: tuple[str, ...] = (),
        optional: tuple[str, ...] = (),
        params: Any = None,
        differentiable: bool = True,
        radius: int | None = None,
        multiple: int = 1,
        description: str = "",
        register: bool = False,
    ) -> Denoiser:
        """A denoiser from a plain function, usable wherever a registered one is (SURE,
        progressive denoising, tiling, evaluators, the CLI once registered).

        ``fn(frame) -> (..., H, W, 3)`` linear radiance, or ``fn(params, frame)`` when
        ``params`` is given (a pytree of its weights, which SURE caches hash). ``needs``:
        the Frame fields it requires besides colour (checked before it runs, e.g.
        ``("albedo", "normal")``); ``optional``: fields it uses when present;
        ``differentiable``: a pure JAX function (SURE by ``jax.jvp``), else NumPy in,
        NumPy out (SURE by finite differences); ``radius``: its receptive field in pixels
        (each side), so large frames can run over tiles (``multiple``: the alignment of
        tile origins, e.g. its pooling grid); None: whole frames only. ``name`` (default:
        the function's name, ``_`` as ``-``); ``register``: also add it to the registry
        under that name (:func:`register`; a name clash is refused), so that commands and
        configs find it by name.
        """
        from jaxden.frame import IMAGE_FIELDS

        if not callable(fn):
            raise ConfigError(f"from_function takes a function, got {type(fn).__name__}")
        for field in (*needs, *optional):
            if field not in IMAGE_FIELDS:
                raise ConfigError(f"from_function: {field!r} is not a Frame field; fields: "
                                  f"{', '.join(IMAGE_FIELDS)}")
        with_params = params is not None
        name = name or _function_name(fn)
        tiling = None
        if radius is not None:
            from jaxden.tiling import TileSpec

            if not (isinstance(radius, int) and radius >= 0 and isinstance(multiple, int)
                    and multiple >= 1):
                raise ConfigError(f"from_function: radius must be an int >= 0 and multiple "
                                  f"an int >= 1, got {radius!r}, {multiple!r}")
            spec = TileSpec(radius=radius, multiple=multiple)
            tiling = lambda config: spec
        definition = DenoiserDef(
            name=name,
            description=description or (fn.__doc__ or "").strip().split("\n")[0]
            or f"the function {getattr(fn, '__qualname__', name)}",
            config_cls=FunctionConfig,
            required=lambda config: tuple(needs),
            apply=_bound_apply(fn, with_params),
            init=(lambda key, config: params) if with_params else None,
            differentiable=differentiable,
            pretrained=with_params,
            tiling=tiling,
            optional=(lambda config: tuple(optional)) if optional else None,
        )
        if register:
            from jaxden.registry import caller_module

            globals()["register"](definition, owner=caller_module())
        return cls(definition, FunctionConfig(), params)

    @property
    def name(self) -> str:
        return self.definition.name

    @property
    def differentiable(self) -> bool:
        return self.definition.differentiable

    def tile_spec(self):
        """:class:`jaxden.tiling.TileSpec` of this denoiser, or None (whole frames only). The
        same object every call, so that programs compiled per function (a tile's apply) are
        reused from frame to frame."""
        return self._tile_spec

    @functools.cached_property
    def _tile_spec(self):
        return None if self.definition.tiling is None else self.definition.tiling(self.config)

    def fields_read(self) -> tuple[str, ...]:
        """Every frame field this denoiser reads: required, then used when present."""
        optional = () if self.definition.optional is None else self.definition.optional(
            self.config)
        return (*self.definition.required(self.config), *optional)

    def check_frame(self, frame: Frame) -> None:
        frame.require(*self.definition.required(self.config), who=f"denoiser '{self.name}'")

    @functools.cached_property
    def _jitted(self):
        definition, config = self.definition, self.config
        return jax.jit(lambda params, frame: definition.apply(params, config, frame))

    def function(self) -> Callable[[Frame], Any]:
        """``frame -> image`` with parameters bound (what SURE and the mixer pipeline take).
        The same object every call on this Denoiser, so that functions compiled per function
        object (:func:`jaxden.sure.sure`) compile once."""
        return self._bound

    @functools.cached_property
    def _bound(self) -> Callable[[Frame], Any]:
        if not self.differentiable:
            return lambda frame: self.definition.apply(self.params, self.config, frame)
        return functools.partial(self._jitted, self.params)

    def __call__(self, frame: Frame):
        self.check_frame(frame)
        return self.function()(frame)

    @property
    def temporal(self) -> bool:
        """Whether it has a temporal form (history carried from frame to frame)."""
        return self.definition.step is not None

    @functools.cached_property
    def _jitted_step(self):
        definition, config = self.definition, self.config
        if not self.differentiable:
            return lambda params, state, frame: definition.step(params, config, state, frame)
        return jax.jit(lambda params, state, frame: definition.step(params, config, state, frame))

    def step(self, state, frame: Frame):
        """One frame of a sequence: ``(image, state)``; ``state`` None for the first frame.
        A denoiser without a temporal form returns ``(self(frame), None)``. Compiled once per
        frame size (twice in all: the first frame has no state)."""
        self.check_frame(frame)
        if self.definition.step is None:
            return self.function()(frame), None
        return self._jitted_step(self.params, state, frame)

    def sequence(self, frames) -> list:
        """The images of consecutive frames of one sequence, in order (history carried
        through a temporal form; each frame alone otherwise)."""
        state, images = None, []
        for frame in frames:
            image, state = self.step(state, frame)
            images.append(image)
        return images

    def deployed(self) -> Denoiser:
        """The inference form: RepVGG blocks folded into single 5x5 convolutions (same outputs
        to float round-off, fewer operations). Models without RepVGG blocks are returned as is."""
        if getattr(self.config, "deploy", None) is not False:
            return self  # no RepVGG blocks, or already deployed
        from jaxden.denoise.nn.layers import reparameterize

        return Denoiser(self.definition, dataclasses.replace(self.config, deploy=True),
                        reparameterize(self.params), self.trained_features)


def _bound_apply(fn, with_params: bool):
    """``apply(params, config, frame)`` of a function denoiser; the function's own module
    and name, so that code hashes and messages point at the user's code."""
    if with_params:
        def apply(params, config, frame):
            return fn(params, frame)
    else:
        def apply(params, config, frame):
            return fn(frame)
    apply.__module__ = getattr(fn, "__module__", apply.__module__)
    apply.__qualname__ = apply.__name__ = getattr(fn, "__qualname__", "function")
    apply.__wrapped__ = fn
    return apply


_FUNCTION_DENOISERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def as_denoiser(denoiser, where: str = "denoiser") -> Denoiser:
    """A :class:`Denoiser` from what a user passes: a Denoiser, a spec for
    :func:`load_denoiser` (a name, a checkpoint path, with options), or a plain function
    ``frame -> image`` (:meth:`Denoiser.from_function`, differentiable, no declared
    fields)."""
    if isinstance(denoiser, Denoiser):
        return denoiser
    if isinstance(denoiser, (str, os.PathLike)):
        return load_denoiser(denoiser)
    if callable(denoiser):
        try:  # one Denoiser per function, so that its compiled forms are reused
            return _FUNCTION_DENOISERS[denoiser]
        except (KeyError, TypeError):
            pass
        wrapped = Denoiser.from_function(denoiser)
        with contextlib.suppress(TypeError):  # not weak-referenceable: no reuse
            _FUNCTION_DENOISERS[denoiser] = wrapped
        return wrapped
    raise ConfigError(f"{where} must be a name, a checkpoint path, a Denoiser or a function "
                      f"frame -> image, got {type(denoiser).__name__}")


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


@functools.cache
def emission_separated(definition: DenoiserDef) -> DenoiserDef:
    """``definition`` with the emission kept out of the filter (:mod:`jaxden.denoise.emission`):
    same config, parameters and init; requires ``emission`` too; named ``NAME+emission-separate``
    (its SURE caches and reports are kept apart from D's). One object per definition, so the
    jit and SURE caches keyed on it hold."""
    name = f"{definition.name}+emission-separate"
    required = definition.required
    tiling = None
    if definition.tiling is not None:
        @functools.cache
        def tiling(config, base=definition.tiling):
            spec = base(config)
            if spec is None or spec.apply is None:
                return spec  # the definition's own apply (below) serves the tiles
            return dataclasses.replace(spec, apply=separated_apply(
                spec.apply, name, definition.differentiable))
    return DenoiserDef(
        name=name,
        description=f"{definition.description}; directly visible emission kept out of the filter",
        config_cls=definition.config_cls,
        required=lambda config: (*required(config), "emission"),
        apply=separated_apply(definition.apply, name, definition.differentiable),
        init=definition.init,
        differentiable=definition.differentiable,
        pretrained=definition.pretrained,
        tiling=tiling,
        optional=definition.optional,
        options=definition.options,
        configure=definition.configure,
        step=None if definition.step is None else separated_step(definition.step),
    )


def spec_options(definition: DenoiserDef | None = None) -> dict[str, tuple[str, ...]]:
    """The spec options ``{KEY: (VALUE, ...)}`` a denoiser takes: :data:`DENOISER_OPTIONS`
    plus ``definition``'s own."""
    return {**DENOISER_OPTIONS, **dict(definition.options if definition is not None else ())}


def split_spec(spec: str | os.PathLike) -> tuple[str | os.PathLike, dict[str, str]]:
    """``(base spec, {option: value})`` of ``SPEC[:KEY=VALUE,...]``: options follow the last
    colon (:func:`spec_options`: :data:`DENOISER_OPTIONS`, and a registered name's own); a
    spec that names an existing path has none. An unknown option or value is one ConfigError
    naming the allowed ones."""
    if not isinstance(spec, str) or ":" not in spec or Path(spec).exists():
        return spec, {}
    base, _, tail = spec.rpartition(":")
    valid = spec_options(REGISTRY.get(base))
    options: dict[str, str] = {}
    for option in (part.strip() for part in tail.split(",")):
        key, equals, value = (p.strip() for p in option.partition("="))
        if not equals or key not in valid:
            raise ConfigError(
                f"denoiser {spec!r}: expected options KEY=VALUE after the last ':' with KEY one "
                f"of {', '.join(valid)}, got {option!r}")
        if value not in valid[key]:
            raise ConfigError(f"denoiser {spec!r}: {key} must be one of "
                              f"{', '.join(valid[key])}, got {value!r}")
        options[key] = value
    return base, options


def with_options(denoiser: Denoiser, emission: str = "filter", **options: str) -> Denoiser:
    """The denoiser with spec options applied: ``emission`` (:data:`DENOISER_OPTIONS`) and
    its definition's own (``options``; a pretrained denoiser's weights are read again for
    the new config, since they may differ with it)."""
    if emission not in EMISSION_MODES:
        raise ConfigError(f"emission must be one of {', '.join(EMISSION_MODES)}, got {emission!r}")
    if options:
        definition = denoiser.definition
        valid = dict(definition.options)
        for key, value in options.items():
            if key not in valid:
                raise ConfigError(f"denoiser '{denoiser.name}': unknown option {key!r}; its "
                                  f"options: {', '.join(spec_options(definition))}")
            if value not in valid[key]:
                raise ConfigError(f"denoiser '{denoiser.name}': {key} must be one of "
                                  f"{', '.join(valid[key])}, got {value!r}")
        config = definition.configure(denoiser.config, options)
        params = denoiser.params
        if definition.pretrained and definition.init is not None:
            params = definition.init(jax.random.PRNGKey(0), config)
        denoiser = Denoiser(definition, config, params, denoiser.trained_features)
    if emission == "filter":
        return denoiser
    return Denoiser(emission_separated(denoiser.definition), denoiser.config, denoiser.params,
                    denoiser.trained_features)




def load_denoiser(spec: str | os.PathLike) -> Denoiser:
    """A ready denoiser from a name or trained weights, with spec options.

    ``spec``: a registered black-box name (``oidn``); a name with weights shipped in the
    package (``jaxden/weights/<name>.msgpack``); a training workdir or checkpoint folder from
    ``jaxden train``; or a released ``.msgpack`` weights file; any of these followed by
    ``:KEY=VALUE,...`` options (:func:`split_spec`, e.g. ``wskp-6:emission=separate``,
    ``oidn-jax:aux=albedo,precision=bfloat16``). The checkpoint's meta record says which
    model and config it holds; a mixer checkpoint or an unknown model is a CheckpointError.
    """
    base, options = split_spec(spec)
    generic = {key: options.pop(key) for key in DENOISER_OPTIONS if key in options}
    return with_options(_load_base(base, options), **generic)


def _load_base(spec: str | os.PathLike, options: dict[str, str] | None = None) -> Denoiser:
    """The denoiser ``spec`` names; ``options``: a registered name's own spec options
    (checked by :func:`split_spec`), applied to its config before its weights are read."""
    from jaxden.checkpoint import load_trained_params, read_checkpoint_meta
    from jaxden.config import load_config

    path = resolve_weights(spec) or Path(spec)
    if not path.exists():
        if REGISTRY.find(str(spec)) is None:
            raise CheckpointError(_unknown_spec_message(str(spec)))
        definition = get_definition(str(spec))
        if definition.init is not None and not definition.pretrained:
            raise CheckpointError(
                f"denoiser '{spec}' needs trained weights: pass a checkpoint folder from "
                f"`jaxden train` (or a .msgpack weights file) instead of its name"
            )
        config = definition.configure(definition.config_cls(), options) if options else None
        return make_denoiser(str(spec), config)
    if options:  # split_spec takes a denoiser's own options only after a registered name
        raise ConfigError(f"denoiser {spec!r}: options {', '.join(options)} apply to "
                          f"registered names only")
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
    from jaxden.data.features import meta_features

    return Denoiser(definition, config, params, meta_features(meta))


def shipped_denoisers() -> list[str]:
    """Names of the trained denoisers shipped in ``jaxden/weights`` (their cards say
    ``kind: denoiser``; the mixers shipped beside them are not denoisers)."""
    import json

    names = []
    for card in sorted(WEIGHTS_DIR.glob("*.json")):
        try:
            kind = json.loads(card.read_text()).get("kind")
        except (OSError, ValueError):
            continue
        if kind == "denoiser" and card.with_suffix(".msgpack").is_file():
            names.append(card.stem)
    return names


def _unknown_spec_message(spec: str) -> str:
    """A denoiser spec that is neither a path nor a name: say which it looked like, list the
    shipped models and the architectures apart, and suggest a close match."""
    import difflib

    if os.sep in spec or spec.endswith((".msgpack", ".json")) or spec.startswith("."):
        return f"{spec}: no such file or folder (a checkpoint folder or .msgpack weights file)"
    shipped = shipped_denoisers()
    built_in = sorted(n for n, d in REGISTRY.items() if d.init is None or d.pretrained)
    architectures = sorted(n for n in REGISTRY if n not in built_in)
    candidates = shipped + built_in + architectures
    normalised = {name.replace("-", "").replace("_", "").lower(): name for name in candidates}
    close = normalised.get(spec.replace("-", "").replace("_", "").lower())
    close = close or next(iter(difflib.get_close_matches(spec, candidates, n=1)), None)
    hint = f" (did you mean {close!r}?)" if close else ""
    return (f"unknown denoiser {spec!r}{hint}; by name: {', '.join(shipped + built_in)}; "
            f"architectures (a checkpoint of one, from jaxden train): {', '.join(architectures)}"
            + ("" if hint else "; a denoiser of your own: name its module with --plugin or "
               "JAXDEN_PLUGINS (docs/your-denoiser.md)"))

