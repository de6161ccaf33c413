"""The rosbag2 profile and the ROS frames of a drive, checked with a third-party ROS 2 implementation (rosbags'
Jazzy typestore and CDR decoder): every schema text, the channels' offered_qos_profiles, /tf_static, and the
nav_msgs/Odometry and /tf of `fieldlog fuse`."""
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from fieldlog.acquire import calib, frames
from fieldlog.drive import bagdir, messages
from fieldlog.fusion import earth
from fieldlog.drive import reader
from fieldlog.tools.fuse import fuse
from fieldlog.tools.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
# nmea_msgs/msg/Sentence.msg (ros-drivers/nmea_msgs, not in the core typestore), without its comments
NMEA_SENTENCE = "std_msgs/Header header\nstring sentence\n"


@pytest.fixture(scope="module")
def typestore():
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = get_types_from_msg(NMEA_SENTENCE, "nmea_msgs/msg/Sentence")
    for f in sorted((ROOT / "fieldlog_msgs" / "msg").glob("*.msg")):
        types.update(get_types_from_msg(f.read_text(), f"fieldlog_msgs/msg/{f.stem}"))
    ts.register(types)
    return ts


def test_every_schema_is_jazzys(typestore):
    written = set(messages.TOPICS.values()) | set(messages.FUSION_SUBTOPICS.values())
    for type_name in sorted(written):
        text, _ = typestore.generate_msgdef(type_name, ros_version=2)
        assert messages.schema_text(type_name) == text, type_name
    # the interface package holds exactly our own types
    ours = {t for t in messages.MSG_DEFS if t.startswith("fieldlog_msgs/")}
    assert {f"fieldlog_msgs/msg/{f.stem}" for f in (ROOT / "fieldlog_msgs" / "msg").glob("*.msg")} == ours
    cmake = (ROOT / "fieldlog_msgs" / "CMakeLists.txt").read_text()
    assert all(f'"msg/{t.split("/")[-1]}.msg"' in cmake for t in ours)
    assert "<name>fieldlog_msgs</name>" in (ROOT / "fieldlog_msgs" / "package.xml").read_text()


def test_navsatstatus_has_jazzys_constants(typestore):
    consts = {name: value for name, _, value in typestore.fielddefs["sensor_msgs/msg/NavSatStatus"][0]}
    assert consts["STATUS_UNKNOWN"] == messages.STATUS_UNKNOWN == -2
    assert consts["STATUS_NO_FIX"] == messages.STATUS_NO_FIX and consts["STATUS_GBAS_FIX"] == messages.STATUS_GBAS_FIX


MOUNTING = calib.Mounting(imu_position_m=[1.2, 0.0, 0.4], imu_rpy_deg=[0.0, 0.0, 0.0], antenna_m=[0.0, -0.8, 1.1])


@pytest.fixture(scope="module")
def fused(tmp_path_factory):
    """A 150 s figure8 drive simulated with a calibration whose [mounting] is not zero, fused with kf."""
    d = tmp_path_factory.mktemp("ros")
    drive, out = d / "drive.mcap", d / "kf.mcap"
    cal = calib.Calibration(calib.default_calibration().gyro, calib.default_calibration().accel, MOUNTING)
    with pytest.MonkeyPatch.context() as mp:   # the simulator's IMU sits where the calibration says
        mp.setattr(calib, "load_calibration", lambda path: cal)
        simulate("figure8", 150, 3, drive)
    fuse(drive, "kf", out)
    return drive, out


def _messages(path, topic):
    with open(path, "rb") as f:
        return [(m.log_time, m.data) for _, ch, m in make_reader(f).iter_messages(topics=[topic])]


def test_every_channel_offers_rosbag2_qos(fused):
    for path in fused:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary.channels
        for ch in summary.channels.values():
            (qos,) = parse_qos(ch.metadata["offered_qos_profiles"])
            assert qos.reliability.name == "RELIABLE", ch.topic
            want = "TRANSIENT_LOCAL" if ch.topic == "/tf_static" or ch.topic.endswith("/datum") else "VOLATILE"
            assert qos.durability.name == want, ch.topic


def test_every_channel_carries_the_rihs01_type_hash(fused, typestore):
    """As rosbag2 Jazzy: the channel's topic_type_hash, and metadata.yaml's type_description_hash."""
    for path in fused:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        for ch in summary.channels.values():
            want = typestore.hash_rihs01(summary.schemas[ch.schema_id].name)
            assert ch.metadata["topic_type_hash"] == want, ch.topic
        meta = bagdir.metadata([bagdir.file_info(path)])["rosbag2_bagfile_information"]
        for tw in meta["topics_with_message_count"]:
            tm = tw["topic_metadata"]
            assert tm["type_description_hash"] == typestore.hash_rihs01(tm["type"]), tm["name"]
    assert len({typestore.hash_rihs01(t) for t in messages.MSG_DEFS}) == len(messages.MSG_DEFS)


def test_drive_has_tf_static_from_the_mounting(fused, typestore):
    drive, _ = fused
    (log_time, data), = _messages(drive, "/tf_static")
    # written with the first read (its host clock): derived stamps can be earlier (a fix is stamped with its UTC,
    # before its sentences arrive), which latched /tf_static (transient local) does not mind
    assert log_time == min(t.first_ns for t in reader.topics(drive) if t.topic.startswith("/raw/"))
    msg = typestore.deserialize_cdr(data, messages.TFMESSAGE)
    tf = {(t.header.frame_id, t.child_frame_id): t.transform for t in msg.transforms}
    assert set(tf) == {("base_link", "imu"), ("imu", "gps_antenna")}
    imu = tf[("base_link", "imu")]
    np.testing.assert_allclose([imu.translation.x, imu.translation.y, imu.translation.z], MOUNTING.imu_position_m)
    C = earth.quat_to_dcm([imu.rotation.x, imu.rotation.y, imu.rotation.z, imu.rotation.w])
    # the IMU's forward (y) axis is base_link's x, its right (x) axis is -y, up is up
    np.testing.assert_allclose(C @ [0, 1, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(C @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    ant = tf[("imu", "gps_antenna")]
    np.testing.assert_allclose([ant.translation.x, ant.translation.y, ant.translation.z], MOUNTING.antenna_m)
    # /imu is in the frame the transform names
    (_, imu_msg), = _messages(drive, "/imu")[:1]
    assert typestore.deserialize_cdr(imu_msg, messages.IMU).header.frame_id == "imu"


def test_fused_drive_has_odometry_and_tf(fused, typestore):
    _, out = fused
    odom = [typestore.deserialize_cdr(d, messages.ODOMETRY) for _, d in _messages(out, "/fusion/kf/odom")]
    tfs = [typestore.deserialize_cdr(d, messages.TFMESSAGE) for _, d in _messages(out, "/tf")]
    fix = reader.read_topic(out, "/fusion/kf/fix")
    vel = reader.read_topic(out, "/fusion/kf/vel")
    att = reader.read_topic(out, "/fusion/kf/attitude")
    n = len(fix["log_time_ns"])
    assert n > 500 and len(odom) == len(tfs) == n
    assert {(o.header.frame_id, o.child_frame_id) for o in odom} == {("odom", "base_link")}
    p = np.array([[o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z] for o in odom])
    q = np.array([[o.pose.pose.orientation.x, o.pose.pose.orientation.y, o.pose.pose.orientation.z,
                   o.pose.pose.orientation.w] for o in odom])
    v_base = np.array([[o.twist.twist.linear.x, o.twist.twist.linear.y, o.twist.twist.linear.z] for o in odom])
    # /tf map -> odom -> base_link: odom -> base_link is the odometry pose, and both compose to the map pose
    assert {tuple((x.header.frame_id, x.child_frame_id) for x in t.transforms) for t in tfs} == \
        {(("map", "odom"), ("odom", "base_link"))}
    tr = np.array([[[x.transform.translation.x, x.transform.translation.y, x.transform.translation.z]
                    for x in t.transforms] for t in tfs])
    np.testing.assert_array_equal(tr[:, 1], p)
    p = tr[:, 0] + tr[:, 1]

    # the map origin is the first solution; the IMU position (base_link origin + C imu_position) is the fix in ENU
    lat, lon, h = np.radians(fix["lat_deg"]), np.radians(fix["lon_deg"]), fix["alt_m"]
    p_imu = (earth.lla_to_ecef(lat, lon, h) - earth.lla_to_ecef(lat[0], lon[0], h[0])) @ earth.C_en(lat[0], lon[0]).T
    C_base_n = earth.quat_to_dcm(q)
    np.testing.assert_allclose(p + C_base_n @ MOUNTING.imu_position_m, p_imu, atol=1e-6)
    assert np.ptp(p[:, 0]) > 50   # it moved

    # base_link is forward-left-up: on a car, the velocity is along +x (forward), not sideways
    speed = np.linalg.norm(vel["v_n"], axis=1)
    moving = speed > 3.0
    assert moving.sum() > 100
    np.testing.assert_allclose(np.linalg.norm(v_base, axis=1), speed, rtol=1e-9)
    assert np.all(v_base[moving, 0] > 0.9 * speed[moving])
    # base_link's orientation is the IMU attitude turned by the mounting
    C_imu_n = earth.quat_to_dcm(att["q_xyzw"])
    np.testing.assert_allclose(C_base_n, C_imu_n @ frames.C_imu_base(MOUNTING).T, atol=1e-9)

    # covariances: the position variances of /fix, and the velocity covariance rotated (same trace)
    pc = np.array([o.pose.covariance for o in odom]).reshape(n, 6, 6)
    np.testing.assert_allclose(pc[:, [0, 1, 2], [0, 1, 2]], fix["position_covariance"][:, [0, 4, 8]], rtol=1e-9)
    assert np.all(pc[:, [3, 4, 5], [3, 4, 5]] > 0)
    tc = np.array([o.twist.covariance for o in odom]).reshape(n, 6, 6)
    vc = vel["covariance"].reshape(n, 6, 6)
    np.testing.assert_allclose(np.trace(tc[:, :3, :3], axis1=1, axis2=2), np.trace(vc[:, :3, :3], axis1=1, axis2=2),
                               rtol=1e-9)
    # yaw rate from the attitude: turning left (counter-clockwise seen from above) is +z in FLU
    heading = np.unwrap(np.arctan2(vel["v_n"][:, 1], vel["v_n"][:, 0]))
    wz = np.array([o.twist.twist.angular.z for o in odom])
    dpsi = np.gradient(heading, fix["log_time_ns"] / 1e9)
    turning = moving & (np.abs(dpsi) > 0.05)
    assert turning.sum() > 50
    assert np.mean(np.sign(wz[turning]) == np.sign(dpsi[turning])) > 0.95


def test_foxglove_layout_names_what_a_fused_drive_holds(fused, typestore):
    """Every topic and message path of docs/foxglove/fieldlog-fused.json resolves in a drive plus its kf fusion."""
    import json

    layout = json.loads((ROOT / "docs" / "foxglove" / "fieldlog-fused.json").read_text())
    first = {}
    for path in fused:
        with open(path, "rb") as f:
            for schema, ch, m in make_reader(f).iter_messages():
                if ch.topic not in first:
                    first[ch.topic] = typestore.deserialize_cdr(m.data, schema.name)
    cfg = layout["configById"]
    topics = set(cfg["map!fieldlog"]["topicColors"]) | set(cfg["3D!fieldlog"]["topics"])
    assert topics <= set(first), topics - set(first)
    assert cfg["3D!fieldlog"]["followTf"] == frames.BASE_LINK
    paths = [p["value"] for k, c in cfg.items() if k.startswith("Plot!") for p in c["paths"]]
    assert len(paths) >= 8
    for p in paths:
        topic, *fields = p.split(".")
        value = first[topic]
        for name in fields:
            value = getattr(value, name)
        assert isinstance(value, float), p
