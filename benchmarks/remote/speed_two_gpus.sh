#!/usr/bin/env bash
# The speed and several-GPU records of one machine with two GPUs, in three calls on that machine (docs/distributed.md).
# Every training run is alone on its GPU(s); willags and splatfacto of a ratio run on the same machine.
#
#   bash benchmarks/remote/speed_two_gpus.sh one $OUT    # needs .whl-gpu .gpu-cache and the scenes .gpu-r .gpu-lib .gpu-sc
#   bash benchmarks/remote/speed_two_gpus.sh two $OUT    # then: adds south-building (.gpu-sb) to the running queues
#   bash benchmarks/remote/speed_two_gpus.sh three $OUT  # then: waits and packs the rest
#
# GPU 0: willags on reichstag to 30000 steps (timed at 15000 and 30000, scored at 30000: the 1-GPU reference of
#   the several-GPU run), liberty's splatfacto, south-building's willags, then the speed suite (--step --render
#   at 1M Gaussians: splatfacto, willags);
# GPU 1: reichstag's splatfacto, sacre-coeur-mini's willags and splatfacto, liberty's willags, south-building's
#   splatfacto;
# then both: willags on 2 GPUs, 30000 images (benchmarks/remote/multi_gpu.sh, RUNS=2@30000, scored by ns-eval).
# The runs are benchmarks/remote/solo.sh queues (stock schedule, timed at their milestones); only the 30000-step
# run is scored (SOLO_SCORE). Everything comes back in OUT/speed.tgz (and OUT/mg.tgz).
set -u
phase=${1:?usage: remote/speed_two_gpus.sh one|two|three OUT}
OUT=${2:?usage: remote/speed_two_gpus.sh one|two|three OUT}
L=/tmp/speed2
mkdir -p "$OUT" "$L"
[ "$phase" != one ] && export GPU_ENV_REUSE=1  # the runs of call one are still going on
# shellcheck disable=SC1091
source benchmarks/remote/env.sh > "$OUT/env-$phase.log" 2>&1 || { cat "$OUT/env-$phase.log"; exit 1; }
export SOLO_MILESTONES="15000 30000" SOLO_SCORE=30000 SOLO_TAG=h100x2-speed SOLO_DEADLINE_S=1500

solo() {  # GPU QUEUE: a detached solo queue on that GPU (its scenes from $L/data, which outlives the call)
  CUDA_VISIBLE_DEVICES=$1 SOLO_DIR=$L/solo$1 SOLO_DATA="$L/data" \
    bash benchmarks/remote/solo.sh start "$2" > "$L/solo$1.start.log" 2>&1
}
sync_solo() {  # each queue takes the scenes now in $L/data and tars its records so far into $L/w<GPU>
  for g in 0 1; do
    [ -d "$L/solo$g" ] && SOLO_DIR=$L/solo$g SOLO_DATA="$L/data" bash benchmarks/remote/solo.sh wait "$L/w$g" 0 > /dev/null 2>&1
  done
}
pack() {
  sync_solo
  tar czf "$OUT/speed.tgz" -C "$L" --exclude=data --exclude='work*' --exclude='solo?' --exclude=multi_gpu.tgz . \
    2>/dev/null
  [ -f "$L/mg/multi_gpu.tgz" ] && cp "$L/mg/multi_gpu.tgz" "$OUT/mg.tgz"
  grep -h "gpu_solo: \(done\|train\|queue\)\|long_run: \(milestone\|train\)" "$L"/solo?/queue.log 2>/dev/null | tail -n 40
  tail -n 30 "$L/mg/multi_gpu_summary.txt" 2>/dev/null
  tail -n 14 "$L/gpu_suite.log" 2>/dev/null
}
until_done() {  # FILE SECONDS: wait for FILE, at most until SECONDS after this call's start
  while [ ! -e "$1" ] && [ "$SECONDS" -lt "$2" ]; do sleep 5; done
}

case "$phase" in
  one)
    mkdir -p "$L/data" && cp -r .gpu-r/reichstag .gpu-lib/liberty .gpu-sc/sacre-coeur-mini "$L/data/"
    solo 0 "reichstag:willags:30000 liberty:splatfacto:15000 south-building:willags:15000"
    solo 1 "reichstag:splatfacto:15000 sacre-coeur-mini:willags:15000 sacre-coeur-mini:splatfacto:15000 \
liberty:willags:15000 south-building:splatfacto:15000"
    setsid nohup bash -c "while [ ! -e $L/solo0/done ]; do sleep 5; done; \
      CUDA_VISIBLE_DEVICES=0 python3 -m benchmarks speed --step --render --n-gaussians 1000000 --size 800 \
        --variants splatfacto,willags --time-budget 300 --json-out $L/gpu_suite.json > $L/gpu_suite.log 2>&1; \
      while [ ! -e $L/solo1/done ]; do sleep 5; done; \
      CUDA_VISIBLE_DEVICES=0,1 SETUP=0 RUNS=2@30000 DEADLINE_S=560 TAG=multi-gpu-lease WORK=$L/work \
        MULTI_GPU_T0=\$(date +%s.%N) bash benchmarks/remote/multi_gpu.sh $L/data/reichstag $L/mg > $L/mg.out 2>&1; \
      touch $L/all.done" > "$L/after.log" 2>&1 < /dev/null &
    sleep $(( ${WAIT_S:-560} - SECONDS ))
    ;;
  two)
    mkdir -p "$L/data" && cp -r .gpu-sb/south-building "$L/data/"
    sync_solo  # the running queues take the scene that came with this call
    until_done "$L/all.done" "${WAIT_S:-565}"
    ;;
  three)
    until_done "$L/all.done" "${WAIT_S:-565}"
    ;;
esac
pack
nvidia-smi --query-gpu=index,name,utilization.gpu,memory.used --format=csv
[ -e "$L/all.done" ] && echo "speed_two_gpus: all done" || echo "speed_two_gpus: still running"
