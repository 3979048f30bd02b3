#!/usr/bin/env bash
# willags on reichstag, 1 GPU vs N GPUs, for the same number of training images seen (issue 16, docs/distributed.md).
#
# With N devices one step trains on N images, so the N-device run gets STEPS / N steps and every schedule counted in
# steps is divided by N (densification warm-up / interval / stop, the resolution and SH schedules, the mask warm-up
# and ramp, the learning-rate decays and warm-ups); the EMA teacher's per-step decay becomes tau^N (the same horizon
# in images). The 1-device run gets the method's own values (dividing by 1). Each run is then scored by `ns-eval`
# (the NeRF-W protocol: latent fitted on the left half of each test image, right half scored).
# Prints one row per device count: steps, ns-train wall time (start-up, image caching and the final checkpoint
# included), protocol PSNR, SSIM and the number of Gaussians.
#
#   DATA=../shared/data/reichstag STEPS=5000 GPUS="1 2" bash benchmarks/multi_gpu.sh
#
# Needs max(GPUS) CUDA GPUs and ns-train / ns-eval of this package on PATH (on a lent GPU machine: `source
# benchmarks/gpu_env.sh` first). DRY_RUN=1 prints the commands only. DEVICE=cpu GPUS=1 is a smoke test of the script
# on a CPU (nerfstudio 1.1.5's launcher needs CUDA for more than one device). Not run yet: no machine with several
# GPUs was available when it was written.
set -euo pipefail

DATA=${DATA:-../shared/data/reichstag}
STEPS=${STEPS:-5000}     # steps of the 1-device run
GPUS=${GPUS:-"1 2"}
METHOD=${METHOD:-willags}
SEED=${SEED:-42}
DEVICE=${DEVICE:-cuda}
OUT=${OUT:-/tmp/willags-multi-gpu}
PYTHON=${PYTHON:-python3}
NS_TRAIN=${NS_TRAIN:-ns-train}
NS_EVAL=${NS_EVAL:-ns-eval}
DRY_RUN=${DRY_RUN:-0}
EXTRA=${EXTRA:-}         # more ns-train arguments, the same for every run

# `--flag value` pairs of the method's step-counted schedules divided by $2 (read from the registered method config)
scaled_flags() {
  "$PYTHON" - "$1" "$2" <<'PY'
import sys

from nerfstudio.plugins.registry import discover_methods

method, n = sys.argv[1], int(sys.argv[2])
config = discover_methods()[0][method]
m = config.pipeline.model


def div(steps: int) -> int:
    return max(1, round(steps / n)) if steps > 0 else steps


flags = {
    "pipeline.model.warmup-length": div(m.warmup_length),
    "pipeline.model.refine-every": div(m.refine_every),
    "pipeline.model.stop-split-at": div(m.stop_split_at),
    "pipeline.model.stop-screen-size-at": div(m.stop_screen_size_at),
    "pipeline.model.resolution-schedule": div(m.resolution_schedule),
    "pipeline.model.sh-degree-interval": div(m.sh_degree_interval),
}
if getattr(m, "appearance", "sh") == "willags" and m.mask.enabled:
    flags["pipeline.model.mask.warmup-steps"] = div(m.mask.warmup_steps)
    flags["pipeline.model.mask.ramp-steps"] = div(m.mask.ramp_steps)
    flags["pipeline.model.mask.teacher.tau"] = repr(m.mask.teacher.tau**n)
for group, settings in config.optimizers.items():
    scheduler = settings.get("scheduler")
    name = group.replace("_", "-")
    if scheduler is not None and hasattr(scheduler, "max_steps"):
        flags[f"optimizers.{name}.scheduler.max-steps"] = div(scheduler.max_steps)
        if getattr(scheduler, "warmup_steps", 0):
            flags[f"optimizers.{name}.scheduler.warmup-steps"] = div(scheduler.warmup_steps)
print(" ".join(f"--{k} {v}" for k, v in flags.items()))
PY
}

mkdir -p "$OUT"
rows=()
for n in $GPUS; do
  if [ $((STEPS % n)) -ne 0 ]; then
    echo "multi_gpu.sh: STEPS=$STEPS is not a multiple of $n: the runs would not see the same number of images" >&2
    exit 2
  fi
  steps=$((STEPS / n))
  name="$(basename "$DATA")-$METHOD-gpus$n"
  # shellcheck disable=SC2207  # the flags are single words
  schedule=($(scaled_flags "$METHOD" "$n"))
  # shellcheck disable=SC2206  # EXTRA is split on purpose
  train=("$NS_TRAIN" "$METHOD" --data "$DATA" --machine.num-devices "$n" --machine.device-type "$DEVICE"
    --machine.seed "$SEED" --max-num-iterations "$steps" --steps-per-save "$steps" --vis tensorboard
    --viewer.quit-on-train-completion True --output-dir "$OUT" --experiment-name "$name" --timestamp run
    "${schedule[@]}" $EXTRA)
  run_dir="$OUT/$name/$METHOD/run"
  evaluate=("$NS_EVAL" --load-config "$run_dir/config.yml" --output-path "$OUT/$name-eval.json")
  if [ "$DRY_RUN" = 1 ]; then
    printf '%q ' "${train[@]}"; echo
    printf '%q ' "${evaluate[@]}"; echo
    continue
  fi
  start=$(date +%s.%N)
  "${train[@]}" > "$OUT/$name-train.log" 2>&1 || { echo "ns-train failed: $OUT/$name-train.log" >&2; tail -n 30 "$OUT/$name-train.log" >&2; exit 1; }
  end=$(date +%s.%N)
  "${evaluate[@]}" > "$OUT/$name-eval.log" 2>&1 || { echo "ns-eval failed: $OUT/$name-eval.log" >&2; tail -n 30 "$OUT/$name-eval.log" >&2; exit 1; }
  rows+=("$("$PYTHON" - "$n" "$steps" "$start" "$end" "$OUT/$name-eval.json" "$run_dir" <<'PY'
import json
import sys
from pathlib import Path

import torch

n, steps, start, end, eval_json, run_dir = sys.argv[1:]
results = json.loads(Path(eval_json).read_text())["results"]
ckpt = sorted(Path(run_dir, "nerfstudio_models").glob("step-*.ckpt"))[-1]
state = torch.load(ckpt, map_location="cpu", weights_only=False)["pipeline"]
gaussians = state["_model.gauss_params.means"].shape[0]
wall = float(end) - float(start)
print(f"{n:>4} {steps:>7} {wall:>9.1f} {results['psnr']:>8.2f} {results['ssim']:>7.4f} {gaussians:>10}")
PY
)")
done
if [ "$DRY_RUN" != 1 ]; then
  echo "scene $(basename "$DATA"), method $METHOD, $STEPS images seen per device count, seed $SEED"
  echo "gpus   steps  wall [s]     PSNR    SSIM  Gaussians"
  printf '%s\n' "${rows[@]}"
fi
