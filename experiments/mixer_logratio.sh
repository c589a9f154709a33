#!/usr/bin/env bash
# The shipped mixer recipe (experiments/configs/mixer-oidn.toml) trained with the log-ratio
# loss reduction (optim.loss_reduction = "log_ratio": the mean over images of
# log(SMAPE(z) / SMAPE(y)), so that a 4096-spp input pulls as hard as a 2-spp one) on the
# 2..4096-spp data of experiments/mixer_4k.sh, and its PD reports on the held-out sets, to
# compare with experiments/results/pd-oidn{,-high}-chain{,-4k}.md. Resumable; ~45 min here.
#
# Peak learning rate 1e-4 instead of the recipe's 5e-4: at 5e-4 the run reached a log ratio of
# -0.6 at step 120 and then collapsed, at step ~150 (lr 4.5e-4), to alpha = 1 everywhere
# (z = y, loss exactly 0, f_act saturated so the gradient is 0) and never left it.
#
#   experiments/mixer_4k.sh          # first: data/default-4k-chain and its OIDN SURE cache
#   experiments/mixer_logratio.sh
set -euo pipefail
cd "$(dirname "$0")/.."
jaxden=${JAXDEN:-.venv/bin/jaxden}
python=${PYTHON:-.venv/bin/python}
XLA_FLAGS=--xla_force_host_platform_device_count=2 "$jaxden" train \
  experiments/configs/mixer-oidn.toml data.dataset=data/default-4k-chain \
  optim.loss_reduction=log_ratio optim.learning_rate=1e-4 --workdir runs/mixer-oidn-4k-logratio
"$python" experiments/pd_report.py pd --data data/test-high-chain --denoiser oidn \
  --mixer runs/mixer-oidn-4k-logratio --swap-average \
  --out experiments/results/pd-oidn-high-chain-logratio
"$python" experiments/pd_report.py pd --data data/test-chain --denoiser oidn \
  --mixer runs/mixer-oidn-4k-logratio --swap-average \
  --out experiments/results/pd-oidn-chain-logratio
