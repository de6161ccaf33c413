"""Per-wheel slip (fusion/odometer.py, ``WheelSlip``): the four wheel speeds tested against the car's motion, a
spinning wheel skipped, the forward speed from the wheels kept; on a simulated drive with a spin event
(``[vehicle] spin_wheel``, tools/sim/vehicle.py) and against the sim's own wheel kinematics."""
from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from fieldlog.drive import reader
from fieldlog.fusion import earth
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.odometer import WHEELS, WheelSlip, body_velocity_at, hub_speeds, wheel_positions

TRACK_M, WHEELBASE_M = 1.6, 2.7


def _turning(seed: int) -> tuple[NavState, np.ndarray, np.ndarray]:
    """A car turning at a random speed and yaw rate, its rear axle centre moving straight ahead: (nav, omega_nb_b,
    r_b)."""
    rng = np.random.default_rng(seed)
    C_bn = earth.euler_to_dcm(rng.uniform(-3, 3), 0.01, -0.02)
    omega = np.array([0.0, 0.0, rng.uniform(-0.4, 0.4)])
    r_b = np.array([0.05, -1.2, -0.3])
    v_n = C_bn @ (np.array([0.0, rng.uniform(4, 25), 0.0]) - np.cross(omega, r_b))
    return NavState(0.0, 0.8, 0.2, 100.0, v_n, earth.dcm_to_quat(C_bn)), omega, r_b


def test_the_rear_wheels_differ_by_yaw_rate_times_the_track():
    """The predicted rear wheel speeds are the forward speed -+ yaw rate x half the track; the front wheels,
    steered, are faster than the rear ones on the same side."""
    for seed in range(5):
        nav, omega, r_b = _turning(seed)
        pred = hub_speeds(nav, omega, wheel_positions(r_b, TRACK_M, WHEELBASE_M))
        v = body_velocity_at(nav, omega, r_b)[1]
        np.testing.assert_allclose(pred[2:], [v - omega[2] * TRACK_M / 2, v + omega[2] * TRACK_M / 2], rtol=1e-9)
        assert np.all(pred[:2] > pred[2:])


@pytest.mark.parametrize("seed", range(4))
def test_a_spinning_wheel_is_skipped_and_the_others_give_the_speed(seed):
    """Wheel ``seed`` reads 20 % high: it alone is skipped, and the forward speed of the others is the rear axle
    centre's within the wheel noise; with all four true, none is skipped."""
    nav, omega, r_b = _turning(seed)
    slip = WheelSlip(wheel_positions(r_b, TRACK_M, WHEELBASE_M))
    rng = np.random.default_rng(10 + seed)
    sigma = 0.02
    true = hub_speeds(nav, omega, slip.r_w)
    v = body_velocity_at(nav, omega, r_b)[1]
    assert abs(slip.forward_speed(nav, omega, r_b, true + rng.normal(0, sigma, 4), sigma ** 2, 1e-4) - v) < 3 * sigma
    assert not slip.skipped.any()
    spun = true + rng.normal(0, sigma, 4)
    spun[seed] *= 1.2
    got = slip.forward_speed(nav, omega, r_b, spun, sigma ** 2, 1e-4)
    assert slip.skipped.tolist() == [int(i == seed) for i in range(4)]
    assert abs(got - v) < 3 * sigma, (got, v)


@pytest.fixture(scope="module")
def spin_drives(tmp_path_factory):
    """Seed 1's figure-eight with CAN wheel speeds, fused by kf, without and with one wheel spinning +20 % for
    3 s: (summary, fix) of each, the spinning wheel, the spin's start and length (s from the drive's start)."""
    pytest.importorskip("cantools", reason="needs cantools (the can extra)")
    from fieldlog.replay import solutions
    from fieldlog.tools.cli import main as fieldlog

    tmp = tmp_path_factory.mktemp("spin")
    wheel, start, length = "RL", 80.0, 3.0
    scenario = tmp / "spin.toml"
    scenario.write_text(f'extends = "figure8"\nname = "figure8-spin"\n[vehicle]\ncan = true\n'
                        f'spin_wheel = "{wheel}"\nspin_start_s = {start}\nspin_s = {length}\n')
    out = {}
    for name, sc in (("plain", "figure8"), ("spin", str(scenario))):
        drive = tmp / f"{name}.mcap"
        assert fieldlog(["sim", "-q", "--scenario", sc, "--duration", "120", "--seed", "1", "--can",
                         "--out", str(drive)]) == 0
        fused = tmp / f"{name}-kf.mcap"
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            assert fieldlog(["fuse", "-q", str(drive), "--method", "kf", "--out", str(fused), "--json"]) == 0
        out[name] = json.loads(buf.getvalue()), solutions.read(fused, "kf", "fix"), drive
    return out, wheel, start, length


@pytest.mark.slow
def test_the_spin_is_found_and_the_fused_track_barely_moves(spin_drives):
    """The spinning wheel is skipped at every GPS epoch inside the spin (at most one more: the speed fit's window
    reaches back across its start or end), the other wheels nowhere, and no wheel on the plain drive; the fused
    positions with the spin stay within a tenth of their own horizontal sigma of those without."""
    out, wheel, start, length = spin_drives
    (plain, fix0, _), (spin, fix1, drive) = out["plain"], out["spin"]
    fixes = reader.read_topic(drive, "/gps/fix")["log_time_ns"]
    t0 = reader.read_topic(drive, "/imu")["log_time_ns"][0]
    t_s = (fixes - t0) * 1e-9
    inside = int(np.sum((t_s >= start) & (t_s < start + length)))
    skipped = spin["odometer_wheels_skipped"]
    assert inside >= 2
    assert inside <= skipped[wheel] <= inside + 1, (skipped, inside)
    assert all(n == 0 for w, n in skipped.items() if w != wheel), skipped
    assert not any(plain["odometer_wheels_skipped"].values()), plain["odometer_wheels_skipped"]
    assert set(skipped) == set(WHEELS) and spin["odometer_wheel_epochs"] > 0.5 * len(fixes)
    lat = np.radians(fix0["lat_deg"])
    d_n = np.radians(fix1["lat_deg"] - fix0["lat_deg"]) * earth.A
    d_e = np.radians(fix1["lon_deg"] - fix0["lon_deg"]) * earth.A * np.cos(lat)
    sigma_h = np.sqrt(fix1["position_covariance"][:, 0] + fix1["position_covariance"][:, 4])
    assert np.max(np.hypot(d_n, d_e) / sigma_h) < 0.1
