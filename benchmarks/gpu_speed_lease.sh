#!/usr/bin/env bash
# The speed and several-GPU records of one nvidia-h100-x4 lease, in two back-to-back device calls (docs/gpu_notes.md,
# docs/distributed.md). Every training run is alone on its GPU(s); the host's other GPUs run other jobs meanwhile, so
# the four GPUs are busy at once. willags and splatfacto of a ratio are on the same machine.
#
#   export WILLAGS_COMMIT=<sha>
#   bash benchmarks/gpu_speed_lease.sh one $OUT    # carry .whl-gpu .gpu-cache .gpu-r .gpu-lib .gpu-sc
#   bash benchmarks/gpu_speed_lease.sh two $OUT    # right after, same machine; carry .whl-gpu .gpu-cache .gpu-sb
#
# Call one:
#   GPU 0: willags on 1 GPU, 30000 images (multi_gpu 1@30000: the several-GPU runs' reference, 30k steps alone);
#   GPU 1: the solo queue (benchmarks/gpu_solo.sh) of reichstag and sacre-coeur-mini / south-building's splatfacto;
#   GPUs 2-3: willags on 2 GPUs, 30000 images (multi_gpu 2@30000); then GPU 2: liberty's willags, south-building's
#   willags; GPU 3: liberty's splatfacto, then benchmarks/gpu_suite.py --step --render at 1M Gaussians;
#   GPU 0, after its run: sacre-coeur-mini's willags.
# Call two: brings south-building, waits for everything above, then willags on 4 GPUs, 30000 images (multi_gpu
#   4@30000), then two "machines" of 2 GPUs (2x2@2000: nerfstudio's several-machine flags, two launches), and tars
#   the records into $OUT (lease.tgz, and mg-<run>.tgz: each multi_gpu.sh's archive).
# Solo runs train 15000 steps with splatfacto's stock schedule and are scored at 15000 only (SOLO_MILESTONES).
set -u
phase=${1:?usage: gpu_speed_lease.sh one|two OUT}
OUT=${2:?usage: gpu_speed_lease.sh one|two OUT}
L=/tmp/lease
mkdir -p "$OUT" "$L"
[ "$phase" = two ] && export GPU_ENV_REUSE=1  # call one's runs are still going on
# shellcheck disable=SC1091
source benchmarks/gpu_env.sh > "$OUT/env-$phase.log" 2>&1 || { cat "$OUT/env-$phase.log"; exit 1; }
export SOLO_MILESTONES="15000 30000" SOLO_TAG=h100x4-speed SOLO_DEADLINE_S=1500 SETUP=0 TAG=multi-gpu-lease
R=$L/data/reichstag

multi() {  # GPUS RUNS NAME: benchmarks/multi_gpu.sh on those GPUs, its own work folder and results folder
  CUDA_VISIBLE_DEVICES=$1 RUNS=$2 IMAGES=30000 DEADLINE_S=${DEADLINE:-590} MULTI_GPU_T0=$(date +%s.%N) \
    WORK=$L/work-$3 bash benchmarks/multi_gpu.sh "$R" "$L/mg-$3" > "$L/mg-$3.out" 2>&1
}
solo() {  # GPU QUEUE: a detached solo queue on that GPU (its scenes from $L/data, which outlives the call)
  CUDA_VISIBLE_DEVICES=$1 SOLO_DIR=$L/solo$1 SOLO_DATA="$L/data" \
    bash benchmarks/gpu_solo.sh start "$2" > "$L/solo$1.start.log" 2>&1
}
pack() {
  for g in 0 1 2 3; do [ -d "$L/solo$g/rec" ] && tar czf "$L/solo$g-records.tgz" -C "$L/solo$g" rec queue.log; done
  tar czf "$OUT/lease.tgz" -C "$L" --exclude=data --exclude='work-*' --exclude='solo?' --exclude=multi_gpu.tgz . \
    2>/dev/null
  for d in "$L"/mg-*/; do [ -f "$d/multi_gpu.tgz" ] && cp "$d/multi_gpu.tgz" "$OUT/$(basename "$d").tgz"; done
  grep -h "gpu_solo: \(done\|train\)\|long_run: milestone" "$L"/solo?/queue.log 2>/dev/null | tail -n 40
  tail -n 25 "$L"/mg-*/multi_gpu_summary.txt 2>/dev/null
}

case "$phase" in
  one)
    mkdir -p "$L/data" && cp -r .gpu-r/reichstag .gpu-lib/liberty .gpu-sc/sacre-coeur-mini "$L/data/"
    solo 1 "reichstag:willags:15000 reichstag:splatfacto:15000 sacre-coeur-mini:splatfacto:15000 south-building:splatfacto:15000"
    setsid nohup bash -c "$(declare -f multi solo); L=$L R=$R; multi 0 1@30000 1; solo 0 sacre-coeur-mini:willags:15000" \
      > "$L/gpu0.log" 2>&1 < /dev/null &
    setsid nohup bash -c "$(declare -f multi solo); L=$L R=$R; multi 2,3 2@30000 2; \
      solo 2 'liberty:willags:15000 south-building:willags:15000'; \
      solo 3 'liberty:splatfacto:15000'; \
      while [ ! -e $L/solo3/done ]; do sleep 5; done; \
      CUDA_VISIBLE_DEVICES=3 python3 benchmarks/gpu_suite.py --step --render --n-gaussians 1000000 --size 800 \
        --variants splatfacto,willags-3dgs,willags --kernel-variants willags,splatfacto --time-budget 400 \
        --json-out $L/gpu_suite.json > $L/gpu_suite.log 2>&1; touch $L/suite.done" \
      > "$L/gpu23.log" 2>&1 < /dev/null &
    sleep $(( ${WAIT_S:-555} - SECONDS ))
    pack
    ;;
  two)
    mkdir -p "$L/data" && cp -r .gpu-sb/south-building "$L/data/"
    for g in 1 2; do  # the running queues take the scene that came with this call
      SOLO_DIR=$L/solo$g SOLO_DATA="$L/data" bash benchmarks/gpu_solo.sh wait "$L/w$g" 0 > /dev/null 2>&1
    done
    until [ -e "$L/suite.done" ] && [ -e "$L/solo0/done" ] && [ -e "$L/solo1/done" ] && [ -e "$L/solo2/done" ]; do
      sleep 5
      [ "$SECONDS" -gt "${WAIT_S:-300}" ] && { echo "lease: still running after $SECONDS s"; break; }
    done
    [ "$SECONDS" -le "${WAIT_S:-300}" ] && DEADLINE=$((575 - SECONDS)) multi 0,1,2,3 4@30000,2x2@2000 4
    pack
    ;;
esac
