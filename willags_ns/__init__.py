"""willags-ns: WilLaGS (latent-conditional 3D appearance fields for robust Gaussian splatting in the wild)
as a nerfstudio method. Importing the package registers the checkpoint globals nerfstudio needs (see _compat)."""

from willags_ns.engine.compat import register_checkpoint_safe_globals

register_checkpoint_safe_globals()

__version__ = "0.1.0"
