"""Gaussian rasterization: `rasterize` with a gsplat (CUDA) and a pure-torch (any device) backend."""

from willags_ns.render.functional import BACKENDS, RENDER_MODES, rasterize

__all__ = ["BACKENDS", "RENDER_MODES", "rasterize"]
