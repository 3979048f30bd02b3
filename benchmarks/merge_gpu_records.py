"""Merge the JSON that GPU runs brought back (benchmarks/records/gpu_runs/*.json, written by benchmarks/train_eval.py
and benchmarks/gpu_suite.py on a lent GPU) into benchmarks/records/benchmarks.json, and regenerate
docs/benchmarks.md.

    python -m benchmarks merge-gpu

Records are taken as the scripts wrote them; this adds only provenance (command, machine, tag, status).
"""

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.records import GPU_RUNS, RECORDS, load_records, merge_records  # noqa: E402
from benchmarks.tables import write_outputs  # noqa: E402

COMMANDS = {
    "train_eval": "python3 benchmarks/train_eval.py --scene <scene> --methods <method> --steps <steps> --protocol-steps 128",
    "gpu_suite": "python3 benchmarks/gpu_suite.py --all --time-budget 500 --json-out gpu_suite.json",
}


def normalise(rec: dict, source: str) -> dict:
    rec = dict(rec)
    kind = "gpu_suite" if {"step_ms", "parity_fwd_rel_err", "render_fps_ratio_vs_gsplat"} & rec.keys() else "train_eval"
    rec.setdefault("status", "error" if "error" in rec else "ok")
    rec.setdefault("machine", f"1x {rec.get('device', 'GPU')} (lent), torch 2.11 cu130, gsplat 1.4.0 (JIT)")
    rec.setdefault("command", COMMANDS[kind])
    rec.setdefault("date", "2026-11-22")
    rec.setdefault("tag", f"gpu-{kind}")
    rec.setdefault("schedule", "default")
    rec["source_file"] = source
    if kind == "gpu_suite":
        rec.setdefault("steps", 0)
    return rec


def main() -> None:
    runs = sorted(GPU_RUNS.glob("*.json"))
    new = []
    for p in runs:
        if p.name.endswith("_details.json"):
            continue
        data = json.loads(p.read_text())
        rows = data if isinstance(data, list) else [data]
        # diagnoses and profiles live beside the records (a "what" and their own fields): not benchmark records
        new.extend(normalise(r, p.name) for r in rows if "error" not in r and "scene" in r)
    records = merge_records(load_records(RECORDS), new)
    js, md = write_outputs(records, RECORDS.with_suffix(""))
    print(f"merged {len(new)} GPU records from {len(runs)} files -> {js}, {md}")


if __name__ == "__main__":
    main()
