"""`willags_ns.inspect`: another name of willags_ns/tools/inspect.py (willags-inspect's evidence and rules). Imports
of either name get that one module object, so patches and attributes agree."""

import sys

from willags_ns.tools import inspect as _module

sys.modules[__name__] = _module
