"""Reliability at the extremes (docs/reliability.md): bad inputs stop with a clear message before training, numerics
stay finite, interrupts keep the work. Each test names its row of the table."""

import json
import math
import os
import pickle
import shlex
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from benchmarks.scale import console_script
from willags_ns.data.dataparser import WillagsDataError, WillagsDataParserConfig
from willags_ns.engine.checks import (
    WillagsInputError,
    WillagsTrainingError,
    check_image_file,
    check_intrinsics,
    check_num_train_images,
    check_poses,
    validate_dataparser_outputs,
)

# ---------------------------------------------------------------------------------------------------------------------
# a tiny writable scene (8 train + 2 test images of 32x24) for the corruption tests


@pytest.fixture(scope="module")
def tiny_scene_src(tmp_path_factory) -> Path:
    from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, write_scene

    cfg = SyntheticSceneConfig(num_train=8, num_test=2, width=32, height=24, num_points=400, supersample=1)
    return write_scene(make_scene(cfg), tmp_path_factory.mktemp("tiny") / "scene")


@pytest.fixture
def scene(tiny_scene_src, tmp_path) -> Path:
    """A fresh copy per test (tests corrupt it)."""
    return Path(shutil.copytree(tiny_scene_src, tmp_path / "scene"))


def _frames(scene: Path) -> dict:
    return json.loads((scene / "transforms.json").read_text())


def _write_frames(scene: Path, meta: dict) -> None:
    (scene / "transforms.json").write_text(json.dumps(meta))


def _first_train_image(scene: Path) -> Path:
    meta = _frames(scene)
    return scene / meta["train_filenames"][0]


def _parse(scene: Path, split: str = "train"):
    return WillagsDataParserConfig(data=scene).setup().get_dataparser_outputs(split)


def _validate(scene: Path) -> list[str]:
    return validate_dataparser_outputs(_parse(scene))


def test_clean_tiny_scene_validates_without_warnings(scene):
    assert _validate(scene) == []


# ---- row 1: a missing image


def test_row1_missing_image_is_named_before_training(scene):
    img = _first_train_image(scene)
    img.unlink()
    with pytest.raises(WillagsDataError, match=img.name):
        _validate(scene)
    # and the pure check, on its own
    with pytest.raises(WillagsInputError, match=r"does not exist.*restore it"):
        check_image_file(img)


# ---- row 2: truncated / corrupt JPEG or PNG


@pytest.mark.parametrize("fmt", ["PNG", "JPEG"])
@pytest.mark.parametrize("damage", ["truncate", "garbage"])
def test_row2_corrupt_or_truncated_image_is_named(tmp_path, fmt, damage):
    path = tmp_path / f"img.{fmt.lower()}"
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(path, format=fmt)
    assert check_image_file(path, (64, 64)) == (64, 64)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] if damage == "truncate" else b"not an image at all" + data[:10])
    with pytest.raises(WillagsInputError, match=rf"{path.name} cannot be decoded.*truncated or corrupt"):
        check_image_file(path, (64, 64))


def test_row2_truncated_png_in_a_scene_stops_validation(scene):
    img = _first_train_image(scene)
    img.write_bytes(img.read_bytes()[:200])
    with pytest.raises(WillagsInputError, match=img.name):
        _validate(scene)


# ---- row 3: image size disagrees with the camera


def test_row3_image_size_mismatch_is_an_error_naming_both_sizes(scene):
    img = _first_train_image(scene)
    Image.open(img).resize((64, 48)).save(img)
    with pytest.raises(WillagsInputError, match=rf"{img.name} is 64x48 but its camera says 32x24"):
        _validate(scene)


# ---- row 4: NaN / Inf pose, non-rotation


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_row4_nonfinite_pose_is_named_by_frame(scene, bad):
    meta = _frames(scene)
    meta["frames"][3]["transform_matrix"][0][3] = bad
    _write_frames(scene, meta)
    name = meta["frames"][3]["file_path"]
    with pytest.raises(WillagsDataError, match=rf"frames\[3\] \({name}\).*finite"):
        _parse(scene)


@pytest.mark.parametrize("kind", ["scaled", "mirrored", "sheared"])
def test_row4_non_rotation_matrix_is_named_by_frame(scene, kind):
    meta = _frames(scene)
    m = np.array(meta["frames"][2]["transform_matrix"])
    if kind == "scaled":
        m[:3, :3] *= 2.0
    elif kind == "mirrored":
        m[:3, 0] *= -1.0
    else:
        m[0, 1] += 0.3
    meta["frames"][2]["transform_matrix"] = m.tolist()
    _write_frames(scene, meta)
    with pytest.raises(WillagsDataError, match=r"frames\[2\].*not a rotation"):
        _parse(scene)


def test_row4_pose_checks_on_parsed_cameras_name_the_frame():
    """The same rules after any dataparser (nerfstudio-data, colmap): on the Cameras' poses."""
    c2w = torch.eye(4)[:3].repeat(3, 1, 1)
    check_poses(c2w, ["a", "b", "c"])
    bad = c2w.clone()
    bad[1, 0, 0] = float("nan")
    with pytest.raises(WillagsInputError, match=r"frame 1 \(b\) has a NaN or Inf"):
        check_poses(bad, ["a", "b", "c"])
    allbad = torch.full_like(c2w, float("nan"))
    with pytest.raises(WillagsInputError, match="spreads one NaN"):
        check_poses(allbad, ["a", "b", "c"])
    skew = c2w.clone()
    skew[2, :3, :3] *= 1.1
    with pytest.raises(WillagsInputError, match=r"frame 2 \(c\).*not a rotation"):
        check_poses(skew, ["a", "b", "c"])


# ---- row 5: zero and one training image


def test_row5_zero_training_images_is_an_error(scene):
    meta = _frames(scene)
    meta["test_filenames"] = meta["val_filenames"] = meta["test_filenames"] + meta["train_filenames"]
    meta["train_filenames"] = []
    _write_frames(scene, meta)
    with pytest.raises(WillagsDataError, match="the training split has no images: check train_filenames"):
        _parse(scene)
    with pytest.raises(WillagsInputError, match="no images"):
        check_num_train_images(0)


def test_row5_single_training_image_trains_with_a_warning(scene, tmp_path):
    meta = _frames(scene)
    meta["train_filenames"] = meta["train_filenames"][:1]
    _write_frames(scene, meta)
    outputs = _parse(scene)
    assert len(outputs.image_filenames) == 1
    warns = validate_dataparser_outputs(outputs)
    assert len(warns) == 1 and "only one training image" in warns[0]
    with pytest.warns(UserWarning, match="only one training image"):
        _, _, losses = _train(tmp_path / "out", scene, steps=3)
    assert len(losses) == 3 and all(math.isfinite(v) for v, _ in losses)


# ---- row 14: degenerate intrinsics


@pytest.mark.parametrize("key,value", [("fl_x", 0.0), ("fl_y", -3.0), ("fl_x", float("nan"))])
def test_row14_degenerate_intrinsics_in_transforms_json_are_named(scene, key, value):
    meta = _frames(scene)
    meta[key] = value
    _write_frames(scene, meta)
    with pytest.raises(WillagsDataError, match=rf"{key} = .*must be a number > 0"):
        _parse(scene)


def test_row14_degenerate_intrinsics_on_parsed_cameras():
    one = torch.ones(2, 1)
    check_intrinsics(100 * one, 100 * one, 16 * one, 12 * one, 32 * one, 24 * one)
    fx = 100 * one
    fx[1] = 0.0
    with pytest.raises(WillagsInputError, match=r"frame 1 \(b\): camera fx = 0.0 is invalid"):
        check_intrinsics(fx, 100 * one, 16 * one, 12 * one, 32 * one, 24 * one, ["a", "b"])


# ---- the pipeline runs the checks for every dataparser, before the model / images; the CLI prints one line


def small_networks() -> dict:
    """Model overrides that keep every component but shrink it (8-d latent, 8x8x4 planes, seeded VGG): the CPU cost
    of a step is then the rasteriser's and the VGG's on 32x24 images."""
    from willags_ns.appearance.triplane import TriplaneConfig
    from willags_ns.appearance.vae import VAEConfig
    from willags_ns.config import LatentConfig
    from willags_ns.mask.rule import MaskConfig

    return {
        "latent": LatentConfig(dim=8, vae=VAEConfig(image_size=16, channels=(8, 8))),
        "triplane": TriplaneConfig(resolution=8, channels=4, hyper_hidden=(16,), feature_dim=8, mlp_hidden=16),
        "intrinsic_dim": 8,
        "mask": MaskConfig(vgg_weights="seeded", warmup_steps=2, start_rule="always", max_resolution=512),
    }


def _train(out: Path, data: Path | None, steps: int, method: str = "willags", dataparser=None, **model_overrides):
    """tests/test_train.py's in-process ns-train, with small networks (mask from step 2)."""
    from tests.test_train import _train as train

    overrides = {"log_images_every": 0, **small_networks(), **model_overrides}
    if dataparser is not None:
        from willags_ns import method_configs

        orig = method_configs._trainer

        def patched(*a, **k):
            cfg = orig(*a, **k)
            cfg.pipeline.datamanager.dataparser = dataparser
            return cfg

        method_configs._trainer = patched
        try:
            return train(out, method, steps=steps, data=data, **overrides)
        finally:
            method_configs._trainer = orig
    return train(out, method, steps=steps, data=data, **overrides)


def test_pipeline_checks_nerfstudios_own_parser_before_building_the_model(scene, tmp_path, monkeypatch):
    """`ns-train willags --data X nerfstudio-data`: the same clear error, before the model or any image load."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from willags_ns.model import WillagsModel

    built = []
    monkeypatch.setattr(WillagsModel, "populate_modules", lambda self: built.append(1))
    img = _first_train_image(scene)
    Image.open(img).resize((16, 12)).save(img)  # exists, decodes, wrong size: only the post-parse check sees it
    with pytest.raises(WillagsInputError, match=rf"{img.name} is 16x12"):
        _train(tmp_path / "out", scene, steps=1, dataparser=NerfstudioDataParserConfig(load_3D_points=False))
    assert not built, "the model was built before the inputs were checked"


def _ns_train(args: list[str]) -> list[str]:
    """The command line of this venv's ns-train with `args`."""
    exe = console_script("ns-train")
    return [str(exe), *args]


def test_cli_prints_one_clear_line_not_a_traceback(scene, tmp_path):
    img = _first_train_image(scene)
    img.unlink()
    cmd = _ns_train(["willags", "--data", str(scene), "--output-dir", str(tmp_path), "--vis", "tensorboard"])
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode != 0
    last = [ln for ln in res.stderr.strip().splitlines() if ln.strip()][-1]
    assert last.startswith("willags: ") and img.name in last and "does not exist" in last, res.stderr[-2000:]
    assert "Traceback" not in res.stderr, res.stderr[-3000:]


# ---- row 15: SIGINT mid-training -> checkpoint; --load-dir resumes at the next step with equal state


def _tiny_config(out: Path, data: Path, steps: int, method: str = "willags", refine_every: int = 3):
    """The config tests/test_train.py's _train builds (in-process ns-train), without training."""
    from willags_ns import method_configs

    config = {"willags": method_configs.willags_config, "willags-3dgs": method_configs.willags_3dgs_config}[method]()
    config.max_num_iterations = steps
    config.steps_per_save = 10**6
    config.steps_per_eval_image = 10**6
    config.vis = "tensorboard"
    config.output_dir = out
    config.timestamp = "t"
    config.experiment_name = "exp"
    config.machine.device_type = "cpu"
    config.pipeline.datamanager.data = data
    m = config.pipeline.model
    m.num_downscales = 0
    m.warmup_length = 3
    m.refine_every = refine_every
    m.reset_alpha_every = 1000
    m.log_images_every = 0
    if method == "willags":
        for k, v in small_networks().items():
            setattr(m, k, v)
    config.set_timestamp()
    return config


def _state_equal(a, b, path="") -> None:
    """Recursive equality of nested dicts / lists of tensors and numbers (optimizer state dicts)."""
    if torch.is_tensor(a):
        assert torch.is_tensor(b) and a.shape == b.shape and torch.equal(a, b), path
    elif isinstance(a, dict):
        assert set(a) == set(b), (path, set(a) ^ set(b))
        for k in a:
            _state_equal(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _state_equal(x, y, f"{path}[{i}]")
    else:
        assert a == b, (path, a, b)


@pytest.fixture
def default_sigint():
    """Python's own SIGINT handler for the test: a suite started as a background job inherits SIG_IGN, and the
    test checks that training restores exactly the handler it found."""
    prev = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, prev)


def test_row15_sigint_writes_a_checkpoint_and_load_dir_resumes_the_same_state(tiny_scene_src, tmp_path, default_sigint):
    from nerfstudio.scripts.train import _set_random_seed

    config = _tiny_config(tmp_path, tiny_scene_src, steps=40)
    config.save_config()
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    orig = trainer.train_iteration

    def interrupted(step):
        if step == 6:  # Ctrl-C arrives in the middle of step 6 (before its forward pass)
            os.kill(os.getpid(), signal.SIGINT)
        return orig(step)

    trainer.train_iteration = interrupted
    with pytest.raises(SystemExit) as exit_info:
        trainer.train()
    assert exit_info.value.code == 130
    assert trainer.step == 6  # step 6 finished; step 7 never started
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handler restored
    ckpt_dir = config.get_checkpoint_dir()
    assert sorted(p.name for p in ckpt_dir.glob("*.ckpt")) == ["step-000000006.ckpt"]
    params = {k: v.detach().clone() if torch.is_tensor(v) else v for k, v in trainer.pipeline.state_dict().items()}
    optim = {k: o.state_dict() for k, o in trainer.optimizers.optimizers.items()}
    n_points = trainer.pipeline.model.num_points

    config2 = _tiny_config(tmp_path, tiny_scene_src, steps=2)
    config2.load_dir = ckpt_dir
    trainer2 = config2.setup(local_rank=0, world_size=1)
    trainer2.setup()
    assert trainer2._start_step == 7
    model2 = trainer2.pipeline.model
    assert model2.num_points == n_points
    _state_equal(params, dict(trainer2.pipeline.state_dict()), "pipeline")
    _state_equal(optim, {k: o.state_dict() for k, o in trainer2.optimizers.optimizers.items()}, "optimizers")
    # the optimisers hold the model's (resized) parameters, so resumed training actually moves the model
    for name, p in model2.gauss_params.items():
        assert trainer2.optimizers.optimizers[name].param_groups[0]["params"][0] is p, name
    before = model2.gauss_params["means"].detach().clone()
    trainer2.train()
    assert not torch.equal(before, model2.gauss_params["means"].detach()), "resumed training did not update means"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored after a normal end too


# ---- row 16: checkpoints load under weights_only=True; an arbitrary pickled object is refused


class _Payload:
    """Unpickling this runs Path.touch(marker): what an attacker's checkpoint would do with os.system."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_row16_checkpoints_load_weights_only_and_pickled_objects_are_refused(tiny_scene_src, tmp_path):
    _, trainer, _ = _train(tmp_path / "run", tiny_scene_src, steps=2)
    ckpt = next(trainer.checkpoint_dir.glob("*.ckpt"))
    state = torch.load(ckpt, map_location="cpu", weights_only=True)  # explicit, and ...
    assert state["step"] == 1 and "pipeline" in state and "optimizers" in state
    torch.load(ckpt, map_location="cpu")  # ... as nerfstudio calls it (torch >= 2.6: weights_only by default)

    marker = tmp_path / "payload-ran"
    state["evil"] = _Payload(marker)
    (tmp_path / "bad").mkdir()
    bad = tmp_path / "bad" / "step-000000001.ckpt"
    torch.save(state, bad)
    with pytest.raises(pickle.UnpicklingError, match="(?i)weights only load failed"):
        torch.load(bad, map_location="cpu")  # nerfstudio's call in Trainer._load_checkpoint / eval_setup
    assert not marker.exists()
    # through the trainer's resume path: refused with one line naming the file, never skipped for an older one
    from willags_ns.engine.checkpoints import CheckpointRefusedError

    config = _tiny_config(tmp_path / "resume", tiny_scene_src, steps=1)
    config.load_dir = tmp_path / "bad"
    trainer2 = config.setup(local_rank=0, world_size=1)
    with pytest.raises(CheckpointRefusedError, match=rf"{bad}.*pickled Python objects.*refused"):
        trainer2.setup()
    assert not marker.exists()


# ---- row 17: the viewer binds 127.0.0.1 for willags methods; an option exposes it


def test_row17_viewer_is_local_by_default_and_the_cli_can_expose_it():
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    from willags_ns import method_configs

    for factory in (
        method_configs.willags_config,
        method_configs.willags_lite_config,
        method_configs.willags_3dgs_config,
    ):
        assert factory().viewer.websocket_host == "127.0.0.1"
    cfg = tyro.cli(AnnotatedBaseConfigUnion, args=["willags"])
    assert cfg.viewer.websocket_host == "127.0.0.1"
    cfg = tyro.cli(AnnotatedBaseConfigUnion, args=["willags", "--viewer.websocket-host", "0.0.0.0"])
    assert cfg.viewer.websocket_host == "0.0.0.0"


# ---- row 9: poses scaled by 1e-3 / 1e4 in the dataset: nerfstudio's auto-scaling undoes it; training is finite


def _scale_scene(scene: Path, s: float) -> None:
    from willags_ns.data.dataparser import read_ply_points
    from willags_ns.data.synthetic import write_ply_points

    meta = _frames(scene)
    for f in meta["frames"]:
        m = np.array(f["transform_matrix"])
        m[:3, 3] *= s
        f["transform_matrix"] = m.tolist()
    _write_frames(scene, meta)
    xyz, rgb = read_ply_points(scene / meta["ply_file_path"])
    write_ply_points(scene / meta["ply_file_path"], xyz * s, rgb)


@pytest.mark.parametrize("s", [1e-3, 1e4])
def test_row9_scaled_poses_parse_to_the_same_scene_and_train_finite(tiny_scene_src, tmp_path, s):
    ref = _parse(tiny_scene_src)
    scene = Path(shutil.copytree(tiny_scene_src, tmp_path / "scaled"))
    _scale_scene(scene, s)
    out = _parse(scene)
    torch.testing.assert_close(out.cameras.camera_to_worlds, ref.cameras.camera_to_worlds, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out.metadata["points3D_xyz"], ref.metadata["points3D_xyz"], atol=1e-3, rtol=1e-3)
    if s < 1:
        _, _, losses = _train(tmp_path / "out", scene, steps=3)
        assert all(math.isfinite(v) for v, _ in losses)


# ---- rows 12 and 13 through nerfstudio's trainer


@pytest.fixture(scope="module")
def tiny_run(tiny_scene_src, tmp_path_factory):
    return _train(tmp_path_factory.mktemp("run"), tiny_scene_src, steps=2)


def test_row12_a_pipeline_with_every_gaussian_pruned_stops_with_a_clear_error(tiny_run):
    _, trainer, _ = tiny_run
    model = trainer.pipeline.model
    saved = {k: v.data for k, v in model.gauss_params.items()}
    try:
        for p in model.gauss_params.values():
            p.data = p.data[:0]
        with pytest.raises(WillagsTrainingError, match="every Gaussian was pruned by step 5"):
            trainer.pipeline.get_train_loss_dict(5)
    finally:
        for k, p in model.gauss_params.items():
            p.data = saved[k]


def test_row13_8x8_images_train_through_nerfstudio_with_the_default_resolution_schedule(tmp_path):
    from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, write_scene

    cfg = SyntheticSceneConfig(num_train=6, num_test=2, width=8, height=8, num_points=200, supersample=1)
    scene = write_scene(make_scene(cfg), tmp_path / "scene8")
    # num_downscales=2: the first steps train at 2x2 pixels
    _, trainer, losses = _train(tmp_path / "out", scene, steps=4, num_downscales=2)
    assert len(losses) == 4 and all(math.isfinite(v) for v, _ in losses)


# ---- row 20: same seed twice on the CPU -> the same losses


def _seeded_losses(out: Path, data: Path, steps: int) -> list[float]:
    from nerfstudio.scripts.train import _set_random_seed

    # densification at steps 30, 60, 90 (every 3 steps, tuned for real images, grows 32x24 scenes 100-fold)
    config = _tiny_config(out, data, steps=steps, refine_every=30)
    from tests.test_train import train_recording

    _set_random_seed(config.machine.seed)  # what ns-train's train_loop does
    return [loss for loss, _ in train_recording(config)[1]]


def test_row20_same_seed_twice_gives_the_same_losses_for_100_steps(tiny_scene_src, tmp_path):
    a = _seeded_losses(tmp_path / "a", tiny_scene_src, 100)
    b = _seeded_losses(tmp_path / "b", tiny_scene_src, 100)
    assert len(a) == 100 and a == b, next((i, x, y) for i, (x, y) in enumerate(zip(a, b, strict=True)) if x != y)


# ---- photo collection: one photo of reichstag replaced by a grey 1x1 image, a photo of another place, a duplicate


def _reichstag_copy(shared: Path, dst: Path) -> tuple[Path, list[str]]:
    """reichstag with every file symlinked (the shared data stays read-only) and images/ a real folder."""
    src = shared / "reichstag"
    dst.mkdir()
    for item in src.iterdir():
        if item.name != "images":
            (dst / item.name).symlink_to(item)
    (dst / "images").mkdir()
    names = sorted(p.name for p in (src / "images").iterdir())
    for n in names:
        (dst / "images" / n).symlink_to(src / "images" / n)
    return dst, names


def _train_names(scene: Path) -> list[str]:
    from willags_ns.data.dataparser import read_split_tsv

    table = read_split_tsv(scene / "reichstag.tsv")
    return sorted(n for n, s in table.items() if s == "train" and (scene / "images" / n).exists())


def test_photo_collection_grey_1x1_photo_is_a_clear_error(shared_data, tmp_path):
    scene, _ = _reichstag_copy(shared_data, tmp_path / "r")
    victim = _train_names(scene)[3]
    (scene / "images" / victim).unlink()
    Image.new("RGB", (1, 1), (128, 128, 128)).save(scene / "images" / victim, format="JPEG")
    with pytest.raises(WillagsInputError, match=rf"{victim} is 1x1 but its camera says \d+x\d+"):
        _validate(scene)


def test_photo_collection_foreign_photo_and_duplicate_run_finite_with_a_warning(shared_data, tmp_path):
    scene, _ = _reichstag_copy(shared_data, tmp_path / "r")
    train = _train_names(scene)
    sizes = {n: Image.open(scene / "images" / n).size for n in train}
    foreign = train[0]
    # a duplicate: another training photo's bytes under a frame whose camera has the same size
    dup_of, dup = next((a, b) for a in train[1:] for b in train[1:] if a < b and sizes[a] == sizes[b])
    other = sorted((shared_data / "sacre-coeur-mini" / "images").iterdir())[0]
    (scene / "images" / foreign).unlink()
    Image.open(other).convert("RGB").resize(sizes[foreign]).save(scene / "images" / foreign, format="JPEG")
    (scene / "images" / dup).unlink()
    shutil.copy(scene / "images" / dup_of, scene / "images" / dup)
    warns = _validate(scene)
    assert any(dup in w and dup_of in w and "byte-identical" in w for w in warns), warns
    with pytest.warns(UserWarning) as record:
        _, _, losses = _train(tmp_path / "out", scene, steps=3, num_downscales=3, resolution_schedule=10**9)
    texts = [str(w.message) for w in record]
    assert any("byte-identical" in t for t in texts), texts
    # the photo of another place: named before training; no genuine photo of the collection is
    flagged = [t for t in texts if "photo of another place" in t]
    assert len(flagged) == 1 and foreign in flagged[0], flagged
    assert len(losses) == 3 and all(math.isfinite(v) for v, _ in losses)


@pytest.mark.timing
def test_row15_ctrl_c_on_ns_train_writes_a_checkpoint_and_exits_cleanly(tiny_scene_src, tmp_path):
    """The real command line: SIGINT to `ns-train willags` while it trains step 5 (the process waits inside that
    step until the signal comes, so the step it stops after does not depend on the machine's speed)."""
    import re

    from tests._paused_ns_train import launch_paused, wait_until_paused

    args = ["willags", "--data", str(tiny_scene_src), "--output-dir", str(tmp_path), "--timestamp", "t"]
    args += ["--vis", "tensorboard", "--max-num-iterations", "100000", "--steps-per-save", "100000"]
    args += ["--pipeline.model.num-downscales", "0", "--pipeline.model.mask.vgg-weights", "seeded"]
    step = 5
    marker = tmp_path / "paused"
    proc = launch_paused(args, "step", step, marker)
    try:
        wait_until_paused(proc, marker)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    out = marker.with_suffix(".log").read_text(errors="replace")
    assert proc.returncode == 130, out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    assert re.search(rf"interrupted after step {step}\b", out), out[-2000:]
    ckpts = list(tmp_path.rglob("*.ckpt"))
    assert [p.name for p in ckpts] == [f"step-{step:09d}.ckpt"], ckpts
    # the exact command: the same arguments, the checkpoint file, and the steps left of the 100000 planned
    resume = re.search(r"^resume with: (.*)$", out, re.M)
    assert resume, out[-2000:]
    at = args.index("--max-num-iterations")
    expected = ["ns-train", "willags", "--load-checkpoint", str(ckpts[0]), "--max-num-iterations", str(99999 - step)]
    assert shlex.split(resume.group(1)) == expected + args[1:at] + args[at + 2 :], resume.group(1)


def test_row6_all_black_and_all_white_training_images_train_finite_through_nerfstudio(scene, tmp_path):
    meta = _frames(scene)
    for i, name in enumerate(meta["train_filenames"]):
        Image.new("RGB", (32, 24), (0, 0, 0) if i % 2 else (255, 255, 255)).save(scene / name)
    # with the VAE latent: its KL term must stay finite too (the default's embedding table has no KL)
    # mask (teacher + VGG) from step 2
    _, _, losses = _train(tmp_path / "out", scene, steps=6, **{"latent.kind": "vae"})
    assert len(losses) == 6 and all(math.isfinite(v) for v, _ in losses)
    masked = [m for _, m in losses if "masked_fraction" in m]
    assert masked and all(math.isfinite(m["vae_kl"]) and math.isfinite(m["masked_fraction"]) for m in masked)
