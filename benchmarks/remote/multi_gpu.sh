#!/usr/bin/env bash
# willags on 1, 2 and 4 GPUs (and 2 "machines" x 2 GPUs, and under a time budget), each rank's step profiled
# (docs/distributed.md). benchmarks/multi_gpu.py does the work (its docstring says what each run is and what comes
# back); this sets up the machine (benchmarks/remote/env.sh: the wheels, gsplat's cached build), starts the deadline's
# clock and runs it detached, so that a run outlives the call that started it.
#
#   export WILLAGS_COMMIT=<git rev-parse --short HEAD>          # a copy of the tree without .git cannot name it
#   bash benchmarks/remote/multi_gpu.sh start --data .gpu-cv1/reichstag --runs 4@30000 --gpus 0,1,2,3
#   bash benchmarks/remote/multi_gpu.sh wait $OUT 540           # waits up to 540 s, then copies the results to $OUT
#   MULTI_GPU_DIR=/tmp/multi_gpu_b GPU_ENV_REUSE=1 bash benchmarks/remote/multi_gpu.sh start ... --gpus 2
#                                                               # a second one beside it, on other GPUs
#   bash benchmarks/remote/multi_gpu.sh run DATA OUT            # in the foreground (RUNS, IMAGES, ... below)
#
# start ARGS...: the arguments of `python -m benchmarks multi-gpu run` (--data, --runs, --images, --gpus, --seed,
# --tag, ...); --out, --work and --deadline-s are set here. Sources env.sh first (in the foreground: minutes at most),
# then starts the runs detached (setsid) with their logs under $MULTI_GPU_DIR (default /tmp/multi_gpu; one folder
# per concurrent invocation; GPU_ENV_REUSE=1 for the second, whose env.sh must not reinstall under the first's runs).
# SETUP=0: env.sh already sourced. DEADLINE_S (default 1500): nothing starts that would not end that many seconds after `start`.
# wait OUT [SECONDS]: waits until the runs end or SECONDS (default 540) pass, then copies into OUT
# multi_gpu_records.json, multi_gpu_summary.txt, multi_gpu.tgz (logs, step profiles, configs, evaluations) and
# multi_gpu.log (the script's output), and says whether it is done; call it again while it still runs.
# run DATA OUT: the runs in the foreground; environment IMAGES (8000), RUNS (4,1,2,4:reference), GPUS, METHOD
# (willags), SEED (42), TAG (multi-gpu), WORK, DEADLINE_S (555), SETUP=0 (env.sh already sourced), DRY_RUN=1.
# Every process started here has NVLink multicast off (NCCL_NVLS_ENABLE=0 and the two others below).
set -uo pipefail
D=${MULTI_GPU_DIR:-/tmp/multi_gpu}
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 PYTHONUNBUFFERED=1

setup() {  # env.sh's wheels, gsplat build and entry points; its output into $1
  # shellcheck disable=SC1091
  source benchmarks/remote/env.sh > "$1" 2>&1 || { cat "$1"; echo "multi_gpu: env.sh failed" >&2; exit 1; }
}

case "${1:-}" in
  start)
    shift
    if [ -e "$D/pid" ] && kill -0 "$(cat "$D/pid")" 2> /dev/null; then
      echo "multi_gpu: $D still has runs going (pid $(cat "$D/pid")): wait for them or use another MULTI_GPU_DIR" >&2
      exit 1
    fi
    rm -rf "$D" && mkdir -p "$D/out"
    export MULTI_GPU_T0
    MULTI_GPU_T0=$(date +%s.%N)
    if [ "${SETUP:-1}" = 1 ]; then setup "$D/env.log" && cat "$D/env.log"; fi
    setsid nohup bash -c 'python3 -m benchmarks multi-gpu run "$@" --out "$0/out" --work "$0/work" \
      --deadline-s "${DEADLINE_S:-1500}"; echo $? > "$0/rc"' "$D" "$@" > "$D/multi_gpu.log" 2>&1 < /dev/null &
    echo $! > "$D/pid"
    echo "multi_gpu: started (pid $(cat "$D/pid"), logs $D/multi_gpu.log): $*"
    ;;
  wait)
    out=${2:?usage: multi_gpu.sh wait OUT [SECONDS]}
    end=$(( $(date +%s) + ${3:-540} ))
    while [ "$(date +%s)" -lt "$end" ] && [ ! -e "$D/rc" ]; do sleep 5; done
    mkdir -p "$out"
    cp "$D"/out/* "$out"/ 2> /dev/null
    cp "$D/multi_gpu.log" "$out/" 2> /dev/null
    grep "multi_gpu:\|Traceback\|Error" "$D/multi_gpu.log" | tail -n 30
    [ -f "$D/out/multi_gpu_summary.txt" ] && cat "$D/out/multi_gpu_summary.txt"
    if [ -e "$D/rc" ]; then echo "multi_gpu: done (exit $(cat "$D/rc"))"; else echo "multi_gpu: still running"; fi
    ;;
  run)
    DATA=${2:?usage: multi_gpu.sh run DATA OUT}
    OUT=${3:?usage: multi_gpu.sh run DATA OUT}
    export MULTI_GPU_T0=${MULTI_GPU_T0:-$(date +%s.%N)}
    mkdir -p "$OUT"
    [ "${SETUP:-1}" = 1 ] && [ "${DRY_RUN:-0}" != 1 ] && setup "$OUT/multi_gpu.log"
    args=(--data "$DATA" --out "$OUT" --images "${IMAGES:-8000}" --runs "${RUNS:-4,1,2,4:reference}"
      --method "${METHOD:-willags}" --seed "${SEED:-42}" --tag "${TAG:-multi-gpu}"
      --deadline-s "${DEADLINE_S:-555}" --work "${WORK:-/tmp/willags-multi-gpu}")
    [ -n "${GPUS:-}" ] && args+=(--gpus "$GPUS")
    [ "${DRY_RUN:-0}" = 1 ] && args+=(--dry-run)
    python3 -m benchmarks multi-gpu run "${args[@]}" 2>&1 | tee -a "$OUT/multi_gpu.log"
    ;;
  *) echo "usage: multi_gpu.sh start ARGS... | wait OUT [SECONDS] | run DATA OUT" >&2; exit 2 ;;
esac
