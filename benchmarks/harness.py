"""Benchmark harness: train a grid of methods x scenes x step budgets, evaluate each run, keep the records.

    python -m benchmarks run --grid configs/benchmark_cpu.json

This module is the harness's one name for scripts and tests, and the child process's entry point
(``python -m benchmarks.harness child SPEC RESULT``, how :func:`benchmarks.runner.run_one` starts a run). The work
is split by job:

- :mod:`benchmarks.methods`: the benchmarked methods (``METHODS``) and the TrainerConfig of one run;
- :mod:`benchmarks.runner`: the grid file, scene look-up and downscaling, running each spec in a child process;
- :mod:`benchmarks.child`: one run inside the child (train, the NeRF-W protocol, FPS, masks, pictures);
- :mod:`benchmarks.records`: record keys, merging, ``<out>.json`` and ``<out>.md``;
- :mod:`benchmarks.tables`, :mod:`benchmarks.fidelity_tables`, :mod:`benchmarks.generalisation`: the markdown.

Imports go one way (no circles): fidelity_tables and tables import methods, tables imports fidelity_tables and
generalisation, records imports tables, child and runner import methods and records, harness imports them all.
"""

import sys

from benchmarks.child import (
    RENDERS_ENV,
    _child_main,
    _patch_stock_splatfacto,
    protocol_scores,
    render_fps,
    run_child,
    save_masks,
    save_right_halves,
    save_two_row_sheet,
    static_observation_scores,
    training_mask,
)
from benchmarks.fidelity_tables import (
    ABLATIONS,
    FIDELITY_TAG,
    PEER_5000,
    PER_VIEW_ROWS,
    PER_VIEW_SCENES,
    ablation_rows,
    fidelity_section,
    fifteen_k_section,
    long_run_section,
    per_view_rows,
)
from benchmarks.methods import (
    BASELINES,
    METHODS,
    MethodSpec,
    apply_schedule,
    base_trainer_config,
    build_config,
    set_lr,
    set_nested,
    stock_adam,
)
from benchmarks.records import load_records, merge_records, record_key
from benchmarks.runner import (
    GRID_KEYS,
    IMAGE_SUFFIXES,
    MIRROR_MARKER,
    REPO,
    RUN_KEYS,
    RunSpec,
    _git_commit,
    _warm_gsplat,
    bench_cache_root,
    downscaled_scene,
    machine_description,
    parse_grid,
    resolve_device,
    resolve_scene,
    run_grid,
    run_one,
    scene_name,
)
from benchmarks.tables import goal_rows, pareto_rows, render_markdown, write_outputs

__all__ = [
    "ABLATIONS",
    "BASELINES",
    "FIDELITY_TAG",
    "GRID_KEYS",
    "IMAGE_SUFFIXES",
    "METHODS",
    "MIRROR_MARKER",
    "PEER_5000",
    "PER_VIEW_ROWS",
    "PER_VIEW_SCENES",
    "RENDERS_ENV",
    "REPO",
    "RUN_KEYS",
    "MethodSpec",
    "RunSpec",
    "_child_main",
    "_git_commit",
    "_patch_stock_splatfacto",
    "_warm_gsplat",
    "ablation_rows",
    "apply_schedule",
    "base_trainer_config",
    "bench_cache_root",
    "build_config",
    "downscaled_scene",
    "fidelity_section",
    "fifteen_k_section",
    "goal_rows",
    "load_records",
    "long_run_section",
    "machine_description",
    "merge_records",
    "pareto_rows",
    "parse_grid",
    "per_view_rows",
    "protocol_scores",
    "record_key",
    "render_fps",
    "render_markdown",
    "resolve_device",
    "resolve_scene",
    "run_child",
    "run_grid",
    "run_one",
    "save_masks",
    "save_right_halves",
    "save_two_row_sheet",
    "scene_name",
    "set_lr",
    "set_nested",
    "static_observation_scores",
    "stock_adam",
    "training_mask",
    "write_outputs",
]

if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "child":
        sys.exit(_child_main(sys.argv[2], sys.argv[3]))
    print("usage: python -m benchmarks.harness child SPEC.json RESULT.json (use python -m benchmarks run)")
    sys.exit(2)
