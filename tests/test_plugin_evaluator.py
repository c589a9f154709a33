"""A user's evaluator (jaxden.evaluate.register_evaluator in a plugin module) joins `jaxden
evaluate` as jaxden's own do: a sub-command made from its options dataclass (one typed flag a
field, defaults from the dataclass), a result with the plugin in its provenance, a clash with a
built-in name refused in one line, and the plugin found through JAXDEN_PLUGINS before a name is
called unknown.

The plugin modules are written into a temporary folder (not on sys.path), so that nothing but
the plugin mechanism can find them; each test leaves the registries and loaded plugins as it
found them."""

from __future__ import annotations

import json
import sys

import pytest
from helpers import build_tiny_dataset

from jaxden import plugins
from jaxden.cli import build_parser, main
from jaxden.errors import ConfigError
from jaxden.evaluate import EVALUATORS, get_evaluator, make_options
from jaxden.sure import SureSettings

#: The plugin: the mean colour and the MC RMSE against the reference per crop and spp of a
#: dataset split, summarised per spp (``lab-mean-colour``; ``lab_rmse`` runs in sweeps too);
#: and an evaluator whose options hold one field of every kind a flag reads (never run).
LAB_EVALUATORS = '''
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from jaxden.data.crops import iter_crops
from jaxden.evaluate import Evaluator, register_evaluator
from jaxden.sure import SureSettings


@dataclasses.dataclass(frozen=True)
class MeanColourOptions:
    split: str = "val"
    spp: tuple[int, ...] = ()
    scale: float = dataclasses.field(default=1.0, metadata={"help": "multiplies the colour"})


def run(data, options, progress=False):
    rows = []
    for crop, reference, inputs in iter_crops(data, options.split, options.spp or None,
                                              min_spp=1):
        for spp, frame in inputs:
            colour = options.scale * np.asarray(frame.color, np.float64)
            error = colour - np.asarray(reference.color, np.float64)
            rows.append({"crop": crop.id, "spp": spp,
                         "mean": [float(v) for v in colour.mean(axis=(0, 1))],
                         "rmse": float(np.sqrt(np.mean(error ** 2)))})
    return rows


def summarize(rows, provenance):
    levels = sorted({row["spp"] for row in rows})
    return {"summary": {str(spp): float(np.mean([r["rmse"] for r in rows if r["spp"] == spp]))
                        for spp in levels}}


def table(fields, rows, provenance):
    lines = ["| spp | MC RMSE |", "|---:|---:|"]
    return "\\n".join(lines + [f"| {spp} | {rmse:.4f} |"
                               for spp, rmse in fields["summary"].items()])


register_evaluator(Evaluator(
    name="lab-mean-colour", description="mean colour and MC RMSE per spp (lab plugin)",
    options=MeanColourOptions, run=run, summarize=summarize, table=table,
    provenance=lambda options: {"scale": options.scale, "spp": list(options.spp)}))

register_evaluator(Evaluator(
    name="lab_rmse", description="MC RMSE per spp, in sweeps too (lab plugin)",
    options=MeanColourOptions, run=run, summarize=summarize, table=table,
    provenance=lambda options: {},
    sweep_options=lambda run_dir, table: MeanColourOptions(split=table["split"]),
    sweep_key="lab", sweep_columns=lambda summary: {"MC RMSE": max(summary.values())}))


@dataclasses.dataclass(frozen=True)
class EveryKindOptions:
    label: str
    count: int = 3
    weight: float = 0.5
    normalise: bool = True
    levels: tuple[int, ...] = (1, 4)
    names: tuple[str, ...] = ()
    mode: Literal["fast", "exact"] = "fast"
    limit: int | None = None
    sure: SureSettings = SureSettings(probes=2)
    table: dict = dataclasses.field(default_factory=dict)


register_evaluator(Evaluator(
    name="lab-every-kind", description="one option of each kind (lab plugin)",
    options=EveryKindOptions, run=run, summarize=summarize, table=table,
    provenance=lambda options: {}))
'''


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny synthetic dataset (one val crop of 32 x 32 pixels at 2, 8 and 32 spp)."""
    return build_tiny_dataset(tmp_path_factory.mktemp("plugin-evaluator") / "tiny")


@pytest.fixture
def isolated(monkeypatch):
    """The evaluator registry, the loaded plugins and their modules as the test found them
    (loading a plugin registers, imports and writes JAXDEN_PLUGINS for good)."""
    monkeypatch.setenv(plugins.ENV, "")  # recorded, so that what loading writes is undone
    monkeypatch.delenv(plugins.ENV)
    monkeypatch.setenv("PYTHONPATH", "")
    entries, owners = dict(EVALUATORS), dict(EVALUATORS.owners)
    loaded, modules = dict(plugins._LOADED), set(sys.modules)
    yield monkeypatch
    EVALUATORS.clear()
    EVALUATORS.update(entries)
    EVALUATORS.owners.clear()
    EVALUATORS.owners.update(owners)
    plugins._LOADED.clear()
    plugins._LOADED.update(loaded)
    for name in set(sys.modules) - modules:
        if name.startswith("lab_") or name.endswith("_evaluator"):
            del sys.modules[name]


def write_plugin(folder, name="lab_evaluators.py", source=LAB_EVALUATORS):
    path = folder / name
    path.write_text(source)
    return path


def test_a_plugins_evaluator_runs_through_jaxden_evaluate(tiny, tmp_path, isolated, capsys):
    plugin = write_plugin(tmp_path)
    out = tmp_path / "results" / "mean"
    assert main(["evaluate", "lab-mean-colour", "--plugin", str(plugin), "--data", str(tiny),
                 "--spp", "2", "32", "--scale", "1.0", "--out", str(out)]) == 0
    result = json.loads(out.with_suffix(".json").read_text())
    assert EVALUATORS.owner("lab-mean-colour") == "lab_evaluators"
    assert sorted(result["summary"]) == ["2", "32"]
    assert result["summary"]["2"] > result["summary"]["32"] > 0  # MC error falls with spp
    assert {row["spp"] for row in result["rows"]} == {2, 32}
    assert all(len(row["mean"]) == 3 for row in result["rows"])
    provenance = result["provenance"]
    assert provenance["plugins"][0]["module"] == "lab_evaluators"
    assert provenance["plugins"][0]["file"] == str(plugin)
    assert provenance["scale"] == 1.0 and provenance["spp"] == [2, 32]
    assert provenance["dataset"]["split"] == "val"
    assert "| 32 |" in out.with_suffix(".md").read_text()
    assert "Traceback" not in capsys.readouterr().err
    # --from-json re-tabulates without measuring
    assert main(["evaluate", "lab-mean-colour", "--plugin", str(plugin), "--data", "unused",
                 "--from-json", str(out.with_suffix(".json")), "--out", str(tmp_path / "again")
                 ]) == 0
    assert json.loads((tmp_path / "again.json").read_text())["rows"] == result["rows"]


def test_the_evaluate_help_lists_a_plugins_evaluator_and_its_flags(tmp_path, isolated,
                                                                    capsys):
    plugin = write_plugin(tmp_path)
    with pytest.raises(SystemExit):
        main(["--plugin", str(plugin), "evaluate", "--help"])
    assert "lab-mean-colour" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--plugin", str(plugin), "evaluate", "lab-mean-colour", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for words in ("--data DATA", "--out OUT", "--from-json", "--keep-current",
                  "--split SPLIT default: val", "--spp SPP [SPP ...]",
                  "--scale SCALE multiplies the colour; default: 1.0"):
        assert words in text, words


def test_generic_flags_parse_types_and_defaults(tmp_path, isolated):
    plugins.load([str(write_plugin(tmp_path))])
    parser = build_parser()

    def options(*words):
        args = parser.parse_args(["evaluate", "lab-every-kind", "--data", "d", "--out", "o",
                                  *words])
        return make_options("lab-every-kind", **args.evaluate_options(args))

    defaults = options("--label", "x")
    assert (defaults.label, defaults.count, defaults.weight, defaults.normalise) == (
        "x", 3, 0.5, True)
    assert (defaults.levels, defaults.names, defaults.mode, defaults.limit) == (
        (1, 4), (), "fast", None)
    assert defaults.sure == SureSettings(probes=2) and defaults.table == {}
    given = options("--label", "y", "--count", "7", "--weight", "2.5", "--no-normalise",
                    "--levels", "8", "16", "--names", "a", "b", "--mode", "exact",
                    "--limit", "4", "--seed", "9", "--probe-dist", "rademacher")
    assert (given.label, given.count, given.weight, given.normalise) == ("y", 7, 2.5, False)
    assert (given.levels, given.names, given.mode, given.limit) == (
        (8, 16), ("a", "b"), "exact", 4)
    assert isinstance(given.count, int) and isinstance(given.weight, float)
    assert given.sure == SureSettings(probes=2, seed=9, probe_dist="rademacher")
    # wrong types and values, a missing required option: argparse's error, exit 2
    for words in (["--label", "x", "--count", "many"], ["--label", "x", "--mode", "slow"],
                  ["--label", "x", "--probes", "0"], []):
        with pytest.raises(SystemExit) as stopped:
            options(*words)
        assert stopped.value.code == 2


def test_a_plugins_evaluator_runs_in_sweeps(tiny, tmp_path, isolated):
    """Its name is an [evaluate] key of a sweep once the plugin is loaded, and a trained
    run's evaluations hold its summary under its sweep key."""
    from jaxden.evaluate import evaluate_run
    from jaxden.evaluate.registry import evaluate_table_class, evaluator_of_sweep_key

    plugins.load([str(write_plugin(tmp_path))])
    table = evaluate_table_class()(lab_rmse=(str(tiny),), split="val")
    assert table.lab_rmse == (str(tiny),)
    evaluations = evaluate_run(tmp_path / "run", {"lab_rmse": [str(tiny)], "split": "val"},
                               "wskp")
    summary = evaluations[f"lab:{tiny}"]
    assert sorted(summary, key=int) == ["2", "8", "32"]
    assert evaluator_of_sweep_key("lab").sweep_columns(summary) == {"MC RMSE": summary["2"]}


def test_an_evaluator_named_like_a_built_in_is_one_line(tmp_path, isolated, capsys):
    clash = write_plugin(tmp_path, "clashing_evaluator.py", (
        "import dataclasses\n"
        "from jaxden.evaluate import Evaluator, register_evaluator\n"
        "@dataclasses.dataclass(frozen=True)\nclass Options:\n    split: str = 'test'\n"
        "register_evaluator(Evaluator('pd', 'not PD', Options, None, None, None, None))\n"))
    assert main(["--plugin", str(clash), "evaluate", "--help"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("jaxden: error: evaluator name 'pd' from module 'clashing_evaluator' "
                   "clashes with jaxden's built-in evaluator 'pd'; register it under another "
                   "name")
    assert EVALUATORS.owner("pd") == "jaxden.evaluate.pd"


def test_evaluators_that_cannot_have_a_command_are_refused_at_registration(isolated):
    import dataclasses

    from jaxden.evaluate import Evaluator, register_evaluator

    @dataclasses.dataclass(frozen=True)
    class Shadowing:
        out: str = ""
        seed: int = 0
        sure: SureSettings = dataclasses.field(default_factory=SureSettings)

    @dataclasses.dataclass(frozen=True)
    class Plain:
        split: str = "test"

    def evaluator(name, options, **extra):
        return Evaluator(name, "x", options, None, None, None, None, **extra)

    with pytest.raises(ConfigError, match=r"option\(s\) out, seed would shadow flags of "
                                          r"`jaxden evaluate lab-shadow` itself"):
        register_evaluator(evaluator("lab-shadow", Shadowing))
    with pytest.raises(ConfigError, match="options must be a dataclass"):
        register_evaluator(evaluator("lab-dict", dict))
    with pytest.raises(ConfigError, match="must be a Python identifier \\(e.g. 'lab_sweep'\\)"):
        register_evaluator(evaluator("lab-sweep", Plain,
                                     sweep_options=lambda run, table: None))
    assert not {"lab-shadow", "lab-dict", "lab-sweep"} & set(EVALUATORS)


def test_an_unknown_evaluator_loads_ambient_plugins_then_says_how_to_add_one(tmp_path,
                                                                            isolated):
    isolated.setenv(plugins.ENV, str(write_plugin(tmp_path, "lab_ambient.py")))
    assert get_evaluator("lab-mean-colour").description.endswith("(lab plugin)")
    assert EVALUATORS.owner("lab-mean-colour") == "lab_ambient"
    with pytest.raises(ConfigError, match="no evaluator named 'psnr'; the evaluators: pd, "
                                          ".*lab-mean-colour.*register_evaluator in a plugin "
                                          "module.*docs/your-denoiser.md"):
        get_evaluator("psnr")
