"""figure8-real with nothing configured: `fuse` finds the IMU's mounting and delay and the wheels' scale, uses
them, and bridges GNSS outages about as well as on the same drive simulated with the IMU straight and prompt;
found from the drive's first minutes alone (``[fusion] installation_span_s``), with the wider sigmas of less
driving.

Each seed's drive (600 s, GNSS withheld 2 x 30 s and 2 x 60 s) is fused by the `fieldlog fuse` command as a
user would run it; the figures are compared with the drive's ``sim.truth`` record and ``/truth`` topics."""
from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from fieldlog.drive import metavalue, reader
from fieldlog.replay import solutions
from fieldlog.tools.cli import main as fieldlog
from fieldlog.tools.evaluation.evaluate import outage_error_series

SEEDS = (1, 2, 3)
DURATION_S = 600.0
OUTAGES = ((120.0, 30.0), (220.0, 60.0), (340.0, 30.0), (440.0, 60.0))  # s from the first IMU sample
STRAIGHT = {"mounting_rpy_deg": (0.0, 0.0, 0.0), "imu_delay_s": 0.006}  # the IMU filter's own delay is the least
SPAN_S = 180.0  # s: the first minutes the span run estimates the installation from (a minute parked, two driving)
NS = 1_000_000_000

pytestmark = pytest.mark.slow


def _fused(drive, out, config=None) -> dict:
    """`fieldlog fuse DRIVE --method kf --json` with the outages (and ``--config config``): its summary."""
    args = ["fuse", str(drive), "--method", "kf", "--out", str(out), "--json", "--force"]
    args += ["--config", str(config)] if config else []
    for start, length in OUTAGES:
        args += ["--outage", f"{start:g}:{length:g}"]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert fieldlog(args) == 0
    return json.loads(buf.getvalue().strip().splitlines()[-1])


def _outage_scores(drive, fused) -> tuple[float, int, int]:
    """(2D RMS of the rows inside the outages, m; horizontal errors (E and N apart) within 3 sigma; their
    number)."""
    t0 = int(reader.read_topic(drive, "/imu")["log_time_ns"][0])
    windows = [(t0 + int(s * NS), t0 + int((s + n) * NS)) for s, n in OUTAGES]
    t, e = outage_error_series(drive, fused, "kf", windows)
    std = solutions.read(fused, "kf", "std")
    sigma = np.stack([np.interp(t, std["log_time_ns"], std["xyz"][:, i]) for i in range(2)], axis=1)
    inside = np.abs(e[:, :2]) <= 3.0 * sigma
    return float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))), int(inside.sum()), inside.size


@pytest.fixture(scope="module")
def runs(simulated, tmp_path_factory) -> list[dict]:
    out = []
    folder = tmp_path_factory.mktemp("installation")
    span = folder / "span.toml"
    span.write_text(f"[fusion]\ninstallation_span_s = {SPAN_S}\n")
    for seed in SEEDS:
        row = {"seed": seed}
        for name, options, config in (("real", {}, None), ("straight", STRAIGHT, None), ("span", {}, span)):
            drive = simulated("figure8-real", DURATION_S, seed, **options)
            fused = folder / f"{name}{seed}.mcap"
            summary = _fused(drive, fused, config)
            truth = reader.read_metadata(drive)["sim.truth"]
            vel = reader.read_topic(drive, "/truth/vel")
            moving = np.linalg.norm(vel["v_n"], axis=1) > 0.01
            t_imu0 = int(reader.read_topic(drive, "/imu")["log_time_ns"][0])
            row[name] = dict(summary=summary, scores=_outage_scores(drive, fused),
                             rpy=np.array(metavalue.load(truth["imu_mounting_rpy_deg"])),
                             delay=float(metavalue.load(truth["imu_delay_s"])),
                             scale=1.0 + float(np.mean(metavalue.load(truth["wheel_speed_scale"]))),
                             t_move_s=(int(vel["log_time_ns"][moving][0]) - t_imu0) / NS)
        print(f"seed {seed}: outage 2D RMS {row['real']['scores'][0]:.2f} m (straight IMU "
              f"{row['straight']['scores'][0]:.2f} m), mounting {row['real']['summary']['mounting_rpy_deg']} "
              f"+- {row['real']['summary']['mounting_sigma_deg']} deg, IMU late by "
              f"{row['real']['summary']['imu_time_offset_s']:.4f} s, odometer scale "
              f"{row['real']['summary']['odometer_scale']:.5f}; from the first {SPAN_S:g} s: outage 2D RMS "
              f"{row['span']['scores'][0]:.2f} m, mounting {row['span']['summary']['mounting_rpy_deg']} +- "
              f"{row['span']['summary']['mounting_sigma_deg']} deg, IMU late by "
              f"{row['span']['summary']['imu_time_offset_s']:.4f} +- "
              f"{row['span']['summary']['imu_time_offset_sigma_s']:.4f} s")
        out.append(row)
    return out


def test_the_askew_late_imu_bridges_outages_as_well_as_a_straight_one(runs):
    for r in runs:
        assert r["real"]["scores"][0] <= 1.2 * r["straight"]["scores"][0], r


def test_mounting_offset_and_scale_are_found_within_the_target_and_their_3_sigma(runs):
    for r in runs:
        for name in ("real", "straight"):
            s, x = r[name]["summary"], r[name]
            err = np.abs(np.array(s["mounting_rpy_deg"]) - x["rpy"])[1:]  # pitch and yaw
            assert np.all(err <= 0.3) and np.all(err <= 3.0 * np.array(s["mounting_sigma_deg"])[1:]), (s, x)
            d = abs(s["imu_time_offset_s"] - x["delay"])
            assert d <= 0.010 and d <= 3.0 * s["imu_time_offset_sigma_s"], (s, x)
            k = abs(s["odometer_scale"] - x["scale"])
            assert k <= 0.002 * x["scale"] and k <= 3.0 * s["odometer_scale_sigma"], (s, x)


def test_the_parked_start_is_found(runs):
    for r in runs:
        a, t_move = r["real"]["summary"]["alignment"], r["real"]["t_move_s"]
        assert a["method"] in ("gyrocompass", "still-level+gps-course"), a
        assert a["start_s"] < 0.1 * t_move and t_move - 5.0 <= a["end_s"] <= t_move, (a, t_move)


def test_nine_tenths_of_the_outage_errors_are_within_3_sigma(runs):
    inside = sum(r["real"]["scores"][1] for r in runs)
    total = sum(r["real"]["scores"][2] for r in runs)
    assert inside >= 0.9 * total, [r["real"]["scores"] for r in runs]


def test_the_first_minutes_find_it_within_their_wider_3_sigma_and_bridge_outages_as_well(runs):
    """The installation from the first ``SPAN_S`` (a minute parked, two driving) alone: read from that span, each
    figure within 3 sigma of the truth, each sigma at least the whole drive's; the whole drive fused with it
    bridges the outages as the straight IMU does, its errors as often within 3 sigma."""
    for r in runs:
        s, w, x = r["span"]["summary"], r["real"]["summary"], r["span"]
        assert abs(s["installation_read_s"] - SPAN_S) < 0.1 and abs(w["installation_read_s"] - DURATION_S) < 0.1
        sigma = np.array(s["mounting_sigma_deg"])[1:]  # pitch and yaw
        assert np.all(np.abs(np.array(s["mounting_rpy_deg"]) - x["rpy"])[1:] <= 3.0 * sigma), (s, x)
        assert np.all(sigma >= np.array(w["mounting_sigma_deg"])[1:]), (s, w)
        assert abs(s["imu_time_offset_s"] - x["delay"]) <= 3.0 * s["imu_time_offset_sigma_s"], (s, x)
        assert s["imu_time_offset_sigma_s"] >= w["imu_time_offset_sigma_s"], (s, w)
        assert r["span"]["scores"][0] <= 1.2 * r["straight"]["scores"][0], r
    inside = sum(r["span"]["scores"][1] for r in runs)
    total = sum(r["span"]["scores"][2] for r in runs)
    assert inside >= 0.9 * total, [r["span"]["scores"] for r in runs]
