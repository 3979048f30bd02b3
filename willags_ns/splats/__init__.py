"""The 3DGS side: the Gaussians, their densification strategy, the rasteriser call and the composite, and the names
splatfacto's exporter reads."""
