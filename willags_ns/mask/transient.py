"""Perceptual transient mask: frozen VGG16 features of the ground truth vs the EMA teacher's render.

For a training image ``I`` and the teacher's render ``R`` of the same view (with the same appearance latent),
VGG16 features at relu1_2, relu2_2 and relu3_3 (ImageNet normalisation) are compared per layer as the mean over
channels of ``|f(I) - f(R)|``; each map is bilinearly upsampled to the image size and the three are summed:

    D[b, y, x] = sum_l up(mean_c |f_l(I) - f_l(R)|)[b, y, x]

Pixels with ``D < threshold`` (0.85) are static and enter the loss; the rest are treated as transient. A
transient (person, car, ...) is something the 3D model cannot explain, so its features differ from the render's
at every scale, while the residual of a static pixel is small and mostly low-level.

Weights. The paper uses torchvision's ImageNet VGG16 (``vgg16-397923af.pth``). :func:`load_vgg16_features`
finds it, in this order for ``weights="auto"``: an explicit state-dict file (``path``), then the torch hub cache
(``$TORCH_HOME/hub/checkpoints/vgg16-397923af.pth``, read with ``torch.load(weights_only=True)`` into layers
built here with the indices of torchvision's ``vgg16().features[0:16]``, so torchvision is not imported).
Nothing is ever downloaded unless ``weights="torchvision"`` is asked for explicitly.

Fallback (no ImageNet weights; ``source`` starts with ``"seeded"``, one warning per process). The same VGG16
layers with a fixed Kaiming-normal initialisation (fan-in, ReLU gain; ``torch.Generator`` seed 0; zero biases),
*calibrated* per tapped layer: on a fixed set of synthetic 1/f ("pink-noise") colour images, a proxy for
natural-image statistics, each tap is rescaled so that the mean per-pixel discrepancy between two *unrelated*
images is ``FALLBACK_UNRELATED_D / 3`` (summed over the three taps: ``FALLBACK_UNRELATED_D``). The rescaling is
folded into the conv weights (ReLU and max-pool are positively homogeneous), so the result is a plain VGG16
``features`` stack. Why random features: randomly initialised deep conv features already carry a perceptual
signal (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features", compare random networks too),
they keep the paper's multi-scale mechanism and code path, and the calibration gives the fixed 0.85 threshold a meaning
("a pixel whose content differs by more than ~0.85 / FALLBACK_UNRELATED_D of an unrelated image's") that does
not depend on the random draw. The real VGG's raw-feature D range could not be measured here (no weights can be
downloaded), so "comparable range" means this calibration, not a match to ImageNet numbers.

What the fallback flags (recall, false positives, IoU on a synthetic occluder and on fox-transient-only, and the
choice of FALLBACK_UNRELATED_D) and where it fails (it is not blur-invariant: it assumes the teacher's render is
about as sharp as the photo) is in docs/design.md, "The perceptual mask without ImageNet weights".
"""

import logging
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

logger = logging.getLogger(__name__)

VGG16_HUB_FILE = "vgg16-397923af.pth"
"""File name of torchvision's ImageNet VGG16 weights (``VGG16_Weights.IMAGENET1K_V1``) in the torch hub cache."""
VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256)
"""torchvision's VGG16 ``features`` configuration up to conv3_3 (indices 0..15 once ReLUs are interleaved)."""
TAPS = (3, 8, 15)
"""Indices in ``features`` of relu1_2, relu2_2, relu3_3."""
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
FALLBACK_SEED = 0
"""Seed of the fallback's Kaiming initialisation and of its calibration images."""
FALLBACK_UNRELATED_D = 2.0
"""Calibration target of the fallback: mean D between two unrelated (independent pink-noise) images, split
equally over the three taps. Chosen by measurement (module docstring) among 1.5 / 2 / 2.5 / 3: the
smallest FP rate with >= 99% of transient pixels flagged."""

VggWeights = Literal["auto", "torchvision", "path", "seeded"]
"""Where the VGG16 weights come from (see :func:`load_vgg16_features`)."""

_FALLBACK_WARNED = False


MIN_VGG_SIDE = 16
"""Images with a side below this are upsampled (bilinear) before the VGG features (relu3_3 is at 1/4 resolution);
D is resampled to the image size anyway. Splatfacto's resolution schedule trains an 8x8 image at 2x2."""


def _vgg16_features_layers() -> nn.Sequential:
    """``nn.Sequential`` with the exact indices of torchvision's ``vgg16().features[:16]`` (conv1_1 .. relu3_3)."""
    layers: list[nn.Module] = []
    c_in = 3
    for v in VGG16_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(c_in, int(v), kernel_size=3, padding=1), nn.ReLU()]
            c_in = int(v)
    return nn.Sequential(*layers)


def _load_state_dict_file(net: nn.Sequential, file: Path) -> None:
    """Load the conv weights of ``features.0 .. features.14`` from a torchvision-layout state dict."""
    sd = torch.load(str(file), map_location="cpu", weights_only=True)
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    wanted = set(net.state_dict().keys())  # "0.weight", "0.bias", ..., "14.bias"
    out = {}
    for k, v in sd.items():
        key = k[len("features.") :] if k.startswith("features.") else k
        if key in wanted:
            out[key] = v
    missing = wanted - out.keys()
    if missing:
        raise ValueError(f"{file}: not a VGG16 state dict, missing {sorted(missing)[:4]}...")
    net.load_state_dict(out, strict=True)


def _pink_noise(n: int, size: int, generator: torch.Generator) -> Tensor:
    """``n`` colour images [n, 3, size, size] in [0, 1] with a 1/f amplitude spectrum (natural-image proxy)."""
    fy = torch.fft.fftfreq(size).view(-1, 1)
    fx = torch.fft.rfftfreq(size).view(1, -1)
    amp = 1.0 / torch.sqrt(fx**2 + fy**2).clamp_min(1.0 / size)  # [S, S//2+1]
    noise = torch.randn(n, 3, size, size // 2 + 1, 2, generator=generator)
    spec = torch.view_as_complex(noise) * amp
    img = torch.fft.irfftn(spec, s=(size, size), dim=(-2, -1))  # [n, 3, S, S]
    # Correlated colour channels (natural images are mostly luminance variation).
    mix = torch.tensor([[0.8, 0.2, 0.0], [0.2, 0.6, 0.2], [0.0, 0.2, 0.8]]) + 0.5
    img = torch.einsum("ij,njhw->nihw", mix / mix.sum(1, keepdim=True), img)
    img = img - img.mean(dim=(-2, -1), keepdim=True)
    img = img / img.std(dim=(1, 2, 3), keepdim=True).clamp_min(1e-8)
    return (0.5 + 0.18 * img).clamp(0.0, 1.0)


def _tap_outputs(net: nn.Sequential, x: Tensor, taps: Sequence[int] = TAPS) -> list[Tensor]:
    feats = []
    for i, layer in enumerate(net):
        x = layer(x)
        if i in taps:
            feats.append(x)
        if i >= max(taps):
            break
    return feats


_NORMALIZE: dict[tuple[torch.device, torch.dtype], tuple[Tensor, Tensor]] = {}


def _imagenet_normalize(images: Tensor) -> Tensor:
    # the constants are copied to the device once: a copy from host memory per call blocks until the GPU has
    # finished all queued work (two pipeline drains per VGG pass otherwise)
    key = (images.device, images.dtype)
    if key not in _NORMALIZE:
        mean = torch.tensor(IMAGENET_MEAN, dtype=images.dtype).view(1, 3, 1, 1).to(images.device)
        std = torch.tensor(IMAGENET_STD, dtype=images.dtype).view(1, 3, 1, 1).to(images.device)
        _NORMALIZE[key] = (mean, std)
    mean, std = _NORMALIZE[key]
    return (images - mean) / std


@torch.no_grad()
def build_seeded_vgg16_features(seed: int = FALLBACK_SEED, unrelated_d: float = FALLBACK_UNRELATED_D) -> nn.Sequential:
    """The calibrated random fallback (see the module docstring). Deterministic for a given seed, on CPU."""
    g = torch.Generator().manual_seed(seed)
    net = _vgg16_features_layers()
    for m in net:
        if isinstance(m, nn.Conv2d):
            fan_in = m.in_channels * m.kernel_size[0] * m.kernel_size[1]
            m.weight.copy_(torch.randn(m.weight.shape, generator=g) * math.sqrt(2.0 / fan_in))
            if m.bias is not None:
                m.bias.zero_()
    imgs = _imagenet_normalize(_pink_noise(16, 64, g))
    feats = _tap_outputs(net, imgs)
    half = imgs.shape[0] // 2
    # Calibrate tap by tap: the factor applied to a tap's convs also scales every later tap, so divide it out.
    convs_per_tap = [[0, 2], [5, 7], [10, 12, 14]]
    applied = 1.0
    for tap_convs, f in zip(convs_per_tap, feats, strict=True):
        err = (f[:half] - f[half:]).abs().mean(dim=1).mean().item()  # raw unrelated-image discrepancy
        scale = (unrelated_d / len(TAPS)) / max(err, 1e-12)  # desired total multiplier of this tap
        ratio = scale / applied  # extra factor on this stage's first conv (input already scaled by `applied`)
        first = net[tap_convs[0]]
        assert isinstance(first, nn.Conv2d) and first.bias is not None
        first.weight.mul_(ratio)
        first.bias.mul_(ratio)
        # later convs of the same stage see the scaled input and must not rescale again: weights unchanged.
        applied = scale
    return net


def _warn_fallback(looked_in: Sequence[str], source: str) -> None:
    global _FALLBACK_WARNED
    if _FALLBACK_WARNED:
        return
    _FALLBACK_WARNED = True
    if looked_in:
        what = f"VGG16 ImageNet weights not found (looked in: {'; '.join(looked_in)})"
    else:
        what = "seeded VGG16 features requested instead of the ImageNet weights"
    msg = (
        f"willags: {what}; using {source} (a seeded, calibrated random VGG16) "
        "-- perceptual mask quality differs from the paper; to get the weights, run once with internet: "
        "python -c \"import torchvision; torchvision.models.vgg16(weights='IMAGENET1K_V1')\""
    )
    warnings.warn(msg, RuntimeWarning, stacklevel=3)  # one line on the terminal (_compat.one_line_own_warnings)


def hub_weights_file() -> Path:
    """Where torchvision caches the ImageNet VGG16 weights: ``torch.hub.get_dir()/checkpoints/vgg16-397923af.pth``."""
    return Path(torch.hub.get_dir()) / "checkpoints" / VGG16_HUB_FILE


def load_vgg16_features(weights: VggWeights = "auto", path: os.PathLike | None = None) -> tuple[nn.Sequential, str]:
    """VGG16 ``features[:16]`` (conv1_1 .. relu3_3), frozen and in eval mode, plus a ``source`` string.

    ``source`` is one of ``"path:<file>"``, ``"torch_hub:<file>"``, ``"torchvision:IMAGENET1K_V1"`` or
    ``"seeded:kaiming-seed0-calibrated"``. An explicit ``path`` that does not exist raises
    ``FileNotFoundError``; a failing "torchvision" load (offline) falls back to the seeded network, with the
    one-time warning.
    """
    looked_in: list[str] = []
    net: nn.Sequential | None = None
    source = ""
    if weights not in ("auto", "torchvision", "path", "seeded"):
        raise ValueError(f"unknown vgg weights option {weights!r}")
    if weights == "path" or (weights == "auto" and path is not None):
        if path is None:
            raise ValueError('vgg_weights="path" needs vgg_weights_path')
        file = Path(path).expanduser()
        if not file.is_file():
            raise FileNotFoundError(f"VGG16 weights file {file} not found")
        net = _vgg16_features_layers()
        _load_state_dict_file(net, file)
        source = f"path:{file}"
    elif weights == "auto":
        file = hub_weights_file()
        looked_in.append(str(file))
        if file.is_file():
            net = _vgg16_features_layers()
            _load_state_dict_file(net, file)
            source = f"torch_hub:{file}"
    elif weights == "torchvision":
        looked_in.append("torchvision.models.vgg16(weights=IMAGENET1K_V1) (hub cache / download)")
        try:
            import torchvision  # lazy: torchvision is heavy and may not import next to a CPU torch

            full = torchvision.models.vgg16(weights=torchvision.models.VGG16_Weights.IMAGENET1K_V1)
            net = _vgg16_features_layers()
            net.load_state_dict(nn.Sequential(*list(full.features.children())[:16]).state_dict(), strict=True)
            source = "torchvision:IMAGENET1K_V1"
        except Exception as e:  # offline, missing torchvision, corrupt cache...
            looked_in[-1] += f" failed: {type(e).__name__}: {e}"
            net = None
    if net is None:
        net = build_seeded_vgg16_features()
        source = f"seeded:kaiming-seed{FALLBACK_SEED}-calibrated"
        _warn_fallback(looked_in, source)
    net.requires_grad_(False)
    net.eval()
    return net, source


class PerceptualFeatures(nn.Module):
    """Frozen VGG16 relu1_2 / relu2_2 / relu3_3 features; the network is built lazily on the input's device.

    The network is deliberately *not* a registered submodule: its weights are not trainable, not part of the
    model's checkpoints (they are reloaded from their source), and building it lazily can therefore never make a
    checkpoint's keys disagree with a fresh model's. ``.to()`` on a parent does not move it; ``forward`` moves it
    to the input's device and dtype.
    """

    def __init__(
        self,
        weights: VggWeights = "auto",
        path: os.PathLike | None = None,
        max_resolution: int = 512,
    ):
        super().__init__()
        self.weights: VggWeights = weights
        self.path = path
        self.max_resolution = max_resolution
        self._holder: list[nn.Sequential] = []  # plain list: hides the network from state_dict / parameters()
        self._source: str | None = None

    @property
    def source(self) -> str | None:
        """Where the weights came from (see :func:`load_vgg16_features`); None before the first use."""
        return self._source

    def network(self, device: torch.device | None = None, dtype: torch.dtype | None = None) -> nn.Sequential:
        """The frozen ``features[:16]`` stack, built on first call and moved to ``device`` / ``dtype``."""
        if not self._holder:
            net, self._source = load_vgg16_features(self.weights, self.path)
            self._holder.append(net)
        net = self._holder[0]
        p = next(net.parameters())
        if (device is not None and p.device != torch.device(device)) or (dtype is not None and p.dtype != dtype):
            net = net.to(device=device, dtype=dtype)
            self._holder[0] = net
        return net

    @torch.no_grad()
    def forward(self, images: Float[Tensor, "B 3 H W"]) -> list[Tensor]:
        """Features ``[relu1_2 [B,64,h,w], relu2_2 [B,128,h/2,w/2], relu3_3 [B,256,h/4,w/4]]`` of images in
        [0, 1], computed at most at ``max_resolution`` (longest side). No gradient (the mask is a selector)."""
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images [B, 3, H, W], got {tuple(images.shape)}")
        h, w = images.shape[-2:]
        long_side = max(h, w)
        if min(h, w) < MIN_VGG_SIDE:  # two 2x2 max-pools before relu3_3: tiny images would pool to nothing
            s = MIN_VGG_SIDE / min(h, w)
            size = (max(MIN_VGG_SIDE, round(h * s)), max(MIN_VGG_SIDE, round(w * s)))
            images = F.interpolate(images, size=size, mode="bilinear", align_corners=False)
        elif long_side > self.max_resolution:
            s = self.max_resolution / long_side
            size = (max(1, round(h * s)), max(1, round(w * s)))
            images = F.interpolate(images, size=size, mode="bilinear", align_corners=False, antialias=True)
        net = self.network(images.device, images.dtype)
        return _tap_outputs(net, _imagenet_normalize(images))


def perceptual_error(
    feats_a: Sequence[Tensor], feats_b: Sequence[Tensor], size: tuple[int, int]
) -> Float[Tensor, "B H W"]:
    """``D = sum_l upsample(mean_c |a_l - b_l|, size)``: per-pixel perceptual discrepancy at ``size = (H, W)``."""
    if len(feats_a) != len(feats_b) or len(feats_a) == 0:
        raise ValueError(f"need matching non-empty feature lists, got {len(feats_a)} and {len(feats_b)}")
    total = None
    for a, b in zip(feats_a, feats_b, strict=True):
        if a.shape != b.shape:
            raise ValueError(f"feature shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
        d = (a - b).abs().mean(dim=1, keepdim=True)  # [B, 1, h, w]
        d = F.interpolate(d, size=tuple(size), mode="bilinear", align_corners=False)  # [B, 1, H, W]
        total = d if total is None else total + d
    assert total is not None
    return total[:, 0]


@torch.no_grad()
def image_distance(perceptual: PerceptualFeatures, image: Tensor, reference: Tensor) -> Float[Tensor, "H W"]:
    """D [H, W] between two images [H, W, 3] in [0, 1] (a photo and the teacher's render of it): both through one
    VGG pass (a batch of two), then :func:`perceptual_error`. The one path of training and of the mask evaluation."""
    H, W = image.shape[:2]
    feats = perceptual(torch.stack((image, reference.to(image.dtype))).permute(0, 3, 1, 2))
    return perceptual_error([f[:1] for f in feats], [f[1:] for f in feats], (H, W))[0]
