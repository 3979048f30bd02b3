#!/usr/bin/env bash
# (scene, method[, tag, seed]) pairs of a grid (configs/benchmark_gpu_*.json) on one GPU, one `python -m benchmarks
# run` per pair, at most $JOBS at once (train times are then shared-GPU times: each record's concurrent_runs says how
# many at most). Source benchmarks/remote/env.sh first.
#
#   GRID=configs/benchmark_gpu_fidelity.json JOBS=12 bash benchmarks/remote/grid.sh run OUT scene:method[:tag[:seed]] ...
#   SHARED_DATA=".gpu-lib .gpu-r" GRID=... bash benchmarks/remote/grid.sh start "liberty:peer:h200-l1:42 ..."
#   bash benchmarks/remote/grid.sh wait $OUT 540      # again until done: each brings back what finished
#
# `run` runs them in the foreground (records: OUT/<scene>-<method>-<tag>.json, log tails: OUT/logs.txt); `start`
# detached (setsid) from a copy of the tree and of the SHARED_DATA scenes in $SHARED_DIR/wrk (/tmp/shared); `wait`
# returns once every pair finished or after SECONDS and tars the records, logs and pictures to OUT/shared-records.tgz.
set -u
run_grid() {  # OUT PAIRS...
  local out=$1; shift
  grid=${GRID:-configs/benchmark_gpu_scenes.json}
  jobs_max=${JOBS:-12}
  logs=/tmp/willags-gpu-logs
  mkdir -p "$out" "$logs"
  # Each pair's record and work directory are named scene-method-tag: two pairs with the same name (seeds of one
  # tag) would share a work directory and leave one record. Repeats take their own tags (h100-r8, h100-r8b, ...).
  names=$(for pair in "$@"; do IFS=: read -r scene method tag seed <<< "$pair"; echo "$scene-$method${tag:+-$tag}"; done)
  dups=$(echo "$names" | sort | uniq -d)
  [ -n "$dups" ] && { echo "gpu_grid: pairs share a record name (give each repeat its own tag): $dups" >&2; exit 2; }
  python3 -c "from benchmarks.grid import warm_gsplat; warm_gsplat()" || exit 1
  at_once=$(( $# < jobs_max ? $# : jobs_max ))
  for pair in "$@"; do
    IFS=: read -r scene method tag seed <<< "$pair"
    name="$scene-$method${tag:+-$tag}"
    extra=()
    [ -n "${tag:-}" ] && extra+=(--tag "$tag")
    [ -n "${seed:-}" ] && extra+=(--seed "$seed")
    while [ "$(jobs -rp | wc -l)" -ge "$jobs_max" ]; do sleep 2; done
    python3 -m benchmarks run --grid "$grid" --scenes "$scene" --methods "$method" "${extra[@]}" \
      --concurrent "$at_once" --out "$logs/$name" --work-dir "/tmp/willags-gpu-work/$name" > "$logs/$name.log" 2>&1 &
  done
  wait
  cp "$logs"/*.json "$out"/ 2>/dev/null
  for f in "$logs"/*.log; do echo "== $f"; tail -n 4 "$f"; done > "$out/logs.txt"
  tail -c 6000 "$out/logs.txt"
}

S=${SHARED_DIR:-/tmp/shared}
case "${1:-}" in
  run)
    shift
    run_grid "$@"
    ;;
  start)
    rm -rf "$S" && mkdir -p "$S/wrk/.whl-gpu" "$S/wrk/.gpu-data" "$S/out" "$S/renders"
    cp -r benchmarks willags_ns configs pyproject.toml "$S/wrk/"
    [ -d .gpu-peer ] && cp -r .gpu-peer "$S/wrk/"
    [ -d .whl-gpu/stub ] && cp -r .whl-gpu/stub "$S/wrk/.whl-gpu/"
    for root in ${SHARED_DATA:-.gpu-data}; do
      for sc in "$root"/*/; do [ -d "$sc" ] && cp -r "$sc" "$S/wrk/.gpu-data/"; done
    done
    cd "$S/wrk" || exit 1
    export PYTHONPATH=/tmp/site:$S/wrk/.whl-gpu/stub:$S/wrk WILLAGS_BENCH_RENDERS=$S/renders
    setsid nohup bash -c "bash benchmarks/remote/grid.sh run $S/out $2; touch $S/done" > "$S/grid.log" 2>&1 < /dev/null &
    echo "gpu_grid: started $(echo "$2" | wc -w) pairs"
    ;;
  wait)
    out=$2
    limit=${3:-540}
    end=$(( $(date +%s) + limit ))
    while [ "$(date +%s)" -lt "$end" ] && [ ! -e "$S/done" ]; do sleep 5; done
    mkdir -p "$out" "$S/out"
    cp /tmp/willags-gpu-logs/*.json "$S/out/" 2>/dev/null
    for f in /tmp/willags-gpu-logs/*.log; do echo "== $f"; tail -n 3 "$f"; done > "$S/out/logs.txt" 2>/dev/null
    tar czf "$out/shared-records.tgz" -C "$S" out renders grid.log
    ls "$S/out" | grep -c '\.json$' | sed 's/^/gpu_grid: records so far: /'
    tail -c 3000 "$S/out/logs.txt"
    [ -e "$S/done" ] && echo "gpu_grid: all done" || echo "gpu_grid: still running"
    ;;
  *) echo "usage: grid.sh run OUT PAIRS... | start PAIRS | wait OUT [SECONDS]" >&2; exit 2 ;;
esac
