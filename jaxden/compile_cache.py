"""JAX's persistent compilation cache, on by default for the ``jaxden`` command.

XLA compiles of jaxden's train steps take 10-20 s on a 2-core CPU, far longer than running
them; the persistent cache turns every later compile of the same program (a resumed run, the
next denoise call, a sweep's next run) into a ~1 s load. Location: ``$JAXDEN_CACHE_DIR/xla`` or
``~/.cache/jaxden/xla``; ``JAXDEN_COMPILATION_CACHE=0`` turns it off.
"""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    root = os.environ.get("JAXDEN_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "jaxden"
    )
    return Path(root) / "xla"


def enable_compilation_cache(directory: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache (idempotent); returns its folder or None."""
    if os.environ.get("JAXDEN_COMPILATION_CACHE", "1") == "0":
        return None
    import jax

    path = Path(directory) if directory is not None else default_cache_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # read-only home: run without the cache rather than fail
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
