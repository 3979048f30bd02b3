"""docs/benchmarks.md, section "Every scene at once": the default, willags-auto and each candidate default
beside splatfacto and the peer on every shared scene, 5000 steps, and the mask's "static observations masked".

A default is decided on every real scene and the fox scenes at once, with 2 seeds: this table is where that decision
is read. It pools the fidelity grid's 5000-step records of every GPU (tags h100-r*, h200-r*).
"""

from __future__ import annotations

from typing import Any

from benchmarks.fidelity_tables import _signed
from benchmarks.methods import AUTO_DEFAULT_SINCE, AUTO_SAME_SINCE

TAGS = ("h100-r", "h200-r")
"""Tag prefixes of the fidelity grid's repeats (configs/benchmark_gpu_fidelity.json), on H100s and H200s."""
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
CANDIDATES = (
    "willags-skyopen",
    "willags-support",
    "willags-skyalpha-support",
    "willags-sky",
    "willags-skyalpha",
    "willags-auto-support",
)
"""Candidate defaults (the sky and the safeguard, alone and together), in the order they are shown (those with no record are left out)."""
NO_KEYPOINTS = ("fox-clean", "fox-appearance-only", "fox-transient-only", "fox-wild")
"""Scenes without COLMAP keypoints (nerfstudio transforms.json): the default's sky (above the SfM skyline) and the
mask's safeguard are off there, so the default trains exactly as the model without both (tests/test_train.py) and
that model's records stand for it."""
DEFAULT_SINCE = AUTO_SAME_SINCE
"""Records of `willags` and `willags-auto` dated from here on (the time of commit 7bf8eff; a record is dated when its run starts) are of today's default: the sky above
the skyline and the mask's safeguard, and willags-inspect's transient threshold 0.12. Earlier ones are of the model
without both (no sky, no safeguard; threshold 0.2)."""
SAME_AS_DEFAULT = ("willags-skyopen-support",)
"""Methods whose settings are today's default, named in full (benchmarks/methods.py)."""
SAME_AS_PREVIOUS = ("willags-prev",)
"""Methods whose settings are the default without the sky and the safeguard, named in full."""
AUTO_UNCHANGED = {
    "reichstag": ("willags-auto-skyopen-support",),  # transient score 0.09: mask off under 0.2 and 0.12
    "south-building": ("willags-auto",),  # score 0.02, open background 0.04: mask and sky off, before and now
    **{sc: ("willags-auto",) for sc in NO_KEYPOINTS},  # same mask decision under both thresholds, no keypoints
}
"""Per scene, records that were made before the change with exactly today's willags-auto settings (the inspector's
decision there did not move): they count as willags-auto. sacre-coeur-mini (score 0.17) has only today's runs."""
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


def _today(r: dict[str, Any]) -> bool:
    return str(r.get("date", "")) >= DEFAULT_SINCE


def _inspects(r: dict[str, Any]) -> bool:
    """A `willags` record of the default that inspects the scene first (dated from benchmarks.methods
    AUTO_DEFAULT_SINCE on; an undated one is older): the configuration this table calls willags-auto."""
    return r.get("method") == "willags" and str(r.get("date") or "") >= AUTO_DEFAULT_SINCE


def default_records(by: dict[tuple[str, str], list[dict[str, Any]]], scene: str) -> list[dict[str, Any]]:
    """Records of today's default on `scene`: `willags` since the change (every `willags` record on a scene without
    keypoints, where nothing changed) and the methods named in full with its settings."""
    recs = [r for r in by.get((scene, "willags"), []) if (_today(r) or scene in NO_KEYPOINTS) and not _inspects(r)]
    return recs + [r for m in SAME_AS_DEFAULT for r in by.get((scene, m), [])]


def previous_records(by: dict[tuple[str, str], list[dict[str, Any]]], scene: str) -> list[dict[str, Any]]:
    """Records of the default without the sky and the safeguard on `scene`."""
    recs = [r for r in by.get((scene, "willags"), []) if not _today(r)]
    return recs + [r for m in SAME_AS_PREVIOUS for r in by.get((scene, m), [])]


def auto_records(by: dict[tuple[str, str], list[dict[str, Any]]], scene: str) -> list[dict[str, Any]]:
    """Records of today's willags-auto on `scene` (AUTO_UNCHANGED: earlier records with today's settings)."""
    recs = [r for r in by.get((scene, "willags-auto"), []) if _today(r)]
    recs += [r for r in by.get((scene, "willags"), []) if _inspects(r)]  # the default since it inspects the scene
    for m in AUTO_UNCHANGED.get(scene, ()):
        recs += [r for r in by.get((scene, m), []) if m != "willags-auto" or not _today(r)]
    return recs


def scene_rows(records: list[dict[str, Any]]) -> list[str]:
    """The table: per scene, splatfacto / peer / today's default / the default without sky and safeguard / willags-auto / candidates,
    with the differences that decide."""
    by = _grid(records)
    cands = [c for c in CANDIDATES if any(k[1] == c for k in by)]
    head = (
        "| scene | splatfacto | peer | **willags** | willags − peer | no sky, no safeguard | sky + safeguard gain | "
        "willags-auto | auto − willags | " + " | ".join(f"{c} | − willags" for c in cands)
    )
    out = [head.rstrip(" |") + " |", "|" + "---|" * (9 + 2 * len(cands))]
    for sc in SCENES:

        def get(m: str, sc: str = sc) -> list[dict[str, Any]]:
            return by.get((sc, m), [])

        default, previous = default_records(by, sc), previous_records(by, sc)
        if not default and not previous and not get("peer"):
            continue
        auto = auto_records(by, sc)
        row = [
            sc,
            _cell(get("splatfacto")),
            _cell(get("peer")),
            _cell(default),
            _diff(default, get("peer")),
            _cell(previous),
            _diff(default, previous),
            _cell(auto),
            _diff(auto, default),
        ]
        for c in cands:
            row += [_cell(get(c)), _diff(get(c), default)]
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
            f"| {r['scene']} | {r['method']} | {r['device']} {r['steps']} steps ({r.get('tag') or ''}, "
            f"{r.get('commit') or '?'}) | "
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
        "## Every scene at once: the default, willags-auto and candidate defaults, 5000 steps",
        "",
        "**willags** here is the full model (`willags-full` since the default inspects the scene first: its `willags` "
        f"records from {AUTO_DEFAULT_SINCE} on count as willags-auto): the sky above each photo's SfM skyline and "
        "the mask's safeguard (since "
        f"commit 7bf8eff: `willags` records from {DEFAULT_SINCE}, and `willags-skyopen-support`); on the fox scenes, "
        "which have no COLMAP keypoints, it is exactly the model without them (tests/test_train.py), whose records count. "
        "**no sky, no safeguard**: `willags` records before the change, and `willags-prev`. **willags-auto**: "
        "today's (transient threshold 0.12), with the earlier records whose settings it repeats (reichstag: "
        "`willags-auto-skyopen-support`; south-building and the fox scenes: `willags-auto`, whose inspector decision "
        "did not move): the default `willags` since it was decided here (docs/design.md, the model).",
        "",
        "Right-half PSNR (NeRF-W protocol), splatfacto's stock schedule, mean ±half the range over seeds (n runs, "
        "seeds 42-47), every fidelity-grid record (H100 tags h100-r*, H200 tags h200-r*; runs shared "
        "one GPU). splatfacto and the peer are run by this harness (`benchmarks/peer.py`). A candidate becomes the "
        "default only when it is not worse on any scene beyond the seed spread; † marks records whose tree was not "
        "exactly their commit (`tree_note` in benchmarks/records/benchmarks.json). Decisions and their reasons: "
        "docs/design.md.",
        "",
        *scene_rows(records),
        *static_obs_rows(records),
        "",
    ]
