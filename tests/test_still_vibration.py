"""The still detector on a car whose engine idles (``figure8-real``: gyro vibration of order 1 deg/s, above the
detector's absolute spread limits): the parked start is found and levelled on, a stop is still, a car creeping at
0.3 m/s is not; ``fuse --json`` says which alignment ran on which interval."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fieldlog.drive import reader
from fieldlog.tools.cli import main as fieldlog
from fieldlog.tools.fuse import fuse

SEEDS = (1, 2, 3)
NS = 1_000_000_000
STATIC_S = 60.0   # figure8-real's parked start
# figure8-real, then: drive off, slow to a 0.3 m/s creep for 55 s (straight: only the GPS speed tells it from a
# stop), stop 30 s with the engine idling, drive on
CREEP = """extends = "figure8-real"
name = "figure8-real-creep"
duration_s = 200.0
[[motion.segments]]
speed_mps = 10.0
distance_m = 300.0
[[motion.segments]]
speed_mps = 0.3
duration_s = 30.0
accel_mps2 = 1.5
[[motion.segments]]
duration_s = 25.0
[[motion.segments]]
speed_mps = 0.0
duration_s = 30.0
accel_mps2 = 0.2
[[motion.segments]]
speed_mps = 10.0
distance_m = 130.0
"""


@pytest.mark.parametrize("seed", SEEDS)
def test_parked_start_with_the_engine_idling_is_found(simulated, tmp_path, capsys, seed):
    drive = simulated("figure8-real", 90.0, seed)
    assert fieldlog(["fuse", str(drive), "--method", "kf", "--out", str(tmp_path / "kf.mcap"), "--json"]) == 0
    alignment = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["alignment"]
    assert alignment["method"] == "still-level+gps-course", alignment     # a MEMS gyro cannot gyrocompass
    # the whole parked minute less the detector's start (two GPS velocities) and its trimmed end; the pull-away's
    # first second moves the car by microns (a smootherstep ramp)
    assert alignment["start_s"] < 6.0 and STATIC_S - 4.0 < alignment["end_s"] <= STATIC_S + 1.0, alignment
    assert alignment["end_s"] < alignment["epoch_s"]


@pytest.mark.parametrize("seed", SEEDS)
def test_a_stop_is_still_and_a_creep_is_not(tmp_path, seed):
    scenario = tmp_path / "creep.toml"
    scenario.write_text(CREEP)
    drive = tmp_path / "creep.mcap"
    assert fieldlog(["sim", "--scenario", str(scenario), "--seed", str(seed), "--out", str(drive)]) == 0
    res = fuse(drive, "kf", tmp_path / "kf.mcap")
    vel = reader.read_topic(drive, "/truth/vel")
    t, speed = vel["stamp_ns"], np.linalg.norm(vel["v_n"], axis=1)
    still = np.array(res.still_ns)
    at_still = np.interp(still, t, speed)
    stop = (speed == 0.0) & (t > t[0] + (STATIC_S + 10.0) * NS)
    creeping = (np.abs(speed - 0.3) < 0.01) & (t < t[stop][0])
    assert creeping.sum() > 40 * 100           # 100 Hz truth: the creep is there
    creep = (t[creeping][0], t[creeping][-1])
    assert not ((still >= creep[0]) & (still <= creep[1])).any(), (still - t[0]) / NS
    # every stationary update where the car stood, or had barely begun to pull away (a smootherstep ramp: its
    # first seconds' acceleration is below what any detector can tell from the vibration)
    assert len(still) and at_still.max() < 0.1, at_still.max()
    stop_s = (t[stop][-1] - t[stop][0]) / NS
    in_stop = ((still >= t[stop][0]) & (still <= t[stop][-1])).sum()
    assert in_stop >= stop_s - 5.0, (in_stop, stop_s)    # 1 Hz epochs: all but the run's start and the braking


@pytest.mark.slow
@pytest.mark.parametrize("seed", SEEDS)
def test_first_pass_finds_the_mounting_and_the_delay(simulated, tmp_path, capsys, seed):
    """figure8-real's askew, late IMU: the pitch and yaw of its mounting and its delay within 3 of their sigmas
    of the truth in `sim.truth`, the offset's sigma below 30 ms; the same drive simulated with the IMU straight
    and prompt gives zeros within 3 sigma."""
    from fieldlog.drive import metavalue

    for options, scale in (({}, 1.0), ({"mounting_rpy_deg": (0.0, 0.0, 0.0), "imu_delay_s": 0.006}, 0.0)):
        drive = simulated("figure8-real", 300.0, seed, **options)
        truth = reader.read_metadata(drive)["sim.truth"]
        rpy = np.array(metavalue.load(truth["imu_mounting_rpy_deg"]))
        delay = metavalue.load(truth["imu_delay_s"])
        assert np.any(rpy != 0.0) == bool(scale)
        assert fieldlog(["fuse", str(drive), "--method", "kf", "--out", str(tmp_path / "kf.mcap"), "--json",
                         "--force"]) == 0
        s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        got, sigma = np.array(s["mounting_rpy_deg"]), np.array(s["mounting_sigma_deg"])
        assert np.all(np.abs(got - rpy)[1:] <= 3.0 * sigma[1:]), (got, sigma, rpy)
        assert abs(s["imu_time_offset_s"] - delay) <= 3.0 * s["imu_time_offset_sigma_s"] < 0.09, s


def test_a_gps_speed_at_twice_its_limit_is_moving_whatever_the_imu_shows():
    """``still.gps_moving`` (which spares the ZUPT its references) holds only where ``verdict`` says "moving" for
    any interval and references, still ones included."""
    from fieldlog.fusion import still
    from fieldlog.fusion.config import FusionConfig

    cfg, rng = FusionConfig(), np.random.default_rng(5)
    w = np.full((301, 3), 1e-5) + rng.normal(0.0, 1e-6, (301, 3))
    f = np.array([0.0, 0.0, 9.8]) + rng.normal(0.0, 1e-4, (301, 3))
    interval = still.ImuSums()
    interval.add(w, f, 0, 300)
    refs = [(w.mean(axis=0), 1e-4, f.mean(axis=0), 0.01)]
    for speed in [(v, limit) for v in (0.0, 0.05, 0.1, 0.19, 0.2, 0.21, 0.4, 1.0, np.nan) for limit in (0.1, 0.2)]:
        said = still.verdict(cfg, interval, speed, refs)
        assert not still.gps_moving(speed) or said == "moving"
        assert still.gps_moving(speed) or said != "moving"
