"""The per-wheel slip study: one wheel spinning in a GNSS outage, found and left out?

Each drive is ``figure8`` with the CAN bus for ``DURATION_S``, once as it is and once with one wheel (seed 1: FR,
2: RL, 3: RR, 4: FL) reading ``1 + SPIN_RATIO`` times its speed for ``SPIN_S`` from ``SPIN_START_S``
(``[vehicle] spin_wheel``, tools/sim/vehicle.py); ``kf`` runs both with GNSS withheld in ``OUTAGE`` (which holds
the spin, so the wheels are the car's only speed then). Printed per seed: the GNSS epochs inside the spin, the
epochs the spinning wheel and the other wheels were skipped at (``fusion.odometer.WheelSlip``), and the 2D RMS
of the position error (against ``/truth/fix``) over the rows inside the outage, without and with the spin.
Run as a script: ``python tests/wheel_slip_study.py OUTDIR [SEED ...]`` (docs/results.md, "Per-wheel slip").
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from fieldlog.drive import reader
from fieldlog.fusion.odometer import WHEELS
from fieldlog.tools.evaluation.evaluate import fix_quality, outage_error_series
from fieldlog.tools.fuse import fuse
from fieldlog.tools.fuse_settings import drive_table, fusion_config

DURATION_S = 150.0
SEEDS = (1, 2, 3)
SPIN_START_S, SPIN_S, SPIN_RATIO = 90.0, 3.0, 0.2
OUTAGE = (80.0, 30.0)  # start s from the first IMU sample, s


def drives(seed: int, work: Path) -> tuple[Path, Path, str]:
    """The plain and the spinning drive of ``seed`` in ``work`` (simulated when not there yet), and the wheel."""
    from fieldlog.tools.sim.simulate import simulate

    wheel = WHEELS[seed % len(WHEELS)]
    scenario = work / f"spin-{wheel}.toml"
    scenario.write_text(f'extends = "figure8"\nname = "figure8-spin"\n[vehicle]\ncan = true\nspin_wheel = "{wheel}"\n'
                        f"spin_start_s = {SPIN_START_S}\nspin_s = {SPIN_S}\nspin_ratio = {SPIN_RATIO}\n")
    out = []
    for name, sc in (("plain", "figure8"), (f"spin{wheel}", str(scenario))):
        path = work / f"{name}_seed{seed}.mcap"
        if not path.exists():
            simulate(sc, DURATION_S, seed, path, can=True)
        out.append(path)
    return out[0], out[1], wheel


def run(drive: Path, out: Path) -> tuple[float, dict[str, int], np.ndarray]:
    """``kf`` with ``OUTAGE`` withheld: the 2D RMS (m) inside it, the epochs each wheel was skipped at, and the
    GNSS epochs' times (s from the first IMU sample)."""
    cfg = fusion_config(drive_table(drive)).replace(outages=(OUTAGE,))
    res = fuse(drive, "kf", out, cfg, force=True, keep=True)
    _, _, t0 = fix_quality(drive, cfg.gps.max_fix_sigma_m)
    s, n = OUTAGE
    _, err = outage_error_series(drive, res.solution, "kf", [(t0 + int(s * 1e9), t0 + int((s + n) * 1e9))])
    rms = math.hypot(float(np.sqrt(np.mean(err[:, 0] ** 2))), float(np.sqrt(np.mean(err[:, 1] ** 2))))
    fixes = (reader.read_topic(drive, "/gps/fix")["log_time_ns"] - t0) * 1e-9
    return rms, res.odometer["wheels_skipped"], fixes


def main(argv: list[str]) -> None:
    work = Path(argv[0])
    work.mkdir(parents=True, exist_ok=True)
    print("seed  wheel  epochs in spin  skipped  others skipped  plain RMS  spin RMS")
    for seed in [int(s) for s in argv[1:]] or list(SEEDS):
        plain, spin, wheel = drives(seed, work)
        rms0, _, _ = run(plain, work / f"plain_seed{seed}_kf.mcap")
        rms1, skipped, fixes = run(spin, work / f"spin_seed{seed}_kf.mcap")
        inside = int(np.sum((fixes >= SPIN_START_S) & (fixes < SPIN_START_S + SPIN_S)))
        others = sum(n for w, n in skipped.items() if w != wheel)
        print(f"{seed:>4}  {wheel:>5}  {inside:>14}  {skipped[wheel]:>7}  {others:>14}  {rms0:9.2f}  {rms1:8.2f}",
              flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
