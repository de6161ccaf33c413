"""REP-105 frames: a simulated drive and its fused file, every message decoded by mcap_ros2 (a third-party
decoder) and every frame_id checked against the TF tree the two files carry."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from fieldlog.acquire import calib
from fieldlog.fusion import earth
from fieldlog.tools.cli import main as fieldlog
from fieldlog.drive.reader import read_metadata
from fieldlog.tools.sim.simulate import simulate


@pytest.fixture(scope="module")
def fused(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("frames")
    drive, out = d / "drive.mcap", d / "kf.mcap"
    simulate("figure8", 100, 2, drive)     # the outage (60 s to 90 s) and GPS again after it
    assert fieldlog(["fuse", str(drive), "--method", "kf", "--outage", "60:30", "--out", str(out)]) == 0
    return drive, out


def decoded(path: Path) -> list[tuple[str, int, object]]:
    with open(path, "rb") as f:
        return [(ch.topic, m.log_time, msg) for _s, ch, m, msg in
                make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]


def tree_edges(msgs) -> dict[str, str]:
    """child -> parent of every transform in /tf and /tf_static."""
    edges: dict[str, str] = {}
    for topic, _t, m in msgs:
        if topic in ("/tf", "/tf_static"):
            for tr in m.transforms:
                assert edges.setdefault(tr.child_frame_id, tr.header.frame_id) == tr.header.frame_id
    return edges


@pytest.mark.slow
def test_every_frame_id_is_a_frame_of_the_tree(fused) -> None:
    msgs = decoded(fused[0]) + decoded(fused[1])
    edges = tree_edges(msgs)
    frames = set(edges) | set(edges.values())
    roots = {p for p in edges.values() if p not in edges}
    assert roots == {"earth"}                                  # one tree: earth -> map -> odom -> base_link -> ...
    for child in edges:
        seen, f = set(), child
        while f in edges:
            assert f not in seen
            seen.add(f)
            f = edges[f]
    used: dict[str, set[str]] = {}
    for topic, _t, m in msgs:
        header = getattr(m, "header", None)
        ids = [header.frame_id] if header is not None else []
        ids += [getattr(m, "child_frame_id", "")]
        for tr in getattr(m, "transforms", []):
            ids += [tr.header.frame_id, tr.child_frame_id]
        for i in ids:
            if i:                                              # (raw bytes and outage records name no frame)
                used.setdefault(i, set()).add(topic)
    assert set(used) <= frames, {k: v for k, v in used.items() if k not in frames}
    assert {"map", "odom", "base_link", "imu", "gps_antenna"} <= set(used)
    assert not set(used) & {"kf", "enu", "truth", "daq", "gps"}
    assert edges["odom"] == "map" and edges["base_link"] == "odom" and edges["map"] == "earth"
    assert edges["imu"] == "base_link" and edges["gps_antenna"] == "imu"


@pytest.mark.slow
def test_tf_static_odom_and_datum_follow_rep_105(fused) -> None:
    drive, out = fused
    msgs = decoded(out)
    by = lambda topic: [(t, m) for tp, t, m in msgs if tp == topic]   # noqa: E731
    (static,) = by("/tf_static")
    tr = {x.child_frame_id: x for x in static[1].transforms}
    mounting = calib.Calibration.from_toml(read_metadata(drive)["calibration"]["toml"]).mounting
    lever = tr["gps_antenna"].transform.translation
    assert np.allclose([lever.x, lever.y, lever.z], mounting.antenna_m)
    # the datum: one NavSatFix in map, the fusion.map record, and earth -> map at its ECEF position
    (datum,) = by("/fusion/kf/datum")
    d = datum[1]
    meta = read_metadata(out)["fusion.map"]
    assert d.header.frame_id == "map" and (d.latitude, d.longitude, d.altitude) == \
        (float(meta["lat_deg"]), float(meta["lon_deg"]), float(meta["h_m"]))
    em = tr["map"].transform.translation
    lat0, lon0, h0 = np.radians(d.latitude), np.radians(d.longitude), d.altitude
    assert np.allclose([em.x, em.y, em.z], earth.lla_to_ecef(lat0, lon0, h0), atol=1e-6)
    # /tf: map -> odom -> base_link composes to the fused position; odom moves only by the fused velocity
    tf = by("/tf")
    p_mo = np.array([[x.transforms[0].transform.translation.x, x.transforms[0].transform.translation.y,
                      x.transforms[0].transform.translation.z] for _, x in tf])
    p_ob = np.array([[x.transforms[1].transform.translation.x, x.transforms[1].transform.translation.y,
                      x.transforms[1].transform.translation.z] for _, x in tf])
    assert all(x.transforms[0].header.frame_id == "map" and x.transforms[1].child_frame_id == "base_link"
               for _, x in tf)
    fix = by("/fusion/kf/fix")
    vel = by("/fusion/kf/vel")
    assert len(fix) == len(tf) == len(vel) == len(by("/fusion/kf/odom"))
    lat = np.radians([m.latitude for _, m in fix])
    lon = np.radians([m.longitude for _, m in fix])
    h = np.array([m.altitude for _, m in fix])
    p_fix = (earth.lla_to_ecef(lat, lon, h) - earth.lla_to_ecef(lat0, lon0, h0)) @ earth.C_en(lat0, lon0).T
    assert np.allclose(p_mo + p_ob, p_fix, atol=1e-3) or not np.allclose(mounting.imu_position_m, 0)
    v = np.array([[m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z] for _, m in vel])
    t = np.array([t for t, _ in fix])
    dead = 0.5 * (v[1:] + v[:-1]) * (np.diff(t) / 1e9)[:, None]
    odom_step = np.linalg.norm(np.diff(p_ob, axis=0) - dead, axis=1)
    map_step = np.linalg.norm(np.diff(p_fix, axis=0) - dead, axis=1)
    assert odom_step.max() < 1e-5                              # continuous: never jumps (10 um: float rounding)
    assert map_step.max() > 1000 * max(odom_step.max(), 1e-5)  # the fused position is corrected (GPS updates)
    assert np.linalg.norm(p_mo[-1]) > 0.01                     # and map -> odom took those corrections up
    odom = by("/fusion/kf/odom")
    assert all(m.header.frame_id == "odom" and m.child_frame_id == "base_link" for _, m in odom)
    p_odom_msg = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z]
                           for _, m in odom])
    assert np.array_equal(p_odom_msg, p_ob)


def test_quaternions_and_mounting_are_scipy_s_floats() -> None:
    """``frames`` computes the quaternions of rotations and the mounting's rotation without scipy on the fuse and
    sim paths: the same floats as ``scipy.spatial.transform.Rotation``, which it still uses otherwise."""
    from scipy.spatial.transform import Rotation

    from fieldlog.acquire import frames

    rng = np.random.default_rng(7)
    mats = list(Rotation.random(2000, rng=rng).as_matrix())
    mats += [earth.C_en(lat, lon).T for lat, lon in rng.uniform([-1.5, -3.1], [1.5, 3.1], (2000, 2))]
    mats += [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    for C in mats:
        q = Rotation.from_matrix(C).as_quat()
        assert np.array_equal(frames.quat_xyzw(C), q * (-1.0 if q[3] < 0 else 1.0)), C
    angles = [np.zeros(3), np.array([0.0, -4.0, 5.0]), np.array([180.0, 90.0, -180.0])]
    angles += list(rng.uniform(-180.0, 180.0, (5000, 3))) + list(rng.normal(0.0, 1e-6, (100, 3)))
    for rpy in angles:
        m = calib.Mounting(imu_rpy_deg=rpy)
        assert np.array_equal(frames.C_imu_base(m),
                              frames.C_RFU_FLU @ Rotation.from_euler("xyz", rpy, degrees=True).as_matrix()), rpy


def test_odometry_does_not_depend_on_where_the_blocks_end(tmp_path: Path) -> None:
    """/fusion/kf/odom and /tf written from the same rows at once and in blocks of 1 to 9 rows: the same messages
    (to the rounding of the matrix products over a block's rows); each angular rate is the turn from the row before
    (0 at the first row), in base_link."""
    from fieldlog.drive.recorder import Recorder
    from fieldlog.fusion.types import Solution
    from fieldlog.replay.solutions import Odometry

    n = 200
    t_ns = 10**18 + np.arange(n, dtype=np.int64) * 100_000_000
    yaw = 0.3 * np.sin(np.arange(n) / 15.0)
    q = np.column_stack([np.zeros(n), np.zeros(n), np.sin(0.5 * yaw), np.cos(0.5 * yaw)])
    v_n = np.column_stack([10.0 * np.sin(yaw), 10.0 * np.cos(yaw), np.zeros(n)])
    sol = Solution(t_ns, 0.7 + np.arange(n) * 1e-7, 0.2 + np.arange(n) * 1e-7, np.full(n, 50.0), v_n, q,
                   np.full((n, 15), 0.1), np.zeros((n, 6)))
    mounting = calib.Mounting(imu_rpy_deg=(0.0, 0.0, 90.0), imu_position_m=(0.5, -0.2, 0.3))
    cuts = np.cumsum(np.random.default_rng(5).integers(1, 10, n))
    cuts = [0, *cuts[cuts < n], n]
    files = {}
    for name, spans in (("once", [(0, n)]), ("blocks", list(zip(cuts, cuts[1:])))):
        files[name] = tmp_path / f"{name}.mcap"
        odom = Odometry("kf", mounting)
        with Recorder(files[name]) as rec:
            for a, b in spans:
                odom.write(rec, Solution(*(getattr(sol, k)[a:b] for k in ("t_ns", "lat", "lon", "h", "v_n", "q",
                                                                           "sigma", "bias"))))
    assert len(cuts) > 30
    once, blocks = ([(tp, t, m) for tp, t, m in decoded(files[k]) if tp in ("/fusion/kf/odom", "/tf")]
                    for k in ("once", "blocks"))
    assert len(once) == len(blocks) == 2 * n and [x[:2] for x in once] == [x[:2] for x in blocks]

    def numbers(m) -> list[float]:  # the poses, twists and covariances of an Odometry or a TFMessage
        xyz = lambda v: [v.x, v.y, v.z] + ([v.w] if hasattr(v, "w") else [])  # noqa: E731
        if hasattr(m, "transforms"):
            return [x for tr in m.transforms for v in (tr.transform.translation, tr.transform.rotation) for x in xyz(v)]
        p, tw = m.pose, m.twist
        return (xyz(p.pose.position) + xyz(p.pose.orientation) + xyz(tw.twist.linear) + xyz(tw.twist.angular)
                + list(p.covariance) + list(tw.covariance))

    a, b = (np.concatenate([numbers(m) for _, _, m in x]) for x in (once, blocks))
    np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)  # the products of a block's rows, to rounding
    w_z = np.array([m.twist.twist.angular.z for tp, _, m in once if tp == "/fusion/kf/odom"])
    assert w_z[0] == 0.0  # base_link's z is the IMU's up here: its yaw rate
    np.testing.assert_allclose(w_z[1:], np.diff(yaw) / 0.1, rtol=1e-9)
