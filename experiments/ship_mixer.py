"""Export a trained mixer into the package (jaxden/weights/NAME.msgpack + .json) and write its
model card (NAME.md) from the training run and, when given, the PD report on the test set.

    python experiments/ship_mixer.py --workdir runs/mixer-oidn --name oidn-pd [--swap-average] \
        [--config experiments/configs/mixer-oidn.toml] \
        [--report experiments/results/pd-oidn-test-shipped.json \
         --report experiments/results/pd-oidn-test-high-shipped.json]

The weights are the run's final checkpoint; the .json meta record gets the training config,
the steps, the dataset's manifest hash, the final validation loss and (``training_facts``)
everything the card says of the training. Rerunning with a report rewrites the same weights
(bit-identical) and adds the measured metrics to the card.

``--set KEY=VALUE`` changes a field of the shipped MixerConfig at inference (recorded in the
.json as ``inference_overrides`` and stated in the card), e.g. ``closed_form_stops=1``.
``--reship NAME`` re-exports weights already shipped, without their training run: the same
parameters, the training facts from their .json (for weights shipped before
``training_facts`` existed: the .json's train config, steps and final validation loss, the
untrained / OIDN validation losses and logged minutes read back from the card, the dataset
config from ``--dataset-config``).

    python experiments/ship_mixer.py --reship oidn-pd --set closed_form_stops=1 \
        --config experiments/configs/mixer-oidn-cflogit.toml --report A.json --report B.json
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def pyoidn_version() -> str:
    """The installed pyoidn's version (its package metadata: pyoidn has no ``__version__``),
    or "not installed"."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pyoidn")
    except PackageNotFoundError:
        return "not installed"


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
        "dataset_manifest_sha256": hashlib.sha256(manifest.read_bytes()).hexdigest()
        if manifest.is_file() else None,
        "dataset_config": json.loads(manifest.read_text())["config"] if manifest.is_file() else None,
    }


_VALIDATION = re.compile(
    r"Validation (?P<metric>\w+) \(val split, \d+ batches\): (?P<initial>[\d.]+) untrained -> "
    r"[\d.]+ trained \(OIDN alone: (?P<baseline>[\d.]+)\); (?P<minutes>\d+) min of logged")
_WORKDIR = re.compile(r"python experiments/ship_mixer\.py --workdir (\S+)")


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
          config_file: str = "experiments/configs/mixer-oidn.toml",
          overrides: tuple[str, ...] = (), versions: dict | None = None) -> str:
    """The model card; ``mc``: the resolved MixerConfig as a dict; ``reports``: (path, pd
    report JSON) pairs, one section each; ``config_file``: the committed training config;
    ``versions``: the .json's version fields (``pyoidn_version`` and, when it differed,
    ``pyoidn_version_trained``)."""
    versions = versions or {}
    oidn = f"pyoidn {versions.get('pyoidn_version', pyoidn_version())}"
    if versions.get("pyoidn_version_trained"):
        oidn += f" (trained with {versions['pyoidn_version_trained']})"
    workdir = facts["workdir"]
    cfg = facts["train_config"]
    data = facts["dataset_config"] or {}
    lines = [
        f"# Model card: `{name}` (progressive-denoising mixer for Intel Open Image Denoise)",
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
        f"and OIDN's output y per pixel; at inference the t-statistic scaling (window "
        f"{mc['tstat']['window']}, a = {mc['tstat']['a']}, c = {mc['tstat']['c']}, "
        f"per_channel = {str(mc['tstat']['per_channel']).lower()}) makes the result consistent"
        + (" and alpha is the mean of the mixer's alpha and 1 - alpha of its swapped call "
           "(`swap_average`, a second mixer call; our addition, see `MixerConfig`). "
           if mc.get("swap_average") else ". ")
        + f"{size / 1024:.0f} KiB of float32 parameters." + _overrides_text(list(overrides)),
        "",
        "Use: `jaxden progressive IN.exr --denoiser oidn --out OUT.exr` (the mixer defaults to "
        f"`{name}` for OIDN), or `jaxden.progressive.shipped_progressive_denoiser('oidn')`. "
        "The input EXR needs colour and the variance of the pixel mean (`variance.R/G/B`), plus "
        "albedo and normal for OIDN.",
        "",
        "## Training data",
        f"- Dataset: `{cfg['data']['dataset']}`, what `jaxden dataset build "
        f"experiments/configs/dataset-default.toml --out {cfg['data']['dataset']}` renders "
        f"(manifest sha256 `{(facts['dataset_manifest_sha256'] or '?')[:16]}...`): "
        f"{len(data.get('scenes', []))} built-in scenes + "
        f"{data.get('procedural', {}).get('count', 0)} procedural scenes (seeds "
        f"{data.get('procedural', {}).get('seed', '?')}+), {data.get('crops_per_scene', '?')} "
        f"crops of {data.get('crop_size', '?')}^2 each, inputs at {data.get('spp')} spp, "
        f"references at {data.get('reference_spp')} spp, dataset seed {data.get('seed')}; "
        f"split by scene (train/val {data.get('splits', {}).get('train')}/"
        f"{data.get('splits', {}).get('val')}); features (albedo, normal): "
        f"{data.get('aux', 'first-hit')}, min(spp, {data.get('feature_spp', 16)}) samples.",
        f"- Denoiser: OIDN via {oidn} (CPU, 'high' quality, HDR, albedo + normal); SURE of its "
        f"output by forward differences, {mc['sure_probes']} probes, eps "
        f"{mc['sure_eps'] if mc['sure_eps'] is not None else '1e-2 (default for black boxes)'}, "
        f"probe seed {mc['sure_seed']} (`jaxden dataset sure-cache`).",
        "",
        "## Training",
        f"- Config: `{config_file}`; seed {cfg['seed']}; "
        f"{facts['steps']} steps of batch {cfg['data']['batch_size']} x "
        f"{cfg['data']['crop_size']}^2 crops (dihedral augmentation, swap of (x, var) and "
        f"(y, SURE) with probability {mc['swap_probability']}); loss {cfg['optim']['loss']}; "
        f"Adam with a one-cycle schedule, peak lr {cfg['optim']['learning_rate']}.",
        f"- Validation {facts['val_metric']} (val split, {cfg['eval_batches']} batches): "
        f"{facts['val_loss_initial']:.5f} untrained -> {facts['val_loss_final']:.5f} trained "
        f"(OIDN alone: {facts['val_baseline_loss']:.5f}); "
        f"{facts['seconds_logged'] / 60:.0f} min of logged step time on the 2-core project CPU "
        f"(2 XLA host devices).",
        f"- Retrain: `jaxden dataset build experiments/configs/dataset-default.toml --out "
        f"{cfg['data']['dataset']}` then `XLA_FLAGS=--xla_force_host_platform_device_count=2 "
        f"jaxden train {config_file} data.dataset={cfg['data']['dataset']}"
        f" --workdir {workdir}`, then `python experiments/ship_mixer.py --workdir {workdir} "
        f"--name {name}{' --swap-average' if mc.get('swap_average') else ''} "
        f"--config {config_file}"
        + "".join(f" --set {o}" for o in overrides)
        + "".join(f" --report {path}" for path, _ in reports) + "`.",
        "",
    ]
    for path, report in reports:
        s = report["summary"]
        h = s["headline"]
        prov = report["provenance"]
        data = prov["dataset"]["config"]
        lines += [
            f"## Measured on `{prov['dataset']['dir']}` ({data.get('name', '?')}: "
            f"{min(s['per_spp'], key=int)}..{s['max_spp']} spp)",
            f"From `{path}` (`{prov['command']}`, commit {prov['commit']}"
            + (f"; the file was renamed from `{prov['renamed_from']}.json`"
               if prov.get("renamed_from") else "")
            + f"): {s['crops']} crops "
            f"of procedural scenes and render seeds never seen in training, errors against "
            f"{data['reference_spp']}-spp references, mean over crops, then the per-spp ratio "
            f"averaged over spp. The oracle mix fits one alpha per 8^2 tile and channel to the "
            f"reference: a bound for mixers of x and y, not a method.",
            "",
            "| ratio | RMSE | RMSE (noise-corrected) | relMSE | FLIP |",
            "|---|---:|---:|---:|---:|",
        ]
        rows = [("pd_over_denoiser", "PD(OIDN) / OIDN, all spp"),
                ("pd_over_denoiser_paper_range", "PD(OIDN) / OIDN, spp >= 32 (paper's range)"),
                ("mixed_over_denoiser", "PD w/o t-test / OIDN, all spp"),
                ("pd_pc_over_denoiser", "PD(OIDN), per-channel t / OIDN, all spp"),
                ("pd_shared_over_denoiser", "PD(OIDN), shared t (authors') / OIDN, all spp"),
                ("oracle_over_denoiser", "oracle mix / OIDN, all spp"),
                ("oracle_over_denoiser_paper_range", "oracle mix / OIDN, spp >= 32"),
                ("pd_over_mc_at_max_spp", f"PD(OIDN) / MC at {s['max_spp']} spp")]
        for key, label in rows:
            if key not in h:
                continue  # a report from before the row existed
            r = h[key]
            lines.append(f"| {label} | {r['rmse']:.3f} | {r['rmse_nc']:.3f} | "
                         f"{r['relmse']:.3f} | {r['flip']:.3f} |")
        lines += ["", f"Per spp: `{Path(path).with_suffix('.md')}`.", ""]
    lines += [
        "## Limits",
        "- Trained on 128^2 crops of 24 scenes at 2..1024 spp (not the paper's 11150 images at "
        "up to 4096 spp); expect it to be less refined than the authors' weights. Above 1024 "
        "spp it extrapolates; the reports above measure how far that holds.",
        "- Trained for OIDN's output only; mixing another denoiser's output with it is possible "
        "(the CLI warns) but not what it learned.",
        "- The channel-summed t-statistic (authors' default) cannot detect a pure hue-shift bias; "
        "see docs/departures.md.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--workdir", help="training workdir of the mixer")
    source.add_argument("--reship", metavar="NAME",
                        help="re-export weights shipped as jaxden/weights/NAME.* (no run needed)")
    parser.add_argument("--name", default=None,
                        help="weights name in jaxden/weights/ (default oidn-pd, or NAME)")
    parser.add_argument("--report", action="append", default=[],
                        help="pd_report.py pd JSON for the card (repeatable)")
    parser.add_argument("--swap-average", action="store_true",
                        help="ship with MixerConfig.swap_average = true (inference option)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="ship with this MixerConfig field changed at inference (repeatable)")
    parser.add_argument("--config", default="experiments/configs/mixer-oidn.toml",
                        help="the committed training config of the run (named in the card; "
                             "the weights' tests compare the run's config with it)")
    parser.add_argument("--dataset-config", type=Path,
                        default=Path("experiments/configs/dataset-default.toml"),
                        help="with --reship of weights without training_facts: the dataset "
                             "config they were trained on")
    args = parser.parse_args(argv)
    name = args.name or args.reship or "oidn-pd"

    from jaxden.config import config_to_dict, load_config
    from jaxden.denoise.registry import WEIGHTS_DIR
    from jaxden.fileio import atomic_write_text
    from jaxden.progressive.mixer import MixerConfig, load_mixer, save_mixer

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=ROOT).stdout.strip()
    oidn_version = pyoidn_version()
    if args.reship:
        shipped = WEIGHTS_DIR / f"{args.reship}.msgpack"
        params, config = load_mixer(str(shipped))
        meta = json.loads(shipped.with_suffix(".json").read_text())
        card_text = shipped.with_suffix(".md").read_text()
        facts = facts_from_shipped(meta, card_text, args.dataset_config)
        versions = {"jaxden_commit": meta["jaxden_commit"], "pyoidn_version": oidn_version,
                    "reshipped_commit": commit}
        trained_with = meta.get("pyoidn_version_trained", meta.get("pyoidn_version"))
        if trained_with not in (None, "unknown", oidn_version):
            versions["pyoidn_version_trained"] = trained_with
        if not args.set:  # a plain re-ship keeps the overrides it was shipped with
            args.set = list(meta.get("inference_overrides", []))
    else:
        params, config = load_mixer(Path(args.workdir))
        facts = _training_facts(Path(args.workdir))
        versions = {"jaxden_commit": commit, "pyoidn_version": oidn_version}
    if args.swap_average:
        config = dataclasses.replace(config, swap_average=True)
    if args.set:
        config = load_config(config, MixerConfig, overrides=args.set)
    extra = {
        "name": name, "trained_steps": facts["steps"], "seed": facts["train_config"]["seed"],
        "train_config": facts["train_config"], "train_config_file": args.config,
        "dataset_manifest_sha256": facts["dataset_manifest_sha256"],
        "val_loss_final": facts["val_loss_final"], **versions,
        "training_facts": facts, "inference_overrides": list(args.set),
    }
    path = WEIGHTS_DIR / f"{name}.msgpack"
    WEIGHTS_DIR.mkdir(exist_ok=True)
    save_mixer(path, params, config, **extra)
    reports = [(p, json.loads(Path(p).read_text())) for p in args.report]
    card = _card(name, facts, config_to_dict(config), reports, path.stat().st_size,
                 args.config, tuple(args.set), versions)
    atomic_write_text(path.with_suffix(".md"), card)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB), {path.with_suffix('.json')} "
          f"and the model card {path.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
