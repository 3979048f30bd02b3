#!/usr/bin/env bash
# Several benchmarks/gpu_solo.sh queues side by side on one GPU: the runs of a queue one after another, the queues at
# the same time (their train times are shared-GPU times; scores do not depend on them). For grids too long to run
# alone in one machine's lease, e.g. every method of a scene trained to 15k for the region table.
#
#   export WILLAGS_COMMIT=<sha>; source benchmarks/gpu_env.sh
#   export WILLAGS_BENCH_REGIONS=/tmp/regions SOLO_MILESTONES="5000 10000 15000" SOLO_DATA=".gpu-r .gpu-lib"
#   bash benchmarks/gpu_queues.sh start "reichstag:peer-full:15000" "reichstag:willags:15000 liberty:willags:15000"
#   bash benchmarks/gpu_queues.sh wait $OUT 540   # this call and each later one (carrying scenes that come later)
#
# `wait OUT SECONDS` gives every queue the scenes carried by this call (SOLO_DATA), returns once every queue is done
# or after SECONDS, and packs every queue's records and logs and the region maps ($WILLAGS_BENCH_REGIONS) into
# OUT/queues.tgz: one file, whatever the number of queues.
set -u
Q=${QUEUES_DIR:-/tmp/queues}
case "${1:-}" in
  start)
    shift
    rm -rf "$Q" && mkdir -p "$Q"
    i=0
    for runs in "$@"; do
      i=$((i + 1))
      SOLO_DIR=$Q/q$i bash benchmarks/gpu_solo.sh start "$runs"
    done
    ;;
  wait)
    out=$2
    limit=${3:-540}
    end=$(( $(date +%s) + limit ))
    for d in "$Q"/q*; do SOLO_DIR=$d bash benchmarks/gpu_solo.sh wait "$Q/.copy" 0 > /dev/null; done  # new scenes
    while [ "$(date +%s)" -lt "$end" ]; do
      left=0
      for d in "$Q"/q*; do [ -e "$d/done" ] || left=$((left + 1)); done
      [ "$left" = 0 ] && break
      sleep 5
    done
    mkdir -p "$out"
    regions=${WILLAGS_BENCH_REGIONS:-}
    tar czf "$out/queues.tgz" -C / $(cd / && ls -d "${Q#/}"/q*/rec "${Q#/}"/q*/queue.log) \
      $( [ -n "$regions" ] && [ -d "$regions" ] && echo "${regions#/}")
    for d in "$Q"/q*; do
      echo "== $(basename "$d"): $(tr -d '\n' < "$d/queue" 2>/dev/null)"
      grep "gpu_solo:\|long_run:\|Traceback\|Error" "$d/queue.log" | tail -n 6
    done
    left=0
    for d in "$Q"/q*; do [ -e "$d/done" ] || left=$((left + 1)); done
    echo "gpu_queues: $left queue(s) still running"
    ;;
  *) echo "usage: gpu_queues.sh start RUNS... | wait OUT [SECONDS]" >&2; exit 2 ;;
esac
