"""benchmarks/__main__.py: one entry point, `python -m benchmarks <verb>`, dispatching to each module's main."""

import json

from benchmarks.__main__ import VERBS, main


def _rec(method: str, psnr: float) -> dict:
    return {
        "scene": "fox-wild", "method": method, "device": "cpu", "steps": 300, "tag": "ds2", "psnr": psnr,
        "ssim": 0.5, "lpips": None, "full_psnr": psnr, "encoder_psnr": psnr, "train_s": 100.0, "s_per_step": 0.3,
        "fps": 10.0, "num_gaussians": 1234, "peak_mem_gb": 1.5, "status": "ok", "date": "2026-01-02T03:04:05",
        "command": "python -m benchmarks run --grid g.json", "machine": "2 CPU cores", "schedule": "short",
        "protocol_steps": 32, "image_hw": [240, 135], "num_train_images": 58, "num_images": 4.0,
    }  # fmt: skip


def test_merge_verb_merges_records_and_writes_the_tables(tmp_path):
    out = tmp_path / "b"
    out.with_suffix(".json").write_text(json.dumps([_rec("willags", 20.0)]))
    fetched = tmp_path / "fetched.json"
    fetched.write_text(json.dumps([_rec("willags", 21.0), _rec("willags-lite", 19.0)]))

    assert main(["merge", str(fetched), "--out", str(out)]) == 0

    recs = json.loads(out.with_suffix(".json").read_text())
    assert sorted((r["method"], r["psnr"]) for r in recs) == [
        ("willags", 21.0),
        ("willags-lite", 19.0),
    ]  # same key replaced
    assert "| willags" in out.with_suffix(".md").read_text()


def test_unknown_verb_and_bare_call_name_the_verbs(capsys):
    assert main(["nope"]) == 2
    err = capsys.readouterr().err
    assert "unknown verb 'nope'" in err and "report" in err
    assert main([]) == 2
    out = capsys.readouterr().out
    assert [v for v in VERBS if f"  {v} " not in out] == []


def test_report_takes_no_options(capsys):
    assert main(["report", "--records", "x.json"]) == 2
    assert "takes no options" in capsys.readouterr().err


def test_every_verb_names_a_module_with_a_main():
    import importlib

    for verb, (module, _) in VERBS.items():
        if verb != "report":
            assert callable(importlib.import_module(f"benchmarks.{module}").main), verb
