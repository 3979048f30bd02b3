"""willags-ns: WilLaGS (latent-conditional 3D appearance fields for robust Gaussian splatting in the wild)
as a nerfstudio method. Importing the package registers the checkpoint globals nerfstudio needs and hides the deprecation warnings of
nerfstudio's own calls (see _compat)."""

from willags_ns._compat import one_line_own_warnings, register_checkpoint_safe_globals, silence_library_noise

register_checkpoint_safe_globals()
silence_library_noise()
one_line_own_warnings()

__version__ = "0.1.0"
