"""What nerfstudio's exporter and viewer read of a Gaussian model, for a model whose colours come from an appearance.

`ns-export gaussian-splat` writes `model.shs_0` / `model.shs_rest` as the PLY's f_dc / f_rest (or `model.colors`
at SH degree 0), and other nerfstudio code reads `model.features_dc` / `model.features_rest`: splatfacto's names
for its SH parameters. With appearance="sh" they are those parameters. With an appearance model the Gaussians have
no colour of their own (the paper's decoder: no SH parameters at all), so these names hand out the chosen appearance
(`current_latent()`) baked to SH (`baked_sh`) or to view-averaged colours (`baked_colors`) by the model's colour
path (appearance/color_path.py: exact for the modulated SH colour, a least-squares fit over view directions for the
decoder).

:class:`SplatExport` is a mixin placed before SplatfactoModel in WillagsModel's bases, so `super()` reaches
splatfacto's own properties. It reads the model's config, Gaussians, chosen latent and colour path (the
declarations under TYPE_CHECKING), and computes nothing itself: the bakes are ColorPath's.
"""

from typing import TYPE_CHECKING, Any

import torch
from nerfstudio.models.splatfacto import RGB2SH
from torch import Tensor

if TYPE_CHECKING:
    from willags_ns.appearance.color_path import ColorContext, ColorPath
    from willags_ns.appearance.networks import AppearanceNetworks


class SplatExport:
    """splatfacto's exporter-facing names (`shs_0`, `shs_rest`, `colors`, `features_dc`, `features_rest`) and the
    bakes behind them: `export_sh`, `baked_sh`, `baked_colors`."""

    if TYPE_CHECKING:  # provided by WillagsModel
        config: Any
        gauss_params: Any
        device: Any
        means: Tensor
        intrinsic_features: Tensor | None
        appearance_nets: AppearanceNetworks | None
        color_path: ColorPath

        def current_latent(self) -> Tensor: ...
        def sh_coeffs(self, gp: dict | None = None) -> Tensor | None: ...
        def color_context(self) -> ColorContext: ...

    @property
    def features_dc(self):
        """Splatfacto's name for the degree-0 SH parameter; with the paper's decoder (no SH parameters), the chosen
        appearance baked to SH."""
        return self.gauss_params["features_dc"] if "features_dc" in self.gauss_params else self.export_sh()[:, 0, :]

    @property
    def features_rest(self):
        return self.gauss_params["features_rest"] if "features_rest" in self.gauss_params else self.export_sh()[:, 1:]

    @property
    def colors(self):
        return super().colors if self.config.appearance == "sh" else self.baked_colors()  # type: ignore[misc]

    @property
    def shs_0(self):
        """What exporters write as f_dc: splatfacto's SH, or the chosen appearance baked to SH."""
        return super().shs_0 if self.config.appearance == "sh" else self.export_sh()[:, 0, :]  # type: ignore[misc]

    @property
    def shs_rest(self):
        return super().shs_rest if self.config.appearance == "sh" else self.export_sh()[:, 1:, :]  # type: ignore[misc]

    @torch.no_grad()
    def export_sh(self) -> Tensor:
        """SH [N, K, 3] of the chosen appearance for exporters (`ns-export gaussian-splat` writes f_dc + f_rest): the
        decoder fitted by SH of degree render_sh_degree (view-dependent, 3DGS layout); with render_sh_degree=-1, the
        decoder colour averaged over export_view_samples directions as degree 0."""
        deg = self.config.render_sh_degree
        if deg < 0:
            return RGB2SH(self.baked_colors())[:, None, :]
        return self.baked_sh(self.current_latent(), self.means, self.intrinsic_features, deg)

    @torch.no_grad()
    def baked_sh(self, z: Tensor, means: Tensor, f_s, degree: int, key: tuple | None = None, sh=None) -> Tensor:
        """SH coefficients [N, (degree + 1)**2, 3] reproducing the appearance's colour (ColorPath.baked_sh)."""
        assert self.appearance_nets is not None
        sh = self.sh_coeffs() if sh is None else sh
        return self.color_path.baked_sh(self.appearance_nets, z, means, f_s, degree, self.color_context(), sh, key)

    @torch.no_grad()
    def baked_colors(self, z: Tensor | None = None) -> Tensor:
        """View-independent colours [N, 3] for export: the appearance averaged over a Fibonacci sphere of views."""
        assert self.appearance_nets is not None
        z = self.current_latent() if z is None else z.to(self.device)
        nets, k, ctx = self.appearance_nets, max(1, self.config.export_view_samples), self.color_context()
        return self.color_path.baked_colors(nets, z, self.means, self.intrinsic_features, k, ctx, self.sh_coeffs())
