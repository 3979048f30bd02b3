"""Real spherical harmonics up to degree 4, evaluated exactly like gsplat 1.4.0.

The basis constants and their order are those of gsplat's `_eval_sh_bases_fast` (Sloan, "Efficient Spherical
Harmonic Evaluation", JCGT 2013), so SH colours from the torch backend match the CUDA backend's
`spherical_harmonics()` to float rounding.
"""

import torch
from torch import Tensor

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
