"""Scene files written as published collections write them: the camera and `$spp`-style
defaults in an included file, textures found through a `<path>` folder. They render through
`jaxden render`, `jaxden dataset build` and the Python API with jaxden's overrides (box
filter, independent sampler, film size) applied to the included sensor; a missing include, a
cycle of includes and an undefined `$name` are one-line errors."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from jaxden import cli
from jaxden.errors import SceneError
from jaxden.io.exr import read_frame, write_image
from jaxden.render.scene_xml import flatten_scene, parse_parameters

CAMERA = """<scene version="3.0.0">
    <default name="spp" value="8"/>
    <default name="resx" value="24"/>
    <default name="resy" value="16"/>
    <sensor type="perspective" id="camera">
        <float name="fov" value="40"/>
        <transform name="to_world">
            <lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="multijitter"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$resx"/>
            <integer name="height" value="$resy"/>
            <rfilter type="gaussian"/>
        </film>
    </sensor>
</scene>
"""

MAIN = """<scene version="3.0.0">
    <path value="textures"/>
    <include filename="include/camera.xml"/>
    <default name="light" value="1.5"/>
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    <bsdf type="diffuse" id="checker">
        <texture type="bitmap" name="reflectance">
            <string name="filename" value="checker.exr"/>
        </texture>
    </bsdf>
    <shape type="rectangle">
        <transform name="to_world"><scale value="2"/></transform>
        <ref id="checker"/>
    </shape>
    <emitter type="constant"><rgb name="radiance" value="$light"/></emitter>
</scene>
"""


@pytest.fixture()
def scene_dir(tmp_path):
    """main.xml + include/camera.xml + textures/checker.exr (a 2x2-tile checker)."""
    (tmp_path / "include").mkdir()
    (tmp_path / "textures").mkdir()
    (tmp_path / "include" / "camera.xml").write_text(CAMERA)
    (tmp_path / "main.xml").write_text(MAIN)
    tiles = (np.indices((16, 16)).sum(axis=0) // 8) % 2
    checker = np.repeat((0.1 + 0.8 * tiles)[..., None], 3, axis=-1).astype(np.float32)
    write_image(tmp_path / "textures" / "checker.exr", checker)
    return tmp_path


def test_flatten_inlines_the_include_and_substitutes_defaults(scene_dir):
    flat = flatten_scene(scene_dir / "main.xml")
    sensors = flat.root.findall("sensor")
    assert len(sensors) == 1 and sensors[0].get("id") == "camera"
    film = sensors[0].find("film")
    assert {e.get("name"): e.get("value") for e in film} == {"width": "24", "height": "16",
                                                               None: None}
    assert sensors[0].find("sampler/integer").get("value") == "8"
    assert flat.root.find("emitter/rgb").get("value") == "1.5"
    assert not flat.root.findall(".//default") and not flat.root.findall(".//include")
    assert not flat.root.findall(".//path")
    assert flat.search_path[0] == (scene_dir / "textures").resolve()
    assert flat.search_path[-1] == scene_dir.resolve()
    assert flat.parameters == {"spp": "8", "resx": "24", "resy": "16", "light": "1.5"}
    assert "$" not in ET.tostring(flat.root, encoding="unicode")


def test_caller_parameters_win_over_defaults(scene_dir):
    flat = flatten_scene(scene_dir / "main.xml", {"resx": "20", "light": "3"})
    assert flat.root.find("sensor/film/integer[@name='width']").get("value") == "20"
    assert flat.root.find("emitter/rgb").get("value") == "3"


def test_parameter_names_longest_match(tmp_path):
    """As Mitsuba replaces "$name" substrings: the longest defined name wins, and what
    follows a defined name stays ($a_x -> 1_x); a name with no defined prefix is an error."""
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0"><default name="a" value="1"/><default name="ab" value="2"/>'
        '<integer name="x" value="$ab"/><integer name="y" value="$a"/>'
        '<string name="z" value="$a_x"/></scene>')
    flat = flatten_scene(tmp_path / "s.xml")
    assert [e.get("value") for e in flat.root] == ["2", "1", "1_x"]
    (tmp_path / "s.xml").write_text('<scene version="3.0.0"><string name="z" value="$zz"/></scene>')
    with pytest.raises(SceneError, match=r"uses \$zz"):
        flatten_scene(tmp_path / "s.xml")


@pytest.mark.parametrize("value", ["nan", "1, inf, 1", "$s"])
def test_non_finite_geometry_is_refused(tmp_path, value):
    """Mitsuba drops a shape whose <scale> is NaN without a word; jaxden refuses the scene,
    also when the NaN comes through a parameter."""
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0"><default name="s" value="nan"/><shape type="sphere">'
        f'<transform name="to_world"><scale value="{value}"/></transform></shape></scene>')
    with pytest.raises(SceneError, match=r"s.xml.*<scale value=.* is not a finite number"):
        flatten_scene(tmp_path / "s.xml")


@pytest.mark.parametrize("case, pattern", [
    ("missing", r"included file 'include/nowhere.xml' not found"),
    ("cycle", r"cycle of includes: main.xml -> a.xml -> b.xml -> a.xml"),
    ("undefined", r"uses \$fov, which is not defined"),
    ("unused", r"parameter\(s\) sppp given"),
    ("path", r"folder 'no-such-folder' not found"),
])
def test_bad_scenes_raise_one_line_errors(scene_dir, case, pattern):
    main = scene_dir / "main.xml"
    parameters = {}
    if case == "missing":
        main.write_text(MAIN.replace("include/camera.xml", "include/nowhere.xml"))
    elif case == "cycle":
        (scene_dir / "a.xml").write_text('<scene version="3.0.0"><include filename="b.xml"/></scene>')
        (scene_dir / "b.xml").write_text('<scene version="3.0.0"><include filename="a.xml"/></scene>')
        main.write_text(MAIN.replace("include/camera.xml", "a.xml"))
    elif case == "undefined":
        (scene_dir / "include" / "camera.xml").write_text(CAMERA.replace('value="40"', 'value="$fov"'))
    elif case == "unused":
        parameters = {"sppp": "4"}
    elif case == "path":
        main.write_text(MAIN.replace('value="textures"', 'value="no-such-folder"'))
    with pytest.raises(SceneError, match=pattern) as info:
        flatten_scene(main, parameters)
    assert "\n" not in str(info.value)
    assert str(scene_dir) in str(info.value)  # names the file it is about


def test_parse_parameters():
    assert parse_parameters(["spp=4", "name=a=b"]) == {"spp": "4", "name": "a=b"}
    for bad in (["spp"], ["=4"], ["1x=2"], ["a=1", "a=2"]):
        with pytest.raises(SceneError):
            parse_parameters(bad)


@pytest.mark.parametrize("case, pattern", [
    ("missing", "included file 'include/nowhere.xml' not found"),
    ("cycle", "cycle of includes"),
    ("undefined", "uses $fov, which is not defined"),
])
def test_cli_render_bad_scene_is_one_line(scene_dir, capsys, case, pattern):
    main = scene_dir / "main.xml"
    if case == "missing":
        main.write_text(MAIN.replace("include/camera.xml", "include/nowhere.xml"))
    elif case == "cycle":
        (scene_dir / "include" / "camera.xml").write_text(
            CAMERA.replace("<default", '<include filename="main.xml"/><default', 1))
    else:
        (scene_dir / "include" / "camera.xml").write_text(CAMERA.replace('value="40"', 'value="$fov"'))
    out = scene_dir / "f.exr"
    code = cli.main(["render", str(main), "--spp", "2", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("jaxden: error: ")
    assert pattern in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def test_render_cli_api_and_dataset_apply_the_overrides(scene_dir, tmp_path, capsys):
    """One render through each front end; the included sensor gets the box filter, the
    independent sampler and the size; -D / parameters reach the included camera."""
    import mitsuba as mi

    from jaxden.render.core import render_frame
    from jaxden.render.load import load_scene

    main = scene_dir / "main.xml"
    scene = load_scene(main, parameters={"resx": "20"})
    sensor = scene.sensors()[0]
    assert tuple(sensor.film().size()) == (20, 16)
    assert str(sensor.film().rfilter()).startswith("BoxFilter")
    assert str(sensor.sampler()).startswith("IndependentSampler")
    assert isinstance(scene, mi.Scene)

    out = tmp_path / "cli.exr"
    code = cli.main(["render", str(main), "--spp", "4", "-D", "resx=20", "-D", "light=2",
                     "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    frame = read_frame(out)
    assert frame.color.shape == (16, 20, 3)
    # the texture was found through <path>: the checker's two reflectances show up
    api = render_frame(main, spp=4, parameters={"resx": "20", "light": "2"})
    np.testing.assert_array_equal(api.color, frame.color)
    assert np.isfinite(api.color).all() and api.color.std() > 0.05
    brighter = render_frame(main, spp=4, parameters={"resx": "20", "light": "4"})
    np.testing.assert_allclose(brighter.color.mean() / api.color.mean(), 2.0, rtol=0.02)

    config = tmp_path / "ds.toml"
    config.write_text(f'name = "xml"\nscenes = ["{main}"]\nsize = [24, 16]\ncrop_size = 8\n'
                      f'crops_per_scene = 1\nspp = [2]\nreference_spp = 4\nseed = 3\n'
                      f'[scene_parameters]\nlight = "2"\n[splits]\ntrain = 1.0\nval = 0.0\n')
    code = cli.main(["dataset", "build", str(config), "--out", str(tmp_path / "ds")])
    assert code == 0, capsys.readouterr().err
    files = sorted((tmp_path / "ds").rglob("*.exr"))
    assert len(files) == 2 and all(read_frame(f).color.shape == (8, 8, 3) for f in files)


def test_a_scene_mitsuba_loads_but_cannot_render_is_one_line(tmp_path):
    # A checkerboard as a bump map loads, but Mitsuba cannot differentiate it while rendering
    # (a RuntimeError from inside drjit.custom): one line naming the file and the plugin. In a
    # subprocess: after such a failure Mitsuba keeps the scene's textures registered, and
    # every later bump-mapped render in the same process fails the same way.
    from helpers import cli_env, run_jaxden

    scene = tmp_path / "bump.xml"
    scene.write_text("""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  </sensor>
  <emitter type="constant"/>
  <shape type="sphere"><bsdf type="bumpmap">
    <texture type="checkerboard" name="arbitrary"/>
    <bsdf type="diffuse"/>
  </bsdf></shape>
</scene>""")
    done = run_jaxden(tmp_path, cli_env(tmp_path / "cache"),
                      ["render", scene, "--spp", "1", "--out", tmp_path / "out.exr"])
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2, done.stderr
    assert len(lines) == 1 and lines[0].startswith("jaxden: error: "), done.stderr
    for word in (str(scene), "could not render", "eval_1_grad"):
        assert word in lines[0]
    assert not (tmp_path / "out.exr").exists()
