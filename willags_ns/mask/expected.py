"""The scene's expected residual: what the colour-residual mask compares a pixel's residual with instead of zero.

The residual mask (willags_ns/mask/residual.py) flags a pixel whose colour residual to the teacher's render stands
out from its image's. A transient does that in the one photo it is in; so does static scene the model fits badly
in every photo (a subject's fine detail against the sky, glass, foliage), which the mask then takes out of the loss
in every photo, where it never improves. What tells them apart is the other photos: behind a passer-by the facade's
residual is small in every other view, the hard detail's is large in all of them.

Each Gaussian carries a level ``h`` (gauss_params "residual_level", [N, 1], densified and saved with the others)
fitted to the residuals it is rendered over. On a step that computes a mask, two channels ride on the student's
rasterisation after the colours (and the teacher's, when fused):

    channel e = render of h, detached:      E[p]  = sum_g w_g(p) h_g        the expected residual at pixel p
    channel q = render of h - h.detach():   Q[p]  = 0 in value              its gradient reaches h alone

and the loss gains ``mean_p sign(E - r)[p] * Q[p]`` with E and r detached: 0 in value, 0 in the gradient of every
Gaussian's geometry and colour (Q's inputs are zeros), and ``mean_p w_g(p) sign(E - r)[p]`` in h_g's gradient: the
gradient of the least-absolute-deviations fit of E to the residual r, so h follows the median of each Gaussian's
residuals over the photos that see it. The median, not the mean: a passer-by's large residual in a few of the
photos does not raise the level of the facade behind them, a detail missed in most photos does. The rule then
holds the excess ``max(r - max(E, 0), 0)`` to the bar of r (the image's own statistics) in place of r, so it masks a
subset of what the plain rule masks. A Gaussian seen in one photo only learns that photo's residual; a transient's
pixels are explained by no Gaussian's level as long as most of the photos that see the Gaussians behind it show them
unoccluded. Measured numbers: docs/design.md, "A weight-free transient mask".

Pure functions; the model appends the channels (model.py), the rule subtracts (mask/rule.py).
"""

import torch
from jaxtyping import Float
from torch import Tensor

LEVEL = "residual_level"
"""The per-Gaussian level's name in gauss_params (and its optimiser group)."""


def expected_on(cfg) -> bool:
    """Whether the model config `cfg` learns the expected residual: the residual mask with mask.residual.expected on
    the full appearance model."""
    m = cfg.mask
    return cfg.appearance == "willags" and m.enabled and m.distance == "residual" and m.residual.expected


def initial_levels(n: int) -> Float[Tensor, "n 1"]:
    """Every Gaussian's level at 0: until the first masks have taught them, the rule is the plain residual's."""
    return torch.zeros(n, 1)


def level_channels(level: Float[Tensor, "n 1"]) -> Float[Tensor, "n 2"]:
    """The two per-Gaussian inputs of the expected-residual channels: h (detached) and h - h.detach() (zero in value,
    the identity in h's gradient)."""
    return torch.cat([level.detach(), level - level.detach()], dim=-1)


def excess_residual(r: Float[Tensor, "H W"], expected: Float[Tensor, "H W"]) -> Float[Tensor, "H W"]:
    """max(r - max(E, 0), 0): the residual beyond what the scene shows at that pixel in the other photos (a level fitted
    below 0 where Gaussians overlap expects nothing, not less than nothing)."""
    return (r - expected.to(r.dtype).clamp_min(0.0)).clamp_min(0.0)


def level_loss(
    expected: Float[Tensor, "H W"], probe: Float[Tensor, "H W"], r: Float[Tensor, "H W"]
) -> Float[Tensor, ""]:
    """mean_p sign(E - r)[p] * Q[p] with E and r detached: 0 in value, the gradient of mean_p |E - r| (the levels'
    least-absolute-deviations fit) through the probe channel Q (module docstring)."""
    return (torch.sign(expected.detach() - r.detach()) * probe).mean()
