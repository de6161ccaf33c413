"""The installation pass's bounded-memory reductions equal their whole-drive forms to the bit: the mounting of row
blocks (``fusion.installation.mounting``) and the rate integral read back a chunk at a time (``GyroTrack``), fed in
blocks that end anywhere."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from fieldlog.fusion import earth, installation
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.smoother import SmootherLog, smooth_solution
from fieldlog.fusion.types import Solution
from fieldlog.replay.inputs import InputStream, resolve
from fieldlog.tools.fuse import BLOCK_S
from fieldlog.tools.fuse_settings import drive_config


@pytest.fixture(scope="module")
def smoothed(figure8_240s_seed3):
    """The aids-off ``kf`` rows of the figure-8 drive, smoothed (the installation pass's rows)."""
    drive = figure8_240s_seed3
    config = drive_config(drive)
    log = SmootherLog()
    engine = Engine("kf", config.replace(nhc=False, zupt=False, odometer=False, outages=()), log=log)
    sol = Solution.concat([engine.process(b.imu, b.gps)[0] for b in InputStream(drive, resolve(drive), BLOCK_S)]
                          + [engine.finish()[0]])
    out = smooth_solution(sol, log)
    log.close()
    return out


def _whole_drive_mounting(sol: Solution, lever_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mounting's formulas on every row at once (the module docstring, numpy's own gradient and unwrap)."""
    ts = (sol.t_ns - sol.t_ns[0]) * 1e-9
    course, speed = np.arctan2(sol.v_n[:, 0], sol.v_n[:, 1]), np.hypot(sol.v_n[:, 0], sol.v_n[:, 1])
    yaw_rate = np.gradient(np.unwrap(course), ts)
    rows = np.flatnonzero((speed >= installation.MIN_SPEED_MPS) & (np.abs(yaw_rate) < installation.MAX_YAW_RATE))
    heading = course[rows] + np.arctan2(yaw_rate[rows] * lever_b[1], speed[rows])
    C_bn = earth.euler_to_dcm(heading, np.arctan2(sol.v_n[rows, 2], speed[rows]), np.zeros(len(rows)))
    yaw, pitch, roll = earth.dcm_to_euler(np.einsum("nji,njk->nik", C_bn, earth.quat_to_dcm(sol.q[rows])))
    rpy = np.stack([roll, pitch, np.remainder(yaw + math.pi, 2.0 * math.pi) - math.pi], axis=1)
    block = ((ts[rows] - ts[rows][0]) // installation.BLOCK_S).astype(np.int64)
    n = np.bincount(block)
    means = np.stack([np.bincount(block, rpy[:, j])[n > 0] / n[n > 0] for j in range(3)], axis=1)
    sig = sol.sigma[rows]
    level = math.sqrt(float(np.mean(0.5 * (sig[:, 6] ** 2 + sig[:, 7] ** 2))))
    climb = math.sqrt(float(np.mean((sig[:, 5] / speed[rows]) ** 2)))
    sigma = np.sqrt((means.std(axis=0, ddof=1) / math.sqrt(len(means))) ** 2
                    + np.array([level, math.hypot(level, climb), math.sqrt(float(np.mean(sig[:, 8] ** 2)))]) ** 2
                    + np.array([math.radians(installation.ROLL_ROAD_DEG), 0.0, 0.0]) ** 2)
    return np.degrees(means.mean(axis=0)), np.degrees(sigma)


def _blocks(sol: Solution, cuts: np.ndarray) -> list[Solution]:
    fields = ("t_ns", "lat", "lon", "h", "v_n", "q", "sigma", "bias")
    edges = np.r_[0, cuts, len(sol.t_ns)]
    return [Solution(*(getattr(sol, k)[i:j] for k in fields)) for i, j in zip(edges[:-1], edges[1:])]


def test_mounting_of_row_blocks_equals_the_whole_drive_formula(smoothed):
    """Any split of the rows (single rows, empty blocks, the drive's ~10 Hz rows in 10 s blocks) gives the
    whole-drive estimate to the bit, its yaw rates across the blocks' edges and its 10 s sums included."""
    lever = np.array([0.0, 1.2, 0.0])
    want = _whole_drive_mounting(smoothed, lever)
    n = len(smoothed.t_ns)
    rng = np.random.default_rng(1)
    splits = (np.zeros(0, np.int64), np.arange(100, n, 100), np.r_[1, 2, 3, 3, np.sort(rng.integers(4, n, 40))])
    for cuts in splits:
        got = installation.mounting(_blocks(smoothed, cuts), lever)
        assert got is not None
        for g, w in zip(got, want):
            assert np.array_equal(g, w), (len(cuts), g - w)


def test_mounting_reads_no_bias_sigma(smoothed):
    """The mounting reads the rows' attitude and vertical-velocity sigmas, not the bias ones: so the installation
    pass runs without the gyro's consider analysis, which adds to the accelerometer-bias sigma alone."""
    other = dataclasses.replace(smoothed, sigma=smoothed.sigma.copy())
    other.sigma[:, 9:15] *= 7.0
    want, got = installation.mounting([smoothed], None), installation.mounting([other], None)
    assert want is not None and all(np.array_equal(g, w) for g, w in zip(got, want))


def test_mounting_needs_rows(smoothed):
    assert installation.mounting([], None) is None
    assert installation.mounting(_blocks(smoothed, np.zeros(0, np.int64))[:0], None) is None
    few = _blocks(smoothed, np.array([2]))[0]
    assert installation.mounting([few], None) is None


def test_gyro_track_read_back_in_chunks_gives_the_same_time_offset(figure8_240s_seed3):
    """The rate integral spilled and read back a few samples at a time: the same heading changes and time offset,
    to the bit, as read back at once."""
    stream = InputStream(figure8_240s_seed3, resolve(figure8_240s_seed3), BLOCK_S)
    once, chunked = installation.GyroTrack(), installation.GyroTrack()
    chunked.CHUNK = 997
    t_gps, v_gps = [], []
    for block in stream:
        for track in (once, chunked):
            track.add(block.imu.t_ns, block.imu.omega_ib_b, block.imu.f_b)
        t_gps.append(block.gps.t_ns)
        v_gps.append(block.gps.v_n)
    t_gps, v_gps = np.concatenate(t_gps), np.concatenate(v_gps)
    lo, hi = once.span_ns
    assert chunked.span_ns == (lo, hi) and len(once._kept) > 5 * chunked.CHUNK
    q = np.linspace(lo - 10**9, hi + 10**9, 20001).astype(np.int64).reshape(1, -1) + np.array([[0], [7]])
    assert np.array_equal(once.heading_change(q, q[:, ::-1]), chunked.heading_change(q, q[:, ::-1]))
    offset = installation.time_offset(once, t_gps, v_gps)
    assert offset is not None and offset == installation.time_offset(chunked, t_gps, v_gps)
    once.close()
    chunked.close()


@pytest.mark.parametrize("cuts", [[1], [5000], [1, 2, 3, 4999, 12345], [7, 17, 1707, 9999, 10000, 10001]])
def test_gyro_track_does_not_depend_on_where_the_blocks_end(cuts):
    """The samples kept, their stamps and the rate integral at them: the same to the bit whatever the blocks the
    samples come in (a jittery 500 Hz IMU; a first block of one sample included)."""
    rng = np.random.default_rng(4)
    n = 20000
    t = 10**18 + np.arange(n, dtype=np.int64) * 2_000_000 + rng.integers(-20_000, 20_000, n)
    w, f = rng.normal(0.0, 0.2, (n, 3)), rng.normal(0.0, 1.0, (n, 3))

    def kept(ends):
        track = installation.GyroTrack()
        for a, b in zip([0, *ends], [*ends, n]):
            track.add(t[a:b], w[a:b], f[a:b])
        rows = track._kept.read(0, len(track._kept))
        track.close()
        return rows

    whole, split = kept([]), kept(cuts)
    assert len(whole) == n // 10 and np.array_equal(split["t_ns"], whole["t_ns"])
    assert np.array_equal(split["angle"], whole["angle"])


def _fused(drive: str, folder, capsys, name: str, table: str = "") -> tuple[dict, np.ndarray]:
    """``fieldlog fuse DRIVE --method kf --json`` (``[fusion]`` ``table`` given as ``--config``): its summary and
    its /fusion/kf/fix rows as local ENU, m."""
    from fieldlog.drive.reader import read_topic
    from fieldlog.tools.cli import main

    args = ["fuse", drive, "--method", "kf", "--json", "-q", "--out", str(folder / f"{name}.mcap")]
    if table:
        (folder / f"{name}.toml").write_text("[fusion]\n" + table)
        args += ["--config", str(folder / f"{name}.toml")]
    assert main(args) == 0
    fix = read_topic(folder / f"{name}.mcap", "/fusion/kf/fix")
    lat = np.radians(fix["lat_deg"])
    enu = np.column_stack([(np.radians(fix["lon_deg"]) - np.radians(fix["lon_deg"][0])) * np.cos(lat) * 6.378e6,
                           (lat - lat[0]) * 6.378e6, fix["alt_m"]])
    return json.loads(capsys.readouterr().out), enu


def test_the_printed_installation_given_back_fuses_the_same_in_one_pass(figure8_240s_seed3, tmp_path, capsys):
    """The README's way to fuse a drive again: the values ``fuse --json`` printed (time offset, mounting and its
    sigma) in ``[fusion]`` with ``estimate_installation = false`` give the first run's solution to the printed
    digits, with no estimate of their own (one pass); the same setting without the values gives another."""
    from fieldlog.tools.fuse_settings import drive_table

    drive = str(figure8_240s_seed3)
    assert not drive_table(drive)  # --config replaces the drive's own settings: it has none
    first, enu = _fused(drive, tmp_path, capsys, "first")
    assert first["mounting_estimate_rpy_deg"] is not None  # the drive shows its mounting
    given = "".join(f"{k} = {first[k]!r}\n" for k in ("imu_time_offset_s", "mounting_rpy_deg", "mounting_sigma_deg"))
    again, enu_again = _fused(drive, tmp_path, capsys, "again", "estimate_installation = false\n" + given)
    _, enu_without = _fused(drive, tmp_path, capsys, "without", "estimate_installation = false\n")
    assert "mounting_estimate_rpy_deg" not in again  # no installation pass ran
    same = np.abs(enu_again - enu).max()
    other = np.abs(enu_without - enu).max()
    assert same < 1e-3 and other > 100 * same, (same, other)


def test_a_span_past_the_drive_is_the_whole_drive_and_a_shorter_one_its_first_blocks(figure8_240s_seed3, tmp_path,
                                                                                      capsys):
    """``installation_span_s``: the installation read from its own stream over the span, the fusion from the
    drive's. A span past the drive's end reads every block: the whole drive's installation and solution, to the
    bit. 120 s reads the first two 60 s blocks alone and gives another installation (the drive's first 28 s are
    still), which the whole drive's fusion then uses."""
    drive = str(figure8_240s_seed3)
    keys = ("installation_read_s", "imu_time_offset_s", "imu_time_offset_sigma_s", "mounting_rpy_deg",
            "mounting_sigma_deg", "mounting_estimate_rpy_deg", "mounting_estimate_sigma_deg")
    whole, enu = _fused(drive, tmp_path, capsys, "whole")
    past, enu_past = _fused(drive, tmp_path, capsys, "past", "installation_span_s = 1000.0\n")
    short, enu_short = _fused(drive, tmp_path, capsys, "short", "installation_span_s = 120.0\n")
    assert {k: past[k] for k in keys} == {k: whole[k] for k in keys}
    assert np.array_equal(enu_past, enu)
    assert 239.0 < whole["installation_read_s"] <= 240.0 and 119.0 < short["installation_read_s"] <= 120.0
    assert short["imu_time_offset_s"] != whole["imu_time_offset_s"]
    assert short["mounting_estimate_rpy_deg"] != whole["mounting_estimate_rpy_deg"]
    assert short["imu_samples"] == whole["imu_samples"] and short["solutions"] == whole["solutions"]
