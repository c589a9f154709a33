"""Export a trained mixer into the package (jaxden/weights/NAME.msgpack + .json) and write its
model card (NAME.md) from the training run and, when given, the PD report on the test set.

    python experiments/ship_mixer.py --workdir runs/mixer-oidn --name oidn-pd [--swap-average] \
        [--config experiments/configs/mixer-oidn.toml] \
        [--report experiments/results/pd/pd-oidn-test-shipped.json \
         --report experiments/results/pd/pd-oidn-test-high-shipped.json]

The card describes the mixer's base denoiser, ``MixerConfig.denoiser``: OIDN (``oidn``), weights
shipped in the package (``wskp-6``) or a checkpoint folder; its name, the EXR channels it reads,
how SURE was taken (finite differences for OIDN, ``jax.jvp`` for JAX denoisers) and, for OIDN
alone, the pyoidn version. ``--config`` defaults to the committed experiments/configs/mixer-*.toml
holding the run's model config (mixer-oidn.toml for an OIDN run when none does); the dataset's
build command names experiments/configs/dataset-NAME.toml for the dataset's config name NAME
when committed, else ``--dataset-config-file`` (default dataset-default.toml).

The weights are the run's final checkpoint; the .json meta record gets the training config,
the steps, the dataset's manifest hash, the final validation loss and (``training_facts``)
everything the card says of the training. Rerunning with a report rewrites the same weights
(bit-identical) and adds the measured metrics to the card.

``--set KEY=VALUE`` changes a field of the shipped MixerConfig at inference (recorded in the
.json as ``inference_overrides`` and stated in the card), e.g. ``closed_form_stops=1``.
``--reship NAME`` re-exports weights already shipped, without their training run: the same
parameters, the training facts from their .json (for weights shipped before
``training_facts`` existed: the .json's train config, steps and final validation loss, the
untrained and base-denoiser-alone validation losses and logged minutes read back from the
card, the dataset config from ``--dataset-config``).

    python experiments/ship_mixer.py --reship oidn-pd --set closed_form_stops=1 \
        --config experiments/configs/mixer-oidn-cflogit.toml --report A.json --report B.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path

from jaxden.evaluate import denoiser_label
from jaxden.provenance import file_sha256, git_commit, package_version

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_TRAIN_CONFIG = "experiments/configs/mixer-oidn.toml"
DEFAULT_DATASET_CONFIG = "experiments/configs/dataset-default.toml"


def pyoidn_version() -> str:
    """The installed pyoidn's version (its package metadata: pyoidn has no ``__version__``),
    or "not installed"."""
    return package_version("pyoidn")


def base_denoiser(spec: str) -> dict:
    """What the card says of the mixer's base denoiser ``spec`` (``MixerConfig.denoiser``).

    ``label`` (:func:`denoiser_label`); ``black_box``: True for registered black boxes (OIDN),
    whose SURE "auto" takes by finite differences (``jaxden.sure.denoiser.resolve_method``);
    ``required``: the frame fields it reads (None when its weights are not here to say);
    ``model`` and ``description``: the registered model of its weights; ``shipped``: its
    weights file in jaxden/weights/, or None.
    """
    from jaxden.checkpoint import read_checkpoint_meta
    from jaxden.config import load_config
    from jaxden.denoise.registry import REGISTRY, WEIGHTS_DIR
    from jaxden.errors import JaxdenError

    base = {"spec": spec, "label": denoiser_label(spec), "black_box": False, "required": None,
            "model": None, "description": None, "shipped": None}
    path, shipped = Path(spec), WEIGHTS_DIR / f"{spec}.msgpack"
    if not path.exists() and shipped.is_file():  # the order of load_denoiser
        path = base["shipped"] = shipped
    if path.exists():
        try:
            meta = read_checkpoint_meta(path)
            definition = REGISTRY[meta["model"]]
            config = load_config(meta.get("model_config", {}), definition.config_cls)
        except (JaxdenError, KeyError):
            return base
        base.update(model=definition.name, description=definition.description,
                    required=tuple(definition.required(config)))
    elif spec in REGISTRY:
        definition = REGISTRY[spec]
        base.update(black_box=not definition.differentiable, model=definition.name,
                    description=definition.description,
                    required=tuple(definition.required(definition.config_cls())))
    return base


def _channels_text(field: str) -> str:
    """``albedo`` -> "albedo.R/G/B", as the EXR names the field's channels."""
    from jaxden.frame import CHANNELS

    prefix = CHANNELS[field][0].split(".")[0]
    return f"{prefix}.{'/'.join(c.split('.', 1)[1] for c in CHANNELS[field])}"


def _words(items: list[str]) -> str:
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


def _plural(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def _held_out_scenes(data: dict) -> str:
    """What a measured set's crops show, from its dataset config: procedural scenes, or the
    scene files it names (built-in scenes are in every training set, so a held-out set has
    none)."""
    files = [Path(scene).name for scene in data.get("scenes", [])]
    if not files:
        return "procedural scenes and render seeds"
    return f"the scene files {', '.join(f'`{f}`' for f in files)}, scenes"


def _use_text(name: str, base: dict) -> str:
    """The card's Use line: today's text for OIDN, else the CLI command naming both."""
    if base["spec"] == "oidn":
        return ("Use: `jaxden progressive IN.exr --denoiser oidn --out OUT.exr` (the mixer "
                f"defaults to `{name}` for OIDN), or "
                "`jaxden.progressive.shipped_progressive_denoiser('oidn')`. The input EXR needs "
                "colour and the variance of the pixel mean (`variance.R/G/B`), plus albedo and "
                "normal for OIDN.")
    from jaxden.progressive.pipeline import SHIPPED_MIXERS

    spec, label = base["spec"], base["label"]
    text = f"Use: `jaxden progressive IN.exr --denoiser {spec} --mixer {name} --out OUT.exr`"
    if SHIPPED_MIXERS.get(spec) == name:  # what shipped_progressive_denoiser(spec) loads
        text += f", or `jaxden.progressive.shipped_progressive_denoiser('{spec}')`"
    text += ". The input EXR needs colour and the variance of the pixel mean (`variance.R/G/B`)"
    if base["required"] is None:
        return text + f", plus the features {label} reads."
    extra = [f for f in base["required"] if f not in ("color", "variance")]
    if not extra:
        return text + "."
    return text + f", plus {_words([f'{f} (`{_channels_text(f)}`)' for f in extra])} for {label}."


def _denoiser_text(mc: dict, base: dict, versions: dict) -> str:
    """The card's Denoiser line: which base, and how SURE of its output was taken (``mc``: the
    MixerConfig as a dict, its SURE settings the ``sure`` table or an older card's flat keys)."""
    from jaxden.progressive.mixer_config import upgrade_mixer_config

    settings = {"method": "auto", "eps": None, "seed": 0, "probe_dist": "normal",
                **upgrade_mixer_config(mc).get("sure", {})}
    method = settings["method"]
    if method == "auto":  # as jaxden.sure.denoiser.resolve_method resolves it
        method = "fd" if base["black_box"] else "jvp"
    if base["spec"] == "oidn":
        oidn = f"pyoidn {versions.get('pyoidn_version', pyoidn_version())}"
        if versions.get("pyoidn_version_trained"):
            oidn += f" (trained with {versions['pyoidn_version_trained']})"
        which = f"OIDN via {oidn} (CPU, 'high' quality, HDR, albedo + normal)"
    else:
        details = []
        if base["shipped"] is not None:
            sha = versions.get("denoiser_weights_sha256") or file_sha256(base["shipped"])
            details.append(f"`jaxden/weights/{base['spec']}.msgpack`, sha256 `{sha[:16]}...`")
        if base["model"]:
            details.append(f"model `{base['model']}`: {base['description']}")
        source = "the weights shipped as" if base["shipped"] is not None else "the checkpoint"
        which = (f"{base['label']}, {source} `{base['spec']}`"
                 + (f" ({'; '.join(details)})" if details else ""))
    dist = settings["probe_dist"] or "normal"
    kind = "" if dist == "normal" else f"{dist} "
    if method == "jvp":
        sure = (f"SURE of its output by jax.jvp (forward-mode derivative), "
                f"{_plural(settings['probes'], kind + 'probe')}")
    else:
        default = ("1e-2 (default for black boxes)" if base["black_box"] else
                   "1e-3 (default for JAX denoisers)")
        eps = settings["eps"] if settings["eps"] is not None else default
        sure = (f"SURE of its output by forward differences, {settings['probes']} {kind}probes, "
                f"eps {eps}")
    return (f"- Denoiser: {which}; {sure}, probe seed {settings['seed']} "
            f"(`jaxden dataset sure-cache`).")


def committed_dataset_config(dataset_config: dict | None) -> str:
    """The committed dataset config that builds a dataset of this manifest config:
    experiments/configs/dataset-NAME.toml for its name, else dataset-default.toml."""
    name = (dataset_config or {}).get("name")
    candidate = f"experiments/configs/dataset-{name}.toml"
    return candidate if name and (ROOT / candidate).is_file() else DEFAULT_DATASET_CONFIG


def committed_train_config(train_config: dict) -> str | None:
    """The one committed experiments/configs/mixer-*.toml whose model config, seed and steps
    are the run's, or None."""
    from jaxden.errors import JaxdenError
    from jaxden.train.config import load_train_config

    matches = []
    for path in sorted((ROOT / "experiments" / "configs").glob("mixer-*.toml")):
        try:
            committed = load_train_config(path)
        except JaxdenError:
            continue
        if (committed.model_config == train_config.get("model_config")
                and committed.seed == train_config.get("seed")
                and committed.optim.steps == train_config.get("optim", {}).get("steps")):
            matches.append(str(path.relative_to(ROOT)))
    return matches[0] if len(matches) == 1 else None


def _log(workdir: Path) -> list[dict]:
    path = workdir / "metrics.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _training_facts(workdir: Path) -> dict:
    log = _log(workdir)
    config = json.loads((workdir / "config.json").read_text())
    evals = [e for e in log if "val_loss" in e]
    steps = [e for e in log if "grad_norm" in e]
    dataset = Path(config["data"]["dataset"])
    manifest = dataset / "manifest.json"
    return {
        "workdir": str(workdir),
        "train_config": config,
        "steps": max(e["step"] for e in log),
        "seconds_logged": round(sum(e.get("seconds", 0.0) for e in steps), 1),
        "val_loss_initial": evals[0]["val_loss"],
        "val_loss_final": evals[-1]["val_loss"],
        "val_baseline_loss": evals[-1].get("val_baseline_loss"),
        "val_metric": config["optim"]["loss"],
        "dataset_manifest_sha256": file_sha256(manifest) if manifest.is_file() else None,
        "dataset_config": json.loads(manifest.read_text())["config"] if manifest.is_file() else None,
    }


_VALIDATION = re.compile(
    r"Validation (?P<metric>\w+) \(val split, \d+ batches\): (?P<initial>[\d.]+) untrained -> "
    r"[\d.]+ trained \(.+? alone: (?P<baseline>[\d.]+)\); (?P<minutes>\d+) min of logged")
_WORKDIR = re.compile(r"python experiments/ship_mixer\.py --workdir (\S+)")
_DATASET_BUILD = re.compile(r"jaxden dataset build (\S+) --out")


def facts_from_shipped(meta: dict, card: str, dataset_config_file: Path | None = None) -> dict:
    """The training facts of shipped weights (see the module doc): ``meta["training_facts"]``
    when recorded, else rebuilt from the .json record and the card's text."""
    if "training_facts" in meta:
        return meta["training_facts"]
    validation, workdir = _VALIDATION.search(card), _WORKDIR.search(card)
    if validation is None or workdir is None:
        raise SystemExit("--reship: the weights' .json has no training_facts and their card has "
                         "no 'Validation ...' line or ship_mixer.py --workdir command to read "
                         "them from")
    if dataset_config_file is None:
        raise SystemExit("--reship: weights shipped before training_facts existed need "
                         "--dataset-config (the dataset config they were trained on)")
    import tomllib

    dataset = tomllib.loads(Path(dataset_config_file).read_text())
    dataset["name"] = Path(meta["train_config"]["data"]["dataset"]).name
    return {
        "workdir": workdir.group(1),
        "train_config": meta["train_config"],
        "steps": meta["trained_steps"],
        "seconds_logged": 60.0 * int(validation.group("minutes")),
        "val_loss_initial": float(validation.group("initial")),
        "val_loss_final": meta["val_loss_final"],
        "val_baseline_loss": float(validation.group("baseline")),
        "val_metric": validation.group("metric"),
        "dataset_manifest_sha256": meta["dataset_manifest_sha256"],
        "dataset_config": dataset,
    }


def _overrides_text(overrides: list[str]) -> str:
    if not overrides:
        return ""
    return (" Shipped with " + ", ".join(f"`{o}`" for o in overrides) + " set at inference "
            "after training (`ship_mixer.py --set`): the network learned its correction on the "
            "training config's settings; the measurements below are of the shipped ones.")


def _head_text(mc: dict) -> str:
    """What the mixer's alpha head computes, for the card."""
    if mc["head"] == "closed_form_logit":
        bound = mc.get("logit_bound")
        correction = "raw" if bound is None else f"{bound:g} tanh(raw / {bound:g})"
        stops = mc.get("closed_form_stops")
        strata = ("" if stops is None else
                  f" over neighbours of similar brightness (strata {stops:g} stops wide, "
                  f"`closed_form_stops`)")
        return (f"alpha = sigmoid(logit(alpha_cf) + {correction}), alpha_cf the paper's Eq. 9 "
                f"with Gaussian local means of width {mc.get('closed_form_sigma')} px{strata} "
                f"clipped "
                f"to [{mc.get('logit_eps'):g}, 1 - {mc.get('logit_eps'):g}]: the network "
                f"corrects the closed form within a bounded logit; our addition")
    if mc["head"] == "f_act":
        return "the paper's f_act = (x1 - x2) / max(x3, eps), clipped to [0, 1]"
    return f"alpha predicted directly ({mc['head']}; the paper's 'w/o f_act' ablation)"


def _card(name: str, facts: dict, mc: dict, reports: list[tuple[str, dict]], size: int,
          config_file: str = DEFAULT_TRAIN_CONFIG,
          overrides: tuple[str, ...] = (), versions: dict | None = None,
          data_config_file: str | None = None) -> str:
    """The model card; ``mc``: the resolved MixerConfig as a dict (its ``denoiser`` is the base
    the card describes); ``reports``: (path, pd report JSON) pairs, one section each;
    ``config_file``: the committed training config; ``versions``: the .json's version fields
    (for OIDN ``pyoidn_version`` and, when it differed, ``pyoidn_version_trained``; for shipped
    JAX weights ``denoiser_weights_sha256``); ``data_config_file``: the dataset config named in
    the build command, None for :func:`committed_dataset_config`'s."""
    versions = versions or {}
    base = base_denoiser(mc["denoiser"])
    label = base["label"]
    workdir = facts["workdir"]
    cfg = facts["train_config"]
    data = train_data = facts["dataset_config"] or {}
    derived_data_config = committed_dataset_config(data)
    data_config_file = data_config_file or derived_data_config
    long_name = "Intel Open Image Denoise" if base["spec"] == "oidn" else label
    lines = [
        f"# Model card: `{name}` (progressive-denoising mixer for {long_name})",
        "",
        "Generated by `python experiments/ship_mixer.py` from the training run; numbers below are "
        "copied from the files named next to them.",
        "",
        "## What it is",
        f"PDNet (Firmino, Frisvad, Jensen 2022, Sec. 4.3): 5x5 first layer, two residual blocks, "
        f"{mc['width']} channels, 6 layers, {len(mc['features'])} x 3 = "
        f"{3 * len(mc['features'])} input channels ({', '.join(mc['features'])}; the "
        f"non-radiance ones through `{mc.get('input_transform', 'atan')}`, see "
        f"`jaxden.progressive.INPUT_TRANSFORMS`"
        + (f"; closed_form: the alpha of the closed-form mixer, the paper's Eq. 9 with Gaussian "
           f"local means of width {mc.get('closed_form_sigma')} px, "
           f"`jaxden.progressive.closed_form_alpha`" if "closed_form" in mc["features"] else "")
        + "), head "
        f"`{mc['head']}` ({_head_text(mc)}, one alpha per colour channel). It mixes the Monte "
        f"Carlo input x "
        f"and {label}'s output y per pixel; at inference the t-statistic scaling (window "
        f"{mc['tstat']['window']}, a = {mc['tstat']['a']}, c = {mc['tstat']['c']}, "
        f"per_channel = {str(mc['tstat']['per_channel']).lower()}) makes the result consistent"
        + (f", and the error guard (`tstat.guard`: alpha <= {mc['tstat'].get('guard_gamma', 2.0)}"
           f" var / E[(y - x)^2] from {mc['tstat'].get('guard_sigma', 1.0)}-px local means, "
           f"the variance raised to an upper confidence bound from the sample count "
           f"({mc['tstat'].get('guard_confidence', 2.0)} standard deviations of its estimate), "
           "scaled to 0 where y is c standard errors off x; our addition, "
           "`jaxden.progressive.guard`) keeps it from ending above x where y is far off"
           if mc["tstat"].get("guard", True) else "")
        + (" and alpha is the mean of the mixer's alpha and 1 - alpha of its swapped call "
           "(`swap_average`, a second mixer call; our addition, see `MixerConfig`). "
           if mc.get("swap_average") else ". ")
        + f"{size / 1024:.0f} KiB of float32 parameters." + _overrides_text(list(overrides)),
        "",
        _use_text(name, base),
        "",
        "## Training data",
        f"- Dataset: `{cfg['data']['dataset']}`, what `jaxden dataset build "
        f"{data_config_file} --out {cfg['data']['dataset']}` renders "
        f"(manifest sha256 `{(facts['dataset_manifest_sha256'] or '?')[:16]}...`): "
        f"{len(data.get('scenes', []))} built-in scenes + "
        f"{data.get('procedural', {}).get('count', 0)} procedural scenes (seeds "
        f"{data.get('procedural', {}).get('seed', '?')}+), "
        f"{_plural(data['crops_per_scene'], 'crop') if 'crops_per_scene' in data else '? crops'} "
        f"of {data.get('crop_size', '?')}^2 each, inputs at {data.get('spp')} spp, "
        f"references at {data.get('reference_spp')} spp, dataset seed {data.get('seed')}; "
        f"split by scene (train/val {data.get('splits', {}).get('train')}/"
        f"{data.get('splits', {}).get('val')}); features (albedo, normal): "
        f"{data.get('aux', 'first-hit')}, min(spp, {data.get('feature_spp', 16)}) samples.",
        _denoiser_text(mc, base, versions),
        "",
        "## Training",
        f"- Config: `{config_file}`; seed {cfg['seed']}; "
        f"{facts['steps']} steps of batch {cfg['data']['batch_size']} x "
        f"{cfg['data']['crop_size']}^2 crops (dihedral augmentation, swap of (x, var) and "
        f"(y, SURE) with probability {mc['swap_probability']}); loss {cfg['optim']['loss']}; "
        f"Adam with a one-cycle schedule, peak lr {cfg['optim']['learning_rate']}.",
        f"- Validation {facts['val_metric']} (val split, {cfg['eval_batches']} batches): "
        f"{facts['val_loss_initial']:.5f} untrained -> {facts['val_loss_final']:.5f} trained "
        f"({label} alone: {facts['val_baseline_loss']:.5f}); "
        f"{facts['seconds_logged'] / 60:.0f} min of logged step time on the 2-core project CPU "
        f"(2 XLA host devices).",
        f"- Retrain: `jaxden dataset build {data_config_file} --out "
        f"{cfg['data']['dataset']}` then `XLA_FLAGS=--xla_force_host_platform_device_count=2 "
        f"jaxden train {config_file} data.dataset={cfg['data']['dataset']}"
        f" --workdir {workdir}`, then `python experiments/ship_mixer.py --workdir {workdir} "
        f"--name {name}{' --swap-average' if mc.get('swap_average') else ''} "
        f"--config {config_file}"
        + (f" --dataset-config-file {data_config_file}"
           if data_config_file != derived_data_config else "")
        + "".join(f" --set {o}" for o in overrides)
        + "".join(f" --report {path}" for path, _ in reports) + "`.",
        "",
    ]
    for path, report in reports:
        s = report["summary"]
        h = s["headline"]
        prov = report["provenance"]
        data = prov["dataset"]["config"]
        measured = denoiser_label(prov.get("denoiser", mc["denoiser"]))
        lines += [
            f"## Measured on `{prov['dataset']['dir']}` ({data.get('name', '?')}: "
            f"{min(s['per_spp'], key=int)}..{s['max_spp']} spp)",
            f"From `{path}` (`{prov['command']}`, commit {prov['commit']}"
            + (f"; the file was renamed from `{prov['renamed_from']}.json`"
               if prov.get("renamed_from") else "")
            + f"): {_plural(s['crops'], 'crop')} "
            f"of {_held_out_scenes(data)} never seen in training, errors against "
            f"{data['reference_spp']}-spp references, mean over crops, then the per-spp ratio "
            f"averaged over spp. The oracle mix fits one alpha per 8^2 tile and channel to the "
            f"reference: a bound for mixers of x and y, not a method.",
            "",
            "| ratio | RMSE | RMSE (noise-corrected) | relMSE | FLIP |",
            "|---|---:|---:|---:|---:|",
        ]
        pd, den = f"PD({measured})", measured
        rows = [("pd_over_denoiser", f"{pd} / {den}, all spp"),
                ("pd_over_denoiser_paper_range", f"{pd} / {den}, spp >= 32 (paper's range)"),
                ("mixed_over_denoiser", f"PD w/o t-test / {den}, all spp"),
                ("pd_pc_over_denoiser", f"{pd}, per-channel t / {den}, all spp"),
                ("pd_shared_over_denoiser", f"{pd}, shared t (authors') / {den}, all spp"),
                ("oracle_over_denoiser", f"oracle mix / {den}, all spp"),
                ("oracle_over_denoiser_paper_range", f"oracle mix / {den}, spp >= 32"),
                ("pd_over_mc_at_max_spp", f"{pd} / MC at {s['max_spp']} spp")]
        for key, row_label in rows:
            if key not in h:
                continue  # a report from before the row existed
            r = h[key]
            lines.append(f"| {row_label} | {r['rmse']:.3f} | {r['rmse_nc']:.3f} | "
                         f"{r['relmse']:.3f} | {r['flip']:.3f} |")
        lines += ["", f"Per spp: `{Path(path).with_suffix('.md')}`.", ""]
    spp = train_data.get("spp")
    low, high = (min(spp), max(spp)) if spp else ("?", "?")
    scenes = (len(train_data["scenes"]) + train_data.get("procedural", {}).get("count", 0)
              if "scenes" in train_data else "?")
    lines += [
        "## Limits",
        f"- Trained on {train_data.get('crop_size', '?')}^2 crops of {scenes} scenes at "
        f"{low}..{high} spp (not the paper's 11150 images at up to 4096 spp); expect it to be "
        f"less refined than the authors' weights. Above {high} spp it extrapolates; the reports "
        "above measure how far that holds.",
        f"- Trained for {label}'s output only; mixing another denoiser's output with it is "
        "possible (the CLI warns) but not what it learned.",
        "- The channel-summed t-statistic (authors' default) cannot detect a pure hue-shift bias; "
        "see docs/departures.md." if not mc["tstat"]["per_channel"] else
        "- The t-statistic is taken per colour channel (the paper's form; the authors' code sums "
        "the channels, which cannot detect a pure hue-shift bias, see docs/departures.md); the "
        "reports above hold the summed form's row too.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--workdir", help="training workdir of the mixer")
    source.add_argument("--reship", metavar="NAME",
                        help="re-export weights shipped as jaxden/weights/NAME.* (no run needed)")
    parser.add_argument("--name", default=None,
                        help="weights name in jaxden/weights/ (default: NAME with --reship, "
                             "else the base denoiser's name + '-pd', e.g. oidn-pd)")
    parser.add_argument("--report", action="append", default=[],
                        help="jaxden evaluate pd JSON for the card (repeatable)")
    parser.add_argument("--swap-average", action="store_true",
                        help="ship with MixerConfig.swap_average = true (inference option)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="ship with this MixerConfig field changed at inference (repeatable)")
    parser.add_argument("--config", default=None,
                        help="the committed training config of the run (named in the card; "
                             "the weights' tests compare the run's config with it); default: "
                             "with --reship the recorded one, else the committed "
                             f"experiments/configs/mixer-*.toml with the run's model config, "
                             f"seed and steps ({DEFAULT_TRAIN_CONFIG} for OIDN when none has)")
    parser.add_argument("--dataset-config", type=Path,
                        default=Path("experiments/configs/dataset-default.toml"),
                        help="with --reship of weights without training_facts: the dataset "
                             "config they were trained on")
    parser.add_argument("--dataset-config-file", default=None,
                        help="the dataset config the card's build commands name; default: "
                             "experiments/configs/dataset-NAME.toml for the dataset's config "
                             f"name NAME when committed (with --reship: the one the card "
                             f"names), else {DEFAULT_DATASET_CONFIG}")
    args = parser.parse_args(argv)

    from jaxden.config import config_to_dict, load_config
    from jaxden.denoise.registry import WEIGHTS_DIR
    from jaxden.fileio import atomic_write_text
    from jaxden.progressive.mixer import MixerConfig, load_mixer, save_mixer

    commit = git_commit(dirty=False)
    meta, card_text = {}, ""
    if args.reship:
        shipped = WEIGHTS_DIR / f"{args.reship}.msgpack"
        params, config = load_mixer(str(shipped))
        meta = json.loads(shipped.with_suffix(".json").read_text())
        card_text = shipped.with_suffix(".md").read_text()
        facts = facts_from_shipped(meta, card_text, args.dataset_config)
        if not args.set:  # a plain re-ship keeps the overrides it was shipped with
            args.set = list(meta.get("inference_overrides", []))
    else:
        params, config = load_mixer(Path(args.workdir))
        facts = _training_facts(Path(args.workdir))
    oidn = config.denoiser == "oidn"
    base = base_denoiser(config.denoiser)
    name = args.name or args.reship
    if name is None:
        if "/" in config.denoiser or config.denoiser.endswith(".msgpack"):
            raise SystemExit(f"--name: the base denoiser {config.denoiser} is a checkpoint, "
                             "not a name to derive the mixer's from; name the weights")
        name = f"{config.denoiser}-pd"
    # pyoidn versions for OIDN alone; a JAX base's weights by their hash
    versions = {"jaxden_commit": meta.get("jaxden_commit", commit)}
    if oidn:
        versions["pyoidn_version"] = pyoidn_version()
    if args.reship:
        versions["reshipped_commit"] = commit
    if oidn and args.reship:
        trained_with = meta.get("pyoidn_version_trained", meta.get("pyoidn_version"))
        if trained_with not in (None, "unknown", versions["pyoidn_version"]):
            versions["pyoidn_version_trained"] = trained_with
    if not oidn and (meta.get("denoiser_weights_sha256") or base["shipped"] is not None):
        versions["denoiser_weights_sha256"] = (meta.get("denoiser_weights_sha256")
                                               or file_sha256(base["shipped"]))
    config_file = args.config or meta.get("train_config_file")
    config_file = config_file or committed_train_config(facts["train_config"])
    if config_file is None:
        if not oidn:
            raise SystemExit("--config: no committed experiments/configs/mixer-*.toml has the "
                             "run's model config, seed and steps; name the run's config")
        config_file = DEFAULT_TRAIN_CONFIG
    data_config_file = args.dataset_config_file
    if data_config_file is None and args.reship:
        found = _DATASET_BUILD.search(card_text)
        data_config_file = found.group(1) if found else None
    if data_config_file is None and committed_dataset_config(facts["dataset_config"]) == \
            DEFAULT_DATASET_CONFIG:
        print(f"ship_mixer: note: no committed dataset config for the dataset's config name "
              f"{(facts['dataset_config'] or {}).get('name')!r}: the card names "
              f"{DEFAULT_DATASET_CONFIG} (--dataset-config-file to name another)",
              file=sys.stderr)
    if args.swap_average:
        config = dataclasses.replace(config, swap_average=True)
    if args.set:
        config = load_config(config, MixerConfig, overrides=args.set)
    extra = {
        "name": name, "trained_steps": facts["steps"], "seed": facts["train_config"]["seed"],
        "train_config": facts["train_config"], "train_config_file": config_file,
        "dataset_manifest_sha256": facts["dataset_manifest_sha256"],
        "val_loss_final": facts["val_loss_final"], **versions,
        "training_facts": facts, "inference_overrides": list(args.set),
    }
    path = WEIGHTS_DIR / f"{name}.msgpack"
    WEIGHTS_DIR.mkdir(exist_ok=True)
    save_mixer(path, params, config, **extra)
    reports = [(p, json.loads(Path(p).read_text())) for p in args.report]
    from jaxden.paths import portable

    card = _card(name, facts, config_to_dict(config), reports, path.stat().st_size,
                 config_file, tuple(args.set), versions, data_config_file)
    atomic_write_text(path.with_suffix(".md"), portable(card))
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB), {path.with_suffix('.json')} "
          f"and the model card {path.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
