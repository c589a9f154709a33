"""The property test of SURE for any denoiser: over many noisy frames around a known clean image,
the mean SURE equals the mean true squared error, by a z-test with a stated significance and
power.

The test
--------
Over the draws of :mod:`jaxden.testing.draws` (per draw i, the mean SURE S_i and the mean true
squared error T_i of the image or a region) SURE is unbiased iff ``E[D_i] = 0``, ``D_i = S_i -
T_i``. Testing the mean of the paired differences ``D`` (common random numbers) rather than
comparing two separately estimated means removes most of the noise: ``Var D`` is far below
``Var S + Var T``. The z-test (:mod:`jaxden.testing.stats`): ``z = mean D / (sd D / sqrt n)``,
two-sided ``p = 2 Phi(-|z|)``; with m tests (the image and each region) each runs at ``alpha /
m`` (Bonferroni), so a correct SURE fails the whole check with probability at most ``alpha``.

The alternative and the power
-----------------------------
A divergence wrong by a relative ``bias`` (the derivative SURE sees off by that fraction, e.g.
a jvp scaled by 0.9: :func:`jaxden.testing.scaled_colour_derivative`) shifts ``E[S_i]`` by
``delta = 2 bias V``, ``V = mean_P var J_ii`` the mean divergence term (estimated from the
draws). The power of the test against it is ``Phi(lambda - z_c) + Phi(-lambda - z_c)``,
``lambda = delta sqrt(n) / sd(D)``, ``z_c = Phi^-1(1 - alpha / (2 m))``. With ``draws=None``
the number of draws comes from that formula: a first batch estimates ``sd(D)`` and ``V``, and
the check runs ``1.25 required_draws(delta, sd(D), alpha / m, power)`` draws (the factor covers
the first batch's error in ``sd(D)``; at least 128, at most ``max_draws``), so the image-level
test reaches the stated power. A denoiser that hardly responds to its colour (``V`` near 0)
has no divergence to get wrong: the power against a relative error of it is low and the
result says so (and a warning is issued).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any

import numpy as np

from jaxden.errors import ConfigError
from jaxden.frame import Frame
from jaxden.testing.draws import NO_PARAMS, SureDraws, SureSampler
from jaxden.testing.stats import ZTest, required_draws, z_test
from jaxden.testing.stats import power as test_power

#: The fewest draws a check runs with ``draws=None`` (the z-test's normal approximation:
#: :mod:`jaxden.testing.stats`).
MIN_DRAWS = 128
#: Factor on the draws the first batch's estimate asks for (its error in sd(D)).
DRAWS_MARGIN = 1.25


def _power_text(value: float) -> str:
    return "> 0.999" if value > 0.999 else f"{value:.3g}"


@dataclasses.dataclass(frozen=True)
class RegionCheck:
    """The test over one region (or the whole image): means over its pixels and channels,
    averaged over the draws; ``test`` the z-test of SURE minus the true error (at the
    region's significance, alpha / m); ``effect`` the shift of the mean SURE under the stated
    alternative (2 bias divergence) and ``power`` the test's power against it."""

    name: str
    estimate: float
    truth: float
    divergence: float
    test: ZTest
    effect: float
    power: float

    @property
    def z(self) -> float:
        return self.test.z

    @property
    def p(self) -> float:
        return self.test.p

    @property
    def reject(self) -> bool:
        return self.test.reject

    def line(self) -> str:
        return (f"{self.name}: mean SURE {self.estimate:.5g} vs true MSE {self.truth:.5g} "
                f"(difference {self.test.mean:.3g} +- {self.test.stderr:.2g}, z = "
                f"{self.z:.3g}, p = {self.p:.3g}; power {_power_text(self.power)})")


@dataclasses.dataclass(frozen=True)
class SureCheck:
    """The outcome of :func:`check_sure_unbiased`.

    ``estimate``, ``truth``, ``divergence``, ``z``, ``p``, ``power``: of the image-level test
    (``tests[0]``); ``tests``: the image, then each region. ``alpha``: the significance of
    the whole check (each of the m tests at alpha / m); ``bias``: the stated alternative, the
    divergence wrong by that fraction; ``power``: the image-level test's probability of
    rejecting that alternative at these draws (estimated from them); ``seed``, ``draws``,
    ``probes``, ``method``: how it ran. ``passed``: no test rejected.
    """

    denoiser: str
    tests: tuple[RegionCheck, ...]
    draws: int
    seed: Any
    alpha: float
    bias: float
    probes: int
    method: str
    passed: bool

    @property
    def estimate(self) -> float:
        return self.tests[0].estimate

    @property
    def truth(self) -> float:
        return self.tests[0].truth

    @property
    def divergence(self) -> float:
        return self.tests[0].divergence

    @property
    def z(self) -> float:
        return self.tests[0].z

    @property
    def p(self) -> float:
        return self.tests[0].p

    @property
    def power(self) -> float:
        return self.tests[0].power

    def __str__(self) -> str:
        verdict = "unbiased (not rejected)" if self.passed else "BIASED (rejected)"
        m = len(self.tests)
        head = (f"SURE of '{self.denoiser}': {verdict} at alpha {self.alpha:g}"
                f"{f' (each of {m} tests at {self.alpha / m:.3g})' if m > 1 else ''}; "
                f"{self.draws} draws, seed {self.seed}, {self.probes} {self.method} probe(s); "
                f"power {_power_text(self.power)} against a {self.bias:.0%} error of the "
                f"divergence "
                f"(mean divergence term {self.divergence:.3g})")
        return "\n".join([head] + ["  " + t.line() + ("  <- rejected" if t.reject else "")
                                   for t in self.tests])


def _summarise(draws: SureDraws, names, alpha: float, bias: float) -> tuple[RegionCheck, ...]:
    m = len(names)
    tests = []
    for j, name in enumerate(names):
        difference = draws.sure[:, j] - draws.truth[:, j]
        test = z_test(difference, alpha=alpha / m)
        divergence = float(draws.divergence[:, j].mean())
        effect = 2.0 * bias * abs(divergence)
        tests.append(RegionCheck(
            name=name, estimate=float(draws.sure[:, j].mean()),
            truth=float(draws.truth[:, j].mean()), divergence=divergence, test=test,
            effect=effect, power=test_power(effect, test.sd, test.draws, alpha / m)))
    return tuple(tests)


def _needed(first: SureDraws, alpha: float, bias: float, power: float, m: int) -> float:
    """Draws the image-level test needs, from the first batch (inf when it cannot)."""
    difference = first.sure[:, 0] - first.truth[:, 0]
    effect = 2.0 * bias * abs(float(first.divergence[:, 0].mean()))
    try:
        return required_draws(effect, float(difference.std(ddof=1)), alpha / m, power)
    except ConfigError:  # no divergence to get wrong
        return math.inf


def check_sure_unbiased(
    denoiser,
    frame: Frame | None = None,
    *,
    draws: int | None = None,
    probes: int = 1,
    method: str = "auto",
    eps: float | None = None,
    seed=0,
    alpha: float = 1e-4,
    bias: float = 0.1,
    power: float = 0.99,
    regions=None,
    params=NO_PARAMS,
    batch: int = 64,
    max_draws: int = 8192,
    raise_on_failure: bool = True,
) -> SureCheck:
    """Test that jaxden's SURE of ``denoiser`` is unbiased: raise AssertionError if the mean
    SURE over many noisy frames differs from the mean true squared error (module docstring).

    Defaults: seed 0; significance ``alpha = 1e-4`` for the whole check (a correct SURE
    fails with probability at most 1e-4 under the normal approximation); draws chosen so that
    the image-level test has power ``0.99`` against a divergence wrong by ``bias = 10 %``
    (twice 10 % of the mean divergence term off the true error). The result states the
    seed, the draws and the power reached. Measured on the built-in frame with
    :func:`jaxden.testing.shrink` (tests/test_testing.py): 192 draws, power > 0.999, z = 0.42,
    and z = -8.9 with its jvp scaled by 0.9; about 1 s per check at XLA -O0 (the test suite's
    setting) and 2.5 s at the default -O3 on 2 CPU cores, compilation included.

    Args:
      denoiser: a :class:`jaxden.denoise.Denoiser`, a registered name or checkpoint
        (:func:`jaxden.denoise.load_denoiser`; black boxes such as ``"oidn"`` run by finite
        differences, one draw at a time), or a JAX function ``frame -> (H, W, 3)`` (with
        ``params``: ``denoiser(params, frame)``). Pass the same function object each time:
        the draws compile once per function (and per shape).
      frame: the clean frame (``color`` = mu (H, W, 3), ``variance`` the variance of the
        noise, plus the features the denoiser reads); None: :func:`synthetic_frame` (16 x
        16, every feature, seed 0).
      draws: None (from the power formula, at least 128, at most ``max_draws``) or a number
        (rounded up to whole batches).
      params: for a plain function ``denoiser(params, frame)``: its parameters, traced (new
        values do not recompile).
      probes, method, eps: SURE's options (:func:`jaxden.sure.sure`: ``num_probes``,
        ``"jvp"``/``"fd"``/``"auto"``, the finite-difference step).
      seed: an integer or a JAX PRNG key.
      alpha: significance of the whole check; bias, power: the alternative and the power
        wanted against it (only used to choose the draws and to report).
      regions: None, a grid size n (n x n blocks) or an integer label map (H, W): also test
        each region (:func:`jaxden.testing.region_weights`), at ``alpha / m`` each.
      batch: draws per compiled call (memory: a batch of frames and their jvps); the first
        batch is the one the draws are chosen from. max_draws: the most ``draws=None`` runs.
      raise_on_failure: False returns the failing result instead of raising.

    Returns:
      :class:`SureCheck` (``str()`` of it is a readable report).

    Raises:
      AssertionError: a test rejected (the message is the report). ConfigError, FrameError:
      bad arguments or frame.
    """
    from jaxden.testing.synthetic import synthetic_frame

    for name, value in (("alpha", alpha), ("power", power)):
        if not 0 < value < 1:
            raise ConfigError(f"check_sure_unbiased: {name} must be in (0, 1), got {value!r}")
    if not bias > 0:
        raise ConfigError(f"check_sure_unbiased: bias must be > 0, got {bias!r}")
    if draws is not None and not (isinstance(draws, (int, np.integer)) and draws >= 2):
        raise ConfigError(f"check_sure_unbiased: draws must be None or an integer >= 2, "
                          f"got {draws!r}")
    frame = synthetic_frame() if frame is None else frame
    batch = int(batch) if draws is None else min(int(batch), int(draws))
    sampler = SureSampler(denoiser, frame, probes=probes, method=method, eps=eps, seed=seed,
                          params=params, regions=regions, batch=batch,
                          where="check_sure_unbiased")
    m = len(sampler.names)
    if draws is None:
        sampler.run(1)
        needed = _needed(sampler.draws(squeeze=False), alpha, bias, power, m)
        total = min(max(MIN_DRAWS, DRAWS_MARGIN * needed), max(int(max_draws), MIN_DRAWS))
    else:
        total = int(draws)
    sampler.run(max(0, -(-int(total) // sampler.batch) - sampler.count // sampler.batch))
    results = sampler.draws(squeeze=False)
    tests = _summarise(results, sampler.names, alpha, bias)
    seed_text = seed if isinstance(seed, (int, np.integer)) else "(a key)"
    result = SureCheck(denoiser=sampler.name, tests=tests,
                       draws=int(results.sure.shape[0]), seed=seed_text, alpha=float(alpha),
                       bias=float(bias), probes=sampler.probes, method=sampler.method,
                       passed=not any(t.reject for t in tests))
    if result.power < power:
        warnings.warn(f"check_sure_unbiased: the test reaches power {result.power:.3g} (< "
                      f"{power}) against a {bias:.0%} error of the divergence at "
                      f"{result.draws} draws (mean divergence term {result.divergence:.3g}); "
                      f"raise draws or max_draws for a stronger test", stacklevel=2)
    if raise_on_failure and not result.passed:
        raise AssertionError(str(result))
    return result
