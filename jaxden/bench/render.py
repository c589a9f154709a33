"""Benchmark ``render``: render_frame (colour + variance + features) vs a plain Mitsuba render.

ratio = median time of :func:`jaxden.render.render_frame` / median time of ``mi.render`` with the
same scene's own colour integrator (``path``), sensor, size, spp and variant, in one run. Both
are warmed up first (JIT compilation excluded) and timed alternately, several repeats each, so
drift of a shared machine hits both alike. render_frame's extra work is the three moment AOVs,
the feature render and the NumPy post-processing. Target <= 1.15, set when the features were
Mitsuba's ``aov`` at min(spp, 16) samples: ``ratio_legacy_features`` measures that
(``aux="first-hit", feature_spp=16``); ``ratio`` measures today's defaults (specular-chain
features at min(spp, 1024) samples, the ones OIDN does best with), which cost more.

``ratio`` uses wall-clock time (what users wait for); ``cpu_ratio`` uses the process's CPU time
over all threads, which is steadier when other jobs share the machine.

``ratio_emission`` (and ``cpu_ratio_emission``): the colour pass with the emission AOVs (one more
camera-ray intersection per sample, 3 more film channels) over the same pass without them
(``moment_integrator(emission=False)``, the integrator before ``Frame.emission``).
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from jaxden.bench import register

SCENE = "cornell-box"
SIZE = (256, 256)
SPP = 64
#: (size, spp, repeats) of ``quick`` (the tests make it smaller still).
QUICK = ((64, 64), 16, 3)


def measure(scene_spec=SCENE, size=SIZE, spp=SPP, repeats: int = 5) -> dict:
    """Times (seconds) and ratio for one scene; see the module docstring."""
    import mitsuba as mi

    from jaxden.render import core, integrators
    from jaxden.render import load as scenes
    from jaxden.render.variant import ensure_variant

    variant = ensure_variant()
    scene = scenes.load_scene(scene_spec, size)
    sensor = scenes.sensor_source(scene).build(tuple(size), None)
    inner, _ = core._integrators(scene, None)

    def frame() -> None:
        core.render_frame(scene, spp, seed=1)

    def legacy() -> None:
        core.render_frame(scene, spp, seed=1, aux="first-hit", feature_spp=core.AOV_SPP)

    def plain() -> None:
        np.array(mi.render(scene, sensor=sensor, integrator=inner, spp=spp, seed=1))

    with_emission = integrators.moment_integrator(inner)
    without_emission = integrators.moment_integrator(inner, emission=False)

    def emission() -> None:
        np.array(mi.render(scene, sensor=sensor, integrator=with_emission, spp=spp, seed=1))

    def no_emission() -> None:
        np.array(mi.render(scene, sensor=sensor, integrator=without_emission, spp=spp, seed=1))

    runs = (("frame", frame), ("legacy", legacy), ("plain", plain), ("emission", emission),
            ("no_emission", no_emission))
    for _, fn in runs:
        fn()  # warm-up: compile every kernel once
    wall: dict[str, list[float]] = {key: [] for key, _ in runs}
    cpu: dict[str, list[float]] = {key: [] for key, _ in runs}
    for _ in range(repeats):
        for key, fn in runs:
            start, start_cpu = time.perf_counter(), time.process_time()
            fn()
            wall[key].append(time.perf_counter() - start)
            cpu[key].append(time.process_time() - start_cpu)
    frame_s, plain_s = statistics.median(wall["frame"]), statistics.median(wall["plain"])
    frame_cpu, plain_cpu = statistics.median(cpu["frame"]), statistics.median(cpu["plain"])
    legacy_s, legacy_cpu = statistics.median(wall["legacy"]), statistics.median(cpu["legacy"])
    return {
        "ratio": frame_s / plain_s,
        "cpu_ratio": frame_cpu / plain_cpu,
        "ratio_legacy_features": legacy_s / plain_s,
        "cpu_ratio_legacy_features": legacy_cpu / plain_cpu,
        "ratio_emission": statistics.median(wall["emission"]) / statistics.median(
            wall["no_emission"]),
        "cpu_ratio_emission": statistics.median(cpu["emission"]) / statistics.median(
            cpu["no_emission"]),
        "render_frame_s": frame_s,
        "plain_path_s": plain_s,
        "render_frame_cpu_s": frame_cpu,
        "plain_path_cpu_s": plain_cpu,
        "scene": scene_spec,
        "size": f"{size[0]}x{size[1]}",
        "spp": spp,
        "repeats": repeats,
        "variant": variant,
    }


@register("render")
def render_bench(quick: bool) -> dict:
    if quick:
        size, spp, repeats = QUICK
        return measure(SCENE, size, spp, repeats=repeats)
    return measure()
