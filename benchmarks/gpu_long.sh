#!/usr/bin/env bash
# One device call's share of the 30k-step runs (benchmarks/long_run.py), optionally beside grid pairs.
# Source benchmarks/gpu_env.sh first. Run state lives in /tmp/long on the device machine: it survives between
# back-to-back calls on the same machine (given back ~30 s after a call), not a new machine.
#   LONG_BUDGET_S=400 LONG_METHODS="willags splatfacto" bash benchmarks/gpu_long.sh OUT [scene:method[:tag[:seed]] ...]
set -u
final=$1; shift
out=/tmp/long-call-out
rm -rf "$out"
budget=${LONG_BUDGET_S:-400}
methods=${LONG_METHODS:-"willags splatfacto"}
data=${LONG_DATA:-.gpu-data/reichstag}
tag=${LONG_TAG:-h100-30k}
mkdir -p "$out" /tmp/long
python3 -c "from benchmarks.harness import _warm_gsplat; _warm_gsplat()" || exit 1
n=$(( $(echo $methods | wc -w) + $# ))
for m in $methods; do
  ( python3 -m benchmarks.long_run train --method "$m" --data "$data" --run-dir "/tmp/long/$m" --budget-s "$budget" \
      >> "/tmp/long/$m.log" 2>&1
    python3 -m benchmarks.long_run eval --run-dir "/tmp/long/$m" >> "/tmp/long/$m.log" 2>&1 ) &
done
[ $# -gt 0 ] && { GRID=${GRID:-configs/benchmark_gpu_fidelity.json} JOBS=${JOBS:-8} bash benchmarks/gpu_scenes.sh "$out/grid" "$@" > "$out/grid.log" 2>&1 & }
wait
for m in $methods; do
  python3 -m benchmarks.long_run record --run-dir "/tmp/long/$m" --tag "$tag" --concurrent "$n" --out "$out/long-$m.json"
  grep "long_run:" "/tmp/long/$m.log" | tail -n 5
done
tail -c 3000 "$out/grid.log" 2>/dev/null
for m in $methods; do cp "/tmp/long/$m/state.json" "$out/state-$m.json"; done
mkdir -p "$final" && tar czf "$final/results.tgz" -C "$out" . && ls -R "$out" | head -30
