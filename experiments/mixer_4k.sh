#!/usr/bin/env bash
# A mixer for OIDN trained on inputs up to 4096 spp, and its PD reports on the held-out sets.
# Every step is resumable: rerun the script after an interruption and it carries on where it
# stopped (finished dataset items, SURE-cache entries and training checkpoints are kept).
#
#   experiments/mixer_4k.sh            # ~6 h on the 2-core project CPU, most of it the build
#
# 1. data/default-4k: dataset-default.toml (48 crops of 24 scenes) at 2..4096 spp with
#    16384-spp references. Rendered with the legacy features (first hit, 16 samples) because
#    the build began before the feature change; step 2 replaces them, and the result equals a
#    build with the new features (tests/test_dataset.py, refeature).
# 2. data/default-4k-chain: the same colour with specular-chain features at min(spp, 1024).
# 3. runs/mixer-oidn-4k-chain: experiments/configs/mixer-oidn.toml on it (SURE cache, 3200 steps).
# 4. PD reports of that mixer on data/test-chain and data/test-high-chain (swap averaging on),
#    to compare with experiments/results/pd-oidn{,-high}-chain.md (the mixer trained to 1024 spp).
set -euo pipefail
cd "$(dirname "$0")/.."
jaxden=${JAXDEN:-.venv/bin/jaxden}
python=${PYTHON:-.venv/bin/python}
"$jaxden" dataset build experiments/configs/dataset-default.toml --out data/default-4k \
  'spp=[2,4,8,16,32,64,128,256,512,1024,2048,4096]' reference_spp=16384 \
  aux=first-hit feature_spp=16
"$jaxden" dataset refeature data/default-4k aux=specular-chain feature_spp=1024 \
  name=default-4k-chain --out data/default-4k-chain
XLA_FLAGS=--xla_force_host_platform_device_count=2 "$jaxden" train \
  experiments/configs/mixer-oidn.toml data.dataset=data/default-4k-chain \
  --workdir runs/mixer-oidn-4k-chain
"$python" experiments/pd_report.py pd --data data/test-high-chain --denoiser oidn \
  --mixer runs/mixer-oidn-4k-chain --swap-average --out experiments/results/pd-oidn-high-chain-4k
"$python" experiments/pd_report.py pd --data data/test-chain --denoiser oidn \
  --mixer runs/mixer-oidn-4k-chain --swap-average --out experiments/results/pd-oidn-chain-4k
