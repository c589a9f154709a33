"""Benchmark ``sure``: the cost of SURE relative to denoising, and jvp against finite differences.

On one 1280 x 720 frame (the Cornell box at 4 spp with its features and variance; 320 x 180
with ``quick``), with WSKP-6 in its inference form (fresh weights: cost does not depend on their
values), all jitted and compiled before timing, timed alternately, median of the repeats:

- ``jvp_k1_over_forward``: SURE with the jvp divergence and K = 1 probe (which includes the
  denoised image itself) / one forward pass of the denoiser (target <= 2.5);
- ``jvp_over_fd_k4``: SURE with K = 4 jvp probes / SURE with K = 4 forward-difference probes
  (eps 1e-3), both with ``probe_batch = 1`` (memory of one probe at a time).
"""

from __future__ import annotations

from jaxden.bench import bench_frame, median_times, register

#: (width, height) and repeats of ``quick`` (the tests make it smaller still).
QUICK_SIZE, QUICK_REPEATS = (320, 180), 3
#: The registered denoiser measured (the tests use the smaller "wskp3").
MODEL = "wskp"
DESCRIPTIONS = {"wskp": "wskp (6 layers, deploy form)", "wskp3": "wskp3 (3 layers, deploy form)"}


@register("sure")
def bench_sure(quick: bool) -> dict:
    import jax

    from jaxden.denoise.registry import make_denoiser
    from jaxden.sure.settings import SureSettings
    from jaxden.sure.stein import sure

    size = QUICK_SIZE if quick else (1280, 720)
    repeats = QUICK_REPEATS if quick else 5
    frame = jax.device_put(bench_frame(size))
    denoiser = make_denoiser(MODEL, key=jax.random.PRNGKey(0)).deployed()
    definition, config, params = denoiser.definition, denoiser.config, denoiser.params

    def apply(p, f):
        return definition.apply(p, config, f)

    key = jax.random.PRNGKey(1)
    forward = jax.jit(apply)
    jvp_k1, jvp_k4, fd_k4 = (
        jax.jit(lambda p, f, k, s=settings: sure(apply, f, k, settings=s, params=p).sure)
        for settings in (SureSettings(probes=1, method="jvp"),
                         SureSettings(probes=4, method="jvp", probe_batch=1),
                         SureSettings(probes=4, method="fd", eps=1e-3, probe_batch=1)))
    runners = {
        "forward": lambda: forward(params, frame),
        "jvp_k1": lambda: jvp_k1(params, frame, key),
        "jvp_k4": lambda: jvp_k4(params, frame, key),
        "fd_k4": lambda: fd_k4(params, frame, key),
    }
    median = median_times(runners, repeats)
    return {
        "jvp_k1_over_forward": median["jvp_k1"] / median["forward"],
        "jvp_over_fd_k4": median["jvp_k4"] / median["fd_k4"],
        **{f"{name}_s": value for name, value in median.items()},
        "denoiser": DESCRIPTIONS.get(MODEL, f"{MODEL} (deploy form)"),
        "width": size[0],
        "height": size[1],
        "repeats": repeats,
    }
