"""fieldlog: logging and replay for in-car GPS/INS field data.

One import package. Its subpackages live in the repository's top-level folders, mapped by setuptools'
``package-dir`` (pyproject.toml): ``fieldlog.acquire`` (acquire/), ``fieldlog.fusion`` (fusion/),
``fieldlog.replay`` (replay/) and ``fieldlog.tools`` (tools/).
"""
from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("fieldlog")
except _metadata.PackageNotFoundError:  # imported from a checkout that was never installed
    __version__ = "0+unknown"
