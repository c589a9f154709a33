#!/usr/bin/env bash
# Retrains the shipped mixer's recipe (mixer-oidn-cflogit.toml) on the range-aware closed form
# it ships with (mixer-oidn-cflogit-stops.toml: closed_form_stops = 1; the shipped weights
# learned their correction on the plain closed form), from nothing: the training set and both
# held-out sets (resumable; 13 min for test and 55 min for test-high measured, ~80 min for the
# training set estimated, on the 2-core project CPU), OIDN's SURE
# cache, the training ($JAXDEN_HOME/runs/mixer-oidn-cflogit-stops1, ~30 min), then the PD
# table with the retrained mixer as an extra row (experiments/pd_tables.sh: every row on the
# same build, experiments/results/pd/pd-oidn-{test,test-high}-retrained-stops1.*).
# Every step resumes; run it again after an interruption.
#   experiments/mixer_cflogit_stops.sh
# To ship the result if it beats the shipped mixer on both sets (see experiments/README.md):
#   python experiments/ship_mixer.py --workdir "$JAXDEN_HOME/runs/mixer-oidn-cflogit-stops1" \
#     --name oidn-pd --swap-average --config experiments/configs/mixer-oidn-cflogit-stops.toml \
#     --report experiments/results/pd/pd-oidn-test-retrained-stops1.json \
#     --report experiments/results/pd/pd-oidn-test-high-retrained-stops1.json
set -euo pipefail
cd "$(dirname "$0")/.."
H="${JAXDEN_HOME:-$HOME/jaxden-work}"
jaxden=${JAXDEN:-.venv/bin/jaxden}
mkdir -p "$H/data" "$H/runs"
"$jaxden" dataset build experiments/configs/dataset-default.toml name=default-chain --out "$H/data/default-chain"
"$jaxden" dataset sure-cache "$H/data/default-chain" --denoiser oidn
XLA_FLAGS=--xla_force_host_platform_device_count=2 "$jaxden" train \
  experiments/configs/mixer-oidn-cflogit-stops.toml data.dataset="$H/data/default-chain" \
  --workdir "$H/runs/mixer-oidn-cflogit-stops1"
"$jaxden" dataset build experiments/configs/dataset-test.toml name=test-chain --out "$H/data/test-chain"
"$jaxden" dataset build experiments/configs/dataset-test-high.toml name=test-high-chain --out "$H/data/test-high-chain"
experiments/pd_tables.sh retrained-stops1 "$H/runs/mixer-oidn-cflogit-stops1"
