"""docs/benchmarks.md from the records: :func:`render_markdown` and the per-device sections (provenance, the
goals, a table per scene, the gpu_suite speed table, the fox-wild Pareto table); :func:`write_outputs` writes the
records and their markdown. The fidelity grid's sections are in :mod:`benchmarks.fidelity_tables`, the every-scene
tables in :mod:`benchmarks.generalisation` and :mod:`benchmarks.every_scene`."""

import math
from pathlib import Path
from typing import Any

from benchmarks.curves import pareto_optimal
from benchmarks.every_scene import every_scene_section
from benchmarks.fidelity_tables import fidelity_section
from benchmarks.generalisation import TAGS as GENERALISATION_TAGS
from benchmarks.generalisation import generalisation_section
from benchmarks.methods import BASELINES, METHODS
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


def _f(v, fmt: str, none: str = "n/a") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return none
    return format(v, fmt)


def _ok(records):
    return [r for r in records if r.get("status", "ok") == "ok"]


def _find(records, scene: str, method: str, steps: int | None = None, tag: str | None = None):
    rs = [r for r in _ok(records) if r["scene"] == scene and r["method"] == method]
    if steps is not None:
        rs = [r for r in rs if int(r["steps"]) == int(steps)]
    if tag is not None:
        rs = [r for r in rs if (r.get("tag") or "") == tag]
    return rs


def _pair(records, scene: str, a: str, b: str):
    """(record of a, record of b) at the largest (steps, tag) both have on `scene`, or None."""
    keys_a = {(int(r["steps"]), r.get("tag") or "") for r in _find(records, scene, a)}
    keys_b = {(int(r["steps"]), r.get("tag") or "") for r in _find(records, scene, b)}
    common = sorted(keys_a & keys_b)
    if not common:
        return None
    steps, tag = common[-1]
    return _find(records, scene, a, steps, tag)[0], _find(records, scene, b, steps, tag)[0]


def _baseline(records, scene: str, against: str = "willags") -> str | None:
    for b in BASELINES:
        if _pair(records, scene, against, b) is not None:
            return b
    return None


def _label(method: str) -> str:
    return f"{method} (stand-in)" if method == "willags-3dgs" else method


def _margin_row(goal: str, have: tuple | None, metric: str, need: float, unit: str, what: str) -> dict[str, Any]:
    """A 'x >= y + need' goal row; need may be negative (a tolerance)."""
    if have is None:
        return {"goal": goal, "measured": "not measured", "target": "", "status": "not measured", "met": None}
    a, b = have
    va, vb = a.get(metric), b.get(metric)
    if va is None or vb is None:
        return {"goal": goal, "measured": "not measured", "target": "", "status": "not measured", "met": None}
    diff = va - vb
    gap = diff - need
    measured = f"{what}: {va:.2f} vs {vb:.2f} ({diff:+.2f} {unit}) at {a['steps']} steps"
    target = f"{'+' if need >= 0 else ''}{need:g} {unit}"
    status = f"met (margin {gap:.2f} {unit})" if gap >= 0 else f"missed by {-gap:.2f} {unit}"
    return {"goal": goal, "measured": measured, "target": target, "status": status, "met": gap >= 0}


def goal_rows(records: list[dict[str, Any]], device: str) -> list[dict[str, Any]]:
    """The project's goals, measured on one device's records (see docs/benchmarks.md)."""
    recs = [r for r in _ok(records) if r["device"] == device]
    rows = []
    base = _baseline(recs, "fox-wild") or "splatfacto"
    rows.append(
        _margin_row(
            f"fox-wild: willags >= {_label(base)} + 4 dB",
            _pair(recs, "fox-wild", "willags", base),
            "psnr",
            4.0,
            "dB",
            "PSNR",
        )
    )
    scenes = ["fox-wild"] + sorted({r["scene"] for r in recs} - {"fox-wild"})
    for sc in scenes:
        pair = _pair(recs, sc, "willags", "willags-vae")
        if pair is not None or sc == "fox-wild":
            rows.append(_margin_row(f"{sc}: willags >= willags-vae (the VAE latent)", pair, "psnr", 0.0, "dB", "PSNR"))
    # mask quality on fox-wild, willags at its largest budget
    w = sorted(_find(recs, "fox-wild", "willags"), key=lambda r: int(r["steps"]))
    w = [r for r in w if r.get("mask_iou") is not None]
    if w:
        r = w[-1]
        iou, fp = r["mask_iou"], r["mask_fp_rate"]
        ok_iou, ok_fp = iou >= 0.6, fp <= 0.05
        parts = []
        if not ok_iou:
            parts.append(f"IoU missed by {0.6 - iou:.2f}")
        if not ok_fp:
            parts.append(f"FP missed by {100 * (fp - 0.05):.1f} pp")
        status = "met" if ok_iou and ok_fp else "; ".join(parts)
        rows.append(
            {
                "goal": "fox-wild: mask IoU >= 0.6 and clean FP <= 5%",
                "measured": f"IoU {iou:.3f}, FP {100 * fp:.1f}% (recall {_f(r.get('mask_recall'), '.3f')}) at "
                f"{r['steps']} steps",
                "target": "IoU >= 0.6, FP <= 5%",
                "status": status,
                "met": ok_iou and ok_fp,
            }
        )
    else:
        rows.append(
            {
                "goal": "fox-wild: mask IoU >= 0.6 and clean FP <= 5%",
                "measured": "not measured",
                "target": "",
                "status": "not measured",
                "met": None,
            }
        )
    base_c = _baseline(recs, "fox-clean") or "splatfacto"
    rows.append(
        _margin_row(
            f"fox-clean: willags >= {_label(base_c)} - 0.2 dB",
            _pair(recs, "fox-clean", "willags", base_c),
            "psnr",
            -0.2,
            "dB",
            "PSNR",
        )
    )
    rows.append(_lite_time_row(recs, base))
    return rows


def _lite_time_row(recs, base: str) -> dict[str, Any]:
    goal = f"fox-wild: willags-lite reaches {_label(base)}'s PSNR in <= 0.5x its train time"
    refs = sorted(_find(recs, "fox-wild", base), key=lambda r: int(r["steps"]))
    lites = sorted(_find(recs, "fox-wild", "willags-lite"), key=lambda r: r["train_s"])
    if not refs or not lites:
        return {"goal": goal, "measured": "not measured", "target": "", "status": "not measured", "met": None}
    ref = refs[-1]
    allowed = 0.5 * ref["train_s"]
    reach = [r for r in lites if r.get("psnr") is not None and r["psnr"] >= ref["psnr"]]
    target = f"<= {allowed:.0f} s (0.5 x {ref['train_s']:.0f} s)"
    if not reach:
        best = max(lites, key=lambda r: r["psnr"])
        return {
            "goal": goal,
            "target": target,
            "met": False,
            "measured": f"{base} {ref['psnr']:.2f} dB at {ref['steps']} steps; best lite {best['psnr']:.2f} dB "
            f"({best['steps']} steps, {best['train_s']:.0f} s)",
            "status": f"missed: never reached (by {ref['psnr'] - best['psnr']:.2f} dB)",
        }
    first = reach[0]
    ratio = first["train_s"] / ref["train_s"]
    met = first["train_s"] <= allowed
    status = f"met ({ratio:.2f}x)" if met else f"missed: {ratio:.2f}x of {base}'s time (allowed 0.5x)"
    return {
        "goal": goal,
        "target": target,
        "met": met,
        "status": status,
        "measured": f"{base} {ref['psnr']:.2f} dB in {ref['train_s']:.0f} s ({ref['steps']} steps); lite "
        f"{first['psnr']:.2f} dB in {first['train_s']:.0f} s ({first['steps']} steps)",
    }


def pareto_rows(records: list[dict[str, Any]], device: str, scene: str = "fox-wild") -> list[dict[str, Any]]:
    """PSNR vs train time of the presets and baselines on `scene`; `pareto` marks points no other point beats
    on both (less time and higher PSNR)."""
    methods = ("willags", "willags-lite", "willags-3dgs", "splatfacto")
    pts = [r for r in _ok(records) if r["device"] == device and r["scene"] == scene and r["method"] in methods]
    pts = sorted(pts, key=lambda r: (methods.index(r["method"]), int(r["steps"])))
    optimal = pareto_optimal([(r["train_s"], r["psnr"]) for r in pts])
    rows = []
    for r, best in zip(pts, optimal, strict=True):
        rows.append(
            {
                "method": r["method"],
                "steps": int(r["steps"]),
                "tag": r.get("tag") or "",
                "train_s": r["train_s"],
                "psnr": r["psnr"],
                "full_psnr": r.get("full_psnr"),
                "pareto": best,
            }
        )
    return rows


def _scene_table(recs: list[dict[str, Any]]) -> list[str]:
    has_mask = any(r.get("mask_status") == "ok" or r.get("mask_iou") is not None for r in recs)
    head = [
        "method",
        "steps",
        "PSNR",
        "SSIM",
        "LPIPS",
        "enc PSNR",
        "full PSNR",
        "train s",
        "s/step",
        "FPS",
        "Gaussians",
        "peak mem GB",
        "load",
    ]
    if has_mask:
        head += ["mask IoU", "IoU/img", "recall", "clean FP", "rejected"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    order = {m: i for i, m in enumerate(METHODS)}
    for r in sorted(recs, key=lambda r: (r.get("tag") or "", order.get(r["method"], 99), int(r["steps"]))):
        name = _label(r["method"]) + (f" [{r['tag']}]" if r.get("tag") else "")
        if r.get("status", "ok") != "ok":
            lines.append(f"| {name} | {r['steps']} | {r['status']} |" + " |" * (len(head) - 3))
            continue
        cells = [
            name,
            str(r["steps"]),
            _f(r.get("psnr"), ".2f"),
            _f(r.get("ssim"), ".3f"),
            _f(r.get("lpips"), ".3f"),
            _f(r.get("encoder_psnr"), ".2f", "-"),
            _f(r.get("full_psnr"), ".2f"),
            _f(r.get("train_s"), ".0f"),
            _f(r.get("s_per_step"), ".2f"),
            _f(r.get("fps"), ".1f"),
            _f(r.get("num_gaussians"), ","),
            _f(r.get("peak_mem_gb"), ".2f"),
            _f(max(r["load_avg_1m"]), ".1f") if r.get("load_avg_1m") else "-",
        ]
        if has_mask:
            cells += [
                _f(r.get("mask_iou"), ".3f", "-"),
                _f(r.get("mask_iou_mean"), ".3f", "-"),
                _f(r.get("mask_recall"), ".3f", "-"),
                (_f(100 * r["mask_fp_rate"], ".1f") + "%") if r.get("mask_fp_rate") is not None else "-",
                f"{int(r['mask_rejected'])}/{int(r['mask_num_images'])}" if r.get("mask_rejected") is not None else "-",
            ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _is_speed_record(r: dict[str, Any]) -> bool:
    """A benchmarks/gpu_suite.py record (train step, render speed, memory, parity), not a train-and-score run."""
    return any(r.get(k) is not None for k in ("step_ms", "render_fps_ratio_vs_gsplat", "parity_fwd_rel_err"))


def _speed_label(r: dict[str, Any]) -> str:
    return r["method"] + (f" [{r['tag']}]" if r.get("tag") else "")


def _speed_table(recs: list[dict[str, Any]]) -> list[str]:
    """Records of benchmarks/gpu_suite.py (train step, render, memory, parity at a fixed N): one row per variant."""
    out = [
        f"### Train step / render / memory: {recs[0]['scene']} (benchmarks/gpu_suite.py)",
        "",
        "| variant | step ms | ratio vs splatfacto | extra peak VRAM GB | host syncs/step | render FPS ratio vs "
        "splatfacto | render FPS ratio vs gsplat | parity fwd / grad rel. err |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(recs, key=lambda r: r.get("step_ms") or 0):
        parity = "-"
        if r.get("parity_fwd_rel_err") is not None:
            parity = f"{r['parity_fwd_rel_err']:.1e} / {r.get('parity_grad_rel_err', float('nan')):.1e}"
        out.append(
            f"| {_speed_label(r)} | {_f(r.get('step_ms'), '.2f')} | {_f(r.get('step_ratio_vs_splatfacto'), '.2f')} | "
            f"{_f(r.get('extra_vram_gb'), '+.2f')} | {_f(r.get('host_syncs_per_step'), '.0f')} | "
            f"{_f(r.get('render_fps_ratio_vs_splatfacto'), '.2f', '-')} | "
            f"{_f(r.get('render_fps_ratio_vs_gsplat'), '.3f', '-')} | {parity} |"
        )
    return out


def render_markdown(records: list[dict[str, Any]]) -> str:
    """docs/benchmarks.md from the records: per device, the runs' provenance, the goals, a table per scene and the
    fox-wild Pareto table."""
    out = [
        "# Benchmarks",
        "",
        "Generated by `python -m benchmarks tables` from `benchmarks/records/benchmarks.json`; do not edit by hand (rerun the "
        "command below; records with the same (scene, method, device, steps, tag) are replaced, others kept).",
        "",
        "Columns. **PSNR / SSIM / LPIPS**: NeRF-W protocol on the test split: the appearance latent is fitted on "
        "the left half of each test image (Adam, `protocol_steps` steps, lr 0.01; initialised from the VAE "
        "encoder, or the mean training embedding without a VAE) and the right half is scored. Methods without a "
        "latent (willags-3dgs, splatfacto) fit nothing. **enc PSNR**: right half with the encoder's latent, no "
        "fitting. **full PSNR**: whole image, fitted latent. LPIPS is n/a where AlexNet weights are not on disk "
        "(offline machines). **train s**: `trainer.train()` wall time (no evaluation during training; data "
        "loading excluded). **FPS**: median `get_outputs` time per test view (eval, no grad, fixed latent). "
        "**peak mem**: CUDA `max_memory_allocated` during training on GPU, the run process's max RSS on CPU. "
        "**mask IoU**: transient mask vs `masks_gt/` over the training images, pooled over all pixels; "
        "**IoU/img**: mean over images with transients; **clean FP**: predicted transient among GT-clean pixels "
        "(see willags_ns/eval/mask_eval.py); **rejected**: images whose mask the mask.max_masked_fraction guard dropped "
        "(training supervises them everywhere). **load**: the machine's 1-minute load average around training "
        "(wall times are only comparable between rows with similar load on a shared machine). `willags-3dgs` is plain 3DGS through willags' rasteriser: the CPU "
        "stand-in for splatfacto (stock splatfacto needs CUDA); goals use stock splatfacto where it ran.",
        "",
    ]
    # data-parallel runs (benchmarks/multi_gpu.py) have a section of their own: their steps are not images
    devices = [r for r in records if "num_devices" in r]
    records = [r for r in records if "num_devices" not in r]
    out += fidelity_section(records)
    out += every_scene_section(records)
    out += generalisation_section(records)
    records = [r for r in records if not str(r.get("tag", "")).startswith(GENERALISATION_TAGS)]
    # runs under a time budget stop at a step of their own, with compressed schedules: no row of a fixed-step table
    # (they are in the full-length runs' section and in docs/curves.md's knob section)
    records = [r for r in records if not r.get("time_budget_minutes")]
    for device in sorted({r["device"] for r in records}):
        recs = [r for r in records if r["device"] == device]
        out += [f"## {device}", ""]
        machines = sorted({r.get("machine", "?") for r in recs})
        commands = sorted({r.get("command", "?") for r in recs})
        dates = sorted({(r.get("date") or "?")[:10] for r in recs})
        commits = sorted({r.get("commit") or r.get("code_commit") or "?" for r in recs})
        out.append("- machine: " + "; ".join(machines))
        out.append("- command: " + "; ".join(f"`{c}`" for c in commands))
        out.append(f"- dates: {', '.join(dates)}; commits: {', '.join(commits)}")
        budgets = sorted({int(r["steps"]) for r in recs})
        out.append(
            f"- step budgets: {', '.join(map(str, budgets))}; schedules: "
            f"{', '.join(sorted({r.get('schedule', '?') for r in recs}))}; protocol steps: "
            f"{', '.join(map(str, sorted({r.get('protocol_steps', 0) for r in recs})))}"
        )
        fails = [r for r in recs if r.get("status", "ok") != "ok"]
        if fails:
            out.append(f"- failed runs: {len(fails)} (listed in the tables)")
        goals = goal_rows(recs, device)
        if any(g["status"] != "not measured" for g in goals):  # speed-only sections measure none of them
            out += ["", "### Goals", "", "| goal | measured | target | status |", "|---|---|---|---|"]
            for g in goals:
                out.append(f"| {g['goal']} | {g['measured']} | {g['target']} | {g['status']} |")
        out.append("")
        if device == "cpu":
            out += [
                "On CPU the baseline is `willags-3dgs` (stand-in), not stock splatfacto; budgets are short and "
                "images downscaled (see each scene's resolution), so these numbers are not comparable to the "
                "GPU table or to published ones.",
                "",
            ]
        speed = [r for r in recs if _is_speed_record(r)]
        if speed:
            out += _speed_table(speed) + [""]
        recs = [r for r in recs if not _is_speed_record(r)]
        for scene in sorted({r["scene"] for r in recs}, key=lambda s: (s != "default", s)):
            srecs = [r for r in recs if r["scene"] == scene]
            ok = _ok(srecs)
            res = sorted({f"{r['image_hw'][1]}x{r['image_hw'][0]}" for r in ok if r.get("image_hw")})
            n_train = sorted({r.get("num_train_images") for r in ok if r.get("num_train_images") is not None})
            n_test = sorted({int(r["num_images"]) for r in ok if r.get("num_images") is not None})
            info = []
            if res:
                info.append(f"first train image {'/'.join(res)} px (WxH)")
            if n_train:
                info.append(f"{'/'.join(map(str, n_train))} train views")
            if n_test:
                info.append(f"{'/'.join(map(str, n_test))} test views scored")
            out += [f"### {scene}", ""]
            if info:
                out += [", ".join(info), ""]
            out += _scene_table(srecs) + [""]
        prow = pareto_rows(recs, device)
        if prow:
            out += [
                "### Pareto: fox-wild PSNR vs train time",
                "",
                "`*` = Pareto-optimal (no other run is both faster and better).",
                "",
                "| method | steps | train s | PSNR | full PSNR | |",
                "|---|---|---|---|---|---|",
            ]
            for p in prow:
                name = _label(p["method"]) + (f" [{p['tag']}]" if p["tag"] else "")
                out.append(
                    f"| {name} | {p['steps']} | {p['train_s']:.0f} | {p['psnr']:.2f} | "
                    f"{_f(p['full_psnr'], '.2f')} | {'*' if p['pareto'] else ''} |"
                )
            out.append("")
    out += devices_section(devices)
    return "\n".join(out) + "\n"


def devices_section(records: list[dict[str, Any]]) -> list[str]:
    """Data-parallel runs (benchmarks/multi_gpu.py, docs/distributed.md): per scene and group of runs measured
    together, each run's GPUs, steps and images seen, wall time, steady-state step time and throughput against the
    group's one-GPU run, protocol PSNR and Gaussians."""
    if not records:
        return []
    out = [
        "## Several GPUs (data-parallel)",
        "",
        "benchmarks/multi_gpu.py: every run of a group sees the same number of images (steps x GPUs), with every "
        "step-counted setting divided by the GPUs. **wall s**: the training command from launch to exit (start-up "
        "included); **step ms**: the median loop iteration over the last quarter of the steps (the ranks' step "
        "profile); **x1**: images per second against the group's one-GPU run.",
        "",
    ]
    for scene, group in sorted({(r["scene"], r.get("group", "")) for r in records}):
        recs = sorted(
            (r for r in records if (r["scene"], r.get("group", "")) == (scene, group)),
            key=lambda r: (r["num_devices"], r.get("num_machines", 1), r.get("reduction", "")),
        )
        one = next((r for r in recs if r["num_devices"] == 1 and r.get("step_ms")), None)
        out += [
            f"### {scene} ({group})",
            "",
            "| GPUs | machines | reduction | steps | images | status | wall s | step ms | x1 | PSNR | Gaussians |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in recs:
            x1 = None
            if one is not None and r.get("step_ms"):
                x1 = r["num_devices"] * one["step_ms"] / r["step_ms"]
            out.append(
                f"| {r['num_devices']} | {r.get('num_machines', 1)} | {r.get('reduction', '')} | {r['steps']} | "
                f"{r.get('images', '')} | {r.get('status', 'ok')} | {_f(r.get('train_wall_s'), '.1f')} | "
                f"{_f(r.get('step_ms'), '.2f')} | {_f(x1, '.2f')} | {_f(r.get('psnr'), '.2f')} | "
                f"{_f(r.get('num_gaussians'), '.0f')} |"
            )
        out.append("")
    return out
