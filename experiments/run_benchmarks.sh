#!/usr/bin/env bash
# Runs every benchmark (or those named) and stores each one's JSON result, with the machine it
# ran on, in experiments/results/bench-NAME.json (bench-NAME$BENCH_SUFFIX.json when BENCH_SUFFIX
# is set, e.g. -h100 on a GPU machine). Run on an otherwise idle machine:
#   experiments/run_benchmarks.sh [render decoder denoisers sharding sure progressive]
# Without Mitsuba (a GPU machine), JAXDEN_BENCH_FRAME=FRAME.exr gives the benchmarks their frame
# (see jaxden.bench.bench_frame); it is recorded in the command.
set -euo pipefail
cd "$(dirname "$0")/.."
jaxden=${JAXDEN:-.venv/bin/jaxden}
suffix=${BENCH_SUFFIX:-}
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(render decoder denoisers sharding sure progressive)
mkdir -p experiments/results
for name in "${names[@]}"; do
  echo "== jaxden bench $name --json"
  log=$(mktemp)
  "$jaxden" bench "$name" --json | tee "$log"
  python3 - "$name" "$log" "$suffix" <<'PY'
import json, os, platform, subprocess, sys, datetime
name, log, suffix = sys.argv[1], sys.argv[2], sys.argv[3]
result = json.loads(open(log).read().strip().splitlines()[-1])
commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
result["_provenance"] = {
    "command": (f"JAXDEN_BENCH_FRAME={os.environ['JAXDEN_BENCH_FRAME']} "
                if os.environ.get("JAXDEN_BENCH_FRAME") else "") + f"jaxden bench {name} --json",
    "commit": commit,
    "date": datetime.date.today().isoformat(),
    "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
    "load_average_1min_after": os.getloadavg()[0],
}
with open(f"experiments/results/bench-{name}{suffix}.json", "w") as handle:
    json.dump(result, handle, indent=2, sort_keys=True)
    handle.write("\n")
PY
  rm -f "$log"
done
