"""Write the Blender Cycles test files of tests/data/cycles/: one small scene rendered with every
pass a Blender user may enable, plainly, with Cycles' denoiser on, and with adaptive sampling
on, as Blender itself saves them. Runs in Blender's own Python (``pip install bpy==5.0.1`` in a
venv of its own); nothing of jaxden is imported.

    /root/bpy-venv/bin/python experiments/renderers/cycles_fixtures.py --out tests/data/cycles

The scene (the one of jaxden issue 48, at 24 x 16 pixels): a floor, a wall with a window that
a sun shines through, a small emissive sphere of strength 400, a gold Suzanne and a glossy
torus; Cycles on the CPU, no clamping (``sample_clamp_direct = sample_clamp_indirect = 0``).
Each file is a 32-bit multilayer EXR (Blender 5: Media Type Multi-Layer EXR) with the view
layer's passes Combined, Z, Position, Normal, Diffuse Color, Emission, Denoising Data and
Debug Sample Count:

=============================  ===============================================================
file                           render settings
=============================  ===============================================================
passes-seed1.exr, -seed2.exr   4 samples, no denoising, no adaptive sampling (seeds 1, 2)
passes-seed1-again.exr         seed 1 once more: Cycles does not repeat a render bit for bit
                               (about 30 % of the values change by rounding)
denoised-seed1.exr, -seed2     the same renders with Render > Denoise on (OpenImageDenoise):
                               Blender adds the Noisy Image pass, Combined is denoised
adaptive-seed1.exr, -seed2     adaptive sampling on (Noise Threshold 0.1, Max Samples 64):
                               Debug Sample Count below 1 where a pixel stopped early
single-layer.exr               passes-seed1's settings saved as a plain (single-layer) OpenEXR
=============================  ===============================================================

About 20 KB a file; the whole set renders in a few seconds.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cycles_render import cycles_scene, store_denoising_passes  # beside it

warnings.filterwarnings("ignore", message=".*use_nodes.*", category=DeprecationWarning)

SIZE = (24, 16)
SPP = 4
#: file stem -> (seed, denoise, adaptive, multilayer)
FILES = {
    "passes-seed1": (1, False, False, True),
    "passes-seed2": (2, False, False, True),
    "passes-seed1-again": (1, False, False, True),
    "denoised-seed1": (1, True, False, True),
    "denoised-seed2": (2, True, False, True),
    "adaptive-seed1": (1, False, True, True),
    "adaptive-seed2": (2, False, True, True),
    "single-layer": (1, False, False, False),
}


def _material(name: str, colour, *, metallic=0.0, roughness=0.5, emission=0.0):
    import bpy

    material = bpy.data.materials.new(name)
    material.use_nodes = True
    shader = material.node_tree.nodes["Principled BSDF"]
    shader.inputs["Base Color"].default_value = (*colour, 1.0)
    shader.inputs["Metallic"].default_value = metallic
    shader.inputs["Roughness"].default_value = roughness
    if emission:
        shader.inputs["Emission Color"].default_value = (*colour, 1.0)
        shader.inputs["Emission Strength"].default_value = emission
    return material


def _add(operator, material, **kwargs):
    import bpy

    operator(**kwargs)
    bpy.context.object.data.materials.append(material)
    return bpy.context.object


def build_scene():
    """The objects, lights and camera (into the current, empty scene)."""
    import bpy

    mesh = bpy.ops.mesh
    grey = _material("grey", (0.6, 0.6, 0.6), roughness=1.0)
    _add(mesh.primitive_plane_add, grey, size=12)
    # A back wall of four blocks around a square window.
    for location, scale in (((0, 3, 0.6), (4, 0.1, 0.6)), ((0, 3, 3.4), (4, 0.1, 0.6)),
                            ((-2.5, 3, 2), (1.5, 0.1, 0.8)), ((2.5, 3, 2), (1.5, 0.1, 0.8))):
        _add(mesh.primitive_cube_add, grey, location=location, scale=scale)
    gold = _material("gold", (1.0, 0.77, 0.34), metallic=1.0, roughness=0.2)
    _add(mesh.primitive_monkey_add, gold, size=1.2, location=(-0.9, 0.5, 0.7),
         rotation=(0, 0, math.radians(-20)))
    glossy = _material("glossy", (0.2, 0.4, 0.8), metallic=0.0, roughness=0.05)
    _add(mesh.primitive_torus_add, glossy, location=(1.2, 0, 0.35), major_radius=0.6,
         minor_radius=0.2)
    lamp = _material("lamp", (1.0, 0.85, 0.7), emission=400.0)
    _add(mesh.primitive_uv_sphere_add, lamp, radius=0.08, location=(0.3, -0.6, 1.1))
    # The sun shines from behind the wall, down towards the camera: a patch of floor in the
    # window's light, the rest lit by bounces, the lamp and a dim sky.
    bpy.ops.object.light_add(type="SUN", location=(0, 6, 5), rotation=(math.radians(-50), 0, 0))
    bpy.context.object.data.energy = 5.0
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.05
    bpy.context.scene.world = world
    bpy.ops.object.camera_add(location=(0, -6, 2.2), rotation=(math.radians(80), 0, 0))
    bpy.context.scene.camera = bpy.context.object


def enable_every_pass(scene) -> None:
    """View Layer Properties > Passes: Data > Combined, Z, Position, Normal, Denoising Data,
    Debug > Sample Count; Light > Diffuse > Color, Other > Emission."""
    layer = scene.view_layers[0]
    store_denoising_passes(scene)
    for name in ("use_pass_combined", "use_pass_z", "use_pass_position", "use_pass_normal",
                 "use_pass_diffuse_color", "use_pass_emit"):
        setattr(layer, name, True)
    layer.cycles.pass_debug_sample_count = True


def render(out: Path, seed: int, denoise: bool, adaptive: bool, multilayer: bool) -> None:
    import bpy

    scene = cycles_scene(*SIZE)  # no denoising, no adaptive sampling, no clamping
    build_scene()
    scene.cycles.seed = seed
    scene.cycles.samples = SPP
    enable_every_pass(scene)
    if denoise:
        scene.cycles.use_denoising = True
    if adaptive:
        scene.cycles.use_adaptive_sampling = True
        scene.cycles.adaptive_threshold = 0.1
        scene.cycles.samples = 64
    if not multilayer:
        settings = scene.render.image_settings
        settings.media_type = "IMAGE"
        settings.file_format = "OPEN_EXR"
        settings.color_depth = "32"
    scene.render.filepath = str(out)
    bpy.ops.render.render(write_still=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="the folder (tests/data/cycles)")
    args = parser.parse_args(argv)
    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    for stem, settings in FILES.items():
        render(folder / f"{stem}.exr", *settings)
    return 0


if __name__ == "__main__":
    sys.exit(main())
