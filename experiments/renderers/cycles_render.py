"""Render a small Cycles scene headless with Blender's ``bpy`` (PyPI), as a multilayer EXR with
the Denoising Data passes: the files a Blender user hands to jaxden (``--from cycles``).

    pip install bpy   # Blender 5.0, Python 3.11, in its own venv
    python experiments/renderers/cycles_render.py --spp 16 --seed 1 --size 32x24 \
        --out tests/data/cycles/spheres-16spp-seed1.exr
    python experiments/renderers/cycles_render.py --scene window --emission --spp 16 \
        --seed 1 --size 160x120 --out window-16spp-seed1.exr

Two scenes (``--scene``), each with a small lamp in view:

- ``spheres`` (the default): a diffuse floor, a glossy metal sphere (roughness 0.15), a
  small emissive sphere (radius 0.15, strength 50, grey base colour) and a point light;
- ``window``: the scene of jaxden issue 48 (``cycles_fixtures.build_scene``): a floor, a
  wall with a window that a sun shines through, a small emissive sphere of strength 400, a
  gold Suzanne and a glossy torus.

Cycles on the CPU, fixed seed, no adaptive sampling, no denoising and no clamping (the raw
Monte Carlo mean: Blender's default Indirect Light clamp of 10 would cut the bright paths and
bias the mean and its variance low). Blender writes one EXR part per pass
(``ViewLayer.Combined``, ``ViewLayer.Depth``, ``ViewLayer.Denoising Albedo`` / ``Normal`` /
``Depth``; with ``--emission`` also ``ViewLayer.Emission`` and ``ViewLayer.Diffuse Color``),
and the sample count in the header attribute ``cycles.ViewLayer.samples``. Blender's
Denoising Albedo holds the emission of the lamps it sees (docs/renderers.md); the Emission
pass lets ``--from cycles`` take it out. ``cycles_fixtures.py`` beside it writes the test
files with every other pass too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def store_denoising_passes(scene) -> None:
    """Write the view layer's Denoising Data passes (albedo, normal, depth) and Z beside
    Combined, as one 32-bit multilayer EXR (a part per pass)."""
    layer = scene.view_layers[0]
    layer.cycles.denoising_store_passes = True
    layer.use_pass_z = True
    settings = scene.render.image_settings
    settings.media_type = "MULTI_LAYER_IMAGE"  # Blender 5.0; before: file_format only
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"


def cycles_scene(width: int, height: int):
    """An empty Blender scene (factory settings) rendered by Cycles on the CPU at ``width`` x
    ``height``, no denoising, no adaptive sampling, no clamping (Render Properties > Light
    Paths > Clamping: Direct and Indirect Light 0; Blender's default clamps indirect light at
    10): what every render of these scripts starts from. Returns the bpy scene."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.sample_clamp_direct = scene.cycles.sample_clamp_indirect = 0.0
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    return scene


def build_scene(spp: int, seed: int, width: int, height: int, name: str = "spheres",
                emission: bool = False):
    """Scene ``name`` (``spheres`` or ``window``, module docstring) at ``spp`` and ``seed``;
    ``emission``: also write the Emission and Diffuse Color passes."""
    import bpy

    scene = cycles_scene(width, height)
    scene.cycles.samples = spp
    scene.cycles.seed = seed
    if emission:
        layer = scene.view_layers[0]
        layer.use_pass_emit = layer.use_pass_diffuse_color = True
    if name == "window":
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from cycles_fixtures import build_scene as issue_scene  # beside it

        issue_scene()
        store_denoising_passes(scene)
        return scene
    if name != "spheres":
        raise SystemExit(f"unknown scene {name!r}: spheres or window")
    bpy.ops.mesh.primitive_plane_add(size=10)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1, location=(-0.6, 0, 1))
    glossy = bpy.data.materials.new("glossy")
    glossy.use_nodes = True
    shader = glossy.node_tree.nodes["Principled BSDF"]
    shader.inputs["Roughness"].default_value = 0.15
    shader.inputs["Metallic"].default_value = 1.0
    bpy.context.object.data.materials.append(glossy)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.15, location=(1.2, 0.5, 0.6))
    lamp = bpy.data.materials.new("lamp")
    lamp.use_nodes = True
    emission = lamp.node_tree.nodes["Principled BSDF"]
    emission.inputs["Emission Color"].default_value = (1.0, 0.8, 0.6, 1.0)
    emission.inputs["Emission Strength"].default_value = 50.0
    bpy.context.object.data.materials.append(lamp)
    bpy.ops.object.light_add(type="POINT", location=(2, -2, 4))
    bpy.context.object.data.energy = 500
    bpy.ops.object.camera_add(location=(0, -6, 3), rotation=(1.2, 0, 0))
    scene.camera = bpy.context.object
    store_denoising_passes(scene)
    return scene


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--size", default="32x24", help="WIDTHxHEIGHT")
    parser.add_argument("--scene", choices=("spheres", "window"), default="spheres")
    parser.add_argument("--emission", action="store_true",
                        help="also write the Emission and Diffuse Color passes")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    import bpy

    scene = build_scene(args.spp, args.seed, width, height, args.scene, args.emission)
    scene.render.filepath = args.out
    bpy.ops.render.render(write_still=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
