"""Compiled kernels for reading many small chunks: libzstd and zlib-ng called from numba loops.

python-zstandard decompresses a batch of frames in one call, but hands the output back in pieces of 128 frames
that must be joined, and its CRC-32 check is one Python call per chunk; the joined buffer is then walked record
by record and the payloads gathered from it, long after it left the cache (in a file of 4 KiB chunks, where
every chunk holds a little of every topic, this cost more than the decompression). ``read_chunks`` calls
libzstd's ``ZSTD_decompressDCtx`` and zlib-ng's ``zng_crc32`` from one compiled loop instead: each chunk is
decompressed into a small buffer that stays in the cache, checked, its records walked, and only the records asked
for copied out, so the batch holds what will be read, packed (as in our own files, whose chunks hold few topics).

The C functions are the ones the two packages already ship: the shared objects of zstandard's cffi backend and of
zlib_ng export their C API. ``ready()`` is False without numba, or when an installed build does not export them;
the callers then take the python-zstandard path (``chunks.decompress_many``, ``chunks.messages_of``).
"""
from __future__ import annotations

import ctypes
import importlib.machinery
import os

import numpy as np

_SYMBOLS = {"zstd": ("ZSTD_createDCtx", "ZSTD_decompressDCtx", "ZSTD_isError"), "zlib_ng": ("zng_crc32",)}
NONE, ZSTD = 0, 1  # the chunk compressions read_chunks takes
OK, CODEC, SIZE, CRC = 0, 1, 2, 3  # what it finds wrong with a chunk
ERRORS = {CODEC: "chunk does not decompress (zstd)", SIZE: "chunk size mismatch", CRC: "chunk CRC mismatch"}

_state: dict[str, object] = {}


def _libraries() -> dict[str, ctypes.CDLL]:
    import zlib_ng.zlib_ng
    import zstandard

    base = os.path.join(os.path.dirname(zstandard.__file__), "_cffi")
    zstd = next(base + s for s in importlib.machinery.EXTENSION_SUFFIXES if os.path.exists(base + s))
    return {"zstd": ctypes.CDLL(zstd), "zlib_ng": ctypes.CDLL(zlib_ng.zlib_ng.__file__)}


def ready() -> bool:
    """Whether the kernels can run (numba installed, the C functions found): decided once per process, which
    then imports numba and compiles the kernels (or loads them from numba's cache)."""
    if "ok" not in _state:
        _state["ok"] = False
        try:
            import llvmlite.binding
            import numba
            from numba import types

            libs = _libraries()
            for lib, names in _SYMBOLS.items():
                for name in names:
                    llvmlite.binding.add_symbol(name, ctypes.cast(getattr(libs[lib], name), ctypes.c_void_p).value)
        except (ImportError, StopIteration, OSError, AttributeError):
            return False
        create = libs["zstd"].ZSTD_createDCtx
        create.restype = ctypes.c_void_p
        ptr = types.uintp
        g = globals()  # the kernels call these by symbol name, so their cached machine code stays valid
        g["_zstd_decompress"] = types.ExternalFunction("ZSTD_decompressDCtx", ptr(ptr, ptr, ptr, ptr, ptr))
        g["_zstd_is_error"] = types.ExternalFunction("ZSTD_isError", types.uint32(ptr))
        g["_crc32"] = types.ExternalFunction("zng_crc32", types.uint64(types.uint64, ptr, types.uint64))
        for name in ("_u64", "_read"):
            g[name] = numba.njit(cache=True)(g[name])
        _state["dctx"] = int(create())  # this process's context (the kernels hold the GIL)
        _state["ok"] = True
    return bool(_state["ok"])


def _u64(buf, at, width):
    v = np.int64(0)
    for b in range(width):
        v |= np.int64(buf[at + b]) << (8 * b)
    return v


def _read(dctx, src, comp, at, length, size, crc, stage, out, want, rec, ch, defs):
    src_at, stage_at = src.ctypes.data, stage.ctypes.data
    k = nd = o = 0
    for j in range(len(at)):
        if comp[j] == ZSTD:
            r = _zstd_decompress(dctx, stage_at, size[j], src_at + at[j], length[j])
            if _zstd_is_error(r) != 0:
                return j, CODEC, o, k, nd
            n = np.int64(r)
        else:
            n = length[j]
            if n == size[j]:
                stage[:n] = src[at[j]:at[j] + n]
        if n != size[j]:
            return j, SIZE, o, k, nd
        if crc[j] != 0 and (_crc32(0, stage_at, n) & 0xFFFFFFFF) != crc[j]:
            return j, CRC, o, k, nd
        pos = 0
        while pos + 9 <= n:  # the chunk's records, while they are in the cache
            body = _u64(stage, pos + 1, 8)
            if body < 0 or pos + 9 + body > n:
                break
            op = stage[pos]
            keep = (op == 3 or op == 4) and body >= 14  # Schema, Channel (14, 16 bytes at least): defined inside
            if op == 5 and body >= 22:  # Message: channel u16, sequence u32, log_time, publish_time
                c = _u64(stage, pos + 9, 2)
                if want[c]:
                    keep = True
                    rec[k, 0], rec[k, 1] = o, body
                    rec[k, 2], rec[k, 3] = _u64(stage, pos + 15, 8), _u64(stage, pos + 23, 8)
                    ch[k] = c
                    k += 1
            elif keep:
                defs[nd, 0], defs[nd, 1], defs[nd, 2] = op, o + 9, body
                nd += 1
            if keep:
                out[o:o + 9 + body] = stage[pos:pos + 9 + body]
                o += 9 + body
            pos += 9 + body
    return -1, OK, o, k, nd


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
    when ``ready()``."""
    n = int(size.sum())
    # rows for as many records as the bytes could hold (compiled code checks no bounds): a message record is 31
    # bytes at least, a schema or channel record kept 23
    rec, ch = np.empty((n // 31 + 1, 4), np.int64), np.empty(n // 31 + 1, np.uint16)
    defs = np.empty((n // 23 + 1, 3), np.int64)
    j, what, used, k, nd = _read(_state["dctx"], np.frombuffer(buf, np.uint8), comp, at, length, size, crc, stage,
                                 out, want, rec, ch, defs)
    return int(j), int(what), int(used), rec[:k], ch[:k], defs[:nd]
