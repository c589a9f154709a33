#!/usr/bin/env bash
# PD over the real-time WSKP-6, the consistent real-time denoiser: ship the trained mixer as
# `wskp-6-pd`, measure it on the progressive sequence (one held-out frame at 2..4096 spp; at
# 1 spp there is no variance, so no PD) and on the held-out pd-test-high set, plot the
# sequence's convergence, measure it on the out-of-distribution scenes (data/ood-first-hit),
# and re-ship with the reports in the model card. A report made on the same data build with the
# same mixer and options is kept (jaxden evaluate pd --keep-current).
#   experiments/pd_wskp6.sh
# Needs (experiments/queue.sh): $JAXDEN_HOME/runs/mixer-wskp6-4k (mixer-wskp6.toml on data/pd-rt4k),
# $JAXDEN_HOME/data/pd-sequence and $JAXDEN_HOME/data/pd-test-high. SURE probe seed 0, one probe
# (the mixer's training probes).
set -euo pipefail
cd "$(dirname "$0")/.."
H="${JAXDEN_HOME:-$HOME/jaxden-work}"
python=${PYTHON:-.venv/bin/python}
R=experiments/results/pd
# Shipped with the paper's per-channel t-statistic (the authors' code sums the channels): on
# the out-of-distribution scenes the shared form made every PD(OIDN) cell that broke the 1 %
# bound (experiments/results/pd/pd-oidn-ood-diagnosis.md), and for WSKP-6 the per-channel form
# is as good or better at every spp there (both rows are in every report).
ship=("$python" experiments/ship_mixer.py --workdir "$H/runs/mixer-wskp6-4k" --name wskp-6-pd
      --config experiments/configs/mixer-wskp6.toml --set tstat.per_channel=true)
"${ship[@]}"
"$python" -m jaxden.cli evaluate pd --data "$H/data/pd-sequence" --denoiser wskp-6 \
  --mixer wskp-6-pd --spp 2 4 8 16 32 64 128 256 512 1024 2048 4096 --out "$R/pd-wskp6-sequence" --keep-current
"$python" -m jaxden.cli evaluate pd --data "$H/data/pd-test-high" --denoiser wskp-6 \
  --mixer wskp-6-pd --out "$R/pd-wskp6-test-high" --keep-current
# outside the training distribution (the OOD scenes with WSKP-6's first-hit features)
"$python" -m jaxden.cli evaluate pd --data "$H/data/ood-first-hit" --denoiser wskp-6 \
  --mixer wskp-6-pd --spp 16 32 64 128 256 512 1024 --out "$R/pd-wskp6-ood-first-hit" \
  --keep-current
"$python" experiments/pd_ood.py "$R/pd-wskp6-ood-first-hit.json" \
  --out "$R/pd-wskp6-ood-first-hit-diagnosis"
"$python" experiments/pd_figure.py convergence --report "$R/pd-wskp6-sequence.json" \
  --out "$R/fig-pd-wskp6-sequence"
"${ship[@]}" --report "$R/pd-wskp6-sequence.json" --report "$R/pd-wskp6-test-high.json" \
  --report "$R/pd-wskp6-ood-first-hit.json"
