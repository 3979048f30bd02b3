#!/usr/bin/env bash
# willags on 1, 2 and 4 GPUs at equal images seen, each rank's step profiled (docs/distributed.md).
# benchmarks/multi_gpu.py does the work (its docstring says what each run is and what comes back); this sets up the
# machine (benchmarks/remote/env.sh: the wheels, gsplat's cached build) and starts the deadline's clock.
#
#   export WILLAGS_COMMIT=<git rev-parse --short HEAD>
#   bash benchmarks/remote/multi_gpu.sh .gpu-r/reichstag $OUT                          # 4 GPUs: runs 4,1,2,4:reference
#   RUNS=2,1,2:reference bash benchmarks/remote/multi_gpu.sh .gpu-r/reichstag $OUT     # 2 GPUs
#   RUNS=4@30000,2x2@2000 bash benchmarks/remote/multi_gpu.sh .gpu-r/reichstag $OUT    # 30k images on 4 GPUs; 2 machines x 2
#
# Environment: IMAGES (images seen per run, default 8000), RUNS, METHOD (willags), SEED (42), TAG (multi-gpu),
# WORK (its scratch folder, /tmp/willags-multi-gpu), DEADLINE_S (555: everything, the set-up included, ends before
# then and the results are under $OUT), SETUP=0 (the wheels are already installed), DRY_RUN=1 (print the runs, their
# steps, schedules and estimated times only), DEVICE=cpu (a smoke test of the script on a CPU: RUNS=1 only,
# nerfstudio's launcher needs CUDA for more).
# $OUT receives multi_gpu.tgz, multi_gpu_records.json, multi_gpu_summary.txt and multi_gpu.log.
set -uo pipefail
export MULTI_GPU_T0=${MULTI_GPU_T0:-$(date +%s.%N)}
DATA=${1:?usage: remote/multi_gpu.sh DATA OUT}
OUT=${2:?usage: remote/multi_gpu.sh DATA OUT}
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 PYTHONUNBUFFERED=1
mkdir -p "$OUT"
if [ "${SETUP:-1}" = 1 ] && [ "${DEVICE:-cuda}" = cuda ] && [ "${DRY_RUN:-0}" != 1 ]; then
  # shellcheck disable=SC1091
  source benchmarks/remote/env.sh > "$OUT/multi_gpu.log" 2>&1 || { cat "$OUT/multi_gpu.log"; exit 1; }
fi
args=(--data "$DATA" --out "$OUT" --images "${IMAGES:-8000}" --runs "${RUNS:-4,1,2,4:reference}"
  --method "${METHOD:-willags}" --seed "${SEED:-42}" --tag "${TAG:-multi-gpu}" --device-type "${DEVICE:-cuda}"
  --deadline-s "${DEADLINE_S:-555}" --work "${WORK:-/tmp/willags-multi-gpu}")
[ "${DRY_RUN:-0}" = 1 ] && args+=(--dry-run)
[ "${DEVICE:-cuda}" = cpu ] && args+=(--eval-gpus 1)
python3 -m benchmarks.multi_gpu run "${args[@]}" 2>&1 | tee -a "$OUT/multi_gpu.log"
