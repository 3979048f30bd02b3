#!/usr/bin/env bash
# Set up Python on a GPU machine that has no internet, from the repository root: `source benchmarks/remote/env.sh`.
# Needs .whl-gpu/ (the wheels that ../shared/gpu/prepare_wheels.sh downloads, plus its stub/), the scenes in
# .gpu-data/ and, optionally, .gpu-cache/gsplat_cuda.so.gz.
# - installs the wheels into /tmp/site;
# - gsplat 1.4.0 JIT-compiles its CUDA code on a fresh machine (~3.5 min). With .gpu-cache/gsplat_cuda.so.gz (the
#   .so an earlier machine of the same image built: /tmp/tex/gsplat_cuda/gsplat_cuda.so, gzipped) it loads that
#   build instead, through benchmarks/remote/gsplat_csrc_shim.py (~6 s);
# - writes willags' entry points (ns-train / ns-eval find the methods) and console scripts (/tmp/site/bin) and exports
#   PATH, PYTHONPATH, MAX_JOBS and TORCH_EXTENSIONS_DIR=/tmp/tex (where a JIT build lands).
# A copy of the tree without .git cannot name its commit: export WILLAGS_COMMIT=<git rev-parse --short HEAD> first so
# the records name it. GPU_ENV_REUSE=1 on a machine set up earlier whose runs still go on: only the exports
# (installing the wheels or gsplat's build again under running processes would break them).
reuse=0
# (a machine whose first call JIT-built gsplat has its build in /tmp/tex, which TORCH_EXTENSIONS_DIR points to)
[ "${GPU_ENV_REUSE:-0}" = 1 ] && [ -d /tmp/site/gsplat ] \
  && { [ -f /tmp/gsplat_cuda.so ] || [ -f /tmp/tex/gsplat_cuda/gsplat_cuda.so ]; } && reuse=1
[ $reuse = 1 ] || python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site \
  .whl-gpu/*.whl >/dev/null 2>&1 || { echo "gpu_env: wheel install failed (needs .whl-gpu/*.whl from ../shared/gpu/prepare_wheels.sh)"; return 1; }
# MAX_JOBS: the JIT build's compile jobs (every core by default); OMP_NUM_THREADS: each training process's CPU threads
# (runs side by side on a machine of many cores would otherwise each start a thread per core)
export PATH=/tmp/site/bin:$PATH PYTHONPATH=/tmp/site:$PWD/.whl-gpu/stub:$PWD MAX_JOBS=${MAX_JOBS:-$(nproc)} PYTHONUNBUFFERED=1 \
  TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1 TORCH_EXTENSIONS_DIR=/tmp/tex OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
if [ $reuse = 1 ]; then
  [ -f /tmp/gsplat_cuda.so ] && export WILLAGS_GSPLAT_SO=/tmp/gsplat_cuda.so
elif [ -f .gpu-cache/gsplat_cuda.so.gz ]; then
  gunzip -c .gpu-cache/gsplat_cuda.so.gz > /tmp/gsplat_cuda.so
  cp benchmarks/remote/gsplat_csrc_shim.py /tmp/site/gsplat/csrc.py
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
# and willags' console scripts (willags-inspect, willags-process, ...) beside the wheels' own (ns-train, ns-eval) in
# /tmp/site/bin, which PATH holds: the benchmarks that start them as programs (benchmarks/scale.py) find them
bindir = pathlib.Path("/tmp/site/bin")
bindir.mkdir(parents=True, exist_ok=True)
for name, target in project["scripts"].items():
    module, func = target.split(":")
    script = bindir / name
    script.write_text(f"#!/usr/bin/env python3\nimport sys\nfrom {module} import {func}\nsys.exit({func}())\n")
    script.chmod(0o755)
PY
[ $reuse = 1 ] || python3 -c "from gsplat.cuda._backend import _C; print('gsplat CUDA module:', _C)"
# every call that starts runs says which commit its records will name (each call carries its own copy of the tree)
if [ -z "${WILLAGS_COMMIT:-}" ] && ! git rev-parse --short HEAD >/dev/null 2>&1; then
  echo "gpu_env: WILLAGS_COMMIT is not set and this copy has no .git: the records of runs started here name no commit"
fi
