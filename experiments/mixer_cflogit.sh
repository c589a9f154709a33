#!/usr/bin/env bash
# The shipped mixer recipe (experiments/configs/mixer-oidn.toml, data/default-chain) with the
# closed_form_logit head: the network predicts a logit-space correction of Eq. 9's alpha
# (closed form with 12-px local means) instead of alpha itself, so that an untrained network
# starts at the closed form. Then its PD reports on the held-out sets, to compare with
# experiments/results/pd-oidn{,-high}-chain{,-cf,-closed-form}.md. Resumable; ~45 min here.
#
#   experiments/mixer_cflogit.sh        # unbounded correction: runs/mixer-oidn-cflogit
#   experiments/mixer_cflogit.sh B      # correction B tanh(raw / B), alpha_cf clipped to
#                                       # [1e-4, 1 - 1e-4]: runs/mixer-oidn-cflogit-bB
set -euo pipefail
cd "$(dirname "$0")/.."
jaxden=${JAXDEN:-.venv/bin/jaxden}
python=${PYTHON:-.venv/bin/python}
name=cflogit
extra=()
if [ $# -gt 0 ]; then
  name=cflogit-b$1
  extra=(model_config.logit_bound="$1" model_config.logit_eps=1e-4)
fi
XLA_FLAGS=--xla_force_host_platform_device_count=2 "$jaxden" train \
  experiments/configs/mixer-oidn.toml data.dataset=data/default-chain \
  model_config.head=closed_form_logit "${extra[@]}" --workdir "runs/mixer-oidn-$name"
"$python" experiments/pd_report.py pd --data data/test-chain --denoiser oidn \
  --mixer "runs/mixer-oidn-$name" --swap-average \
  --out "experiments/results/pd-oidn-chain-$name"
"$python" experiments/pd_report.py pd --data data/test-high-chain --denoiser oidn \
  --mixer "runs/mixer-oidn-$name" --swap-average \
  --out "experiments/results/pd-oidn-high-chain-$name"
