"""Render a Blender Cycles training set in the layout of `jaxden dataset import`: procedural
scenes, several camera views each, low-spp inputs with the Denoising Data passes and a merged
high-spp reference per view. Runs in Blender's own Python (``pip install bpy``, a venv of its
own); nothing of jaxden is imported.

    $JAXDEN_HOME/bpy-venv/bin/python experiments/renderers/cycles_dataset.py \\
        --out $JAXDEN_HOME/cycles-src
    jaxden dataset import $JAXDEN_HOME/cycles-src --from cycles --crop 128 \\
        --crops-per-view 4 --val s06v0,s06v1 --held-out s07v0,s07v1,s08v0,s08v1 \\
        --out $JAXDEN_HOME/data/cycles

Written per view (``SRC/s<scene>v<view>/``, the import layout, docs/your-renderer.md):
``spp1.exr`` (one 1-sample render), ``spp2/b0..b1.exr`` and ``spp4/b0..b3.exr`` (independent
1-sample renders that the import merges into 2- and 4-spp inputs with the variance of their
mean), ``reference/b0..b3.exr`` (4 renders of --reference-spp / 4 samples; 256 spp by
default, as the references WSKP-6 was trained against, experiments/configs/dataset-rt.toml).
Every render has its own seed (CRC-32 of its file name and --seed). Multilayer EXR, 32-bit
float, with the Combined, Depth, Emission and Denoising Albedo / Normal / Depth passes, which
`--from cycles` reads as the colour and WSKP-6's features (colour, albedo, normal, depth; the
Denoising Albedo, which holds the light of the lamps it sees, is read clipped to [0, 1], and
the Emission pass is kept as the frames' emission, for ``:emission=separate``). The
defaults make 9 scenes of 2 views at 256 x 256: 12 views to train on (scenes 0-5), 2 to
validate (scene 6) and 4 held out (scenes 7, 8).

The scenes are none of jaxden's Mitsuba scenes: for each scene seed, a floor (plain or
checkered) and sometimes a back wall, 3..6 objects among spheres, cubes, cylinders, cones,
tori, icospheres and Suzanne, each diffuse, plastic, glossy metal (roughness 0.03..0.35) or
glass; one area, point, spot or sun lamp, a dim coloured sky, and 1..2 small emissive spheres
(radius 0.04..0.12, strength 50..400: small bright lights, also seen in reflections); each
view a camera on a circle around the objects (radius 5..8, height 1..4, lens 28..55 mm).
Cycles on the CPU as a plain Monte Carlo estimator: no adaptive sampling, no denoising, no
clamping, a one-pixel box filter, Blender's default light paths; the scene data persist
between the renders of a scene (the BVH is built once).

Time, measured on the project's 2-core machine (Blender 5.0.1) while other jobs kept its load
average at 7-10, so in CPU seconds: the 9 scenes with one view each and 32-spp references
took 117 CPU-s (228 s wall): about 0.4 CPU-s per 1-sample render, 160-250 k samples per CPU-s
for the references, scene 7 the slowest (1.33 times the mean); scene 7's first view at the
defaults took 113 CPU-s (257 s wall), scene 0's at 1024 spp 268 CPU-s. The defaults (18 views,
7 one-sample renders and 256 reference samples each) so come to about 1500 CPU-s: 13 min on
two free cores, 25 min on one.

Resumable: a finished file is kept (files are written under a hidden name and renamed), so
rerunning the command renders only what is missing. ``--time`` prints each render's seconds;
``--scenes 1 --views 1`` is the small case to time before sizing a full run.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import sys
import time
import warnings
import zlib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cycles_render import cycles_scene, store_denoising_passes  # the fixtures' script, beside it

# Blender 5 deprecates `use_nodes` (nodes are always on from 6.0); 4.x still needs it set.
warnings.filterwarnings("ignore", message=".*use_nodes.*", category=DeprecationWarning)

INPUT_BUFFERS = {1: 0, 2: 2, 4: 4}  # level -> 1-spp buffers (0: one file spp<N>.exr)
REFERENCE_BUFFERS = 4


# ----------------------------------------------------------------------------- the scene
def _material(name: str, rng: random.Random, kind: str):
    import bpy

    material = bpy.data.materials.new(name)
    material.use_nodes = True
    shader = material.node_tree.nodes["Principled BSDF"]
    colour = [rng.uniform(0.1, 0.9) for _ in range(3)] + [1.0]
    shader.inputs["Base Color"].default_value = colour
    if kind == "diffuse":
        shader.inputs["Roughness"].default_value = 1.0
    elif kind == "plastic":
        shader.inputs["Roughness"].default_value = rng.uniform(0.05, 0.3)
    elif kind == "metal":
        shader.inputs["Metallic"].default_value = 1.0
        shader.inputs["Roughness"].default_value = rng.uniform(0.03, 0.35)
    elif kind == "glass":
        shader.inputs["Base Color"].default_value = [1.0, 1.0, 1.0, 1.0]
        shader.inputs["Transmission Weight"].default_value = 1.0
        shader.inputs["Roughness"].default_value = rng.uniform(0.0, 0.1)
        shader.inputs["IOR"].default_value = 1.5
    elif kind == "checker":
        nodes, links = material.node_tree.nodes, material.node_tree.links
        checker = nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = rng.uniform(4.0, 16.0)
        checker.inputs["Color1"].default_value = colour
        checker.inputs["Color2"].default_value = [c * 0.3 for c in colour[:3]] + [1.0]
        links.new(checker.outputs["Color"], shader.inputs["Base Color"])
        shader.inputs["Roughness"].default_value = rng.uniform(0.4, 1.0)
    return material


def _emitter(name: str, strength: float, colour):
    import bpy

    material = bpy.data.materials.new(name)
    material.use_nodes = True
    shader = material.node_tree.nodes["Principled BSDF"]
    shader.inputs["Base Color"].default_value = [0.0, 0.0, 0.0, 1.0]
    shader.inputs["Emission Color"].default_value = list(colour) + [1.0]
    shader.inputs["Emission Strength"].default_value = strength
    return material


def _add_object(rng: random.Random, index: int, position):
    import bpy

    shape = rng.choice(("sphere", "cube", "cylinder", "cone", "torus", "ico", "monkey"))
    size = rng.uniform(0.35, 0.9)
    x, y = position
    if shape == "sphere":
        bpy.ops.mesh.primitive_uv_sphere_add(radius=size, location=(x, y, size),
                                             segments=48, ring_count=24)
    elif shape == "cube":
        bpy.ops.mesh.primitive_cube_add(size=1.6 * size, location=(x, y, 0.8 * size))
    elif shape == "cylinder":
        bpy.ops.mesh.primitive_cylinder_add(radius=0.7 * size, depth=2 * size,
                                            location=(x, y, size), vertices=48)
    elif shape == "cone":
        bpy.ops.mesh.primitive_cone_add(radius1=size, depth=2 * size, location=(x, y, size),
                                        vertices=48)
    elif shape == "torus":
        bpy.ops.mesh.primitive_torus_add(major_radius=size, minor_radius=0.3 * size,
                                         location=(x, y, 0.3 * size))
    elif shape == "ico":
        bpy.ops.mesh.primitive_ico_sphere_add(radius=size, location=(x, y, size),
                                              subdivisions=2)
    else:
        bpy.ops.mesh.primitive_monkey_add(size=1.6 * size, location=(x, y, 0.8 * size))
    obj = bpy.context.object
    obj.rotation_euler[2] = rng.uniform(0.0, 2 * math.pi)
    if shape in ("sphere", "cylinder", "cone", "torus", "monkey"):
        bpy.ops.object.shade_smooth()
    kind = rng.choices(("diffuse", "plastic", "metal", "glass"), weights=(3, 3, 3, 1))[0]
    obj.data.materials.append(_material(f"m{index}", rng, kind))
    return size


def _add_light(rng: random.Random, centre) -> None:
    import bpy

    kind = rng.choice(("AREA", "POINT", "SPOT", "SUN"))
    light = bpy.data.lights.new("lamp", type=kind)
    light.color = [rng.uniform(0.8, 1.0) for _ in range(3)]
    if kind == "SUN":
        light.energy = rng.uniform(2.0, 5.0)
        light.angle = math.radians(rng.uniform(0.5, 5.0))
    elif kind == "AREA":
        light.energy = rng.uniform(300.0, 1000.0)
        light.size = rng.uniform(0.5, 2.0)
    else:  # point and spot: small sources, hard shadows
        light.energy = rng.uniform(300.0, 1500.0)
        light.shadow_soft_size = rng.uniform(0.02, 0.3)
        if kind == "SPOT":
            light.spot_size = math.radians(rng.uniform(40.0, 80.0))
    lamp = bpy.data.objects.new("lamp", light)
    bpy.context.scene.collection.objects.link(lamp)
    angle = rng.uniform(0.0, 2 * math.pi)
    lamp.location = (centre[0] + 3 * math.cos(angle), centre[1] + 3 * math.sin(angle),
                     rng.uniform(3.0, 6.0))
    _look_at(lamp, (centre[0], centre[1], 0.0))


def _look_at(obj, target) -> None:
    from mathutils import Vector

    direction = Vector(target) - Vector(obj.location)
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def build_scene(scene_seed: int, width: int, height: int):
    """The scene of ``scene_seed`` (module docstring) with Cycles' settings; returns the
    bpy scene and the point the cameras look at."""
    import bpy

    rng = random.Random(scene_seed)
    scene = cycles_scene(width, height)  # no clamping, no denoising, no adaptive sampling
    scene.cycles.pixel_filter_type = "BOX"  # one pixel's samples per pixel, as jaxden's data
    scene.cycles.filter_width = 1.0
    scene.render.use_persistent_data = True
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    background = world.node_tree.nodes["Background"]
    background.inputs["Color"].default_value = [rng.uniform(0.3, 1.0) for _ in range(3)] + [1.0]
    background.inputs["Strength"].default_value = rng.uniform(0.03, 0.3)
    scene.world = world
    bpy.ops.mesh.primitive_plane_add(size=30)
    floor = "checker" if rng.random() < 0.5 else "diffuse"
    bpy.context.object.data.materials.append(_material("floor", rng, floor))
    if rng.random() < 0.5:
        bpy.ops.mesh.primitive_plane_add(size=30, location=(0, 4, 0), rotation=(math.pi / 2, 0, 0))
        bpy.context.object.data.materials.append(_material("wall", rng, "diffuse"))
    count = rng.randint(3, 6)
    positions = []
    for index in range(count):
        for _ in range(50):  # rejection: objects apart
            spot = (rng.uniform(-2.2, 2.2), rng.uniform(-1.8, 2.0))
            if all(math.dist(spot, p) > 1.3 for p in positions):
                break
        positions.append(spot)
        _add_object(rng, index, spot)
    centre = (sum(p[0] for p in positions) / count, sum(p[1] for p in positions) / count)
    _add_light(rng, centre)
    for index in range(rng.randint(1, 2)):
        radius = rng.uniform(0.04, 0.12)
        bpy.ops.mesh.primitive_uv_sphere_add(
            radius=radius, location=(rng.uniform(-2.5, 2.5), rng.uniform(-2.0, 2.5),
                                     rng.uniform(radius, 2.5)))
        colour = (1.0, rng.uniform(0.6, 1.0), rng.uniform(0.3, 1.0))
        bpy.context.object.data.materials.append(
            _emitter(f"bulb{index}", rng.uniform(50.0, 400.0), colour))
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    store_denoising_passes(scene)
    # The Denoising Albedo holds the emission of the bulbs it sees (--from cycles reads it
    # clipped to [0, 1]); the Emission pass is the frames' emission (docs/renderers.md).
    scene.view_layers[0].use_pass_emit = True
    return scene, (centre[0], centre[1], 0.5)


def place_camera(scene, rng: random.Random, target) -> None:
    camera = scene.camera
    angle = rng.uniform(-0.75 * math.pi, -0.25 * math.pi)  # in front of the wall (y < 4)
    radius = rng.uniform(5.0, 8.0)
    camera.location = (target[0] + radius * math.cos(angle), target[1] + radius * math.sin(angle),
                       rng.uniform(1.0, 4.0))
    camera.data.lens = rng.uniform(28.0, 55.0)
    _look_at(camera, (target[0] + rng.uniform(-0.5, 0.5), target[1] + rng.uniform(-0.5, 0.5),
                      target[2]))


# ----------------------------------------------------------------------------- renders
def render_file(scene, path: Path, spp: int, base_seed: int, relative: str) -> float | None:
    """Render ``path`` at ``spp`` (seed from its name) unless it exists; seconds or None."""
    import bpy

    if path.exists():
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.partial.exr")
    scene.cycles.samples = spp
    scene.cycles.seed = zlib.crc32(f"{base_seed}/{relative}".encode()) & 0x7FFFFFFF
    scene.render.filepath = str(partial)
    start = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    seconds = time.perf_counter() - start
    os.replace(partial, path)
    return seconds


def view_files(reference_spp: int) -> list[tuple[str, int]]:
    """``(path in the view folder, spp)`` of every render of one view, inputs first."""
    files = []
    for level, buffers in INPUT_BUFFERS.items():
        if buffers == 0:
            files.append((f"spp{level}.exr", level))
        else:
            files += [(f"spp{level}/b{k}.exr", level // buffers) for k in range(buffers)]
    per_buffer = reference_spp // REFERENCE_BUFFERS
    files += [(f"reference/b{k}.exr", per_buffer) for k in range(REFERENCE_BUFFERS)]
    return files


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="the source folder to write")
    parser.add_argument("--scenes", type=int, default=9, help="procedural scenes (default 9)")
    parser.add_argument("--views", type=int, default=2, help="camera views per scene (default 2)")
    parser.add_argument("--first-scene", type=int, default=0,
                        help="index of the first scene (default 0)")
    parser.add_argument("--size", default="256x256", help="WIDTHxHEIGHT (default 256x256)")
    parser.add_argument("--reference-spp", type=int, default=256,
                        help=f"the reference's samples, {REFERENCE_BUFFERS} renders of a quarter "
                             f"each (default 256)")
    parser.add_argument("--seed", type=int, default=0, help="scene and sampler seeds (default 0)")
    parser.add_argument("--time", action="store_true", help="print each render's seconds")
    args = parser.parse_args(argv)
    if args.reference_spp % REFERENCE_BUFFERS:
        parser.error(f"--reference-spp must be a multiple of {REFERENCE_BUFFERS}")
    width, height = (int(v) for v in args.size.lower().split("x"))
    totals: dict[str, float] = {}
    start = time.perf_counter()
    for scene_index in range(args.first_scene, args.first_scene + args.scenes):
        scene_seed = zlib.crc32(f"{args.seed}/scene{scene_index}".encode())
        names = [f"s{scene_index:02d}v{v}" for v in range(args.views)]
        todo = [(name, file, spp) for name in names for file, spp in
                view_files(args.reference_spp) if not (args.out / name / file).exists()]
        if not todo:
            continue
        scene, target = build_scene(scene_seed, width, height)
        for name in names:
            place_camera(scene, random.Random(zlib.crc32(f"{args.seed}/{name}".encode())),
                         target)
            for file, spp in view_files(args.reference_spp):
                relative = f"{name}/{file}"
                seconds = render_file(scene, args.out / relative, spp, args.seed, relative)
                if seconds is not None:
                    kind = "reference" if file.startswith("reference") else "input"
                    totals[kind] = totals.get(kind, 0.0) + seconds
                    if args.time:
                        print(f"{relative}: {spp} spp, {seconds:.2f} s", flush=True)
    wall = time.perf_counter() - start
    print(f"done in {wall:.1f} s (renders: inputs {totals.get('input', 0.0):.1f} s, references "
          f"{totals.get('reference', 0.0):.1f} s) -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
