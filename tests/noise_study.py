"""The noise study of ``figure8-real``: does the ``table2-mems`` preset, run as it is, do as well in GNSS outages as
the preset with its white noise hand-tuned?

Each drive is ``figure8-real`` for ``DURATION_S`` with GNSS withheld in ``WINDOWS`` (two 30 s and two 60 s
windows after the filter has converged, each after at least a minute of good GNSS). ``kf`` runs it with the
drive's own ``[fusion]`` record plus

- ``preset``: ``imu = "table2-mems"`` and nothing else (what a user writes);
- ``adapted``: the preset with ``adapt_noise = true`` (``fusion.adaptive``);
- ``x1``, ``x3``, ``x10``: the preset with its white noise densities (``gyro_noise_dps_rthz``,
  ``accel_noise_ug_rthz``) times 1, 3 and 10 (the tuning a user would otherwise do by hand); the bias-process
  figures (random walks, priors) stay the preset's: the tuning this models is of the white noise the car's
  vibration adds, and the bias processes are the sensor's, which the vibration does not change; ``adapt_noise`` off
  (the figures as given).

The score is the 2D RMS of the position error (against ``/truth/fix``) over every solution row inside the
windows. Run as a script (``python tests/noise_study.py OUTDIR [SEED ...]``) it prints the table of
docs/results.md, "Noise from the drive"; with ``--paired`` instead of seeds, ``kf`` with its defaults and
``adapt_noise`` off and on over ``PAIRED`` and ``SEEDS`` (``paired``).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from fieldlog.fusion import imugrade
from fieldlog.tools.evaluation.evaluate import fix_quality, outage_error_series
from fieldlog.tools.fuse import fuse
from fieldlog.tools.fuse_settings import drive_table, fusion_config

SCENARIO = "figure8-real"
DURATION_S = 600.0
SEEDS = (1, 2, 3)
WINDOWS = ((120.0, 30.0), (210.0, 30.0), (300.0, 60.0), (420.0, 60.0))  # (start s from the first IMU sample, s)
FACTORS = (1.0, 3.0, 10.0)
PRESET = "table2-mems"
PAIRED = ("figure8", "urban", SCENARIO)  # the ordinary drives and the rough one, kf with and without adaptation


def variants(extra: dict | None = None) -> dict[str, dict]:
    """The [fusion] tables of the study's runs (module docstring), each with ``extra`` on top."""
    g = imugrade.grade(PRESET).filter_settings()
    out = {"preset": {"imu": PRESET}, "adapted": {"imu": PRESET, "adapt_noise": True}}
    for k in FACTORS:
        out[f"x{k:g}"] = {"imu": PRESET, "gyro_noise_dps_rthz": k * g["gyro_noise_dps_rthz"],
                          "accel_noise_ug_rthz": k * g["accel_noise_ug_rthz"], "adapt_noise": False}
    return {name: {**t, **(extra or {})} for name, t in out.items()}


def outage_rms_2d(drive: Path, table: dict, out: Path) -> float:
    """``kf`` on the drive with its [fusion] record plus ``table`` and the study's windows withheld: the 2D RMS of
    the position error (m) over the rows inside the windows."""
    cfg = fusion_config({**drive_table(drive), **table}).replace(outages=WINDOWS)
    res = fuse(drive, "kf", out, cfg, force=True, keep=True)
    _, _, t0 = fix_quality(drive, cfg.gps.max_fix_sigma_m)
    win = [(t0 + int(s * 1e9), t0 + int((s + n) * 1e9)) for s, n in WINDOWS]
    _, err = outage_error_series(drive, res.solution, "kf", win)
    return math.hypot(float(np.sqrt(np.mean(err[:, 0] ** 2))), float(np.sqrt(np.mean(err[:, 1] ** 2))))


def study(drive: Path, work: Path, extra: dict | None = None) -> dict[str, float]:
    """The 2D outage RMS (m) of each of ``variants(extra)`` on one drive."""
    return {name: outage_rms_2d(drive, table, work / f"{drive.stem}_{name}.mcap")
            for name, table in variants(extra).items()}


def paired(drive: Path, work: Path, table: dict | None = None) -> tuple[float, float]:
    """The 2D outage RMS (m) of ``kf`` on the drive with ``table`` (default: the drive's record alone), with
    ``adapt_noise`` off and on."""
    return tuple(outage_rms_2d(drive, {**(table or {}), "adapt_noise": on}, work / f"{drive.stem}_adapt{on}.mcap")
                 for on in (False, True))


def drive(scenario: str, seed: int, work: Path) -> Path:
    """The study's drive of the scenario and seed in ``work``, simulated when it is not there yet."""
    from fieldlog.tools.sim.simulate import simulate

    path = work / f"{scenario}_seed{seed}.mcap"
    if not path.exists():
        simulate(scenario, DURATION_S, seed, path)
    return path


def main(argv: list[str]) -> None:
    work = Path(argv[0])
    work.mkdir(parents=True, exist_ok=True)
    if argv[1:2] == ["--paired"]:
        print("scenario      seed  adapt off  adapt on   on/off")
        for scenario in PAIRED:
            for seed in SEEDS:
                off, on = paired(drive(scenario, seed, work), work)
                print(f"{scenario:<13} {seed:>4}  {off:9.2f}  {on:8.2f}   {on / off:.3f}", flush=True)
        return
    seeds = [int(s) for s in argv[1:]] or list(SEEDS)
    names = list(variants())
    print("seed  " + "  ".join(f"{n:>7}" for n in names) + "   preset/best adapted/best")
    for seed in seeds:
        r = study(drive(SCENARIO, seed, work), work)
        best = min(r[n] for n in names if n.startswith("x"))
        print(f"{seed:>4}  " + "  ".join(f"{r[n]:7.2f}" for n in names)
              + f"   {r['preset'] / best:.3f}  {r['adapted'] / best:.3f}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
