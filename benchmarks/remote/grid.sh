#!/usr/bin/env bash
# Run (scene, method[, tag, seed]) pairs of a grid on one GPU, one harness process per pair, at most $JOBS at once
# (the runs are mostly launch/Python-bound at ~100k-300k Gaussians, so they share a large GPU well; train times
# are then shared-GPU times). Records: OUT/<scene>-<method>-<tag>.json; the tail of each log: OUT/logs.txt.
#   GRID=configs/benchmark_gpu_fidelity.json JOBS=12 bash benchmarks/remote/grid.sh OUT scene:method[:tag[:seed]] ...
set -u
out=$1; shift
grid=${GRID:-configs/benchmark_gpu_scenes.json}
jobs_max=${JOBS:-12}
logs=/tmp/willags-gpu-logs
mkdir -p "$out" "$logs"
# Each pair's record and work directory are named scene-method-tag: two pairs with the same name (seeds of one
# tag) would share a work directory and leave one record. Repeats take their own tags (h100-r8, h100-r8b, ...).
names=$(for pair in "$@"; do IFS=: read -r scene method tag seed <<< "$pair"; echo "$scene-$method${tag:+-$tag}"; done)
dups=$(echo "$names" | sort | uniq -d)
[ -n "$dups" ] && { echo "gpu_scenes: pairs share a record name (give each repeat its own tag): $dups" >&2; exit 2; }
python3 -c "from benchmarks.harness import _warm_gsplat; _warm_gsplat()" || exit 1
for pair in "$@"; do
  IFS=: read -r scene method tag seed <<< "$pair"
  name="$scene-$method${tag:+-$tag}"
  extra=()
  [ -n "${tag:-}" ] && extra+=(--tag "$tag")
  [ -n "${seed:-}" ] && extra+=(--seed "$seed")
  while [ "$(jobs -rp | wc -l)" -ge "$jobs_max" ]; do sleep 2; done
  python3 -m benchmarks run --grid "$grid" --scenes "$scene" --methods "$method" "${extra[@]}" \
    --out "$logs/$name" --work-dir "/tmp/willags-gpu-work/$name" > "$logs/$name.log" 2>&1 &
done
wait
cp "$logs"/*.json "$out"/ 2>/dev/null
for f in "$logs"/*.log; do echo "== $f"; tail -n 4 "$f"; done > "$out/logs.txt"
tail -c 6000 "$out/logs.txt"
