"""Synthetic inputs for `benchmarks/gpu_suite.py`: seed point clouds, cameras, and rasteriser parity scenes.

Pure torch (no nerfstudio, no gsplat), so the parity part of the suite runs where nerfstudio does not import.
Conventions:
- nerfstudio camera-to-world [3, 4] is OpenGL (camera looks along -z, +y up): `look_at_c2w`.
- gsplat world-to-camera `viewmats` [C, 4, 4] is OpenCV (camera looks along +z): parity scenes are drawn in that
  camera frame and mapped to the world through a random rigid transform, so the viewmat path is exercised too.
"""

import math
from dataclasses import dataclass

import torch
from torch import Tensor


def seed_points(n: int, seed: int = 0, half_extent: float = 1.0) -> tuple[Tensor, Tensor]:
    """A seed point cloud as a dataparser gives it: (xyz float32 [n, 3], rgb uint8 [n, 3]), uniform in a box.

    Uniform points in [-1, 1]^3: at n = 1M the 3-NN spacing is ~0.01, so with the orbit camera below (distance
    3, 60 deg field of view) each Gaussian starts a few pixels wide at 800 px, a plausible load for the tiler.
    """
    g = torch.Generator().manual_seed(seed)
    xyz = (torch.rand(n, 3, generator=g) * 2.0 - 1.0) * half_extent
    rgb = torch.randint(0, 256, (n, 3), generator=g, dtype=torch.uint8)
    return xyz, rgb


def look_at_c2w(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """nerfstudio (OpenGL) camera-to-world [3, 4]: columns right, up, back (= -forward), position."""
    fwd = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, up), dim=0)
    cam_up = torch.linalg.cross(right, fwd)
    return torch.stack([right, cam_up, -fwd, eye], dim=1)  # [3, 4]


def orbit_c2ws(n: int, radius: float = 3.0, height: float = 0.8) -> Tensor:
    """n cameras on a circle around the z axis, looking at the origin: [n, 3, 4] (nerfstudio convention)."""
    out = []
    for i in range(n):
        a = 2.0 * math.pi * i / max(n, 1)
        eye = torch.tensor([radius * math.cos(a), radius * math.sin(a), height])
        out.append(look_at_c2w(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])))
    return torch.stack(out)


def focal_for(width: int, fov_deg: float = 60.0) -> float:
    """Pinhole focal length (pixels) of a horizontal field of view."""
    return 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)


def smooth_image(height: int, width: int, seed: int = 0) -> Tensor:
    """A smooth random uint8 image [H, W, 3] (low-frequency noise): a stand-in ground truth that is not constant."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, 8, 8, generator=g)
    img = torch.nn.functional.interpolate(coarse, size=(height, width), mode="bicubic", align_corners=False)
    img = img + 0.05 * torch.rand(1, 3, height, width, generator=g)
    return (img.clamp(0, 1)[0].permute(1, 2, 0) * 255).to(torch.uint8)


# ---------------------------------------------------------------------------------------------- parity scenes
@dataclass
class ParityCase:
    """One rasteriser input set (all float32 on CPU; activated scales/opacities, as `rasterize` takes them)."""

    name: str
    means: Tensor  # [N, 3] world
    quats: Tensor  # [N, 4] wxyz, not normalised
    scales: Tensor  # [N, 3] > 0
    opacities: Tensor  # [N] in (0, 1)
    colors: Tensor  # [N, 3] or SH [N, K, 3]
    viewmats: Tensor  # [1, 4, 4] world-to-camera (OpenCV)
    Ks: Tensor  # [1, 3, 3]
    width: int
    height: int
    sh_degree: int | None = None
    render_mode: str = "RGB"

    def tensors(self) -> dict[str, Tensor]:
        return {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "colors": self.colors,
        }


def _random_rotation(g: torch.Generator) -> Tensor:
    q = torch.nn.functional.normalize(torch.randn(4, generator=g), dim=0)
    w, x, y, z = q.tolist()
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _uniform(g: torch.Generator, shape, lo: float, hi: float) -> Tensor:
    return lo + (hi - lo) * torch.rand(shape, generator=g)


def _log_uniform(g: torch.Generator, shape, lo: float, hi: float) -> Tensor:
    return torch.exp(_uniform(g, shape, math.log(lo), math.log(hi)))


def make_parity_case(
    name: str,
    n: int,
    width: int,
    height: int,
    seed: int,
    *,
    z_range: tuple[float, float] = (2.0, 6.0),
    xy_spread: float = 1.1,
    scale_range: tuple[float, float] = (0.01, 0.2),
    opacity_range: tuple[float, float] = (0.05, 0.95),
    anisotropy: float | None = None,
    sh_degree: int | None = None,
    render_mode: str = "RGB",
) -> ParityCase:
    """A random scene in front of one pinhole camera.

    Means are drawn in the OpenCV camera frame: depth z uniform in `z_range`, x/y uniform over `xy_spread` times
    the half field of view at that depth (> 1 puts some off-screen), then mapped to the world through a random
    rigid transform (that transform is the viewmat). Scales are log-uniform in `scale_range`; with `anisotropy`
    one axis is multiplied by it (needles / discs).
    """
    g = torch.Generator().manual_seed(seed)
    fov = math.radians(float(_uniform(g, (), 40.0, 70.0)))
    fx = 0.5 * width / math.tan(fov / 2)
    fy = fx * float(_uniform(g, (), 0.95, 1.05))
    cx = width / 2 + float(_uniform(g, (), -0.05, 0.05)) * width
    cy = height / 2 + float(_uniform(g, (), -0.05, 0.05)) * height
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    z = _uniform(g, (n,), *z_range)
    x = _uniform(g, (n,), -1.0, 1.0) * xy_spread * z * (width / 2) / fx
    y = _uniform(g, (n,), -1.0, 1.0) * xy_spread * z * (height / 2) / fy
    means_c = torch.stack([x, y, z], dim=-1)  # [N, 3] camera frame

    R = _random_rotation(g)
    t = torch.randn(3, generator=g)
    viewmat = torch.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = t
    means = (means_c - t) @ R  # world = R^T (x_c - t)

    scales = _log_uniform(g, (n, 3), *scale_range)
    if anisotropy is not None:
        scales[:, 0] *= anisotropy
    quats = torch.randn(n, 4, generator=g)
    opacities = _uniform(g, (n,), *opacity_range)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g)
    else:
        colors = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g)
        colors[:, 0] = torch.rand(n, 3, generator=g)
    return ParityCase(
        name, means, quats, scales, opacities, colors, viewmat[None], K[None], width, height, sh_degree, render_mode
    )


def parity_cases(quick: bool = False) -> list[ParityCase]:
    """Random scenes (several seeds, N in 100..5000, 64..256 px, square and not) plus the extremes.

    Extremes: tiny scales (sub-pixel, eps2d-dominated), huge scales (covering the image), Gaussians behind the
    camera (z in [-3, 3]), at the near plane (z around 0.01), off-screen (Jacobian clipping), needles
    (anisotropy 100), near-opaque (early termination), SH degree 3 colours, RGB+ED depth.
    """
    cases: list[ParityCase] = []
    if quick:
        sizes = [(100, 64, 64), (500, 64, 48)]
        seeds = [0]
    else:
        sizes = [(100, 64, 64), (1000, 128, 128), (5000, 256, 256), (2000, 256, 160), (3000, 200, 256)]
        seeds = [0, 1, 2]
    for seed in seeds:
        for n, w, h in sizes:
            cases.append(make_parity_case(f"random n={n} {w}x{h} s{seed}", n, w, h, seed))
    w, h = (64, 64) if quick else (128, 128)
    k = 4 if quick else 1  # fewer Gaussians in quick mode
    ext = [
        ("tiny scales", dict(n=1000 // k, scale_range=(1e-5, 1e-3))),
        ("huge scales", dict(n=200 // k, scale_range=(0.5, 3.0))),
        ("behind camera", dict(n=2000 // k, z_range=(-3.0, 3.0))),
        ("near plane", dict(n=500 // k, z_range=(0.002, 0.05), scale_range=(1e-4, 1e-2))),
        ("off-screen", dict(n=2000 // k, xy_spread=3.0)),
        ("needles", dict(n=1000 // k, scale_range=(1e-3, 1e-2), anisotropy=100.0)),
        ("near-opaque", dict(n=3000 // k, opacity_range=(0.98, 0.999))),
        ("sh degree 3", dict(n=2000 // k, sh_degree=3)),
        ("RGB+ED", dict(n=2000 // k, render_mode="RGB+ED")),
    ]
    for i, (name, kw) in enumerate(ext):
        cases.append(make_parity_case(name, width=w, height=h, seed=100 + i, **kw))
    return cases
