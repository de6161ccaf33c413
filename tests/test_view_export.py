"""`fieldlog view` (.rrd checked with the rerun command line) and `fieldlog export` (Parquet round trip)."""

import os
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import rerun.blueprint as rrb
from mcap.reader import make_reader

from fieldlog.drive import messages
from fieldlog.drive import reader
from fieldlog.replay import view as rview
from fieldlog.replay.export import drive_frames
from fieldlog.drive.reader import read_topic
from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.sim.simulate import simulate
from fieldlog.tools.sim.trajectory import SCENARIO_DIR

os.environ["CI"] = "1"  # rerun analytics off
RERUN = Path(sys.executable).parent / "rerun"
NO_FIX = (90.0, 8.0)  # receiver outage in the scenario: /gps/fix epochs without a fix


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    d = tmp_path_factory.mktemp("view")
    text = (SCENARIO_DIR / "figure8.toml").read_text()
    text, n = re.subn(r"(?m)^outages = \[\]", f"outages = [[{NO_FIX[0]}, {NO_FIX[1]}]]", text)
    assert n == 1
    scenario = d / "figure8_nofix.toml"
    scenario.write_text(text)
    sim = d / "sim.mcap"
    simulate(str(scenario), 120.0, 2, sim)
    kf = d / "kf.mcap"
    assert cli_main(["fuse", str(sim), "--method", "kf", "--outage", "60:15", "--out", str(kf)]) == 0
    return sim, kf


def _rerun(*args: str) -> str:
    res = subprocess.run([str(RERUN), "rrd", *args], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "CI": "1"})
    assert res.returncode == 0, res.stderr
    return res.stdout + res.stderr


def _rows(printed: str) -> Counter:
    """Rows per (entity, component) summed over the chunks that `rerun rrd print` lists."""
    out: Counter = Counter()
    for m in re.finditer(r"with (\d+) rows .* - (/\S+) - data columns: \[([^\]]*)\]", printed):
        for comp in m.group(3).split():
            out[m.group(2), comp] += int(m.group(1))
    return out


def test_view_rrd_has_every_entity_with_the_expected_rows(drives, tmp_path):
    sim, kf = drives
    rrd = tmp_path / "out.rrd"
    assert cli_main(["view", str(sim), str(kf), "--rrd", str(rrd)]) == 0
    print(f"{rrd.stat().st_size / 1e6:.2f} MB")
    assert "1 file verified without error" in _rerun("verify", str(rrd))
    rows = _rows(_rerun("print", str(rrd)))

    fix = read_topic(sim, "/gps/fix")
    has_fix = (fix["status"] >= 0) & np.isfinite(fix["lat_deg"])
    n_fix, n_no_fix = int(has_fix.sum()), int((~has_fix).sum())
    assert n_no_fix >= NO_FIX[1] - 1  # the scenario's outage is there
    imu = read_topic(sim, "/imu")
    n_imu = int(imu["valid"].sum()) // rview.IMU_DECIMATION
    n_kf = len(read_topic(kf, "/fusion/kf/fix")["log_time_ns"])
    n_truth = -(-len(read_topic(sim, "/truth/fix")["log_time_ns"]) // rview.TRUTH_DECIMATION)
    n_sync = len(read_topic(sim, "/time/sync")["log_time_ns"])
    n_att = int(read_topic(kf, "/fusion/kf/attitude")["valid"].sum())
    n_status = len(read_topic(kf, "/fusion/kf/status")["log_time_ns"])
    assert n_status > n_kf  # the rows before the alignment too
    assert n_att == n_kf
    n_gga = sum(1 for m in read_topic(sim, "/gps/nmea")["msgs"] if m.sentence[3:7] == "GGA,")
    assert n_gga >= n_fix + n_no_fix - 1  # one GGA per epoch, no-fix epochs too
    reasons = sorted(m.reason for m in read_topic(kf, "/fusion/outage")["msgs"])
    assert reasons == ["injected", "no_fix"]  # the forced outage and the receiver's (disjoint windows)

    expected = {
        ("/map/gps", "GeoPoints:positions"): n_fix,
        ("/enu/gps", "LineStrips3D:strips"): n_fix,
        ("/map/no_fix", "GeoPoints:positions"): n_no_fix,
        ("/status/no_fix", "Scalars:scalars"): n_fix + n_no_fix,
        ("/map/truth", "GeoPoints:positions"): n_truth,
        ("/enu/truth", "LineStrips3D:strips"): n_truth,
        ("/map/fusion/kf", "GeoPoints:positions"): n_kf,
        ("/enu/fusion/kf", "LineStrips3D:strips"): n_kf,
        ("/errors/pos/east/kf", "Scalars:scalars"): n_kf,
        ("/errors/vel/up/kf", "Scalars:scalars"): n_kf,
        ("/bias/gyro/kf", "Scalars:scalars"): n_kf,
        ("/bias/accel/kf", "Scalars:scalars"): n_kf,
        ("/bias/gyro/truth", "Scalars:scalars"): n_truth,
        ("/solution_status/kf", "Scalars:scalars"): n_status,
        ("/status/outage", "Scalars:scalars"): 1 + 2 * 2,  # drive start, then each window's start and end
        ("/map/outage", "GeoLineStrings:line_strings"): 1,  # one static row holding both windows' strips
        ("/map/gps/track", "GeoLineStrings:line_strings"): 1,
        ("/imu/gyro", "Scalars:scalars"): n_imu,
        ("/imu/accel", "Scalars:scalars"): n_imu,
        ("/timesync/state", "Scalars:scalars"): n_sync,
        ("/timesync/rate_ppm", "Scalars:scalars"): n_sync,
        ("/timesync/residual_us", "Scalars:scalars"): n_sync,
        # the vehicle: pose in base_link, attitude with sigma, attitude errors, GPS quality
        ("/enu/fusion/kf/base_link", "Transform3D:translation"): n_att,
        ("/enu/fusion/kf/base_link", "Transform3D:quaternion"): n_att,
        ("/enu/fusion/kf/base_link", "Boxes3D:half_sizes"): 1,
        ("/enu/truth/base_link", "Transform3D:translation"): n_truth,
        ("/attitude/roll/kf", "Scalars:scalars"): n_att,
        ("/attitude/heading/kf", "Scalars:scalars"): n_att,
        ("/attitude/pitch/truth", "Scalars:scalars"): n_truth,
        ("/errors/att/roll/kf", "Scalars:scalars"): n_att,
        ("/errors/att/heading/kf", "Scalars:scalars"): n_att,
        ("/gps/satellites", "Scalars:scalars"): n_gga,
        ("/gps/hdop", "Scalars:scalars"): n_gga,
        ("/gps/fix_type", "Scalars:scalars"): n_gga,
    }
    got = {k: rows.get(k, 0) for k in expected}
    assert got == expected
    assert n_imu == 60000 // rview.IMU_DECIMATION
    assert rows["/viewport", "ViewportBlueprint:root_container"] == 1  # the default blueprint is in the file
    # ... with the screenshot's panels: collapsed, the time cursor following the newest data
    for entity, comp in (("/time_panel", "TimePanelBlueprint:play_state"), ("/blueprint_panel", "PanelBlueprint:state"),
                         ("/selection_panel", "PanelBlueprint:state")):
        assert rows[entity, comp] == 1, entity
    stats = _rerun("stats", str(rrd))
    assert "gps_time" in stats


def _containers(c) -> list:
    """Every container under ``c`` (a blueprint container), depth first."""
    return [c] + [x for v in c.contents if hasattr(v, "contents") for x in _containers(v)]


def test_blueprint_shows_error_axes_and_attitude_side_by_side():
    bp = rview.blueprint(follow="fusion/kf")
    kinds = {}
    for c in _containers(bp.root_container):
        for v in c.contents:
            if hasattr(v, "origin"):
                kinds[str(v.origin)] = c.kind
    horizontal = rrb.Horizontal().kind
    for group in ("errors/pos", "attitude", "errors/att"):
        axes = rview.ANGLES if "att" in group else rview.AXES
        assert {kinds[f"{group}/{a}"] for a in axes} == {horizontal}, group  # not tabs
    row = {kinds[o] for o in ("status", "solution_status", "gps/satellites", "gps/hdop", "gps/fix_type",
                              "timesync/state")}
    assert row == {horizontal}  # GPS quality and the sync state on one row
    views = [v for c in _containers(bp.root_container) for v in c.contents if hasattr(v, "origin")]
    assert sum(isinstance(v, rrb.Spatial3DView) for v in views) == 2  # the trajectory and the close-up


def test_the_viewer_logs_without_importing_pandas(tmp_path):
    """rerun-sdk hands pyarrow Python lists, and pyarrow's first look at a list imports pandas when it is
    installed; the viewer answers that look. A fresh process that writes a recording with the blueprint and
    logged lists never imports pandas, and pyarrow's own pandas conversions still work after it."""
    pytest.importorskip("pandas")
    code = """if True:
        import sys
        import rerun as rr
        from fieldlog.replay import view
        rec = rr.RecordingStream("fieldlog")
        rec.save(sys.argv[1], default_blueprint=view.blueprint(follow="truth"))
        rec.log("x", rr.SeriesLines(names=["a"], colors=[(1, 2, 3)]), static=True)
        rec.flush()
        rec.disconnect()
        assert "pandas" not in sys.modules
        import pandas as pd
        import pyarrow as pa
        assert pa.Table.from_pandas(pd.DataFrame({"a": [1, 2]})).to_pandas()["a"].tolist() == [1, 2]
    """
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "x.rrd")], check=True)
    assert (tmp_path / "x.rrd").stat().st_size > 0


def test_attitude_and_pose_against_truth(drives):
    """The fused vehicle's roll, pitch and heading against the simulator's, within 3 sigma of the filter; the
    base_link pose through the drive's /tf_static mounting."""
    sim, kf = drives
    truth = rview.truth_track(read_topic(sim, "/truth/fix"), None)
    origin = (float(truth.lat_deg[0]), float(truth.lon_deg[0]), float(truth.alt_m[0]))
    mount = rview.mounting(sim)
    tf = read_topic(sim, "/tf_static")["msgs"][0].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("base_link", "imu")
    att = read_topic(sim, "/truth/attitude")
    q = rview._interp(truth.t_ns, att["log_time_ns"], att["q_xyzw"])
    ok = np.isfinite(q).all(axis=1)
    truth_pose = rview.base_pose(truth.take(ok), q[ok], mount, origin)
    fused = rview._fused(rview._read_fused(kf, "kf", wheels=False))
    pose = rview.base_pose(fused, read_topic(kf, "/fusion/kf/attitude")["q_xyzw"], mount, origin)
    np.testing.assert_allclose(np.linalg.det(pose.C_base_n), 1.0, atol=1e-9)
    err = pose.euler_deg() - rview._interp(pose.t_ns, truth_pose.t_ns, truth_pose.euler_deg(unwrap=True))
    err[:, 2] = rview.wrap_deg(err[:, 2])
    sigma = rview.attitude_sigma_deg(read_topic(kf, "/fusion/kf/attitude_std")["xyz"], pose.euler_deg()[:, 2])
    assert np.all(sigma > 0) and np.all(sigma[:, 2] > sigma[:, :2].min())  # heading the least observable
    inside = np.abs(err) < 3 * sigma
    assert inside.mean(axis=0).min() > 0.9, inside.mean(axis=0)
    # base_link is the IMU's point less the lever arm turned into ENU: base_link's forward axis is the heading
    fwd = pose.C_base_n[:, :, 0]
    heading = np.degrees(np.arctan2(fwd[:, 0], fwd[:, 1]))
    np.testing.assert_allclose(rview.wrap_deg(heading - pose.euler_deg()[:, 2]), 0.0, atol=1e-6)
    lever = np.array([1.2, -0.4, 0.9])  # an IMU off base_link: the same attitude, base_link |lever| away
    moved = rview.base_pose(fused, read_topic(kf, "/fusion/kf/attitude")["q_xyzw"], (lever, mount[1]), origin)
    np.testing.assert_allclose(np.linalg.norm(moved.p_n - pose.p_n, axis=1), np.linalg.norm(lever), rtol=1e-9)
    np.testing.assert_allclose(moved.euler_deg(), pose.euler_deg())
    np.testing.assert_allclose(rview.wrap_deg(np.array([179.0 + 2.0, -181.0, 360.0])), [-179.0, 179.0, 0.0])


def test_errors_against_truth(drives):
    sim, kf = drives
    truth = rview.truth_track(read_topic(sim, "/truth/fix"), read_topic(sim, "/truth/vel"))
    origin = (float(truth.lat_deg[0]), float(truth.lon_deg[0]), float(truth.alt_m[0]))
    self_err = rview.errors(truth, truth, True, origin)  # the truth against itself: zero
    assert np.abs(self_err.pos).max() < 1e-6 and np.abs(self_err.vel).max() < 1e-9
    e = rview.errors(rview._fused(rview._read_fused(kf, "kf", wheels=False)), truth, True, origin)
    t0 = int(read_topic(sim, "/imu")["log_time_ns"][0])
    with_gps = (e.t_ns > t0 + 50e9) & (e.t_ns < t0 + 60e9)  # the filter aligns at ~46 s
    in_outage = (e.t_ns > t0 + 65e9) & (e.t_ns < t0 + 75e9)
    h = np.hypot(e.pos[:, 0], e.pos[:, 1])
    assert h[with_gps].max() < 5.0
    assert (e.sigma_pos[in_outage, 0].mean() > e.sigma_pos[with_gps, 0].mean())  # sigma grows in the outage
    assert np.all(e.sigma_pos > 0)


def test_pure_helpers():
    assert rview.merge_windows([(5, 9), (1, 3), (2, 4), (9, 10)]) == [(1, 4), (5, 10)]
    t = np.arange(25, dtype=np.int64) * 2_000_000 + 10**18
    x = np.arange(25 * 6, dtype=float).reshape(25, 6)
    tm, xm = rview.decimate_means(t, x, 10)
    assert len(tm) == 2 and tm[0] == t[0] + 9_000_000
    np.testing.assert_allclose(xm[1], x[10:20].mean(axis=0))
    tm, xm = rview.decimate_means(t[:7], x[:7], 10)  # fewer samples than a group (a short live block)
    assert tm.shape == (0,) and xm.shape == (0, 6)
    p = np.array([[0.0, 0, 0], [1, 0, 0], [1, 2, 0]])
    seg = rview._step_segments(p)
    assert seg.shape == (3, 2, 3)
    np.testing.assert_array_equal(seg[0], p[[0, 0]])
    np.testing.assert_array_equal(seg[2], p[1:3])
    enu = rview.to_enu(np.array([45.0, 45.0 + 1 / 111_132.954]), np.array([7.0, 7.0]), np.array([100.0, 101.0]),
                       (45.0, 7.0, 100.0))
    np.testing.assert_allclose(enu[0], 0, atol=1e-6)
    np.testing.assert_allclose(enu[1], [0.0, 1.0, 1.0], atol=0.01)  # ~1 m north, 1 m up


def _mcap_log_times(path: Path) -> dict[str, np.ndarray]:
    """log_time per topic straight from the mcap library (independent of drive.reader)."""
    out: dict[str, list[int]] = {}
    with open(path, "rb") as f:
        for _, channel, msg in make_reader(f).iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append(msg.log_time)
    return {k: np.sort(np.array(v, dtype=np.int64)) for k, v in out.items()}


def test_export_parquet_round_trip(drives, tmp_path):
    sim, kf = drives
    out = tmp_path / "export"
    assert cli_main(["export", str(sim), "--out", str(out)]) == 0
    assert cli_main(["export", str(kf), "--out", str(out), "--force"]) == 0  # its /tf_static replaces the drive's
    assert cli_main(["export", str(sim), "--out", str(tmp_path / "sim"), "--topics", "/tf_static"]) == 0
    for drive, where in ((sim, tmp_path / "sim"), (kf, None)):
        truth = _mcap_log_times(drive)
        for topic, times in truth.items():
            # (both files have /tf_static, the fused one's written last into ``out``)
            base = where if where is not None and topic == "/tf_static" else out
            df = pl.read_parquet(base.joinpath(*topic.strip("/").split("/")).with_suffix(".parquet"))
            got = df["log_time_ns"].to_numpy()
            if topic in ("/tf", "/tf_static"):   # one row per transform: the drive's base_link -> imu ->
                # gps_antenna; the fused file's and earth -> map; /tf map -> odom -> base_link
                per = 2 if topic == "/tf" or drive is sim else 3
                assert df.height == len(times) * per, topic
                got = got[np.r_[True, np.diff(got) != 0]]
            assert len(got) == len(times), topic
            np.testing.assert_array_equal(got, times, err_msg=topic)
            assert df["valid"].all(), topic
    imu = pl.read_parquet(out / "imu.parquet")
    assert imu.schema["log_time_ns"] == pl.Int64 and imu.schema["stamp_ns"] == pl.Int64
    assert (imu["stamp_ns"] == imu["log_time_ns"]).all()  # derived topics: stamp = log_time = UTC
    assert abs(imu["f_b_z"].mean() - 9.8) < 0.3  # specific force, body up
    fix = pl.read_parquet(out / "gps" / "fix.parquet")
    assert fix.schema["position_covariance"] == pl.Array(pl.Float64, 9)
    assert (fix["status"] == -1).sum() >= NO_FIX[1] - 1
    outage = pl.read_parquet(out / "fusion" / "outage.parquet")
    assert outage["reason"].to_list() == ["injected", "no_fix"]
    assert (outage["end_ns"] - outage["start_ns"]).to_list()[0] == 15 * 10**9
    nmea = pl.read_parquet(out / "gps" / "nmea.parquet")
    assert nmea["sentence"].str.starts_with("$").all()
    frames = drive_frames(sim, ["/gps/fix", "/pps"])
    assert set(frames) == {"/gps/fix", "/pps"} and frames["/gps/fix"].equals(fix)
    assert frames["/pps"]["source"].str.starts_with("pps").all()


def test_export_csv_flattens_lists(drives, tmp_path):
    sim, _ = drives
    assert cli_main(["export", str(sim), "--out", str(tmp_path), "--format", "csv",
                     "--topics", "/gps/fix,/raw/gps"]) == 0
    fix = pl.read_csv(tmp_path / "gps" / "fix.csv")
    assert "position_covariance_8" in fix.columns and fix.height == len(read_topic(sim, "/gps/fix")["log_time_ns"])
    raw = pl.read_csv(tmp_path / "raw" / "gps.csv")
    first = bytes.fromhex(raw["data"][0])
    assert b"$" in first or first.isascii()
    assert cli_main(["export", str(sim), "--out", str(tmp_path), "--topics", "/nope"]) == 2


def test_errors_against_gps_and_an_imported_nmea_log_on_the_map(drives, tmp_path):
    sim, kf = drives
    gps, epochs, no_fix = rview.gps_track(read_topic(sim, "/gps/fix"))
    v = read_topic(sim, "/gps/vel")
    gps.v_n = rview._interp(gps.t_ns, v["log_time_ns"], v["v_n"])
    origin = (float(gps.lat_deg[0]), float(gps.lon_deg[0]), float(gps.alt_m[0]))
    fused = rview._fused(rview._read_fused(kf, "kf", wheels=False))
    e = rview.errors(fused, gps, False, origin)
    inside = (gps.t_ns >= fused.t_ns[0]) & (gps.t_ns <= fused.t_ns[-1])
    np.testing.assert_array_equal(e.t_ns, gps.t_ns[inside])  # evaluated at the GPS fix epochs
    assert np.isnan(e.vel[:, 2]).all() and np.isfinite(e.vel[:, :2]).all()
    assert np.median(np.hypot(e.pos[:, 0], e.pos[:, 1])) < 5.0

    nmea = tmp_path / "log.nmea"
    nmea.write_text("".join(m.sentence.strip() + "\r\n" for m in read_topic(sim, "/gps/nmea")["msgs"]))
    imported, rrd = tmp_path / "imported.mcap", tmp_path / "imported.rrd"
    assert cli_main(["import", "--gps", str(nmea), "--out", str(imported)]) == 0
    assert cli_main(["view", str(imported), "--rrd", str(rrd)]) == 0
    rows = _rows(_rerun("print", str(rrd)))
    assert rows["/map/gps", "GeoPoints:positions"] == len(epochs) - int(no_fix.sum())
    assert rows["/map/gps/track", "GeoLineStrings:line_strings"] == 1


def test_raw_batch_decoder_equals_the_per_message_decode(drives):
    """/raw/* read in batch (drive.reader.read_raw) equals mcap_ros2's per-message decode, bit for bit; rows that
    are not RawBytes come out invalid, never raising."""
    sim, _ = drives
    for topic in ("/raw/daq", "/raw/gps"):
        batch = reader.read_raw(sim, topic)
        ref = read_topic(sim, topic)
        msgs = ref["msgs"]
        assert len(msgs) > 100 and batch["valid"].all()
        np.testing.assert_array_equal(batch["log_time_ns"], ref["log_time_ns"])
        np.testing.assert_array_equal(batch["stamp_ns"], [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                                                          for m in msgs])
        np.testing.assert_array_equal(batch["mono_ns"], [m.mono_ns for m in msgs])
        assert list(batch["port"]) == [m.port for m in msgs] and set(batch["port"]) == {topic.split("/")[-1]}
        assert list(batch["data"]) == [bytes(m.data) for m in msgs]
        in_order = [r for b in reader.iter_raw_batches(sim, topic) for r in b["data"]]
        assert b"".join(in_order) == b"".join(bytes(m.data) for m in msgs)  # file order = read order here
    good = messages.encode_raw(1_777_000_000_123_456_789, 42, "gps", b"$GPGGA,1*00\r\n", frame_id="x")
    bad = [good[:20], good[:-3], b"", b"\x01" + good[1:], good[:12] + b"\xff\xff\xff\x7f" + good[16:]]
    d = reader.decode_raw_batch(messages.Packed.from_list([good, *bad, good]))
    assert d["valid"].tolist() == [True] + [False] * len(bad) + [True]
    assert list(d["data"]) == [b"$GPGGA,1*00\r\n"] + [b""] * len(bad) + [b"$GPGGA,1*00\r\n"]
    assert d["stamp_ns"][0] == 1_777_000_000_123_456_789 and d["mono_ns"][-1] == 42 and d["port"][0] == "gps"
    empty = reader.decode_raw_batch(messages.Packed.from_list([]))
    assert len(empty["valid"]) == 0 and len(empty["data"]) == 0
