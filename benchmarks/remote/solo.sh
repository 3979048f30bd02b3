#!/usr/bin/env bash
# A queue of runs ALONE on the GPU, one after another (their train times are the methods' own), each scored at its
# milestones right after it trained (one evaluation process per milestone, nothing training meanwhile): the curves
# (benchmarks/curves.py) come from it. Source benchmarks/remote/env.sh first.
#
#   SOLO_DATA=".gpu-data" bash benchmarks/remote/solo.sh start "reichstag:peer:15000 reichstag:willags:30000 ..."
#   SOLO_DATA=".gpu-sb" bash benchmarks/remote/solo.sh wait $OUT 560   # copies new scenes, brings back the records
#
# A run is scene:method:steps[:seed[:budget_minutes]]: a benchmarks/methods.py method trained to `steps` with
# splatfacto's stock schedule (the learning-rate schedules do not depend on the step count, so the 15k point of a
# 30k run is a 15k run), scored at 1000, 2000, 5000, 10000, 15000 and 30000 up to `steps` (SOLO_MILESTONES: another
# list; SOLO_SCORE: only these; SOLO_VARIANTS: the last one also under other fit settings, see run_one); with
# budget_minutes under `--pipeline.time-budget-minutes`, scored where it stopped.
# The queue runs detached (setsid) from a copy of the tree in $SOLO_DIR (/tmp/solo). Scenes are copied from the folders
# in SOLO_DATA by `start` and by every `wait`; runs whose scene is missing wait at the back of the queue (up to
# SOLO_WAIT_S, 900 s); no run starts after SOLO_DEADLINE_S (1560 s), and no run of SOLO_LONG_STEPS steps or more
# (10000) after SOLO_LONG_DEADLINE_S (SOLO_DEADLINE_S): a long run that could not end inside the lease is dropped while
# shorter runs behind it still start. Records: $SOLO_DIR/rec/long-<run>.json (tag
# SOLO_TAG, default h200-curve; -s<seed> for other seeds, -knob<min> for budget runs), tarred by `wait` to
# OUT/solo-records.tgz with the logs.
#
# `queues start|add QUEUE...` runs several queues side by side (their train times are then shared-GPU times; scores
# do not depend on them), queue i on GPU i of QUEUE_GPUS (default: every GPU, round robin); `queues wait OUT SECONDS`
# packs every queue's records and logs into OUT/queues.tgz and the region maps ($WILLAGS_BENCH_REGIONS) into
# OUT/regions.tgz: the side-by-side grid of docs/results.md ("How the records were made").
set -u
S=${SOLO_DIR:-/tmp/solo}  # (tests point it elsewhere)
export SOLO_DIR=$S
copy_data() {
  mkdir -p "$S/data"
  for root in ${SOLO_DATA:-.gpu-data}; do
    for sc in "$root"/*/; do
      [ -d "$sc" ] || continue
      name=$(basename "$sc")
      [ -e "$S/data/$name/.ready" ] && continue
      rm -rf "$S/data/$name.tmp" && cp -r "$sc" "$S/data/$name.tmp" && mv "$S/data/$name.tmp" "$S/data/$name" \
        && touch "$S/data/$name/.ready" && echo "gpu_solo: scene $name ready"
    done
  done
}

milestones_for() {  # steps -> the milestones up to it (SOLO_MILESTONES: another list, e.g. "15000 30000"), and the
  local out="" m  # last step itself when no milestone lies below it
  for m in ${SOLO_MILESTONES:-1000 2000 5000 10000 15000 30000}; do [ "$m" -le "$1" ] && out="$out,$m"; done
  [ -n "$out" ] || out=",$1"
  echo "${out#,}"
}

sharing() {  # runs sharing the GPU: the queues pinned to this one (`queues`; asked when a run starts and when it is
  # recorded, so queues added meanwhile count), 1 for a queue alone
  if [ -f "$S/gpu" ]; then grep -lx "$(cat "$S/gpu")" "$(dirname "$S")"/q*/gpu 2> /dev/null | wc -l; else echo 1; fi
}

run_one() {
  local scene=$1 m=$2 steps=$3 seed=$4 bm=$5
  local name="$scene-$m-$steps-s$seed${bm:+-knob$bm}" tag=${SOLO_TAG:-h200-curve}
  [ "$seed" != 42 ] && tag="$tag-s$seed"
  [ -n "$bm" ] && tag="$tag-knob$bm"
  local d=$S/runs/$name
  local ms
  ms=$(milestones_for "$steps")
  [ -n "$bm" ] && ms=$steps  # the knob's run: scored where it stops (and at the cap, were it reached)
  echo "gpu_solo: train $name ($(date +%T))"
  python3 -m benchmarks.long_run train --method "$m" --data "$S/data/$scene" --run-dir "$d" --budget-s 100000 \
    --steps "$steps" --milestones "$ms" --seed "$seed" --concurrent "$(sharing)" ${bm:+--budget-minutes "$bm"} \
    >> "$d.log" 2>&1
  grep "long_run:\|time budget" "$d.log" | tail -n 4
  local timed
  timed=$(python3 -c "import json,sys; print(' '.join(json.load(open(sys.argv[1])).get('milestone_train_s', {})))" \
    "$d/state.json" 2>/dev/null)
  echo "gpu_solo: score $name at ${timed:-nothing} ($(date +%T))"
  for k in $timed; do
    # SOLO_SCORE: the milestones to score ("none", or a list; default: every timed one)
    [ -n "${SOLO_SCORE:-}" ] && [[ " $SOLO_SCORE " != *" $k "* ]] && continue
    python3 -m benchmarks.long_run eval --run-dir "$d" --milestones "$k" >> "$d.eval-$k.log" 2>&1 &
  done
  # SOLO_VARIANTS: "NAME:STEPS:LR[:oracle][:startK] ...", the run's last milestone scored again under each of these
  # fit settings beside the protocol's own (`long_run eval --variant`; the record carries them as protocol_variants);
  # startK: the fit starts from the best of the usual start and K training latents (--protocol-start-candidates K);
  # resmean: the modulation's local residual reads the training latents' mean (--residual-latent mean)
  local last=${timed##* } v vname vsteps vlr vflags f extra
  for v in ${SOLO_VARIANTS:-}; do
    [ -n "$last" ] || break
    IFS=: read -r vname vsteps vlr vflags <<< "$v"
    extra=()
    for f in ${vflags//:/ }; do
      case $f in
        oracle) extra+=(--oracle) ;;
        start*) extra+=(--protocol-start-candidates "${f#start}") ;;
        resmean) extra+=(--residual-latent mean) ;;
      esac
    done
    python3 -m benchmarks.long_run eval --run-dir "$d" --milestones "$last" --variant "$vname" \
      --protocol-steps "$vsteps" --protocol-lr "$vlr" ${extra[@]+"${extra[@]}"} --train-views 0 >> "$d.eval-$last-$vname.log" 2>&1 &
  done
  wait
  python3 -m benchmarks.long_run record --run-dir "$d" --tag "$tag" --concurrent "$(sharing)" --milestones all \
    --out "$S/rec/long-$name.json" > /dev/null 2>> "$d.log"
  cat "$d".eval-*.log >> "$d.log" 2>/dev/null
  grep "long_run:" "$d.log" | tail -n 8
  grep -i "Traceback\|Error" "$d.log" | tail -n 3
  cp "$d.log" "$S/rec/$name.log"
  cp "$d/state.json" "$S/rec/state-$name.json" 2>/dev/null
  echo "gpu_solo: done $name ($(date +%T))"
}

loop() {
  # a detached queue keeps none of its starter's descriptors but stdio: a lock the starter held (`flock FILE solo.sh
  # queues add ...`) would otherwise stay held as long as the queue runs, and the next `flock` would wait for it
  local fd
  for fd in /proc/self/fd/*; do
    fd=${fd##*/}
    [ "$fd" -gt 2 ] 2> /dev/null && eval "exec $fd>&-" 2> /dev/null
  done
  cd "$S/wrk" || exit 1
  export PYTHONPATH=/tmp/site:$S/wrk/.whl-gpu/stub:$S/wrk
  python3 -c "from benchmarks.grid import warm_gsplat; warm_gsplat()" || { touch "$S/done"; exit 1; }
  local t0 todo=() left=() waited=0 run scene m steps seed bm
  t0=$(cat "$S/t0")
  read -r -a todo < "$S/queue"
  while [ ${#todo[@]} -gt 0 ]; do
    if [ $(( $(date +%s) - t0 )) -gt "${SOLO_DEADLINE_S:-1560}" ]; then
      echo "gpu_solo: deadline passed; not started: ${todo[*]}"
      break
    fi
    left=()
    run=""
    for r in "${todo[@]}"; do
      IFS=: read -r scene m steps seed bm <<< "$r"
      if [ "$steps" -ge "${SOLO_LONG_STEPS:-10000}" ] \
        && [ $(( $(date +%s) - t0 )) -gt "${SOLO_LONG_DEADLINE_S:-${SOLO_DEADLINE_S:-1560}}" ]; then
        echo "gpu_solo: long-run deadline passed; not started: $r"
        continue
      fi
      if [ -z "$run" ] && [ -e "$S/data/$scene/.ready" ]; then run=$r; else left+=("$r"); fi
    done
    if [ -z "$run" ]; then
      [ "$waited" -ge "${SOLO_WAIT_S:-900}" ] && { echo "gpu_solo: no data for ${todo[*]}"; break; }
      sleep "${SOLO_POLL_S:-10}"
      waited=$((waited + ${SOLO_POLL_S:-10}))
      continue
    fi
    IFS=: read -r scene m steps seed bm <<< "$run"
    run_one "$scene" "$m" "$steps" "${seed:-42}" "${bm:-}"
    todo=("${left[@]}")
  done
  echo "gpu_solo: queue finished ($(date +%T))"
  touch "$S/done"
}

unfinished() {  # how many of the queues under $1 have not finished
  local d n=0
  for d in "$1"/q*; do [ -e "$d/done" ] || n=$((n + 1)); done
  echo "$n"
}

queue_gpus() {  # the GPUs queues are spread over: $QUEUE_GPUS, else every GPU nvidia-smi lists, else none
  if [ -n "${QUEUE_GPUS:-}" ]; then echo "$QUEUE_GPUS"; return; fi
  command -v nvidia-smi > /dev/null 2>&1 && nvidia-smi -L 2> /dev/null | awk '{print NR - 1}' | tr '\n' ' '
}

queues() {  # start RUNS... | add RUNS... | wait OUT [SECONDS]: several queues side by side
  local Q=${QUEUES_DIR:-/tmp/queues} self=${BASH_SOURCE[0]} out limit end regions i d runs gpus gpu
  case "${1:-}" in
    start | add)
      # queue i runs on GPU number i of the list, round robin (CUDA_VISIBLE_DEVICES); `add` appends queues to the
      # running ones (scenes that travel in a later call) and goes on round the list from where it stood
      [ "$1" = start ] && rm -rf "$Q"
      shift
      mkdir -p "$Q"
      read -r -a gpus <<< "$(queue_gpus)"
      i=$(find "$Q" -mindepth 1 -maxdepth 1 -name 'q*' -type d | wc -l)
      for runs in "$@"; do
        i=$((i + 1))
        gpu=""
        [ ${#gpus[@]} -gt 0 ] && gpu=${gpus[$(( (i - 1) % ${#gpus[@]} ))]}
        if [ -n "$gpu" ]; then
          CUDA_VISIBLE_DEVICES=$gpu SOLO_DIR=$Q/q$i bash "$self" start "$runs"
          echo "$gpu" > "$Q/q$i/gpu"
        else
          SOLO_DIR=$Q/q$i bash "$self" start "$runs"
        fi
      done
      ;;
    wait)
      out=$2
      limit=${3:-540}
      end=$(( $(date +%s) + limit ))
      for d in "$Q"/q*; do SOLO_DIR=$d bash "$self" wait "$Q/.copy" 0 > /dev/null; done  # new scenes
      while [ "$(date +%s)" -lt "$end" ] && [ "$(unfinished "$Q")" != 0 ]; do sleep 5; done
      mkdir -p "$out"
      regions=${WILLAGS_BENCH_REGIONS:-}
      tar czf "$out/queues.tgz" -C / $(cd / && ls -d "${Q#/}"/q*/rec "${Q#/}"/q*/queue.log)
      # the region maps apart (they are the bulk, and each file that comes back has a size limit)
      [ -n "$regions" ] && [ -d "$regions" ] && tar czf "$out/regions.tgz" -C / "${regions#/}"
      for d in "$Q"/q*; do
        echo "== $(basename "$d")$( [ -f "$d/gpu" ] && echo " (GPU $(cat "$d/gpu"))"): $(tr -d '\n' < "$d/queue" 2>/dev/null)"
        grep "gpu_solo:\|long_run:\|Traceback\|Error" "$d/queue.log" | tail -n 6
      done
      echo "gpu_queues: $(unfinished "$Q") queue(s) still running"
      ;;
    *) echo "usage: solo.sh queues start RUNS... | queues add RUNS... | queues wait OUT [SECONDS]" >&2; exit 2 ;;
  esac
}

case "${1:-}" in
  queues)
    shift
    queues "$@"
    ;;
  start)
    rm -rf "$S" && mkdir -p "$S/wrk/.whl-gpu" "$S/rec" "$S/runs"
    cp -r benchmarks willags_ns configs pyproject.toml "$S/wrk/"
    [ -d .gpu-peer ] && cp -r .gpu-peer "$S/wrk/"
    [ -d .whl-gpu/stub ] && cp -r .whl-gpu/stub "$S/wrk/.whl-gpu/"
    date +%s > "$S/t0"
    echo "$2" > "$S/queue"
    copy_data
    setsid nohup bash "$S/wrk/benchmarks/remote/solo.sh" _loop > "$S/queue.log" 2>&1 < /dev/null &
    echo "gpu_solo: queue started: $2"
    ;;
  _loop) loop ;;
  wait)
    out=$2
    limit=${3:-560}
    copy_data
    end=$(( $(date +%s) + limit ))
    while [ "$(date +%s)" -lt "$end" ] && [ ! -e "$S/done" ]; do sleep "${SOLO_POLL_S:-5}"; done
    mkdir -p "$out"
    tar czf "$out/solo-records.tgz" -C "$S" rec queue.log
    grep "gpu_solo:\|long_run:\|time budget\|Traceback\|Error" "$S/queue.log" | tail -n 60
    [ -e "$S/done" ] && echo "gpu_solo: all done" || echo "gpu_solo: still running"
    ;;
  *) echo "usage: solo.sh start QUEUE | wait OUT [SECONDS] | queues start|add QUEUE... | queues wait OUT [SECONDS]" >&2; exit 2 ;;
esac
