#!/usr/bin/env bash
# Long runs in checkpointed segments (benchmarks/long_run.py), each call training up to LONG_BUDGET_S seconds and
# the next call resuming them, optionally beside grid pairs (benchmarks/remote/grid.sh). Source
# benchmarks/remote/env.sh first. Run state lives in /tmp/long: it survives between calls on one machine.
#   LONG_BUDGET_S=400 LONG_METHODS="willags splatfacto" bash benchmarks/remote/long.sh OUT [scene:method[:tag[:seed]] ...]
#   LONG_RUNS="fox-clean:peer sacre-coeur-mini:willags" LONG_STEPS=15000 LONG_MILESTONES=15000 LONG_TAG=h100-15k \
#     LONG_BUDGET_S=450 bash benchmarks/remote/long.sh OUT           # several scenes; scenes from $LONG_DATA_ROOT
# LONG_SEED (default 42): the runs' seed; a repeat takes its own seed and its own LONG_TAG (h100-15k-s43), since
# records of one (scene, method, steps, tag) replace each other when merged.
set -u
final=$1; shift
out=/tmp/long-call-out
rm -rf "$out"
budget=${LONG_BUDGET_S:-400}
steps=${LONG_STEPS:-30000}
milestones=${LONG_MILESTONES:-7000,15000,30000}
root=${LONG_DATA_ROOT:-.gpu-data}
tag=${LONG_TAG:-h100-30k}
seed=${LONG_SEED:-42}
if [ -z "${LONG_RUNS:-}" ]; then  # the 30k-step form: methods on one scene
  data=${LONG_DATA:-$root/reichstag}
  LONG_RUNS=""
  for m in ${LONG_METHODS:-willags splatfacto}; do LONG_RUNS="$LONG_RUNS $(basename "$data"):$m"; done
fi
mkdir -p "$out" /tmp/long
python3 -c "from benchmarks.harness import _warm_gsplat; _warm_gsplat()" || exit 1
n=$(( $(echo $LONG_RUNS | wc -w) + $# ))
for run in $LONG_RUNS; do
  IFS=: read -r scene m <<< "$run"
  d=/tmp/long/$scene-$m-s$seed
  ( python3 -m benchmarks.long_run train --method "$m" --data "$root/$scene" --run-dir "$d" --budget-s "$budget" \
      --steps "$steps" --milestones "$milestones" --seed "$seed" --concurrent "$n" >> "$d.log" 2>&1
    python3 -m benchmarks.long_run eval --run-dir "$d" --milestones "$milestones" >> "$d.log" 2>&1 ) &
done
[ $# -gt 0 ] && { GRID=${GRID:-configs/benchmark_gpu_fidelity.json} JOBS=${JOBS:-8} bash benchmarks/remote/grid.sh run "$out/grid" "$@" > "$out/grid.log" 2>&1 & }
wait
for run in $LONG_RUNS; do
  IFS=: read -r scene m <<< "$run"
  d=/tmp/long/$scene-$m-s$seed
  python3 -m benchmarks.long_run record --run-dir "$d" --tag "$tag" --concurrent "$n" --milestones "$milestones" \
    --out "$out/long-$scene-$m.json"
  grep "long_run:" "$d.log" | tail -n 5
  tail -n 3 "$d.log" | grep -i "error\|Traceback" && tail -n 30 "$d.log"
  cp "$d/state.json" "$out/state-$scene-$m.json" 2>/dev/null
done
tail -c 3000 "$out/grid.log" 2>/dev/null
mkdir -p "$final" && tar czf "$final/results.tgz" -C "$out" . && ls -R "$out" | head -40
