"""Shared pytest setup: the ``--runslow`` option, the ``slow`` marker, and a PRNG key fixture.

Tests marked ``@pytest.mark.slow`` (statistical or rendering-heavy) are skipped unless pytest
runs with ``--runslow``. The ``slow`` marker itself is declared in pyproject.toml.
"""

from __future__ import annotations

import os

# Two host "devices" so data-parallel code is exercised on the CPU (must precede importing jax).
# XLA's backend (LLVM) at optimisation level 0: compiles, not runs, dominate the suite (tiny
# arrays, hundreds of distinct programs; e.g. initialising the default U-Net compiles in ~6 s
# instead of ~55 s on the 2-core machine, tests/test_models.py takes 30 s instead of 70 s).
# Results differ from -O3 only in the last float32 bits (measured: 2e-5 on O(1) outputs of a
# KP model), below every tolerance the tests state. Set XLA_FLAGS yourself to test -O3.
os.environ.setdefault(
    "XLA_FLAGS", "--xla_force_host_platform_device_count=2 --xla_backend_optimization_level=0")
# Full float32 matrix products and convolutions. On the CPU this is XLA's default anyway; on an
# NVIDIA GPU the default is TF32 (~1e-3 relative), under which the NumPy-reference, deploy-form
# and finite-difference tests fail by 1e-3..1e-2 (measured on an H100) although the code is
# right. Training on a GPU may keep TF32.
os.environ.setdefault("JAX_DEFAULT_MATMUL_PRECISION", "float32")

import pytest


def pytest_sessionstart(session: pytest.Session) -> None:
    # XLA compiles dominate test time on 2 cores; identical programs (a resumed run, the same
    # model in several tests) are compiled once per session through the persistent cache.
    import tempfile

    from jaxden.compile_cache import enable_compilation_cache

    path = os.environ.get("JAXDEN_TEST_XLA_CACHE")
    if not path:  # a session's own cache, removed when it ends
        path = session.config._jaxden_xla_cache = tempfile.mkdtemp(prefix="jaxden-xla-")
    enable_compilation_cache(path)


def pytest_sessionfinish(session: pytest.Session) -> None:
    import shutil

    path = getattr(session.config, "_jaxden_xla_cache", None)
    if path:
        shutil.rmtree(path, ignore_errors=True)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--runslow", action="store_true", default=False, help="also run tests marked slow"
    )


def pytest_configure(config: pytest.Config) -> None:
    # Declared here too so the marker is known even when pyproject.toml is not the rootdir's.
    config.addinivalue_line("markers", "slow: long-running test; run with --runslow")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow test: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)


@pytest.fixture(autouse=True, scope="module")
def _release_mitsuba_scenes():
    """After each test module, drop the Mitsuba scenes and integrators jaxden keeps cached.

    Every live Mitsuba BSDF, shape, emitter and texture of the variant is in Dr.Jit's instance
    registry, and a symbolic virtual call traces (and compiles into the kernel) the code of
    *every* registered instance, not just the rendered scene's. When jaxden's caches held up to
    14 scenes, later test files' renders traced ~350 instances instead of ~25 and compiled
    kernels that the on-disk cache had never seen (5-11 s per Mitsuba test in the full suite,
    0.1-2 s alone). The caches now hold one scene each (render.core, render.scene_cache) and
    render.load holds sensors only; clearing them keeps test files independent all the same.
    """
    yield
    import sys

    caches = [getattr(sys.modules.get("jaxden.render.load"), "_loaded", None),
              getattr(sys.modules.get("jaxden.render.core"), "_spec_scenes", None),
              getattr(sys.modules.get("jaxden.render.core"), "_integrator_cache", None),
              getattr(sys.modules.get("jaxden.render.scene_cache"), "_SCENE_CACHE", None)]
    for cache in caches:
        if cache:
            cache.clear()  # reference counting frees the objects (measured: 0 left per module)


@pytest.fixture(scope="session")
def key():
    """jax.random.PRNGKey(0), shared by the session (split it; never reuse it for two draws)."""
    import jax

    return jax.random.PRNGKey(0)
