#!/usr/bin/env bash
# Several benchmarks/remote/solo.sh queues side by side on one GPU: the runs of a queue one after another, the queues
# at the same time (their train times are shared-GPU times; scores do not depend on them). For grids too long to run
# one at a time, e.g. every method of a scene trained to 15k for the region table. Source benchmarks/remote/env.sh.
#
#   export WILLAGS_BENCH_REGIONS=/tmp/regions SOLO_MILESTONES="5000 10000 15000" SOLO_DATA=".gpu-r .gpu-lib"
#   bash benchmarks/remote/queues.sh start "reichstag:peer-full:15000" "reichstag:willags:15000 liberty:willags:15000"
#   bash benchmarks/remote/queues.sh wait $OUT 540   # again until done; each call copies scenes that arrived since
#
# `wait OUT SECONDS` gives every queue the scenes in SOLO_DATA, returns once every queue is done or after SECONDS,
# and packs every queue's records and logs and the region maps ($WILLAGS_BENCH_REGIONS) into OUT/queues.tgz.
set -u
Q=${QUEUES_DIR:-/tmp/queues}
case "${1:-}" in
  start)
    shift
    rm -rf "$Q" && mkdir -p "$Q"
    i=0
    for runs in "$@"; do
      i=$((i + 1))
      SOLO_DIR=$Q/q$i bash benchmarks/remote/solo.sh start "$runs"
    done
    ;;
  wait)
    out=$2
    limit=${3:-540}
    end=$(( $(date +%s) + limit ))
    for d in "$Q"/q*; do SOLO_DIR=$d bash benchmarks/remote/solo.sh wait "$Q/.copy" 0 > /dev/null; done  # new scenes
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
  *) echo "usage: remote/queues.sh start RUNS... | wait OUT [SECONDS]" >&2; exit 2 ;;
esac
