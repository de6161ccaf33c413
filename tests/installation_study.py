"""The rows of docs/results.md's "Mounting and time offset applied" table: ``python tests/installation_study.py
OUTDIR``. Each seed's figure8-real drive and its straight-IMU twin are simulated into OUTDIR (kept for a re-run),
fused by `fieldlog fuse` as tests/test_installation_applied.py does, and scored the same way."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import test_installation_applied as study  # noqa: E402  (the test's runs and scores)

from fieldlog.drive import metavalue, reader  # noqa: E402
from fieldlog.tools.sim.simulate import simulate  # noqa: E402


def row(seed: int, work: Path) -> str:
    """One seed's table row: outage 2D RMS askew / straight (m), their ratio, rows within 3 sigma, the pitch and yaw
    found (deg), the IMU's delay (s), the wheels' scale against the four wheels' true mean, the still start."""
    got = {}
    for name, options in (("real", {}), ("straight", study.STRAIGHT)):
        drive = work / f"{name}{seed}.mcap"
        if not drive.exists():
            simulate("figure8-real", study.DURATION_S, seed, drive, **options)
        fused = work / f"{name}{seed}_kf.mcap"
        got[name] = (study._fused(drive, fused), *study._outage_scores(drive, fused), drive)
    s, rms, within, n, drive = got["real"]
    _, rms_s, within_s, n_s, _ = got["straight"]
    truth = metavalue.load(reader.read_metadata(drive)["sim.truth"]["wheel_speed_scale"])
    m, ms = s["mounting_rpy_deg"], s["mounting_sigma_deg"]
    a = s["alignment"]
    return (f"| {seed} | {rms:.2f} / {rms_s:.2f} | {rms / rms_s:.2f} | {within / n:.3f} / {within_s / n_s:.3f} | "
            f"{m[1]:.3f} ± {ms[1]:.3f}, {m[2]:.3f} ± {ms[2]:.3f} | {s['imu_time_offset_s']:.4f} ± "
            f"{s['imu_time_offset_sigma_s']:.4f} | {s['odometer_scale']:.5f} ± {s['odometer_scale_sigma']:.5f} "
            f"({1.0 + sum(truth) / len(truth):.5f}) | {a['start_s']:.1f}–{a['end_s']:.1f} s |")


if __name__ == "__main__":
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    for seed in study.SEEDS:
        print(row(seed, out), flush=True)
