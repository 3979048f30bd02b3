"""willags-ns: WilLaGS (latent-conditional 3D appearance fields for robust Gaussian splatting in the wild)
as a nerfstudio method. Importing the package registers the checkpoint globals nerfstudio needs and the classes of
config.yml files written before the package had its rooms, and hides the deprecation warnings of nerfstudio's own
calls (see engine/compat.py)."""

import yaml

from willags_ns.engine.compat import (
    one_line_own_warnings,
    register_checkpoint_safe_globals,
    register_config_yml_classes,
    silence_library_noise,
)

register_checkpoint_safe_globals()
register_config_yml_classes(yaml.Loader)
register_config_yml_classes(yaml.UnsafeLoader)
silence_library_noise()
one_line_own_warnings()

__version__ = "0.1.0"
