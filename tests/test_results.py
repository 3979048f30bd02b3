"""benchmarks/results.py: docs/results.md and README.md's results table come from the records, and are up to date."""

import pytest

from benchmarks import results


def _rec(scene: str, method: str, psnr: float, seed: int, steps: int = 15000, **kw) -> dict:
    """A record of the side-by-side grid: a run scored at `steps` (its milestone)."""
    rec = {
        "scene": scene,
        "method": method,
        "device": "cuda",
        "steps": steps,
        "tag": "h200x4" if seed == 42 else f"h200x4-s{seed}",
        "seed": seed,
        "psnr": psnr,
        "milestones": {str(steps): {"psnr": psnr, "train_s": 100.0}},
        "status": "ok",
        "date": "2030-01-01T00:00:00",  # after every cut-off date of the selections: today's default
        "protocol_steps": 128,
        "num_train_images": 54,
        "num_images": 8,
    }
    return {**rec, **kw}


def test_headline_row_means_margin_over_the_stronger_peer_and_goal():
    records = [
        _rec("reichstag", "peer", 19.0, 42),
        _rec("reichstag", "peer", 19.4, 43),
        _rec("reichstag", "peer-full", 18.0, 42),
        _rec("reichstag", "willags-noprior", 20.0, 42),
        _rec("reichstag", "willags-noprior", 20.6, 43),
        _rec("reichstag", "willags-noprior", 25.0, 44, tag="h100-r44"),  # another grid: not side by side
        _rec("reichstag", "willags", 30.0, 42),  # not the configuration the grid trained as its default
    ]
    head, rule, row = results.headline_rows(records)
    assert head.startswith("| scene | steps | peer | peer-full | **willags-noprior** |") and rule.startswith("|---|")
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells == [
        "reichstag (real photos: 54 train / 8 test)",
        "15k",
        "19.20 ±0.20 (n=2)",
        "18.00 (n=1)",
        "20.30 ±0.30 (n=2)",
        "+1.10",
        "met",
    ]
    records[3]["milestones"]["15000"]["psnr"] = 19.4  # willags' mean 20.0: 0.2 short of the stronger peer + 1 dB
    assert results.headline_rows(records)[2].endswith("| +0.80 | missed by 0.20 |")
    records += [_rec("reichstag", "peer-full", 21.0, 43)]  # now the full peer is the stronger one (19.5 vs 19.2)
    assert results.headline_rows(records)[2].endswith("| +0.50 | missed by 0.50 |")


def test_equal_time_reads_each_method_at_the_defaults_time():
    ms = lambda *pts: {str(s): {"psnr": p, "train_s": t} for s, t, p in pts}  # noqa: E731
    records = [
        _rec("reichstag", "willags-noprior", 19.0, 42, milestones=ms((5000, 100.0, 18.0), (15000, 300.0, 19.0))),
        _rec("reichstag", "peer-full", 18.0, 42, milestones=ms((5000, 200.0, 17.0), (10000, 400.0, 18.0))),
        _rec("reichstag", "peer", 18.0, 42, milestones=ms((5000, 400.0, 18.0))),  # not at 300 s yet
    ]
    rows = results.equal_time_rows(records)
    cells = [c.strip() for c in rows[2].strip("|").split("|")]
    assert cells == ["reichstag", "300 s", "–", "17.50 (7.5k steps, n=1)", "19.00 (15.0k steps, n=1)"]


def test_readme_block_is_replaced_between_its_markers():
    text = f"intro\n{results.README_BEGIN}\nold table\n{results.README_END}\noutro\n"
    out = results.with_readme_block(text, f"{results.README_BEGIN}\nnew\n{results.README_END}")
    assert out == f"intro\n{results.README_BEGIN}\nnew\n{results.README_END}\noutro\n"
    with pytest.raises(SystemExit, match="no generated results block"):
        results.with_readme_block("no markers here", "x")


def test_readmes_table_is_the_cross_validated_default_against_the_peers():
    """README's table: per collection the default (two seeds averaged photo by photo) against the peer, with the
    interval and the goal, from the fold runs; a fold record relabelled `willags` by its configuration counts as
    the default, one of another configuration does not."""
    ps = lambda base: [{"image": f"p{i}.jpg", "psnr": base + 0.1 * i} for i in range(4)]  # noqa: E731

    def fold(k, method, base, seed=42, **kw):
        ms = {"15000": {"psnr": base, "per_image": [{**p, "image": f"f{k}{p['image']}"} for p in ps(base)]}}
        return {"scene": f"lund-cv{k}of2", "method": method, "device": "cuda", "steps": 15000, "seed": seed,
                "tag": "t", "status": "ok", "milestones": ms, **kw}  # fmt: skip

    records = [fold(k, "peer", 15.0) for k in (1, 2)]
    records += [fold(k, "willags-prior-low", 17.0, configuration="willags") for k in (1, 2)]
    records += [fold(k, "willags", 18.0, seed=43) for k in (1, 2)]
    records += [fold(k, "willags", 30.0, configuration="willags-noprior") for k in (1, 2)]
    block = results.readme_block(records).splitlines()
    assert block[0] == results.README_BEGIN and block[-1] == results.README_END
    cells = [c.strip() for c in block[3].strip("|").split("|")]
    assert cells[:7] == ["lund", "15k", "2", "8", "15.15", "–", "17.65"]  # README keeps the fold means out
    assert cells[7].startswith("peer: +2.50 [") and cells[8] == "met"


def test_the_generated_pages_match_the_records():
    """docs/results.md and README.md's table are what the records give: rerun `python -m benchmarks.results` after
    merging records."""
    assert results.main(["--check"]) == 0
