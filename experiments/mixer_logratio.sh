#!/usr/bin/env bash
# The shipped mixer recipe (experiments/configs/mixer-oidn.toml) trained with the log-ratio
# loss reduction (optim.loss_reduction = "log_ratio": the mean over images of
# log(SMAPE(z) / SMAPE(y)), so that a 4096-spp input pulls as hard as a 2-spp one) on the
# 2..4096-spp data of experiments/mixer_4k.sh, and its PD reports on the held-out sets, to
# compare with experiments/results/pd-oidn{,-high}-chain{,-4k}.md. Resumable; ~45 min here.
#
#   experiments/mixer_4k.sh          # first: data/default-4k-chain and its OIDN SURE cache
#   experiments/mixer_logratio.sh
set -euo pipefail
cd "$(dirname "$0")/.."
jaxden=${JAXDEN:-.venv/bin/jaxden}
python=${PYTHON:-.venv/bin/python}
XLA_FLAGS=--xla_force_host_platform_device_count=2 "$jaxden" train \
  experiments/configs/mixer-oidn.toml data.dataset=data/default-4k-chain \
  optim.loss_reduction=log_ratio --workdir runs/mixer-oidn-4k-logratio
"$python" experiments/pd_report.py pd --data data/test-high-chain --denoiser oidn \
  --mixer runs/mixer-oidn-4k-logratio --swap-average \
  --out experiments/results/pd-oidn-high-chain-logratio
"$python" experiments/pd_report.py pd --data data/test-chain --denoiser oidn \
  --mixer runs/mixer-oidn-4k-logratio --swap-average \
  --out experiments/results/pd-oidn-chain-logratio
