"""fusion's compiled kernels (fusion/_ins.c, fusion/_cycles.c), loaded once per process through ctypes.

They are built with the package (setup.py: plain C, no Python headers). fusion imports nothing of the rest of
fieldlog, so it has this loader of its own beside ``fieldlog.drive.native``.
"""

from __future__ import annotations

import ctypes
import importlib.util

_loaded: dict[str, ctypes.CDLL] = {}


def load(module: str, signatures: dict[str, list]) -> ctypes.CDLL:
    """The kernel ``module`` (e.g. "fieldlog.fusion._ins") with its functions' argtypes set from ``signatures``
    (name: argtypes; every function returns nothing). Raises ImportError, naming the module, when it is not
    built."""
    if module not in _loaded:
        spec = importlib.util.find_spec(module)
        if spec is None or spec.origin is None:
            raise ImportError(f"fieldlog's compiled kernel {module} is not built: reinstall fieldlog "
                              "(pip install -e . builds it; needs a C compiler)", name=module)
        lib = ctypes.CDLL(spec.origin)
        for name, argtypes in signatures.items():
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = None, argtypes
        _loaded[module] = lib
    return _loaded[module]
