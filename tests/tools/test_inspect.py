"""willags-inspect: the evidence separates synthetic scenes with and without appearance change / transients / open
background, the recommendation follows it, bad input gives one clear line (no traceback)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, project, write_ply_points, write_scene
from willags_ns.scripts import inspect as cli
from willags_ns.tools.inspection import (
    InspectConfig,
    InspectError,
    SceneViews,
    against,
    background_fractions,
    covered_cells,
    enclosed_fraction,
    format_report,
    inspect_scene,
    open_from_top,
    project_points,
    raw_colour_twins,
    read_scene,
    recommend,
    sky_flags,
    sky_settings,
    surround_fraction,
    zbuffer_visible,
)

SMALL = dict(num_train=20, num_test=2, width=96, height=72, num_points=3000, supersample=1)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Four small synthetic scenes: (appearance change?, transients?) -> scene directory."""
    root = tmp_path_factory.mktemp("inspect_scenes")
    out = {}
    for app in (False, True):
        for tr in (False, True):
            cfg = SyntheticSceneConfig(appearance_strength=float(app), transient_fraction=0.6 if tr else 0.0, **SMALL)
            out[(app, tr)] = write_scene(make_scene(cfg), root / f"app{int(app)}_tr{int(tr)}")
    return out


@pytest.fixture(scope="module")
def reports(scenes):
    return {k: inspect_scene(InspectConfig(data=d)) for k, d in scenes.items()}


def test_reader_projects_like_the_generator(scenes):
    """The transforms.json reader's OpenCV cameras put the points where the generator's OpenGL projection does."""
    scene = read_scene(scenes[(False, False)])
    gen = make_scene(SyntheticSceneConfig(appearance_strength=0.0, transient_fraction=0.0, **SMALL))
    for i in (0, 7):
        uv, z = project_points(scene.points, scene.w2c[i], scene.K[i], scene.dist[i])
        uv_ref, z_ref = project(gen.points.astype(np.float64), gen.c2w[i], gen.K)
        np.testing.assert_allclose(uv, uv_ref, atol=1e-3)
        np.testing.assert_allclose(z, z_ref, rtol=1e-6)


def test_zbuffer_hides_the_farther_point_of_a_cell():
    px = np.array([[1, 1], [2, 2], [20, 20]])
    z = np.array([1.0, 3.0, 3.0])
    assert zbuffer_visible(px, z, 32, 32, cell=8, tolerance=0.1).tolist() == [True, False, True]


def test_appearance_evidence_separates(reports):
    thr = InspectConfig().appearance_threshold
    for tr in (False, True):
        without, with_ = reports[(False, tr)]["evidence"], reports[(True, tr)]["evidence"]
        assert without["method"] == with_["method"] == "sfm-points"
        assert without["appearance_score"] < thr / 2, without["appearance_score"]
        assert with_["appearance_score"] > thr, with_["appearance_score"]


def test_transient_evidence_separates(reports):
    thr = InspectConfig().transient_threshold
    for app in (False, True):
        without, with_ = reports[(app, False)]["evidence"], reports[(app, True)]["evidence"]
        assert without["transient_score"] < thr / 2, without["transient_score"]
        assert with_["transient_score"] > thr, with_["transient_score"]
        assert with_["transient_fraction_mean"] > 3 * without["transient_fraction_mean"] + 0.01


def test_recommendation_follows_the_evidence(reports, scenes):
    expected = {
        (False, False): (False, False, "willags-3dgs"),
        (True, False): (True, False, "willags"),
        (False, True): (False, True, "willags"),
        (True, True): (True, True, "willags"),
    }
    for key, (app, mask, preset) in expected.items():
        rec = reports[key]["recommendation"]
        assert rec["appearance_latent"]["on"] is app and rec["mask"]["on"] is mask, (key, rec)
        assert rec["teacher"]["on"] is mask and rec["triplane_field"]["on"] is False
        assert rec["preset"]["value"] == preset
        for part in ("appearance_latent", "mask", "triplane_field", "latent_dim", "preset"):
            assert rec[part]["reason"], part
        assert "threshold" in rec["appearance_latent"]["reason"] and "threshold" in rec["mask"]["reason"]
        assert str(scenes[key]) in rec["command"]
    assert "--pipeline.model.mask.enabled False" in reports[(True, False)]["recommendation"]["preset"]["flags"]
    assert reports[(False, True)]["recommendation"]["latent_dim"]["value"] == 8
    # the train split is analysed: 20 of the 22 images
    assert reports[(True, True)]["facts"]["analysed_images"] == 20 and reports[(True, True)]["facts"]["images"] == 22


def test_thresholds_move_the_recommendation(scenes):
    rec = inspect_scene(InspectConfig(data=scenes[(False, False)], appearance_threshold=0.0))["recommendation"]
    assert rec["appearance_latent"]["on"] and rec["preset"]["value"] == "willags"


def _without_ply(src, dst):
    """A copy of the transforms.json scene `src` in `dst` without its ply (frames point at src's images)."""
    meta = json.loads((src / "transforms.json").read_text())
    meta.pop("ply_file_path")
    meta["frames"] = [{**f, "file_path": str(src / f["file_path"])} for f in meta["frames"]]
    (dst / "transforms.json").write_text(json.dumps(meta))
    return dst


def test_fallback_without_points(scenes, tmp_path):
    """A transforms.json scene without a ply: per-image colour statistics, transients not measured, said so."""
    report = inspect_scene(InspectConfig(data=_without_ply(scenes[(True, False)], tmp_path)))
    assert report["evidence"]["method"] == "global-color-stats"
    assert report["evidence"]["transient_score"] is None
    assert report["recommendation"]["mask"]["on"] and "not measured" in report["recommendation"]["mask"]["reason"]
    assert "no SfM points" in report["recommendation"]["appearance_latent"]["reason"]


def test_cli_writes_json_and_prints(scenes, tmp_path, capsys):
    out = tmp_path / "sub" / "report.json"
    assert cli.main(InspectConfig(data=scenes[(True, True)], output=out)) == 0
    printed = capsys.readouterr().out
    assert "preset: willags" in printed and "appearance_latent: ON" in printed
    report = json.loads(out.read_text())
    assert report["recommendation"]["mask"]["on"] is True
    assert set(report["facts"]["estimate"]) >= {"gpu_memory_gb", "gpu_hours", "cpu_hours", "rough", "how"}
    assert len(report["per_image"]["names"]) == len(report["per_image"]["per_image_color_change"]) == 20


def test_entrypoint(scenes, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["willags-inspect", "--data", str(scenes[(False, False)])])
    with pytest.raises(SystemExit) as exc:
        cli.entrypoint()
    assert exc.value.code == 0
    assert "preset: willags-3dgs" in capsys.readouterr().out


def _bad_inputs(tmp_path, scenes):
    missing = tmp_path / "nope"
    empty = tmp_path / "empty"
    empty.mkdir()
    no_images = tmp_path / "no_images"
    no_images.mkdir()
    (no_images / "transforms.json").write_text((scenes[(False, False)] / "transforms.json").read_text())
    broken_json = tmp_path / "broken_json"
    broken_json.mkdir()
    (broken_json / "transforms.json").write_text("{not json")
    bad_model = tmp_path / "bad_model"
    (bad_model / "sparse" / "0").mkdir(parents=True)
    for f in ("cameras.bin", "images.bin", "points3D.bin"):
        (bad_model / "sparse" / "0" / f).write_bytes(b"\x01\x02garbage")
    return {
        missing: str(missing),
        empty: str(empty),
        no_images: str(no_images / "images"),
        broken_json: str(broken_json / "transforms.json"),
        bad_model: str(bad_model / "sparse" / "0"),
    }


def test_bad_input_raises_naming_the_path(tmp_path, scenes):
    for data, named in _bad_inputs(tmp_path, scenes).items():
        with pytest.raises(InspectError) as exc:
            inspect_scene(InspectConfig(data=data))
        assert named in str(exc.value), (data, str(exc.value))


def test_bad_input_cli_one_line_no_traceback(tmp_path, scenes, capsys):
    for data, named in _bad_inputs(tmp_path, scenes).items():
        assert cli.main(InspectConfig(data=data)) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith("willags-inspect: ") and named in err and "\n" not in err, err
    # through the module's __main__, as a user runs it
    proc = subprocess.run(
        [sys.executable, "-m", "willags_ns.scripts.inspect", "--data", str(tmp_path / "nope")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr and str(tmp_path / "nope") in proc.stderr


@pytest.mark.data
def test_shared_fox_scenes(shared_data):
    clean = inspect_scene(InspectConfig(data=shared_data / "fox-clean"))
    transient = inspect_scene(InspectConfig(data=shared_data / "fox-transient-only"))
    appearance = inspect_scene(InspectConfig(data=shared_data / "fox-appearance-only"))
    # transients: only fox-transient-only needs the mask
    assert transient["recommendation"]["mask"]["on"]
    assert not clean["recommendation"]["mask"]["on"] and not appearance["recommendation"]["mask"]["on"]
    # appearance: the synthetic change of fox-appearance-only measures far above the phone video's exposure drift
    # (fox-clean and fox-transient-only share it: ~8 levels, above the threshold, so the cheap latent stays on)
    assert appearance["recommendation"]["appearance_latent"]["on"]
    drift = (clean["evidence"]["appearance_score"], transient["evidence"]["appearance_score"])
    assert max(drift) + 4 < appearance["evidence"]["appearance_score"], drift
    assert abs(drift[0] - drift[1]) < 2, drift


# --------------------------------------------------------------------------------------------------------------------
# evidence 4: open background (sky)

SKY_ON = "--pipeline.model.sky.enabled True"
SKY_OFF = "--pipeline.model.sky.enabled False"


def write_plane_scene(root, lower_only: bool, n: int = 8, width: int = 64, height: int = 48, column: bool = False):
    """n cameras looking down +z (OpenCV) from (x, 0, 0), x in [-1, 1], at a grid of points on the plane z = 10
    spaced 0.3 (1.5 px); lower_only keeps the points with y >= 0, which every camera sees in the lower half of its
    image (y down, cy = height / 2); column keeps the points with |x| <= 1, a narrow upright subject in the middle of
    every image with open background on both sides. Each image is a uniform grey of its own level (an appearance change of ~29
    levels, no transients), so the preset is willags and the sky switch shows in its command."""
    root.mkdir(parents=True)
    (root / "images").mkdir()
    f = 50.0
    xs = np.arange(-10.0, 10.0, 0.3)
    ys = np.arange(0.05, 6.0, 0.3) if lower_only else np.arange(-5.95, 6.0, 0.3)
    if column:
        xs = xs[np.abs(xs) <= 1.0]
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 10.0)], axis=1)
    write_ply_points(root / "points.ply", pts.astype(np.float32), np.full((len(pts), 3), 128, dtype=np.uint8))
    frames = []
    for i, (x, grey) in enumerate(zip(np.linspace(-1.0, 1.0, n), np.linspace(0.3, 0.7, n), strict=True)):
        name = f"images/{i:03d}.png"
        Image.fromarray(np.full((height, width, 3), round(grey * 255), dtype=np.uint8)).save(root / name)
        c2w = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV identity rotation in nerfstudio's OpenGL axes
        c2w[0, 3] = x
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    meta = dict(fl_x=f, fl_y=f, cx=width / 2, cy=height / 2, w=width, h=height, frames=frames)
    (root / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "points.ply"}))
    return root


@pytest.fixture(scope="module")
def plane_reports(tmp_path_factory):
    root = tmp_path_factory.mktemp("plane_scenes")
    return {
        lower: inspect_scene(InspectConfig(data=write_plane_scene(root / f"lower{int(lower)}", lower)))
        for lower in (True, False)
    }


def test_covered_cells_known_answers():
    # a point in the middle of a 32 x 32 grid covers its cell and, dilated, the 8 around it
    cov = covered_cells(np.array([[16.5, 16.5]]), 32.0, 32.0, grid=32)
    assert cov.shape == (32, 32) and cov.sum() == 9 and cov[15:18, 15:18].all()
    # a corner point: 4 cells; points outside the image count for nothing
    assert covered_cells(np.array([[0.2, 0.2], [-5.0, 3.0], [40.0, 3.0]]), 32.0, 32.0, grid=32).sum() == 4
    # portrait image: 32 cells along the long (vertical) side, 24 across
    assert covered_cells(np.zeros((0, 2)), 48.0, 64.0, grid=32).shape == (32, 24)
    assert not covered_cells(np.zeros((0, 2)), 48.0, 64.0, grid=32).any()


def test_lower_half_covered_is_half_background_and_wants_the_sky(plane_reports):
    report = plane_reports[True]
    frac = report["per_image"]["per_image_background_fraction"]
    # 24 cell rows: the points fill rows 12-23, the dilation adds row 11, rows 0-10 are open
    assert len(frac) == 8 and np.allclose(frac, 11 / 24), frac
    ev, rec = report["evidence"], report["recommendation"]
    assert ev["background_score"] == pytest.approx(11 / 24) and ev["background_fraction_mean"] == pytest.approx(11 / 24)
    assert rec["preset"]["value"] == "willags" and rec["sky"]["on"] is True and rec["sky"]["measured"] is True
    assert "0.46" in rec["sky"]["reason"] and ">= threshold" in rec["sky"]["reason"]
    # the willags default has the sky: turning it on needs no flag, and none switches it off
    assert sky_flags("skyline") == [] and SKY_OFF not in rec["preset"]["flags"] and SKY_OFF not in rec["command"]
    assert "sky: ON  skyline" in format_report(report) and rec["sky"]["mode"] == "skyline"
    # a plane under the sky: what SfM covers has open background only above it, never on both sides
    assert ev["surround_score"] == 0.0 and "< threshold 0.6" in rec["sky"]["reason"]


def test_fully_covered_has_no_background_and_no_sky(plane_reports):
    report = plane_reports[False]
    assert report["per_image"]["per_image_background_fraction"] == [0.0] * 8
    rec = report["recommendation"]
    assert rec["preset"]["value"] == "willags" and rec["sky"]["on"] is False
    assert "< threshold" in rec["sky"]["reason"]
    assert sky_flags("off") == [SKY_OFF] and SKY_OFF in rec["command"]


def test_sky_threshold_moves_the_recommendation(tmp_path):
    scene = write_plane_scene(tmp_path / "lower", lower_only=True)
    rec = inspect_scene(InspectConfig(data=scene, sky_threshold=0.6))["recommendation"]
    assert rec["sky"]["on"] is False and SKY_OFF in rec["command"]


def test_synthetic_dome_scenes_have_no_open_background(reports):
    """The synthetic world is closed (a textured dome: every ray hits something), so its points cover the images."""
    thr = InspectConfig().sky_threshold
    for key, report in reports.items():
        assert report["evidence"]["background_score"] < thr / 2, (key, report["evidence"]["background_score"])
        assert report["recommendation"]["sky"]["on"] is False


def _evidence(appearance: float, transient: float, transient_mean: float, background: float, background_mean: float):
    """The evidence `recommend` reads, as an SfM-point inspection of scene "x" reports it."""
    return dict(
        data="x",
        method="sfm-points",
        appearance_score=appearance,
        transient_score=transient,
        transient_fraction_mean=transient_mean,
        background_score=background,
        background_fraction_mean=background_mean,
    )


def test_plain_3dgs_gets_no_sky():
    """Open background without appearance change or transients: willags-3dgs, which has no latent for a sky."""
    evidence = _evidence(0.5, 0.0, 0.0, 0.5, 0.5)
    rec = recommend(evidence, 40, InspectConfig())
    assert rec["preset"]["value"] == "willags-3dgs" and rec["preset"]["flags"] == []
    assert rec["sky"]["on"] is False and "no latent" in rec["sky"]["reason"]
    rec = recommend({**evidence, "appearance_score": 20.0}, 40, InspectConfig())
    assert rec["preset"]["value"] == "willags" and rec["sky"]["on"] is True


def test_a_reason_never_prints_a_value_on_the_wrong_side_of_its_threshold():
    """A score just under its threshold reads with the decimals that show it under, not rounded onto it."""
    assert against(0.1496, 0.15) == "0.1496" and against(0.1504, 0.15) == "0.15" and against(0.37, 0.15) == "0.37"
    assert against(0.15, 0.15) == "0.15" and against(3.96, 4.0, 1) == "3.96" and against(12.6, 4.0, 1) == "12.6"
    evidence = _evidence(12.6, 0.1199, 0.01, 0.1496, 0.16)
    rec = recommend(evidence, 40, InspectConfig(sky_threshold=0.15, transient_threshold=0.12))
    assert rec["sky"]["on"] is False and "covers 0.1496 (mean 0.16) < threshold 0.15" in rec["sky"]["reason"]
    assert rec["mask"]["on"] is False and rec["mask"]["reason"].startswith("0.1199 of the images")


def test_background_ignores_points_folded_in_by_distortion():
    """A strong barrel distortion (k1 = -0.3) maps a point far outside the field of view (pinhole u = 132 in a
    64 px image) back inside; it must not cover the image."""
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    w2c = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    point = np.array([[2.0, 0.0, 1.0]])
    uv, _ = project_points(point, w2c, K, np.array([-0.3, 0.0, 0.0, 0.0]))
    assert 0 <= uv[0, 0] < 64, uv  # folded in: the case the guard is for
    scene = SceneViews(
        kind="transforms",
        root=Path("."),
        image_paths=[Path("a.png")],
        w2c=w2c[None],
        K=K[None],
        dist=np.array([[-0.3, 0.0, 0.0, 0.0]]),
        cam_size=np.array([[64.0, 48.0]]),
        points=point,
    )
    assert background_fractions(scene, np.array([0]), 32).tolist() == [1.0]
    scene.dist = np.zeros((1, 4))
    scene.points = np.array([[0.0, 0.0, 1.0]])  # on the optical axis: covered, 3 x 3 of 32 x 24 cells
    assert background_fractions(scene, np.array([0]), 32)[0] == pytest.approx(1 - 9 / (32 * 24))


def test_without_points_the_sky_is_not_measured(scenes, tmp_path):
    report = inspect_scene(InspectConfig(data=_without_ply(scenes[(True, False)], tmp_path)))
    assert report["evidence"]["background_score"] is None
    sky = report["recommendation"]["sky"]
    # the method's own setting (the willags default's sky: on), so the command names no sky flag
    assert sky["measured"] is False and sky["on"] is True and "not measured" in sky["reason"]
    command = report["recommendation"]["command"]
    assert "method's own setting" in sky["reason"] and SKY_ON not in command and SKY_OFF not in command
    assert "open background not measured" in format_report(report)


@pytest.mark.data
def test_shared_scenes_sky(shared_data):
    """The Internet photo collections have open background (sky); the fox close-up and south-building's facade
    do not (docs/inspect.md)."""
    thr = InspectConfig().sky_threshold
    for name, sky in (("fox-clean", False), ("south-building", False), ("reichstag", True), ("sacre-coeur-mini", True)):
        report = inspect_scene(InspectConfig(data=shared_data / name))
        score = report["evidence"]["background_score"]
        assert report["recommendation"]["sky"]["on"] is sky, (name, score)
        assert (score > 2 * thr) if sky else (score < thr / 2), (name, score)


# --------------------------------------------------------------------------------------------------------------------
# the sky's mode: a subject against the sky


def test_open_from_top_and_surround_known_answers():
    covered = np.zeros((6, 8), dtype=bool)
    covered[2:, 3:5] = True  # an upright subject in the middle, from row 2 down
    sky = open_from_top(covered)
    assert sky.sum() == 48 - 8 and not (sky & covered).any()
    assert surround_fraction(covered) == 1.0  # every covered cell has sky to its left and right
    wall = np.zeros((6, 8), dtype=bool)
    wall[2:] = True  # a building across the whole width: sky only above it
    assert open_from_top(wall).sum() == 16 and surround_fraction(wall) == 0.0
    plaza = wall.copy()
    plaza[4:, 2:6] = False  # an uncovered plaza under the facade is not connected to the top: not sky
    assert open_from_top(plaza).sum() == 16 and surround_fraction(plaza) == 0.0
    tower = wall.copy()
    tower[2:4, :3] = False  # the left part of the top rows is sky: the covered cells there have sky on one side
    assert open_from_top(tower).sum() == 22 and surround_fraction(tower) == 0.0
    assert surround_fraction(np.zeros((4, 4), dtype=bool)) == 0.0  # nothing covered
    assert enclosed_fraction(plaza) == 8 / 48  # the plaza under the facade: ground, not sky
    assert enclosed_fraction(wall) == enclosed_fraction(covered) == enclosed_fraction(tower) == 0.0


@pytest.mark.data
def test_shared_scenes_ground_under_the_subject(shared_data):
    """reichstag's plaza, where the crowds stand, is open ground under the facade; no other shared scene has any
    (docs/inspect.md). Printed, and a hint in the mask's reason: reichstag's mask stays off."""
    for name, ground in (("reichstag", True), ("liberty", False), ("sacre-coeur-mini", False), ("fox-clean", False)):
        report = inspect_scene(InspectConfig(data=shared_data / name))
        score = report["evidence"]["ground_score"]
        assert (score > 0.1) if ground else (score < 0.03), (name, score)
        assert f"ground under it {score:.2f} (median)" in format_report(report)
        assert len(report["per_image"]["per_image_ground_fraction"]) == len(report["per_image"]["names"])
    reichstag = inspect_scene(InspectConfig(data=shared_data / "reichstag"))["recommendation"]["mask"]
    assert reichstag["on"] is False and "try --pipeline.model.mask.enabled True" in reichstag["reason"]
    liberty = inspect_scene(InspectConfig(data=shared_data / "liberty"))["recommendation"]["mask"]
    assert "ground under the subject" not in liberty["reason"]


def test_ground_under_the_subject_hints_at_the_mask_and_switches_nothing():
    """Open ground under the subject (a plaza SfM left empty) adds a hint to try the mask to its reason when the
    transient count keeps it off; it never turns the mask on, and says nothing when the mask is on or the ground low."""
    cfg = InspectConfig(ground_hint_threshold=0.1, transient_threshold=0.12)
    crowds = {**_evidence(12.0, 0.02, 0.007, 0.37, 0.37), "ground_score": 0.16}
    rec = recommend(crowds, 40, cfg)
    assert rec["mask"]["on"] is False and "--pipeline.model.mask.enabled False" in rec["command"]
    assert "ground under the subject 0.16 >= 0.1" in rec["mask"]["reason"]
    assert "try --pipeline.model.mask.enabled True" in rec["mask"]["reason"]
    for evidence in (
        {**crowds, "ground_score": 0.0999},
        {**crowds, "ground_score": None},
        {**crowds, "transient_score": 0.2},
    ):
        assert "ground under the subject" not in recommend(evidence, 40, cfg)["mask"]["reason"], evidence
    assert recommend({**crowds, "transient_score": 0.2}, 40, cfg)["mask"]["on"] is True


def test_a_subject_against_the_sky_gets_the_surround_sky(tmp_path):
    report = inspect_scene(InspectConfig(data=write_plane_scene(tmp_path / "column", lower_only=False, column=True)))
    ev, sky = report["evidence"], report["recommendation"]["sky"]
    assert ev["surround_score"] > 0.9 and ev["background_score"] > 0.5
    assert sky["on"] and sky["mode"] == "surround" and ">= threshold 0.6" in sky["reason"]
    command = report["recommendation"]["command"]
    assert "--pipeline.model.sky.region everywhere" in command and "--pipeline.model.sky.alpha-penalty 0.1" in command
    assert "sky: ON  surround" in format_report(report)
    high = inspect_scene(InspectConfig(data=tmp_path / "column", surround_threshold=1.01))["recommendation"]
    assert high["sky"]["mode"] == "skyline" and "sky.region" not in high["command"]


def test_sky_modes_map_to_settings_and_flags():
    assert sky_settings("off")["sky.enabled"] is False
    assert sky_settings("surround") == {"sky.enabled": True, "sky.region": "everywhere", "sky.alpha_penalty": 0.1}
    assert sky_flags("surround") == ["--pipeline.model.sky.region everywhere", "--pipeline.model.sky.alpha-penalty 0.1"]
    with pytest.raises(ValueError, match="unknown sky mode 'on'"):
        sky_settings("on")


# --------------------------------------------------------------------------------------------------------------------
# transients: a colour that recurs in another photo is light, not an occluder


def test_raw_colour_twins():
    colors = np.full((2, 4, 3), np.nan, dtype=np.float32)
    colors[0] = [[0.5] * 3, [0.1] * 3, [0.12] * 3, [0.5] * 3]  # the dark photo 1 has a twin (photo 2)
    colors[1, :3] = [[0.5] * 3, [0.9] * 3, [0.5] * 3]  # the bright photo 1 has none
    seen = ~np.isnan(colors[..., 0])
    cand = np.zeros((2, 4), dtype=bool)
    cand[0, 1] = cand[1, 1] = True
    twins = raw_colour_twins(colors, seen, cand, 0.1)
    assert twins[0, 1] and not twins[1, 1] and twins.sum() == 1  # only candidates are marked
    assert not raw_colour_twins(colors, seen, cand, 0.01).any()


def test_shared_scenes_transients_and_sky_modes(shared_data):
    """liberty (a statue against the sky, photographed under every light, no occluder in its photos): no mask, the
    sky behind every pixel; the other shared scenes keep their decisions (docs/inspect.md)."""
    expected = {  # name: (mask, sky mode)
        "liberty": (False, "surround"),
        "reichstag": (False, "skyline"),
        "sacre-coeur-mini": (True, "skyline"),
        "south-building": (False, "off"),
        "fox-wild": (True, "off"),
        "fox-transient-only": (True, "off"),
        "fox-clean": (False, "off"),
    }
    for name, (mask, mode) in expected.items():
        rec = inspect_scene(InspectConfig(data=shared_data / name))["recommendation"]
        assert (rec["mask"]["on"], rec["sky"]["mode"]) == (mask, mode), (name, rec["mask"], rec["sky"])


def test_the_time_estimate_follows_the_resolution_schedule_the_run_trains_with():
    """One estimate of time: the run trains at 1/4 size for 3000 steps, 1/2 for 3000, then full size, and the
    estimate counts each step at its size (a step at full size alone would overstate it ~1.2x; the first size alone,
    what an ETA early in the run sees, understates it ~15x on 800x571 photos)."""
    import numpy as np

    from willags_ns.tools.inspection import InspectConfig, resolution_spans, resource_estimate

    assert resolution_spans(30000) == {2: 3000, 1: 3000, 0: 24000}
    assert resolution_spans(4000) == {2: 3000, 1: 1000} and resolution_spans(500) == {2: 500}
    sizes = np.array([[800, 571]] * 12)
    est = resource_estimate(12, sizes, 3975, InspectConfig(data=None, steps=30000))
    hours = est["cpu_hours"]
    full, first = est["cpu_full_step_s"], est["cpu_first_step_s"]
    assert first < full
    want = (3000 * first + 3000 * full / 4 + 24000 * full) / 3600
    assert abs(hours - want) < 0.1 and first * 30000 / 3600 < hours < full * 30000 / 3600


def test_the_resource_estimate_stops_at_the_defaults_gaussian_cap():
    import numpy as np

    from willags_ns.splats.mcmc import McmcConfig
    from willags_ns.tools.inspection import InspectConfig, resource_estimate

    cfg = InspectConfig()
    assert cfg.max_gaussians == McmcConfig().cap_max
    sizes = np.array([[800, 600]] * 10)
    assert resource_estimate(10, sizes, 1_000_000, cfg)["expected_gaussians"] == cfg.max_gaussians
    assert resource_estimate(10, sizes, 12_000, cfg)["expected_gaussians"] == 120_000


def test_the_estimate_counts_the_photos_at_the_size_training_reads_them(scenes, tmp_path, monkeypatch):
    """Training reads photos above 1600 px at 1/2**k of their size (the data parser's rule) or at the factor given:
    the time and memory estimate counts the pixels of that size, and says which factor it used."""
    from willags_ns.data.dataparser import auto_downscale_factor, downscale_for_side
    from willags_ns.tools import inspection as insp

    folder = tmp_path / "images"
    folder.mkdir()
    Image.new("RGB", (3300, 8)).save(folder / "a.png")  # the first by name decides
    Image.new("RGB", (100, 8)).save(folder / "b.png")
    assert downscale_for_side(3300) == auto_downscale_factor(folder) == 4
    assert [downscale_for_side(s) for s in (1600, 1601, 8000)] == [1, 2, 8]
    seen = []
    real = insp.resource_estimate

    def spy(n, sizes, points, cfg):
        seen.append(sizes)
        return real(n, sizes, points, cfg)

    monkeypatch.setattr(insp, "resource_estimate", spy)
    full = insp.inspect_scene(InspectConfig(data=scenes[(True, True)]))["facts"]["estimate"]
    half = insp.inspect_scene(InspectConfig(data=scenes[(True, True)], downscale_factor=2))["facts"]["estimate"]
    assert (full["downscale_factor"], half["downscale_factor"]) == (1, 2)  # the synthetic photos are small
    np.testing.assert_allclose(seen[1], seen[0] / 2)


def test_the_report_says_how_many_gaussians_the_method_trains_and_what_the_other_rule_would_allow(plane_reports):
    from willags_ns.splats.mcmc import McmcConfig, scene_cap

    report = plane_reports[True]
    mpx = report["facts"]["train_megapixels"]
    (line,) = [ln for ln in format_report(report).splitlines() if ln.startswith("  capacity: ")]
    assert f"MCMC grows to at most {McmcConfig().cap_max:,} Gaussians (rule fixed" in line
    assert f"cap-rule pixels would allow {scene_cap(mpx, McmcConfig())[0]:,} for these {mpx:.1f} Mpx" in line
    assert "more (--pipeline.model.mcmc.cap-max 1000000) cost training time" in line  # the other side of the trade
    assert "on a CPU splatfacto's densification" in line
