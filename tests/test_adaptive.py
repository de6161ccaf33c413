"""Noise from the drive (``fusion.adaptive``): the still start's white densities, covariance matching of the
GNSS velocity's R and of Q's white noise, and ``fuse -v`` naming where each noise figure came from."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fieldlog.fusion import adaptive, align, kf
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.errmodel import N_STATES, VEL
from fieldlog.tools.cli import main as fieldlog

RATE_HZ = 500
SEEDS = (1, 2, 3)


def _parked(rng: np.random.Generator, seconds: int, gyro_dps: float, accel_ug: float) -> list[tuple]:
    """One-second ImuSums of white noise of the given densities about a level, still IMU."""
    out = []
    for _ in range(seconds):
        s = align.ImuSums()
        w = rng.normal(0.0, gyro_dps * math.pi / 180.0 * math.sqrt(RATE_HZ), (RATE_HZ + 1, 3))
        f = rng.normal(0.0, accel_ug * 9.80665e-6 * math.sqrt(RATE_HZ), (RATE_HZ + 1, 3)) + [0.0, 0.0, 9.8]
        s.add(w, f, 0, RATE_HZ)
        out.append((s, 1.0))
    return out


@pytest.mark.parametrize("seed", SEEDS)
def test_still_start_densities_are_the_white_noise_of_the_parked_samples(seed):
    """The Allan deviation of 60 one-second means gives the density within 4 of its standard errors (relative
    1 / sqrt(3 (n - 1)) for the three axes' differences together)."""
    rng = np.random.default_rng(seed)
    intervals = _parked(rng, 60, 0.05, 400.0)
    means_w = np.array([s.sum_w / s.n for s, _ in intervals])
    means_f = np.array([s.sum_f / s.n for s, _ in intervals])
    gyro, accel = adaptive.still_densities(means_w, means_f, 1.0)
    tol = 4.0 / math.sqrt(3 * 59)
    assert abs(gyro / 0.05 - 1.0) < tol and abs(accel / 400.0 - 1.0) < tol, (gyro, accel)


def test_the_still_start_raises_a_density_never_lowers_it():
    """Above the configured density the still start's replaces it (and Q's white entries), below it nothing
    changes; the bias random walks stay."""
    rng = np.random.default_rng(4)
    cfg = FusionConfig().replace(gyro_noise_dps_rthz=0.01, accel_noise_ug_rthz=5000.0)
    q = cfg.sensor.noise_psd()
    a = adaptive.Adaptation(q, 0.01, 5000.0)
    a.still_start(_parked(rng, 60, 0.05, 400.0))
    gyro, src = a.noise["gyro_noise_dps_rthz"]
    assert gyro > 0.04 and "still start" in src
    assert a.noise["accel_noise_ug_rthz"] == (5000.0, adaptive.CONFIGURED)
    assert math.isclose(a.q[0, 0], (gyro * math.pi / 180.0) ** 2) and np.array_equal(a.q[3:, 3:], q[3:, 3:])


def _velocity_fixes(a: adaptive.Adaptation, rng: np.random.Generator, sigma_true: float, sigma_said: float,
                    fixes: int) -> None:
    """GNSS velocity fixes through a real KalmanFilter with the adaptation around its updates: the velocity
    error state's prior 0.01 m/s, the receiver says sigma_said, its errors are sigma_true (m/s)."""
    for _ in range(fixes):
        f = kf.KalmanFilter(np.eye(N_STATES) * 1e-4, a.q)
        H = np.zeros((2, N_STATES))
        H[:, VEL.start:VEL.start + 2] = np.eye(2)
        z = rng.normal(0.0, math.hypot(sigma_true, 0.01), 2)
        obs = a.before([kf.Observation("velocity", (z, H, np.eye(2) * sigma_said ** 2), True)], f.state,
                       f.covariance)
        f.update_batch(obs)
        a.after(f.state, f.covariance)


@pytest.mark.parametrize("seed", SEEDS)
def test_velocity_variance_matched_up_and_floored_at_the_receivers(seed):
    """A receiver that says 0.05 m/s where its errors are 0.2 gets its variance scaled by about 16 (within 4
    standard errors of a window's 60 rows); one that says 0.2 where they are 0.05 keeps its own (the floor), and
    Q's white scale stays within its bounds."""
    rng = np.random.default_rng(seed)
    q = FusionConfig().sensor.noise_psd()
    high = adaptive.Adaptation(q, 0.03, 300.0)
    _velocity_fixes(high, rng, 0.2, 0.05, adaptive.WINDOW)
    want = (0.2 ** 2 + 0.01 ** 2) / 0.05 ** 2
    assert abs(high.r_scale[adaptive.KIND] / want - 1.0) < 4.0 * math.sqrt(2.0 / 60), high.r_scale
    low = adaptive.Adaptation(q, 0.03, 300.0)
    _velocity_fixes(low, rng, 0.05, 0.2, adaptive.WINDOW)
    assert low.r_scale[adaptive.KIND] == 1.0 and low.q_scale == 1.0
    for a in (high, low):
        assert 1.0 <= a.q_scale <= adaptive.MAX_Q_SCALE and a.windows == 1


def test_fuse_v_names_where_each_noise_figure_came_from(simulated, tmp_path, capsys):
    """-v: one line per noise figure with its source; the still start's estimate where it exceeds the grade's, the
    grade's bias random walks, the defaults without a config; --json carries the same."""
    drive = simulated("figure8-real", 90.0, 1)
    conf = tmp_path / "adapt.toml"
    conf.write_text('[fusion]\nimu = "table2-mems"\nadapt_noise = true\n')
    out = tmp_path / "kf.mcap"
    assert fieldlog(["fuse", "-v", str(drive), "--config", str(conf), "--out", str(out)]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("noise ")]
    by_key = {x.split()[1]: x for x in lines}
    assert set(by_key) >= {"gyro_noise_dps_rthz", "accel_noise_ug_rthz", "gyro_bias_rw_dps_rts",
                           "accel_bias_rw_ug_rts"}, lines
    assert "estimated from the still start" in by_key["gyro_noise_dps_rthz"]
    assert "grade table2-mems" in by_key["gyro_bias_rw_dps_rts"]
    assert fieldlog(["fuse", "--json", str(drive), "--out", str(out), "--force"]) == 0
    noise = json.loads(capsys.readouterr().out)["noise"]
    assert {v["source"] for k, v in noise.items()} == {"default"}, noise
    assert noise["gyro_noise_dps_rthz"]["value"] == FusionConfig().sensor.gyro_noise_dps_rthz
