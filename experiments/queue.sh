#!/usr/bin/env bash
# The background job queue: dataset builds, then training runs, each resumable. Run it again
# after an interruption and it carries on where it stopped (finished steps are skipped).
#   setsid nohup experiments/queue.sh > "$JAXDEN_HOME/queue.log" 2>&1 &
# Data and runs live under $JAXDEN_HOME (default ~/jaxden-work), outside the checkout.
set -uo pipefail
cd "$(dirname "$0")/.."
H="${JAXDEN_HOME:-$HOME/jaxden-work}"
J=.venv/bin/jaxden
mkdir -p "$H/data" "$H/runs"
step() {  # step NAME COMMAND...: run unless $H/done/NAME exists, time it
  local name=$1; shift
  if [ -e "$H/done/$name" ]; then echo "queue: $name already done"; return 0; fi
  echo "queue: $name started $(date -Is)"
  local t0=$SECONDS
  if "$@"; then
    mkdir -p "$H/done"; echo "$((SECONDS - t0)) s" > "$H/done/$name"
    echo "queue: $name finished in $((SECONDS - t0)) s"
  else
    echo "queue: $name FAILED (exit $?)"; return 1
  fi
}
step data-rt $J dataset build experiments/configs/dataset-rt.toml --out "$H/data/rt" || exit 1
step data-rt-test $J dataset build experiments/configs/dataset-rt-test.toml --out "$H/data/rt-test" || exit 1
step data-rt-seq $J dataset sequences experiments/configs/sequences-rt-test.toml --out "$H/data/rt-seq" --quiet || exit 1
# The real-time sweeps (experiments/README.md), most wanted first; each resumes where it stopped.
step sweep-rt-main $J sweep experiments/sweeps/rt-main.toml --workdir "$H/runs/sweeps/rt-main"
step sweep-rt-noise2noise $J sweep experiments/sweeps/rt-noise2noise.toml --workdir "$H/runs/sweeps/rt-noise2noise"
# Progressive denoising over the real-time WSKP-6 (`wskp-6-pd`): the bases' training set, the
# mixer's (jvp SURE, one probe, width 16), and the 1..4096-spp sequence it is measured on.
step data-pd-rt $J dataset build experiments/configs/dataset-pd-rt.toml --out "$H/data/pd-rt"
# Mixers train over the paper's whole range, 2..4096 spp (dataset-pd-rt4k.toml); pd-rt (to
# 1024 spp) trains the bases.
step data-pd-rt4k $J dataset build experiments/configs/dataset-pd-rt4k.toml --out "$H/data/pd-rt4k"
step mixer-wskp6-4k env XLA_FLAGS=--xla_force_host_platform_device_count=2 $J train \
  experiments/configs/mixer-wskp6.toml data.dataset="$H/data/pd-rt4k" --workdir "$H/runs/mixer-wskp6-4k"
step data-pd-sequence $J dataset build experiments/configs/dataset-pd-sequence.toml \
  --out "$H/data/pd-sequence"
step data-pd-test-high $J dataset build experiments/configs/dataset-pd-test-high.toml \
  --out "$H/data/pd-test-high"
step sweep-rt-ablation $J sweep experiments/sweeps/rt-ablation.toml --workdir "$H/runs/sweeps/rt-ablation"
# The remaining real-time models (WSKP-3, KP-1, KP-2, WSKP-MR, U-Net, WSKP-6+1x1), about 3 h.
step sweep-rt-variants $J sweep experiments/sweeps/rt-variants.toml --workdir "$H/runs/sweeps/rt-variants"
# The progressive-denoising paper's Tables 1 and 2 on our data: bases trained on PD data
# (U-Net x 4 feature sets, KP 5 x 5, WSKP-6), one mixer per base (on pd-rt4k), PD reports on
# pd-test-high, and SURE's accuracy for each base (experiments/README.md).
step sweep-pd-bases env XLA_FLAGS=--xla_force_host_platform_device_count=2 $J sweep \
  experiments/sweeps/pd-bases.toml --workdir "$H/runs/sweeps/pd-bases"
# SURE by jvp against the true error of every JAX base (into the checkout's
# experiments/results: commit it). The shipped WSKP-6 first, then the pd-bases runs. On
# pd-test-high rebuilt with the colour covariance (same config and seeds, so the same renders
# plus Frame.covariance): SURE from the covariance and the paper's per-channel form, side by
# side.
step data-pd-test-high-cov $J dataset build experiments/configs/dataset-pd-test-high.toml \
  name=pd-test-high-cov --out "$H/data/pd-test-high-cov"
B="$H/runs/sweeps/pd-bases"
step sure-pd-bases-cov .venv/bin/python experiments/pd_report.py sure \
  --data "$H/data/pd-test-high-cov" --denoiser wskp-6 --denoiser "$B/unet-hdr" \
  --denoiser "$B/unet-hdr-var" --denoiser "$B/unet-hdr-alb-nrm" \
  --denoiser "$B/unet-hdr-alb-nrm-var" --denoiser "$B/kp5" --denoiser "$B/wskp6" \
  --out experiments/results/sure-pd-bases
step sweep-pd-mixers env XLA_FLAGS=--xla_force_host_platform_device_count=2 $J sweep \
  experiments/sweeps/pd-mixers.toml --workdir "$H/runs/sweeps/pd-mixers"
# Eq. 9 alone (the closed-form mixer, no network) over each base, SURE from the colour
# covariance, per-channel t: the pd_bases_tables.py rows "Eq. 9 alone" (reports outside the
# checkout, one per base; --keep-current skips a finished one).
pd_closed_form() {
  mkdir -p "$H/runs/pd-closed-form"
  for base in unet-hdr unet-hdr-var unet-hdr-alb-nrm unet-hdr-alb-nrm-var kp5 wskp6; do
    .venv/bin/python experiments/pd_report.py pd --data "$H/data/pd-test-high-cov" \
      --denoiser "$H/runs/sweeps/pd-bases/$base" --mixer closed-form \
      --mixer-set sure_covariance=true --tstat per_channel=true --probes 1 --keep-current \
      --out "$H/runs/pd-closed-form/$base" || return 1
  done
}
step pd-bases-closed-form pd_closed_form
# The same mixers with SURE from the colour covariance, on pd-rt4k rebuilt with it
# (pd-mixers-cov.toml; ~1 h for the data, ~1.5 h for the six runs).
step data-pd-rt4k-cov $J dataset build experiments/configs/dataset-pd-rt4k.toml \
  name=pd-rt4k-cov --out "$H/data/pd-rt4k-cov"
step sweep-pd-mixers-cov env XLA_FLAGS=--xla_force_host_platform_device_count=2 $J sweep \
  experiments/sweeps/pd-mixers-cov.toml --workdir "$H/runs/sweeps/pd-mixers-cov"
for extra in "$H"/queue.d/*.sh; do   # ad-hoc steps of this machine, outside the checkout
  [ -e "$extra" ] && source "$extra"
done
echo "queue: all done $(date -Is)"
