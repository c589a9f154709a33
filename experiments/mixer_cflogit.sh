#!/usr/bin/env bash
# The shipped mixer recipe (experiments/configs/mixer-oidn.toml, data/default-chain) with the
# closed_form_logit head: the network predicts a logit-space correction of Eq. 9's alpha
# (closed form with 12-px local means) instead of alpha itself, so that an untrained network,
# or one whose inputs lie outside what it learned (low-spp fireflies), falls back to the
# closed form. Then its PD reports on the held-out sets, to compare with
# experiments/results/pd-oidn{,-high}-chain{,-cf,-closed-form}.md. Resumable; ~45 min here.
set -euo pipefail
cd "$(dirname "$0")/.."
jaxden=${JAXDEN:-.venv/bin/jaxden}
python=${PYTHON:-.venv/bin/python}
XLA_FLAGS=--xla_force_host_platform_device_count=2 "$jaxden" train \
  experiments/configs/mixer-oidn.toml data.dataset=data/default-chain \
  model_config.head=closed_form_logit --workdir runs/mixer-oidn-cflogit
"$python" experiments/pd_report.py pd --data data/test-high-chain --denoiser oidn \
  --mixer runs/mixer-oidn-cflogit --swap-average \
  --out experiments/results/pd-oidn-high-chain-cflogit
"$python" experiments/pd_report.py pd --data data/test-chain --denoiser oidn \
  --mixer runs/mixer-oidn-cflogit --swap-average \
  --out experiments/results/pd-oidn-chain-cflogit
