"""`willags_ns.autoconfig`: another name of willags_ns/tools/autoconfig.py (the automatic configuration). Imports of
either name get that one module object, so patches and attributes agree."""

import sys

from willags_ns.tools import autoconfig as _module

sys.modules[__name__] = _module
