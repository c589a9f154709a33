"""The z-test of a mean, its power against a stated alternative, and the number of draws that
power needs: the statistics behind jaxden's property tests (pure NumPy and SciPy).

The test
--------
``n`` independent draws ``v_1 .. v_n`` (for SURE: per noise draw, the mean SURE minus the mean
true squared error of the same draw, so that ``E[v] = 0`` when SURE is unbiased). With the
sample mean ``m``, the sample standard deviation ``s`` (``ddof = 1``) and the null value
``m0``::

    se = s / sqrt(n),      z = (m - m0) / se

By the central limit theorem ``z`` is approximately standard normal under the null, so::

    p = 2 Phi(-|z|)               (two-sided; "greater": Phi(-z), "less": Phi(z))

and the test rejects at significance ``alpha`` iff ``p < alpha``, i.e. iff ``|z| > z_c`` with
the critical value ``z_c = Phi^-1(1 - alpha / 2)`` (one-sided: ``Phi^-1(1 - alpha)``). ``Phi``
is the standard normal CDF. The normal approximation replaces Student's t with ``n - 1``
degrees of freedom: at alpha = 1e-4 the false-rejection rate of normal draws is 2.4e-4 at
n = 64, 1.6e-4 at n = 128 (the fewest the SURE check runs) and 1.1e-4 at n = 512.

Power
-----
If the true mean is ``m0 + delta`` and the draws have standard deviation ``sigma``, ``z`` is
approximately normal with mean ``lambda = delta sqrt(n) / sigma`` and variance 1, so the
probability of rejecting is::

    power = Phi(lambda - z_c) + Phi(-lambda - z_c)    (two-sided)
    power = Phi(lambda - z_c)                          ("greater"; "less": Phi(-lambda - z_c))

Draws needed
------------
Ignoring the far tail (which only adds power), ``power >= 1 - beta`` needs
``lambda >= z_c + z_beta`` with ``z_beta = Phi^-1(1 - beta)``::

    n = ceil(((z_c + z_beta) sigma / |delta|)^2)

(:func:`required_draws` then lowers ``n`` while the exact two-sided power still reaches the
target). For alpha = 1e-4 and power 0.99, ``(z_c + z_beta)^2 = (3.891 + 2.326)^2 = 38.7``:
a shift of one standard deviation of a draw needs 39 draws, a tenth of one 3866.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np
from scipy.special import ndtr, ndtri

from jaxden.errors import ConfigError

Alternative = Literal["two-sided", "greater", "less"]
ALTERNATIVES = ("two-sided", "greater", "less")


def _check_alternative(alternative) -> None:
    if alternative not in ALTERNATIVES:
        raise ConfigError(f"alternative must be one of {', '.join(ALTERNATIVES)}, "
                         f"got {alternative!r}")


def _check_probability(name: str, value) -> float:
    value = float(value)
    if not 0.0 < value < 1.0:
        raise ConfigError(f"{name} must be in (0, 1), got {value!r}")
    return value


def z_critical(alpha: float, alternative: Alternative = "two-sided") -> float:
    """The critical value of the z-test at significance ``alpha``: ``Phi^-1(1 - alpha / 2)``
    (two-sided) or ``Phi^-1(1 - alpha)`` (one-sided). 1.96 at 0.05, 3.891 at 1e-4."""
    alpha = _check_probability("alpha", alpha)
    _check_alternative(alternative)
    tail = alpha / 2.0 if alternative == "two-sided" else alpha
    return float(-ndtri(tail))


def p_value(z: float, alternative: Alternative = "two-sided") -> float:
    """The p-value of a z statistic: ``2 Phi(-|z|)`` (two-sided), ``Phi(-z)`` ("greater"),
    ``Phi(z)`` ("less"). ``z = +-inf`` gives 0 (or 1 on the wrong side); NaN gives NaN."""
    _check_alternative(alternative)
    z = float(z)
    if alternative == "two-sided":
        return float(min(1.0, 2.0 * ndtr(-abs(z))))
    return float(ndtr(-z) if alternative == "greater" else ndtr(z))


def _draws(values, baseline) -> np.ndarray:
    values = np.asarray(values, np.float64) - np.asarray(baseline, np.float64)
    return values.reshape(-1) if values.ndim <= 1 else values


def z_score(values, baseline=0.0) -> float:
    """``(mean - null) / stderr`` of the draws ``values`` in float64: the z of the test that
    the mean of ``values - baseline`` is 0 (see the module docstring).

    ``baseline`` is a number (the null mean) or an array of the draws' shape: paired draws,
    e.g. ``z_score(sure_per_draw, true_error_per_draw)`` tests that their means agree on
    common random numbers. With a zero standard deviation: 0 if the mean is 0, else +-inf.
    """
    differences = _draws(values, baseline)
    if differences.ndim != 1:
        raise ConfigError(f"z_score: expected one value per draw, got shape {differences.shape}")
    if differences.size < 2:
        raise ConfigError(f"z_score: needs at least 2 draws, got {differences.size}")
    mean = float(differences.mean())
    stderr = float(differences.std(ddof=1) / math.sqrt(differences.size))
    if stderr > 0:
        return mean / stderr
    return 0.0 if mean == 0 else math.copysign(math.inf, mean)


@dataclasses.dataclass(frozen=True)
class ZTest:
    """The outcome of :func:`z_test`.

    ``mean`` and ``stderr``: of the differences ``values - baseline``; ``sd`` their standard
    deviation (one draw's); ``z``, ``p`` as in the module docstring; ``reject``: ``p <
    alpha``; ``draws``: n.
    """

    mean: float
    stderr: float
    sd: float
    z: float
    p: float
    draws: int
    alpha: float
    alternative: str
    reject: bool

    def __str__(self) -> str:
        verdict = "rejected" if self.reject else "accepted"
        return (f"mean {self.mean:.4g} +- {self.stderr:.2g} (z = {self.z:.3g}, p = {self.p:.3g}, "
                f"{self.draws} draws): {verdict} at alpha {self.alpha:g} ({self.alternative})")


def z_test(values, baseline=0.0, *, alpha: float = 1e-4,
           alternative: Alternative = "two-sided") -> ZTest:
    """The z-test that the mean of ``values - baseline`` is 0 at significance ``alpha``
    (``baseline``: a null mean, or paired per-draw values; see :func:`z_score`).

    Returns a :class:`ZTest`; ``reject`` is True when ``p < alpha``.
    """
    alpha = _check_probability("alpha", alpha)
    z = z_score(values, baseline)
    differences = _draws(values, baseline)
    sd = float(differences.std(ddof=1))
    p = p_value(z, alternative)
    return ZTest(mean=float(differences.mean()), stderr=sd / math.sqrt(differences.size),
                 sd=sd, z=z, p=p, draws=int(differences.size), alpha=alpha,
                 alternative=alternative, reject=bool(p < alpha))


def power(effect: float, sd: float, draws: int, alpha: float = 1e-4,
          alternative: Alternative = "two-sided") -> float:
    """The probability that the z-test at significance ``alpha`` rejects over ``draws`` draws
    whose true mean is ``effect`` away from the null and whose standard deviation is ``sd``:
    ``Phi(lambda - z_c) + Phi(-lambda - z_c)``, ``lambda = effect sqrt(draws) / sd``
    (two-sided; module docstring). ``sd = 0``: 1 for a non-zero effect, else alpha."""
    z_c = z_critical(alpha, alternative)
    if draws < 1:
        raise ConfigError(f"power: draws must be >= 1, got {draws!r}")
    if sd < 0 or not math.isfinite(sd):
        raise ConfigError(f"power: sd must be finite and >= 0, got {sd!r}")
    effect = float(effect)
    if sd == 0:
        lam = 0.0 if effect == 0 else math.copysign(math.inf, effect)
    else:
        lam = effect * math.sqrt(draws) / sd
    if alternative == "two-sided":
        return float(ndtr(lam - z_c) + ndtr(-lam - z_c))
    return float(ndtr(lam - z_c) if alternative == "greater" else ndtr(-lam - z_c))


_power = power  # required_draws' argument ``power`` hides the function


def required_draws(effect: float, sd: float, alpha: float = 1e-4, power: float = 0.99,
                   alternative: Alternative = "two-sided") -> int:
    """The fewest draws with which the z-test at ``alpha`` rejects a true shift ``effect`` of
    the mean (draws of standard deviation ``sd``) with probability at least ``power``:
    ``ceil(((z_c + z_beta) sd / |effect|)^2)``, lowered while :func:`power` still reaches the
    target, and at least 2 (module docstring). An effect of the wrong sign for a one-sided
    test, or of 0, can never reach the target: ConfigError."""
    target = _check_probability("power", power)
    z_c = z_critical(alpha, alternative)
    effect = float(effect)
    if alternative == "less":
        effect = -effect
    elif alternative == "two-sided":
        effect = abs(effect)
    if not effect > 0 or not math.isfinite(effect):
        raise ConfigError(f"required_draws: the effect must be finite and non-zero (and in the "
                         f"tested direction), got {effect!r}")
    if sd < 0 or not math.isfinite(sd):
        raise ConfigError(f"required_draws: sd must be finite and >= 0, got {sd!r}")
    z_beta = float(ndtri(target))
    draws = max(2, math.ceil(((z_c + z_beta) * sd / effect) ** 2))
    while draws > 2 and _power(effect, sd, draws - 1, alpha, alternative) >= target:
        draws -= 1
    return draws


def relative_mean(values, reference) -> tuple[float, float]:
    """``(mean(values) / r, stderr(values) / |r|)`` with ``r = mean(reference)``, in float64: a
    bias and its standard error as a fraction of a reference quantity (e.g. SURE minus the
    true error per draw, relative to the true error)."""
    values = np.asarray(values, np.float64).reshape(-1)
    scale = float(np.mean(np.asarray(reference, np.float64)))
    if values.size < 2:
        raise ConfigError(f"relative_mean: needs at least 2 draws, got {values.size}")
    return (float(values.mean() / scale),
            float(values.std(ddof=1) / math.sqrt(values.size) / abs(scale)))
