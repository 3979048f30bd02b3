"""NeRF-W protocol: halves, latent fitting, and a frozen scene (willags_ns/eval/protocol.py)."""

import math
import warnings

import pytest
import torch

from willags_ns.eval.protocol import EvalProtocolConfig, evaluate_model, fit_latent, split_halves


@pytest.mark.parametrize("width", [2, 3, 7, 8, 135, 240])
def test_split_halves_disjoint_and_covering(width):
    left, right = split_halves(width)
    cols_l = set(range(width)[left])
    cols_r = set(range(width)[right])
    assert cols_l and cols_r
    assert not cols_l & cols_r
    assert cols_l | cols_r == set(range(width))
    assert max(cols_l) < min(cols_r)  # left is left
    assert len(cols_l) == width // 2


@pytest.mark.parametrize("width", [0, 1])
def test_split_halves_too_narrow_raises(width):
    with pytest.raises(ValueError):
        split_halves(width)


def test_fit_latent_uses_only_the_given_columns():
    """A toy renderer: the image is sigmoid(z) per channel; the left half of the GT is one colour, the right
    another. Fitting on the left must reach the left colour whatever the right half holds."""
    H, W = 16, 24  # the loss has an SSIM term: 11-px window
    left, right = split_halves(W)
    target = torch.tensor([0.2, 0.5, 0.8])

    def render(z):
        return torch.sigmoid(z).view(1, 1, 3).expand(H, W, 3)

    z0 = torch.zeros(3)
    fits = []
    for right_colour in (0.0, 1.0):
        gt = torch.empty(H, W, 3)
        gt[:, left] = target
        gt[:, right] = right_colour
        z, hist = fit_latent(render, gt, z0, left, steps=300, lr=0.05)
        assert hist[-1] < hist[0]
        fits.append(torch.sigmoid(z))
    torch.testing.assert_close(fits[0], fits[1])  # the right half never entered the loss
    torch.testing.assert_close(fits[0], target, atol=0.03, rtol=0)
    assert torch.equal(z0, torch.zeros(3))  # the initial latent is not modified in place


# ---------------------------------------------------------------- a tiny real WillagsModel


def _camera(width=32, height=24):
    from nerfstudio.cameras.cameras import Cameras, CameraType

    c2w = torch.eye(4)[:3][None].clone()  # looks down -z from the origin
    c2w[0, 2, 3] = 3.0
    f = 0.9 * width
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


def _tiny_model(use_vae: bool = True, **overrides):
    from nerfstudio.data.scene_box import SceneBox

    from tests._configs import all_components, latent, mask
    from willags_ns.appearance.triplane import TriplaneConfig
    from willags_ns.appearance.vae import VAEConfig
    from willags_ns.config import WillagsModelConfig

    g = torch.Generator().manual_seed(0)
    xyz = (torch.rand(300, 3, generator=g) - 0.5) * torch.tensor([2.0, 1.5, 0.5])
    rgb = (torch.rand(300, 3, generator=g) * 255).to(torch.uint8)
    kw = all_components(
        latent=latent(use_vae, dim=8, vae=VAEConfig(image_size=16, channels=(8, 8))),
        triplane=TriplaneConfig(resolution=8, channels=4, hyper_hidden=(16,), feature_dim=8, mlp_hidden=16),
        intrinsic_dim=8,
        mask=mask(enabled=False),
        backend="torch",
        background_color="black",
        num_downscales=0,
    )
    kw.update(overrides)
    torch.manual_seed(0)
    cfg = WillagsModelConfig(**kw)
    scene_box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = cfg.setup(scene_box=scene_box, num_train_data=2, seed_points=(xyz, rgb))
    with torch.no_grad():
        # opaque, visible Gaussians, so the render depends on the colours
        model.gauss_params["opacities"].fill_(2.0)
        # the field starts nearly independent of z (small init); scale it up as training would, so the latent
        # visibly changes the render
        field = getattr(model.appearance_nets, "field", None) if model.appearance_nets is not None else None
        if field is not None:
            field.basis.weight.mul_(300.0)
            field.mlp[-1].weight.mul_(30.0)
        # the modulated colour transform starts at the identity (z has no effect yet): give it a trained-like,
        # z-dependent state
        mod = getattr(model.appearance_nets, "modulation", None) if model.appearance_nets is not None else None
        if mod is not None:
            for p in mod.parameters():
                p.add_(0.2 * torch.randn(p.shape, generator=g))
    return model


def _state(model):
    return {k: v.detach().clone() for k, v in model.state_dict().items() if torch.is_tensor(v)}


def _render_under(model, cam, z):
    """The model's own render of `cam` under latent z: a ground truth whose appearance is known."""
    c = cam.to("cpu")
    c.metadata = {"appearance_latent": z}
    with torch.no_grad():
        return model.get_outputs(c)["rgb"].clone()


def test_protocol_fits_the_latent_and_leaves_the_scene_untouched():
    model = _tiny_model()
    cam = _camera()
    model.eval()
    # ground truth: the model's own render under a latent far from the encoder's guess
    z_true = 3.0 * torch.randn(8, generator=torch.Generator().manual_seed(1))
    gt = _render_under(model, cam, z_true)
    assert gt.std() > 0.01
    before = _state(model)
    flags = {n: p.requires_grad for n, p in model.named_parameters()}
    agg, per_image = evaluate_model(model, cam, [gt], EvalProtocolConfig(steps=25, lr=0.1), names=["a.png"])
    assert agg["left_loss_after"] < agg["left_loss_before"]
    assert per_image[0]["image"] == "a.png"
    for k in ("psnr", "ssim", "encoder_psnr", "full_psnr"):
        assert math.isfinite(agg[k])
    assert agg["psnr"] > agg["encoder_psnr"]  # the fitted latent explains the held-out half better
    after = {k: v for k, v in model.state_dict().items() if torch.is_tensor(v)}
    assert before.keys() == after.keys()
    for k, v in before.items():
        assert torch.equal(v, after[k]), f"evaluate_model changed {k}"
    assert {n: p.requires_grad for n, p in model.named_parameters()} == flags  # frozen only inside


def test_protocol_without_vae_starts_from_the_mean_embedding():
    model = _tiny_model(use_vae=False)
    cam = _camera()
    model.eval()
    gt = _render_under(model, cam, torch.full((8,), 2.0))
    before = _state(model)
    agg, _ = evaluate_model(model, cam, [gt], EvalProtocolConfig(steps=15, lr=0.1))
    assert agg["left_loss_after"] < agg["left_loss_before"]
    for k, v in before.items():
        assert torch.equal(v, model.state_dict()[k]), k


def test_protocol_sh_model_has_no_latent():
    model = _tiny_model(appearance="sh", use_vae=False, use_field=False)
    cam = _camera()
    model.eval()
    with torch.no_grad():
        gt = model.get_outputs(cam.to("cpu"))["rgb"].clone()
    before = _state(model)
    agg, per_image = evaluate_model(model, cam, [gt, gt], EvalProtocolConfig(steps=5, max_images=1))
    assert agg["num_images"] == 1 and len(per_image) == 1
    assert "left_loss_before" not in agg and "encoder_psnr" not in agg
    assert agg["psnr"] > 40  # scored against its own render: identical up to float noise
    for k, v in before.items():
        assert torch.equal(v, model.state_dict()[k]), k


def test_oracle_latent_and_train_view_scores():
    """Diagnosis keys: the oracle (latent fitted on the whole image) explains the right half at least as well as the
    protocol's left-half fit; train-view scores render each training image with its own stored latent."""
    from willags_ns.eval.protocol import train_view_scores

    model = _tiny_model()
    cam = _camera()
    model.eval()
    z_true = 3.0 * torch.randn(8, generator=torch.Generator().manual_seed(1))
    gt = _render_under(model, cam, z_true)
    agg, _ = evaluate_model(model, cam, [gt], EvalProtocolConfig(steps=25, lr=0.1, oracle=True))
    assert math.isfinite(agg["oracle_psnr"]) and agg["oracle_psnr"] >= agg["psnr"] - 0.5
    model.train_latents[0] = z_true
    scores = train_view_scores(model, cam, [gt], max_images=4)
    assert scores["train_num_images"] == 1 and scores["train_psnr"] > 40  # its own latent reproduces its render
    model.train_latents[0] = -z_true
    assert train_view_scores(model, cam, [gt])["train_psnr"] < scores["train_psnr"] - 3  # a wrong latent does not


def test_reduced_fit_never_sees_the_right_half_and_still_fits():
    """fit_max_side: the latent is fitted on a k-times smaller image (k = 3 for 72 px at 24), the score stays at
    full resolution. The fitted pixels come from the left half only: a different right half gives the same latent;
    the fit still explains the held-out half better than the encoder's latent; progress sees every Adam step."""
    from willags_ns.eval.protocol import block_mean, downscale_camera, fit_factor, resolve_fit_max_side

    assert fit_factor(72, 48, 24) == 3 and fit_factor(72, 48, 0) == 1 and fit_factor(20, 10, 24) == 1
    assert resolve_fit_max_side(-1, "cpu") == 320 and resolve_fit_max_side(0, "cpu") == 0
    assert resolve_fit_max_side(-1, "cuda") == 0 and resolve_fit_max_side(100, "cuda") == 100
    img = torch.arange(7 * 8 * 1, dtype=torch.float32).view(7, 8, 1)
    torch.testing.assert_close(block_mean(img, 3), torch.tensor([[[9.0], [12.0]], [[33.0], [36.0]]]))
    cam = _camera(72, 48)
    small = downscale_camera(cam, 3)
    assert (int(small.width), int(small.height)) == (24, 16)
    torch.testing.assert_close(small.fx, cam.fx / 3)
    torch.testing.assert_close(small.cx, cam.cx / 3)

    model = _tiny_model()
    model.eval()
    z_true = 3.0 * torch.randn(8, generator=torch.Generator().manual_seed(1))
    gt = _render_under(model, cam, z_true)
    other = gt.clone()
    other[:, 36:] = torch.rand(48, 36, 3, generator=torch.Generator().manual_seed(2))  # another right half

    class Recorder:
        def __init__(self):
            self.tasks: dict[int, list] = {}

        def add_task(self, description, total):
            self.tasks[len(self.tasks)] = [description, total, 0]
            return len(self.tasks) - 1

        def advance(self, task, n=1):
            self.tasks[task][2] += n

    cfg = EvalProtocolConfig(steps=20, lr=0.1, fit_max_side=24)
    rec = Recorder()
    agg, per_image = evaluate_model(model, cam, [gt], cfg, names=["a.png"], progress=rec)
    assert rec.tasks == {0: ["image 1/1 a.png (latent fit, left half at 24x16 px)", 20, 20]}
    assert per_image[0]["fit_scale"] == 3.0
    assert agg["left_loss_after"] < agg["left_loss_before"] and agg["psnr"] > agg["encoder_psnr"]
    _, per_other = evaluate_model(model, cam, [other], cfg)
    assert per_other[0]["left_loss_after"] == per_image[0]["left_loss_after"]  # the right half never entered the fit
    assert per_other[0]["full_psnr"] != per_image[0]["full_psnr"]  # ... though it is scored


def test_a_uint8_test_image_scores_as_the_training_loss_sees_it():
    """The eval split stays cached as uint8 (eval_split_images hands the cache over as it is); the protocol turns each
    image into floats at use, the values the training loss sees (splatfacto's get_gt_img: uint8 / 255): the same
    scores as the float image."""
    from types import SimpleNamespace

    from willags_ns.eval.protocol import eval_split_images, train_view_scores, unit_float

    model = _tiny_model()
    cam = _camera()
    model.eval()
    gt = _render_under(model, cam, 3.0 * torch.randn(8, generator=torch.Generator().manual_seed(1)))
    gt8 = (gt * 255).round().to(torch.uint8)
    assert torch.equal(unit_float(gt8), model.get_gt_img(gt8))  # what the loss compares a render with
    cached = SimpleNamespace(cached_eval=[{"image": gt8}])
    images = eval_split_images(cached)
    assert images[0] is gt8  # no float copy of the split
    cfg = EvalProtocolConfig(steps=3, lr=0.1)
    torch.manual_seed(0)
    from_uint8, _ = evaluate_model(model, cam, images, cfg)
    torch.manual_seed(0)
    from_float, _ = evaluate_model(model, cam, [gt8.float() / 255.0], cfg)
    assert from_uint8 == from_float
    assert train_view_scores(model, cam, [gt8]) == train_view_scores(model, cam, [gt8.float() / 255.0])


# ---------------------------------------------------------------- the fit's start among the training latents


def test_spread_picks_start_with_the_usual_start_then_take_the_farthest_rows_first():
    from willags_ns.eval.protocol import spread_picks

    table = torch.tensor([[0.0, 0.0], [1.0, 0.0], [10.0, 0.0], [10.1, 0.0]])
    first = torch.zeros(2)
    assert torch.equal(spread_picks(table, first, 0), first[None])
    two = spread_picks(table, first, 2)
    assert torch.equal(two, torch.stack([first, table[3], table[1]]))  # the far end, then the row farthest from both
    every = spread_picks(table, first, 10)
    assert every.shape == (5, 2) and sorted(every[1:, 0].tolist()) == sorted(table[:, 0].tolist())
    assert torch.equal(spread_picks(table[:0], first, 3), first[None])  # no training latent: the usual start alone


def test_best_start_picks_the_candidate_the_left_half_prefers_and_keeps_the_usual_start_on_ties():
    from willags_ns.eval.protocol import best_start

    H, W = 16, 24
    left, right = split_halves(W)

    def render(z):
        return torch.sigmoid(z).view(1, 1, 3).expand(H, W, 3)

    cands = torch.tensor([[0.0, 0.0, 0.0], [-2.0, 0.0, 2.0], [2.0, 2.0, 2.0]])
    gt = torch.empty(H, W, 3)
    gt[:, left] = torch.sigmoid(cands[1])
    gt[:, right] = torch.sigmoid(cands[2])  # the right half would prefer another: it is never seen
    z, i, losses = best_start(render, gt, left, cands)
    assert i == 1 and torch.equal(z, cands[1]) and len(losses) == 3 and losses[1] == min(losses)
    _, i, _ = best_start(render, gt, left, torch.stack([cands[1], cands[1]]))
    assert i == 0


def test_protocol_starts_a_far_photo_from_the_training_latent_its_left_half_matches():
    model = _tiny_model(use_vae=False)
    cam = _camera()
    model.eval()
    table = model.appearance_nets.embeddings.weight
    z_far = 3.0 * torch.randn(8, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        table[0] = z_far  # a training photo of the far appearance ...
        table[1] = -z_far  # ... and one of the opposite: their mean, the usual start, is neither
    gt = _render_under(model, cam, z_far)
    plain, _ = evaluate_model(model, cam, [gt], EvalProtocolConfig(steps=3, lr=0.01))
    before = _state(model)
    agg, per_image = evaluate_model(model, cam, [gt], EvalProtocolConfig(steps=3, lr=0.01, start_candidates=2))
    assert per_image[0]["start_pick"] == 1  # the far row (the first picked: both rows are as far from the mean)
    assert agg["psnr"] > plain["psnr"] + 3  # three small steps from the right start beat three from the mean
    assert agg["left_loss_before"] < plain["left_loss_before"]
    for k, v in before.items():
        assert torch.equal(v, model.state_dict()[k]), k
    assert "start_pick" not in plain
