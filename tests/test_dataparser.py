"""willags-data: each branch (synthetic, transforms.json, COLMAP + NeRF-W tsv), eval-only metadata, the open3d-free
PLY reader, the tsv reader and clear errors for bad input."""

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from willags_ns.data.dataparser import (
    WillagsDataError,
    WillagsDataParserConfig,
    read_ply_points,
    read_split_tsv,
    willags_dataparser,
)
from willags_ns.data.synthetic import SyntheticSceneConfig, scene_dir_for, write_ply_points

SMALL = SyntheticSceneConfig(num_train=6, num_test=2, width=40, height=30, num_points=500)
# Tests taking the `shared_data` fixture (tests/conftest.py: the repo's sibling ../shared/data) skip when it is absent.


def _outputs(data, **kwargs):
    parser = WillagsDataParserConfig(data=data, **kwargs).setup()
    return parser, {s: parser.get_dataparser_outputs(s) for s in ("train", "val", "test")}


def _names(outputs) -> list:
    return [p.name for p in outputs.image_filenames]


# ---- synthetic branch


@pytest.mark.parametrize("data", [None, Path(), Path(".")])
def test_no_data_uses_the_synthetic_scene(data, tmp_path_factory):
    cache = tmp_path_factory.getbasetemp() / "willags-cache"  # shared by the parametrisations: generated once
    parser, out = _outputs(data, synthetic=SMALL, cache_dir=cache)
    scene = scene_dir_for(SMALL, cache)
    assert len(out["train"].image_filenames) == SMALL.num_train
    assert _names(out["val"]) == _names(out["test"]) and len(out["test"].image_filenames) == SMALL.num_test
    assert all(p.parent == scene / "images" for p in out["train"].image_filenames)
    assert out["train"].metadata["masks_gt_dir"] == scene / "masks_gt"
    assert out["train"].metadata["gt_clean_dir"] == scene / "gt_clean"
    assert out["train"].metadata["points3D_xyz"].shape == (SMALL.num_points, 3)
    assert parser.config.data == scene  # so datamanager.get_datapath() (ns-viewer) names a real directory


def test_synthetic_points_follow_the_pose_transform(tmp_path):
    """The seed points (read without open3d) get the same orientation/centring/scale as the cameras."""
    from willags_ns.data.synthetic import make_scene

    _, out = _outputs(None, synthetic=SMALL, cache_dir=tmp_path)
    scene = make_scene(SMALL)
    train = out["train"]
    cams = train.cameras.camera_to_worlds[:, :3, 3].double()  # [C, 3] transformed camera centres
    pts = train.metadata["points3D_xyz"].double()  # [P, 3] transformed points
    orig_cams = torch.from_numpy(scene.c2w[scene.is_train][:, :3, 3])
    orig_pts = torch.from_numpy(scene.points).double()
    ratio = torch.cdist(cams, pts[:50]) / torch.cdist(orig_cams, orig_pts[:50])
    torch.testing.assert_close(ratio, torch.full_like(ratio, train.dataparser_scale), rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(train.metadata["points3D_rgb"].numpy(), scene.colors)


def test_synthetic_scene_respects_the_cache_env(tmp_path, monkeypatch):
    monkeypatch.setenv("WILLAGS_CACHE", str(tmp_path))
    cfg = replace(SMALL, num_train=3, num_test=1)
    _, out = _outputs(None, synthetic=cfg)
    assert out["train"].image_filenames[0].is_relative_to(tmp_path / "scenes")


# ---- transforms.json branch


@pytest.mark.data
def test_transforms_scene_keeps_its_explicit_split(shared_data):
    meta = json.loads((shared_data / "fox-clean" / "transforms.json").read_text())
    _, out = _outputs(shared_data / "fox-clean")
    assert _names(out["train"]) == sorted(Path(f).name for f in meta["train_filenames"])
    assert _names(out["test"]) == sorted(Path(f).name for f in meta["test_filenames"])
    assert out["train"].metadata["points3D_xyz"].shape[0] == 5684  # sparse_pc.ply (README)
    assert "masks_gt_dir" not in out["train"].metadata and "gt_clean_dir" not in out["train"].metadata


@pytest.mark.data
def test_transforms_scene_exposes_eval_only_dirs(shared_data):
    _, out = _outputs(shared_data / "fox-wild")
    assert out["test"].metadata["masks_gt_dir"] == shared_data / "fox-wild" / "masks_gt"
    assert out["test"].metadata["gt_clean_dir"] == shared_data / "fox-wild" / "gt_clean"
    assert not any("masks_gt" in str(p) for p in out["train"].image_filenames)
    assert out["train"].mask_filenames is None  # training never sees the ground-truth masks


@pytest.mark.data
def test_transforms_json_file_path_works(shared_data):
    _, out = _outputs(shared_data / "fox-clean" / "transforms.json")
    assert len(out["train"].image_filenames) == 58


# ---- COLMAP branch


@pytest.mark.data
def test_colmap_scene_uses_the_tsv_split(shared_data):
    table = read_split_tsv(shared_data / "sacre-coeur-mini" / "sacre-coeur-mini.tsv")
    _, out = _outputs(shared_data / "sacre-coeur-mini")
    assert sorted(_names(out["train"])) == sorted(n for n, s in table.items() if s == "train")
    assert sorted(_names(out["test"])) == sorted(n for n, s in table.items() if s == "test")
    assert _names(out["val"]) == _names(out["test"])
    assert out["train"].metadata["points3D_xyz"].shape[0] == 3975
    assert out["train"].cameras.shape[0] == len(out["train"].image_filenames)


def _colmap_copy(shared_data: Path, dst: Path, tsv_rows=None) -> Path:
    """A COLMAP scene made of symlinks into sacre-coeur-mini, with our own tsv (or none)."""
    src = shared_data / "sacre-coeur-mini"
    dst.mkdir()
    os.symlink(src / "images", dst / "images")
    os.symlink(src / "colmap", dst / "colmap")
    if tsv_rows is not None:
        lines = ["filename\tid\tsplit\tdataset"] + ["\t".join(r) for r in tsv_rows]
        (dst / "mine.tsv").write_text("\n".join(lines) + "\n")
    return dst


@pytest.mark.data
def test_colmap_split_follows_a_custom_tsv(shared_data, tmp_path):
    names = sorted(p.name for p in (shared_data / "sacre-coeur-mini" / "images").iterdir())
    test_names = names[:3]  # not nerfstudio's interval split
    rows = [(n, str(i), "test" if n in test_names else "train", "x") for i, n in enumerate(names[:-1])]
    rows.append(("not_registered.jpg", "nan", "train", "x"))  # NeRF-W tsvs list unregistered images too
    _, out = _outputs(_colmap_copy(shared_data, tmp_path / "s", rows))
    assert sorted(_names(out["test"])) == test_names
    assert sorted(_names(out["train"])) == names[3:-1]  # the image missing from the tsv is in neither split


@pytest.mark.data
def test_colmap_without_tsv_falls_back_to_interval(shared_data, tmp_path):
    split = json.loads((shared_data / "sacre-coeur-mini" / "split.json").read_text())
    _, out = _outputs(_colmap_copy(shared_data, tmp_path / "s"))
    assert sorted(_names(out["test"])) == sorted(Path(f).name for f in split["test"])


@pytest.mark.data
def test_colmap_model_under_sparse_0(shared_data, tmp_path):
    dst = tmp_path / "s"
    dst.mkdir()
    os.symlink(shared_data / "sacre-coeur-mini" / "images", dst / "images")
    (dst / "sparse").mkdir()
    os.symlink(shared_data / "sacre-coeur-mini" / "colmap" / "sparse" / "0", dst / "sparse" / "0")
    _, out = _outputs(dst)
    assert len(out["train"].image_filenames) + len(out["test"].image_filenames) == 14


# ---- errors


def test_missing_directory(tmp_path):
    with pytest.raises(WillagsDataError, match="does not exist"):
        _outputs(tmp_path / "nope")


def test_directory_without_a_scene(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(WillagsDataError, match="neither transforms.json nor a COLMAP model"):
        _outputs(tmp_path)


@pytest.mark.data
def test_malformed_tsv_names_file_and_line(shared_data, tmp_path):
    scene = _colmap_copy(shared_data, tmp_path / "s", [("ptc_02928139_3448003521.jpg", "1", "validation", "x")])
    with pytest.raises(WillagsDataError, match=r"mine\.tsv, line 2: split 'validation'"):
        _outputs(scene)


def test_tsv_without_split_column(tmp_path):
    (tmp_path / "a.tsv").write_text("filename\tid\n0.jpg\t1\n")
    with pytest.raises(WillagsDataError, match="no 'split' column"):
        read_split_tsv(tmp_path / "a.tsv")


@pytest.mark.data
def test_several_tsv_files_are_ambiguous(shared_data, tmp_path):
    scene = _colmap_copy(shared_data, tmp_path / "s", [("ptc_02928139_3448003521.jpg", "1", "train", "x")])
    (scene / "other.tsv").write_text("filename\tid\tsplit\tdataset\n")
    with pytest.raises(WillagsDataError, match="several split files"):
        _outputs(scene)


def _tiny_transforms(root: Path, **overrides) -> Path:
    root.mkdir(exist_ok=True)
    (root / "images").mkdir(exist_ok=True)
    from PIL import Image

    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(root / "images" / "a.png")
    Image.fromarray(np.ones((4, 4, 3), np.uint8)).save(root / "images" / "b.png")
    moved = np.eye(4)
    moved[0, 3] = 1.0
    meta: dict = {"fl_x": 4, "fl_y": 4, "cx": 2, "cy": 2, "w": 4, "h": 4}
    meta["frames"] = [
        {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()},
        {"file_path": "images/b.png", "transform_matrix": moved.tolist()},
    ]
    meta.update(overrides)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def test_transforms_with_a_missing_image(tmp_path):
    root = _tiny_transforms(tmp_path / "s")
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"].append({"file_path": "images/gone.png", "transform_matrix": np.eye(4).tolist()})
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(WillagsDataError, match=r"frames\[2\] image .*gone\.png does not exist"):
        _outputs(root)


def test_transforms_errors_name_the_field(tmp_path):
    root = _tiny_transforms(tmp_path / "a", fl_x=None)
    meta = json.loads((root / "transforms.json").read_text())
    del meta["fl_x"]
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(WillagsDataError, match="'fl_x'"):
        _outputs(root)
    bad_pose = _tiny_transforms(tmp_path / "b", frames=[{"file_path": "images/a.png", "transform_matrix": [[1, 0]]}])
    with pytest.raises(WillagsDataError, match="transform_matrix"):
        _outputs(bad_pose)
    frames = [{"file_path": f"images/{n}", "transform_matrix": np.eye(4).tolist()} for n in ("a.png", "b.png")]
    with pytest.raises(WillagsDataError, match="same position"):
        _outputs(_tiny_transforms(tmp_path / "e", frames=frames))
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "transforms.json").write_text("{not json")
    with pytest.raises(WillagsDataError, match="not valid JSON"):
        _outputs(tmp_path / "c")
    unknown = _tiny_transforms(tmp_path / "d", train_filenames=["images/zzz.png"])
    with pytest.raises(WillagsDataError, match="train_filenames lists files with no frame"):
        _outputs(unknown)


@pytest.mark.data
def test_colmap_with_missing_images(shared_data, tmp_path):
    dst = tmp_path / "s"
    (dst / "images").mkdir(parents=True)
    os.symlink(shared_data / "sacre-coeur-mini" / "colmap", dst / "colmap")
    with pytest.raises(WillagsDataError, match="14 image\\(s\\) of the COLMAP model are missing"):
        _outputs(dst)


# ---- readers


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_read_ply_formats(tmp_path, fmt):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(20, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, size=(20, 3)).astype(np.uint8)
    header = f"ply\nformat {fmt} 1.0\ncomment test\nelement vertex 20\nproperty float x\nproperty float y\n"
    header += "property float z\nproperty float nx\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
    header += "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    path = tmp_path / "p.ply"
    if fmt == "ascii":
        body = "".join(
            f"{x:.9g} {y:.9g} {z:.9g} 0 {r} {g} {b}\n" for (x, y, z), (r, g, b) in zip(xyz, rgb, strict=True)
        )
        path.write_bytes(header.encode() + body.encode())
    else:
        o = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype(
            [("x", o + "f4"), ("y", o + "f4"), ("z", o + "f4"), ("nx", o + "f4")] + [(c, "u1") for c in "rgb"]
        )
        arr = np.zeros(20, dt)
        arr["x"], arr["y"], arr["z"] = xyz.T
        arr["r"], arr["g"], arr["b"] = rgb.T
        path.write_bytes(header.encode() + arr.tobytes())
    got_xyz, got_rgb = read_ply_points(path)
    np.testing.assert_allclose(got_xyz, xyz, rtol=1e-6)
    np.testing.assert_array_equal(got_rgb, rgb)


def test_read_ply_matches_our_writer_and_rejects_garbage(tmp_path):
    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    rgb = np.array([[0, 1, 2], [3, 4, 5], [250, 251, 252], [9, 9, 9]], np.uint8)
    write_ply_points(tmp_path / "a.ply", xyz, rgb)
    got = read_ply_points(tmp_path / "a.ply")
    np.testing.assert_array_equal(got[0], xyz)
    np.testing.assert_array_equal(got[1], rgb)
    (tmp_path / "b.ply").write_bytes(b"not a ply")
    with pytest.raises(WillagsDataError, match="b.ply is not a PLY"):
        read_ply_points(tmp_path / "b.ply")
    truncated = (tmp_path / "a.ply").read_bytes()[:-5]
    (tmp_path / "c.ply").write_bytes(truncated)
    with pytest.raises(WillagsDataError, match="truncated"):
        read_ply_points(tmp_path / "c.ply")


@pytest.mark.data
def test_read_ply_of_the_fox_scene(shared_data):
    xyz, rgb = read_ply_points(shared_data / "fox-clean" / "sparse_pc.ply")
    assert xyz.shape == (5684, 3) and rgb.shape == (5684, 3) and np.isfinite(xyz).all()
    assert rgb.std() > 5  # real colours, not the grey fallback


def test_read_split_tsv(tmp_path):
    (tmp_path / "s.tsv").write_text("filename\tid\tsplit\tdataset\na.jpg\t1\ttrain\tx\nb.jpg\tnan\tTest\tx\n\n")
    assert read_split_tsv(tmp_path / "s.tsv") == {"a.jpg": "train", "b.jpg": "test"}
    (tmp_path / "d.tsv").write_text("filename\tid\tsplit\tdataset\na.jpg\t1\ttrain\tx\na.jpg\t1\ttest\tx\n")
    with pytest.raises(WillagsDataError, match="line 3: a.jpg is listed in both splits"):
        read_split_tsv(tmp_path / "d.tsv")


# ---- registration


def test_specification_and_entry_point():
    from importlib.metadata import entry_points

    assert isinstance(willags_dataparser.config, WillagsDataParserConfig) and willags_dataparser.config.data is None
    eps = {ep.name: ep for ep in entry_points(group="nerfstudio.dataparser_configs")}
    if "willags-data" not in eps:
        pytest.skip("willags-ns is not installed in this environment (pip install -e .)")
    assert eps["willags-data"].load() is willags_dataparser


def test_explicit_downscale_reads_images_n_and_writes_it_when_missing(tmp_path):
    root = _tiny_transforms(tmp_path / "s")
    (root / "images_2").mkdir()
    for name in ("a.png", "b.png"):  # only the downscaled copies exist
        (root / "images" / name).rename(root / "images_2" / name)
    with pytest.raises(WillagsDataError, match="a.png does not exist"):
        _outputs(root, eval_mode="all")
    _, out = _outputs(root, eval_mode="all", downscale_factor=2)
    assert out["train"].image_filenames == [root / "images_2" / "a.png", root / "images_2" / "b.png"]
    assert int(out["train"].cameras.width[0]) == 2

    fresh = _tiny_transforms(tmp_path / "fresh")  # only images/: images_2 is written from it
    _, out = _outputs(fresh, eval_mode="all", downscale_factor=2)
    assert out["train"].image_filenames == [fresh / "images_2" / "a.png", fresh / "images_2" / "b.png"]
    from PIL import Image

    with Image.open(fresh / "images_2" / "a.png") as im:
        assert im.size == (int(out["train"].cameras.width[0]), int(out["train"].cameras.height[0]))


@pytest.mark.data
def test_colmap_downscale_without_images_n_writes_it(shared_data, tmp_path, monkeypatch):
    """A COLMAP scene downscales with only images/: images_N is written from it (no interactive question, no
    hand-made folder); the factor may come as a float (willags-render dataset passes 2.0); 0.5 is refused."""
    from PIL import Image

    from willags_ns.data import dataparser

    root = _colmap_copy(shared_data, tmp_path / "s")
    _, out = _outputs(root, downscale_factor=2.0)
    first = out["train"].image_filenames[0]
    assert first.parent == root / "images_2"
    with Image.open(first) as im, Image.open(root / "images" / first.name) as full:
        assert im.size == (full.width // 2, full.height // 2)
        assert (int(out["train"].cameras.width[0]), int(out["train"].cameras.height[0])) == im.size
    for bad in (0.5, 1.5, 0):
        with pytest.raises(WillagsDataError, match=f"downscale_factor {bad!r}"):
            _outputs(root, downscale_factor=bad)

    # no factor: nerfstudio's rule (largest side <= MAX_AUTO_SIDE) picks one and its folder is written
    monkeypatch.setattr(dataparser, "MAX_AUTO_SIDE", 300)
    auto = _colmap_copy(shared_data, tmp_path / "auto")
    _, out = _outputs(auto)
    assert out["train"].image_filenames[0].parent == auto / "images_4"
    assert max(int(out["train"].cameras.width[0]), int(out["train"].cameras.height[0])) <= 300
    # the factor it read them at, as willags-render dataset asks for it (a fresh parser, before parsing)
    assert WillagsDataParserConfig(data=auto).setup().image_downscale_factor() == 4
    assert WillagsDataParserConfig(data=auto, downscale_factor=2).setup().image_downscale_factor() == 2
