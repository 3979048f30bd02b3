#!/usr/bin/env bash
# benchmarks/remote/grid.sh detached: the pairs of a grid share one GPU (at most $JOBS at once) and outlive the
# shell that started them, so `wait` can be called again until a long grid finishes. Source benchmarks/remote/env.sh.
#
#   SHARED_DATA=".gpu-lib .gpu-r" GRID=configs/benchmark_gpu_fidelity.json JOBS=12 \
#     bash benchmarks/remote/shared.sh start "liberty:peer:h200-l1:42 liberty:willags:h200-l1:42 ..."
#   bash benchmarks/remote/shared.sh wait $OUT 540      # again until done: each brings back what finished
#
# `start` copies the tree to /tmp/shared/wrk (a later copy of the tree changes nothing under a running run) and the
# scenes of the folders in SHARED_DATA to its .gpu-data, then runs grid.sh there under setsid.
# `wait OUT SECONDS` returns once every pair finished or after SECONDS, and tars the records, the logs and the
# pictures (WILLAGS_BENCH_RENDERS) to OUT/shared-records.tgz.
set -u
S=${SHARED_DIR:-/tmp/shared}
case "${1:-}" in
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
    setsid nohup bash -c "bash benchmarks/remote/grid.sh $S/out $2; touch $S/done" > "$S/grid.log" 2>&1 < /dev/null &
    echo "gpu_shared: started $(echo "$2" | wc -w) pairs"
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
    ls "$S/out" | grep -c '\.json$' | sed 's/^/gpu_shared: records so far: /'
    tail -c 3000 "$S/out/logs.txt"
    [ -e "$S/done" ] && echo "gpu_shared: all done" || echo "gpu_shared: still running"
    ;;
  *) echo "usage: remote/shared.sh start PAIRS | wait OUT [SECONDS]" >&2; exit 2 ;;
esac
