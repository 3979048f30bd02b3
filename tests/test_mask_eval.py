"""Transient-mask scores against ground truth (willags_ns/eval/mask_eval.py)."""

import math
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from willags_ns.eval import mask_eval
from willags_ns.eval.mask_eval import aggregate_counts, count_pixels, mask_scores, resize_mask, teacher_render


def _rect(h, w, y0, y1, x0, x1):
    m = torch.zeros(h, w, dtype=torch.bool)
    m[y0:y1, x0:x1] = True
    return m


def test_counts_and_iou_known_answer():
    gt = _rect(10, 10, 0, 4, 0, 5)  # 20 px
    pred = _rect(10, 10, 0, 4, 2, 7)  # 20 px, 12 shared
    c = count_pixels(pred, gt)
    assert (c.tp, c.fp, c.fn, c.tn) == (12, 8, 8, 72)
    assert c.iou == pytest.approx(12 / 28)
    agg = aggregate_counts([c])
    assert agg["iou"] == pytest.approx(12 / 28)
    assert agg["recall"] == pytest.approx(12 / 20)
    assert agg["fp_rate"] == pytest.approx(8 / 80)


def test_images_without_transients_give_no_nan():
    empty = torch.zeros(6, 6, dtype=torch.bool)
    clean = count_pixels(empty, empty)
    assert clean.iou is None  # no IoU of its own ...
    agg = aggregate_counts([clean, clean])
    assert agg["iou"] is None and agg["iou_mean"] is None and agg["recall"] is None
    assert agg["fp_rate"] == 0.0 and agg["num_with_transients"] == 0
    # ... and with one occluded image, the clean image's false positives still count in the pooled IoU
    gt = _rect(6, 6, 0, 3, 0, 3)
    fp_only = count_pixels(_rect(6, 6, 5, 6, 5, 6), empty)
    agg = aggregate_counts([count_pixels(gt, gt), fp_only])
    assert agg["iou"] == pytest.approx(9 / 10)
    assert agg["iou_mean"] == pytest.approx(1.0)  # per-image mean over images with transients only
    for v in agg.values():
        assert v is None or not math.isnan(v)


def test_resize_mask_area_rule():
    m = np.zeros((4, 4), bool)
    m[0:2, 0:2] = True  # full block -> True
    m[2, 2] = True  # 1 of 4 -> False
    m[0, 2:4] = True  # 2 of 4 -> True (>= one half)
    out = resize_mask(m, 2, 2)
    assert out.tolist() == [[True, True], [False, False]]
    assert resize_mask(m, 4, 4).tolist() == m.tolist()


# ---------------------------------------------------------------- a tiny real model and a fake dataset


def _camera(width, height):
    from nerfstudio.cameras.cameras import Cameras, CameraType

    c2w = torch.eye(4)[:3][None].clone()
    c2w[0, 2, 3] = 2.5
    f = 0.8 * width
    return Cameras(
        camera_to_worlds=c2w,
        fx=torch.tensor([[f]]),
        fy=torch.tensor([[f]]),
        cx=torch.tensor([[width / 2]]),
        cy=torch.tensor([[height / 2]]),
        width=torch.tensor([[width]]),
        height=torch.tensor([[height]]),
        camera_type=CameraType.PERSPECTIVE,
    )


def _tiny_model(use_vae: bool, color_mode: str = "modulated", mask_fields: dict | None = None, **overrides):
    from nerfstudio.data.scene_box import SceneBox

    from tests._configs import all_components, latent, mask
    from willags_ns.appearance.triplane import TriplaneConfig
    from willags_ns.appearance.vae import VAEConfig
    from willags_ns.config import WillagsModelConfig

    g = torch.Generator().manual_seed(0)
    xyz = (torch.rand(800, 3, generator=g) - 0.5) * torch.tensor([2.4, 1.8, 0.4])
    rgb = (torch.rand(800, 3, generator=g) * 255).to(torch.uint8)
    torch.manual_seed(0)
    cfg = WillagsModelConfig(
        **all_components(
            latent=latent(use_vae, dim=8, vae=VAEConfig(image_size=16, channels=(8, 8))),
            triplane=TriplaneConfig(resolution=8, channels=4, hyper_hidden=(16,), feature_dim=8, mlp_hidden=16),
            intrinsic_dim=8,
            color_mode=color_mode,
            mask=mask(vgg_weights="seeded", **(mask_fields or {})),
            backend="torch",
            background_color="black",
            num_downscales=0,
            **overrides,
        )
    )
    scene_box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = cfg.setup(scene_box=scene_box, num_train_data=2, seed_points=(xyz, rgb))
    with torch.no_grad():
        model.gauss_params["opacities"].fill_(3.0)
        model.gauss_params["scales"].fill_(math.log(0.04))
    model.eval()
    return model


class _FakeDataset:
    """What mask_scores reads from an InputDataset: file names, uint8 images, the original cameras."""

    def __init__(self, images, cameras, names):
        self.images = images
        self.image_filenames = [Path(n) for n in names]
        self._dataparser_outputs = SimpleNamespace(cameras=cameras)
        self.scale_factor = 1.0

    def get_data(self, idx, image_type="uint8"):
        return {"image": torch.from_numpy(self.images[idx]), "image_idx": idx}


OCC = (180, 120, 60)


def _scene_with_occluder(tmp_path, use_vae=False):
    """Two training views of the model's own teacher render; view 0 gets a flat magenta rectangle (the transient),
    view 1 none. GT masks go to tmp_path/masks_gt."""
    from nerfstudio.cameras.cameras import Cameras

    H, W = 96, 128
    model = _tiny_model(use_vae)
    cam = _camera(W, H)
    cams = Cameras(
        camera_to_worlds=cam.camera_to_worlds.repeat(2, 1, 1),
        fx=cam.fx.repeat(2, 1),
        fy=cam.fy.repeat(2, 1),
        cx=cam.cx.repeat(2, 1),
        cy=cam.cy.repeat(2, 1),
        width=cam.width.repeat(2, 1),
        height=cam.height.repeat(2, 1),
        camera_type=cam.camera_type.repeat(2, 1),
    )
    images, masks = [], []
    for i in range(2):
        # no VAE: the teacher's latent does not depend on the image, so the clean GT is exactly its render
        r = teacher_render(model, cams[i : i + 1], torch.zeros(H, W, 3), i)
        img = (r.clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        m = np.zeros((H, W), bool)
        if i == 0:
            m[30:62, 44:84] = True
            img[m] = OCC
        images.append(img)
        masks.append(m)
    mdir = tmp_path / "masks_gt"
    mdir.mkdir()
    for i, m in enumerate(masks):
        Image.fromarray(m.astype(np.uint8) * 255).save(mdir / f"{i:04d}.png")
    ds = _FakeDataset(images, cams, [f"images/{i:04d}.png" for i in range(2)])
    return model, ds, mdir, images, masks


def test_known_occluder_gives_high_iou_and_clean_image_no_fp(tmp_path):
    model, ds, mdir, images, _ = _scene_with_occluder(tmp_path)
    assert images[1].std() > 10  # the renders are textured, not a flat background
    before = {k: v.clone() for k, v in model.state_dict().items() if torch.is_tensor(v)}
    out = mask_scores(model, ds, mdir, threshold=0.85, keep_per_image=True)
    assert out["status"] == "ok"
    assert out["num_images"] == 2 and out["num_with_transients"] == 1
    assert out["recall"] > 0.95
    assert out["iou"] > 0.6
    assert out["fp_rate"] < 0.05
    assert out["d_median_transient"] > 0.85 > out["d_median_clean"]
    clean = out["per_image"][1]
    assert clean["fp"] == 0 and clean["iou"] is None  # D = 0 up to 8-bit rounding: nothing flagged
    for k, v in out.items():
        assert not (isinstance(v, float) and math.isnan(v)), k
    for k, v in before.items():  # scoring changes nothing in the model
        assert torch.equal(v, model.state_dict()[k]), k


def test_before_mask_warmup_nothing_is_transient(tmp_path):
    model, ds, mdir, _, _ = _scene_with_occluder(tmp_path)
    assert model.step < model.config.mask.warmup_steps
    out = mask_scores(model, ds, mdir)  # the threshold training would use now: inf
    assert out["threshold"] == math.inf
    assert out["recall"] == 0.0 and out["fp_rate"] == 0.0 and out["iou"] == 0.0


def test_max_images_and_missing_masks(tmp_path):
    model, ds, mdir, _, _ = _scene_with_occluder(tmp_path)
    out = mask_scores(model, ds, mdir, max_images=1, threshold=0.85)
    assert out["num_images"] == 1
    assert mask_scores(model, ds, tmp_path / "nowhere")["status"].startswith("no training image")


@pytest.mark.parametrize("use_vae", [False, True])
def test_teacher_render_matches_the_training_path(use_vae):
    """mask_eval renders the teacher as a training step renders its pseudo-GT (its own rasterisation)."""
    model = _tiny_model(use_vae)
    H, W = 24, 32
    cam = _camera(W, H)
    g = torch.Generator().manual_seed(3)
    image = torch.rand(H, W, 3, generator=g)
    # perturb the teacher so it differs from the student (as after EMA updates)
    with torch.no_grad():
        for p in model.teacher.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))
    ours = teacher_render(model, cam, image, 1)
    model.train()
    model.config.mask.warmup_steps = 0
    model.config.mask.teacher.fused = False
    model.optimizers = {}  # only read by densification, which a single forward does not reach
    model.set_train_batch({"image": image, "image_idx": 1})
    out = model.get_outputs(_camera(W, H))
    model.end_step(0)
    torch.testing.assert_close(ours, out["teacher_rgb"])
    # and it is the teacher, not the student
    assert not torch.allclose(out["rgb"].detach(), ours)


def test_training_view_matches_nerfstudio_undistortion(shared_data):
    """fox-wild is OPENCV with distortion: the image and camera must be what the datamanager caches for training."""
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig

    from willags_ns.data.dataparser import WillagsDataParserConfig

    dm = FullImageDatamanagerConfig(
        dataparser=WillagsDataParserConfig(data=shared_data / "fox-wild"), cache_images_type="uint8"
    ).setup(device="cpu", test_mode="val")
    ds = dm.train_dataset
    for i in (0, 7):
        raw = ds.get_data(i, image_type="uint8")["image"]
        gt = mask_eval.load_gt_mask(
            shared_data / "fox-wild" / "masks_gt" / f"{Path(ds.image_filenames[i]).stem}.png",
            raw.shape[0],
            raw.shape[1],
        )
        cam, image, mask = mask_eval.training_view(ds, i, gt)
        cached = dm.cached_train[i]["image"].numpy()
        assert image.shape == cached.shape and mask.shape == cached.shape[:2]
        assert np.array_equal(image, cached)
        for attr in ("fx", "fy", "cx", "cy", "width", "height"):
            assert float(getattr(cam, attr)[0, 0]) == pytest.approx(
                float(getattr(dm.train_dataset.cameras, attr)[i, 0])
            )
        assert abs(mask.mean() - gt.mean()) < 0.02  # the occluder survives the warp


def test_residual_distance_scores_the_occluder_without_vgg(tmp_path):
    """mask.distance "residual": the same scene's flat occluder is found from the colour residual alone."""
    model, ds, mdir, _, _ = _scene_with_occluder(tmp_path)
    model.config.mask.distance = "residual"
    out = mask_scores(model, ds, mdir, threshold=0.1, keep_per_image=True)
    assert out["status"] == "ok" and out["rule"] == "residual"
    assert out["recall"] > 0.9 and out["iou"] > 0.8
    assert out["per_image"][1]["fp"] == 0  # the clean view: nothing masked
    from willags_ns.viewer import training_view_panels

    model.step = model.config.mask.warmup_steps  # the viewer's mask picture: the occluder tinted red, once masked
    W = ds.images[0].shape[1]
    pic = training_view_panels(model, ds, 0, max_width=3 * W).astype(int)
    overlay = pic[:, 2 * W :]
    assert overlay.shape[:2] == ds.images[0].shape[:2]
    occluded = np.zeros(overlay.shape[:2], bool)
    occluded[30:62, 44:84] = True
    tint = (overlay - pic[:, :W])[..., 0]  # overlay minus photo, red channel: what the mask added
    assert tint[occluded].mean() > 30 and abs(tint[~occluded]).mean() < 2
    model.step = 0  # before the warm-up: nothing is transient
    out = mask_scores(model, ds, mdir)
    assert out["threshold"] == math.inf and out["recall"] == 0.0 and out["fp_rate"] == 0.0


def test_without_ground_truth_fp_rate_is_the_share_dropped(tmp_path):
    """A scene without masks_gt/: every pixel counts as static, so fp_rate is the share of all pixels the mask drops
    (the occluder's 32 x 40 pixels of one of the two images)."""
    model, ds, mdir, images, masks = _scene_with_occluder(tmp_path)
    with_gt = mask_scores(model, ds, mdir, threshold=0.85)
    out = mask_scores(model, ds, None, threshold=0.85)
    assert out["status"] == "ok" and out["num_images"] == 2 and out["num_with_transients"] == 0
    dropped = with_gt["recall"] * sum(int(m.sum()) for m in masks) + with_gt["fp_rate"] * sum(
        int((~m).sum()) for m in masks
    )
    assert out["fp_rate"] == pytest.approx(dropped / sum(m.size for m in masks), abs=1e-6)
    assert 0.5 * masks[0].sum() / (2 * masks[0].size) < out["fp_rate"] < 2 * masks[0].sum() / (2 * masks[0].size)


def test_training_fit_over_the_kept_pixels_leaves_out_what_the_mask_leaves_unfit(tmp_path):
    """Training view 0 holds an occluder the model does not render: its whole-photo PSNR counts it, the PSNR over
    the pixels the mask keeps does not; the clean view keeps every pixel and scores the same either way."""
    from willags_ns.eval.protocol import psnr, train_view_scores

    model, ds, _, images, masks = _scene_with_occluder(tmp_path)
    cams = ds._dataparser_outputs.cameras
    imgs = [torch.from_numpy(im) for im in images]
    assert mask_eval.kept_pixels(model, cams[0:1], imgs[0].float() / 255, 0) is None  # before the mask's warm-up
    keep = mask_eval.kept_pixels(model, cams[0:1], imgs[0].float() / 255, 0, threshold=0.85)
    occluder = torch.from_numpy(masks[0])
    assert not keep[occluder].any() and keep[~occluder].float().mean() > 0.95  # the occluder, not the scene
    model.step = 30000  # the mask's bar in force: train_view_scores uses the step's own
    out = train_view_scores(model, cams, imgs, max_images=-1)
    assert 0.9 < out["train_kept_share"] < 1.0
    assert out["train_psnr_kept"] > out["train_psnr"] + 10  # the occluder held the whole photo's error
    pred = torch.rand(4, 4, 3, generator=torch.Generator().manual_seed(0))
    gt = pred.clone()
    gt[0, 0] += 0.5
    everything = torch.ones(4, 4, dtype=torch.bool)
    assert psnr(pred[everything], gt[everything]) < 40  # the kept pixels' PSNR, as train_view_scores takes it
    everything_but = everything.clone()
    everything_but[0, 0] = False
    assert psnr(pred[everything_but], gt[everything_but]) > 100
    model.config.mask.enabled = False  # no mask: the whole photo's scores only
    assert "train_psnr_kept" not in train_view_scores(model, cams, imgs)


def test_the_training_fit_counts_the_blobs_the_model_leaves_unfit_with_the_mask_on_or_off(tmp_path):
    """train_outlier_share: the colour-residual rule's share of each training photo against the model's own render.
    View 0 holds an occluder the model does not render, view 1 is clean: about half the occluder's share of one
    photo, and the same with the mask switched off (a diagnosis of the collection, not of the mask)."""
    from willags_ns.eval.protocol import train_view_scores

    model, ds, _, images, masks = _scene_with_occluder(tmp_path)
    cams = ds._dataparser_outputs.cameras
    imgs = [torch.from_numpy(im) for im in images]
    occluded = float(masks[0].mean()) / 2  # one photo of two
    with_mask = train_view_scores(model, cams, imgs, max_images=-1)["train_outlier_share"]
    model.config.mask.enabled = False
    without = train_view_scores(model, cams, imgs, max_images=-1)["train_outlier_share"]
    assert 0.6 * occluded < with_mask < 1.3 * occluded and without == pytest.approx(with_mask)
