"""Training through nerfstudio itself (its Trainer, datamanager, optimisers, callbacks, checkpoints) on CPU."""

import json
import subprocess
from pathlib import Path

import pytest
import torch
import yaml

from benchmarks.scale import console_script

pytestmark = pytest.mark.slow


def _train(
    tmp_path: Path,
    method: str = "willags",
    steps: int = 20,
    data=None,
    eval_steps: int = 8,
    device: str | None = None,
    **model_overrides,
):
    """Train in-process exactly as `ns-train` does (config.setup -> trainer.setup -> trainer.train), on `device`
    (the GPU where there is one when None)."""
    from willags_ns import method_configs

    factory = {
        "willags": method_configs.willags_config,
        "willags-lite": method_configs.willags_lite_config,
        "willags-3dgs": method_configs.willags_3dgs_config,
    }[method]
    config = factory()
    config.max_num_iterations = steps
    config.steps_per_save = steps
    config.vis = "tensorboard"
    config.output_dir = tmp_path
    config.timestamp = "t"
    config.experiment_name = "exp"
    config.machine.device_type = device or ("cuda" if torch.cuda.is_available() else "cpu")
    if data is not None:
        config.pipeline.datamanager.data = data
    config.pipeline.eval_protocol.steps = eval_steps  # saved in config.yml, so ns-eval uses it too
    m = config.pipeline.model
    m.num_downscales = 0
    m.warmup_length = 5
    m.refine_every = 5
    m.reset_alpha_every = 1000
    if hasattr(m, "mask"):
        m.mask.warmup_steps = 4
        # the mask's path in every short run (the start rule's own tests: tests/mask/test_start_rule.py)
        m.mask.start_rule = "always"
        m.log_images_every = 10
    for k, v in model_overrides.items():  # "a.b": the field b of the group a
        *groups, leaf = k.split(".")
        owner = m
        for g in groups:
            owner = getattr(owner, g)
        setattr(owner, leaf, v)
    config.set_timestamp()
    config.save_config()
    trainer, losses = train_recording(config)
    return config, trainer, losses


def train_recording(config):
    """Set up and train `config` with nerfstudio's Trainer; returns (trainer, [(loss, scalar metrics)] per step)."""
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    losses = []
    orig = trainer.train_iteration

    def spy(step):
        loss, loss_dict, metrics = orig(step)
        losses.append((float(loss), {k: float(v) for k, v in metrics.items() if torch.is_tensor(v) and v.numel() == 1}))
        return loss, loss_dict, metrics

    trainer.train_iteration = spy
    trainer.train()
    return trainer, losses


def _check_finite(losses):
    assert losses, "no training step ran"
    assert all(torch.isfinite(torch.tensor(v)) for v, _ in losses), [v for v, _ in losses]


def test_willags_trains_saves_and_reloads(tmp_path):
    config, trainer, losses = _train(tmp_path, "willags", steps=20)
    _check_finite(losses)
    metrics = [m for _, m in losses]
    assert any("masked_fraction" in m for m in metrics), "the transient mask never ran after its warm-up"
    # the default latent is a per-image embedding table (no VAE, no KL term)
    assert not any("vae_kl" in m for m in metrics)
    nets = trainer.pipeline.model.appearance_nets
    assert nets.vae is None and nets.embeddings is not None
    run_dir = config.get_base_dir()
    ckpts = list((run_dir / "nerfstudio_models").glob("*.ckpt"))
    assert ckpts, "no checkpoint written"

    # reload through nerfstudio's eval_setup: torch.load with weights_only=True (our safe globals) and render
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, step = eval_setup(run_dir / "config.yml", test_mode="test")
    model = pipeline.model
    assert model.num_points == trainer.pipeline.model.num_points
    assert model.loaded_perceptual_source, "checkpoint does not record which VGG weights made the masks"
    cam = pipeline.datamanager.eval_dataset.cameras[0:1]
    with torch.no_grad():
        out = model.get_outputs_for_camera(cam)
    rgb = out["rgb"]
    assert rgb.shape == (int(cam.height), int(cam.width), 3)
    assert torch.isfinite(rgb).all() and rgb.std() > 0.01  # renders a scene, not a flat background


def test_training_steps_take_the_cameras_sizes_from_the_pipeline_and_never_read_them(tmp_path, monkeypatch):
    """The pipeline tells the model the training images' sizes once, after the first next_train (nerfstudio caches
    and undistorts the photos there, which can change a camera's size); no training step then reads a training
    camera's width or height (a wait for the GPU there): here reading one fails. Downscale 2 at every step."""
    from tests.render.test_camera import unreadable_size
    from willags_ns.data.datamanager import WillagsDatamanager
    from willags_ns.engine.pipeline import WillagsPipeline

    next_train, tell = WillagsDatamanager.next_train, WillagsPipeline._tell_model_the_image_sizes
    told = []

    def cameras_without_a_readable_size(self, step):
        camera, batch = next_train(self, step)
        return unreadable_size(camera), batch

    def spy(self):
        told.append("cached_train" in vars(self.datamanager))  # the photos cached, the cameras final
        tell(self)

    monkeypatch.setattr(WillagsDatamanager, "next_train", cameras_without_a_readable_size)
    monkeypatch.setattr(WillagsPipeline, "_tell_model_the_image_sizes", spy)
    _, trainer, losses = _train(tmp_path, "willags", steps=4, num_downscales=1)
    _check_finite(losses)
    assert len(losses) == 4 and told == [True]
    model, cameras = trainer.pipeline.model, trainer.pipeline.datamanager.train_dataset.cameras
    sizes = [(int(w), int(h)) for w, h in zip(cameras.width.reshape(-1), cameras.height.reshape(-1), strict=True)]
    assert model.train_image_sizes == sizes
    assert model.last_size in {(h // 2, w // 2) for w, h in sizes}


@pytest.mark.parametrize("switch", ["latent.kind", "use_field", "mask.enabled"])
def test_each_ablation_switch_trains(tmp_path, switch):
    _, trainer, losses = _train(
        tmp_path, "willags", steps=8, **{switch: "embedding" if switch == "latent.kind" else False}
    )
    _check_finite(losses)
    model = trainer.pipeline.model
    if switch == "latent.kind":
        assert model.appearance_nets.vae is None and model.appearance_nets.embeddings is not None
    if switch == "use_field":
        assert model.appearance_nets.field is None
    if switch == "mask.enabled":
        assert model.teacher is None and not any("masked_fraction" in m for _, m in losses)


def test_plain_3dgs_baseline_trains(tmp_path):
    _, trainer, losses = _train(tmp_path, "willags-3dgs", steps=8)
    _check_finite(losses)
    assert "features_dc" in trainer.pipeline.model.gauss_params


def test_fox_clean_trains(tmp_path, shared_data):
    _, _, losses = _train(tmp_path, "willags", steps=6, data=shared_data / "fox-clean")
    _check_finite(losses)


def test_default_without_sfm_keypoints_trains_exactly_as_without_sky_and_safeguard(tmp_path):
    """The default's sky (above the SfM skyline) and the mask's safeguard both read COLMAP's keypoints; a scene
    without them (nerfstudio transforms.json, the fox scenes) must train bit for bit as the default without both, so
    the fox scenes' records made without the two parts stand for the default. On the CPU on every machine: on CUDA the
    rasteriser's backward adds with atomics in no fixed order, and Adam turns those roundings into whole steps."""
    torch.manual_seed(0)
    _, new, new_losses = _train(tmp_path / "new", "willags", steps=8, device="cpu")
    torch.manual_seed(0)
    _, old, old_losses = _train(
        tmp_path / "old", "willags", steps=8, device="cpu", **{"sky.enabled": False, "mask.safeguard.enabled": False}
    )
    model = new.pipeline.model
    assert model.config.mask.safeguard.enabled and model.mask_step.observations is None
    assert model.appearance_nets.sky is None and model.open_regions is None  # the sky found no skyline: off
    assert [v for v, _ in new_losses] == [v for v, _ in old_losses]
    for k, p in model.gauss_params.items():
        assert torch.equal(p, old.pipeline.model.gauss_params[k]), k


def test_default_on_a_colmap_scene_trains_its_sky_and_safeguard_and_reloads_them(tmp_path, shared_data):
    """On a COLMAP scene (keypoints) the default builds the sky above the skyline and the mask's safeguard; a
    checkpoint reloads with the same sky (ns-render / ns-eval rebuild the model from the scene's metadata)."""
    from nerfstudio.utils.eval_utils import eval_setup

    # 1/8 resolution while training (the resolution schedule's first stage): what is checked does not depend on it
    config, trainer, losses = _train(
        tmp_path, "willags", steps=6, data=shared_data / "sacre-coeur-mini", num_downscales=3
    )
    _check_finite(losses)
    model = trainer.pipeline.model
    assert model.appearance_nets.sky is not None and model.open_regions is not None
    assert model.mask_step.observations is not None and len(model.mask_step.observations) == model.num_train_data
    _, pipeline, _, _ = eval_setup(config.get_base_dir() / "config.yml", test_mode="test")
    sky = pipeline.model.appearance_nets.sky
    assert sky is not None
    for k, v in model.appearance_nets.sky.state_dict().items():
        assert torch.equal(v.cpu(), sky.state_dict()[k].cpu()), k
    cam = pipeline.datamanager.eval_dataset.cameras[0:1]
    with torch.no_grad():
        out = pipeline.model.get_outputs_for_camera(cam)
    assert torch.isfinite(out["rgb"]).all()


def test_the_sfm_depth_loss_trains_on_every_step_of_a_colmap_scene_and_is_off_by_default(tmp_path, shared_data):
    """With sfm_depth.weight > 0 every training step of a COLMAP scene holds the render's depth to its photo's SfM
    points (some observations used, the loss finite); the default leaves it out, depth not even rendered."""
    data = shared_data / "sacre-coeur-mini"
    _, trainer, losses = _train(
        tmp_path, "willags", steps=4, data=data, num_downscales=3, device="cpu", **{"sfm_depth.weight": 0.1}
    )
    _check_finite(losses)
    model = trainer.pipeline.model
    assert model.sfm_depth_on and model._render_mode() == "RGB+ED"
    assert all(m.get("sfm_depth_used", 0) > 0 for _, m in losses), [m.get("sfm_depth_used") for _, m in losses]
    default = _train(tmp_path / "default", "willags", steps=1, data=data, num_downscales=3, device="cpu")[2]
    assert "sfm_depth_used" not in default[0][1]

    def unreadable():
        raise OSError("points3D.bin: truncated")

    model._sfm_depths_of, model._sfm_depths = unreadable, None  # a points file that cannot be read: the loss goes off
    assert model._sfm_depth_term({}, {"image_idx": 0}, {}) == {} and not model.sfm_depth_on


def test_entry_points_resolve():
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    for name in ("willags", "willags-lite", "willags-3dgs"):
        assert name in methods, f"{name} not registered through nerfstudio.method_configs"
    from willags_ns.config import WillagsModelConfig

    assert isinstance(methods["willags"].pipeline.model, WillagsModelConfig)


def test_ns_train_cli_help_lists_willags_and_documents_options():
    exe = console_script("ns-train")
    out = subprocess.run([str(exe), "willags", "--help"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout
    for opt in ("--pipeline.model.latent.kind", "--pipeline.model.use-field", "--pipeline.model.mask.enabled"):
        assert opt in text
    assert "beta-VAE" in text  # docstrings reach the CLI help
    listing = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=300).stdout
    assert "willags" in listing


def test_ns_train_cli_runs_without_data_or_device_flags(tmp_path):
    """`ns-train willags` with no --data and no --machine.device-type: the default scene, on CPU."""
    exe = console_script("ns-train")
    cmd = [
        str(exe),
        "willags",
        "--max-num-iterations",
        "3",
        "--steps-per-save",
        "3",
        "--vis",
        "tensorboard",
        "--output-dir",
        str(tmp_path),
        "--timestamp",
        "t",
        "--pipeline.model.num-downscales",
        "0",
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, (out.stdout[-3000:], out.stderr[-3000:])
    assert list(tmp_path.rglob("*.ckpt"))
    cfg = next(tmp_path.rglob("config.yml")).read_text()
    if not torch.cuda.is_available():
        assert "device_type: cpu" in cfg
    # the default inspects the scene first; the embedded scene cannot be, so it trains the full model, says why, and
    # config.yml is resolved (reloading it does not try again)
    assert "not applied (no --data given: the embedded scene is not inspected)" in out.stdout
    assert "auto_config: false" in cfg and "mask: !!python/object:willags_ns.mask.rule.MaskConfig" in cfg
    assert yaml.load(cfg, Loader=yaml.Loader).pipeline.model.mask.enabled is True
    assert json.loads(next(tmp_path.rglob("auto_config.json")).read_text())["applied"] is False


def test_ns_eval_runs_the_protocol(tmp_path):
    config, _, _ = _train(tmp_path, "willags", steps=6)
    exe = console_script("ns-eval")
    out_json = tmp_path / "eval.json"
    cmd = [str(exe), "--load-config", str(config.get_base_dir() / "config.yml"), "--output-path", str(out_json)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, (res.stdout[-3000:], res.stderr[-3000:])
    results = json.loads(out_json.read_text())["results"]
    for k in ("psnr", "ssim", "encoder_psnr", "full_psnr", "left_loss_before", "left_loss_after"):
        assert k in results
    assert results["left_loss_after"] <= results["left_loss_before"] + 1e-6


def _run_ns_tool(tool: str, args: list[str], appearance: str) -> None:
    """Run a nerfstudio console script of this venv with WILLAGS_APPEARANCE=appearance; it must succeed."""
    import os

    cmd = [console_script(tool), *args]
    env = {**os.environ, "WILLAGS_APPEARANCE": appearance}
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert res.returncode == 0, (res.stdout[-2000:], res.stderr[-2000:])


def _look_trained(trainer) -> None:
    """After 6 steps the colour transform is still ~the identity (z barely matters) and the higher SH bands are zero:
    give the checkpoint a trained-looking, z-dependent, view-dependent state and save it again."""
    model = trainer.pipeline.model
    with torch.no_grad():
        g = torch.Generator().manual_seed(0)
        for name, p in model.appearance_nets.named_parameters():
            # the colour transform takes z ~ N(0, I) of 64 dims: a small perturbation already changes colours by
            # tens of 8-bit levels without saturating them
            p.add_((0.05 if name.startswith("modulation") else 0.3) * torch.randn(p.shape, generator=g).to(p.device))
        if "features_rest" in model.gauss_params:
            model.gauss_params["features_rest"].add_(
                0.05 * torch.randn(model.gauss_params["features_rest"].shape, generator=g).to(model.device)
            )
    trainer.save_checkpoint(trainer.config.max_num_iterations)


def test_ns_export_bakes_the_chosen_appearance_into_a_standard_ply(tmp_path):
    """`ns-export gaussian-splat` on a willags checkpoint: a 3DGS PLY whose colours follow WILLAGS_APPEARANCE."""

    import numpy as np
    from plyfile import PlyData

    config, trainer, _ = _train(tmp_path, "willags", steps=6)
    _look_trained(trainer)
    n = trainer.pipeline.model.num_points
    dc = {}
    for spec in ("mean", "sample:3"):
        out_dir = tmp_path / spec.replace(":", "_")
        _run_ns_tool(
            "ns-export",
            [
                "gaussian-splat",
                "--load-config",
                str(config.get_base_dir() / "config.yml"),
                "--output-dir",
                str(out_dir),
            ],
            appearance=spec,
        )
        ply = PlyData.read(str(out_dir / "splat.ply"))
        v = ply["vertex"]
        assert v.count <= n and v.count > 0
        for field in ("x", "opacity", "scale_0", "rot_0", "f_dc_0", "f_dc_1", "f_dc_2"):
            assert field in v.data.dtype.names
        dc[spec] = np.stack([v["f_dc_0"], v["f_dc_1"], v["f_dc_2"]], 1)
        # view-dependent colour as degree-3 SH (the colour transform applied to the SH): 15 x 3 f_rest, Inria layout
        rest = np.stack([v[f"f_rest_{i}"] for i in range(45)], 1)
        assert f"f_rest_{45}" not in v.data.dtype.names and np.isfinite(rest).all() and np.abs(rest).max() > 0
        assert np.isfinite(dc[spec]).all()
    # a different appearance gives different baked colours for the same Gaussians
    assert dc["mean"].shape == dc["sample:3"].shape and not np.allclose(dc["mean"], dc["sample:3"])


def test_ns_render_uses_the_chosen_appearance(tmp_path):
    """`ns-render dataset` on a willags checkpoint: WILLAGS_APPEARANCE picks the appearance of the frames."""

    import numpy as np
    from PIL import Image

    config, trainer, _ = _train(tmp_path, "willags", steps=6)
    _look_trained(trainer)
    frames = {}
    for spec in ("mean", "sample:5"):
        out_dir = tmp_path / ("render_" + spec.replace(":", "_"))
        _run_ns_tool(
            "ns-render",
            [
                "dataset",
                "--load-config",
                str(config.get_base_dir() / "config.yml"),
                "--output-path",
                str(out_dir),
                "--split",
                "test",
                "--rendered-output-names",
                "rgb",
                "--image-format",
                "png",
            ],
            appearance=spec,
        )
        pngs = sorted(out_dir.rglob("*.png"))
        assert pngs, f"ns-render wrote no frame under {out_dir}"
        frames[spec] = np.asarray(Image.open(pngs[0])).astype(np.float32)
    assert frames["mean"].shape == frames["sample:5"].shape
    assert np.abs(frames["mean"] - frames["sample:5"]).mean() > 0.5  # 8-bit levels: the appearance changed


def test_willags_optimisers_are_splatfactos_adam_fused_where_the_parameters_are_on_cuda():
    import torch

    from willags_ns.method_configs import FusedAdamOptimizerConfig, willags_config, willags_paper_config

    for cfg in (willags_config(), willags_paper_config()):
        assert all(isinstance(g["optimizer"], FusedAdamOptimizerConfig) for g in cfg.optimizers.values())
    means = willags_config().optimizers["means"]["optimizer"]
    opt = means.setup([torch.nn.Parameter(torch.zeros(4, 3))])
    assert isinstance(opt, torch.optim.Adam) and opt.defaults["eps"] == 1e-15 and opt.defaults["lr"] == means.lr
    assert not opt.defaults["fused"]  # CPU: torch's default implementation
    if torch.cuda.is_available():
        assert means.setup([torch.nn.Parameter(torch.zeros(4, 3, device="cuda"))]).defaults["fused"]
