"""The embedded synthetic in-the-wild scene: determinism, exact transient masks, clean test views, camera conventions,
seed points, the written layout (read back by nerfstudio's own parser) and the cache's atomic writes."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from willags_ns.data import synthetic
from willags_ns.data.synthetic import (
    COMPLETE_MARKER,
    SyntheticSceneConfig,
    apply_appearance,
    camera_rays,
    ensure_default_scene,
    make_objects,
    make_scene,
    project,
    scene_dir_for,
    to_uint8,
    trace,
    write_scene,
)

SMALL = SyntheticSceneConfig(num_train=10, num_test=3, width=48, height=32, num_points=1500)


@pytest.fixture(scope="module")
def scene():
    return make_scene(SMALL)


@pytest.fixture(scope="module")
def written(scene, tmp_path_factory):
    return write_scene(scene, tmp_path_factory.mktemp("syn") / "scene")


def _tree_bytes(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_gives_identical_bytes(scene, written, tmp_path):
    again = write_scene(make_scene(SMALL), tmp_path / "again")
    a, b = _tree_bytes(written), _tree_bytes(again)
    assert a.keys() == b.keys() and len(a) > 20
    assert all(a[k] == b[k] for k in a)
    other = make_scene(replace(SMALL, seed=1))
    assert not np.array_equal(other.images, scene.images)


def test_shapes_and_split(scene):
    n = SMALL.num_train + SMALL.num_test
    assert scene.images.shape == (n, SMALL.height, SMALL.width, 3) and scene.images.dtype == np.uint8
    assert scene.clean.shape == scene.images.shape and scene.masks.shape == (n, SMALL.height, SMALL.width)
    assert scene.split.count("train") == SMALL.num_train and scene.split.count("test") == SMALL.num_test
    assert scene.points.shape == (SMALL.num_points, 3) and scene.colors.shape == (SMALL.num_points, 3)
    assert scene.colors.dtype == np.uint8
    # test views are spread among the training views, not bunched at one end of the ring
    test_idx = np.flatnonzero(~scene.is_train)
    assert test_idx.min() < n / 2 < test_idx.max()


def test_images_differ_from_appearance_only_inside_masks(scene):
    for i in np.flatnonzero(scene.is_train):
        expected = to_uint8(apply_appearance(scene.clean[i] / 255.0, scene.appearance[i]))
        m = scene.masks[i]
        np.testing.assert_array_equal(scene.images[i][~m], expected[~m])
        if m.any():  # the occluders are opaque random colours: (nearly) every masked pixel changed
            changed = np.any(scene.images[i] != expected, axis=-1)
            assert changed[m].mean() > 0.95


def test_occluder_count_and_coverage(scene):
    train = np.flatnonzero(scene.is_train)
    occluded = [i for i in train if scene.occluders[i]]
    assert len(occluded) == round(SMALL.transient_fraction * SMALL.num_train)
    lo, hi = SMALL.transient_coverage
    for i in train:
        cov = scene.masks[i].mean()
        assert (lo <= cov <= hi) if scene.occluders[i] else cov == 0


def test_test_images_have_no_transients(scene):
    for i in np.flatnonzero(~scene.is_train):
        assert not scene.masks[i].any() and scene.occluders[i] == []
        np.testing.assert_array_equal(
            scene.images[i], to_uint8(apply_appearance(scene.clean[i] / 255.0, scene.appearance[i]))
        )


def test_appearance_really_changes_images_and_strength_zero_disables_it(scene):
    test = np.flatnonzero(~scene.is_train)
    diff = np.abs(scene.images[test].astype(int) - scene.clean[test].astype(int)).mean()
    assert diff > 5
    plain = make_scene(replace(SMALL, appearance_strength=0.0, transient_fraction=0.0))
    np.testing.assert_array_equal(plain.images, plain.clean)
    np.testing.assert_array_equal(plain.clean, scene.clean)  # same geometry and cameras whatever the nuisances


def test_nuisance_streams_are_independent(scene):
    """Dropping the occluders keeps the appearance parameters (like the fox-* variants)."""
    no_occ = make_scene(replace(SMALL, transient_fraction=0.0))
    assert no_occ.appearance == scene.appearance and not no_occ.masks.any()


def test_cameras_look_at_the_scene(scene):
    centre = np.array([[0.0, 0.0, 0.35]])
    for c2w in scene.c2w:
        r = c2w[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
        assert np.linalg.det(r) == pytest.approx(1.0)
        assert c2w[2, 3] > 0  # above the ground
        xy, depth = project(centre, c2w, scene.K)
        assert depth[0] > 0
        assert 0 <= xy[0, 0] < SMALL.width and 0 <= xy[0, 1] < SMALL.height
        assert c2w[2, 1] > 0  # camera y is up-ish: the ground is at the bottom of the image (OpenGL convention)


def test_rays_and_projection_agree_on_pixel_centres(scene):
    o, d = camera_rays(scene.c2w[0], scene.K, SMALL.width, SMALL.height, supersample=1)
    pts = (o + 3.0 * d)[:, :, 0, :].reshape(-1, 3)
    xy, depth = project(pts, scene.c2w[0], scene.K)
    grid = np.stack(np.meshgrid(np.arange(SMALL.width) + 0.5, np.arange(SMALL.height) + 0.5), -1).reshape(-1, 2)
    np.testing.assert_allclose(xy, grid, atol=1e-9)
    assert (depth > 0).all()


def test_every_ray_hits_and_shading_is_bounded(scene):
    o, d = camera_rays(scene.c2w[3], scene.K, SMALL.width, SMALL.height, supersample=1)
    t, obj, rgb = trace(o.reshape(-1, 3), d.reshape(-1, 3), make_objects(SMALL), SMALL.seed)
    assert np.isfinite(t).all() and (obj >= 0).all()
    assert (rgb >= 0).all() and (rgb <= 1).all()
    assert len(np.unique(obj)) >= 3  # the view sees the ground, the dome and objects


def test_seed_points_project_onto_their_colours(scene):
    objects = make_objects(SMALL)
    errs, shuffled = [], []
    rng = np.random.default_rng(0)
    for i in np.flatnonzero(scene.is_train):
        xy, depth = project(scene.points.astype(np.float64), scene.c2w[i], scene.K)
        inside = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < SMALL.width) & (xy[:, 1] >= 0) & (xy[:, 1] < SMALL.height)
        p = scene.points[inside].astype(np.float64)
        o = np.broadcast_to(scene.c2w[i, :3, 3], p.shape)
        dist = np.linalg.norm(p - o, axis=1)
        t, _, _ = trace(o, (p - o) / dist[:, None], objects, SMALL.seed)
        visible = np.abs(t - dist) < 0.05  # not hidden behind another surface in this view
        px = np.floor(xy[inside][visible]).astype(int)
        seen = scene.clean[i][px[:, 1], px[:, 0]].astype(int)
        cols = scene.colors[inside][visible].astype(int)
        errs.append(np.abs(seen - cols).max(axis=1))
        shuffled.append(np.abs(seen - rng.permutation(cols)).max(axis=1))
    err, base = np.concatenate(errs), np.concatenate(shuffled)
    assert len(err) > 1000
    assert np.median(err) < 20 and np.median(err) < 0.4 * np.median(base)


def test_written_layout(scene, written):
    meta = json.loads((written / "transforms.json").read_text())
    train = [f"images/{n}" for n, s in zip(scene.filenames, scene.split, strict=True) if s == "train"]
    test = [f"images/{n}" for n, s in zip(scene.filenames, scene.split, strict=True) if s == "test"]
    assert meta["train_filenames"] == train and meta["test_filenames"] == test == meta["val_filenames"]
    assert (meta["w"], meta["h"]) == (SMALL.width, SMALL.height) and meta["ply_file_path"] == "sparse_pc.ply"
    assert len(meta["frames"]) == len(scene.filenames)
    for i, name in enumerate(scene.filenames):
        stem = Path(name).stem
        np.testing.assert_array_equal(np.asarray(Image.open(written / "images" / name)), scene.images[i])
        if scene.split[i] == "train":
            mask = np.asarray(Image.open(written / "masks_gt" / f"{stem}.png"))
            np.testing.assert_array_equal(mask == 255, scene.masks[i])
            assert not (written / "gt_clean" / f"{stem}.png").exists()
        else:
            np.testing.assert_array_equal(np.asarray(Image.open(written / "gt_clean" / f"{stem}.png")), scene.clean[i])
            assert not (written / "masks_gt" / f"{stem}.png").exists()
    app = json.loads((written / "appearance.json").read_text())["images"]
    assert app[scene.filenames[0]]["exposure"] == scene.appearance[0]["exposure"]
    assert (written / COMPLETE_MARKER).is_file() and (written / "README.md").is_file()


def test_ply_round_trip(scene, written):
    from willags_ns.data.dataparser import read_ply_points

    xyz, rgb = read_ply_points(written / "sparse_pc.ply")
    np.testing.assert_array_equal(xyz, scene.points)
    np.testing.assert_array_equal(rgb, scene.colors)


def test_written_folder_loads_with_nerfstudio_parser(scene, written):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    # load_3D_points=False: nerfstudio reads the ply with open3d, which may not import (see test_dataparser)
    parser = NerfstudioDataParserConfig(data=written, load_3D_points=False).setup()
    train = parser.get_dataparser_outputs("train")
    test = parser.get_dataparser_outputs("test")
    expected = [n for n, s in zip(scene.filenames, scene.split, strict=True) if s == "train"]
    assert [p.name for p in train.image_filenames] == expected
    assert len(test.image_filenames) == SMALL.num_test
    assert int(train.cameras.width[0]) == SMALL.width and int(train.cameras.height[0]) == SMALL.height
    assert float(train.cameras.fx[0]) == pytest.approx(scene.K[0, 0])


def test_ensure_default_scene_caches_and_reuses(tmp_path, monkeypatch):
    cfg = replace(SMALL, num_train=3, num_test=1, num_points=100)
    path = ensure_default_scene(cfg, root=tmp_path)
    assert path == scene_dir_for(cfg, tmp_path) and path.name.startswith("default-")
    assert (path / COMPLETE_MARKER).is_file()

    def boom(*args, **kwargs):
        raise AssertionError("a complete cached scene must not be regenerated")

    monkeypatch.setattr(synthetic, "make_scene", boom)
    assert ensure_default_scene(cfg, root=tmp_path) == path
    # another config -> another directory
    assert scene_dir_for(replace(cfg, seed=5), tmp_path) != path


def test_ensure_default_scene_replaces_an_interrupted_write(tmp_path):
    cfg = replace(SMALL, num_train=3, num_test=1, num_points=100)
    dst = scene_dir_for(cfg, tmp_path)
    (dst / "images").mkdir(parents=True)
    (dst / "images" / "junk.png").write_bytes(b"half")
    path = ensure_default_scene(cfg, root=tmp_path)
    assert (path / COMPLETE_MARKER).is_file() and not (path / "images" / "junk.png").exists()
    assert len(list((path / "images").iterdir())) == 4


def test_killed_write_leaves_no_scene(tmp_path, monkeypatch):
    cfg = replace(SMALL, num_train=3, num_test=1, num_points=100)

    def fail(scene, out):
        (out / "images").mkdir()
        raise KeyboardInterrupt

    monkeypatch.setattr(synthetic, "_write_files", fail)
    with pytest.raises(KeyboardInterrupt):
        ensure_default_scene(cfg, root=tmp_path)
    assert list(tmp_path.iterdir()) == []  # neither the scene nor the temporary directory remains


def test_write_scene_refuses_to_overwrite(scene, written):
    with pytest.raises(FileExistsError):
        write_scene(scene, written)


def test_default_scene_parameters():
    """The default scene (what `ns-train willags` trains on): 32 train / 8 test at 128x96, 60% occluded."""
    cfg = SyntheticSceneConfig()
    s = make_scene(cfg)
    assert s.images.shape == (40, 96, 128, 3)
    assert s.split.count("train") == 32 and s.split.count("test") == 8
    assert sum(bool(o) for o in s.occluders) == round(0.6 * 32)
    assert len(s.points) == cfg.num_points


def test_our_rays_match_nerfstudio_cameras(scene, written):
    """The images are rendered with the same pixel/axis conventions nerfstudio (and so gsplat) assumes."""
    import torch
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    parser = NerfstudioDataParserConfig(
        data=written, load_3D_points=False, orientation_method="none", center_method="none", auto_scale_poses=False
    ).setup()
    cameras = parser.get_dataparser_outputs("train").cameras
    i = int(np.flatnonzero(scene.is_train)[1])
    np.testing.assert_allclose(cameras.camera_to_worlds[1].numpy(), scene.c2w[i, :3, :], atol=1e-5)
    rays = cameras.generate_rays(camera_indices=1)
    o, d = camera_rays(scene.c2w[i], scene.K, SMALL.width, SMALL.height, supersample=1)
    torch.testing.assert_close(
        rays.origins.double(), torch.from_numpy(np.ascontiguousarray(o[:, :, 0])), atol=1e-5, rtol=0
    )
    torch.testing.assert_close(
        rays.directions.double(), torch.from_numpy(np.ascontiguousarray(d[:, :, 0])), atol=1e-5, rtol=0
    )


def _ground_patch_detail(objects: list, x0: float, y0: float, seed: int = 0, n: int = 16) -> np.ndarray:
    """Luminance of the ground seen straight down over [x0, x0 + 0.2] x [y0, y0 + 0.2] (inside one checker cell),
    minus its best-fitting plane: the patch's fine detail, what a feature descriptor sees beyond the cell's colour."""
    u = np.linspace(0.02, 0.18, n)
    gx, gy = np.meshgrid(x0 + u, y0 + u)
    o = np.stack([gx.ravel(), gy.ravel(), np.ones(n * n)], -1)
    d = np.broadcast_to([0.0, 0.0, -1.0], o.shape)
    _, ids, rgb = trace(o, d, objects, seed)
    assert (np.asarray([objects[i]["type"] for i in ids]) == "ground").all()
    lum = rgb.mean(-1)
    design = np.stack([gx.ravel(), gy.ravel(), np.ones(n * n)], -1)
    return lum - design @ np.linalg.lstsq(design, lum, rcond=None)[0]


def test_unique_texture_makes_repeated_surfaces_distinct():
    """Two same-colour checker cells 1 m apart (two periods): without the texture, each patch is flat but for a
    smooth gradient and the two copies look alike to a descriptor; with it, each carries fine detail of its own."""
    plain = make_objects(SyntheticSceneConfig())
    textured = make_objects(SyntheticSceneConfig(unique_texture=0.8))
    assert all("unique_texture" not in obj for obj in plain)
    assert {o["type"] for o in textured if "unique_texture" in o} == {"ground", "dome", "sphere", "box"}
    for objects, distinct in ((plain, False), (textured, True)):
        a = _ground_patch_detail(objects, 3.05, 3.05)
        b = _ground_patch_detail(objects, 4.05, 3.05)
        if distinct:
            assert a.std() > 0.01 and b.std() > 0.01
            assert (a - b).std() > 0.5 * max(a.std(), b.std())
            assert np.corrcoef(a, b)[0, 1] < 0.5
        else:
            assert a.std() < 0.005 and b.std() < 0.005


def test_unique_texture_off_keeps_the_scene_and_its_cache_key():
    """The field's default leaves the default scene's objects, images and cache key as they are without it."""
    cfg = replace(SMALL, num_train=2, num_test=1)
    # the default scene's cache key as it was before the field existed (a GENERATOR_VERSION bump changes it)
    assert SyntheticSceneConfig().params_hash() == "cc398114e3d8"
    assert replace(cfg, unique_texture=0.8).params_hash() != cfg.params_hash()
    plain, textured = make_scene(cfg), make_scene(replace(cfg, unique_texture=0.8))
    assert np.abs(textured.clean.astype(int) - plain.clean.astype(int)).mean() > 5
    assert (textured.masks == plain.masks).all()
    np.testing.assert_allclose(textured.c2w, plain.c2w)
