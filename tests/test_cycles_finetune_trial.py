"""The fine-tuning road of docs/your-renderer.md (sections 5-7) on an import a user may have:
Blender Cycles renders with the input levels 1 and 4 spp only (no ``spp2``) and a val split
of 2 crops, fewer examples than one batch of the shipped config. It trains (validation padded
and masked), and the stock and fine-tuned models are evaluated on the held-out views with the
relMSE on their lamp pixels, side by side (experiments/finetune_gain.py).

A slow test over the renders of experiments/renderers/cycles_dataset.py in
``$JAXDEN_HOME/cycles-src`` (the queue's step data-cycles-src; about 13 minutes of rendering,
so skipped where they are not): a small import of 8 of its views, whole views as crops (the
held-out views' emitters are then in their crops), 40 steps. About 3 minutes on 2 cores.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from helpers import ROOT, load_script, run_cli

from jaxden.data.layout import load_manifest

SOURCE = Path(os.environ.get("JAXDEN_HOME", Path.home() / "jaxden-work")) / "cycles-src"
CONFIG = ROOT / "experiments" / "configs" / "finetune-wskp6-cycles.toml"
TRAIN = ("s00v0", "s01v0", "s02v0", "s03v0")  # 4 crops x 2 levels: one batch of 8
VAL = ("s06v0", "s06v1")  # 2 crops, 4 examples: fewer than a batch
HELD_OUT = ("s07v0", "s08v0")  # each sees an emitter
KEPT = ("reference", "spp1.exr", "spp4")  # the source's spp2/ is left out


def _source_with_levels_1_and_4(folder: Path) -> Path:
    """The views of TRAIN, VAL and HELD_OUT as the import reads them, without their 2-spp
    renders: symbolic links to the reference, spp1.exr and spp4/ of each."""
    for view in TRAIN + VAL + HELD_OUT:
        (folder / view).mkdir(parents=True)
        for name in KEPT:
            (folder / view / name).symlink_to(SOURCE / view / name)
    return folder


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_docs_finetune_on_levels_1_and_4_with_two_val_crops(tmp_path, capsys):
    if not all((SOURCE / view / name).exists() for view in TRAIN + VAL + HELD_OUT
               for name in KEPT):
        pytest.skip(f"needs the Cycles renders in {SOURCE}: experiments/renderers/"
                    f"cycles_dataset.py --out $JAXDEN_HOME/cycles-src (docs/your-renderer.md)")
    src = _source_with_levels_1_and_4(tmp_path / "src")
    data = tmp_path / "data"
    code, errors, _ = run_cli(["dataset", "import", src, "--from", "cycles", "--crop", 256,
                               "--crops-per-view", 1, "--val", ",".join(VAL),
                               "--held-out", ",".join(HELD_OUT), "--quiet", "--out", data],
                              capsys)
    assert code == 0, errors
    manifest = load_manifest(data)
    assert manifest.config["spp"] == [1, 4]
    assert manifest.split_counts() == {"train": 4, "val": 2, "test": 2}

    run = tmp_path / "run"  # the config as shipped: every level the import has, batch 8
    code, errors, _ = run_cli(["train", CONFIG, f"data.dataset={data}", "optim.steps=40",
                                     "log_every=10", "--workdir", run, "--no-tensorboard"],
                                    capsys)
    assert code == 0, errors
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in records if "loss" in r]
    validations = [r for r in records if "val_loss" in r]
    assert len(losses) == 4 and [r["step"] for r in validations] == [0, 40]
    print(f"\ntrain: losses at steps 10..40 {[round(x, 4) for x in losses]}; validation "
          f"(4 examples) {[(r['step'], round(r['val_loss'], 4)) for r in validations]}")

    results = {}
    for name, denoiser in (("stock", "wskp-6"), ("tuned", run)):
        results[name] = tmp_path / name
        code, errors, _ = run_cli(["evaluate", "denoise", "--data", data, "--split", "test",
                                   "--spp", 1, "--denoiser", denoiser,
                                   "--out", results[name]], capsys)
        assert code == 0, errors
        table = results[name].with_suffix(".md").read_text()
        assert "| relMSE (lamps) | lamp mean / reference | lamp pixels |" in table
        summary = json.loads(results[name].with_suffix(".json").read_text())["summary"]
        assert summary["count"] == 2 and summary["lamp_pixels"] > 0
        print(f"{name} ({denoiser}):\n{table}")
    gain = tmp_path / "gain"
    assert load_script("finetune_gain").main([
        "--stock", str(results["stock"].with_suffix(".json")),
        "--tuned", str(results["tuned"].with_suffix(".json")), "--out", str(gain)]) == 0
    text = gain.with_suffix(".md").read_text()
    assert "relMSE on lamps: stock | fine-tuned" in text
    print(text)
