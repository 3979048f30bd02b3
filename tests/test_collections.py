"""benchmarks/collections.py: the manifest, photo selection, resizing, reading a pinned commit and the scene's
README/sources (no network, no SfM)."""

import json
import re
import subprocess
from dataclasses import replace
from pathlib import Path

import pytest
from PIL import Image

from benchmarks.collections import (
    COLLECTIONS,
    LEFT_BEHIND,
    MAX_SIDE,
    Collection,
    CollectionError,
    Source,
    finish_scene,
    main,
    model_digest,
    pin_verdict,
    resize_photo,
    scene_name,
    select_photos,
)
from tests._scenes import sfm_model_stub


def _jpeg(path: Path, size=(64, 48), color=(200, 30, 30), exif=None) -> bytes:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, color).save(path, format="JPEG", **({"exif": exif} if exif is not None else {}))
    return path.read_bytes()


def _coll(**kw) -> Collection:
    base = Collection(name="t", repo="o/r", commit="0" * 40, folder="pics", about="a test", licence="none")
    return replace(base, **kw)


def test_manifest_is_well_formed():
    assert COLLECTIONS
    for name, c in COLLECTIONS.items():
        assert c.name == name
        assert re.fullmatch(r"[0-9a-f]{40}", c.commit), name
        assert re.fullmatch(r"[\w.-]+/[\w.-]+", c.repo), name
        assert c.folder and not c.folder.startswith("/") and not c.folder.endswith("/"), name
        assert len(set(c.photos)) == len(c.photos), name
        assert all(Path(p).suffix.lower() in (".jpg", ".jpeg", ".png") for p in c.photos), name
        assert len({scene_name(p) for p in c.photos}) == len(c.photos), name  # no two photos share a scene name
        assert c.mapper in ("auto", "incremental", "global"), name
        assert c.about and c.licence, name
        assert c.model_sha256 == "" or re.fullmatch(r"[0-9a-f]{64}", c.model_sha256), name


def test_select_photos_takes_the_listed_ones_or_every_photo():
    available = ["b.jpg", "a.JPG", "notes.txt", "c.png"]
    assert select_photos(available, _coll(photos=("c.png", "b.jpg"))) == ["b.jpg", "c.png"]
    assert select_photos(available, _coll()) == ["a.JPG", "b.jpg", "c.png"]
    with pytest.raises(CollectionError, match=r"lacks x\.jpg"):
        select_photos(available, _coll(photos=("b.jpg", "x.jpg")))
    with pytest.raises(CollectionError, match="no photos"):
        select_photos(["readme.md"], _coll())


def test_scene_name_keeps_safe_stems_and_replaces_spaces_and_punctuation():
    assert scene_name("01.jpg") == "01.jpg"
    assert scene_name("DSC_0182.JPG") == "DSC_0182.jpg"
    assert scene_name("img.v2-a.png") == "img.v2-a.jpg"
    assert scene_name("Street Art, London - April 2011 594.jpg") == "Street_Art_London_-_April_2011_594.jpg"
    assert scene_name("Westminster Abbey.JPG") != scene_name("Westminster-Abbey.jpg")
    assert re.fullmatch(r"[A-Za-z0-9._-]+", scene_name("  (é) x .jpg"))
    assert scene_name("ä ö.png") == "photo.jpg"  # never a hidden ".jpg"


def test_resize_photo_caps_the_long_side_applies_orientation_and_keeps_exif(tmp_path):
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise to view
    exif[0x010F] = "TestMaker"  # Make
    data = _jpeg(tmp_path / "src.jpg", size=(1600, 1200), exif=exif.tobytes())

    sizes = resize_photo(data, tmp_path / "out.jpg")

    assert sizes == {"orig_size": [1600, 1200], "size": [600, MAX_SIDE]}  # upright: portrait
    with Image.open(tmp_path / "out.jpg") as im:
        assert im.size == (600, MAX_SIDE)
        assert im.getexif().get(0x0112) is None and im.getexif().get(0x010F) == "TestMaker"
    small = _jpeg(tmp_path / "small.jpg", size=(320, 200))
    assert resize_photo(small, tmp_path / "small_out.jpg")["size"] == [320, 200]


def _git(*args, cwd):
    subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True)


def test_source_reads_the_pinned_commit_from_a_clone_a_bare_mirror_or_a_folder(tmp_path):
    repo = tmp_path / "repo"
    first = _jpeg(repo / "pics" / "a.jpg", color=(10, 200, 10))
    _jpeg(repo / "pics" / "b.jpg")
    _git("init", "-q", cwd=repo)
    _git("add", ".", cwd=repo)
    _git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "photos", cwd=repo)
    pinned = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True).stdout.strip()
    _jpeg(repo / "pics" / "a.jpg", color=(0, 0, 255))  # a later commit changes a photo
    _git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "later", cwd=repo)
    _git("clone", "-q", "--bare", str(repo), str(tmp_path / "mirror.git"), cwd=tmp_path)
    coll = _coll(commit=pinned)

    for root in (repo, tmp_path / "mirror.git"):
        src = Source(coll, root)
        assert src.names() == ["a.jpg", "b.jpg"]
        assert src.read("a.jpg") == first  # the pinned commit's bytes, not the working tree's
    with pytest.raises(CollectionError, match="has no commit"):
        Source(_coll(commit="1" * 40), repo)
    plain = tmp_path / "plain"
    _jpeg(plain / "pics" / "a.jpg")
    assert Source(coll, plain).names() == ["a.jpg"]
    with pytest.raises(CollectionError, match="has no folder pics"):
        Source(coll, tmp_path / "empty")


def test_photos_in_subfolders_are_listed_read_and_named_apart(tmp_path):
    """A source that splits one landmark's photos over subfolders (a classifier's train/ and test/): every file below
    the folder is listed by its relative path, from a git repository (names with spaces and non-ASCII letters as
    they are) and from a plain folder alike, read at the pinned commit, and two subfolders' photos of one name get
    two scene names; a photo directly in the folder keeps its plain name."""
    repo = tmp_path / "repo"
    train = _jpeg(repo / "pics" / "train" / "Ho Chi Minh (1).jpg", color=(10, 200, 10))
    _jpeg(repo / "pics" / "test" / "Ho Chi Minh (1).jpg")
    _jpeg(repo / "pics" / "é.jpg")
    _git("init", "-q", cwd=repo)
    _git("add", ".", cwd=repo)
    _git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "photos", cwd=repo)
    pinned = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True).stdout.strip()
    coll = _coll(commit=pinned)
    want = ["test/Ho Chi Minh (1).jpg", "train/Ho Chi Minh (1).jpg", "é.jpg"]
    for src in (Source(coll, repo), Source(replace(coll, folder="repo/pics"), tmp_path)):  # git, plain folder
        assert src.names() == want
        assert src.read("train/Ho Chi Minh (1).jpg") == train
    names = [scene_name(n) for n in select_photos(want, coll)]
    assert names == ["test_Ho_Chi_Minh_1.jpg", "train_Ho_Chi_Minh_1.jpg", "photo.jpg"]


def test_model_digest_follows_the_model_bytes_and_names_a_missing_file(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    sfm_model_stub(a)
    sfm_model_stub(b)
    (b / "images").mkdir()  # what is not the model does not count
    assert model_digest(a) == model_digest(b) and len(model_digest(a)) == 64
    sfm_model_stub(b, points=b"pointz")
    assert model_digest(a) != model_digest(b)
    (a / "colmap" / "sparse" / "0" / "images.bin").unlink()
    with pytest.raises(CollectionError, match=r"no SfM model file colmap/sparse/0/images\.bin"):
        model_digest(a)


def test_pin_verdict_says_whether_a_build_is_the_pinned_scene():
    digest = "ab" * 32
    assert "no model pinned" in pin_verdict(_coll(), digest)
    same = pin_verdict(_coll(model_sha256=digest), digest)
    assert "the pinned one" in same and "differs" not in same
    other = pin_verdict(_coll(model_sha256="cd" * 32), digest)
    assert "differs from the pinned cdcdcdcdcdcd" in other and "do not compare with runs on the pinned" in other
    assert all(len(v.splitlines()) == 1 for v in (same, other))


def test_finish_scene_drops_sfm_leftovers_and_writes_sources_and_readme(tmp_path):
    out = tmp_path / "scene"
    _jpeg(out / "images" / "a.jpg", size=(80, 60))
    sfm_model_stub(out)
    (out / "colmap" / "distorted" / "0").mkdir(parents=True)
    (out / "colmap" / "database.db").write_bytes(b"db")
    summary = {
        "registered": 1, "total": 2, "points3D": 1234, "mean_reprojection_error_px": 0.5, "mean_track_length": 4.0,
        "camera_model": "SIMPLE_RADIAL", "matching": "exhaustive", "num_pairs": 1, "num_train": 0, "num_test": 1,
        "split_file": "scene.tsv", "wall_s": 12.0, "stage_s": {"mapping": 3.0}, "pycolmap": "4.2.1",
    }  # fmt: skip
    (out / "process_summary.json").write_text(json.dumps(summary))
    rows = [
        {"name": n, "repo": "o/r @ " + "0" * 40, "path": f"pics/{n}", "orig_size": [8, 6], "size": [8, 6]}
        for n in ("a.jpg", "b.jpg")
    ]

    res = finish_scene(_coll(name="scene", mapper="global"), out, rows)

    assert not any((out / rel).exists() for rel in LEFT_BEHIND)
    sources = json.loads((out / "sources.json").read_text())
    assert [(s["name"], s["registered"]) for s in sources] == [("a.jpg", True), ("b.jpg", False)]
    assert sources[0]["undistorted_size"] == [80, 60] and res["points3D"] == 1234
    readme = (out / "README.md").read_text()
    assert "| photos / registered | 2 / 1 |" in readme and "0.500 px" in readme
    assert "--mapper global" in readme and "Not registered (1): b.jpg" in readme
    assert res["model_sha256"] == model_digest(out) and f"`{model_digest(out)}`" in readme


def test_cli_lists_the_collections_and_names_an_unknown_one(tmp_path, capsys):
    assert main(["list"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in COLLECTIONS)
    assert main(["build", "nope", "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err
    assert "unknown collection 'nope'" in err and len(err.strip().splitlines()) == 1
