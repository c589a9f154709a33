#!/usr/bin/env bash
# The background job queue: dataset builds, then training runs, each resumable. Run it again
# after an interruption and it carries on where it stopped (finished steps are skipped).
#   setsid nohup experiments/queue.sh > "$JAXDEN_HOME/queue.log" 2>&1 &
# Data and runs live under $JAXDEN_HOME (default ~/jaxden-work), outside the checkout.
# Ordered for a machine that starts from nothing: what the open work needs first (the
# progressive-denoising tables over the JAX bases), then what regenerates finished results.
set -uo pipefail
cd "$(dirname "$0")/.."
# Run this checkout's jaxden even when .venv holds an editable install of another checkout
# (a queue worktree sharing the main checkout's .venv would otherwise import the main one's
# working copy, edits in progress included).
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
H="${JAXDEN_HOME:-$HOME/jaxden-work}"
J=.venv/bin/jaxden
X=(env XLA_FLAGS=--xla_force_host_platform_device_count=2)
mkdir -p "$H/data" "$H/runs"
step() {  # step NAME COMMAND...: run unless $H/done/NAME exists, time it
  local name=$1; shift
  # QUEUE_ONLY=REGEX runs only the steps whose names match (a second queue beside the first).
  if [ -n "${QUEUE_ONLY:-}" ] && ! [[ $name =~ $QUEUE_ONLY ]]; then return 0; fi
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
# The comparisons of both papers (SVGF, BMFR, NBGD, MR-KP, NFOR, the Deep Combiner): the
# real-time sets their tables are measured on and the trained baselines learn from, first.
step data-rt-test $J dataset build experiments/configs/dataset-rt-test.toml --out "$H/data/rt-test" || exit 1
step data-rt-seq $J dataset sequences experiments/configs/sequences-rt-test.toml --out "$H/data/rt-seq" --quiet || exit 1
step data-rt $J dataset build experiments/configs/dataset-rt.toml --out "$H/data/rt" || exit 1
# Progressive denoising on every pixel (lamps, highlights): the held-out sets every shipped
# mixer is measured on, the stress set built to break it first (experiments/configs/
# dataset-stress.toml, full frames with small emitters, glints and caustics), then the rest.
step data-pd-test-high $J dataset build experiments/configs/dataset-pd-test-high.toml \
  --out "$H/data/pd-test-high"
step data-stress $J dataset build experiments/configs/dataset-stress.toml --out "$H/data/stress"
step data-test-chain $J dataset build experiments/configs/dataset-test.toml name=test-chain \
  --out "$H/data/test-chain"
step data-ood $J dataset build experiments/configs/dataset-ood.toml --out "$H/data/ood"
step data-test-high-chain $J dataset build experiments/configs/dataset-test-high.toml \
  name=test-high-chain --out "$H/data/test-high-chain"
# The mixers' training set, and the paper's f_act mixer over the shipped WSKP-6 (the recipe of
# wskp-6-pd with the f_act head of the paper's Table 4): measured beside the shipped mixers.
step data-pd-rt4k $J dataset build experiments/configs/dataset-pd-rt4k.toml --out "$H/data/pd-rt4k"
# An independent replica of the mixers' training set (same crops, other seeds; its reference
# at the top input's spp, unused): the second half of each item for the neural James-Stein
# combiner, whose cross-regression fits one half on the other.
step data-pd-rt4k-r1 $J dataset build experiments/configs/dataset-pd-rt4k.toml name=pd-rt4k-r1 \
  replica=1 reference_spp=4096 --out "$H/data/pd-rt4k-r1"
# StatMC's statistics (Frame.boxcox) on the held-out crops and the stress frames: the same
# configs, seeds and samples (the colour is that of the sets above), 4..4096 spp.
STATS="statistics=true spp=[4,8,16,32,64,128,256,512,1024,2048,4096]"
step data-stress-stats $J dataset build experiments/configs/dataset-stress.toml name=stress-stats \
  $STATS --out "$H/data/stress-stats"
step data-pd-test-high-stats $J dataset build experiments/configs/dataset-pd-test-high.toml \
  name=pd-test-high-stats $STATS --out "$H/data/pd-test-high-stats"
# The Deep Combiner over OIDN in JAX, two seeds, on the mixers' training set, and the
# progressive-denoising paper's Fig. 11 on pd-test-high: MC, OIDN, DC, PD(OIDN), PD(DC)
# (into $H/runs/pd-fig11; `python experiments/pd_fig11.py` tabulates them).
step dc-oidn-s0 "${X[@]}" $J train experiments/configs/train-dc.toml --workdir "$H/runs/dc-oidn-s0"
pd_eval() {  # pd_eval SET DENOISER MIXER OUT [OPTIONS]: `evaluate pd` on $H/data/SET
  mkdir -p "$(dirname "$4")"
  if [ "$3" = closed-form ]; then  # Eq. 9 alone: SURE from the covariance, per-channel t
    set -- "$@" --mixer-set sure.covariance=true --tstat per_channel=true --probes 1
  fi
  .venv/bin/python -m jaxden.cli evaluate pd --data "$H/data/$1" --denoiser "$2" \
    --mixer "$3" --keep-current --out "$4" "${@:5}"
}
fig11_pd() {  # fig11_pd DENOISER MIXER NAME
  pd_eval pd-test-high "$1" "$2" "$H/runs/pd-fig11/$3"
}
# The trained baselines of the WSKP paper's tables (NBGD, MR-KP; two seeds each), then the
# progressive-denoising evaluations of the first DC, then WSKP-6 and KP (rt-main) for the same
# tables (`python experiments/rt_comparisons.py` reads whatever has finished).
step sweep-rt-baselines "${X[@]}" $J sweep experiments/sweeps/rt-baselines.toml \
  --workdir "$H/runs/sweeps/rt-baselines"
step fig11-pd-dc-s0 fig11_pd "$H/runs/dc-oidn-s0" closed-form pd-dc-s0
step fig11-pd-oidn-closed-form fig11_pd oidn-jax closed-form pd-oidn-closed-form
step fig11-pd-oidn fig11_pd oidn-jax oidn-pd pd-oidn
step dc-oidn-s1 "${X[@]}" $J train experiments/configs/train-dc.toml seed=1 --workdir "$H/runs/dc-oidn-s1"
step fig11-pd-dc-s1 fig11_pd "$H/runs/dc-oidn-s1" closed-form pd-dc-s1
# The table of consistent denoisers (experiments/consistent_table.py reads $H/runs/consistent):
# MC, OIDN, PD(OIDN), PD(WSKP-6), DC and PD(DC), StatMC and its Moon-CI test, on the held-out
# crops, the stress frames and whole frames, each with StatMC's statistics.
step data-frames-stats $J dataset build experiments/configs/dataset-frames-stats.toml \
  --out "$H/data/frames-stats"
# Replicas of the three sets (same crops, other seeds; references at the top input's spp,
# unused): the second halves the neural James-Stein combiner needs; NJS at 2s spp combines
# the set's and the replica's s-spp items.
R1="replica=1 statistics=false reference_spp=4096 spp=[4,8,16,32,64,128,256,512,1024,2048,4096]"
step data-stress-stats-r1 $J dataset build experiments/configs/dataset-stress.toml \
  name=stress-stats-r1 $R1 --out "$H/data/stress-stats-r1"
step data-pd-test-high-stats-r1 $J dataset build experiments/configs/dataset-pd-test-high.toml \
  name=pd-test-high-stats-r1 $R1 --out "$H/data/pd-test-high-stats-r1"
step data-frames-stats-r1 $J dataset build experiments/configs/dataset-frames-stats.toml \
  name=frames-stats-r1 replica=1 statistics=false reference_spp=1024 \
  --out "$H/data/frames-stats-r1"
for set in stress-stats pd-test-high-stats frames-stats; do
  C="$H/runs/consistent/$set"
  LEVELS=(4 8 16 32 64 128 256 512 1024 2048 4096)
  if [ "$set" = frames-stats ]; then LEVELS=("${LEVELS[@]:0:9}"); fi
  step "consistent-$set-statmc" $J evaluate denoise --data "$H/data/$set" --denoiser statmc \
    --spp "${LEVELS[@]}" --out "$C/statmc"
  step "consistent-$set-statmc-moon" $J evaluate denoise --data "$H/data/$set" \
    --denoiser statmc-moon --spp "${LEVELS[@]}" --no-input --out "$C/statmc-moon"
  step "consistent-$set-pd-oidn" pd_eval "$set" oidn-jax oidn-pd "$C/pd-oidn"
  step "consistent-$set-pd-wskp6" pd_eval "$set" wskp-6 wskp-6-pd "$C/pd-wskp6"
  # WSKP-6 with the lamps taken out before the filter and added back (emission=separate): the
  # documented remedy for its lamp spreading, beside WSKP-6 alone.
  step "consistent-$set-wskp6-separate" $J evaluate denoise --data "$H/data/$set" \
    --denoiser wskp-6:emission=separate --spp "${LEVELS[@]}" --no-input --out "$C/wskp6-separate"
  for seed in 0 1; do
    step "consistent-$set-pd-dc-s$seed" pd_eval "$set" "$H/runs/dc-oidn-s$seed" closed-form \
      "$C/pd-dc-s$seed"
  done
done
# The neural James-Stein combiner over OIDN in JAX (train-njs.toml), two seeds on pd-rt4k and
# its replica (the first run builds the cross-regression cache, ~15 min), then NJS at 2s spp
# from the s-spp items of each set and its replica, for the consistent table.
step njs-oidn-s0 "${X[@]}" $J train experiments/configs/train-njs.toml --workdir "$H/runs/njs-oidn-s0"
step njs-oidn-s1 "${X[@]}" $J train experiments/configs/train-njs.toml seed=1 \
  --workdir "$H/runs/njs-oidn-s1"
for set in pd-test-high-stats stress-stats frames-stats; do
  for seed in 0 1; do
    step "consistent-$set-njs-s$seed" $J evaluate njs --data "$H/data/$set" \
      --replica "$H/data/$set-r1" --denoiser "$H/runs/njs-oidn-s$seed" \
      --out "$H/runs/consistent/$set/njs-s$seed"
  done
done
# NJS over WSKP-6 (the issue's second base): two seeds, on the held-out crops and the stress
# frames (the first run builds its own cross-regression cache).
for seed in 0 1; do
  step "njs-wskp6-s$seed" "${X[@]}" $J train experiments/configs/train-njs.toml \
    model_config.base=wskp-6 seed=$seed --workdir "$H/runs/njs-wskp6-s$seed"
  for set in pd-test-high-stats stress-stats; do
    step "consistent-$set-njs-wskp6-s$seed" $J evaluate njs --data "$H/data/$set" \
      --replica "$H/data/$set-r1" --denoiser "$H/runs/njs-wskp6-s$seed" \
      --out "$H/runs/consistent/$set/njs-wskp6-s$seed"
  done
done
step sweep-rt-main $J sweep experiments/sweeps/rt-main.toml --workdir "$H/runs/sweeps/rt-main"
step sweep-rt-wskp3 $J sweep experiments/sweeps/rt-wskp3.toml --workdir "$H/runs/sweeps/rt-wskp3"
step mixer-wskp6-fact "${X[@]}" $J train experiments/configs/mixer-wskp6.toml \
  data.dataset="$H/data/pd-rt4k" model_config.head=f_act model_config.logit_bound=none \
  model_config.logit_eps=0.001 --workdir "$H/runs/mixer-wskp6-fact"
B="$H/runs/sweeps/pd-bases"
# The progressive-denoising paper's Tables 1 and 2 on our data (experiments/README.md): bases
# trained on PD data (U-Net x 4 feature sets, KP 5 x 5, WSKP-6) on pd-rt (2..1024 spp), one
# mixer per base on pd-rt4k (2..4096 spp), PD reports on pd-test-high. The builds record
# Frame.covariance, which the per-channel SURE of the paper drops and SURE from the colour
# covariance uses.
# One base at a time through its covariance-SURE mixer and Eq. 9 alone (the closed-form
# mixer, no network, SURE from the covariance, per-channel t; reports outside the checkout,
# read by pd_bases_tables.py), most wanted first: the U-Net on HDR + ALB + NRM + VAR, whose
# per-channel-SURE mixer ended furthest above MC at 4096 spp, the bases short of the paper's
# PD / den, Table 4 over the first, then the other bases.
step data-pd-rt $J dataset build experiments/configs/dataset-pd-rt.toml --out "$H/data/pd-rt"
closed_form() {  # closed_form BASE
  mkdir -p "$H/runs/pd-closed-form"
  .venv/bin/python -m jaxden.cli evaluate pd --data "$H/data/pd-test-high" \
    --denoiser "$B/$1" --mixer closed-form --mixer-set sure.covariance=true \
    --tstat per_channel=true --probes 1 --keep-current --out "$H/runs/pd-closed-form/$1"
}
base_steps() {  # base_steps BASE: the base, its covariance-SURE mixer, Eq. 9 alone over it
  local base=$1
  step "pd-base-$base" "${X[@]}" $J sweep experiments/sweeps/pd-bases.toml --workdir "$B" \
    --only "$base"
  step "pd-mixer-cov-$base" "${X[@]}" $J sweep experiments/sweeps/pd-mixers-cov.toml \
    --workdir "$H/runs/sweeps/pd-mixers-cov" --only "$base"
  step "pd-closed-form-$base" closed_form "$base"
}
base_steps wskp6  # Table 2's WSKP-6 row, the one the tables still lack
# PD of OIDN with SURE by jvp (OIDN-JAX, K = 1 and 4 probes) beside the finite-difference PD
# tables of the C++ OIDN (pd-oidn-test-shipped, pd-oidn-test-high-shipped): into the
# checkout's experiments/results/pd (commit them), then `python experiments/pd_oidn_sure_forms.py`.
oidnjax_pd() {  # oidnjax_pd SET PROBES NAME [--probe-dist rademacher]
  .venv/bin/python -m jaxden.cli evaluate pd --data "$H/data/$1" --denoiser oidn-jax \
    --mixer oidn-pd --probes "$2" --keep-current --out "experiments/results/pd/$3" "${@:4}"
}
step pd-oidnjax-k1-test oidnjax_pd test-chain 1 pd-oidnjax-k1-test
step pd-oidnjax-k4-test oidnjax_pd test-chain 4 pd-oidnjax-test
step pd-oidnjax-k1-test-high oidnjax_pd test-high-chain 1 pd-oidnjax-k1-test-high
step pd-oidnjax-k4-test-high oidnjax_pd test-high-chain 4 pd-oidnjax-test-high
# ... and one Rademacher probe (the signs of the same draws: no diagonal probe noise)
step pd-oidnjax-k1rad-test-high oidnjax_pd test-high-chain 1 pd-oidnjax-k1rad-test-high \
  --probe-dist rademacher
step pd-oidnjax-k1rad-test oidnjax_pd test-chain 1 pd-oidnjax-k1rad-test --probe-dist rademacher
# OIDN's own weights fine-tuned on jaxden renders (experiments/configs/finetune-oidn.toml):
# pd-rt's training crops with the held-out sets' features, then stock against fine-tuned OIDN
# on test-chain (held out) into the checkout's experiments/results/oidn (commit them).
oidn_finetune_eval() {  # oidn_finetune_eval DENOISER NAME
  $J evaluate denoise --data "$H/data/test-chain" --spp 2 4 8 16 64 --denoiser "$1" \
    --out "experiments/results/oidn/$2"
}
step data-pd-rt-chain $J dataset refeature "$H/data/pd-rt" aux=specular-chain feature_spp=1024 \
  --out "$H/data/pd-rt-chain"
step finetune-oidn "${X[@]}" $J train experiments/configs/finetune-oidn.toml \
  --workdir "$H/runs/finetune-oidn"
step oidn-finetune-stock oidn_finetune_eval oidn-jax oidn-finetune-stock
step oidn-finetune-tuned oidn_finetune_eval "$H/runs/finetune-oidn" oidn-finetune-tuned
step oidn-finetune-gain .venv/bin/python experiments/finetune_gain.py \
  --stock experiments/results/oidn/oidn-finetune-stock.json \
  --tuned experiments/results/oidn/oidn-finetune-tuned.json \
  --title "OIDN fine-tuned on jaxden renders, held-out test-chain" \
  --out experiments/results/oidn/oidn-finetune
# A mixer trained on one-probe (Rademacher) jvp SURE of OIDN in JAX (configs/mixer-oidnjax-k1.toml,
# the shipped oidn-pd recipe otherwise): its training set first (about 80 min here).
step data-default-chain $J dataset build experiments/configs/dataset-default.toml \
  name=default-chain --out "$H/data/default-chain"
step mixer-oidnjax-k1 "${X[@]}" $J train experiments/configs/mixer-oidnjax-k1.toml \
  data.dataset="$H/data/default-chain" --workdir "$H/runs/mixer-oidnjax-k1"
# ... scored as oidn-pd is shipped (swap average, range-aware closed form, per-channel t), one
# probe, on both held-out sets; then `python experiments/pd_oidn_sure_forms.py` has its rows.
k1_mixer_pd() {  # k1_mixer_pd SET NAME
  .venv/bin/python -m jaxden.cli evaluate pd --data "$H/data/$1" --denoiser oidn-jax \
    --mixer "$H/runs/mixer-oidnjax-k1" --probes 1 --swap-average \
    --mixer-set closed_form_stops=1 --tstat per_channel=true --keep-current \
    --out "experiments/results/pd/$2"
}
step pd-oidnjax-k1mixer-test k1_mixer_pd test-chain pd-oidnjax-k1mixer-test
step pd-oidnjax-k1mixer-test-high k1_mixer_pd test-high-chain pd-oidnjax-k1mixer-test-high
# Blender Cycles renders (experiments/renderers/cycles_dataset.py, Blender's bpy in
# $H/bpy-venv) imported as a dataset, WSKP-6 fine-tuned on them, stock against fine-tuned on
# the held-out views (into the checkout's experiments/results/renderers: commit them).
cycles_eval() {  # cycles_eval DENOISER NAME
  $J evaluate denoise --data "$H/data/cycles" --split test --spp 1 --denoiser "$1" \
    --out "experiments/results/renderers/$2"
}
step data-cycles-src "$H/bpy-venv/bin/python" experiments/renderers/cycles_dataset.py \
  --out "$H/cycles-src"
step data-cycles $J dataset import "$H/cycles-src" --from cycles --crop 128 --crops-per-view 4 \
  --val s06v0,s06v1 --held-out s07v0,s07v1,s08v0,s08v1 --out "$H/data/cycles" --quiet
step finetune-wskp6-cycles "${X[@]}" $J train experiments/configs/finetune-wskp6-cycles.toml \
  --workdir "$H/runs/finetune-wskp6-cycles"
step cycles-wskp6-stock cycles_eval wskp-6 cycles-wskp6-stock
step cycles-wskp6-finetuned cycles_eval "$H/runs/finetune-wskp6-cycles" cycles-wskp6-finetuned
step cycles-wskp6-stock-separate cycles_eval wskp-6:emission=separate cycles-wskp6-stock-separate
step cycles-wskp6-finetuned-separate cycles_eval "$H/runs/finetune-wskp6-cycles:emission=separate" \
  cycles-wskp6-finetuned-separate
step cycles-wskp6-gain .venv/bin/python experiments/finetune_gain.py \
  --stock experiments/results/renderers/cycles-wskp6-stock.json \
  --tuned experiments/results/renderers/cycles-wskp6-finetuned.json \
  --title "WSKP-6 fine-tuned on Blender Cycles renders, held-out views" \
  --out experiments/results/renderers/cycles-wskp6-gain
step pd-base-unet-hdr-alb-nrm-var "${X[@]}" $J sweep experiments/sweeps/pd-bases.toml \
  --workdir "$B" --only unet-hdr-alb-nrm-var
# The held-out set and the mixers' training set.
step data-pd-test-high $J dataset build experiments/configs/dataset-pd-test-high.toml \
  --out "$H/data/pd-test-high"
step data-pd-rt4k $J dataset build experiments/configs/dataset-pd-rt4k.toml --out "$H/data/pd-rt4k"
for base in unet-hdr-alb-nrm-var unet-hdr unet-hdr-var; do base_steps "$base"; done
# Table 4 (the paper's ablations, per-channel SURE as the paper) over the U-Net on HDR + ALB +
# NRM + VAR: the f_act mixer, without SURE, without f_act, and our closed_form_logit head.
for run in unet-hdr-alb-nrm-var t4-full t4-no-sure t4-no-f_act; do
  step "pd-mixer-$run" "${X[@]}" $J sweep experiments/sweeps/pd-mixers.toml \
    --workdir "$H/runs/sweeps/pd-mixers" --only "$run"
done
for base in unet-hdr-alb-nrm kp5; do base_steps "$base"; done
# The sweeps' summaries (every run is finished by now) and SURE by jvp against the true error
# of every JAX base (into the checkout's experiments/results/sure: commit it), SURE from the
# covariance and the paper's per-channel form.
step sweep-pd-bases "${X[@]}" $J sweep experiments/sweeps/pd-bases.toml --workdir "$B"
step sweep-pd-mixers-cov "${X[@]}" $J sweep experiments/sweeps/pd-mixers-cov.toml \
  --workdir "$H/runs/sweeps/pd-mixers-cov"
step sure-pd-bases .venv/bin/python -m jaxden.cli evaluate sure \
  --data "$H/data/pd-test-high" --denoiser wskp-6 --denoiser "$B/unet-hdr" \
  --denoiser "$B/unet-hdr-var" --denoiser "$B/unet-hdr-alb-nrm" \
  --denoiser "$B/unet-hdr-alb-nrm-var" --denoiser "$B/kp5" --denoiser "$B/wskp6" \
  --out experiments/results/sure/sure-pd-bases
# The paper's per-channel SURE mixers (pd-mixers.toml: Tables 1, 2 and 4).
step sweep-pd-mixers "${X[@]}" $J sweep experiments/sweeps/pd-mixers.toml \
  --workdir "$H/runs/sweeps/pd-mixers"
# Progressive denoising over the real-time WSKP-6 (`wskp-6-pd`): the mixer (jvp SURE, one
# probe, width 16) and the 1..4096-spp sequence it is measured on.
step mixer-wskp6-4k "${X[@]}" $J train \
  experiments/configs/mixer-wskp6.toml data.dataset="$H/data/pd-rt4k" --workdir "$H/runs/mixer-wskp6-4k"
step data-pd-sequence $J dataset build experiments/configs/dataset-pd-sequence.toml \
  --out "$H/data/pd-sequence"
# The real-time denoisers: data, then the sweeps, most wanted first; each resumes.
step data-rt $J dataset build experiments/configs/dataset-rt.toml --out "$H/data/rt" || exit 1
step data-rt-test $J dataset build experiments/configs/dataset-rt-test.toml --out "$H/data/rt-test" || exit 1
step data-rt-seq $J dataset sequences experiments/configs/sequences-rt-test.toml --out "$H/data/rt-seq" --quiet || exit 1
step sweep-rt-main $J sweep experiments/sweeps/rt-main.toml --workdir "$H/runs/sweeps/rt-main"
step sweep-rt-noise2noise $J sweep experiments/sweeps/rt-noise2noise.toml --workdir "$H/runs/sweeps/rt-noise2noise"
step sweep-rt-ablation $J sweep experiments/sweeps/rt-ablation.toml --workdir "$H/runs/sweeps/rt-ablation"
# The remaining real-time models (WSKP-3, KP-1, KP-2, WSKP-MR, U-Net, WSKP-6+1x1), about 3 h.
step sweep-rt-variants $J sweep experiments/sweeps/rt-variants.toml --workdir "$H/runs/sweeps/rt-variants"
# The error guard's variants on textured scenes at low spp (pd-guard-textured.md), ~2 h.
step pd-guard-textured .venv/bin/python experiments/pd_guard_textured.py --run \
  --out experiments/results/pd/pd-guard-textured
for extra in "$H"/queue.d/*.sh; do   # ad-hoc steps of this machine, outside the checkout
  [ -e "$extra" ] && source "$extra"
done
echo "queue: all done $(date -Is)"
