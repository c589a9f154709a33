"""Choosing Mitsuba's variant: ``llvm_ad_rgb`` where it works, ``scalar_rgb`` otherwise.

Mitsuba's fast CPU variant ``llvm_ad_rgb`` JIT-compiles kernels with libLLVM. With Debian 12's
libLLVM 15 or 16 the first render aborts the whole process (SIGABRT in LLVM's instruction
selector), which no ``try``/``except`` can catch. So the variant is chosen by rendering a tiny
1-spp probe scene in a *subprocess*; if that dies or fails, jaxden renders with ``scalar_rgb``
and says so once on stderr. Installing libLLVM 19 (``apt-get install libllvm19``) fixes it.

Order of decision:

1. ``JAXDEN_MITSUBA_VARIANT`` (e.g. ``scalar_rgb``) overrides everything; it must name an
   installed RGB variant.
2. The in-process cache (one probe per process at most).
3. A small JSON cache file, ``$JAXDEN_CACHE_DIR`` or ``$XDG_CACHE_HOME/jaxden`` or
   ``~/.cache/jaxden``, file ``mitsuba-variant.json``. Its key holds the Mitsuba and Dr.Jit
   versions, the Python executable, ``DRJIT_LIBLLVM_PATH`` and the identity (path, size, mtime)
   of every libLLVM library found in the usual library folders. Any change to those (an LLVM
   installed or removed, Mitsuba upgraded) changes the key and forces a new probe, so a stale
   entry cannot select a variant that would abort; an unreadable or corrupt file is ignored.
   Set ``JAXDEN_MITSUBA_VARIANT_CACHE=0`` to disable the file.
4. The subprocess probe.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

from jaxden.errors import JaxdenError

FAST_VARIANT = "llvm_ad_rgb"
FALLBACK_VARIANT = "scalar_rgb"
ENV_VARIANT = "JAXDEN_MITSUBA_VARIANT"
ENV_CACHE = "JAXDEN_MITSUBA_VARIANT_CACHE"
CACHE_FILE_NAME = "mitsuba-variant.json"
PROBE_TIMEOUT_S = 300.0
_PROBE_OK = "JAXDEN_PROBE_OK"

# The probe renders a diffuse sphere under a constant emitter at 4 x 4 pixels, 1 spp: it
# compiles and runs a full path-tracing kernel, which is what crashes with a bad libLLVM.
_PROBE_SCRIPT = """
import sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "path", "max_depth": 3},
    "sensor": {"type": "perspective",
               "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}},
               "sampler": {"type": "independent", "sample_count": 1}},
    "sphere": {"type": "sphere", "bsdf": {"type": "diffuse"}},
    "light": {"type": "constant"},
})
import numpy as np
image = np.array(mi.render(scene, spp=1, seed=0))
assert image.shape[:2] == (4, 4) and np.isfinite(image).all(), "probe image is not finite"
print("%s")
""" % _PROBE_OK

_chosen: str | None = None
_notice_printed = False


def _cache_dir() -> Path:
    if os.environ.get("JAXDEN_CACHE_DIR"):
        return Path(os.environ["JAXDEN_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxden"


def _llvm_libraries() -> list[tuple[str, int, int]]:
    """(path, size, mtime_ns) of every libLLVM shared library in the usual folders."""
    folders = {"/lib", "/lib64", "/usr/lib", "/usr/lib64", "/usr/local/lib",
               "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib"}
    multiarch = sysconfig.get_config_var("MULTIARCH")
    if multiarch:
        folders |= {f"/lib/{multiarch}", f"/usr/lib/{multiarch}"}
    folders |= set(glob.glob("/usr/lib/llvm-*/lib"))
    for variable in ("LD_LIBRARY_PATH", "DYLD_LIBRARY_PATH"):
        folders |= {p for p in os.environ.get(variable, "").split(os.pathsep) if p}
    candidates: set[str] = set()
    for folder in folders:
        candidates |= set(glob.glob(os.path.join(folder, "libLLVM*.so*")))
        candidates |= set(glob.glob(os.path.join(folder, "libLLVM*.dylib")))
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        candidates.add(os.environ["DRJIT_LIBLLVM_PATH"])
    found = []
    for path in sorted(candidates):
        try:
            stat = os.stat(path)  # follows links: the identity of the library actually loaded
        except OSError:
            continue
        found.append((path, stat.st_size, stat.st_mtime_ns))
    return found


def cache_key() -> str:
    """A hash of everything that decides whether ``llvm_ad_rgb`` can work here."""
    import drjit
    import mitsuba

    parts = {
        "mitsuba": mitsuba.__version__,
        "drjit": drjit.__version__,
        "python": sys.executable,
        "DRJIT_LIBLLVM_PATH": os.environ.get("DRJIT_LIBLLVM_PATH", ""),
        "libllvm": _llvm_libraries(),
    }
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


def _read_cache(key: str) -> tuple[str, str] | None:
    """(variant, reason) from the cache file if its key matches; None when it is missing,
    unreadable, malformed, wrongly typed or stale (a broken cache is a miss, never an error:
    the probe runs again and rewrites it)."""
    from jaxden.fileio import read_json

    try:
        data = read_json(_cache_dir() / CACHE_FILE_NAME, "the Mitsuba variant cache",
                         fields={"key": str, "variant": str, "reason?": str})
    except JaxdenError:
        return None
    if data["key"] != key or data["variant"] not in (FAST_VARIANT, FALLBACK_VARIANT):
        return None
    return data["variant"], data.get("reason") or ""


def _write_cache(key: str, variant: str, reason: str) -> None:
    """Record the choice (atomic: readers never see half a file; nothing is left behind
    when the disk is full or the folder read-only: the next run just probes again)."""
    from jaxden.fileio import atomic_write_text

    try:
        folder = _cache_dir()
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_text(folder / CACHE_FILE_NAME,
                          json.dumps({"key": key, "variant": variant, "reason": reason}))
    except (OSError, JaxdenError):
        pass


def probe_variant(variant: str, timeout: float = PROBE_TIMEOUT_S) -> tuple[bool, str]:
    """Render a 1-spp probe with ``variant`` in a subprocess.

    Returns (ok, reason): reason is '' when ok, else a one-line description (the signal that
    killed the probe or the last line of its error output).
    """
    try:
        result = subprocess.run(
            [sys.executable, "-c", _PROBE_SCRIPT, variant],
            capture_output=True, text=True, timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return False, f"the probe render did not finish in {timeout:.0f} s"
    except OSError as error:
        return False, f"could not start the probe: {error}"
    if result.returncode == 0 and _PROBE_OK in result.stdout:
        return True, ""
    lines = [line.strip() for line in (result.stderr or "").splitlines() if line.strip()]
    last = lines[-1] if lines else "no error output"
    if result.returncode < 0:
        import signal

        try:
            name = signal.Signals(-result.returncode).name
        except ValueError:
            name = f"signal {-result.returncode}"
        return False, f"probe render killed by {name}: {last[:200]}"
    return False, f"probe render failed (exit {result.returncode}): {last[:200]}"


def _notice(reason: str) -> None:
    global _notice_printed
    if not _notice_printed:
        _notice_printed = True
        print(
            f"jaxden: Mitsuba {FAST_VARIANT} unavailable ({reason}); rendering with "
            f"{FALLBACK_VARIANT} (several times slower). Install libllvm19 to fix.",
            file=sys.stderr,
        )


def choose_variant() -> str:
    """The Mitsuba variant jaxden renders with: 'llvm_ad_rgb' or 'scalar_rgb' (or the override).

    Raises JaxdenError if ``JAXDEN_MITSUBA_VARIANT`` names a variant that is not installed or
    not an RGB variant (jaxden's integrators need RGB colour).
    """
    global _chosen
    import mitsuba as mi

    override = os.environ.get(ENV_VARIANT, "").strip()
    if override:
        if override not in mi.variants() or not override.endswith("_rgb"):
            valid = ", ".join(v for v in mi.variants() if v.endswith("_rgb"))
            raise JaxdenError(
                f"{ENV_VARIANT}={override!r} is not an installed RGB Mitsuba variant; "
                f"valid: {valid}"
            )
        return override
    if _chosen is not None:
        return _chosen
    if FAST_VARIANT not in mi.variants():
        reason = f"Mitsuba was built without {FAST_VARIANT}"
        _notice(reason)
        _chosen = FALLBACK_VARIANT
        return _chosen
    use_file = os.environ.get(ENV_CACHE, "1") != "0"
    key = cache_key()
    cached = _read_cache(key) if use_file else None
    if cached is not None:
        variant, reason = cached
    else:
        ok, reason = probe_variant(FAST_VARIANT)
        variant = FAST_VARIANT if ok else FALLBACK_VARIANT
        if use_file:
            _write_cache(key, variant, reason)
    if variant == FALLBACK_VARIANT:
        _notice(reason or "the probe render failed")
    _chosen = variant
    return variant


def ensure_variant() -> str:
    """Set Mitsuba's variant to :func:`choose_variant` (once) and return it.

    jaxden owns the variant while it renders: if other code switched Mitsuba to another variant
    in between, this switches back.
    """
    import mitsuba as mi

    variant = choose_variant()
    if mi.variant() != variant:
        mi.set_variant(variant)
    return variant


def _reset_for_tests() -> None:
    """Forget the in-process choice (tests only)."""
    global _chosen, _notice_printed
    _chosen = None
    _notice_printed = False
