#!/usr/bin/env bash
# The shipped recipe (mixer-oidn-cflogit.toml) trained on the range-aware closed form
# (mixer-oidn-cflogit-stops.toml: closed_form_stops = 1), from nothing: the three datasets
# (resumable; ~80 + 13 + 55 min on the 2-core project CPU), OIDN's SURE cache, the training
# (runs/mixer-oidn-cflogit-stops1, ~30 min) and its PD reports on both held-out sets, beside
# the shipped mixer's on the same build. Every step resumes; rerun after an interruption.
set -euo pipefail
cd "$(dirname "$0")/.."
jaxden=${JAXDEN:-.venv/bin/jaxden}
python=${PYTHON:-.venv/bin/python}
"$jaxden" dataset build experiments/configs/dataset-default.toml name=default-chain --out data/default-chain
"$jaxden" dataset sure-cache data/default-chain --denoiser oidn
XLA_FLAGS=--xla_force_host_platform_device_count=2 "$jaxden" train \
  experiments/configs/mixer-oidn-cflogit-stops.toml data.dataset=data/default-chain \
  --workdir runs/mixer-oidn-cflogit-stops1
"$jaxden" dataset build experiments/configs/dataset-test.toml name=test-chain --out data/test-chain
"$jaxden" dataset build experiments/configs/dataset-test-high.toml name=test-high-chain --out data/test-high-chain
for set in chain high-chain; do
  data=data/test-chain; [ "$set" = high-chain ] && data=data/test-high-chain
  [ -f "experiments/results/pd-oidn-$set-cflogit-stops1.json" ] || \
    "$python" experiments/pd_report.py pd --data "$data" --denoiser oidn \
      --mixer runs/mixer-oidn-cflogit-stops1 --swap-average --out "experiments/results/pd-oidn-$set-cflogit-stops1"
done
