#!/usr/bin/env bash
# Run configs/benchmark_gpu_scenes.json on one GPU with one harness process per (scene, method) pair, all at
# once (the runs are mostly launch/Python-bound at ~100k Gaussians, so they share a large GPU well; train times
# are then shared-GPU times). Records: OUT/<scene>-<method>.json; the tail of each log: OUT/logs.txt.
#   bash benchmarks/gpu_scenes.sh OUT scene:method [scene:method ...]
set -u
out=$1; shift
mkdir -p "$out" /tmp/willags-gpu-logs
python3 -c "from willags_ns.eval.harness import _warm_gsplat; _warm_gsplat()" || exit 1
for pair in "$@"; do
  scene=${pair%%:*}; method=${pair##*:}
  python3 benchmarks/run_benchmark.py --grid configs/benchmark_gpu_scenes.json --scenes "$scene" --methods "$method" \
    --out "/tmp/willags-gpu-logs/$scene-$method" --work-dir "/tmp/willags-gpu-work/$scene-$method" \
    > "/tmp/willags-gpu-logs/$scene-$method.log" 2>&1 &
done
wait
cp /tmp/willags-gpu-logs/*.json "$out"/ 2>/dev/null
for f in /tmp/willags-gpu-logs/*.log; do echo "== $f"; tail -n 6 "$f"; done > "$out/logs.txt"
cat "$out/logs.txt"
