#!/usr/bin/env bash
# A cross-validated lease on the GPU machine: every fold of the carried bundles (`python -m benchmarks cv bundle`) as
# a queue of its own, all side by side (solo.sh queues, one per GPU round robin, under CUDA MPS). Run from the
# repository root there, one bundle per call (a call carries 64 MiB with the tree and the wheels):
#
#   export CV_METHOD=willags-prior-low-field CV_STEPS=15000 SOLO_TAG=h200x2-cv19 WILLAGS_COMMIT=<sha>
#   bash benchmarks/remote/cv_lease.sh start .gpu-x4b      # first call: the wheels, gsplat, MPS, the bundle's folds
#   bash benchmarks/remote/cv_lease.sh add .gpu-x4a        # each later call: one more bundle's folds
#   bash benchmarks/remote/cv_lease.sh wait "$OUT" 560     # as often as the runs need: records in $OUT/queues.tgz
#   bash benchmarks/remote/cv_lease.sh runs .gpu-x4a       # the runs a bundle gives, one queue a line (here too)
#
# CV_METHOD (willags; several, space-separated: each fold once per method, e.g. "willags peer peer-full"), CV_STEPS
# (15000), CV_SEED (42): the runs; CV_FOLDS: only these fold folders of the bundles (names, space- or
# newline-separated: `python -m benchmarks cv missing --method M` lists those a method still lacks); CV_EXTRA: more
# queues after the folds' (each a solo.sh queue, e.g. "fox-clean:willags:5000:42"), whose scenes travel in any
# bundle; SOLO_DATA (/tmp/cvdata): where every call copies its bundles' scenes; SOLO_MILESTONES ("5000 15000"). A
# queue that runs a peer needs its source in .gpu-peer (benchmarks/peer.py), carried in the first call. The first
# call brings back gsplat's build as $OUT/gsplat_cuda.so.gz when it made one (keep it as .gpu-cache/gsplat_cuda.so.gz:
# the next machine loads it in seconds). CV_DRY_RUN=1: print what would start, start nothing (no set-up either).
set -u
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
export SOLO_DATA=${SOLO_DATA:-/tmp/cvdata} SOLO_MILESTONES=${SOLO_MILESTONES:-5000 15000}

runs() {  # BUNDLE... -> one run a line: every fold folder (<scene>-cv<k>of<K>) of each bundle, once per CV_METHOD
  # the methods' order turns by one at each fold: queues go round the GPUs in order, so with as many methods as GPUs
  # (or a multiple) each method would otherwise land on the same GPU every time, its slowest all on one
  local b d n found j=0 k
  local -a methods
  read -r -a methods <<< "${CV_METHOD:-willags}"
  for b in "$@"; do
    found=0
    for d in "$b"/*-cv*of*/; do
      [ -d "$d" ] || continue  # no fold folder: the pattern itself, not a scene
      n=$(basename "$d")
      if [ -n "${CV_FOLDS:-}" ] && ! grep -qxF "$n" <<< "$(tr ' ' '\n' <<< "$CV_FOLDS")"; then
        found=1
        continue
      fi
      for ((k = 0; k < ${#methods[@]}; k++)); do
        echo "$n:${methods[$(((j + k) % ${#methods[@]}))]}:${CV_STEPS:-15000}:${CV_SEED:-42}"
      done
      j=$((j + 1))
      found=1
    done
    [ $found = 1 ] || echo "cv_lease: $b holds no fold folder (its scenes travel for CV_EXTRA's runs only)" >&2
  done
}

start_or_add() {  # start|add BUNDLE...
  local verb=$1 q=() r
  shift
  while IFS= read -r r; do q+=("$r"); done < <(runs "$@")
  if [ "$verb" = start ]; then
    for r in ${CV_EXTRA:-}; do q+=("$r"); done
  fi
  [ ${#q[@]} -gt 0 ] || [ "$verb" = add ] || { echo "cv_lease: no run to start" >&2; return 2; }
  if [ "${CV_DRY_RUN:-0}" = 1 ]; then
    if [ ${#q[@]} -gt 0 ]; then printf 'solo.sh queues %s' "$verb"; printf ' "%s"' "${q[@]}"; echo
    else echo "copy only: $*"; fi
    return 0
  fi
  if [ "$verb" = start ]; then
    source "$here/env.sh" || return 1
    [ -f /tmp/tex/gsplat_cuda/gsplat_cuda.so ] && [ -n "${OUT:-}" ] \
      && gzip -c /tmp/tex/gsplat_cuda/gsplat_cuda.so > "$OUT/gsplat_cuda.so.gz"
    command -v nvidia-cuda-mps-control > /dev/null && nvidia-cuda-mps-control -d && echo "cv_lease: MPS on"
  else
    GPU_ENV_REUSE=1 source "$here/env.sh" || return 1
  fi
  mkdir -p "$SOLO_DATA"
  for b in "$@"; do cp -r "$b"/. "$SOLO_DATA"/; done
  # a bundle without folds (scenes for CV_EXTRA's runs): copied, and the running queues take it at the next wait
  [ ${#q[@]} -gt 0 ] || { echo "cv_lease: scenes of $* copied; no run added"; return 0; }
  bash "$here/solo.sh" queues "$verb" "${q[@]}"
}

case "${1:-}" in
  runs) shift; runs "$@" ;;
  start | add) start_or_add "$@" ;;
  wait)
    GPU_ENV_REUSE=1 source "$here/env.sh" || exit 1
    bash "$here/solo.sh" queues wait "${2:?cv_lease.sh wait OUT [SECONDS]}" "${3:-560}"
    ;;
  *) echo "usage: cv_lease.sh start BUNDLE... | add BUNDLE... | wait OUT [SECONDS] | runs BUNDLE..." >&2; exit 2 ;;
esac
