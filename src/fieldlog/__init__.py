"""fieldlog: logging and replay for in-car GPS/INS field data.

One import package. Its subpackages live in the repository's top-level folders, mapped by setuptools'
``package-dir`` (pyproject.toml): ``fieldlog.acquire`` (acquire/), ``fieldlog.fusion`` (fusion/),
``fieldlog.replay`` (replay/) and ``fieldlog.tools`` (tools/).
"""


def __getattr__(name: str) -> str:
    """``__version__``, read from the installed metadata on first use (importlib.metadata would add to every
    command's start-up)."""
    if name != "__version__":
        raise AttributeError(f"module 'fieldlog' has no attribute {name!r}")
    from importlib import metadata

    try:
        return metadata.version("fieldlog")
    except metadata.PackageNotFoundError:  # imported from a checkout that was never installed
        return "0+unknown"
