"""Real spherical harmonics up to degree 4, evaluated exactly like gsplat 1.4.0.

The basis constants and their order are those of gsplat's `_eval_sh_bases_fast` (Sloan, "Efficient Spherical
Harmonic Evaluation", JCGT 2013), so SH colours from the torch backend match the CUDA backend's
`spherical_harmonics()` to float rounding.
"""

import torch
from jaxtyping import Float
from torch import Tensor

from willags_ns.tensor_constants import constant

MAX_SH_DEGREE = 4


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients used by `degree`: (degree + 1) ** 2."""
    return (degree + 1) ** 2


def eval_sh_bases(degree: int, dirs: Tensor) -> Tensor:
    """SH basis values at unit directions.

    Args:
        degree: SH degree in [0, 4].
        dirs: unit directions. [..., 3]

    Returns:
        basis values. [..., (degree + 1) ** 2]
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be in [0, {MAX_SH_DEGREE}], got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, 0.2820947917738781)]
    if degree >= 1:
        a = -0.48860251190292
        out += [a * y, -a * z, a * x]
    if degree >= 2:
        z2 = z * z
        tb = -1.092548430592079 * z
        ta = 0.5462742152960395
        c1 = x * x - y * y
        s1 = 2 * x * y
        out += [ta * s1, tb * y, 0.9461746957575601 * z2 - 0.3153915652525201, tb * x, ta * c1]
        if degree >= 3:
            tc = -2.285228997322329 * z2 + 0.4570457994644658
            tb = 1.445305721320277 * z
            ta = -0.5900435899266435
            c2 = x * c1 - y * s1
            s2 = x * s1 + y * c1
            out += [
                ta * s2,
                tb * s1,
                tc * y,
                z * (1.865881662950577 * z2 - 1.119528997770346),
                tc * x,
                tb * c1,
                ta * c2,
            ]
            if degree >= 4:
                td = z * (-4.683325804901025 * z2 + 2.007139630671868)
                tc = 3.31161143515146 * z2 - 0.47308734787878
                tb = -1.770130769779931 * z
                ta = 0.6258357354491763
                c3 = x * c2 - y * s2
                s3 = x * s2 + y * c2
                out += [
                    ta * s3,
                    tb * s2,
                    tc * s1,
                    td * y,
                    1.984313483298443 * z2 * (1.865881662950577 * z2 - 1.119528997770346)
                    - 1.006230589874905 * (0.9461746957575601 * z2 - 0.3153915652525201),
                    td * x,
                    tc * c1,
                    tb * c2,
                    ta * c3,
                ]
    return torch.stack(out, dim=-1)


SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(dirs: Float[Tensor, "N 3"], degree: int) -> Float[Tensor, "N K"]:
    """Real spherical-harmonics basis of unit directions up to ``degree`` (0..3): ``K = (degree + 1)**2``, as 3DGS
    writes it (the colour decoder's view encoding, the SH bake's least-squares fit).

    The same functions, order and signs as `eval_sh_bases` (equal to float rounding: tests/appearance/test_decoder.py), in
    another evaluation order: the colour decoder's outputs, and so the paper configuration's training, depend on
    its last bits. ``dirs`` must be unit length.
    At d = (0, 0, 1), degree 1: [C0, 0, C1, 0] (the basis is -C1*y, C1*z, -C1*x after the constant).
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z  # [N] each (unused for degree < 2)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def _monomial_exponents(degree: int) -> list[tuple[int, int, int]]:
    """Exponents (i, j, k) of x^i y^j z^k: every monomial of total degree `degree`, then of `degree - 1`."""
    out = []
    for d in (degree, degree - 1):
        out += [(i, j, d - i - j) for i in range(d, -1, -1) for j in range(d - i, -1, -1)] if d >= 0 else []
    return out


def _monomial_factors(degree: int) -> list[list[int]]:
    """For each monomial of `_monomial_exponents(degree)`, its `degree` factors as indices into (1, x, y, z)."""
    out = []
    for e in _monomial_exponents(degree):
        f = [1] * e[0] + [2] * e[1] + [3] * e[2]
        out.append([0] * (degree - len(f)) + f)
    return out


_FACTOR_INDEX: dict[tuple[int, str], list[Tensor]] = {}


def homogeneous_monomials(degree: int, dirs: Tensor) -> Tensor:
    """The monomials of total degree `degree` and `degree - 1` of unit directions (in `_monomial_exponents`'
    order): (degree + 1) ** 2 of them, as many as SH bases up to `degree`, and on the unit sphere they span the same
    functions (every lower-degree monomial is one of them times (x^2 + y^2 + z^2)^k = 1). Each is a product of
    `degree` entries of (1, x, y, z): 2 * degree tensor operations for any degree, against one per term of
    `eval_sh_bases`.

    Args:
        degree: in [0, 4].
        dirs: unit directions. [..., 3]

    Returns:
        [..., (degree + 1) ** 2]
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be in [0, {MAX_SH_DEGREE}], got {degree}")
    if degree == 0:
        return torch.ones_like(dirs[..., :1])
    key = (degree, str(dirs.device))
    if key not in _FACTOR_INDEX:  # built once per device: a host-to-device copy in a training step would wait
        cols = list(zip(*_monomial_factors(degree), strict=True))
        _FACTOR_INDEX[key] = [torch.tensor(c, device=dirs.device) for c in cols]
    v = torch.cat([torch.ones_like(dirs[..., :1]), dirs], dim=-1)  # (1, x, y, z)
    out = v.index_select(-1, _FACTOR_INDEX[key][0])
    for index in _FACTOR_INDEX[key][1:]:
        out = out * v.index_select(-1, index)
    return out


_MONOMIAL_TO_SH: dict[int, Tensor] = {}


def monomial_to_sh(degree: int) -> Tensor:
    """[K, K] float64 matrix P with eval_sh_bases(degree, d) = homogeneous_monomials(degree, d) @ P for every unit
    direction d (K = (degree + 1) ** 2): solved once by least squares over directions spread over the sphere (exact
    to float64 rounding: both sides are polynomials of degree <= `degree` in d)."""
    if degree not in _MONOMIAL_TO_SH:
        g = torch.Generator().manual_seed(0)
        d = torch.nn.functional.normalize(torch.randn(512, 3, generator=g, dtype=torch.float64), dim=-1)
        _MONOMIAL_TO_SH[degree] = torch.linalg.lstsq(
            homogeneous_monomials(degree, d), eval_sh_bases(degree, d)
        ).solution
    return _MONOMIAL_TO_SH[degree]


_GSPLAT_SH: list = []


def _gsplat_sh():
    """gsplat's CUDA spherical_harmonics, or None where gsplat (or its CUDA build) is unavailable."""
    if not _GSPLAT_SH:
        try:
            from gsplat import spherical_harmonics as fused
        except Exception:  # no gsplat: the torch version
            fused = None
        _GSPLAT_SH.append(fused)
    return _GSPLAT_SH[0]


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Evaluate SH colours along (not necessarily unit) view directions, like gsplat's `spherical_harmonics()`.

    Only the first (degree + 1) ** 2 coefficients are used, so a model can grow its active degree over training.
    Note that gsplat's `rasterization()` adds 0.5 and clamps at 0 *after* this; `rasterize` does the same.

    Args:
        degree: SH degree in [0, 4].
        dirs: view directions (normalised here). [..., 3]
        coeffs: SH coefficients. [..., K, 3] with K >= (degree + 1) ** 2

    Returns:
        colours. [..., 3]
    """
    nb = num_sh_bases(degree)
    if coeffs.shape[-2] < nb:
        raise ValueError(f"sh_degree={degree} needs {nb} SH coefficients, got {coeffs.shape[-2]}")
    if coeffs.is_cuda and coeffs.dtype == torch.float32 and dirs.dtype == torch.float32:
        fused = _gsplat_sh()
        if fused is not None:
            # gsplat's fused kernel (forward and backward in one pass each; same maths, float32): the torch version
            # below launches ~40 element-wise kernels over [N, 16, 3] per call, which at 1M Gaussians costs
            # several ms per training step
            return fused(degree, dirs, coeffs)
    if degree == 0:
        return 0.2820947917738781 * coeffs[..., 0, :]
    # Clamped norm: a direction of length 0 (mean at the camera centre) stays finite, gradient included.
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    bases = eval_sh_bases(degree, dirs)  # [..., nb]
    return (bases[..., None] * coeffs[..., :nb, :]).sum(dim=-2)


def sh_color(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """The colour 3DGS gives SH coefficients [..., K, 3] seen along `dirs` [..., 3]: `spherical_harmonics` + 0.5,
    clamped at 0 (gsplat's rasterisation does the same). [..., 3]"""
    rgb = spherical_harmonics(degree, dirs, coeffs)
    return (rgb + constant(0.5, rgb)).clamp_min(0.0)
