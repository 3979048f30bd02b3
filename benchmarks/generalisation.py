"""docs/benchmarks.md, section "Every scene at once" (issue 26): the default, willags-auto and each candidate default
beside splatfacto and the peer on every shared scene, 5000 steps, and the mask's "static observations masked".

A default is decided on every real scene and the fox scenes at once, with 2 seeds: this table is where that decision
is read. It pools the fidelity grid's 5000-step records of every session (tags h100-r*, h200-r*).
"""

from __future__ import annotations

from typing import Any

from benchmarks.fidelity_tables import _signed

TAGS = ("h100-r", "h200-r")
"""Tag prefixes of the fidelity grid's repeats (configs/benchmark_gpu_fidelity.json), H100 and H200 sessions."""
SCENES = (
    "reichstag",
    "sacre-coeur-mini",
    "south-building",
    "fox-clean",
    "fox-appearance-only",
    "fox-transient-only",
    "fox-wild",
)
REAL = ("reichstag", "sacre-coeur-mini", "south-building")
CANDIDATES = ("willags-skyalpha-support", "willags-sky", "willags-skyalpha", "willags-support")
"""Candidate defaults of issue 26, in the order they are shown (those with no record are left out)."""
STATIC_OBS_MIN_TRACK = 5


def _grid(records: list[dict[str, Any]]) -> dict[tuple[str, str], list[dict[str, Any]]]:
    by: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in records:
        if (
            r.get("steps") == 5000
            and r.get("status", "ok") == "ok"
            and r.get("psnr") is not None
            and str(r.get("tag", "")).startswith(TAGS)
        ):
            by.setdefault((r["scene"], r["method"]), []).append(r)
    return by


def _mean(vals: list[float]) -> float | None:
    return sum(vals) / len(vals) if vals else None


def _cell(recs: list[dict[str, Any]]) -> str:
    """mean ±half-range (n), a dagger when a record carries a tree note (its tree was not exactly its commit)."""
    vals = [float(r["psnr"]) for r in recs]
    if not vals:
        return "–"
    note = "†" if any(r.get("tree_note") for r in recs) else ""
    m = _mean(vals)
    if len(vals) == 1:
        return f"{m:.2f}{note} (n=1)"
    return f"{m:.2f} ±{(max(vals) - min(vals)) / 2:.2f}{note} (n={len(vals)})"


def _diff(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> str:
    ma, mb = _mean([float(r["psnr"]) for r in a]), _mean([float(r["psnr"]) for r in b])
    return "–" if ma is None or mb is None else _signed(ma - mb)


def scene_rows(records: list[dict[str, Any]]) -> list[str]:
    """The table: per scene, splatfacto / peer / default / auto / candidates, with the differences that decide."""
    by = _grid(records)
    cands = [c for c in CANDIDATES if any(k[1] == c for k in by)]
    head = "| scene | splatfacto | peer | **willags** | willags − peer | willags-auto | auto − willags | " + " | ".join(
        f"{c} | − willags" for c in cands
    )
    out = [head + " |", "|" + "---|" * (7 + 2 * len(cands))]
    for sc in SCENES:

        def get(m: str, sc: str = sc) -> list[dict[str, Any]]:
            return by.get((sc, m), [])

        if not get("willags") and not get("peer"):
            continue
        row = [
            sc,
            _cell(get("splatfacto")),
            _cell(get("peer")),
            _cell(get("willags")),
            _diff(get("willags"), get("peer")),
            _cell(get("willags-auto")),
            _diff(get("willags-auto"), get("willags")),
        ]
        for c in cands:
            row += [_cell(get(c)), _diff(get(c), get("willags"))]
        out.append("| " + " | ".join(row) + " |")
    return out


def static_obs_rows(records: list[dict[str, Any]]) -> list[str]:
    """Per real scene and method: the share of static observations the mask flags, as training used the mask and
    for the perceptual mask alone (every record that measured it)."""
    rows = []
    for r in sorted(records, key=lambda r: (r["scene"], r["device"], r["method"], str(r.get("tag")))):
        if r.get("static_obs_masked") is None or r["scene"] not in REAL:
            continue
        rows.append(
            f"| {r['scene']} | {r['method']} | {r['device']} {r['steps']} steps ({r.get('tag') or ''}) | "
            f"{100 * r['static_obs_masked']:.2f} % | {100 * r['static_obs_masked_perceptual']:.2f} % | "
            f"{r['static_obs_count']} in {r['static_obs_images']} images |"
        )
    if not rows:
        return []
    return [
        "",
        "### Static observations masked (goal <= 2 % on every real scene)",
        "",
        f"Observations (keypoints) in the training images of SfM points that >= {STATIC_OBS_MIN_TRACK} training images "
        "see: each shows static scene, so the share that an image's last transient mask flags should be 0 "
        "(`harness.static_observation_scores`). **used**: the mask training applied; **perceptual alone**: before "
        "the SfM-track safeguard (the same where the safeguard is off).",
        "",
        "| scene | method | run | used | perceptual alone | observations |",
        "|---|---|---|---|---|---|",
        *rows,
    ]


def generalisation_section(records: list[dict[str, Any]]) -> list[str]:
    """Markdown of the section (empty without fidelity records)."""
    if not _grid(records):
        return []
    return [
        "## Every scene at once (issue 26): the default, willags-auto and candidate defaults, 5000 steps",
        "",
        "Right-half PSNR (NeRF-W protocol), splatfacto's stock schedule, mean ±half the range over seeds (n runs, "
        "seeds 42-47), every fidelity-grid record of every session (H100 tags h100-r*, H200 tags h200-r*; runs shared "
        "one GPU). splatfacto and the peer are run by this harness (`benchmarks/peer.py`). A candidate becomes the "
        "default only when it is not worse on any scene beyond the seed spread; † marks records whose tree was not "
        "exactly their commit (`tree_note` in docs/benchmarks.json). Decisions and their reasons: "
        "docs/fidelity.md, section of the eighth session.",
        "",
        *scene_rows(records),
        *static_obs_rows(records),
        "",
    ]
