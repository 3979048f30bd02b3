"""benchmarks/generalisation.py (the every-scene table that decides a default) and the harness's static-observation
measurement."""

from types import SimpleNamespace

import numpy as np
import torch

from benchmarks.generalisation import generalisation_section, scene_rows, static_obs_rows
from benchmarks.harness import static_observation_scores, training_mask
from willags_ns.mask.static_support import StaticSupportConfig, support_map


def _rec(scene, method, psnr, tag="h200-r1", **kw):
    return {
        "scene": scene,
        "method": method,
        "psnr": psnr,
        "tag": tag,
        "steps": 5000,
        "status": "ok",
        "device": "cuda",
        **kw,
    }


def test_scene_rows_pool_seeds_and_compare_with_the_default():
    today = {"date": "2026-11-25T16:00:00"}
    recs = [
        _rec("reichstag", "willags", 19.0, **today),
        _rec("reichstag", "willags-skyopen-support", 19.4, tag="h100-r2"),  # today's default, named in full
        _rec("reichstag", "willags", 18.0, date="2026-11-24T10:00:00"),  # the previous default
        _rec("reichstag", "willags-prev", 18.4),
        _rec("reichstag", "peer", 19.5),
        _rec("reichstag", "willags-auto", 19.1, tree_note="wip", **today),
        _rec("reichstag", "willags-auto", 25.0),  # before the change, not today's settings there: left out
        _rec("reichstag", "willags-skyalpha-support", 18.0),
        _rec("reichstag", "willags", 30.0, tag="other", **today),  # not a fidelity-grid tag: left out
        _rec("reichstag", "willags", 30.0, steps=15000, **today),  # not 5000 steps: left out
        _rec("fox-wild", "willags", 22.0),  # no keypoints: the previous default's record is today's too
    ]
    rows = scene_rows(recs)
    assert "willags-skyalpha-support" in rows[0] and "willags-sky |" not in rows[0]  # only candidates that ran
    row = next(r for r in rows if r.startswith("| reichstag"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3] == "19.20 ±0.20 (n=2)"
    assert cells[4] == "-0.30"  # willags - peer
    assert cells[5] == "18.20 ±0.20 (n=2)" and cells[6] == "+1.00"  # the previous default, and the change
    assert cells[7] == "19.10† (n=1)" and cells[8] == "-0.10"
    assert cells[9] == "18.00 (n=1)" and cells[10] == "-1.20"
    fox = [c.strip() for c in next(r for r in rows if r.startswith("| fox-wild")).strip("|").split("|")]
    assert fox[3] == fox[5] == "22.00 (n=1)" and fox[6] == "+0.00"
    assert not any(r.startswith("| fox-clean") for r in rows)  # a scene without records has no row


def test_section_is_empty_without_grid_records():
    assert generalisation_section([_rec("reichstag", "willags", 19.0, tag="x")]) == []
    assert generalisation_section([_rec("reichstag", "willags", 19.0)])[0].startswith("## Every scene at once")


def test_static_obs_rows_only_for_real_scenes_that_measured_it():
    recs = [
        _rec(
            "reichstag",
            "willags",
            19.0,
            static_obs_masked=0.001,
            static_obs_masked_perceptual=0.01,
            static_obs_count=100,
            static_obs_images=5,
        ),
        _rec(
            "fox-wild",
            "willags",
            22.0,
            static_obs_masked=0.5,
            static_obs_masked_perceptual=0.5,
            static_obs_count=1,
            static_obs_images=1,
        ),
        _rec("sacre-coeur-mini", "willags", 14.0),
    ]
    rows = [r for r in static_obs_rows(recs) if r.startswith("| ") and "%" in r]
    assert len(rows) == 1 and "| 0.10 % | 1.00 % | 100 in 5 images |" in rows[0]
    assert static_obs_rows([_rec("reichstag", "willags", 19.0)]) == []


def _fake_model(enabled: bool):
    cfg = StaticSupportConfig(enabled=enabled, grid=16)
    rng = np.random.default_rng(0)
    uv = np.stack([0.2 + 0.02 * rng.standard_normal(30), 0.5 + 0.02 * rng.standard_normal(30)], 1)
    obs = [np.concatenate([uv, np.full((30, 1), 6.0)], 1).astype(np.float32)]
    model = SimpleNamespace(sfm_observations=obs, last_masks={0: torch.zeros(40, 80, dtype=torch.bool)})
    model.static_support = lambda idx, h, w: support_map(obs[idx], w, h, cfg) if enabled else None
    return model


def test_static_observation_scores_with_and_without_the_safeguard():
    off = static_observation_scores(_fake_model(False))
    assert off["static_obs_masked"] == 1.0 and off["static_obs_masked_perceptual"] == 1.0
    assert off["static_obs_count"] == 30 and off["static_obs_images"] == 1
    on = static_observation_scores(_fake_model(True))
    assert on["static_obs_masked_perceptual"] == 1.0 and on["static_obs_masked"] < 0.2
    m = training_mask(_fake_model(True), 0)
    assert m.shape == (40, 80) and m[20, 16] and not m[20, 70]


def test_willags_records_since_the_default_inspects_count_as_willags_auto():
    """After AUTO_DEFAULT_SINCE a `willags` record is of the default that inspects first: the table's willags-auto
    column, not the full model's."""
    full = {"date": "2026-11-25T16:00:00"}
    later = {"date": "2026-11-26T10:00:00"}
    recs = [
        _rec("south-building", "willags", 20.8, **full),
        _rec("south-building", "willags", 22.0, **later),
        _rec("south-building", "willags-auto", 22.2, **full),
        _rec("south-building", "peer", 21.9),
    ]
    row = scene_rows(recs)[2]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3] == "20.80 (n=1)"  # the full model: only the record before the change
    assert cells[7] == "22.10 ±0.10 (n=2)"  # willags-auto: its own record and the later willags one


def test_subject_masked_scores_count_the_subject_pixels_the_mask_flags(tmp_path):
    """The "subject masked" figure: the share of a photo's subject (masks_subject/<stem>.png) that the last mask
    flags, for the mask as used (with the safeguard) and for the perceptual mask alone; photos without an outline
    or with an empty one do not count."""
    from PIL import Image

    from benchmarks.child import subject_masked_scores

    model = _fake_model(True)
    raw = torch.ones(40, 80, dtype=torch.bool)
    raw[:, :40] = False  # the perceptual mask flags the left half
    model.last_masks[0] = raw
    model.last_masks[1] = torch.zeros(40, 80, dtype=torch.bool)  # an image without an outline
    model.sfm_observations.append(model.sfm_observations[0])
    subject = np.zeros((80, 160), dtype=np.uint8)  # outlines at twice the mask's resolution: resized
    subject[:, 20:100] = 255  # columns 10..50 at the mask's size: half in the flagged half
    Image.fromarray(subject).save(tmp_path / "a.png")
    dataset = SimpleNamespace(image_filenames=[tmp_path / "images" / "a.jpg", tmp_path / "images" / "b.jpg"])
    out = subject_masked_scores(model, dataset, tmp_path)
    assert out["subject_masked_images"] == 1
    assert out["subject_masked_perceptual"] == 0.75  # columns 10..39 of 10..49 flagged
    assert out["subject_masked"] < out["subject_masked_perceptual"]  # the safeguard keeps part of it
    Image.fromarray(np.zeros((80, 160), dtype=np.uint8)).save(tmp_path / "a.png")
    assert subject_masked_scores(model, dataset, tmp_path) == {}


def test_every_scene_section_reads_todays_default_per_scene():
    """liberty: today's default is the inspector's new choice (records of the method named in full with its model,
    and `willags` since INSPECTOR_SINCE), its earlier `willags` runs are the previous default; on the other real
    scenes the inspector's decision did not move, so today's default is willags-auto's records there."""
    from benchmarks.every_scene import INSPECTOR_SINCE, every_scene_section, mask_rows, sky_rows

    before, after = {"date": "2026-11-26T09:00:00"}, {"date": INSPECTOR_SINCE}
    recs = [
        _rec("liberty", "peer", 16.6),
        _rec("liberty", "peer", 16.7, tag="h200-r1b"),
        _rec("liberty", "willags", 15.0, subject_masked=0.45, static_obs_masked=0.1, **before),
        _rec("liberty", "willags-skyalpha-nomask", 19.0),
        _rec("liberty", "willags", 19.4, auto_config={"settings": {"use_mask": False}}, **after),
        _rec(
            "liberty",
            "willags-skyalpha-support",
            18.0,
            subject_masked=0.2,
            subject_masked_perceptual=0.25,
            static_obs_masked=0.04,
            static_obs_masked_perceptual=0.15,
        ),
        _rec("reichstag", "peer", 19.3),
        _rec("reichstag", "willags", 19.2, date="2026-11-26T08:00:00"),  # the default that inspects
    ]
    rows = sky_rows(recs)
    lib = [c.strip() for c in next(r for r in rows if r.startswith("| liberty")).strip("|").split("|")]
    assert lib[3] == "19.20 ±0.20 (n=2)" and lib[4] == "+2.55" and lib[5] == "met"
    assert lib[6] == "15.00 (n=1)" and lib[7] == "+4.20"
    rei = [c.strip() for c in next(r for r in rows if r.startswith("| reichstag")).strip("|").split("|")]
    assert rei[3] == "19.20 (n=1)" and rei[5] == "missed by 1.10" and rei[6] == "= willags"
    masks = mask_rows(recs)
    assert any("| liberty | willags (today) | 2 | no mask: nothing flagged |" in r for r in masks)
    assert any("| liberty | willags-skyalpha-support | 1 | 20.0 % | 25.0 % | 4.0 % | 15.0 % |" in r for r in masks)
    assert every_scene_section(recs)[0].startswith("## Every real scene")
    assert every_scene_section([_rec("fox-wild", "willags", 22.0)]) == []
