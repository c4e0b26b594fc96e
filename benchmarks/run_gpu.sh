#!/usr/bin/env bash
# The GPU figures in one command: the demo and the compile, solver, cue, video, scale and shadow
# benchmarks on the accelerator (JAX_PLATFORMS=cuda,cpu; Embree stays on the CPU), then the same on
# this machine's CPU platform, written side by side to OUT/gpu.json (default out/gpu).
#
#   bash benchmarks/run_gpu.sh [OUT] [--quick]
#
# Each script runs in its own process with a private compilation cache under OUT (so the first
# run of each is the cold one, as a new user's), and never preallocates the GPU's memory
# (XLA_PYTHON_CLIENT_PREALLOCATE=false: the benchmarks that start processes share the card).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/gpu}
QUICK=${2:-}
PY=${PYTHON:-python3}
mkdir -p "$OUT"
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1

run() {  # run PLATFORM NAME COMMAND...: seconds and exit status into OUT/PLATFORM/NAME.status
  local platform=$1 name=$2
  shift 2
  local dir="$OUT/$platform/$name"
  mkdir -p "$dir"
  local t0=$(date +%s%N)
  JAX_PLATFORMS=$platform HIDDENJAX_CACHE="$OUT/$platform/cache" "$@" --out "$dir" $QUICK >"$dir/log.txt" 2>&1
  local rc=$?
  echo "{\"seconds\": $(( ($(date +%s%N) - t0) / 1000000 ))e-3, \"rc\": $rc}" >"$dir/status.json"
  echo "$platform $name: rc $rc, $(tail -1 "$dir/log.txt")"
}

for platform in cuda,cpu cpu; do
  run "$platform" demo "$PY" -m hiddenjax.cli demo
  run "$platform" bench_compile "$PY" benchmarks/bench_compile.py
  for bench in bench_solvers bench_cues bench_video bench_scale bench_shadows; do
    run "$platform" "$bench" "$PY" "benchmarks/$bench.py"
  done
done

"$PY" - "$OUT" <<'EOF'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
table = {}
for platform in ("cuda,cpu", "cpu"):
    for d in sorted((out / platform).glob("*/")):
        if d.name == "cache":
            continue
        entry = json.loads((d / "status.json").read_text())
        results = d / "results.json"
        entry["results"] = json.loads(results.read_text()) if results.exists() else None
        table.setdefault(d.name, {})[platform] = entry
(out / "gpu.json").write_text(json.dumps(table, indent=1))
for name, runs in table.items():
    gpu, cpu = runs.get("cuda,cpu", {}), runs.get("cpu", {})
    ratio = cpu.get("seconds", 0) / gpu["seconds"] if gpu.get("seconds") else float("nan")
    print(f"{name:16s} gpu {gpu.get('seconds', float('nan')):7.1f} s (rc {gpu.get('rc')})  "
          f"cpu {cpu.get('seconds', float('nan')):7.1f} s (rc {cpu.get('rc')})  cpu/gpu {ratio:.2f}")
print(f"wrote {out}/gpu.json")
EOF
