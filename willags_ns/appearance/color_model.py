"""The colour model contract: what the appearance needs from a model that turns a latent into Gaussians' colours.

A colour model is an `nn.Module` subclass of :class:`ColorModel` (the way gsplat's densification strategies share
`strategy/base.py`). It says which per-Gaussian tensors it reads (the Gaussians' own SH, an intrinsic feature f_s of
its size), colours Gaussians for a latent and view directions, prices what it adds (its penalty) and, where its
colours are linear in the SH coefficients, gives the exact SH of a fixed appearance (rendering and export bake
through it; without one the colour path fits SH by least squares). Everything else (caches, the teacher, the camera,
the field's f_d) is the colour path's (appearance/color_path.py), which calls only these methods.

The models, by `color_mode` (config.py):

| color_mode | module | what it is |
|---|---|---|
| "modulated" | appearance/modulation.py | the Gaussian's own SH colour under a global transform of z, plus a penalised per-Gaussian residual |
| "decoder" | appearance/decoder.py | the paper's T_color MLP of (f_d, f_s, view direction) |

A new colour model is one module holding its subclass and its config dataclass; config.py gives the config a group
and appearance/networks.py's `COLOR_MODELS` its `color_mode` name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor, nn


@dataclass(frozen=True)
class GaussianLayout:
    """The per-Gaussian tensors a colour model reads, which the Gaussians are built with (splats/gaussians.py)."""

    sh: bool
    """The Gaussians carry SH coefficients (splatfacto's features_dc / features_rest)."""
    intrinsic_dim: int
    """Size of the per-Gaussian intrinsic feature f_s (0: none)."""
    seed_color_in_features: bool = False
    """f_s's first 3 entries start at the seed point's colour (centred): an easy first solution for a model that
    regresses the colour from f_s alone."""

    def initial_features(self, n: int, seed_rgb: Tensor | None) -> Tensor | None:
        """f_s [n, intrinsic_dim] at initialisation (small and random, the seed colour where asked), or None."""
        if self.intrinsic_dim <= 0:
            return None
        f_s = 0.1 * torch.randn(n, self.intrinsic_dim)
        if self.seed_color_in_features and seed_rgb is not None and self.intrinsic_dim >= 3:
            f_s[:, :3] = seed_rgb * 2.0 - 1.0
        return f_s


class ColorModel(nn.Module):
    """The contract. Subclasses implement :meth:`build`, :meth:`layout` and :meth:`rgb` and set `reads_sh`; the rest
    has defaults (no per-Gaussian preparation, no penalty, no exact SH)."""

    reads_sh: ClassVar[bool] = False
    """Whether the model transforms the Gaussians' own SH colours: then the Gaussians carry SH coefficients, and the
    colour path evaluates them from the camera (`base`) before :meth:`rgb`."""

    @classmethod
    def build(cls, cfg: Any, latent_dim: int, field_dim: int) -> ColorModel:
        """The model for the model config `cfg`, a latent of `latent_dim` and the field's feature of `field_dim`
        (0: no field)."""
        raise NotImplementedError

    @classmethod
    def layout(cls, cfg: Any) -> GaussianLayout:
        """The per-Gaussian tensors it reads under the model config `cfg` (known before any network is built)."""
        raise NotImplementedError

    def prepare(self, z: Tensor, f_s: Tensor | None, f_d: Tensor | None, n: int) -> Tensor | None:
        """What the model computes once per latent for n Gaussians, whatever the view direction (e.g. the
        modulation's per-Gaussian residual), handed back to :meth:`rgb`, :meth:`penalty` and :meth:`exact_sh`; None
        when it has none."""
        return None

    def rgb(
        self,
        z: Tensor,
        base: Tensor | None,
        f_s: Tensor | None,
        f_d: Tensor | None,
        dirs: Tensor,
        prepared: Tensor | None,
    ) -> Tensor:
        """Colours [N, 3] (>= 0) of N Gaussians under latent z [D]: `base` [N, 3] their SH colours from the camera
        (models with `reads_sh`, else None), f_s [N, Fs] (its layout's intrinsic_dim) or None, the field's f_d [N, F] or None, `dirs`
        [N, 3] the directions from the camera centre to them (not normalised), `prepared` :meth:`prepare`'s."""
        raise NotImplementedError

    def penalty(self, prepared: Tensor | None) -> Tensor | None:
        """The model's term in the training loss, weighted, for one step's :meth:`prepare` output (None: no term)."""
        return None

    def anchors_render(self) -> bool:
        """Whether, outside training, the model's per-Gaussian part reads one fixed latent (:meth:`set_render_anchor`)
        instead of the appearance's, so that the appearance changes only what all Gaussians share. False here."""
        return False

    def set_render_anchor(self, z: Tensor | None) -> None:
        """The fixed latent of :meth:`anchors_render` (the model gives the training latents' mean when it leaves
        training, None when it trains again). Ignored here."""

    def exact_sh(
        self, z: Tensor, sh: Tensor, f_s: Tensor | None, f_d: Tensor | None, degree: int, active_degree: int
    ) -> Tensor | None:
        """SH coefficients [N, (degree + 1)**2, 3] that reproduce :meth:`rgb` exactly from any direction (gsplat's
        evaluation: sum_k c_k Y_k(d) + 0.5), from the Gaussians' SH `sh` [N, K, 3] used up to `active_degree`; None
        when the model has no exact form (the colour path then fits SH by least squares)."""
        return None
