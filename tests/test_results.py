"""benchmarks/results.py: docs/results.md and README.md's results table come from the records, and are up to date."""

import pytest

from benchmarks import results


def _rec(scene: str, method: str, psnr: float, seed: int, **kw) -> dict:
    rec = {
        "scene": scene,
        "method": method,
        "device": "cuda",
        "steps": 5000,
        "tag": f"h100-r{seed}",
        "seed": seed,
        "psnr": psnr,
        "status": "ok",
        "date": "2030-01-01T00:00:00",  # after every cut-off date of the selections: today's default
        "protocol_steps": 128,
        "num_train_images": 54,
        "num_images": 8,
    }
    return {**rec, **kw}


def test_headline_row_means_margin_and_goal():
    records = [
        _rec("reichstag", "peer", 19.0, 42),
        _rec("reichstag", "peer", 19.4, 43),
        _rec("reichstag", "willags", 20.0, 42),
        _rec("reichstag", "willags", 20.6, 43),
        _rec("reichstag", "splatfacto", 15.0, 42),
    ]
    head, rule, row = results.headline_rows(records)
    assert head.startswith("| scene | splatfacto | peer | **willags** |") and rule.startswith("|---|")
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells == [
        "reichstag (real photos: 54 train / 8 test)",
        "15.00 (n=1)",
        "19.20 ±0.20 (n=2)",
        "20.30 ±0.30 (n=2)",
        "+1.10",
        "met",
    ]
    records[2]["psnr"] = 19.4  # willags' mean 20.0: 0.2 short of the peer + 1 dB
    assert results.headline_rows(records)[2].endswith("| +0.80 | missed by 0.20 |")


def test_readme_block_is_replaced_between_its_markers():
    text = f"intro\n{results.README_BEGIN}\nold table\n{results.README_END}\noutro\n"
    out = results.with_readme_block(text, f"{results.README_BEGIN}\nnew\n{results.README_END}")
    assert out == f"intro\n{results.README_BEGIN}\nnew\n{results.README_END}\noutro\n"
    with pytest.raises(SystemExit, match="no generated results block"):
        results.with_readme_block("no markers here", "x")


def test_the_generated_pages_match_the_records():
    """docs/results.md and README.md's table are what the records give: rerun `python -m benchmarks.results` after
    merging records."""
    assert results.main(["--check"]) == 0
