"""fusion's compiled kernels (fusion/_ins.c, fusion/_cycles.c), loaded once per process through ctypes.

They are built with the package (setup.py: plain C, no Python headers). fusion imports nothing of the rest of
fieldlog, so it has this loader of its own beside ``fieldlog.drive.native``.
"""

from __future__ import annotations

import ctypes
import importlib.util

_loaded: dict[str, ctypes.CDLL] = {}
_NO_BYTES = ctypes.c_char * 0


def load(module: str, signatures: dict[str, list | tuple[list, type]]) -> ctypes.CDLL:
    """The kernel ``module`` (e.g. "fieldlog.fusion._ins") with its functions' argtypes set from ``signatures``
    (name: argtypes, for a function that returns nothing; or name: (argtypes, restype)). Raises ImportError,
    naming the module, when it is not built.

    Parameters
    ----------
    module : str
        The kernel's module name.
    signatures : dict
        Each function's argtypes, or (argtypes, restype).

    Returns
    -------
    ctypes.CDLL
        The loaded library, once per process.
    """
    if module not in _loaded:
        spec = importlib.util.find_spec(module)
        if spec is None or spec.origin is None:
            raise ImportError(f"fieldlog's compiled kernel {module} is not built: reinstall fieldlog "
                              "(pip install -e . builds it; needs a C compiler)", name=module)
        lib = ctypes.CDLL(spec.origin)
        for name, sig in signatures.items():
            fn = getattr(lib, name)
            fn.argtypes, fn.restype = sig if isinstance(sig, tuple) else (sig, None)
        _loaded[module] = lib
    return _loaded[module]


def address(a) -> ctypes.Array | int:
    """Where a kernel's ``c_void_p`` argument finds the array ``a``'s data: a ctypes view of its buffer (which keeps
    ``a`` alive through the call), or for an array that gives no writable contiguous buffer its data address.
    Cheaper than numpy's ``a.ctypes``, which builds Python objects per call: a few calls per filter cycle add up.

    Parameters
    ----------
    a : numpy.ndarray
        The array, C-contiguous as the kernel reads it.

    Returns
    -------
    ctypes.Array or int
    """
    try:
        return _NO_BYTES.from_buffer(a)
    except (TypeError, ValueError, BufferError):
        return a.ctypes.data
