#!/usr/bin/env bash
# The GPU figures in one command: the demo, the compile and stage profiles, and the cue, scale, video,
# shadow and solver benchmarks on the accelerator (JAX_PLATFORMS=cuda,cpu; Embree stays on the CPU),
# and the same on this machine's CPU platform (JAX_PLATFORMS=cpu), written side by side to OUT/gpu.json.
#
#   bash benchmarks/run_gpu.sh [OUT] [--quick]        (default OUT: out/gpu)
#
# Steps run in order of importance, each under its own time limit, and none starts after
# RUN_GPU_BUDGET_S seconds (default 480): the demo cold and warm, bench_compile and profile_stages
# on both platforms, then the benchmarks (bench_scale on RUN_GPU_SCALE_GRIDS, default its two
# smaller grids, and on the CPU platform on RUN_GPU_SCALE_CPU_GRIDS, default 32x64; without the
# layout study). RUN_GPU_STEPS=name,... runs only those steps. A step cut by its limit is reported
# with rc 124, and a study that saves as it goes (bench_scale) keeps what it finished.
# Each platform has a private compilation cache under OUT (so the first demo is the cold one, as a
# new user's), and no process preallocates the GPU's memory (XLA_PYTHON_CLIENT_PREALLOCATE=false:
# the benchmarks that start processes share the card).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/gpu}
QUICK=${2:-}
PY=${PYTHON:-python3}
BUDGET=${RUN_GPU_BUDGET_S:-480}
STEPS=${RUN_GPU_STEPS:-}
mkdir -p "$OUT"
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
START=$(date +%s)

step() {  # step PLATFORM NAME LIMIT_S COMMAND...: seconds and exit status into OUT/PLATFORM/NAME/status.json
  local platform=$1 name=$2 limit=$3
  shift 3
  if [[ -n "$STEPS" && ",$STEPS," != *",$name,"* ]]; then
    return
  fi
  local left=$(( BUDGET - ($(date +%s) - START) ))
  if (( left < 20 )); then
    echo "$platform $name: skipped (the budget of $BUDGET s is spent)"
    return
  fi
  (( limit > left )) && limit=$left
  local dir="$OUT/$platform/$name"
  mkdir -p "$dir"
  local t0=$(date +%s%N)
  JAX_PLATFORMS=$platform HIDDENJAX_CACHE="$OUT/$platform/cache" timeout "$limit" "$@" --out "$dir" $QUICK \
    >"$dir/log.txt" 2>&1
  local rc=$?
  echo "{\"seconds\": $(( ($(date +%s%N) - t0) / 1000000 ))e-3, \"rc\": $rc, \"limit\": $limit}" >"$dir/status.json"
  echo "$platform $name: rc $rc in $(( ($(date +%s%N) - t0) / 1000000000 )) s; $(tail -1 "$dir/log.txt")"
}

CASES=solve,solve_many,leverage,uncertainty
for platform in cuda,cpu cpu; do
  step "$platform" demo 120 "$PY" -m hiddenjax.cli demo
  step "$platform" demo_warm 90 "$PY" -m hiddenjax.cli demo
  step "$platform" bench_compile 150 "$PY" benchmarks/bench_compile.py --cases "$CASES"
  step "$platform" profile_stages 90 "$PY" benchmarks/profile_stages.py
done
for platform in cuda,cpu cpu; do
  step "$platform" bench_cues 90 "$PY" benchmarks/bench_cues.py
  step "$platform" bench_video 60 "$PY" benchmarks/bench_video.py
done
step cuda,cpu bench_scale "${RUN_GPU_SCALE_LIMIT_S:-120}" "$PY" benchmarks/bench_scale.py \
  --grids "${RUN_GPU_SCALE_GRIDS:-32x64,64x128}" --skip "${RUN_GPU_SCALE_SKIP:-layouts}"
step cpu bench_scale "${RUN_GPU_SCALE_LIMIT_S:-120}" "$PY" benchmarks/bench_scale.py \
  --grids "${RUN_GPU_SCALE_CPU_GRIDS:-32x64}" --skip "${RUN_GPU_SCALE_SKIP:-layouts}"
for platform in cuda,cpu cpu; do
  step "$platform" bench_shadows 90 "$PY" benchmarks/bench_shadows.py --quick
  step "$platform" bench_solvers 120 "$PY" benchmarks/bench_solvers.py
done

"$PY" - "$OUT" <<'EOF'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
table = {}
for platform in ("cuda,cpu", "cpu"):
    for d in sorted((out / platform).glob("*/")):
        if not (d / "status.json").exists():
            continue
        entry = json.loads((d / "status.json").read_text())
        results = d / "results.json"
        entry["results"] = json.loads(results.read_text()) if results.exists() else None
        table.setdefault(d.name, {})[platform] = entry
(out / "gpu.json").write_text(json.dumps(table, indent=1))
nan = float("nan")
for name, runs in table.items():
    gpu, cpu = runs.get("cuda,cpu", {}), runs.get("cpu", {})
    ratio = cpu.get("seconds", nan) / gpu["seconds"] if gpu.get("seconds") else nan
    print(f"{name:16s} gpu {gpu.get('seconds', nan):7.1f} s (rc {gpu.get('rc')})  "
          f"cpu {cpu.get('seconds', nan):7.1f} s (rc {cpu.get('rc')})  cpu/gpu {ratio:.2f}")
    for platform, entry in runs.items():
        seconds = (entry.get("results") or {}).get("seconds")
        if seconds:
            print(f"    {platform:9s} stages {seconds}")
print(f"wrote {out}/gpu.json")
EOF
