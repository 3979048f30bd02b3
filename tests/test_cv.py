"""benchmarks/cv.py: folds that hold every photo once, paired differences with bootstrap intervals, the queues."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import cv
from benchmarks.long_run import per_image_scores
from tests.conftest import SHARED_DATA

SACRE = SHARED_DATA / "sacre-coeur-mini"


def test_assign_folds_puts_every_photo_in_one_fold_of_near_equal_size():
    names = [f"img_{i:03d}.jpg" for i in range(23)][::-1]
    folds = cv.assign_folds(names, 4)
    assert sorted(folds) == sorted(names)
    sizes = np.bincount(list(folds.values()))[1:]
    assert len(sizes) == 4 and sizes.max() - sizes.min() <= 1
    assert folds["img_000.jpg"] == 1 and folds["img_001.jpg"] == 2 and folds["img_004.jpg"] == 1  # by name order
    with pytest.raises(ValueError, match="at least 2 folds"):
        cv.assign_folds(names, 1)
    with pytest.raises(ValueError, match="cannot fill"):
        cv.assign_folds(names[:3], 4)


def test_fold_names_parse_back_and_other_scenes_are_not_folds():
    assert cv.parse_fold(cv.fold_name("sacre-coeur-mini", 3, 7)) == ("sacre-coeur-mini", 3, 7)
    assert cv.parse_fold("reichstag") is None
    assert cv.parse_fold("reichstag-cv5of4") is None  # a fold beyond the count


@pytest.mark.skipif(not SACRE.is_dir(), reason="needs ../shared/data/sacre-coeur-mini")
def test_fold_scenes_test_each_registered_photo_once_through_the_data_parser(tmp_path):
    from willags_ns.data.dataparser import WillagsDataParserConfig

    folds = cv.write_fold_scenes(SACRE, 4, tmp_path)
    assert [d.name for d in folds] == [f"sacre-coeur-mini-cv{k}of4" for k in range(1, 5)]
    tested: list[str] = []
    for d in folds:
        assert (d / "images").is_symlink() and not (d / "README.md").exists()
        assert [p.name for p in d.glob("*.tsv")] == [f"{d.name}.tsv"]  # the collection's own split is not linked
        parser = WillagsDataParserConfig(data=d).setup()
        test = [Path(p).name for p in parser.get_dataparser_outputs("test").image_filenames]
        train = [Path(p).name for p in parser.get_dataparser_outputs("train").image_filenames]
        assert not set(test) & set(train) and len(test) + len(train) == 14
        tested += test
    assert sorted(tested) == sorted(p.name for p in (SACRE / "images").iterdir())
    # the links are relative: the collection and its folds move together
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / SACRE.name).symlink_to(SACRE)
    again = cv.write_fold_scenes(moved / SACRE.name, 4, moved)
    assert not Path((again[0] / "images").readlink()).is_absolute()
    with open(again[0] / f"{again[0].name}.tsv") as f:
        rows = list(csv.DictReader(f, delimiter="\t"))
    assert {r["split"] for r in rows} == {"train", "test"} and len(rows) == 14


def test_bootstrap_interval_brackets_the_mean_and_narrows_with_more_photos():
    assert cv.bootstrap_interval([0.5] * 10) == (0.5, 0.5, 0.5)
    rng = np.random.default_rng(1)
    small = rng.normal(0.3, 1.0, 16)
    big = rng.normal(0.3, 1.0, 400)
    m, lo, hi = cv.bootstrap_interval(small)
    assert lo < m < hi and m == pytest.approx(small.mean())
    m2, lo2, hi2 = cv.bootstrap_interval(big)
    assert hi2 - lo2 < (hi - lo) / 3
    assert hi2 - lo2 == pytest.approx(2 * 1.96 * big.std() / np.sqrt(big.size), rel=0.15)  # the normal interval
    assert cv.bootstrap_interval(small) == (m, lo, hi)  # seeded: the tables regenerate identically
    with pytest.raises(ValueError):
        cv.bootstrap_interval([])


def _fold_rec(scene: str, fold: int, folds: int, method: str, scores: dict[str, float], steps: int = 5000) -> dict:
    per = [{"image": k, "psnr": v} for k, v in scores.items()]
    return {
        "scene": cv.fold_name(scene, fold, folds),
        "method": method,
        "device": "cuda",
        "steps": steps,
        "tag": "cv-test",
        "seed": 42,
        "status": "ok",
        "milestones": {str(steps): {"psnr": float(np.mean(list(scores.values()))), "per_image": per}},
    }


def _records(shift: float, folds_of_b: int = 2) -> list[dict]:
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}
    recs = [_fold_rec("scene", k, 2, "willags", p) for k, p in photos.items()]
    recs += [
        _fold_rec("scene", k, 2, "peer", {n: v - shift for n, v in p.items()})
        for k, p in photos.items()
        if k <= folds_of_b
    ]
    recs.append(_fold_rec("scene", 1, 2, "peer", {"a.jpg": 99.0}, steps=15000))  # another step count
    recs.append({**_fold_rec("reichstag", 1, 2, "peer", {"x.jpg": 1.0}), "status": "failed"})
    return recs


def _on(collection: str, recs: list[dict]) -> list[dict]:
    """_records' runs of "scene" as runs of `collection`."""
    return [{**r, "scene": r["scene"].replace("scene-", f"{collection}-", 1)} for r in recs]


def test_collect_pairs_each_photo_across_folds_and_methods():
    by = cv.collect(_records(1.5), 5000)
    assert set(by) == {"scene"} and set(by["scene"]) == {"willags", "peer"}
    w, p = by["scene"]["willags"], by["scene"]["peer"]
    assert w.per_photo == {"a.jpg": 20.0, "c.jpg": 22.0, "b.jpg": 18.0, "d.jpg": 24.0}
    assert w.fold_means == {1: 21.0, 2: 21.0} and w.complete and w.mean == 21.0
    assert cv.paired(w, p) == (pytest.approx(1.5), pytest.approx(1.5), pytest.approx(1.5), 4)
    assert cv.goal_cell(w, p) == "met"
    low = cv.collect(_records(0.7), 5000)["scene"]
    assert cv.goal_cell(low["willags"], low["peer"]) == "missed by 0.30"
    assert cv.collect(_records(1.5), 15000)["scene"]["peer"].per_photo == {"a.jpg": 99.0}


def test_capacity_rows_average_each_methods_training_fit_and_gaussians_per_collection():
    """Per collection the mean over the method's fold runs of the training photos' PSNR and of its Gaussians at that
    step; runs without either, failed runs, other step counts and scenes that are not folds do not count."""
    recs = _records(0.5)
    fits = ((25.0, 300_000), (27.0, 100_000), (30.0, 450_000), (32.0, 450_000))
    for rec, (fit, n) in zip(recs[:4], fits, strict=True):
        rec["milestones"]["5000"].update(train_psnr=fit, num_gaussians=n)
    recs.append({**_fold_rec("scene", 1, 2, "peer", {"a.jpg": 1.0}), "status": "failed"})
    recs[-1]["milestones"]["5000"].update(train_psnr=99.0, num_gaussians=1)
    recs.append({**_fold_rec("other", 1, 2, "willags", {"x.jpg": 1.0}), "scene": "other"})  # not a fold
    recs[-1]["milestones"]["5000"].update(train_psnr=99.0, num_gaussians=1)
    head, rows = cv.capacity_rows(recs, 5000)
    assert head == ["method", "scene"]
    assert rows == [["willags", "26.0 / 200k"], ["peer", "31.0 / 450k"]]
    assert cv.capacity_rows(recs, 15000) == (["method"], [])  # the 15000-step record has neither
    table = cv.cv_rows(recs, 5000)
    assert "| willags | 26.0 / 200k |" in table and "| peer | 31.0 / 450k |" in table


def test_cv_rows_give_means_fold_means_intervals_and_say_what_is_missing():
    noise, _, head, _, row = cv.cv_rows(_records(0.5, folds_of_b=1), 5000)
    assert noise.startswith("Run noise: no replicate pair yet")
    assert "willags − stronger peer" in head
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:4] == ["scene", "5k", "2", "4"]
    assert cells[4] == "20.50 (20.50; 1 of 2 folds)"  # the peer's one fold
    assert cells[6] == "21.00 (21.00 / 21.00)"
    assert cells[7] == "peer: +0.50 [+0.50, +0.50] (n=2)"  # paired on the photos both scored
    assert cells[8] == "–"  # no goal on an incomplete cross-validation
    assert cv.cv_rows([], 5000) == ["No cross-validated run scored at 5000 steps yet."]


def test_plan_deals_every_run_once_by_priority_and_balances_the_queues():
    counts = {"a-cv1of2": 10, "a-cv2of2": 10, "b-cv1of2": 40, "b-cv2of2": 40}
    runs = cv.plan_runs(counts, ["willags", "peer", "willags-capscene"], 5000)
    qs = cv.balance(runs, 4)
    specs = [r.spec() for q in qs for r in q]
    assert sorted(specs) == sorted(r.spec() for r in runs) and len(specs) == 12
    for q in qs:
        assert [r.priority for r in q] == sorted(r.priority for r in q)  # the first methods first in every queue
    loads = [sum(r.cost for r in q) for q in qs]
    assert max(loads) - min(loads) <= max(r.cost for r in runs)
    assert all(s.endswith(":5000:42") for s in specs)
    grouped = cv.plan_runs(counts, ["willags,peer", "willags-capscene"], 5000)
    assert {r.method for r in grouped if r.priority == 0} == {"willags", "peer"}
    assert {r.method for r in grouped if r.priority == 1} == {"willags-capscene"}


def test_long_run_records_keep_each_photos_scores():
    per = [{"image": "a.jpg", "psnr": 20.0, "ssim": 0.5, "fit_scale": 2.0, "encoder_psnr": 10.0}]
    assert per_image_scores(per) == [{"image": "a.jpg", "psnr": 20.0, "ssim": 0.5}]


def test_run_noise_comes_from_replicates_and_widens_every_interval():
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}

    def runs(method, shift, seed=42, gaussians=1000):
        out = []
        for k, p in photos.items():
            rec = _fold_rec("scene", k, 2, method, {n: v + shift for n, v in p.items()})
            rec["seed"] = seed
            rec["tag"] = "cv-test" if seed == 42 else f"cv-test-s{seed}"
            rec["milestones"]["5000"]["num_gaussians"] = gaussians
            out.append(rec)
        return out

    records = runs("willags", 0.0) + runs("willags", 0.4, seed=43) + runs("peer", -1.0)
    records += runs("willags-noprior", 0.1)
    records += runs("willags-capscene", -0.1)  # the cap not reached: the same model as willags-noprior, a replicate
    diffs = {what: d for _, what, d in cv.replicate_differences(records, 5000)}
    assert diffs == {
        "willags seeds 43 - 42": pytest.approx(0.4),
        "willags-capscene - willags-noprior (seed 42, equal Gaussians)": pytest.approx(-0.2),
    }
    sigma, n = cv.run_noise(records, 5000)
    assert n == 2 and sigma == pytest.approx(np.sqrt((0.4**2 + 0.2**2) / 2 / 2))
    more = records[:-2] + runs("willags-capscene", -0.1, gaussians=5000)  # a larger model: not a replicate
    assert len(cv.replicate_differences(more, 5000)) == 1
    assert cv.run_noise(runs("willags", 0.0), 5000) == (None, 0)

    by = cv.collect(records, 5000)["scene"]
    w, p = by["willags"], by["peer"]
    assert w.seeds == 2 and p.seeds == 1 and w.mean == pytest.approx(21.2)  # two seeds averaged per photo
    mean, low, high, _ = cv.paired(w, p)
    assert (mean, low, high) == (pytest.approx(1.2), pytest.approx(1.2), pytest.approx(1.2))  # no spread over photos
    mean, low, high, _ = cv.paired(w, p, sigma)
    half = 1.96 * sigma * np.sqrt(1 / 2 + 1 / 1)
    assert (low, high) == (pytest.approx(1.2 - half), pytest.approx(1.2 + half))
    assert cv.cv_rows(records, 5000)[0].startswith(f"Run noise: sigma = {sigma:.2f} dB")


@pytest.mark.parametrize("rule", ["willags-prior-low-captransients", "willags-prior-low-captransients25"])
def test_replicates_are_runs_of_one_build_and_a_rule_that_kept_the_cap_is_one(rule):
    """Runs of one collection on two SfM builds are different scenes, never replicates; the transients cap rule's
    runs that kept MCMC's cap on every fold (the default's Gaussian count) replicate the default, at either bar."""
    photos = {1: {"a.jpg": 20.0}, 2: {"b.jpg": 18.0}}

    def runs(method, shift, build, seed=42, gaussians=300000):
        out = []
        for k, p in photos.items():
            rec = _fold_rec("scene", k, 2, method, {n: v + shift for n, v in p.items()})
            rec.update(seed=seed, scene_model_sha256=build)
            rec["milestones"]["5000"]["num_gaussians"] = gaussians
            out.append(rec)
        return out

    records = runs("willags", 0.0, "old") + runs("willags", 0.3, "new", seed=43)
    assert cv.replicate_differences(records, 5000) == []  # two builds: not the same model's seeds
    records += runs("willags", 0.1, "new") + runs(rule, -0.2, "new")
    diffs = {what: d for _, what, d in cv.replicate_differences(records, 5000)}
    assert diffs == {
        "willags seeds 43 - 42": pytest.approx(0.2),
        f"{rule} - willags (seed 42, equal Gaussians)": pytest.approx(-0.3),
    }
    grown = records[:-2] + runs(rule, -0.2, "new", gaussians=1000000)
    assert len(cv.replicate_differences(grown, 5000)) == 1  # the rule raised the cap: another model


def test_readout_compares_the_same_runs_under_a_variant_photo_by_photo():
    """`cv readout`: the default's runs under a protocol variant against their own scores, per collection and over
    the collections with every fold scored both ways; a run without the variant is left out, another method's
    variant is not read."""
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}
    records = []
    for scene, shifts in (("one", {"a.jpg": 0.5, "b.jpg": 0.5, "c.jpg": 0.3, "d.jpg": 0.3}), ("two", None)):
        for k, p in photos.items():
            rec = _fold_rec(scene, k, 2, "willags", p)
            if shifts is not None or k == 1:  # "two": only fold 1 scored under the variant
                delta = shifts or {n: -1.0 for n in p}
                per = [{"image": n, "psnr": v + delta[n]} for n, v in p.items()]
                rec["protocol_variants"] = {"rm": {"5000": {"psnr": 0.0, "per_image": per}}}
            records.append(rec)
    peer = _fold_rec("one", 1, 2, "peer", photos[1])
    peer["protocol_variants"] = {"rm": {"5000": {"psnr": 0.0, "per_image": [{"image": "a.jpg", "psnr": 99.0}]}}}
    lines = cv.readout_rows([*records, peer], 5000, "rm")
    one = next(line for line in lines if line.startswith("| one "))
    assert "| 2 of 2 | 21.00 | 21.40 | +0.40 [+0.30, +0.50] (n=4) |" in one
    two = next(line for line in lines if line.startswith("| two "))
    assert "| 1 of 2 |" in two and "-1.00 [-1.00, -1.00] (n=2)" in two
    assert not any("at once" in line for line in lines)  # one whole collection: nothing to pool
    per = [{"image": n, "psnr": v - 1.0} for n, v in photos[2].items()]
    records[3]["protocol_variants"] = {"rm": {"5000": {"psnr": 0.0, "per_image": per}}}  # "two", fold 2
    lines = cv.readout_rows(records, 5000, "rm")
    assert lines[-1].startswith("| **2 at once** |") and "-0.30 [" in lines[-1] and "(n=8)" in lines[-1]
    assert cv.readout_variants(records, 5000) == ["rm"]
    assert cv.readout_rows(records, 5000, "nothing")[0].startswith("cv: no fold run of willags")


def test_merge_puts_the_fold_runs_in_their_own_file(tmp_path, monkeypatch):
    import json

    from benchmarks import grid

    cv_file = tmp_path / "cv.json"
    monkeypatch.setattr(grid, "CV_RECORDS", cv_file)
    fresh = tmp_path / "fresh.json"
    plain = {**_fold_rec("x", 1, 2, "peer", {"a.jpg": 1.0}), "scene": "reichstag"}
    fresh.write_text(json.dumps([_fold_rec("scene", 1, 2, "willags", {"a.jpg": 20.0}), plain]))
    assert grid.main(["--out", str(tmp_path / "bench"), "--merge", str(fresh)]) == 0
    kept = json.loads((tmp_path / "bench.json").read_text())
    folds = json.loads(cv_file.read_text())
    assert [r["scene"] for r in kept] == ["reichstag"] and [r["scene"] for r in folds] == ["scene-cv1of2"]


def test_the_fit_table_sets_each_variant_beside_the_protocols_own_score_photo_by_photo():
    per = [{"image": "a.jpg", "psnr": 20.0}, {"image": "b.jpg", "psnr": 18.0}, {"image": "c.jpg", "psnr": 19.0}]
    longer = [{"image": "a.jpg", "psnr": 20.2}, {"image": "b.jpg", "psnr": 22.0}, {"image": "c.jpg", "psnr": 17.5}]
    rec = {
        "scene": "reichstag-cv1of4",
        "method": "willags",
        "seed": 43,
        "milestones": {"15000": {"psnr": 19.0, "per_image": per}},
        "protocol_variants": {
            "fit512": {
                "15000": {"protocol": {"steps": 512, "lr": 0.01, "oracle": False}, "psnr": 19.9, "per_image": longer}
            }
        },
    }
    (row,) = [
        line for line in cv.fit_rows([rec, {"scene": "x", "method": "peer", "milestones": {}}]) if "fit512" in line
    ]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:5] == ["reichstag-cv1of4", "willags", "43", "15000", "fit512 (512 steps, lr 0.01)"]
    assert cells[5:] == ["19.00", "19.90 (+0.90)", "–", "1 / 1 of 3"]
    assert cv.fit_rows([{"scene": "x", "method": "peer", "milestones": {}}]) == [
        "No run scored under a protocol variant yet."
    ]
    start = {"protocol": {"steps": 128, "lr": 0.01, "oracle": False, "start_candidates": 16}, "psnr": 19.5}
    rec["protocol_variants"] = {"start16": {"15000": {**start, "per_image": longer}}}
    (row,) = [line for line in cv.fit_rows([rec]) if "start16" in line]
    assert "start16 (128 steps, lr 0.01, best of 16 + 1 starts)" in row
    mean = {"protocol": {"steps": 128, "lr": 0.01, "oracle": False, "residual_latent": "mean"}, "psnr": 19.5}
    rec["protocol_variants"] = {"resmean": {"15000": {**mean, "per_image": longer}}}
    (row,) = [line for line in cv.fit_rows([rec]) if "resmean" in line]
    assert "resmean (128 steps, lr 0.01, residual at the mean latent)" in row


def test_pooled_weighs_each_collection_the_same_and_says_whether_the_interval_holds_zero():
    def method(scores: dict[str, float], seeds: int = 1) -> cv.MethodCV:
        return cv.MethodCV(folds=1, per_photo=scores, fold_means={1: float(np.mean(list(scores.values())))}, runs=seeds)

    big_a = method({f"p{i}.jpg": 21.0 + 0.1 * (i % 3) for i in range(100)})
    big_b = method({f"p{i}.jpg": 21.0 + 0.1 * (i % 3) for i in range(100)})  # no difference on 100 photos
    small_a, small_b = method({"x.jpg": 12.0, "y.jpg": 14.0}), method({"x.jpg": 10.0, "y.jpg": 12.0})  # +2 on 2
    mean, low, high, photos = cv.pooled([(big_a, big_b), (small_a, small_b)])
    assert mean == pytest.approx(1.0) and photos == 102  # (0 + 2) / 2, not (0 * 100 + 2 * 2) / 102
    assert (low, high) == (pytest.approx(1.0), pytest.approx(1.0))  # no spread within either collection
    mean, low, high, _ = cv.pooled([(big_a, big_b), (small_a, small_b)], sigma=0.5)
    half = 1.96 * 0.5 * np.sqrt(2 + 2) / 2  # each collection's run noise, averaged over the two
    assert (low, high) == (pytest.approx(1.0 - half), pytest.approx(1.0 + half))
    assert cv.verdict(low, high) == "better"
    assert cv.verdict(-0.3, 0.2) == "no change" and cv.verdict(-0.5, -0.1) == "worse"
    rng = np.random.default_rng(3)
    noisy = {f"q{i}.jpg": float(v) for i, v in enumerate(rng.normal(0, 1, 40))}
    m, lo, hi, _ = cv.pooled([(method(noisy), method(dict.fromkeys(noisy, 0.0))), (small_a, small_b)])
    assert lo < m < hi and m == pytest.approx((np.mean(list(noisy.values())) + 2) / 2)
    with pytest.raises(ValueError, match="no collection"):
        cv.pooled([])
    with pytest.raises(ValueError, match="no photo both"):
        cv.pooled([(small_a, method({"z.jpg": 1.0}))])


def test_cv_rows_pool_only_the_methods_complete_on_every_collection():
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}
    recs = []
    for scene in ("one", "two"):
        for k, p in photos.items():
            recs.append(_fold_rec(scene, k, 2, "willags", p))
            recs.append(_fold_rec(scene, k, 2, "willags-x", {n: v + 0.5 for n, v in p.items()}))
            if scene == "one":  # willags-y misses a collection: not pooled
                recs.append(_fold_rec(scene, k, 2, "willags-y", {n: v + 9.0 for n, v in p.items()}))
    rows = cv.cv_rows(recs, 5000)
    pooled = [r for r in rows if r.startswith("| willags-")]
    assert pooled == ["| willags-x | 2 | 8 | +0.50 [+0.50, +0.50] | better |"]
    assert not any("Every collection at once" in r for r in cv.cv_rows(recs[:6], 5000))  # one collection: none
    for k, p in photos.items():  # a third collection where willags-x has not run: pooled over two, no verdict
        recs.append(_fold_rec("three", k, 2, "willags", p))
        recs.append(_fold_rec("three", k, 2, "willags-y", {n: v - 1.0 for n, v in p.items()}))
    pooled = [r for r in cv.cv_rows(recs, 5000) if r.startswith("| willags-")]
    assert pooled == [
        "| willags-x | 2 of 3 (one, two) | 8 | +0.50 [+0.50, +0.50] | none yet (better on these) |",
        "| willags-y | 2 of 3 (one, three) | 8 | +4.00 [+4.00, +4.00] | none yet (better on these) |",
    ]


def test_a_protocol_variant_gets_its_own_tables_once_the_default_and_a_peer_are_scored_under_it():
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}
    recs = []
    for k, p in photos.items():
        for method, shift, under in (("willags", 0.0, 2.0), ("peer", -1.0, 0.5)):
            rec = _fold_rec("hall", k, 2, method, {n: v + shift for n, v in p.items()})
            per = [{"image": n, "psnr": v + shift + under} for n, v in p.items()]
            rec["protocol_variants"] = {"start16": {"5000": {"psnr": 0.0, "per_image": per}}}
            if method == "peer" and k == 2:
                rec["protocol_variants"]["half"] = rec["protocol_variants"]["start16"]  # one fold: no table
            recs.append(rec)
    assert cv.compared_variants(recs, 5000) == ["start16"]
    assert cv.compared_variants(recs, 15000) == []
    by = cv.collect(recs, 5000, variant="start16")["hall"]
    assert by["willags"].mean == pytest.approx(23.0) and by["peer"].mean == pytest.approx(20.5)
    (row,) = [r for r in cv.cv_rows(recs, 5000, variant="start16") if r.startswith("| hall |")]
    assert "peer: +2.50 [+2.50, +2.50] (n=4)" in row  # under the variant: +1 + (2.0 - 0.5)
    (row,) = [r for r in cv.cv_rows(recs, 5000) if r.startswith("| hall |")]
    assert "peer: +1.00 [+1.00, +1.00] (n=4)" in row  # the protocol's own scores untouched
    for k, p in photos.items():  # a collection where only a candidate was scored under the variant
        rec = _fold_rec("yard", k, 2, "willags-x", p)
        rec["protocol_variants"] = {
            "start16": {"5000": {"psnr": 0.0, "per_image": rec["milestones"]["5000"]["per_image"]}}
        }
        recs.append(rec)
    assert not [r for r in cv.cv_rows(recs, 5000, variant="start16") if r.startswith("| yard")]  # no row: no reference
    assert [r for r in cv.cv_rows(recs, 5000, variant="start16") if r.startswith("| hall |")]


def test_a_method_is_set_against_the_one_whose_settings_it_extends():
    pairs = {(b, a): added for b, a, added in cv.switch_pairs(["willags", "peer", "willags-noprior", "willags-mask",
                                                                "willags-prior-low-mask", "willags-capscene"])}  # fmt: skip
    # willags-prior-low-mask sets the prior another way than willags-noprior: not one of its extensions
    assert pairs == {
        ("willags-mask", "willags-noprior"): ["mask.distance=residual", "mask.enabled=True"],
        ("willags-capscene", "willags-noprior"): ["mcmc.cap_rule=pixels"],
    }
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}
    recs = []
    for scene, gain in (("one", 1.0), ("two", -0.5)):
        for k, p in photos.items():
            recs.append(_fold_rec(scene, k, 2, "willags", p))
            recs.append(_fold_rec(scene, k, 2, "willags-noprior", p))
            recs.append(_fold_rec(scene, k, 2, "willags-mask", {n: v + gain for n, v in p.items()}))
    rows = [r for r in cv.cv_rows(recs, 5000) if r.startswith("| willags-mask | willags-noprior |")]
    added = "mask.distance=residual, mask.enabled=True"
    assert rows == [
        f"| willags-mask | willags-noprior | {added} | one | +1.00 [+1.00, +1.00] (n=4) |  |",
        f"| willags-mask | willags-noprior | {added} | two | -0.50 [-0.50, -0.50] (n=4) |  |",
        f"| willags-mask | willags-noprior | {added} | **2 at once** | +0.25 [+0.25, +0.25] (n=8) | better |",
    ]
    only_one = [r for r in recs if not r["scene"].startswith("two") or r["method"] == "willags"]
    rows = [r for r in cv.cv_rows(only_one, 5000) if r.startswith("| willags-mask | willags-noprior |")]
    assert len(rows) == 1 and "| one |" in rows[0]  # one collection: no row at once


def test_the_synthetic_scenes_are_compared_photo_by_photo_on_their_own_split():
    """fox-wild keeps its split: the default's seeds averaged photo by photo, each compared method and the peer set
    against it with the run noise of their step count; CPU runs, other step counts and other scenes left out."""
    photos = {"a.jpg": 20.0, "b.jpg": 22.0, "c.jpg": 24.0}

    def run(method, shift, seed=42, **kw):
        rec = _fold_rec("x", 1, 2, method, {n: v + shift for n, v in photos.items()})
        return {**rec, "scene": "fox-wild", "seed": seed, **kw}

    records = [run("willags", 0.0), run("willags", 1.0, seed=43), run("peer", -2.0), run("willags-noprior", -0.5)]
    at = lambda steps, rec: {**rec, "milestones": {str(steps): rec["milestones"]["5000"]}}  # noqa: E731
    records += [run("willags-noprior", 9.0, device="cpu"), at(300, run("willags", 9.0, scene="fox-clean"))]
    records += [at(15000, run("willags-lowpen", 5.0))]
    by = cv.fixed_split(records, "fox-wild", 5000)
    assert set(by) == {"willags", "peer", "willags-noprior"} and by["willags"].runs == 2
    assert by["willags"].per_photo == {"a.jpg": 20.5, "b.jpg": 22.5, "c.jpg": 24.5}
    rows = cv.fixed_split_rows(records, ["willags-noprior", "willags-lowpen"], {5000: None})
    cells = [[c.strip() for c in r.strip("|").split("|")] for r in rows[2:]]
    assert cells == [
        ["fox-wild", "5000", "3", "**willags**", "2", "22.50", ""],
        ["fox-wild", "5000", "3", "willags-noprior", "1", "21.50", "-1.00 [-1.00, -1.00]"],
        ["fox-wild", "5000", "3", "peer", "1", "20.00", "-2.50 [-2.50, -2.50]"],
    ]
    wide = cv.fixed_split_rows(records, ["willags-noprior"], {5000: 0.5})
    low, high = (float(x) for x in wide[3].split("[")[1].split("]")[0].split(", "))
    assert low < -1.0 < high  # the run noise widens the photo bootstrap's interval


@pytest.mark.skipif(not SACRE.is_dir(), reason="needs ../shared/data/sacre-coeur-mini")
def test_a_bundle_holds_writable_copies_and_their_folds_and_moves_as_one_folder(tmp_path, capsys):
    from willags_ns.data.dataparser import WillagsDataParserConfig

    bundle = tmp_path / "bundle"
    assert cv.main(["bundle", "--data", str(SACRE), "--folds", "7", "--out", str(bundle)]) == 0
    names = sorted(p.name for p in bundle.iterdir())
    assert names == ["sacre-coeur-mini", *(f"sacre-coeur-mini-cv{k}of7" for k in range(1, 8))]
    copy = bundle / "sacre-coeur-mini"
    assert not copy.is_symlink() and (copy / "images").is_dir() and not (copy / "images").is_symlink()
    assert sorted(p.name for p in (copy / "images").iterdir()) == sorted(p.name for p in (SACRE / "images").iterdir())
    import stat

    for q in (copy, *copy.rglob("*")):  # the source's read-only modes are not copied: the bundle can be removed
        assert q.stat().st_mode & stat.S_IWUSR, q
    size = cv.tree_bytes(bundle)
    splits = sum(
        (bundle / f"sacre-coeur-mini-cv{k}of7" / f"sacre-coeur-mini-cv{k}of7.tsv").stat().st_size for k in range(1, 8)
    )
    assert size == cv.tree_bytes(copy) + splits  # the folds are links and their split files
    assert f"{size / 2**20:.1f} MiB to carry" in capsys.readouterr().out
    moved = tmp_path / "moved"
    bundle.rename(moved)  # links relative to the copy: the bundle moves as one folder
    parser = WillagsDataParserConfig(data=moved / "sacre-coeur-mini-cv1of7").setup()
    assert len(parser.get_dataparser_outputs("test").image_filenames) == 2
    with pytest.raises(SystemExit, match="2 fold counts for 1 collections"):
        cv.main(["bundle", "--data", str(SACRE), "--folds", "4", "7", "--out", str(tmp_path / "b2")])


def test_what_length_is_worth_pairs_one_runs_two_checkpoints_and_skips_runs_scored_once():
    def both(scene: str, fold: int, method: str, short: dict[str, float], long: dict[str, float]) -> dict:
        rec = _fold_rec(scene, fold, 2, method, short)
        rec["milestones"]["15000"] = _fold_rec(scene, fold, 2, method, long, steps=15000)["milestones"]["15000"]
        return rec

    recs = []
    for scene, gain in (("one", 1.0), ("two", -0.5)):
        recs += [
            both(scene, 1, "willags", {"a.jpg": 20.0, "c.jpg": 21.0}, {"a.jpg": 20.0 + gain, "c.jpg": 21.0 + gain}),
            both(scene, 2, "willags", {"b.jpg": 18.0}, {"b.jpg": 18.0 + gain}),
        ]
    recs += [both("one", 1, "peer", {"a.jpg": 19.0, "c.jpg": 19.0}, {"a.jpg": 19.5, "c.jpg": 19.5})]  # one fold of 2
    recs += [_fold_rec("one", 2, 2, "willags", {"b.jpg": 0.0})]  # another run scored only at 5000: not counted
    _, _, *rows = cv.length_rows(recs, 5000, 15000)
    cells = [[c.strip() for c in r.strip("|").split("|")] for r in rows]
    assert cells[0] == ["one", "willags", "19.67", "20.67", "+1.00 [+1.00, +1.00] (n=3)"]
    assert cells[1] == ["two", "willags", "19.67", "19.17", "-0.50 [-0.50, -0.50] (n=3)"]
    assert cells[2][:2] == ["**2 at once**", "willags"] and cells[2][4].startswith("+0.25 [+0.25, +0.25]")
    assert len(cells) == 3  # the peer is not complete on any collection
    assert cv.length_rows(recs, 5000, 30000) == []
    # one method at two counts, photo by photo: the run scored only at 5000 is left out there too
    gains = cv.photo_differences(recs, "one", ("willags", 15000), ("willags", 5000))
    assert gains == {"a.jpg": pytest.approx(1.0), "b.jpg": pytest.approx(1.0), "c.jpg": pytest.approx(1.0)}


def test_photos_name_the_ends_and_correlate_with_the_inspectors_per_image_evidence(tmp_path, capsys):
    recs = [_fold_rec("scene", 1, 2, "willags", {"a.jpg": 20.0, "c.jpg": 22.0})]
    recs += [_fold_rec("scene", 2, 2, "willags", {"b.jpg": 18.0, "d.jpg": 24.0})]
    recs += [
        _fold_rec("scene", k, 2, "peer", p)
        for k, p in ((1, {"a.jpg": 21.0, "c.jpg": 21.0}), (2, {"b.jpg": 16.0, "d.jpg": 24.0}))
    ]
    diffs = cv.photo_differences(recs, "scene", cv.parse_side("willags", 5000), cv.parse_side("peer@5000", 15000))
    assert diffs == {"a.jpg": -1.0, "b.jpg": 2.0, "c.jpg": 1.0, "d.jpg": 0.0}
    report = {"per_image": {"names": ["a.jpg", "b.jpg", "c.jpg", "d.jpg", "x.jpg"],
                            "rises": [-1.0, 2.0, 1.0, 0.0, 9.0], "flat": [1.0] * 5}}  # fmt: skip
    corr = cv.evidence_correlations(diffs, report)
    assert set(corr) == {"rises"} and corr["rises"] == (pytest.approx(1.0), 4)  # x.jpg was scored by neither
    lines = cv.photo_lines(diffs, 1, corr)
    assert lines[0] == "4 photos: mean +0.50, median +0.50, below -1 dB 0, above +1 dB 1"
    assert lines[1:] == ["lowest: a.jpg -1.00", "highest: b.jpg +2.00", "r with rises: +1.00 (4 photos)"]
    with pytest.raises(ValueError, match="no fold run of peer on scene scored at 15000"):
        cv.photo_differences(recs, "scene", ("willags", 5000), cv.parse_side("peer", 15000))
    with pytest.raises(ValueError, match="not METHOD or METHOD@STEPS"):
        cv.parse_side("peer@late", 5000)
    records = tmp_path / "cv.json"
    records.write_text(json.dumps(recs))
    (tmp_path / "insp.json").write_text(json.dumps(report))
    args = ["photos", "--scene", "scene", "--a", "willags@5000", "--b", "peer@5000", "--records", str(records)]
    assert cv.main([*args, "--inspect", str(tmp_path / "insp.json"), "--top", "2"]) == 0
    assert "highest: b.jpg +2.00, c.jpg +1.00" in capsys.readouterr().out
    # another pair's differences on the same photos: the peer at 5000 against itself is flat, so no r
    assert cv.pair_correlation(diffs, {"a.jpg": 1.0, "b.jpg": -2.0, "c.jpg": -1.0}) == (pytest.approx(-1.0), 3)
    assert cv.pair_correlation(diffs, {"a.jpg": 1.0, "b.jpg": 1.0, "c.jpg": 1.0}) is None
    assert cv.pair_correlation(diffs, {"a.jpg": 1.0, "b.jpg": 2.0}) is None  # under 3 photos in common
    assert cv.main([*args, "--with", "peer@5000", "willags@5000"]) == 0
    assert "r with peer@5000 - willags@5000: -1.00 (4 photos)" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no fold run of peer-full on scene"):
        cv.main([*args, "--with", "peer-full@5000", "willags@5000"])
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(SystemExit, match="bad.json: not a willags-inspect report"):
        cv.main([*args, "--inspect", str(tmp_path / "bad.json")])


def test_the_stopping_rule_ends_early_only_the_runs_whose_chosen_photos_say_so(tmp_path, capsys):
    """`cv stop`: a run whose photos all score 1 dB better at the earlier step ends there (+1 on its other photos),
    one whose photos score worse, or better by less than the margin, keeps its last step (0)."""
    better = [(21.0, 20.0)] * 6
    worse = [(19.0, 20.0)] * 6
    inside = [(20.05, 20.0)] * 6
    assert cv.stopping_gain([better], photos=2, margin=0.1) == (pytest.approx(1.0), 1.0)
    assert cv.stopping_gain([worse], photos=2, margin=0.1) == (0.0, 0.0)
    assert cv.stopping_gain([inside], photos=2, margin=0.1) == (0.0, 0.0)
    gain, early = cv.stopping_gain([better, worse], photos=2, margin=0.1)
    assert gain == pytest.approx(0.5) and early == 0.5  # 4 scored photos each: +1 and 0
    # mixed photos: the choice follows the photos drawn, so the gain lies between none and all of the early lead
    mixed = [(22.0, 20.0), (22.0, 20.0), (19.0, 20.0), (19.0, 20.0)]
    gain, early = cv.stopping_gain([mixed], photos=1, margin=0.1, draws=200)
    assert 0.0 < early < 1.0 and -1.0 < gain < 2.0

    def both(fold: int, short: dict[str, float], long: dict[str, float]) -> dict:
        rec = _fold_rec("one", fold, 2, "willags", short)
        rec["milestones"]["15000"] = _fold_rec("one", fold, 2, "willags", long, steps=15000)["milestones"]["15000"]
        return rec

    photos = {f"{i}.jpg": 20.0 for i in range(4)}
    recs = [both(1, {k: v + 1 for k, v in photos.items()}, photos), both(2, photos, photos)]
    runs = cv.run_milestone_photos(recs, "willags", 5000, 15000)
    assert [len(r) for r in runs["one"]] == [4, 4]
    path = tmp_path / "cv.json"
    path.write_text(json.dumps(recs))
    assert cv.main(["stop", "--records", str(path), "--photos", "2"]) == 0
    out = capsys.readouterr().out
    assert "| one | 2 | +0.50 | +0.50 | 0.50 |" in out
    with pytest.raises(SystemExit, match="no fold run of peer"):
        cv.main(["stop", "--records", str(path), "--method", "peer"])


def test_runs_of_one_collection_from_two_builds_of_its_scene_are_named():
    recs = _records(1.0)
    assert cv.model_lines(recs, 5000) == []  # records that name no model say nothing
    for r in recs:
        r["scene_model_sha256"] = "a" * 64
    assert cv.model_lines(recs, 5000) == []  # one model
    peer_fold_2 = next(r for r in recs if r["method"] == "peer" and r["scene"].endswith("2of2"))
    peer_fold_2["scene_model_sha256"] = "b" * 64
    (line,) = cv.model_lines(recs, 5000)
    assert (
        line == f"- **scene**: the fold runs started from 2 SfM models ({'a' * 12}: peer, willags; {'b' * 12}: peer)."
    )
    rows = cv.cv_rows(recs, 5000)
    assert line in rows and any("different builds of their scene" in r for r in rows)
    assert cv.model_lines(recs, 15000) == []  # only the runs scored at the step count asked


def test_runs_that_name_no_build_beside_runs_that_do_are_another_build_and_the_named_one_is_scored_alone():
    """Old records name no SfM model: beside runs that name one, they count as a build of their own, and the named
    build on which the default and a peer have every fold gets the default against the peer from its runs alone."""
    old = _on("lund", _records(0.2))  # a rebuilt collection; the default 0.2 dB above the peer: the mixed table
    new = [
        {**r, "scene_model_sha256": "c" * 64, "tag": "pinned"}
        for r in _on("lund", _records(1.5))
        if r["scene"].startswith("lund") and r.get("status", "ok") == "ok"
    ]
    lines = cv.model_lines(old + new, 5000)
    assert lines[0] == (
        f"- **lund**: the fold runs started from 2 SfM models ({'c' * 12}: peer, willags; {cv.UNRECORDED}: peer, "
        "willags)."
    )
    assert lines[1] == (
        f"  On {'c' * 12} alone (runs a fold: willags 1, peer 1): willags 21.00, peer 19.50, willags − peer +1.50 "
        "[+1.50, +1.50] (n=4), goal met."
    )
    assert len(lines) == 2
    assert cv.collect(old + new, 5000)["lund"]["willags"].runs == 4  # the tables themselves keep every run
    only_old_peer = old + [r for r in new if r["method"] == "willags"]  # no peer on the named build: no such line
    assert cv.model_lines(only_old_peer, 5000) == [lines[0].replace("peer, willags;", "willags;")]


def test_a_bundle_says_whether_a_rebuilt_collection_is_its_pinned_scene(tmp_path):
    from benchmarks.collections import COLLECTIONS, model_digest
    from tests._scenes import sfm_model_stub

    lund, other = sfm_model_stub(tmp_path / "lund"), sfm_model_stub(tmp_path / "my-scene")
    (line,) = cv.pin_lines([lund, other])  # a folder that is no rebuilt collection: nothing to say
    assert line.startswith(f"cv: lund: SfM model {model_digest(lund)[:12]} differs from the pinned")
    assert COLLECTIONS["lund"].model_sha256[:12] in line
    (lund / "colmap" / "sparse" / "0" / "points3D.bin").unlink()
    (line,) = cv.pin_lines([lund])
    assert "no SfM model file colmap/sparse/0/points3D.bin" in line


def test_a_candidate_is_set_against_the_default_on_its_own_build_where_the_default_spans_builds():
    """The default ran on two builds (none named, and a pinned one 1.5 dB apart from it); a candidate run only on the
    pinned one is compared with the default's pinned runs, in its row and in the pooled rows; a candidate on the
    unnamed build with the default's unnamed runs; with no default on the candidate's build, with every run."""
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}
    pinned = {"scene_model_sha256": "c" * 64}

    def runs(method, shift, build=None, scene="lund"):  # a rebuilt collection
        return [
            {**_fold_rec(scene, k, 2, method, {n: v + shift for n, v in p.items()}), **(build or {})}
            for k, p in photos.items()
        ]

    recs = runs("willags", 0.0) + runs("willags", 1.5, pinned) + runs("peer", -1.0)
    recs += runs("cand-pinned", 1.7, pinned) + runs("cand-old", 0.3)
    recs += runs("willags", 0.0, scene="other") + runs("cand-pinned", 0.2, scene="other")  # one build: as before
    refs = cv.same_build_refs(recs, 5000)
    assert set(refs) == {("lund", "cand-pinned"), ("lund", "cand-old"), ("lund", "peer")}  # the peer's pooled row
    assert refs[("lund", "cand-pinned")][1] == "c" * 64 and refs[("lund", "cand-old")][1] == cv.UNRECORDED
    assert refs[("lund", "cand-pinned")][0].mean == pytest.approx(22.5)
    rows = "\n".join(cv.cv_rows(recs, 5000))
    assert (
        "| lund | cand-pinned | 22.70 (22.70 / 22.70) | +0.20 [" in rows
        and f"(the default's runs on {'c' * 12})" in rows
    )
    assert (
        "| lund | cand-old | 21.30 (21.30 / 21.30) | +0.30 [" in rows
        and "the default's runs that name no build" in rows
    )
    assert "| other | cand-pinned | 21.20 (21.20 / 21.20) | +0.20 [" in rows  # the default spans no build there
    by_scene = cv.collect(recs, 5000)
    (row,) = [r for r in cv.pooled_rows_of(by_scene, None, "willags", refs) if r[0] == "cand-pinned"]
    assert row[3].startswith("+0.20 [")  # (+0.20 on lund against the pinned default, +0.20 on other) / 2
    (mixed,) = [r for r in cv.pooled_rows_of(by_scene, None, "willags") if r[0] == "cand-pinned"]
    assert mixed[3].startswith("+0.57 [")  # against every run of the default: (+0.95 + 0.20) / 2


def test_on_a_fixed_collection_runs_that_name_no_build_share_its_one_named_build():
    """A collection nobody rebuilds is one folder of data: its older runs, whose records name no SfM model, started
    from the scene its newer runs name, so no line says it has two builds and no candidate is set apart; only if its
    named runs name two digests do the unnamed ones stay a build of their own."""
    old = _records(0.2)  # "scene" is no rebuilt collection (benchmarks.collections.COLLECTIONS)
    new = [{**r, "method": "cand", "scene_model_sha256": "d" * 64} for r in old if r["method"] == "willags"]
    key = cv.build_key(old + new)
    assert {key(r) for r in old + new if r.get("status", "ok") == "ok"} == {"d" * 64}
    assert cv.model_lines(old + new, 5000) == [] and cv.same_build_refs(old + new, 5000) == {}
    assert cv.method_builds(old + new, 5000)[("scene", "willags")] == {"d" * 64}
    new[0]["scene_model_sha256"] = "e" * 64  # the folder changed under the runs: no single build to join
    (line,) = cv.model_lines(old + new, 5000)
    assert f"3 SfM models ({'d' * 12}: cand; {'e' * 12}: cand; {cv.UNRECORDED}: peer, willags)" in line
    lund = _on("lund", old) + [{**r, "scene": r["scene"].replace("scene-", "lund-")} for r in new[1:]]
    assert cv.build_key(lund)(_on("lund", old)[0]) == cv.UNRECORDED  # a rebuilt collection's older runs: any build


def test_a_setting_measured_across_two_builds_is_shown_apart_and_left_out_of_the_pooled_row():
    """switch_rows pairs a method with the one it extends; on a rebuilt collection where each ran on another build
    the row says so and the pooled row leaves that collection out."""
    base, more = "willags-prior-low-cap1m", "willags-prior-low-mask-expected-cap1m"
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}

    def runs(scene, method, shift, build=None):
        extra = {"scene_model_sha256": build} if build else {}
        return [{**_fold_rec(scene, k, 2, method, {n: v + shift for n, v in p.items()}), **extra}
                for k, p in photos.items()]  # fmt: skip

    recs = runs("lund", base, 0.0, "c" * 64) + runs("lund", more, 2.0)
    recs += runs("scene", base, 0.0) + runs("scene", more, 0.5) + runs("other", base, 0.0) + runs("other", more, 0.5)
    by_scene = cv.collect(recs, 5000)
    rows = cv.switch_rows(by_scene, None, "willags", cv.method_builds(recs, 5000))
    (lund,) = [r for r in rows if r[3] == "lund"]
    assert lund[4].startswith("+2.00 [") and "different builds: left out of the pooled row" in lund[4]
    (pool,) = [r for r in rows if "at once" in r[3]]
    assert pool[3] == "**2 at once**" and pool[4].startswith("+0.50 [")
    (mixed,) = [r for r in cv.switch_rows(by_scene, None, "willags") if "at once" in r[3]]  # no builds given
    assert mixed[3] == "**3 at once**" and mixed[4].startswith("+1.00 [")
    assert any("different builds: left out" in line for line in cv.cv_rows(recs, 5000))


def test_missing_lists_the_folds_a_method_lacks_where_the_default_has_every_fold(tmp_path, capsys):
    recs = _records(1.0)  # "scene": the default on both folds, the peer on both
    recs += [r for r in _on("other", _records(1.0)) if r["method"] == "willags"]  # "other": the default alone
    recs += [
        _fold_rec("half", 1, 2, "willags", {"x.jpg": 20.0})
    ]  # the default on one fold of two: not a collection yet
    cand = [{**r, "method": "cand"} for r in recs if r["method"] == "willags" and r["scene"] == "scene-cv2of2"]
    assert cv.missing_folds(recs + cand, "cand", 5000) == ["other-cv1of2", "other-cv2of2", "scene-cv1of2"]
    assert cv.missing_folds(recs, "peer", 5000) == ["other-cv1of2", "other-cv2of2"]
    assert cv.missing_folds(recs, "peer", 15000) == []  # no collection whole at that step count
    path = tmp_path / "cv.json"
    path.write_text(json.dumps(recs + cand))
    assert cv.main(["missing", "--method", "cand", "--steps", "5000", "--records", str(path)]) == 0
    out = capsys.readouterr()
    assert out.out.split() == ["other-cv1of2", "other-cv2of2", "scene-cv1of2"]
    assert "cand lacks 3 fold run(s) scored at 5000 steps" in out.err


def test_the_readme_headline_says_the_default_against_the_peer_over_the_collections_at_once():
    one = cv.cv_headline(_records(1.0), 5000)
    assert not any("at once" in line for line in one)  # one collection: its row says it all
    two = cv.cv_headline(_records(1.0) + _on("other", _records(0.5)), 5000)
    assert two[-1].startswith("Over the 2 collections at once: willags − peer +0.75 dB [")
    assert two[-1].endswith("(8 photos).")
    part = cv.cv_headline(_records(1.0) + _on("other", _records(0.5, folds_of_b=1)), 5000)
    assert not any("at once" in line for line in part)  # the peer lacks a fold of "other": one collection whole


def test_bar_composes_the_two_methods_fold_by_fold_from_the_rules_shares():
    """cv bar: below the bar a fold takes the high method's run, else the low one's, and the table reads the
    composition against the low method; a collection missing a fold of one of the three is left out, and named."""
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}
    recs = []
    for k, p in photos.items():
        recs.append(_fold_rec("scene", k, 2, "willags", p, steps=15000))
        recs.append(_fold_rec("scene", k, 2, "willags-prior-low-cap1m", {n: v + 1.0 for n, v in p.items()}, 15000))
        rule = _fold_rec("scene", k, 2, "willags-prior-low-captransients", p, steps=15000)
        rule["milestones"]["15000"]["cap_rule_share"] = {1: 0.01, 2: 0.05}[k]
        recs.append(rule)
    recs.append(_fold_rec("other", 1, 2, "willags-prior-low-captransients", {"x.jpg": 1.0}, steps=15000))
    recs[-1]["milestones"]["15000"]["cap_rule_share"] = 0.0
    lines = cv.bar_rows(
        recs, 15000, "willags-prior-low-captransients", "willags", "willags-prior-low-cap1m", [0.0, 0.02, 0.1]
    )
    assert lines[0] == "| bar | other | scene | at once |"
    none, one, both = lines[2:5]
    assert "| – | +0.00 [+0.00, +0.00] (0/2 willags-prior-low-cap1m) |" in none
    assert "| – | +0.50 [" in one and "(1/2 willags-prior-low-cap1m)" in one and "+0.50 [" in one.split("|")[-2]
    assert "| – | +1.00 [+1.00, +1.00] (2/2 willags-prior-low-cap1m) | +1.00 [+1.00, +1.00] over 1: better |" in both
    assert (
        lines[-1]
        == "- left out: other: a fold lacks a run of willags-prior-low-captransients, willags or willags-prior-low-cap1m"
    )
    assert cv.bar_rows(recs, 5000, "willags-prior-low-captransients", "willags", "x", [0.02]) == [
        "cv: no fold run of willags-prior-low-captransients recorded cap_rule_share at 5000 steps"
    ]


def test_a_candidate_that_only_turns_a_switch_off_takes_the_defaults_runs_where_the_default_had_it_off():
    """`willags-prior-low-nomask` is the default wherever the inspector kept the mask off (the default's record has no
    mask_status): on such a fold without a run of its own it takes the default's runs, so it needs runs only where the
    default trained the mask; on a fold where it ran, its own run counts; its taken folds are named in the table and
    are never replicates; until it has a run of its own the tables leave it out."""
    nomask = "willags-prior-low-nomask"
    photos = {1: {"a.jpg": 20.0, "c.jpg": 22.0}, 2: {"b.jpg": 18.0, "d.jpg": 24.0}}
    recs = []
    for scene, masked in (("open", ()), ("crowd", (1,))):
        for k, p in photos.items():
            rec = _fold_rec(scene, k, 2, "willags", p)
            if k in masked:
                rec["mask_status"] = "ok"
            recs.append(rec)
            recs.append(_fold_rec(scene, k, 2, "peer", {n: v - 1.0 for n, v in p.items()}))
    assert cv.missing_folds(recs, nomask, 5000) == ["crowd-cv1of2"]  # the one fold where the default had the mask
    assert nomask not in cv.collect(recs, 5000)["open"]  # no run of its own yet: the tables leave it out
    by = cv.collect(recs, 5000, borrowers=[nomask])
    assert by["open"][nomask].complete and by["open"][nomask].borrowed == (1, 2)
    assert cv.paired(by["open"][nomask], by["open"]["willags"])[:3] == (0.0, 0.0, 0.0)
    assert not by["crowd"][nomask].complete and by["crowd"][nomask].borrowed == (2,)
    assert [r[0] for r in cv.pooled_rows_of(by, None, "willags")] == ["peer"]  # whole on one collection of two

    recs.append(_fold_rec("crowd", 1, 2, nomask, {"a.jpg": 21.0, "c.jpg": 23.0}))  # without the mask: +1 there
    by = cv.collect(recs, 5000)
    crowd = by["crowd"][nomask]
    assert crowd.complete and crowd.borrowed == (2,) and crowd.per_photo["a.jpg"] == 21.0
    assert cv.paired(crowd, by["crowd"]["willags"])[0] == pytest.approx(0.5)  # +1 on fold 1's photos, 0 on fold 2's
    row = cv.pooled_rows_of(by, None, "willags")
    assert [r[0] for r in row] == ["peer", nomask]  # counted on both collections, one of them wholly borrowed
    assert row[1][1] == "2 (1 wholly willags's runs: cv.BORROWS)"
    assert cv.replicate_differences(recs, 5000) == []  # a taken run is the default's own, not a second run
    text = "\n".join(cv.cv_rows(recs, 5000))
    assert "(folds 2: willags's runs, the inspector kept the default's mask off there: the same model)" in text
    assert "(folds 1/2: willags's runs" in text

    own = recs + [_fold_rec("open", 2, 2, nomask, {"b.jpg": 17.0, "d.jpg": 23.0})]  # its own run wins on that fold
    assert cv.collect(own, 5000)["open"][nomask].borrowed == (1,)
    assert cv.collect(own, 5000)["open"][nomask].per_photo["b.jpg"] == 17.0

    # a default run whose mask the start rule kept off had the inspector's mask on: a run of another model, not lent
    for rec in recs:
        if rec["scene"].startswith("open-cv1of2") and rec["method"] == "willags":
            rec["mask_started"] = False
    assert cv.collect(recs, 5000, borrowers=[nomask])["open"][nomask].borrowed == (2,)


def test_every_borrower_is_a_method_that_keeps_the_switch_it_turns_off_from_the_inspector():
    """A BORROWS candidate trains the lender's model wherever the lender's record shows the mask off: it is the lender
    with the mask pinned off (keep, so that the inspector cannot turn it on) or with only mask settings changed (which
    act only where the mask is on), and the lender is a benchmarked method."""
    from benchmarks.methods import METHODS

    for borrower, (lender, fields, _) in cv.BORROWS.items():
        spec, base = METHODS[borrower], METHODS[lender]
        assert fields == ("mask_status", "mask_started") and spec.base == base.base
        added = [(k, v) for k, v in spec.overrides if (k, v) not in base.overrides]
        mask = [k for k, _ in added if k.startswith("mask.")]
        pinned_off = ("mask.enabled", False) in added and "mask.enabled" in spec.keep
        only_settings = bool(mask) and "mask.enabled" not in mask and not spec.keep
        # besides the mask, only what the lender is on a GPU: its prior weight named, MCMC (willags-prior-low)
        assert {k for k, _ in added} - set(mask) <= {"latent.prior_weight", "densification"}
        assert pinned_off or only_settings, borrower
