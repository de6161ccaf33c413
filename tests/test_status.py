"""The solution status, ``/fusion/<method>/status``: on a drive built to visit every value (a still start for the
alignment, GNSS, a long silence, then an IMU frame that turns wrong), each value in order, the seconds since the
last GNSS update right to the epoch; a wrong ``--imu-frame`` is told as diverged, the right one never."""

from __future__ import annotations

import numpy as np
import pytest

from fieldlog.fusion import output
from fieldlog.replay import solutions
from fieldlog.drive import reader
from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.fuse import fuse
from fieldlog.tools.fuse_settings import drive_config

from foreign_drives import Foreign, write_foreign

SILENT = (90.0, 100.0)  # the GPS silence, s from the first IMU sample
WRONG_FROM_S = 210.0  # the IMU in FRD from here, read as FLU: the frame turns wrong


def _first_appearances(code: np.ndarray) -> list[int]:
    return list(dict.fromkeys(int(c) for c in code))


@pytest.fixture(scope="module")
def built(figure8_240s_seed3, tmp_path_factory):
    """The figure8 drive (240 s: a still start, then driving) as another logger writes it: FLU IMU at 100 Hz
    with /tf_static, no GPS messages in SILENT, the IMU axes in FRD from WRONG_FROM_S on."""
    out = tmp_path_factory.mktemp("status") / "built.mcap"
    return write_foreign(figure8_240s_seed3, out, Foreign(frame="flu", imu_rate_hz=100.0, silent=(SILENT,),
                                                          frame_after=(WRONG_FROM_S, "frd"), tf_static=True))


def test_status_takes_every_value_in_order(built, tmp_path):
    """First the default threshold: no degraded row, and the horizontal sigma of the silence rises well above
    that of the aided rows before it; then a threshold between the two: aligning, aligned, aided, coasting,
    degraded, diverged appear in that order, each where the drive puts it."""
    first = fuse(built, "kf", tmp_path / "default.mcap")
    st = solutions.read(first.path, "kf", "status")
    code, sigma_h = st["status"], st["sigma_h_m"]
    assert output.DEGRADED not in code
    coasting = np.flatnonzero(code == output.COASTING)
    aided_before = sigma_h[:coasting[0]][code[:coasting[0]] == output.AIDED]
    assert sigma_h[coasting].max() > 1.5 * aided_before.max()
    threshold = float(np.sqrt(sigma_h[coasting].max() * aided_before.max()))

    cfg = drive_config(built).replace(status_max_sigma_m=threshold)
    res = fuse(built, "kf", tmp_path / "status.mcap", config=cfg)
    st = solutions.read(res.path, "kf", "status")
    t_ns, code = st["stamp_ns"], st["status"]
    assert st["valid"].all() and np.all(np.diff(t_ns) > 0)
    assert _first_appearances(code) == list(range(len(output.STATUS)))
    t0 = int(reader.read_topic(built, "/sensors/imu")["stamp_ns"][0])
    rel = (t_ns - t0) * 1e-9
    silent = (rel > SILENT[0] + 1.5) & (rel < SILENT[0] + SILENT[1])  # past the first missing epoch
    assert set(np.unique(code[silent])) <= {output.COASTING, output.DEGRADED}
    assert (code[(rel > SILENT[0] + SILENT[1] + 1.5) & (rel < WRONG_FROM_S)] == output.AIDED).all()
    assert code[-1] == output.DIVERGED and rel[np.argmax(code == output.DIVERGED)] > WRONG_FROM_S
    # a status row per solution row once aligned, before it one per output slot without a solution
    fix_t = solutions.read(res.path, "kf", "fix")["stamp_ns"]
    np.testing.assert_array_equal(t_ns[code != output.ALIGNING], fix_t)
    assert (t_ns[code == output.ALIGNING] < fix_t[0]).all()
    assert np.all(np.diff(t_ns[code == output.ALIGNING]) >= 0.9e9 / cfg.filter.output_hz)

    # the seconds since the last update: to the last usable fix before the row (none in the silence or in an
    # outage window), to the nanosecond
    fixes = reader.read_topic(built, "/sensors/gnss/fix")["stamp_ns"]
    out = np.zeros(len(fixes), bool)
    for m in reader.read_topic(res.path, solutions.OUTAGE)["msgs"]:
        out |= (fixes >= m.start_ns) & (fixes < m.end_ns)
    used = fixes[~out]
    after = code >= output.AIDED
    last = used[np.searchsorted(used, t_ns[after], side="left") - 1]
    assert np.abs(st["since_update_s"][after] - (t_ns[after] - last) * 1e-9).max() < 1e-9
    assert np.isnan(st["since_update_s"][code <= output.ALIGNED]).all()
    assert st["since_update_s"][silent].max() > SILENT[1] - 2.0


def test_wrong_imu_frame_is_diverged_and_the_right_one_never(simulated, tmp_path):
    """An RFU drive fused as FRD (the CLI's --imu-frame): diverged once it drives; as RFU: never diverged nor
    degraded, aided from the first update on; smoothed, the file carries the forward pass's status."""
    drive = simulated("figure8", 120.0, 1)
    for frame, more in (("frd", []), ("rfu", []), ("rfu", ["--smooth"])):
        assert cli_main(["fuse", str(drive), "--method", "kf", "--imu-frame", frame, "-q", *more,
                         "--out", str(tmp_path / f"{frame}{''.join(more)}.mcap")]) == 0
    wrong = solutions.read(tmp_path / "frd.mcap", "kf", "status")
    right = solutions.read(tmp_path / "rfu.mcap", "kf", "status")
    assert output.DIVERGED in wrong["status"] and wrong["nis"][wrong["status"] == output.DIVERGED].min() > 25.0
    assert _first_appearances(right["status"]) == [output.ALIGNING, output.ALIGNED, output.AIDED]
    assert np.nanmax(right["nis"]) < 3.0
    smoothed = solutions.read(tmp_path / "rfu--smooth.mcap", "kf", "status")
    for k in ("stamp_ns", "status", "since_update_s", "sigma_h_m"):
        np.testing.assert_array_equal(smoothed[k], right[k])
