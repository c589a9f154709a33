"""The consistency check of a progressive-denoising mixer: as the variance goes to 0 (spp to
infinity), PD's output is no worse than the Monte Carlo input, even over a biased denoiser.

The check
---------
For a clean frame (colour mu, variance of the mean var at ``spp``) and levels ``k = 0 .. L - 1``
the variance shrinks by 4 per level, as from quadrupling the sample count::

    var_k = var 4^-k,   spp_k = spp 4^k,   x_k = mu + sqrt(var_k) n

with one standard normal ``n`` for every level (common random numbers: the levels differ only
in the noise's scale, so the curve is smooth). Each x_k goes through
:func:`jaxden.progressive.progressive_denoise` with the mixer and a denoiser ``y = D(x)`` whose
bias stays as the variance shrinks (default: a 3 x 3 box blur times 1.1,
:func:`jaxden.testing.denoisers.biased_blur`). With the mean squared errors over the pixels
and channels::

    MC_k = mean (x_k - mu)^2,   PD_k = mean (z'_k - mu)^2,   ratio_k = PD_k / MC_k

A consistent mixer (the t-statistic scaling and the error guard, paper Sec. 4.2) sends alpha'
to 0 where y's bias becomes significant against the shrinking noise, so ``ratio_k`` falls to
1 or below; one that keeps mixing in y has ``PD_k -> mean (y - mu)^2 > 0`` while ``MC_k -> 0``,
so its ratio grows by about 4 per level. The check passes iff ``ratio_k <= 1 + tol`` at each
of the last ``settle`` levels (the smallest variances: it has converged, not crossed 1 + tol
once).
"""

from __future__ import annotations

import dataclasses
import os
import warnings

import jax
import numpy as np

from jaxden.errors import ConfigError
from jaxden.frame import Frame


@dataclasses.dataclass(frozen=True)
class MixerCheck:
    """The outcome of :func:`check_mixer_consistent`; the tuples have one entry per level,
    from the largest variance to the smallest.

    ``variance_scale``: var_k / var (4^-k); ``spp``: spp_k; ``mc``, ``denoised``, ``pd``:
    mean squared errors of x, y and z' against mu (radiance^2); ``ratio``: pd / mc;
    ``alpha``: mean alpha' (the scaled mixing weight). ``passed``: ratio <= 1 + tol at each
    of the last ``settle`` levels.
    """

    mixer: str
    denoiser: str
    variance_scale: tuple[float, ...]
    spp: tuple[float, ...]
    mc: tuple[float, ...]
    denoised: tuple[float, ...]
    pd: tuple[float, ...]
    ratio: tuple[float, ...]
    alpha: tuple[float, ...]
    tol: float
    settle: int
    seed: int
    passed: bool

    def __str__(self) -> str:
        verdict = "consistent" if self.passed else "NOT consistent"
        head = (f"mixer '{self.mixer}' over '{self.denoiser}': {verdict} (PD / MC error <= "
                f"{1 + self.tol:g} at the last {self.settle} of {len(self.ratio)} variance "
                f"levels; seed {self.seed})")
        rows = [f"  var x {s:.3g} (spp {n:g}): MC {mc:.3g}, denoised {y:.3g}, PD {pd:.3g}, "
                f"PD / MC {r:.3g}, mean alpha' {a:.3g}"
                for s, n, mc, y, pd, r, a in zip(self.variance_scale, self.spp, self.mc,
                                                 self.denoised, self.pd, self.ratio, self.alpha)]
        return "\n".join([head, *rows])


def _mixer(mixer) -> tuple[object, object, str]:
    """(params, MixerConfig, a name) from a spec or a (params, config) pair."""
    from jaxden.progressive import MixerConfig, load_mixer

    if isinstance(mixer, (str, os.PathLike)):
        params, config = load_mixer(mixer)
        return params, config, str(mixer)
    if (isinstance(mixer, tuple) and len(mixer) == 2 and isinstance(mixer[1], MixerConfig)):
        config = mixer[1]
        name = ("closed-form" if config.kind == "closed_form"
                else f"{config.kind} mixer ({config.head} head)")
        return mixer[0], config, name
    raise ConfigError(f"mixer must be a spec for load_mixer (a shipped name such as 'oidn-pd', "
                      f"'closed-form[:...]', a checkpoint) or a (params, MixerConfig) pair, got "
                      f"{type(mixer).__name__}")


def check_mixer_consistent(
    mixer,
    frame: Frame | None = None,
    *,
    denoiser=None,
    levels: int = 10,
    tol: float = 0.05,
    settle: int = 2,
    seed: int = 0,
    raise_on_failure: bool = True,
) -> MixerCheck:
    """Check progressive denoising's promise for ``mixer``: PD's error relative to MC's is
    at most ``1 + tol`` as the variance goes to 0 (module docstring).

    Args:
      mixer: a shipped name (``"oidn-pd"``, ``"wskp-6-pd"``), a closed-form spec
        (``"closed-form[:KEY=VALUE,...]"``), a mixer checkpoint, or ``(params,
        MixerConfig)``; its own t-statistic and guard settings apply.
      frame: the clean frame at the largest variance (``color`` mu (H, W, 3), ``variance``,
        ``spp``, and the features the denoiser reads); None: :func:`synthetic_frame` (32 x
        32, seed 0) at 4 spp with a relative standard deviation of the mean of 0.4 to 1.2,
        where the default denoiser is far better than x (the curve starts well below 1).
      denoiser: a :class:`jaxden.denoise.Denoiser` or a spec for
        :func:`jaxden.denoise.load_denoiser`; None: :func:`biased_blur` (a 3 x 3 box blur
        times 1.1). It needs a bias that does not vanish with the variance, else there is
        nothing to check.
      levels: variance levels (each a quarter of the last); tol, settle: the pass criterion.
      seed: the noise n (NumPy) and SURE's probes (``jax.random.key(seed)``).
      raise_on_failure: False returns the failing result instead of raising.

    Returns:
      :class:`MixerCheck` (``str()`` of it: the error curve).

    Raises:
      AssertionError: the mixer is not consistent (the message holds the curve).
    """
    from jaxden import progressive
    from jaxden.progressive import progressive_denoise
    from jaxden.sure.denoiser import resolve_denoiser
    from jaxden.testing.denoisers import biased_blur
    from jaxden.testing.synthetic import synthetic_frame

    if not (isinstance(levels, int) and levels >= 2):
        raise ConfigError(f"check_mixer_consistent: levels must be an integer >= 2, got "
                          f"{levels!r}")
    if not (isinstance(settle, int) and 1 <= settle <= levels):
        raise ConfigError(f"check_mixer_consistent: settle must be an integer in 1..{levels}, "
                          f"got {settle!r}")
    if not tol >= 0:
        raise ConfigError(f"check_mixer_consistent: tol must be >= 0, got {tol!r}")
    params, config, mixer_name = _mixer(mixer)
    model = resolve_denoiser(biased_blur() if denoiser is None else denoiser)
    if frame is None:
        frame = synthetic_frame(0, 32, 32, relative_std=(0.4, 1.2), spp=4.0)
    if frame.variance is None:
        from jaxden.errors import FrameError

        raise FrameError("check_mixer_consistent: the clean frame needs its variance of the "
                         "pixel mean (Frame.variance) at the largest variance level")
    frame = frame.numpy().validated(where="check_mixer_consistent")
    mu = np.asarray(frame.color, np.float64)
    var = np.asarray(frame.variance, np.float64)
    normals = np.random.default_rng(seed).standard_normal(mu.shape)
    base_spp = 1.0 if frame.spp is None else np.asarray(frame.spp, np.float64)
    key = jax.random.key(seed)
    other_denoiser = getattr(progressive, "MixerDenoiserWarning", None)
    rows = []
    for k in range(levels):
        scale = 4.0 ** -k
        x = mu + np.sqrt(var * scale) * normals
        noisy = frame.replace(color=x.astype(np.float32), variance=(var * scale).astype(
            np.float32), spp=np.float32(base_spp * 4.0**k), variance_dof=None,
            covariance=None if frame.covariance is None else
            (np.asarray(frame.covariance, np.float64) * scale).astype(np.float32))
        with warnings.catch_warnings():
            if other_denoiser is not None:  # a mixer over another denoiser: the point here
                warnings.simplefilter("ignore", other_denoiser)
            z_prime, alpha_prime, extras = progressive_denoise(noisy, model, params, config,
                                                               key)
        z_prime = np.asarray(z_prime, np.float64)
        y = np.asarray(extras["denoised"], np.float64)
        mc = float(np.mean(np.square(x - mu)))
        pd = float(np.mean(np.square(z_prime - mu)))
        rows.append((scale, float(np.mean(base_spp) * 4.0**k), mc,
                     float(np.mean(np.square(y - mu))), pd, pd / mc,
                     float(np.mean(np.asarray(alpha_prime)))))
    columns = [tuple(column) for column in zip(*rows)]
    ratio = columns[5]
    passed = all(r <= 1.0 + tol for r in ratio[-settle:])
    result = MixerCheck(mixer_name, model.name, *columns, tol=float(tol), settle=settle,
                        seed=seed, passed=passed)
    if raise_on_failure and not passed:
        raise AssertionError(str(result))
    return result
