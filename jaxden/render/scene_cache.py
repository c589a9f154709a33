"""``render_cached``: :func:`jaxden.render.core.render_frame` with the loaded scene kept between
calls in this process (the dataset builder's default renderer, also used by ``jaxden render``
and the evaluators that render their own inputs).
"""

from __future__ import annotations

from typing import Any

# Per worker process: the most recently loaded Mitsuba scenes. render_frame reloads a scene
# given by name on every call, and a freshly loaded scene with textures (the procedural ones)
# misses Dr.Jit's kernel cache: a recompile per render (docs/results.md, "Data"). Rendering a
# loaded mi.Scene reuses the kernels (same images: the seeds and the scene are the same). One
# scene only: every live scene is traced into each render's kernels (jaxden.render.load), so a
# second one held would slow the renders of the first; crops of one scene are built one after
# another.
_SCENE_CACHE: dict[tuple[str, tuple[int, int]], Any] = {}
_SCENE_CACHE_SIZE = 1


def render_cached(
    scene: str,
    spp: int,
    seed: int = 0,
    size: tuple[int, int] | None = None,
    *,
    crop: tuple[int, int, int, int] | None = None,
    aux: str = "first-hit",
    feature_spp: int = 16,
    colour: Any = None,
    parameters: dict[str, str] | None = None,
    statistics: bool = False,
) -> Any:
    """:func:`jaxden.render.core.render_frame` with the loaded scene kept between calls (the
    builder's default renderer). ``parameters``: ``$name`` values of an XML scene."""
    from jaxden.render.core import render_frame
    from jaxden.render.load import load_scene

    key = (scene, tuple(size) if size is not None else None,
           tuple(sorted((parameters or {}).items())))
    loaded = _SCENE_CACHE.get(key)
    if loaded is None:
        loaded = load_scene(scene, size, parameters or None)
        while len(_SCENE_CACHE) >= _SCENE_CACHE_SIZE:
            _SCENE_CACHE.pop(next(iter(_SCENE_CACHE)))
        _SCENE_CACHE[key] = loaded
    return render_frame(loaded, spp, seed=seed, size=size, crop=crop, aux=aux,
                        feature_spp=feature_spp, colour=colour, statistics=statistics)
