"""Benchmark ``progressive``: what progressive denoising costs on top of the denoiser it wraps.

On one 1280 x 720 frame (the Cornell box at 4 spp with its features and variance; 320 x 180
with ``quick``), OIDN on the CPU ('high' quality) and the shipped mixer ``oidn-pd``, everything
compiled and warmed up before timing, timed alternately, median of the repeats:

- ``pd_over_oidn``: the whole pipeline (OIDN for y, SURE by forward differences with 4 probes,
  i.e. 4 more OIDN calls, the mixer as shipped (``swap_average``: two mixer calls), the
  t-statistic scaling) / one OIDN call. The finite-difference SURE of a black box dominates:
  expect about 1 + K;
- ``pd_single_over_oidn``: the same with one mixer call (``swap_average`` off, the paper's form);
- ``mixer_over_oidn``: one mixer call (PDNet on the 18 input channels) / one OIDN call;
- ``tstat_over_oidn``: the t-statistic scaling alone / one OIDN call;
- ``guard_over_oidn``: the error guard after it (``tstat.guard``, on in every pipeline above)
  alone / one OIDN call;
- ``guard_strata_over_guard``: the error guard with its noise-strata option
  (``tstat.guard_strata = 1``: one more pair of local sums per occupied noise stratum) / the
  guard as shipped, the cost of the option;
- ``closed_form_over_oidn``: the closed-form mixer's alpha (``--mixer closed-form``: Eq. 9
  with Gaussian local means, width 12 px) / one OIDN call; it replaces the mixer call;
- ``closed_form_stops_over_closed_form``: the range-aware closed form (``closed_form_stops =
  1``: one blurred pair of local sums per occupied brightness stratum) / the plain one, the
  cost of the strata;
- ``pd_wskp6_over_wskp6``: the whole pipeline around the shipped real-time denoiser WSKP-6
  (jitted, deploy form) with its shipped mixer ``wskp-6-pd``: y, SURE by ``jax.jvp`` with the
  mixer's training probes (one), the mixer (one call) and the t-statistic / one WSKP-6
  forward. SURE by jvp costs about one forward per probe; the WSKP paper's point is a
  real-time base, so this ratio says what PD adds. (Without ``wskp-6-pd`` in the package it
  falls back to ``oidn-pd``'s weights with 4 probes, and ``pd_wskp6_mixer`` says so);
- ``pd_wskp6_closed_form_k1_over_wskp6``: the same with the closed-form mixer (range-aware,
  ``closed-form:stops=1``) and one probe: the cheapest PD(WSKP-6) jaxden offers;
- ``pd_oidnjax_over_oidn``: the whole pipeline around OIDN in JAX (``oidn-jax``: Intel's
  weights, the same network as the OIDN call, jitted) with SURE by ``jax.jvp`` and one
  Rademacher probe (``progressive --denoiser oidn-jax``'s default,
  :data:`jaxden.progressive.pipeline.TWIN_SURE`), the shipped mixer ``oidn-pd`` as shipped (as
  in ``pd_over_oidn``) and the t-statistic / one pyoidn call: PD(OIDN) with a differentiable
  OIDN, beside the finite-difference PD(OIDN)
  above. Its parts, each / one pyoidn call: ``oidnjax_over_oidn`` the forward alone,
  ``oidnjax_sure_over_oidn`` SURE (y and its SURE map from one jvp pass),
  ``oidnjax_mixer_over_oidn`` the mixer as the pipeline calls it, ``oidnjax_tstat_over_oidn``
  the t-statistic scaling. ``pd_oidnjax_k4_over_oidn``: the same pipeline with 4 normal
  probes (4 jvp passes), the mixer's own K (experiments/results/pd/pd-oidn-sure-forms.md has
  the PD tables of every form).
"""

from __future__ import annotations

from jaxden.bench import bench_frame, median_times, register

#: (width, height) and repeats of ``quick`` (the tests make it smaller still).
QUICK_SIZE, QUICK_REPEATS = (320, 180), 2


@register("progressive")
def bench_progressive(quick: bool) -> dict:
    import dataclasses

    import jax
    import numpy as np

    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive.closed_form import closed_form_alpha
    from jaxden.progressive.mixer_checkpoints import load_mixer
    from jaxden.progressive.mixer_config import closed_form_mixer
    from jaxden.progressive.network import inference_alpha, mixer_alpha
    from jaxden.progressive.pipeline import TWIN_SURE, progressive_denoise, shipped_mixer_path
    from jaxden.progressive.tstat import error_guard, t_statistic_scaling
    from jaxden.sure.denoiser import denoise_with_sure
    from jaxden.sure.settings import SureSettings

    size = QUICK_SIZE if quick else (1280, 720)
    repeats = QUICK_REPEATS if quick else 3
    frame = bench_frame(size)
    oidn = load_denoiser("oidn")
    params, config = load_mixer(str(shipped_mixer_path("oidn")))
    key = jax.random.PRNGKey(0)
    result, _ = denoise_with_sure(oidn, frame, key, sure=SureSettings(probes=4))
    x, var = np.asarray(frame.color), np.asarray(frame.variance)
    y, sure_map = np.asarray(result.denoised), np.asarray(result.sure)
    alpha = mixer_alpha(params, config, x, y, var, sure_map)
    mixed = np.asarray(x + alpha * (y - x))

    def pd(swap_average: bool):
        return progressive_denoise(frame, oidn, params, config, key,
                                   sure=SureSettings(probes=4), swap_average=swap_average)[0]

    wskp6 = load_denoiser("wskp-6")
    wskp6_forward = wskp6.function()
    device_frame = jax.device_put(frame)

    closed_params, closed_config = closed_form_mixer("closed-form:stops=1")

    wskp6_mixer = shipped_mixer_path("wskp-6")
    if wskp6_mixer is not None:
        wskp6_params, wskp6_config = load_mixer(str(wskp6_mixer))
        wskp6_mixer_name = wskp6_mixer.stem
    else:
        wskp6_params, wskp6_config = params, dataclasses.replace(
            config, sure=config.sure.replace(probes=4))
        wskp6_mixer_name = "oidn-pd (no wskp-6-pd shipped)"

    def pd_wskp6(mixer_params=wskp6_params, mixer_config=wskp6_config, probes=None):
        out = progressive_denoise(device_frame, wskp6, mixer_params, mixer_config, key,
                                  sure=SureSettings(probes=probes), swap_average=False)[0]
        return jax.block_until_ready(out)

    oidnjax = load_denoiser("oidn-jax")
    oidnjax_forward = oidnjax.function()
    # The SURE the pipeline takes for the twin: TWIN_SURE over the mixer's settings.
    one_probe = TWIN_SURE["oidn-jax"].over(config.sure)

    def oidnjax_sure():
        result, _ = denoise_with_sure(oidnjax, device_frame, key, sure=one_probe)
        return result.sure

    jax_result = denoise_with_sure(oidnjax, device_frame, key, sure=one_probe)[0]
    jax_y, jax_sure = np.asarray(jax_result.denoised), np.asarray(jax_result.sure)
    jax_alpha = np.asarray(inference_alpha(params, x, jax_y, var, jax_sure, config,
                                           config.swap_average))
    jax_mixed = np.asarray(x + jax_alpha * (jax_y - x))

    def pd_oidnjax(probes: int = 1):
        settings = one_probe if probes == 1 else SureSettings(probes=probes, method="jvp")
        out = progressive_denoise(device_frame, oidnjax, params, config, key, sure=settings)[0]
        return jax.block_until_ready(out)

    runners = {
        "oidn": lambda: oidn(frame),
        "pd_oidnjax": pd_oidnjax,
        "pd_oidnjax_k4": lambda: pd_oidnjax(4),
        "oidnjax": lambda: jax.block_until_ready(oidnjax_forward(device_frame)),
        "oidnjax_sure": oidnjax_sure,
        "oidnjax_mixer": lambda: inference_alpha(params, x, jax_y, var, jax_sure, config,
                                                 config.swap_average),
        "oidnjax_tstat": lambda: t_statistic_scaling(jax_alpha, x, jax_mixed, var,
                                                     config.tstat),
        "wskp6": lambda: jax.block_until_ready(wskp6_forward(device_frame)),
        "pd_wskp6": pd_wskp6,
        "pd_wskp6_closed_form_k1": lambda: pd_wskp6(closed_params, closed_config, 1),
        "pd": lambda: pd(True),
        "pd_single": lambda: pd(False),
        "mixer": lambda: mixer_alpha(params, config, x, y, var, sure_map),
        "tstat": lambda: t_statistic_scaling(alpha, x, mixed, var, config.tstat),
        "guard": lambda: error_guard(alpha, x, y, var, config.tstat, spp=4),
        "guard_strata": lambda: error_guard(alpha, x, y, var, config.tstat, spp=4,
                                            guard_strata=1.0),
        "closed_form": lambda: closed_form_alpha(x, y, var, sure_map),
        "closed_form_stops": lambda: closed_form_alpha(x, y, var, sure_map, stops=1.0),
    }
    median = median_times(runners, repeats)
    return {
        **{f"{name}_over_oidn": median[name] / median["oidn"]
           for name in ("pd", "pd_single", "mixer", "tstat", "guard", "closed_form",
                        "pd_oidnjax", "pd_oidnjax_k4", "oidnjax", "oidnjax_sure",
                        "oidnjax_mixer",
                        "oidnjax_tstat")},
        "closed_form_stops_over_closed_form": median["closed_form_stops"] / median["closed_form"],
        "guard_strata_over_guard": median["guard_strata"] / median["guard"],
        "pd_wskp6_over_wskp6": median["pd_wskp6"] / median["wskp6"],
        "pd_wskp6_closed_form_k1_over_wskp6": median["pd_wskp6_closed_form_k1"] / median["wskp6"],
        **{f"{name}_s": value for name, value in median.items()},
        "denoiser": "oidn (CPU, high quality)",
        "mixer": "oidn-pd",
        "sure": "forward differences, 4 probes",
        "pd_wskp6_mixer": wskp6_mixer_name,
        "pd_wskp6_sure": f"jvp, {wskp6_config.sure.probes} probes",
        "pd_oidnjax_denoiser": f"oidn-jax ({oidnjax.config.quality} quality, albedo + normal)",
        "pd_oidnjax_sure": f"jvp, {one_probe.probes} {one_probe.probe_dist} probe",
        "pd_oidnjax_mixer": f"oidn-pd (swap_average {config.swap_average})",
        "width": size[0],
        "height": size[1],
        "repeats": repeats,
    }
