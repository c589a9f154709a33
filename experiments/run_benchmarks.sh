#!/usr/bin/env bash
# Runs every benchmark (or those named) and stores each one's JSON result, with the machine it
# ran on, in experiments/results/bench/bench-NAME.json (bench-NAME$BENCH_SUFFIX.json when
# BENCH_SUFFIX is set, e.g. -h100 on a GPU machine). Run on an otherwise idle machine:
#   experiments/run_benchmarks.sh [render decoder denoisers sharding sure progressive frames
#                                  frames-denoisers]
# "frames" is `jaxden bench progressive --size 1280x720,1920x1080,3840x2160,7680x4320 --quick`:
# whole frames, each command in its own process, stored as bench-frames-progressive.json;
# "frames-denoisers" the same for `jaxden bench denoisers` (bench-frames-denoisers.json).
# Without Mitsuba (a GPU machine), JAXDEN_BENCH_FRAME=FRAME.exr gives the benchmarks their frame
# (see jaxden.bench.bench_frame); it is recorded in the command.
set -euo pipefail
cd "$(dirname "$0")/.."
jaxden=${JAXDEN:-.venv/bin/jaxden}
python=${PYTHON:-.venv/bin/python}
suffix=${BENCH_SUFFIX:-}
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(render decoder denoisers sharding sure progressive)
mkdir -p experiments/results/bench
for name in "${names[@]}"; do
  args=("$name")
  sizes=1280x720,1920x1080,3840x2160,7680x4320
  if [ "$name" = frames ]; then
    args=(progressive --size "$sizes" --quick)
    name=frames-progressive
  elif [ "$name" = frames-denoisers ]; then
    args=(denoisers --size "$sizes" --quick)
  fi
  echo "== jaxden bench ${args[*]} --json"
  log=$(mktemp)
  "$jaxden" bench "${args[@]}" --json | tee "$log"
  "$python" - "$name" "$log" "$suffix" "${args[*]}" <<'PY'
import json, os, sys
from jaxden.provenance import git_commit, machine, today
name, log, suffix, args = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]
result = json.loads(open(log).read().strip().splitlines()[-1])
result["_provenance"] = {
    "command": (f"JAXDEN_BENCH_FRAME={os.environ['JAXDEN_BENCH_FRAME']} "
                if os.environ.get("JAXDEN_BENCH_FRAME") else "") + f"jaxden bench {args} --json",
    "commit": git_commit(dirty=False),
    "date": today(),
    "machine": machine(),
    "load_average_1min_after": os.getloadavg()[0],
}
with open(f"experiments/results/bench/bench-{name}{suffix}.json", "w") as handle:
    json.dump(result, handle, indent=2, sort_keys=True)
    handle.write("\n")
PY
  rm -f "$log"
done
