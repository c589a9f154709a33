"""SureSettings: the one value that SURE's options travel in.

Every option of Monte Carlo SURE (:mod:`jaxden.sure.stein`) is a field of one frozen value,
validated once when it is made, and passed whole: from the command line
(:func:`jaxden.cli.options.add_sure_options` makes the flags from the fields), from a mixer's
config (``MixerConfig.sure``, the TOML table ``[model_config.sure]``) and from an evaluator's
options down to :func:`jaxden.sure.sure`.

Unset: every field is None until it is given. ``given.over(base)`` takes each unset field from
``base``; "unset: the mixer's" is ``given.over(mixer_config.sure)`` wherever it is meant
(:func:`resolve_settings` is that rule for the functions). A field still unset after that
takes its default (:data:`DEFAULTS`, listed with each field below); for ``eps`` and
``probe_batch`` the default None is itself an instruction to the consumer (the measured step
of :func:`jaxden.sure.denoiser.default_eps`; all probes in one pass).

``seed`` is for callers that draw the probes' key themselves (the command line, SURE caches,
evaluators); a function that takes a key uses that key.

A new option is one field here (type, default, range, help); it is read where SURE is
computed (:mod:`jaxden.sure.stein`), and the command line's flag follows from the field.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, Literal

import numpy as np

from jaxden.errors import ConfigError

Method = Literal["auto", "jvp", "fd"]
FdScheme = Literal["forward", "central"]
ProbeDist = Literal["normal", "rademacher"]
#: The probe distributions, in the order of :data:`ProbeDist`.
PROBE_DISTS: tuple[str, ...] = typing.get_args(ProbeDist)


def _option(default, help: str, *, low=None, high=None, low_open: bool = False,
            metavar: str | None = None, default_text: str | None = None) -> Any:
    """A field of :class:`SureSettings`: None (unset) until given. ``default``: what it is when
    left unset (:data:`DEFAULTS`); ``low`` / ``high`` (``low_open``): the range of a number;
    ``help``, ``metavar`` and ``default_text`` (how the default reads): its command-line flag."""
    return dataclasses.field(default=None, metadata={"sure": {
        "default": default, "help": help, "low": low, "high": high, "low_open": low_open,
        "metavar": metavar, "default_text": default_text}})


@dataclasses.dataclass(frozen=True)
class SureSettings:
    """How SURE is estimated (module docstring: None = unset, :meth:`over`, :data:`DEFAULTS`).

    Raises ConfigError naming the option on a value of the wrong type, choice or range.
    """

    probes: int | None = _option(
        4, "SURE probes K averaged per pixel (the authors use 1 or 4)", low=1, metavar="K")
    method: Method | None = _option(  # noqa: RUF009 (a Field, not a default value)
        "auto", "SURE divergence: jvp (exact J b by forward-mode AD; JAX denoisers, oidn-jax "
        "included), fd (finite differences; the only choice for a black box such as the C++ "
        "OIDN), auto (jvp for JAX denoisers, fd for black boxes)")
    eps: float | None = _option(
        None, "finite-difference step, relative to the probe (x + eps b)", low=0,
        low_open=True, default_text="measured: 1e-2 for black boxes, 1e-3 for JAX fd")
    fd_scheme: FdScheme | None = _option(  # noqa: RUF009
        "forward", "finite-difference scheme: forward (the authors', K + 1 denoiser calls) or "
        "central (2K + 1 calls, a smaller error per probe)")
    probe_batch: int | None = _option(
        None, "probes per jvp pass (memory grows with it; 1 bounds it to one jvp for big "
        "images)", low=1, metavar="B", default_text="all probes in one pass")
    probe_dist: ProbeDist | None = _option(  # noqa: RUF009
        "normal", "SURE probe distribution: normal, or rademacher (random signs: no diagonal "
        "term in the probe noise, much less noisy per pixel at high spp)")
    covariance: bool | None = _option(
        True, "draw the probes from the colour covariance of a frame that carries one "
        "(covariance.RG/GB/BR); off: per channel, the paper's form",
        default_text="on (a mixer: off unless it was trained with it)")
    seed: int | None = _option(
        0, "seed of the SURE probes' key", low=0, high=2**32 - 1, metavar="SEED")

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if value is not None:
                object.__setattr__(self, field.name, _checked(field, value))

    def over(self, base: SureSettings | None) -> SureSettings:
        """These settings with every unset field taken from ``base`` (None: unchanged)."""
        if base is None:
            return self
        return SureSettings(**{name: base_value if value is None else value
                               for name, value, base_value in _pairs(self, base)})

    def resolved(self) -> SureSettings:
        """These settings with every unset field at its default (:data:`DEFAULTS`)."""
        return self.over(DEFAULTS)

    def given(self) -> dict:
        """The fields that are set, by name."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}

    def replace(self, **changes) -> SureSettings:
        return dataclasses.replace(self, **changes)

    def __repr__(self) -> str:
        return "SureSettings(" + ", ".join(f"{k}={v!r}" for k, v in self.given().items()) + ")"


def _pairs(settings: SureSettings, base: SureSettings):
    for field in dataclasses.fields(settings):
        yield field.name, getattr(settings, field.name), getattr(base, field.name)


def _checked(field: dataclasses.Field, value):
    """``value`` of ``field`` as a plain Python value (NumPy scalars too), or ConfigError."""
    spec = field.metadata["sure"]
    kind = next(a for a in typing.get_args(_FIELD_TYPES[field.name]) if a is not type(None))
    name = f"SURE option {field.name}"
    if typing.get_origin(kind) is Literal:
        choices = typing.get_args(kind)
        if not isinstance(value, str) or value not in choices:
            raise ConfigError(f"{name} must be one of {', '.join(choices)}, got {value!r}")
        return value
    if kind is bool:
        if not isinstance(value, (bool, np.bool_)):
            raise ConfigError(f"{name} must be true or false, got {value!r}")
        return bool(value)
    low, high, low_open = spec["low"], spec["high"], spec["low_open"]
    if kind is int:
        ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
        what = "an integer"
    else:
        ok = (isinstance(value, (int, float, np.integer, np.floating))
              and not isinstance(value, (bool, np.bool_)) and math.isfinite(value))
        what = "a finite number"
    if ok:
        value = kind(value)
        ok = ((low is None or (value > low if low_open else value >= low))
              and (high is None or value <= high))
    if not ok:
        bounds = (f"in [{low}, {high}]" if high is not None
                  else f"{'>' if low_open else '>='} {low}")
        raise ConfigError(f"{name} must be {what} {bounds}, got {value!r}")
    return value


_FIELD_TYPES = typing.get_type_hints(SureSettings)

#: Nothing set: every option taken from the base (a mixer's settings, or :data:`DEFAULTS`).
UNSET = SureSettings()

#: Every option at its default: what an option left unset means.
DEFAULTS = SureSettings(**{f.name: f.metadata["sure"]["default"]
                           for f in dataclasses.fields(SureSettings)})

#: The finite-difference steps an unset ``eps`` means for a denoiser's SURE
#: (:func:`default_eps`; measured: docs/history.md, "Defaults of the code").
FD_EPS_BLACKBOX = 1e-2
FD_EPS_JAX = 1e-3


def default_eps(method: str, differentiable: bool) -> float | None:
    """The finite-difference step of an unset ``eps`` for a denoiser: None for ``jvp``; 1e-2
    for black boxes (their error floor is their own float32 output), 1e-3 for JAX denoisers
    with ``fd`` (the float32 optimum)."""
    if method == "jvp":
        return None
    return FD_EPS_JAX if differentiable else FD_EPS_BLACKBOX


#: The keywords of the older signatures (``sure(fn, frame, key, num_probes=4)``,
#: ``denoise_with_sure(..., num_probes=...)``) that name a field differently.
RENAMED_KEYWORDS = {"num_probes": "probes"}


def resolve_settings(sure: SureSettings | None = None, base: SureSettings | None = None,
                     **options) -> SureSettings:
    """The settings a SURE function runs with: its loose keywords ``options`` (the older
    signatures' ``num_probes=``, ``method=``, ..., ``probe_dist=``; None: not given) over
    ``sure`` over ``base`` (what unset means for the caller: a mixer's settings; None:
    nothing) over :data:`DEFAULTS`. The one place that says what an unset option becomes."""
    if sure is not None and not isinstance(sure, SureSettings):
        raise ConfigError(f"sure must be a SureSettings (jaxden.sure.SureSettings) or None, "
                          f"got {type(sure).__name__}")
    given = {}
    for keyword, value in options.items():
        name = RENAMED_KEYWORDS.get(keyword, keyword)
        try:
            given[name] = getattr(SureSettings(**{name: value}), name)
        except ConfigError as error:  # named as the caller wrote it
            raise ConfigError(str(error).replace(f"option {name} ", f"option {keyword} ", 1)
                              ) from None
    return SureSettings(**given).over(sure).over(base).resolved()
