#!/usr/bin/env bash
# Progressive denoising on the stress set (dataset-stress.toml: full frames with lamps of 1-3 px,
# their glossy reflections, glints and caustics) and its promise checked image by image:
#   experiments/pd_stress.sh
# Results (experiments/results/pd/pd-stress-ROW), each with MC, the denoiser and the 8 x 8 oracle:
#   oidn-pd               the shipped oidn-pd (OIDN with the specular-chain features)
#   oidn-pd-t-test-only   the same with the paper's t-test alone (tstat.guard=false)
#   wskp6-pd              the shipped wskp-6-pd, on the set's first-hit refeature (what WSKP-6
#                         was trained with)
#   wskp6-pd-t-test-only  the same with the t-test alone
#   wskp6-closed-form     Eq. 9 alone over WSKP-6 (no network; per-channel t, one probe)
#   oidn-pd-strata, wskp6-pd-strata   the shipped mixers with the guard's noise strata on
#                         (tstat.guard_strata=1, an option; jaxden/progressive/guard.py)
# then experiments/results/pd/pd-targets over them, the pd-test-high reports of wskp-6-pd and
# oidn-pd's report on test (experiments/pd_tables.sh).
# A result already made on the same build with the same options is kept (--keep-current).
# Data: $JAXDEN_HOME/data/stress (experiments/queue.sh); the first-hit refeature is made here.
set -euo pipefail
cd "$(dirname "$0")/.."
H="${JAXDEN_HOME:-$HOME/jaxden-work}"
python=${PYTHON:-.venv/bin/python}
R=experiments/results/pd
[ -f "$H/data/stress/manifest.json" ] || { echo "pd_stress: no dataset at $H/data/stress" >&2; exit 2; }
if [ ! -f "$H/data/stress-first-hit/manifest.json" ]; then
  "$python" -m jaxden.cli dataset refeature "$H/data/stress" aux=first-hit feature_spp=16 \
    --out "$H/data/stress-first-hit"
fi
pd() { "$python" -m jaxden.cli evaluate pd "$@" --keep-current; }
pd --data "$H/data/stress" --denoiser oidn --mixer oidn-pd --out "$R/pd-stress-oidn-pd"
pd --data "$H/data/stress-first-hit" --denoiser wskp-6 --mixer wskp-6-pd --out "$R/pd-stress-wskp6-pd"
pd --data "$H/data/stress-first-hit" --denoiser wskp-6 --mixer closed-form --probes 1 \
  --tstat per_channel=true --out "$R/pd-stress-wskp6-closed-form"
pd --data "$H/data/stress" --denoiser oidn --mixer oidn-pd --tstat guard_strata=1 \
  --out "$R/pd-stress-oidn-pd-strata"
pd --data "$H/data/stress-first-hit" --denoiser wskp-6 --mixer wskp-6-pd --tstat guard_strata=1 \
  --out "$R/pd-stress-wskp6-pd-strata"
pd --data "$H/data/stress" --denoiser oidn --mixer oidn-pd --tstat guard=false \
  --out "$R/pd-stress-oidn-pd-t-test-only"
pd --data "$H/data/stress-first-hit" --denoiser wskp-6 --mixer wskp-6-pd --tstat guard=false \
  --out "$R/pd-stress-wskp6-pd-t-test-only"
# The paper's f_act mixer over WSKP-6 (queue.sh step mixer-wskp6-fact), measured beside the
# shipped one; the guard's noise strata on pd-test-high.
if [ -d "$H/runs/mixer-wskp6-fact" ]; then
  pd --data "$H/data/stress-first-hit" --denoiser wskp-6 --mixer "$H/runs/mixer-wskp6-fact" \
    --tstat per_channel=true --out "$R/pd-stress-wskp6-fact"
  pd --data "$H/data/pd-test-high" --denoiser wskp-6 --mixer "$H/runs/mixer-wskp6-fact" \
    --tstat per_channel=true --out "$R/pd-wskp6-fact-test-high"
fi
pd --data "$H/data/pd-test-high" --denoiser wskp-6 --mixer wskp-6-pd --tstat guard_strata=1 \
  --out "$R/pd-wskp6-test-high-strata"
"$python" experiments/pd_targets.py "$R"/pd-stress-oidn-pd.json "$R"/pd-stress-wskp6-pd.json \
  "$R"/pd-stress-wskp6-closed-form.json "$R"/pd-stress-oidn-pd-strata.json \
  "$R"/pd-stress-wskp6-pd-strata.json "$R"/pd-stress-oidn-pd-t-test-only.json \
  "$R"/pd-stress-wskp6-pd-t-test-only.json "$R"/pd-wskp6-test-high.json \
  "$R"/pd-wskp6-test-high-closed-form.json "$R"/pd-wskp6-test-high-t-test-only.json \
  "$R"/pd-oidn-test-shipped.json "$R"/pd-stress-wskp6-fact.json \
  "$R"/pd-wskp6-fact-test-high.json "$R"/pd-wskp6-test-high-strata.json --out "$R/pd-targets"
