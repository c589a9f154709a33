"""Benchmark ``denoisers``: inference time of jaxden's denoisers / OIDN on the same frame.

One 1280 x 720 frame (the Cornell box at 4 spp with its features; 320 x 180 with ``quick``) is
denoised by WSKP-3, WSKP-6, WSKP-MR, KP (13 x 13, WSKP backbone), KP-1 (2 layers, 13 x 13),
KP-2 (5 layers, 7 x 7), the U-Net and OIDN ('high' quality,
pyoidn on the same CPU). The JAX models run in their inference (deploy) form, jitted and
compiled before timing, with freshly initialised weights (inference time does not depend on
the weights' values). Each is timed alternately with the others, median of the repeats.
OIDN in JAX with Intel's weights (``oidnjax``) is timed beside them, and so are the methods
the two papers compare against: SVGF and BMFR (their single-frame form, and ``svgf_step`` /
``bmfr_step``: one frame of a sequence with the history of the frame before), StatMC and its
Moon CI variant (``statmc``, ``statmc_moon``; the bench frame carries no Box-Cox statistics,
so StatMC gets those :func:`jaxden.denoise.statmc.approximate_boxcox` derives from its colour
and variance: the same arrays and the same work as measured ones), the Deep
Combiner over OIDN in JAX (``dc``, the base's time included), NBGD and MR-KP (freshly
initialised, as the models above), and NFOR on two half buffers (``nfor``: the Cornell box at
2 spp with seeds 11 and 12, or the bench frame twice when it is read from a file; timed once
after a call that compiles it, minutes at 1280 x 720 on a CPU) and the neural James-Stein
combiner over OIDN in JAX on the same halves (``njs``: the base on each half and on their
mean, the cross regressions and the freshly initialised network; timed as NFOR is).
``<key>_over_wskp6`` = its
time / WSKP-6's, the comparisons' tables' unit. Keys
``<model>_over_oidn`` = model time / OIDN time, ``<model>_over_kp`` = model time / KP's
(the WSKP paper's target: WSKP-6 <= 0.5 KP) and ``wskp6_network_over_kp``: WSKP-6's
ImportanceNet alone (its 6 layers, no kernel decoding) / KP, the floor of ``wskp6_over_kp``
for any decoder (the two models share that backbone; KP's last layer and 13 x 13 filter are
what WSKP-6 saves).
"""

from __future__ import annotations

import numpy as np

from jaxden.bench import bench_frame, median_times, register

MODELS = {"wskp3": "wskp3", "wskp6": "wskp", "wskp_mr": "wskp_mr", "kp": "kp", "kp1": "kp1",
          "kp2": "kp2", "unet": "unet", "nbgd": "nbgd", "mrkp": "mrkp"}
#: Training-free baselines by spec, timed in their single-frame form; those in TEMPORAL also
#: as one step of a sequence (``<key>_step``).
BASELINES = {"svgf": "svgf", "bmfr": "bmfr", "statmc": "statmc", "statmc_moon": "statmc-moon"}
TEMPORAL = ("svgf", "bmfr")
#: The Deep Combiner over this base (the one experiments/configs/train-dc.toml trains over).
DC_BASE: str | None = "oidn-jax"
#: Time NFOR on two half buffers (once, after a compiling call).
NFOR = True
#: Time the neural James-Stein combiner over this base on the same two half buffers (once,
#: after a compiling call; freshly initialised network; None: not timed).
NJS_BASE: str | None = "oidn-jax"
#: Also time OIDN in JAX (Intel's weights, :mod:`jaxden.denoise.oidn_jax`) against pyoidn,
#: the same network and inputs (albedo, normal, clean features, quality high).
OIDN_JAX = True
#: (width, height) and repeats of ``quick`` (the tests make it smaller still).
QUICK_SIZE, QUICK_REPEATS = (320, 180), 3


@register("denoisers")
def bench_denoisers(quick: bool) -> dict:
    import jax

    from jaxden.denoise.registry import make_denoiser

    size = QUICK_SIZE if quick else (1280, 720)
    repeats = QUICK_REPEATS if quick else 7
    frame = bench_frame(size)
    device_frame = jax.device_put(frame)
    runners = {}
    for key, name in MODELS.items():
        denoiser = make_denoiser(name, key=jax.random.PRNGKey(0)).deployed()
        function = denoiser.function()
        runners[key] = (lambda f=function: jax.block_until_ready(f(device_frame)))
    oidn = make_denoiser("oidn")
    runners["oidn"] = lambda: oidn(frame)
    if OIDN_JAX:
        runners["oidnjax"] = _oidn_jax_runner(frame)
    if "wskp6" in MODELS:
        from jaxden.denoise.nn.wskp import RepVGGStack, network_inputs

        wskp6 = make_denoiser("wskp", key=jax.random.PRNGKey(0)).deployed()
        config = wskp6.config
        net = RepVGGStack(config.num_layers, config.width, 2 * len(config.kernel_sizes),
                          config.deploy)
        network = jax.jit(lambda f: net.apply(wskp6.params, network_inputs(f, config.tonemap)))
        runners["wskp6_network"] = lambda: jax.block_until_ready(network(device_frame))
    runners |= _baseline_runners(device_frame)
    median = median_times(runners, repeats)
    if NFOR or NJS_BASE is not None:
        halves = _half_buffers(frame, size)
        if NFOR:
            from jaxden.denoise.nfor import nfor

            median["nfor"] = _once_time(lambda: jax.block_until_ready(nfor(*halves)))
        if NJS_BASE is not None:
            median["njs"] = _njs_time(halves, NJS_BASE)
    result: dict = {f"{key}_over_oidn": median[key] / median["oidn"]
                    for key in (*MODELS, *(["oidnjax"] if OIDN_JAX else []))}
    if "wskp6" in median:
        result.update({f"{key}_over_wskp6": value / median["wskp6"]
                       for key, value in median.items() if key != "wskp6"})
    result.update({f"{key}_over_kp": median[key] / median["kp"] for key in MODELS
                   if key != "kp" and "kp" in median})
    if "wskp6_network" in median and "kp" in median:
        result["wskp6_network_over_kp"] = median["wskp6_network"] / median["kp"]
    result.update({f"{key}_s": value for key, value in median.items()})
    result.update({"width": size[0], "height": size[1], "repeats": repeats,
                   "devices": len(jax.devices()), "oidn_quality": "high"})
    assert np.isfinite(list(median.values())).all()
    return result


def _oidn_jax_runner(frame):
    """OIDN-JAX on the bench frame, jitted and compiled before timing."""
    import jax

    from jaxden.denoise.oidn_jax import load_oidn, oidn_denoise

    params, spec = load_oidn(albedo=True, normal=True, clean_aux=True)
    inputs = [jax.device_put(np.clip(np.asarray(value, np.float32), low, 1.0)) if low is not None
              else jax.device_put(np.asarray(value, np.float32))
              for value, low in ((frame.color, None), (frame.albedo, 0.0), (frame.normal, -1.0))]
    function = jax.jit(lambda c, a, n: oidn_denoise(params, spec, c, a, n))
    jax.block_until_ready(function(*inputs))
    return lambda: jax.block_until_ready(function(*inputs))



def _baseline_runners(device_frame) -> dict:
    """Runners of :data:`BASELINES` (and their sequence steps) and of the Deep Combiner."""
    import jax

    from jaxden.denoise.registry import load_denoiser, make_denoiser

    runners = {}
    for key, spec in BASELINES.items():
        denoiser = load_denoiser(spec)
        function = denoiser.function()
        frame = with_statistics(device_frame) if "boxcox" in denoiser.fields_read() \
            else device_frame
        runners[key] = (lambda f=function, frame=frame: jax.block_until_ready(f(frame)))
        if key in TEMPORAL:
            _, state = denoiser.step(None, device_frame)  # the history of a frame before
            runners[f"{key}_step"] = (lambda d=denoiser, s=state: jax.block_until_ready(
                d.step(s, device_frame)[0]))
    if DC_BASE is not None:
        from jaxden.denoise.deep_combiner import DeepCombinerConfig

        dc = make_denoiser("dc", DeepCombinerConfig(base=DC_BASE), key=jax.random.PRNGKey(0))
        function = dc.function()
        runners["dc"] = lambda: jax.block_until_ready(function(device_frame))
    return runners


def with_statistics(frame):
    """``frame`` with Box-Cox statistics (StatMC's input) approximated from its colour and
    variance where it has none (:func:`jaxden.denoise.statmc.approximate_boxcox`); a frame
    that has them, as it is."""
    if frame.boxcox is not None:
        return frame
    import jax

    from jaxden.denoise.statmc import approximate_boxcox

    boxcox = approximate_boxcox(frame.color, frame.variance, frame.statistics_count())
    return frame.replace(boxcox=jax.device_put(boxcox))


def _half_buffers(frame, size) -> list:
    """Two independent half buffers of ``size``: the Cornell box at 2 spp with seeds 11 and
    12, or the bench frame twice when it is read from a file."""
    import os

    from jaxden.bench import BENCH_FRAME_ENV

    if os.environ.get(BENCH_FRAME_ENV):
        return [frame, frame]
    from jaxden.render.core import render_frame

    return [render_frame("cornell-box", 2, seed=seed, size=size) for seed in (11, 12)]


def _once_time(run) -> float:
    """Seconds of one call of ``run`` after a first (compiling) call."""
    import time

    run()
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def _njs_time(halves, base: str) -> float:
    """Seconds of the neural James-Stein combiner over ``base`` on the two half buffers (the
    base on each half and on their mean, the cross regressions, the network), after a
    compiling call; the network freshly initialised. (The authors' 51 x 51 regression window,
    narrowed only on frames under 26 pixels a side, which it does not fit.)"""
    import jax

    from jaxden.denoise.njs import OLS_WINDOW
    from jaxden.denoise.njs_model import (
        NJSModel,
        NJSModelConfig,
        checked_base,
        njs_denoise,
        njs_model_init,
    )

    height, width = halves[0].color.shape[-3:-1]
    radius = min(OLS_WINDOW // 2, min(height, width) - 1)
    config = NJSModelConfig(base=base, ols_window=2 * radius + 1)
    model = NJSModel(njs_model_init(jax.random.PRNGKey(0), config), config, checked_base(config))
    return _once_time(lambda: njs_denoise(model, *halves))
