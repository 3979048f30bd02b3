"""benchmarks/regions.py: co-visibility by reprojected depth, the regions of a test view, PSNR per region, and the
maps a scored run writes (a tiny CPU run)."""

import json
import math

import numpy as np
import pytest

from benchmarks import regions as rg


def _look_at_plane(x: float) -> np.ndarray:
    """A nerfstudio camera (OpenGL axes) at (x, 0, 5) looking down -z at the plane z = 0."""
    c2w = np.zeros((3, 4))
    c2w[:, :3] = np.eye(3)
    c2w[:, 3] = [x, 0.0, 5.0]
    return c2w


def _view(x: float, depth: float = 5.0, size: int = 40, f: float = 40.0) -> dict:
    return {
        "c2w": _look_at_plane(x),
        "fx": f,
        "fy": f,
        "cx": size / 2,
        "cy": size / 2,
        "depth": np.full((size, size), depth),
    }


def test_lift_and_project_are_inverse():
    rng = np.random.default_rng(0)
    c2w = _look_at_plane(0.3)
    c2w[:, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    us, vs, d = rng.uniform(0, 40, 50), rng.uniform(0, 30, 50), rng.uniform(1, 9, 50)
    pts = rg.lift(d, c2w, 35.0, 36.0, 20.0, 15.0, us, vs)
    u2, v2, z = rg.project(pts, c2w, 35.0, 36.0, 20.0, 15.0)
    np.testing.assert_allclose(np.stack([u2, v2, z]), np.stack([us, vs, d]), atol=1e-9)


def test_a_point_counts_in_the_views_that_see_it_unoccluded():
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -3.0], [30.0, 0.0, 0.0]])  # on the plane, behind it, far aside
    views = [_view(0.0), _view(0.5), _view(-0.5), _view(1.0, depth=2.0)]  # the last one sees a nearer surface
    counts = rg.visible_counts(pts, views)
    assert counts.tolist() == [3, 0, 0]


def test_covisibility_of_a_test_view_counts_its_right_half_per_block():
    views = [_view(0.0), _view(0.5), _view(0.9)]
    depth = np.full((40, 40), 5.0)
    c = rg.covisibility(depth, _look_at_plane(0.0), 40.0, 40.0, 20.0, 20.0, views, block=2)
    assert c.shape == (20, 10)
    # the right half of the test view spans x in [0, 2.5) on the plane; a view at x0 sees (x0 - 2.5, x0 + 2.5)
    assert c.min() == 3
    shifted = rg.covisibility(depth, _look_at_plane(3.0), 40.0, 40.0, 20.0, 20.0, views, block=2)
    assert shifted.max() < 3 and shifted.min() == 0  # moved away: its far side is seen by none


def test_far_background_is_beyond_every_photographed_surface():
    pts = np.stack([np.linspace(-1, 1, 200), np.zeros(200), -np.linspace(0, 5, 200)], axis=-1)  # depths 5 to 10
    far = rg.far_depth(pts, _look_at_plane(0.0), 40.0, 40.0, 20.0, 20.0, 40, 40)
    assert 9.9 < far <= 10.0
    assert rg.far_depth(pts + [100.0, 0, 0], _look_at_plane(0.0), 40.0, 40.0, 20.0, 20.0, 40, 40) == float("inf")
    lab = rg.region_labels(np.full((1, 3), 3), np.ones((1, 3)), depth=np.array([[6.0, 9.0, 40.0]]), far=far)
    assert [rg.REGIONS[k] for k in lab[0]] == ["covisible", "covisible", "sky"]


def test_regions_and_their_psnr():
    covis = np.array([[3, 3, 1, 0]])
    acc = np.array([[1.0, 1.0, 1.0, 0.1]])
    err_a = np.array([[0.01, 0.01, 0.0001, 0.1]])
    lab = rg.region_labels(covis, acc)
    assert [rg.REGIONS[k] for k in lab[0]] == ["covisible", "covisible", "few", "sky"]
    s = rg.region_scores([err_a], [lab])
    assert s["covisible"]["psnr"] == pytest.approx(20.0) and s["covisible"]["share"] == 0.5
    assert s["few"]["psnr"] == pytest.approx(40.0) and math.isnan(s["unseen"]["psnr"])
    assert s["all"]["psnr"] == pytest.approx(-10 * math.log10(np.mean(err_a)))
    # every method errs over a whole 3x3 neighbourhood: outliers; one method right at a block: its neighbours
    # are not outliers either
    big = np.full((5, 5), 0.2)
    outlier = rg.REGIONS.index("outlier")
    lab = rg.region_labels(np.full((5, 5), 3), np.ones((5, 5)), [big, big])
    assert (lab == outlier).all()
    good = big.copy()
    good[2, 2] = 0.0
    lab = rg.region_labels(np.full((5, 5), 3), np.ones((5, 5)), [big, good])
    assert not (lab[1:4, 1:4] == outlier).any() and (lab[0] == outlier).all()


@pytest.mark.slow
def test_a_scored_run_writes_its_maps_and_the_report_reads_them(tmp_path, monkeypatch):
    from benchmarks.child import protocol_scores
    from tests.test_train import _train

    _, trainer, _ = _train(tmp_path / "run", steps=6)
    trainer.pipeline.model.eval()
    dumps = tmp_path / "dumps"
    monkeypatch.setenv(rg.REGIONS_ENV, str(dumps))
    spec = {"method": "willags", "protocol_steps": 2, "protocol_lr": 0.01, "max_test_images": 2, "scene_name": "s"}
    rec = protocol_scores(trainer, spec)
    with np.load(dumps / "s-willags.npz") as z:
        assert len(z["names"]) == 2
        err, covis, acc = z["rms_0"], z["covis_0"], z["acc_0"]
    assert err.shape == covis.shape == acc.shape and np.isfinite(err).all() and (covis >= 0).all()
    # the pooled right halves' PSNR is the protocol's right-half PSNR over those images (same pixels)
    with np.load(dumps / "s-willags.npz") as z:
        assert z["depth_0"].shape == err.shape and float(z["far_0"]) > 0  # the synthetic scene's points
    text = rg.report(dumps, tmp_path / "regions.md", tmp_path / "pictures", tmp_path / "regions.json")
    assert "| s | willags | 1 |" in text and (tmp_path / "pictures" / "s.png").exists()
    assert set(json.loads((tmp_path / "regions.json").read_text())["s"]["willags"]) == {"all", *rg.REGIONS}
    assert np.isfinite(rec["psnr"])


@pytest.mark.slow
def test_a_diagnosis_that_fails_leaves_the_protocols_scores_in_the_record(tmp_path, monkeypatch, capsys):
    """The training fit is scored after the protocol; if it fails, the record keeps the protocol's scores (a whole
    GPU run's worth) and names the failure, in the record and in the log."""
    from benchmarks.child import protocol_scores
    from tests.test_train import _train
    from willags_ns.eval import protocol

    _, trainer, _ = _train(tmp_path / "run", steps=6)

    def broken(*args, **kwargs):
        raise AttributeError("no attribute 'mask'")

    monkeypatch.setattr(protocol, "train_view_scores", broken)
    spec = {"method": "willags", "protocol_steps": 2, "protocol_lr": 0.01, "max_test_images": 2, "train_views": 2}
    rec = protocol_scores(trainer, spec)
    assert np.isfinite(rec["psnr"]) and len(rec["per_image"]) == 2 and rec["num_test_images"] >= 2
    assert rec["train_views_error"] == "AttributeError: no attribute 'mask'" and "train_psnr" not in rec
    assert "train_views failed" in capsys.readouterr().err
    monkeypatch.undo()
    rec = protocol_scores(trainer, {**spec, "scene_name": "s"})
    assert "train_views_error" not in rec and np.isfinite(rec["train_psnr"])
