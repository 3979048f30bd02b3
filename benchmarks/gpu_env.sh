#!/usr/bin/env bash
# Source on the lent GPU machine, from the repository root (carry .whl-gpu, the scenes in .gpu-data and, when you
# have it, .gpu-cache):   source benchmarks/gpu_env.sh && GRID=... bash benchmarks/gpu_scenes.sh OUT pairs...
# - installs the wheels of ../shared/gpu/prepare_wheels.sh into /tmp/site;
# - gsplat 1.4.0 JIT-compiles its CUDA code on every fresh machine (~3.5 min). With .gpu-cache/gsplat_cuda.so.gz
#   (the .so a previous machine of the same image built: copy /tmp/tex/gsplat_cuda/gsplat_cuda.so, gzipped, to
#   $OUT once) it loads that build instead, through benchmarks/gsplat_csrc_shim.py (~6 s);
# - exports PYTHONPATH, MAX_JOBS, TORCH_EXTENSIONS_DIR=/tmp/tex (where a JIT build lands).
# The machine's copy of the tree does not carry this checkout's git HEAD: start the command with
# `export WILLAGS_COMMIT=<git rev-parse --short HEAD, run here>` so the records name the right commit.
# GPU_ENV_REUSE=1 on a machine where an earlier call set up and whose runs still go on: only the exports (writing
# the wheels or gsplat's build again under running processes would break them)
reuse=0
# (a machine whose first call JIT-built gsplat has its build in /tmp/tex, which TORCH_EXTENSIONS_DIR points to)
[ "${GPU_ENV_REUSE:-0}" = 1 ] && [ -d /tmp/site/gsplat ] \
  && { [ -f /tmp/gsplat_cuda.so ] || [ -f /tmp/tex/gsplat_cuda/gsplat_cuda.so ]; } && reuse=1
[ $reuse = 1 ] || python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site \
  .whl-gpu/*.whl >/dev/null 2>&1 || { echo "gpu_env: wheel install failed (carry .whl-gpu)"; return 1; }
export PYTHONPATH=/tmp/site:$PWD/.whl-gpu/stub:$PWD MAX_JOBS=16 PYTHONUNBUFFERED=1 TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1 \
  TORCH_EXTENSIONS_DIR=/tmp/tex
if [ $reuse = 1 ]; then
  [ -f /tmp/gsplat_cuda.so ] && export WILLAGS_GSPLAT_SO=/tmp/gsplat_cuda.so
elif [ -f .gpu-cache/gsplat_cuda.so.gz ]; then
  gunzip -c .gpu-cache/gsplat_cuda.so.gz > /tmp/gsplat_cuda.so
  cp benchmarks/gsplat_csrc_shim.py /tmp/site/gsplat/csrc.py
  export WILLAGS_GSPLAT_SO=/tmp/gsplat_cuda.so
fi
# willags' entry points as `pip install` writes them (the tree itself is on PYTHONPATH): `ns-train willags` and
# `ns-eval` find the methods, and nerfstudio loads them before it lists its installable methods, which
# willags_ns/engine/compat.py makes quick (seconds of every process's start-up, each rank of a multi-GPU run included)
[ $reuse = 1 ] || python3 - <<'PY'
import pathlib, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
info = pathlib.Path(f"/tmp/site/willags_ns-{project['version']}.dist-info")
info.mkdir(parents=True, exist_ok=True)
(info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: willags-ns\nVersion: {project['version']}\n")
groups = project["entry-points"]
text = "".join(f"[{g}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) + "\n" for g, eps in groups.items())
(info / "entry_points.txt").write_text(text)
PY
[ $reuse = 1 ] || python3 -c "from gsplat.cuda._backend import _C; print('gsplat CUDA module:', _C)"
