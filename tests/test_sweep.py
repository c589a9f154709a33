"""Sweeps (jaxden/sweep.py, `jaxden sweep`): planning from a sweep file, clear errors, and a
tiny mixer sweep end to end (Mitsuba-free data): every run trained and evaluated in its own
folder, a summary with the spread over seeds, and a rerun that skips finished runs."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from jaxden.cli import main
from jaxden.config import load_config
from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig
from jaxden.errors import ConfigError
from jaxden.render.synthetic import synthetic_render
from jaxden.sweep import load_sweep, plan_runs, run_sweep
from jaxden.train.config import load_train_config

ROOT = Path(__file__).resolve().parent.parent
TINY_MIXER = ROOT / "experiments" / "configs" / "mixer-tiny.toml"


def write_sweep(folder: Path, body: str, base: Path = TINY_MIXER) -> Path:
    path = folder / "sweep.toml"
    path.write_text(f'base = "{base}"\n' + body)
    return path


def pd_over_denoiser_rmse(run_dir, dataset, split, spp, seed=0, probes=4):
    """The sweep summary's headline PD / denoiser RMSE, recomputed from the files: the mixer
    saved in ``run_dir`` run by progressive_denoise on every (crop, spp) of ``split`` (SURE key
    fold_in(PRNGKey(seed), i) for the i-th), RMSE of PD and of the denoiser against the
    reference, crop means per spp, the ratio per spp, the mean of those ratios."""
    import jax
    import numpy as np

    from jaxden.data.crops import iter_crops
    from jaxden.progressive.mixer import load_mixer
    from jaxden.progressive.pipeline import progressive_denoise

    params, config = load_mixer(run_dir)
    errors: dict[int, list[tuple[float, float]]] = {}
    index = 0
    for _, reference, inputs in iter_crops(dataset, split, spp):
        truth = np.asarray(reference.color, np.float64)
        for level, frame in inputs:
            key = jax.random.fold_in(jax.random.PRNGKey(seed), index)
            z, _, extras = progressive_denoise(frame, config.denoiser, params, config, key,
                                               num_probes=probes)
            index += 1
            rmse = [float(np.sqrt(np.mean((np.asarray(image, np.float64) - truth) ** 2)))
                    for image in (z, extras["denoised"])]
            errors.setdefault(level, []).append(tuple(rmse))
    assert sorted(errors) == sorted(spp) and index >= 2
    return float(np.mean([np.mean([e[0] for e in group]) / np.mean([e[1] for e in group])
                          for group in errors.values()]))


def test_grid_and_zip_plans(tmp_path):
    grid = write_sweep(tmp_path, 'overrides = ["optim.steps=7"]\n[axes]\n'
                                 '"model_config.head" = ["f_act", "sigmoid"]\nseed = [0, 1, 2]\n')
    config, axes, base = load_sweep(grid, ["data.crop_size=8"])
    runs = plan_runs(config, axes)
    assert base == TINY_MIXER.resolve() and len(runs) == 6
    assert runs[0].name == "head=f_act__seed=0" and runs[-1].name == "head=sigmoid__seed=2"
    assert runs[4].overrides == ("optim.steps=7", "data.crop_size=8",
                                 'model_config.head="sigmoid"', "seed=1")
    loaded = load_train_config(base, list(runs[4].overrides))  # the overrides really apply
    assert (loaded.model_config["head"], loaded.seed, loaded.optim.steps,
            loaded.data.crop_size) == ("sigmoid", 1, 7, 8)

    zipped = write_sweep(tmp_path, 'mode = "zip"\n[axes]\nname = ["full", "no-sure"]\n'
                                   '"model_config.features" = [["hdr", "den", "var", "sure"], '
                                   '["hdr", "den", "var"]]\n')
    config, axes, _ = load_sweep(zipped)
    runs = plan_runs(config, axes)
    assert [r.name for r in runs] == ["full", "no-sure"]
    assert runs[1].overrides == ('model_config.features=["hdr", "den", "var"]',)


@pytest.mark.parametrize("body, words", [
    ('mdoe = "grid"\n[axes]\nseed = [0]\n', "mdoe"),
    ('mode = "zip"\n[axes]\nseed = [0, 1]\n"optim.steps" = [3]\n', "equal length"),
    ("[axes]\nseed = []\n", "non-empty list"),
    ('mode = "grid"\n', r"needs an \[axes\] table"),
    ('[axes]\nname = ["a", "a"]\n', "same folder name"),
])
def test_sweep_file_errors_name_the_file(tmp_path, body, words):
    path = write_sweep(tmp_path, body)
    with pytest.raises(ConfigError, match=words) as info:
        config, axes, _ = load_sweep(path)
        plan_runs(config, axes)
    assert "sweep.toml" in str(info.value) or words == "same folder name"


def test_bad_base_or_run_config_fails_before_any_training(tmp_path, capsys):
    missing = write_sweep(tmp_path, "[axes]\nseed = [0]\n", base=tmp_path / "absent.toml")
    assert main(["sweep", str(missing), "--workdir", str(tmp_path / "w")]) == 2
    assert "absent.toml" in capsys.readouterr().err
    typo = write_sweep(tmp_path, '[axes]\n"model_config.haed" = ["f_act"]\n')
    assert main(["sweep", str(typo), "--workdir", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err
    assert "haed" in err and "run haed=f_act" in err
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize("body, words", [
    ('[axes]\n"model_config.haed" = ["f_act"]\n', "run haed=f_act"),
    ('[axes]\n"optim.learning_rate" = [-0.1]\n', "learning_rate"),
    ('[axes]\n"model_config.head" = ["tree"]\n', "head"),
    ('[evaluate]\npd = ["NOWHERE"]\n[axes]\nseed = [0]\n',
     r"\[evaluate\] pd = .*nowhere.*no such dataset folder"),
])
def test_dry_run_makes_the_checks_of_a_real_sweep(tmp_path, capsys, body, words):
    """`--dry-run` exits 2 on the first problem a sweep would meet before training (a typo'd
    axis key, an out-of-range value, an unknown choice, a missing [evaluate] dataset), naming
    the file, and a real sweep stops there too, before any run folder exists."""
    path = write_sweep(tmp_path, body.replace("NOWHERE", str(tmp_path / "nowhere")))
    assert main(["sweep", str(path), "--workdir", str(tmp_path / "w"), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "sweep.toml" in err and re.search(words, err), err
    assert main(["sweep", str(path), "--workdir", str(tmp_path / "w")]) == 2
    assert re.search(words, capsys.readouterr().err)
    assert not (tmp_path / "w").exists()


def test_tiny_mixer_sweep_end_to_end_and_resume(tmp_path, capsys):
    dataset = tmp_path / "tiny"
    data_config = load_config(ROOT / "experiments" / "configs" / "dataset-tiny.toml",
                              DatasetConfig, ["crops_per_scene=2"])
    build_dataset(data_config, dataset, executor="serial", render_fn=synthetic_render,
                  progress=False)
    sweep = write_sweep(tmp_path, f'overrides = ["data.dataset={dataset}", "optim.steps=4", '
                                  '"eval_every=4", "checkpoint_every=4"]\n'
                                  "[axes]\nseed = [0, 1]\n"
                                  f'[evaluate]\npd = ["{dataset}"]\nsplit = "val"\n'
                                  "spp = [8, 32]\n")
    workdir = tmp_path / "sweep"
    # --only runs one point and writes no summary (a summary covers the whole sweep) ...
    with pytest.raises(ConfigError, match="no run named 'seed=2'.*seed=0, seed=1"):
        run_sweep(sweep, workdir, progress=False, only=["seed=2"])
    first = run_sweep(sweep, workdir, progress=False, only=["seed=1"])
    assert [(r["run"], r["skipped"]) for r in first] == [("seed=1", False)]
    assert not (workdir / "seed=0").exists() and not (workdir / "summary.md").exists()
    # ... and the whole sweep then finds it finished.
    results = run_sweep(sweep, workdir, progress=False)
    assert [r["run"] for r in results] == ["seed=0", "seed=1"]
    assert [r["skipped"] for r in results] == [False, True]
    # (read back from its result.json, where the per-spp keys are strings)
    assert results[1]["evaluations"] == json.loads(json.dumps(first[0]["evaluations"]))
    for result in results:
        run_dir = workdir / result["run"]
        assert (run_dir / "metrics.jsonl").is_file() and (run_dir / "result.json").is_file()
        assert result["config"]["seed"] == result["values"]["seed"]
        head = result["evaluations"][f"pd:{dataset}"]["headline"]
        # The headline ratio is what the run's saved mixer gives on the val crops, recomputed
        # here from the run folder and the dataset files (float32 pipeline, float64 errors).
        want = pd_over_denoiser_rmse(run_dir, dataset, "val", (8, 32))
        assert head["pd_over_denoiser"]["rmse"] == pytest.approx(want, rel=1e-4)
        # Per spp too (the PD paper's Table 4 is per spp): the same ratio from the means.
        per_spp = result["evaluations"][f"pd:{dataset}"]["per_spp"]
        assert sorted(map(int, per_spp)) == [8, 32]
        ratios = [m["pd_rmse"] / m["denoiser_rmse"] for m in per_spp.values()]
        assert head["pd_over_denoiser"]["rmse"] == pytest.approx(np.mean(ratios), rel=1e-6)
        per_crop = result["evaluations"][f"pd:{dataset}"]["per_crop"]
        assert len(per_crop) == result["evaluations"][f"pd:{dataset}"]["crops"]
    # Different seeds train different mixers.
    assert results[0]["train"]["val_loss"] != results[1]["train"]["val_loss"]
    summary = (workdir / "summary.md").read_text()
    assert "| seed=0 |" in summary and "| seed=1 |" in summary
    assert "Mean ± standard deviation over seeds" in summary and "| 2 |" in summary
    data = json.loads((workdir / "summary.json").read_text())
    assert data["groups"][0]["seeds"] == 2
    assert data["provenance"]["command"].startswith(f"jaxden sweep {sweep} --workdir {workdir}")
    assert summary.startswith("<!-- generated by: jaxden sweep")
    log = (workdir / "seed=0" / "metrics.jsonl").read_text()

    # A rerun skips both runs (nothing retrained, nothing re-evaluated) ...
    capsys.readouterr()
    assert main(["sweep", str(sweep), "--workdir", str(workdir)]) == 0
    out = capsys.readouterr().out
    assert "0 run now, 2 already finished" in out
    assert (workdir / "seed=0" / "metrics.jsonl").read_text() == log
    # ... also when its recorded config predates a config field (a finished run recorded
    # before `data.target_spp` existed is still finished) ...
    record = workdir / "seed=0" / "result.json"
    old = json.loads(record.read_text())
    del old["config"]["data"]["target_spp"]
    record.write_text(json.dumps(old))
    assert [r["skipped"] for r in run_sweep(sweep, workdir, progress=False)] == [True, True]
    # ... but not when a field it recorded differs.
    old["config"]["optim"]["steps"] += 1
    record.write_text(json.dumps(old))
    assert [r["skipped"] for r in run_sweep(sweep, workdir, progress=False)] == [False, True]
    # ... and a run whose result is lost is redone from its finished checkpoint.
    (workdir / "seed=1" / "result.json").unlink()
    again = run_sweep(sweep, workdir, progress=False)
    assert [r["skipped"] for r in again] == [True, False]
    assert json.loads(json.dumps(again[1]["evaluations"])) == results[1]["evaluations"]


SWEEP_FILES = sorted((ROOT / "experiments" / "sweeps").glob("*.toml"))


def test_there_are_shipped_sweep_files():
    assert SWEEP_FILES, ROOT / "experiments" / "sweeps"


@pytest.mark.parametrize("path", SWEEP_FILES, ids=lambda p: p.name)
def test_shipped_sweep_files_plan_valid_runs(path):
    """Every experiments/sweeps/*.toml loads, plans at least one run, and each run's overrides
    resolve into a valid training config (the axis values really land in it)."""
    config, axes, base = load_sweep(path)
    runs = plan_runs(config, axes)
    assert len(runs) >= 1 and base.is_file()
    assert len({run.name for run in runs}) == len(runs)
    for run in runs:
        resolved = load_train_config(base, list(run.overrides))
        for key, value in run.values.items():
            if key == "name":
                continue
            section, _, field = key.rpartition(".")
            holder = getattr(resolved, section) if section else resolved
            got = holder[field] if isinstance(holder, dict) else getattr(holder, field)
            # TOML has no null (jaxden.config): "none" is None once typed; a model_config
            # table stays as written until the model's config class reads it (below)
            expected = value if isinstance(holder, dict) or value != "none" else None
            assert (list(got) if isinstance(got, tuple) else got) == expected, (run.name, key)
        if resolved.model == "mixer":
            from jaxden.config import load_config
            from jaxden.progressive.mixer import MixerConfig

            mixer = load_config(resolved.model_config, MixerConfig)
            for key, value in run.values.items():
                if key.startswith("model_config."):
                    got = getattr(mixer, key.removeprefix("model_config."))
                    want = None if value == "none" else value
                    if key == "model_config.denoiser":
                        from jaxden.paths import expand_path

                        want = expand_path(value)
                    assert (list(got) if isinstance(got, tuple) else got) == want, (run.name, key)


def test_relative_dataset_and_init_paths_reach_the_runs_absolute(tmp_path, monkeypatch):
    """A run may execute in another folder (a Ray node): relative data.dataset and init paths
    that exist here are made absolute; a shipped model's name stays a name."""
    from types import SimpleNamespace

    from jaxden.sweep import _absolute_overrides

    monkeypatch.chdir(tmp_path)
    (tmp_path / "data").mkdir()
    (tmp_path / "runs" / "a").mkdir(parents=True)
    config = SimpleNamespace(data=SimpleNamespace(dataset="data"), init="runs/a")
    assert _absolute_overrides(config, ("seed=1",)) == (
        "seed=1", f'data.dataset="{tmp_path / "data"}"', f'init="{tmp_path / "runs" / "a"}"')
    shipped = SimpleNamespace(data=SimpleNamespace(dataset=str(tmp_path / "data")), init="wskp-6")
    assert _absolute_overrides(shipped, ()) == ()


# ------------------------------------------------------------- the evaluators' sweep columns
def pd_summary(max_spp: int, ratio: float) -> dict:
    """The part of a PD evaluation's summary that a sweep's summary reads."""
    return {"max_spp": max_spp, "headline": {
        "pd_over_denoiser": {"rmse": ratio, "relmse": ratio / 2},
        "mixed_over_denoiser": {"rmse": ratio + 0.1, "relmse": ratio},
        "pd_over_mc_at_max_spp": {"rmse": 1.01, "relmse": 1.02}}}


def test_summary_columns_match_the_committed_pd_ablations_summary():
    """The columns of a PD sweep (from the pd evaluator's sweep_columns) are those of the
    committed summary of experiments/sweeps/pd-ablations.toml, labels and order alike."""
    from jaxden.sweep import summarize

    committed = ROOT / "experiments" / "results" / "pd" / "pd-ablations.md"
    header = committed.read_text().splitlines()[1]
    axes = ["name", "model_config.features", "model_config.head"]
    result = {"run": "full", "values": {"name": "full", "model_config.features": ["hdr", "den"],
                                        "model_config.head": "f_act"},
              "train": {"val_loss": 0.5, "val_baseline_loss": 0.7},
              "evaluations": {"pd:/data/test": pd_summary(1024, 0.8),
                              "pd:/data/test-high/": pd_summary(4096, 0.9)}}
    lines = summarize([result], axes)["markdown"].splitlines()
    assert lines[0] == header
    assert lines[2].startswith("| full | full | hdr+den | f_act | 0.5 | 0.7 | 0.8 | 0.4 | 0.9 |")


def test_summary_columns_of_denoiser_sweeps():
    """A denoise and a sequences evaluation: PSNR, SSIM, relMSE, FLIP per dataset, and the
    same after temporal accumulation for sequences; the mean and spread over seeds."""
    from jaxden.sweep import summarize

    def result(seed, psnr):
        metrics = {f"{p}_{m}": v for p in ("den", "mc", "tdn") for m, v in
                   (("psnr", psnr), ("ssim", 0.9), ("relmse", 0.01), ("flip", 0.1),
                    ("rmse", 0.2))}
        return {"run": f"seed={seed}", "values": {"seed": seed}, "train": {"val_loss": 1.0},
                "evaluations": {"den:/d/rt-test": {k: v for k, v in metrics.items()
                                                   if not k.startswith("tdn")},
                                "seq:/d/rt-seq": metrics}}

    summary = summarize([result(0, 30.0), result(1, 32.0)], ["seed"])
    lines = summary["markdown"].splitlines()
    assert lines[0] == (
        "| run | seed | val_loss | rt-test PSNR | rt-test SSIM | rt-test relMSE | rt-test FLIP | "
        "rt-seq PSNR | rt-seq SSIM | rt-seq relMSE | rt-seq FLIP | rt-seq temporal PSNR | "
        "rt-seq temporal SSIM | rt-seq temporal relMSE | rt-seq temporal FLIP |")
    assert lines[2].startswith("| seed=0 | 0 | 1 | 30 | 0.9 | 0.01 | 0.1 | 30 |")
    assert summary["groups"][0]["metrics"]["rt-seq temporal PSNR"]["mean"] == 31.0


@pytest.fixture
def toy_evaluator(monkeypatch, tmp_path):
    """An evaluator registered from outside jaxden (as a plugin's would be): datasets are
    folders holding ``toy.txt``, one setting ``level``, one summary column."""
    from jaxden.errors import DatasetError
    from jaxden.evaluate import registry
    from jaxden.evaluate.evaluator import Evaluator

    def check(folder, table):
        if not (Path(folder) / "toy.txt").is_file():
            raise DatasetError("not a toy set (no toy.txt)")

    toy = Evaluator(
        name="toy", description="a toy", options=dict,
        run=lambda data, options, progress=False: [{"score": float(options["level"])}],
        summarize=lambda rows, provenance: {"summary": {"score": rows[0]["score"]}},
        table=lambda fields, rows, provenance: "", provenance=lambda options: {},
        sweep_options=lambda run_dir, table: {"level": table["level"]},
        sweep_settings=(("level", int, 3),), sweep_check=check, sweep_key="toy",
        sweep_columns=lambda summary: {"toy score": summary["score"]}, trains="mixer")
    monkeypatch.setitem(registry.EVALUATORS, "toy", toy)
    folder = tmp_path / "toyset"
    folder.mkdir()
    (folder / "toy.txt").write_text("toy")
    return toy, folder


def test_an_evaluator_from_outside_runs_in_a_sweep(toy_evaluator, tmp_path):
    """The [evaluate] keys, the dataset check, the evaluation and the summary's columns all
    come from the registered evaluators: one registered from outside jaxden takes part in
    each, and a finished run recorded before it was registered is still finished."""
    from jaxden.evaluate.registry import evaluate_run
    from jaxden.sweep import _evaluate_record, _same_evaluate, check_sweep, summarize

    _, folder = toy_evaluator
    body = f'[evaluate]\ntoy = ["{folder}"]\nlevel = 5\n[axes]\nseed = [0]\n'
    path = write_sweep(tmp_path, body)
    config, *_ = check_sweep(path)
    assert config.evaluate.toy == (str(folder),) and config.evaluate.level == 5
    record = _evaluate_record(config.evaluate)
    assert record["toy"] == [str(folder)] and record["pd"] == [] and record["split"] == "test"
    evaluations = evaluate_run(tmp_path / "run", record, "mixer")
    assert evaluations == {f"toy:{folder}": {"score": 5.0}}
    result = {"run": "seed=0", "values": {"seed": 0}, "train": {}, "evaluations": evaluations}
    assert summarize([result], ["seed"])["markdown"].splitlines()[0] == (
        "| run | seed | toyset toy score |")
    # A run recorded before "toy" existed: the same [evaluate] as one that leaves it out.
    plain = write_sweep(tmp_path, "[axes]\nseed = [0]\n")
    now = _evaluate_record(check_sweep(plain)[0].evaluate)
    before = {k: v for k, v in now.items() if k not in ("toy", "level")}
    assert _same_evaluate(before, now) and not _same_evaluate(before, record)
    # Its setting is typed, and its check runs before any training.
    bad = write_sweep(tmp_path, '[evaluate]\nlevel = "high"\n[axes]\nseed = [0]\n')
    with pytest.raises(ConfigError, match=r"sweep.toml: .*'evaluate.level': expected int"):
        check_sweep(bad)
    (folder / "toy.txt").unlink()
    write_sweep(tmp_path, body)
    with pytest.raises(ConfigError, match=r"\[evaluate\] toy = .*toyset.*: not a toy set"):
        check_sweep(path)


def test_evaluate_keys_come_from_the_evaluators(toy_evaluator, tmp_path):
    path = write_sweep(tmp_path, '[evaluate]\ntoys = ["x"]\n[axes]\nseed = [0]\n')
    with pytest.raises(ConfigError, match=r"sweep.toml: .*unknown key 'toys' in table "
                                          r"\[evaluate\].*did you mean 'toy'.*Allowed keys: "
                                          r"denoise, denoise_spp, denoiser, level, pd, probes, "
                                          r"seed, sequences, split, spp, toy"):
        load_sweep(path)


def test_evaluators_declaring_one_key_differently_are_refused(toy_evaluator, monkeypatch):
    import dataclasses

    from jaxden.evaluate import registry

    toy, _ = toy_evaluator
    monkeypatch.setitem(registry.EVALUATORS, "toy", dataclasses.replace(
        toy, sweep_settings=(("split", str, "val"),)))
    with pytest.raises(ValueError, match="'pd' and 'toy' declare the \\[evaluate\\] key "
                                         "'split' differently"):
        registry.evaluate_table_class()


@pytest.mark.parametrize("key, words", [
    ("pd", "is not a jaxden dataset: it has no manifest.json"),
    ("denoise", "is not a jaxden dataset: it has no manifest.json"),
    ("sequences", "is not a jaxden sequence set: it has no sequences.json"),
])
def test_evaluate_datasets_are_checked_as_their_evaluator_reads_them(tmp_path, key, words):
    """Each evaluator's sweep_check: a rendered dataset or a sequence set, before training."""
    from jaxden.sweep import check_sweep

    empty = tmp_path / "empty"
    empty.mkdir()
    path = write_sweep(tmp_path, f'[evaluate]\n{key} = ["{empty}"]\n[axes]\nseed = [0]\n')
    with pytest.raises(ConfigError, match=rf"sweep.toml: \[evaluate\] {key} = .*empty.*: "
                                          rf".*{words}"):
        check_sweep(path)
