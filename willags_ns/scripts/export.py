"""`willags-export`: nerfstudio's `ns-export gaussian-splat` (same options) plus `--appearance SPEC`.

    willags-export --load-config run/config.yml --output-dir exports --appearance image:IMG_0042

The PLY is a standard 3DGS file: the colour field under the chosen appearance, baked into per-Gaussian SH
(`WillagsModel.export_sh`). `ns-export gaussian-splat` itself bakes $WILLAGS_APPEARANCE (default: the mean).
SPECs: willags_ns.appearance_spec; interp needs its weight T here (a PLY is one appearance).
"""

import tyro
from nerfstudio.scripts import exporter as ns_exporter

from willags_ns.scripts.render import with_appearance_options

ExportGaussianSplat = with_appearance_options(ns_exporter.ExportGaussianSplat, ns_exporter)


def entrypoint() -> None:
    """Entrypoint for use with pyproject scripts."""
    tyro.extras.set_accent_color("bright_yellow")
    tyro.cli(tyro.conf.FlagConversionOff[ExportGaussianSplat]).main()  # type: ignore[valid-type]


if __name__ == "__main__":
    entrypoint()
