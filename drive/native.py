"""Compiled kernels for reading many small chunks: libzstd and zlib-ng called from one C loop.

python-zstandard decompresses a batch of frames in one call, but hands the output back in pieces of 128 frames
that must be joined, and its CRC-32 check is one Python call per chunk; the joined buffer is then walked record
by record and the payloads gathered from it, long after it left the cache (in a file of 4 KiB chunks, where
every chunk holds a little of every topic, this cost more than the decompression). ``read_chunks`` calls
libzstd's ``ZSTD_decompressDCtx`` and zlib-ng's ``zng_crc32`` from one compiled loop instead (drive/_chunks.c):
each chunk is decompressed into a small buffer that stays in the cache, checked, its records walked, and only
the records asked for copied out, so the batch holds what will be read, packed (as in our own files, whose
chunks hold few topics).

The C functions are the ones the two packages already ship: the shared objects of zstandard's cffi backend and of
zlib_ng export their C API, and their addresses are passed to the kernel. ``ready()`` is False when an installed
build does not export them; the callers then take the python-zstandard path (``chunks.decompress_many``,
``chunks.messages_of``). ``library`` loads the package's compiled kernels (setup.py), which need no Python
headers and are called through ctypes.
"""
from __future__ import annotations

import ctypes
import importlib.machinery
import importlib.util
import os
import threading

import numpy as np

_SYMBOLS = {"zstd": ("ZSTD_createDCtx", "ZSTD_decompressDCtx", "ZSTD_isError"), "zlib_ng": ("zng_crc32",)}
NONE, ZSTD = 0, 1  # the chunk compressions read_chunks takes
OK, CODEC, SIZE, CRC = 0, 1, 2, 3  # what it finds wrong with a chunk
ERRORS = {CODEC: "chunk does not decompress (zstd)", SIZE: "chunk size mismatch", CRC: "chunk CRC mismatch"}

_state: dict[str, object] = {}
_thread = threading.local()  # each thread's zstd context: a ctypes call releases the GIL, so threads run at once


_libs: dict[str, ctypes.CDLL] = {}
P, I64 = ctypes.c_void_p, ctypes.c_int64  # a pointer (an array's ``ctypes.data``), an int64_t
CHUNKS = {"fieldlog_walk": (I64, [P, I64, I64, I64, P, P, P, P]),  # drive/_chunks.c: name -> (restype, argtypes)
          "fieldlog_read_chunks": (None, [P] * 6 + [I64] + [P] * 11),
          "fieldlog_prefix": (None, [I64, I64, P, P, P, P])}


def library(module: str, signatures: dict[str, tuple[object, list]]) -> ctypes.CDLL:
    """The compiled kernels of extension ``module`` (``fieldlog.drive._chunks``, ...), loaded once per process,
    with the C ``signatures`` of its functions (name -> (restype, argtypes)) set. ImportError, naming the fix,
    when the package was installed without them.

    Parameters
    ----------
    module : the extension's module name
    signatures : C function name -> (restype, argtypes)

    Returns
    -------
    ctypes.CDLL : the library
    """
    if module not in _libs:
        spec = importlib.util.find_spec(module)
        if spec is None or spec.origin is None:
            raise ImportError(f"fieldlog's compiled kernels ({module}) are not built: reinstall fieldlog "
                              "(pip install -e . builds them; needs a C compiler)", name=module)
        lib = ctypes.CDLL(spec.origin)
        for name, (restype, argtypes) in signatures.items():
            getattr(lib, name).restype, getattr(lib, name).argtypes = restype, argtypes
        _libs[module] = lib
    return _libs[module]


def _shipped() -> dict[str, ctypes.CDLL]:
    import zlib_ng.zlib_ng
    import zstandard

    base = os.path.join(os.path.dirname(zstandard.__file__), "_cffi")
    zstd = next(base + s for s in importlib.machinery.EXTENSION_SUFFIXES if os.path.exists(base + s))
    return {"zstd": ctypes.CDLL(zstd), "zlib_ng": ctypes.CDLL(zlib_ng.zlib_ng.__file__)}


def ready() -> bool:
    """Whether ``read_chunks`` can run (the C functions of zstandard and zlib_ng found): decided once per
    process.

    Returns
    -------
    bool
    """
    if "ok" not in _state:
        _state["ok"] = False
        try:
            libs = _shipped()
            fns = [ctypes.cast(getattr(libs[lib], name), ctypes.c_void_p).value
                   for lib, names in _SYMBOLS.items() for name in names]
        except (ImportError, StopIteration, OSError, AttributeError):
            return False
        create = libs["zstd"].ZSTD_createDCtx
        create.restype = ctypes.c_void_p
        _state["fns"] = (fns[1], fns[2], fns[3])  # ZSTD_decompressDCtx, ZSTD_isError, zng_crc32
        _state["create_dctx"] = create
        _state["ok"] = True
    return bool(_state["ok"])


def read_chunks(buf, comp: np.ndarray, at: np.ndarray, length: np.ndarray, size: np.ndarray, crc: np.ndarray,
                stage: np.ndarray, out: np.ndarray, want: np.ndarray
                ) -> tuple[int, int, int, np.ndarray, np.ndarray, np.ndarray]:
    """Chunks ``j`` (``comp[j]``: ``NONE`` or ``ZSTD``; the ``length[j]`` bytes at ``at[j]`` of ``buf``,
    ``size[j]`` bytes with CRC-32 ``crc[j]`` (0: none) once uncompressed), one after the other: decompressed into
    ``stage`` (a uint8 array of at least ``size.max()`` bytes, reused for every chunk so it stays in the cache),
    checked, its records walked, and the messages on the channels marked in ``want`` (bool per channel id, 65536
    long), with the schema and channel records, copied out into ``out`` (at least ``size.sum()`` bytes). Returns
    (-1, ``OK``, the bytes of ``out`` used, the messages as rows (record start in ``out``, body length, log_time,
    publish_time), their channel ids (uint16), the schema and channel records as rows (opcode, body start in
    ``out``, body length)), or the first bad chunk and what is wrong with it (``CODEC``, ``SIZE``, ``CRC``). Only
    when ``ready()``.

    Parameters
    ----------
    buf : the file's bytes (mmap or array)
    comp : (k,) codec per chunk
    at, length : (k,) file offset and length of each chunk's compressed records, bytes
    size, crc : (k,) uncompressed size, bytes, and CRC-32 of each
    stage : uint8 scratch of at least ``size.max()`` bytes
    out : uint8 output of at least ``size.sum()`` bytes
    want : (65536,) bool per channel id

    Returns
    -------
    tuple : as said above
    """
    n = int(size.sum())
    # rows for as many records as the bytes could hold: a message record is 31 bytes at least, a schema or
    # channel record kept 23
    rec, ch = np.empty((n // 31 + 1, 4), np.int64), np.empty(n // 31 + 1, np.uint16)
    defs = np.empty((n // 23 + 1, 3), np.int64)
    src = np.frombuffer(buf, np.uint8)
    arrays = [np.ascontiguousarray(a, np.int64) for a in (at, length, size, crc)]
    comp, want = np.ascontiguousarray(comp, np.uint8), np.ascontiguousarray(want, np.uint8)
    first, last = arrays[0], arrays[0] + arrays[1]
    if (len(want) != 1 << 16 or stage.nbytes < int(size.max(initial=0)) or out.nbytes < n
            or len(first) and (first.min() < 0 or last.max() > len(src) or arrays[1].min() < 0)):
        raise ValueError("read_chunks: chunks outside the buffer, or want, stage or out of the wrong size")
    if getattr(_thread, "dctx", None) is None:
        _thread.dctx = _state["create_dctx"]()
    res = np.zeros(5, np.int64)
    library("fieldlog.drive._chunks", CHUNKS).fieldlog_read_chunks(
        *_state["fns"], _thread.dctx, src.ctypes.data, len(comp), comp.ctypes.data,
        *(a.ctypes.data for a in arrays), stage.ctypes.data, out.ctypes.data, want.ctypes.data, rec.ctypes.data,
        ch.ctypes.data, defs.ctypes.data, res.ctypes.data)
    j, what, used, k, nd = res.tolist()
    return j, what, used, rec[:k], ch[:k], defs[:nd]
