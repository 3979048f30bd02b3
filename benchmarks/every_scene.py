"""docs/benchmarks.md, section "Every real scene, liberty included": the default beside splatfacto, the peer and the
sky candidates on the four real collections, 5000 steps, with the goal (the peer + 1 dB) and what the transient mask
eats there ("subject masked" on liberty's statue, "static observations masked" on every real scene).

Today's default is what `willags` trains after inspecting each scene (willags_ns/tools/inspect.py). Where the inspector's
decision for a scene did not change with the surround sky and the colour-twin test (reichstag, sacre-coeur-mini,
south-building: tests/tools/test_inspect.py checks the decisions), its records are generalisation.auto_records'. On
liberty the inspector now picks no mask and the sky behind every pixel with its alpha penalty: exactly the model of
`willags-skyalpha-nomask` (tests/tools/test_autoconfig.py checks), whose records count, with `willags` records from
INSPECTOR_SINCE on; liberty's earlier `willags` records are of the inspector without those two rules (the mask, the
sky above the skyline).
"""

from __future__ import annotations

from typing import Any

from benchmarks.generalisation import _cell, _diff, _grid, _mean, auto_records

REAL_SCENES = ("liberty", "reichstag", "sacre-coeur-mini", "south-building")
INSPECTOR_SINCE = "2026-11-26T10:25:13"
"""`willags` records dated from here on (commit ceadd55; a record is dated when its run starts) ran the inspector with the surround
sky and the colour-twin transient test; liberty's earlier ones ran the inspector without them."""
RESOLVED_AS = {"liberty": ("willags-skyalpha-nomask",)}
"""Per scene, methods named in full whose model is exactly what today's default resolves to there."""
SKY_CANDIDATES = ("willags-skyalpha", "willags-skyalpha-support", "willags-skyalpha-nomask")
GOAL_DB = 1.0
"""The goal: the default at least this much above the peer on every real scene (mean of 2 seeds)."""


def _since(r: dict[str, Any]) -> bool:
    return str(r.get("date") or "") >= INSPECTOR_SINCE


def today_records(by: dict[tuple[str, str], list[dict[str, Any]]], scene: str) -> list[dict[str, Any]]:
    """Records of today's default on `scene` (module docstring)."""
    if scene in RESOLVED_AS:
        recs = [r for r in by.get((scene, "willags"), []) if _since(r)]
        return recs + [r for m in RESOLVED_AS[scene] for r in by.get((scene, m), [])]
    return auto_records(by, scene)


def previous_records(by: dict[tuple[str, str], list[dict[str, Any]]], scene: str) -> list[dict[str, Any]]:
    """Records of the default before the surround sky and the colour-twin test; the same as today's where the
    inspector's decision did not move."""
    if scene in RESOLVED_AS:
        return [r for r in by.get((scene, "willags"), []) if not _since(r)]
    return today_records(by, scene)


def _mask_off(r: dict[str, Any]) -> bool:
    """A run trained without the transient mask: the inspector switched it off, or the method has none."""
    settings = (r.get("auto_config") or {}).get("settings") or {}
    # "use_mask": the field's name in records written before the mask's settings became one group
    off = settings.get("mask.enabled", settings.get("use_mask")) is False
    return off or str(r.get("method", "")).endswith("-nomask")


def _share(recs: list[dict[str, Any]], key: str) -> str:
    vals = [float(r[key]) for r in recs if r.get(key) is not None]
    if not vals:
        return "–"
    return f"{100 * min(vals):.1f}-{100 * max(vals):.1f} %" if len(vals) > 1 else f"{100 * vals[0]:.1f} %"


def goal_cell(today: list[dict[str, Any]], peer: list[dict[str, Any]]) -> str:
    """`met` when the mean of `today` is at least GOAL_DB above the mean of `peer`, else by how much it is missed."""
    mt, mp = _mean([float(r["psnr"]) for r in today]), _mean([float(r["psnr"]) for r in peer])
    if mt is None or mp is None:
        return "–"
    return "met" if mt >= mp + GOAL_DB else f"missed by {mp + GOAL_DB - mt:.2f}"


def sky_rows(records: list[dict[str, Any]]) -> list[str]:
    """One row per real scene: splatfacto, the peer, today's default and its margin over the peer against the goal,
    the inspector's choice without the surround sky and the twin test (mask + skyline sky), the sky candidates."""
    by = _grid(records)
    cands = [c for c in SKY_CANDIDATES if any(k[1] == c for k in by)]
    head = (
        "| scene | splatfacto | peer | **willags** | willags − peer | goal (peer + 1 dB) | mask + skyline sky | "
        "willags − it | " + " | ".join(cands) + " |"
    )
    out = [head, "|" + "---|" * (8 + len(cands))]
    for sc in REAL_SCENES:
        peer, today, prev = by.get((sc, "peer"), []), today_records(by, sc), previous_records(by, sc)
        if not today and not peer:
            continue
        row = [
            sc,
            _cell(by.get((sc, "splatfacto"), [])),
            _cell(peer),
            _cell(today),
            _diff(today, peer),
            goal_cell(today, peer),
            _cell(prev) if sc in RESOLVED_AS else "= willags",
            _diff(today, prev) if sc in RESOLVED_AS else "+0.00",
        ]
        row += [_cell(by.get((sc, c), [])) for c in cands]
        out.append("| " + " | ".join(row) + " |")
    return out


def mask_rows(records: list[dict[str, Any]]) -> list[str]:
    """Per real scene and configuration: what the transient mask flagged of the subject (liberty's statue) and of the
    static observations, as training used the mask and for the perceptual mask alone (range over the runs)."""
    by = _grid(records)
    out = [
        "| scene | configuration | runs | subject masked (used) | perceptual alone | static observations masked (used) "
        "| perceptual alone |",
        "|---|---|---|---|---|---|---|",
    ]
    for sc in REAL_SCENES:
        groups = [("willags (today)", today_records(by, sc))]
        if sc in RESOLVED_AS:
            groups.append(("mask + skyline sky", previous_records(by, sc)))
        groups += [(c, by.get((sc, c), [])) for c in ("willags-skyalpha", "willags-skyalpha-support")]
        for name, recs in groups:
            if not recs:
                continue
            measured = [r for r in recs if r.get("static_obs_masked") is not None]
            if not measured:
                masked = "no mask: nothing flagged" if all(_mask_off(r) for r in recs) else "not measured"
                out.append(f"| {sc} | {name} | {len(recs)} | {masked} | | | |")
                continue
            out.append(
                f"| {sc} | {name} | {len(measured)} | {_share(measured, 'subject_masked')} | "
                f"{_share(measured, 'subject_masked_perceptual')} | {_share(measured, 'static_obs_masked')} | "
                f"{_share(measured, 'static_obs_masked_perceptual')} |"
            )
    return out if len(out) > 2 else []


def every_scene_section(records: list[dict[str, Any]]) -> list[str]:
    """Markdown of the section (empty without fidelity records of a real scene)."""
    rows = sky_rows(records)
    if len(rows) <= 2:
        return []
    return [
        "## Every real scene, liberty included: the default, the peer, the sky candidates (5000 steps)",
        "",
        "Right-half PSNR (NeRF-W protocol), splatfacto's stock schedule (1/4 resolution to step 3000, 1/2 to 5000, "
        "scored at full), mean ±half the range over seeds (n runs), fidelity-grid records (runs "
        "shared one GPU). **willags**: what the default trains after inspecting the scene (liberty: no mask, the sky "
        "behind every pixel with the alpha penalty, i.e. `willags-skyalpha-nomask`'s model; the other scenes: as "
        "before, their inspector decisions did not move). **mask + skyline sky**: liberty's `willags` runs before the "
        f"surround sky and the colour-twin transient test ({INSPECTOR_SINCE}). Decisions: docs/inspect.md. Command: "
        "`GRID=configs/benchmark_gpu_fidelity.json bash benchmarks/remote/grid.sh start "
        '"liberty:willags:<tag>:42 ..."`.',
        "",
        *rows,
        "",
        "### What the transient mask flags: the subject and the static observations (goal <= 2 % each)",
        "",
        "**Subject masked**: the share of liberty's statue (`masks_subject/`, evaluation only) that each training "
        "photo's last mask flags, pooled (`benchmarks/child.py` subject_masked_scores). **Static observations "
        "masked**: keypoints of SfM points that >= 5 training photos see, flagged by the mask "
        "(`static_observation_scores`). **used**: the mask training applied (with the SfM-track safeguard where on); "
        "**perceptual alone**: before the safeguard.",
        "",
        *mask_rows(records),
        "",
    ]
