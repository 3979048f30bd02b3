"""benchmarks.placement: a model's cameras against the true poses, up to a similarity; placed = registered, near the
true centre and turned like the true camera."""

import json

import numpy as np
import pytest

from benchmarks import placement as pl


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _truth(n: int = 30, seed: int = 0) -> dict[str, np.ndarray]:
    """Cameras on a ring of radius 3 looking roughly inwards (world-to-camera)."""
    rng = np.random.default_rng(seed)
    out = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        c2w = np.eye(4)
        c2w[:3, :3] = _random_rotation(rng)
        c2w[:3, 3] = [3 * np.cos(a), 3 * np.sin(a), rng.uniform(0.5, 1.5)]
        out[f"{i:04d}.jpg"] = np.linalg.inv(c2w)
    return out


def _moved(w2c: dict[str, np.ndarray], scale: float, rot: np.ndarray, shift: np.ndarray) -> dict[str, np.ndarray]:
    """The same cameras in another frame: world' = scale * rot @ world + shift."""
    sim = np.eye(4)
    sim[:3, :3], sim[:3, 3] = scale * rot, shift
    out = {}
    for name, m in w2c.items():
        c2w = sim @ np.linalg.inv(m)
        c2w[:3, :3] /= scale  # keep a rotation
        out[name] = np.linalg.inv(c2w)
    return out


def test_a_model_in_another_frame_is_placed_everywhere():
    truth = _truth()
    rng = np.random.default_rng(1)
    est = _moved(truth, 0.37, _random_rotation(rng), np.array([5.0, -2.0, 1.0]))
    r = pl.placement(est, truth)
    assert r["compared"] == r["total"] == 30
    assert r["placed"] == r["within_5pct"] == 1.0
    assert r["median_center_error_rel"] < 1e-9 and r["max_rotation_error_deg"] < 1e-6
    assert r["pairwise_distance_correlation"] == pytest.approx(1.0)


def test_moved_turned_and_missing_photos_are_not_placed():
    truth = _truth()
    est = {k: v.copy() for k, v in truth.items()}
    names = sorted(truth)
    del est[names[0]], est[names[1]]  # not registered
    c2w = np.linalg.inv(est[names[2]])
    c2w[:3, 3] += [0.0, 0.0, 0.6]  # a fifth of the radius away
    est[names[2]] = np.linalg.inv(c2w)
    turn = np.array([[np.cos(0.3), -np.sin(0.3), 0.0], [np.sin(0.3), np.cos(0.3), 0.0], [0.0, 0.0, 1.0]])
    c2w = np.linalg.inv(est[names[3]])
    c2w[:3, :3] = c2w[:3, :3] @ turn  # 17 degrees off, centre right
    est[names[3]] = np.linalg.inv(c2w)
    r = pl.placement(est, truth)
    assert r["compared"] == 28 and r["total"] == 30
    assert r["within_5pct"] == pytest.approx(27 / 28)  # the moved one (the turned one's centre is right)
    assert r["placed"] == pytest.approx(26 / 30)  # neither the missing two nor the moved or the turned one
    assert r["max_rotation_error_deg"] == pytest.approx(np.degrees(0.3), abs=0.5)
    assert r["max_center_error_rel"] > 0.15


def test_a_folded_model_is_registered_but_not_placed():
    """Every camera registered at another camera's place (what repeated textures do): nothing placed."""
    truth = _truth(40)
    names = sorted(truth)
    shuffled = np.random.default_rng(2).permutation(len(names))
    est = {n: truth[names[j]] for n, j in zip(names, shuffled, strict=True)}
    r = pl.placement(est, truth)
    assert r["compared"] == 40
    assert r["placed"] < 0.2 and r["median_center_error_rel"] > 0.3
    assert abs(r["pairwise_distance_correlation"]) < 0.5


def test_too_few_photos_in_common_is_one_clear_error():
    truth = _truth()
    est = {k: truth[k] for k in sorted(truth)[:2]}
    with pytest.raises(ValueError, match="need >= 3 photos"):
        pl.placement(est, truth)


def test_the_command_reads_colmap_models_and_names_a_missing_one(tmp_path, capsys):
    pytest.importorskip("pycolmap")
    from benchmarks import scale
    from willags_ns.tools.sfm import model_w2c

    src = scale.synthetic_source(tmp_path / "src", views=8, long_side=48, points=200)
    model = src / "colmap" / "sparse" / "0"
    assert pl.main(["--truth", str(model), "--model", str(model)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["placed"] == 1.0 and out["total"] == len(model_w2c(model)) == 8
    assert pl.main(["--truth", str(model), "--model", str(tmp_path / "nothing")]) == 2
    assert "cannot read the model" in capsys.readouterr().err
