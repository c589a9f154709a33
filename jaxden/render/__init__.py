"""Mitsuba 3 side of jaxden: variant choice, moment/AOV integrators, scene library, render_frame.

Public API:

* :func:`choose_variant` - 'llvm_ad_rgb' where it works here, else 'scalar_rgb' (probed once in a
  subprocess; ``JAXDEN_MITSUBA_VARIANT`` overrides).
* :func:`list_scenes` - built-in scene names and descriptions.
* :func:`load_scene` - a scene spec (name, ``procedural:SEED``, XML path, dict) -> ``mi.Scene``
  with box filter + independent sampler enforced.
* :func:`prepare_scene` - the same at dict level (patched scene dict, not loaded; no XML).
* :func:`render_frame` - scene + spp + seed -> :class:`jaxden.frame.Frame` with colour, variance
  of the mean, albedo, normal, depth, position.

Beside them: :func:`jaxden.render.scene_cache.render_cached` (render_frame with the loaded scene
kept between calls: the dataset builder's default renderer) and
:func:`jaxden.render.synthetic.synthetic_render` (a Mitsuba-free stand-in for tests and dry runs).

Importing this package does not import Mitsuba; the first call does.
"""

from jaxden.render.core import render_frame
from jaxden.render.load import load_scene, prepare_scene
from jaxden.render.scenes import list_scenes
from jaxden.render.variant import choose_variant

__all__ = ["choose_variant", "list_scenes", "load_scene", "prepare_scene", "render_frame"]
