"""Every method's solution on two simulated 400 s drives, as ``fieldlog fuse`` computes it, and the reference of
tests/data/engine_reference.npz that tests/test_engine_reference.py compares it with.

The reference holds, per run (drive, method, smoothing), the SHA-256 of each full solution array, every
``EVERY``-th row of it, and the run's counts (fixes used, epochs bridged, stationary updates, raised gammas);
and the SHA-256 of each simulated drive's inputs, so that a changed simulator is told apart from a changed
engine. Regenerate it (only after checking that a change of the solutions is meant) with::

    .venv/bin/python tests/engine_reference.py --write
"""
from __future__ import annotations

import hashlib
import os
import platform
import sys
from pathlib import Path

import numpy as np

from fieldlog.fusion.methods import METHODS
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.smoother import SmootherLog, smooth_solution
from fieldlog.fusion.types import Solution
from fieldlog.replay import inputs as inputs_mod
from fieldlog.drive import reader
from fieldlog.replay.inputs import InputStream
from fieldlog.tools.fuse import BLOCK_S
from fieldlog.tools.fuse_settings import drive_config

PATH = Path(__file__).resolve().parent / "data" / "engine_reference.npz"
EVERY = 100
OUTAGES = ((120.0, 30.0), (250.0, 60.0))  # s from the first IMU sample: the predictors bridge, the UKF switches
# (name, scenario, seed, {flat [fusion] keys}, runs (method, smooth)): figure8 runs every method with and without
# smoothing; urban stops at lights (stationary updates) and loses the GPS in tunnels
DRIVES = (("figure8", "figure8", 1, {"outages": OUTAGES}, [(m, s) for m in METHODS for s in (False, True)]),
          ("urban", "urban", 2, {}, [("kf", False), ("kf", True), ("dkf-rbfn", True), ("ssr-sckf", False),
                                     ("hinf", False)]))
DURATION_S = 400.0
ARRAYS = ("t_ns", "lat", "lon", "h", "v_n", "q", "sigma", "bias", "local")


def digest(a: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and bytes."""
    a = np.ascontiguousarray(a)
    return hashlib.sha256(f"{a.dtype.str}{a.shape}".encode() + a.tobytes()).hexdigest()


def platform_key() -> str:
    """What decides the last bits of the floats: the machine, numpy and the CPU features it dispatches to, and
    OpenBLAS's kernel when ``OPENBLAS_CORETYPE`` forces one other than the CPU's own (some hosts set it)."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as feats
    except ImportError:  # numpy 1.x
        from numpy.core._multiarray_umath import __cpu_features__ as feats
    key = f"{platform.machine()} numpy {np.__version__} " + ",".join(sorted(k for k, v in feats.items() if v))
    coretype = os.environ.get("OPENBLAS_CORETYPE", "").strip()
    return f"{key} openblas {coretype}" if coretype else key


def simulate(folder: Path) -> dict[str, Path]:
    """The reference drives, simulated into folder (as ``fieldlog sim`` and tests/conftest.py's ``simulated``)."""
    from fieldlog.tools.sim.simulate import simulate as sim

    out = {}
    for name, scenario, seed, _, _ in DRIVES:
        out[name] = folder / f"{name}.mcap"
        sim(scenario, DURATION_S, seed, out[name])
    return out


def input_digest(drive: Path) -> str:
    """SHA-256 over the numeric columns of the drive's /imu, /gps/fix and /gps/vel."""
    h = hashlib.sha256()
    for topic in ("/imu", "/gps/fix", "/gps/vel"):
        d = reader.read_topic(drive, topic)
        for k in sorted(d):
            a = np.asarray(d[k])
            if a.dtype.kind in "fiub":
                h.update(digest(a).encode())
    return h.hexdigest()


def run(drive: Path, method: str, smooth: bool, keys: dict) -> dict[str, np.ndarray]:
    """The solution arrays of one run (``tools.fuse.fuse``'s loop, without the file) and its counts."""
    log = SmootherLog() if smooth else None
    eng = Engine(method, drive_config(drive).replace(**keys), log=log)
    parts = []
    for b in InputStream(drive, inputs_mod.resolve(drive), BLOCK_S):
        parts.append(eng.process(b.imu, b.gps)[0])
    parts.append(eng.finish()[0])
    sol = Solution.concat(parts)
    if log is not None:
        sol = smooth_solution(sol, log)
        log.close()
    out = {k: getattr(sol, k) for k in ARRAYS if getattr(sol, k) is not None}
    out["counts"] = np.array([eng.updates, eng.predicted, len(eng.used("Stationary")),
                              getattr(eng.filter, "raised", 0)])
    return out


def runs(drives: dict[str, Path]):
    """(run label, arrays) of every run of ``DRIVES``."""
    for name, _, _, keys, todo in DRIVES:
        for method, smooth in todo:
            yield f"{name}/{method}/{'smooth' if smooth else 'forward'}", run(drives[name], method, smooth, keys)


def write(folder: Path) -> None:
    drives = simulate(folder)
    ref: dict[str, np.ndarray] = {"platform": np.array(platform_key())}
    for name, path in drives.items():
        ref[f"{name}/input"] = np.array(input_digest(path))
    for label, arrays in runs(drives):
        for k, a in arrays.items():
            ref[f"{label}/{k}"] = a[::EVERY] if k != "counts" else a
            ref[f"{label}/{k}/sha256"] = np.array(digest(a))
        print(label, arrays["counts"], flush=True)
    PATH.parent.mkdir(exist_ok=True)
    np.savez_compressed(PATH, **ref)
    print(f"wrote {PATH} ({PATH.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit(__doc__)
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        write(Path(d))
