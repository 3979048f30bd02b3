# device-only shim: gsplat tries `from gsplat import csrc` before its JIT build; load the .so built on an earlier
# machine of the same image instead of compiling again (saves ~3.5 minutes of device time per machine)
import importlib.machinery
import importlib.util
import os

import torch  # noqa: F401  (the extension needs libtorch loaded)

_p = os.environ["WILLAGS_GSPLAT_SO"]
_loader = importlib.machinery.ExtensionFileLoader("gsplat_cuda", _p)
_spec = importlib.util.spec_from_file_location("gsplat_cuda", _p, loader=_loader)
_m = importlib.util.module_from_spec(_spec)
_loader.exec_module(_m)
globals().update({k: getattr(_m, k) for k in dir(_m) if not k.startswith("__")})
