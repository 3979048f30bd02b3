"""docs/benchmarks.md from the records: every record in a table of its kind, nothing chosen. Grid runs per scene
(GPU, then CPU), long runs with their milestones, the speed suite, runs on several GPUs. :func:`write_outputs` writes
the records and their markdown."""

import math
from pathlib import Path
from typing import Any

from benchmarks.records import RECORDS, REPO, sort_records, write_records

BENCHMARKS_MD = REPO / "docs" / "benchmarks.md"
"""The markdown of the project's records (:data:`benchmarks.records.RECORDS`)."""


def markdown_path(out_prefix: Path) -> Path:
    """Where the markdown of the records file ``<out_prefix>.json`` goes: docs/benchmarks.md for the project's
    records, ``<out_prefix>.md`` beside any other."""
    out_prefix = Path(out_prefix)
    if out_prefix.with_suffix(".json").resolve() == RECORDS.resolve():
        return BENCHMARKS_MD
    return out_prefix.with_suffix(".md")


def write_outputs(records: list[dict[str, Any]], out_prefix: Path) -> tuple[Path, Path]:
    """Write ``<out_prefix>.json`` (sorted records) and its markdown (:func:`markdown_path`), regenerated from them."""
    records = sort_records(records)
    jpath = write_records(records, Path(out_prefix).with_suffix(".json"))
    mpath = markdown_path(out_prefix)
    mpath.parent.mkdir(parents=True, exist_ok=True)
    mpath.write_text(render_markdown(records))
    return jpath, mpath


def _f(v, fmt: str, none: str = "–") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return none
    return format(v, fmt)


def kind(rec: dict[str, Any]) -> str:
    """ "devices" (a data-parallel run), "speed" (the speed suite), "long" (a long run) or "grid"."""
    if "num_devices" in rec:
        return "devices"
    if any(rec.get(k) is not None for k in ("step_ms", "render_fps_ratio_vs_gsplat", "parity_fwd_rel_err")):
        return "speed"
    return "long" if rec.get("kind") == "long_run" else "grid"


def gpu(rec: dict[str, Any]) -> str:
    """The GPU model a record ran on (H100, H200, ...), "cpu" for CPU runs."""
    if rec.get("device") == "cpu":
        return "cpu"
    where = rec.get("machine") if rec.get("device") == "cuda" else rec.get("device")  # the speed suite names its GPU
    name = str(where or "").split("(")[0].replace("NVIDIA", "").split()
    return name[0] if name else "?"


def md_table(head: list[str], rows: list[list[str]]) -> list[str]:
    """A markdown table: the head, its rule and a line per row of cells."""
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head), *("| " + " | ".join(r) + " |" for r in rows)]


def grid_table(recs: list[dict[str, Any]]) -> list[str]:
    """One row per grid run of a scene, by steps, method, tag; mask columns where a run scored its mask."""
    has_mask = any(r.get("mask_iou") is not None or r.get("mask_fp_rate") is not None for r in recs)
    head = ["method", "tag", "seed", "steps", "PSNR", "SSIM", "LPIPS", "train s", "Gaussians"]
    head += ["mask IoU", "clean FP"] if has_mask else []
    rows = []
    for r in sorted(recs, key=lambda r: (int(r["steps"]), r["method"], str(r.get("tag") or ""))):
        ok = r.get("status", "ok") == "ok"
        cells = [r["method"], r.get("tag") or "–", _f(r.get("seed"), "d"), str(r["steps"])]
        cells += [_f(r.get("psnr"), ".2f") if ok else r["status"], _f(r.get("ssim"), ".3f")]
        cells += [_f(r.get("lpips"), ".3f"), _f(r.get("train_s"), ".0f"), _f(r.get("num_gaussians"), ",")]
        if has_mask:
            fp = r.get("mask_fp_rate")
            cells += [_f(r.get("mask_iou"), ".3f"), "–" if fp is None else f"{100 * fp:.1f}%"]
        rows.append(cells + [gpu(r), str(r.get("commit") or r.get("code_commit") or "–")])
    return md_table(head + ["GPU", "commit"], rows)


def _milestones(r: dict[str, Any]) -> str:
    def label(k: str) -> str:
        return f"{int(k) // 1000}k" if int(k) % 1000 == 0 else k

    ms = sorted((r.get("milestones") or {}).items(), key=lambda kv: int(kv[0]))
    return ", ".join(f"{label(k)}: {_f(v.get('psnr'), '.2f')}" for k, v in ms) or "–"


def long_table(recs: list[dict[str, Any]]) -> list[str]:
    """One row per long run: its scored milestones (right-half PSNR) and its time budget, if it trained under one."""
    rows = []
    for r in sorted(recs, key=lambda r: (r["scene"], r["method"], str(r.get("tag") or ""))):
        budget = r.get("time_budget_minutes")
        cells = [r["scene"], r["method"], r.get("tag") or "–", _f(r.get("seed"), "d"), str(r.get("steps_done", "–"))]
        cells += [_f(r.get("train_s"), ".0f"), _milestones(r), "–" if budget is None else f"{budget:g} min"]
        rows.append(cells + [gpu(r), str(r.get("commit") or "–")])
    head = ["scene", "method", "tag", "seed", "steps", "train s", "PSNR at milestones", "time budget", "GPU", "commit"]
    return md_table(head, rows)


def speed_table(recs: list[dict[str, Any]]) -> list[str]:
    """The speed suite's records (train step, render, memory, parity at a fixed N): one row per variant and GPU."""
    rows = []
    for r in sorted(recs, key=lambda r: (r["scene"], gpu(r), str(r.get("tag") or ""), r.get("step_ms") or 0)):
        parity = "–"
        if r.get("parity_fwd_rel_err") is not None:
            parity = f"{r['parity_fwd_rel_err']:.1e} / {r.get('parity_grad_rel_err', float('nan')):.1e}"
        cells = [r["scene"], r["method"], r.get("tag") or "–", gpu(r), _f(r.get("step_ms"), ".2f")]
        cells += [_f(r.get("step_ratio_vs_splatfacto"), ".2f"), _f(r.get("extra_vram_gb"), "+.2f")]
        cells += [_f(r.get("host_syncs_per_step"), ".0f"), _f(r.get("render_fps_ratio_vs_splatfacto"), ".2f")]
        cells += [_f(r.get("render_fps_ratio_vs_gsplat"), ".3f"), parity, str(r.get("commit") or r.get("code_commit"))]
        rows.append(cells)
    head = ["scene", "variant", "tag", "GPU", "step ms", "ratio vs splatfacto", "extra peak VRAM GB", "host syncs/step"]
    head += ["render FPS vs splatfacto", "render FPS vs gsplat", "parity fwd / grad rel. err", "commit"]
    return md_table(head, rows)


def devices_table(recs: list[dict[str, Any]]) -> list[str]:
    """Data-parallel runs: GPUs, steps, images seen, wall and step time, images per second against the one-GPU run
    of their group (x1), PSNR."""
    rows = []
    for r in sorted(recs, key=lambda r: (r["scene"], r.get("group", ""), r["num_devices"], r.get("tag") or "")):
        one = [o for o in recs if o.get("group") == r.get("group") and o["num_devices"] == 1 and o.get("step_ms")]
        x1 = r["num_devices"] * one[0]["step_ms"] / r["step_ms"] if one and r.get("step_ms") else None
        cells = [r["scene"], r.get("tag") or "–", str(r["num_devices"]), str(r.get("num_machines", 1))]
        cells += [str(r["steps"]), str(r.get("images", "–")), _f(r.get("train_wall_s"), ".1f")]
        cells += [_f(r.get("step_ms"), ".2f"), _f(x1, ".2f"), _f(r.get("psnr"), ".2f"), _f(r.get("num_gaussians"), ",")]
        rows.append(cells)
    head = ["scene", "tag", "GPUs", "machines", "steps", "images", "wall s", "step ms", "x1", "PSNR", "Gaussians"]
    return md_table(head, rows)


def render_markdown(records: list[dict[str, Any]]) -> str:
    """docs/benchmarks.md: every record in the table of its kind (:func:`kind`)."""
    by: dict[str, list[dict[str, Any]]] = {}
    for r in records:
        by.setdefault(kind(r), []).append(r)
    out = [
        "# Benchmarks",
        "",
        "Generated by `python -m benchmarks tables` from `benchmarks/records/benchmarks.json`; do not edit by hand. "
        "Every record is in one table of its kind; a record keeps the method name it ran as (docs/results.md names "
        "the configuration each measured). **PSNR / SSIM / LPIPS**: the NeRF-W protocol on the test split, the "
        "appearance latent fitted on the left half of each test image and the right half scored (methods without a "
        "latent fit nothing; LPIPS – where AlexNet's weights were not on disk). **train s**: `trainer.train()` wall "
        "time, set-up and evaluation excluded; runs sharing a GPU have shared-GPU times (docs/curves.md tells them "
        "apart). **mask IoU**: the transient mask against `masks_gt/`, pooled over the training images; **clean "
        "FP**: pixels flagged among the clean ones. **tag**: the set of runs a record belongs to; the tags "
        "docs/design.md cites are found here. Commands: docs/results.md, benchmarks/remote/README.md.",
        "",
    ]
    for device, title in (("gpu", "Grid runs on the GPU"), ("cpu", "Grid runs on the CPU")):
        recs = [r for r in by.get("grid", []) if (gpu(r) == "cpu") == (device == "cpu")]
        out += [f"## {title}", ""] if recs else []
        for scene in sorted({r["scene"] for r in recs}):
            srecs = [r for r in recs if r["scene"] == scene]
            out += [f"### {scene} ({'cpu' if device == 'cpu' else 'GPU'})", "", *grid_table(srecs), ""]
    sections = (
        (
            "long",
            "Long runs",
            "Trained to their steps with splatfacto's stock schedule (`python -m benchmarks "
            "long-run`), scored at milestones; a run under the time budget stops where the budget says.",
        ),
        (
            "speed",
            "Speed suite",
            "`python -m benchmarks speed`: a synthetic scene of N Gaussians, one train step and "
            "one render timed per variant, at a step past every warm-up with densification off.",
        ),
        ("devices", "Several GPUs", "willags data-parallel at equal images seen (docs/distributed.md)."),
    )
    for k, title, what in sections:
        if by.get(k):
            table = {"long": long_table, "speed": speed_table, "devices": devices_table}[k](by[k])
            out += [f"## {title}", "", what, "", *table, ""]
    return "\n".join(out)
