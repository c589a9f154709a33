#!/usr/bin/env bash
# The progressive-denoising table of README.md and docs/results.md on both held-out sets,
# Figure 10 (convergence plots of the shipped mixer, image series of crop s002), the shipped
# mixer outside the training distribution (both OOD variants, with pd_ood.py's diagnosis) and
# the model card of oidn-pd, which quotes the two held-out reports:
#   experiments/pd_tables.sh [NAME MIXER]
# Rows, each one `jaxden evaluate pd` result per set
# (experiments/results/pd/pd-oidn-{test,test-high}-ROW):
#   shipped              the shipped mixer oidn-pd as shipped
#   shipped-stops-none   the same weights on the plain closed form (closed_form_stops=none)
#   closed-form-stops1   the closed-form mixer with brightness strata, no network
#   closed-form          the plain closed-form mixer
#   NAME                 optional: another mixer (a run folder), swap-averaged, e.g.
#                        retrained-stops1 "$JAXDEN_HOME/runs/mixer-oidn-cflogit-stops1"
# Every report also holds MC, OIDN and the 8 x 8-tile oracle. All rows of a set must be on one
# build of it: a report already made on the same build (same manifest hash) with the same
# mixer, config and options is kept (jaxden evaluate pd --keep-current), any other is made
# again, so the script resumes after an interruption and refreshes everything after a rebuild or a
# re-ship. Data: $JAXDEN_HOME/data/test-chain and test-high-chain (dataset-test.toml and
# dataset-test-high.toml built with name=test-chain / name=test-high-chain), data/ood and
# data/ood-first-hit (dataset-ood.toml; experiments/README.md).
set -euo pipefail
cd "$(dirname "$0")/.."
H="${JAXDEN_HOME:-$HOME/jaxden-work}"
python=${PYTHON:-.venv/bin/python}
extra_name=${1:-}
extra_mixer=${2:-}
if [ -n "$extra_name" ] && [ -z "$extra_mixer" ]; then
  echo "usage: experiments/pd_tables.sh [NAME MIXER]" >&2; exit 2
fi

current() {  # current OUT DATA: OUT.json exists and was made on DATA's build
  "$python" - "$1.json" "$2/manifest.json" <<'PY'
import json, sys
from pathlib import Path
from jaxden.provenance import file_sha256
report, manifest = Path(sys.argv[1]), Path(sys.argv[2])
ok = report.is_file() and json.loads(report.read_text())["provenance"]["dataset"][
    "manifest_sha256"] == file_sha256(manifest)
sys.exit(0 if ok else 1)
PY
}

report() {  # report DATA OUT ARGS...: jaxden evaluate pd unless OUT is current
  local data=$1 out=$2; shift 2
  "$python" -m jaxden.cli evaluate pd --data "$data" --denoiser oidn "$@" --out "$out" \
    --keep-current
}

for set in test test-high; do
  data="$H/data/$set-chain"
  [ -f "$data/manifest.json" ] || { echo "pd_tables: no dataset at $data" >&2; exit 2; }
  out=experiments/results/pd/pd-oidn-$set
  report "$data" "$out-shipped" --mixer oidn-pd
  report "$data" "$out-shipped-stops-none" --mixer oidn-pd --mixer-set closed_form_stops=none
  report "$data" "$out-closed-form-stops1" --mixer closed-form:stops=1
  report "$data" "$out-closed-form" --mixer closed-form
  if [ -n "$extra_name" ]; then
    report "$data" "$out-$extra_name" --mixer "$extra_mixer" --swap-average
  fi
done

for set in ood ood-first-hit; do
  data="$H/data/$set"
  [ -f "$data/manifest.json" ] || { echo "pd_tables: no dataset at $data" >&2; exit 2; }
  report "$data" "experiments/results/pd/pd-oidn-$set-shipped" --mixer oidn-pd \
    --spp 16 32 64 128 256 512 1024
  "$python" experiments/pd_ood.py "experiments/results/pd/pd-oidn-$set-shipped.json" \
    --out "experiments/results/pd/pd-oidn-$set-diagnosis"
done

"$python" experiments/ship_mixer.py --reship oidn-pd \
  --report experiments/results/pd/pd-oidn-test-shipped.json \
  --report experiments/results/pd/pd-oidn-test-high-shipped.json

"$python" experiments/pd_figure.py convergence \
  --report experiments/results/pd/pd-oidn-test-high-shipped.json \
  --title "test-high (32..4096 spp, 16384-spp references): mean over 8 held-out crops" \
  --out experiments/results/pd/fig10-convergence-high
"$python" experiments/pd_figure.py convergence \
  --report experiments/results/pd/pd-oidn-test-shipped.json \
  --title "test (2..1024 spp, 4096-spp references): mean over 8 held-out crops" \
  --out experiments/results/pd/fig10-convergence
if ! current experiments/results/pd/fig10-s002 "$H/data/test-high-chain"; then
  "$python" experiments/pd_figure.py images --data "$H/data/test-high-chain" --crop s002-c000 \
    --spp 64 512 4096 --out experiments/results/pd/fig10-s002
fi
