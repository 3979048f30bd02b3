"""`willags_ns.data.process`: another name of willags_ns/tools/process.py (willags-process: photos to a COLMAP
scene). Imports of either name get that one module object, so patches and attributes agree."""

import sys

from willags_ns.tools import process as _module

sys.modules[__name__] = _module
