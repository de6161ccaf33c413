"""drive.messages: our CDR bytes against mcap_ros2's own encoder and decoder."""

from __future__ import annotations

import io

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.reader import read_ros2_messages
from mcap_ros2.writer import Writer as Ros2Writer

from fieldlog.drive import messages as m

T0 = 1_700_000_000 * 10**9
RNG = np.random.default_rng(7)


def _stamps(n: int) -> np.ndarray:
    return T0 + np.sort(RNG.integers(0, 10**12, n)) + np.array([-1_500_000_000] + [0] * (n - 1))


def _roundtrip_ours(type_name: str, payloads: list[bytes]) -> list:
    """Write our bytes into an MCAP with a ros2msg schema; decode with mcap_ros2's reader."""
    buf = io.BytesIO()
    w = Writer(buf)
    w.start(profile="ros2")
    sid = w.register_schema(type_name, "ros2msg", m.schema_text(type_name).encode())
    cid = w.register_channel("/t", "cdr", sid)
    for i, b in enumerate(payloads):
        w.add_message(cid, T0 + i + 1, b, T0 + i + 1)
    w.finish()
    buf.seek(0)
    return [msg.ros_msg for msg in read_ros2_messages(buf)]


def _mcap_ros2_bytes(type_name: str, objs: list) -> list[bytes]:
    """Serialise message objects/dicts with mcap_ros2's own encoder; return the raw payloads."""
    buf = io.BytesIO()
    w = Ros2Writer(buf)
    schema = w.register_msgdef(type_name, m.schema_text(type_name))
    for i, o in enumerate(objs):
        w.write_message("/t", schema, o, log_time=T0 + i + 1)
    w.finish()
    buf.seek(0)
    return [msg.data for _, _, msg in make_reader(buf).iter_messages()]


def _stamp_ns(h) -> int:
    return h.stamp.sec * 10**9 + h.stamp.nanosec


def _check_same_bytes(type_name: str, p: m.Packed) -> list:
    ours = p.to_list()
    decoded = _roundtrip_ours(type_name, ours)
    assert len(decoded) == len(ours)
    assert _mcap_ros2_bytes(type_name, decoded) == ours  # byte-identical to mcap_ros2
    return decoded


def test_imu_encode_matches_mcap_ros2_and_decoders_agree():
    n = 50
    t = _stamps(n)
    w, f = RNG.normal(size=(n, 3)), RNG.normal(size=(n, 3))
    gcov = RNG.normal(size=(n, 9))
    acov = RNG.normal(size=9)
    p = m.encode_imu(t, w, f, gcov, acov)
    dec = _check_same_bytes(m.IMU, p)
    for i, d in enumerate(dec):
        assert _stamp_ns(d.header) == t[i]
        assert d.header.frame_id == "imu"
        assert [d.angular_velocity.x, d.angular_velocity.y, d.angular_velocity.z] == w[i].tolist()
        assert [d.linear_acceleration.x, d.linear_acceleration.y, d.linear_acceleration.z] == f[i].tolist()
        assert list(d.angular_velocity_covariance) == gcov[i].tolist()
        assert list(d.linear_acceleration_covariance) == acov.tolist()
        assert d.orientation_covariance[0] == -1.0
    ours = m.decode_imu(p)
    assert ours["valid"].all()
    np.testing.assert_array_equal(ours["stamp_ns"], t)
    np.testing.assert_array_equal(ours["omega_ib_b"], [[d.angular_velocity.x, d.angular_velocity.y, d.angular_velocity.z] for d in dec])
    np.testing.assert_array_equal(ours["f_b"], f)
    np.testing.assert_array_equal(ours["gyro_cov"], gcov)
    some = m.decode_imu(p, ("omega_ib_b", "valid"))  # the keys asked for alone, the same values, contiguous
    assert sorted(some) == ["omega_ib_b", "valid"]
    assert all(v.flags.c_contiguous for v in ours.values()) and some["omega_ib_b"].flags.c_contiguous
    np.testing.assert_array_equal(some["omega_ib_b"], ours["omega_ib_b"])


def test_imu_with_orientation():
    n = 5
    q = RNG.normal(size=(n, 4))
    p = m.encode_imu(_stamps(n), np.zeros((n, 3)), np.zeros((n, 3)), orientation_xyzw=q, frame_id="base_link")
    dec = _check_same_bytes(m.IMU, p)
    assert [[d.orientation.x, d.orientation.y, d.orientation.z, d.orientation.w] for d in dec] == q.tolist()
    assert dec[0].header.frame_id == "base_link"
    np.testing.assert_array_equal(m.decode_imu(p)["orientation_xyzw"], q)


def test_navsatfix():
    n = 20
    t = _stamps(n)
    lat, lon, alt = RNG.uniform(-90, 90, n), RNG.uniform(-180, 180, n), RNG.normal(300, 50, n)
    cov = RNG.uniform(0, 10, (n, 9))
    status = RNG.integers(-1, 3, n)
    p = m.encode_navsatfix(t, lat, lon, alt, cov, covariance_type=3, status=status, service=9)
    dec = _check_same_bytes(m.NAVSATFIX, p)
    for i, d in enumerate(dec):
        assert (d.latitude, d.longitude, d.altitude) == (lat[i], lon[i], alt[i])
        assert d.status.status == status[i] and d.status.service == 9
        assert list(d.position_covariance) == cov[i].tolist()
        assert d.position_covariance_type == 3
    ours = m.decode_navsatfix(p)
    np.testing.assert_array_equal(ours["stamp_ns"], t)
    np.testing.assert_array_equal(ours["lat_deg"], [d.latitude for d in dec])
    np.testing.assert_array_equal(ours["lon_deg"], lon)
    np.testing.assert_array_equal(ours["alt_m"], alt)
    np.testing.assert_array_equal(ours["status"], status)
    np.testing.assert_array_equal(ours["position_covariance"], cov)


def test_twist_quaternion_vector3():
    n = 10
    t = _stamps(n)
    v, om, cov = RNG.normal(size=(n, 3)), RNG.normal(size=(n, 3)), RNG.normal(size=(n, 36))
    dec = _check_same_bytes(m.TWIST, m.encode_twist(t, v, om, cov))
    assert [[d.twist.twist.linear.x, d.twist.twist.linear.y, d.twist.twist.linear.z] for d in dec] == v.tolist()
    assert [list(d.twist.covariance) for d in dec] == cov.tolist()
    ours = m.decode_twist(m.encode_twist(t, v, om, cov))
    np.testing.assert_array_equal(ours["v_n"], v)
    np.testing.assert_array_equal(ours["omega"], om)
    np.testing.assert_array_equal(ours["covariance"], cov)

    q = RNG.normal(size=(n, 4))
    dq = _check_same_bytes(m.QUATERNION, m.encode_quaternion(t, q))
    assert [[d.quaternion.x, d.quaternion.y, d.quaternion.z, d.quaternion.w] for d in dq] == q.tolist()
    np.testing.assert_array_equal(m.decode_quaternion(m.encode_quaternion(t, q))["q_xyzw"], q)

    x = RNG.normal(size=(n, 3))
    dv = _check_same_bytes(m.VECTOR3, m.encode_vector3(t, x, frame_id="ab"))
    assert [[d.vector.x, d.vector.y, d.vector.z] for d in dv] == x.tolist()
    np.testing.assert_array_equal(m.decode_vector3(m.encode_vector3(t, x))["stamp_ns"], t)


@pytest.mark.parametrize("frame_id,source", [("", "x"), ("daq", "gps_pps"), ("abcdefg", "")])
def test_time_reference(frame_id, source):
    n = 8
    t = _stamps(n)
    ref = (t // 10**9) * 10**9
    p = m.encode_time_reference(t, ref, source=source, frame_id=frame_id)
    dec = _check_same_bytes(m.TIMEREF, p)
    assert [d.source for d in dec] == [source] * n
    assert [d.time_ref.sec * 10**9 + d.time_ref.nanosec for d in dec] == ref.tolist()
    ours = m.decode_time_reference(p)
    assert ours["valid"].all()
    np.testing.assert_array_equal(ours["time_ref_ns"], ref)
    np.testing.assert_array_equal(ours["stamp_ns"], t)


def test_time_sync():
    n = 6
    t = _stamps(n)
    state = np.array([0, 1, 2, 2, 1, 0])
    rate, res = RNG.normal(size=n) * 30, RNG.uniform(0, 500, n)
    used, rej = RNG.integers(0, 1000, n), RNG.integers(0, 10, n)
    p = m.encode_time_sync(t, state, rate, res, used, rej)
    dec = _check_same_bytes(m.TIMESYNC, p)
    assert [(d.state, d.rate_ppm, d.residual_us, d.edges_used, d.edges_rejected) for d in dec] == list(
        zip(state.tolist(), rate.tolist(), res.tolist(), used.tolist(), rej.tolist())
    )
    assert "uint8 LOCKED=2" in m.schema_text(m.TIMESYNC) and m.TIMESYNC_LOCKED == 2
    ours = m.decode_time_sync(p)
    np.testing.assert_array_equal(ours["state"], state)
    np.testing.assert_array_equal(ours["rate_ppm"], rate)
    np.testing.assert_array_equal(ours["edges_used"], used)


def test_variable_length_types():
    sentences = ["$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47", "", "$X*1"]
    ps = [m.encode_sentence(T0 + i, s) for i, s in enumerate(sentences)]
    dec = _check_same_bytes(m.SENTENCE, m.Packed.from_list(ps))
    assert [d.sentence for d in dec] == sentences

    raws = [bytes(RNG.integers(0, 256, k, dtype=np.uint8)) for k in (0, 1, 38, 1000)]
    pr = [m.encode_raw(T0 + i, 123456789 + i, "/dev/ttyUSB0", r) for i, r in enumerate(raws)]
    dec = _check_same_bytes(m.RAWBYTES, m.Packed.from_list(pr))
    assert [bytes(d.data) for d in dec] == raws
    assert [d.mono_ns for d in dec] == [123456789 + i for i in range(4)]
    assert dec[2].port == "/dev/ttyUSB0"

    po = [m.encode_outage(T0, T0 + 5, T0 + 30 * 10**9, "injected")]
    dec = _check_same_bytes(m.OUTAGE, m.Packed.from_list(po))
    assert (dec[0].start_ns, dec[0].end_ns, dec[0].reason) == (T0 + 5, T0 + 30 * 10**9, "injected")
    assert m.decode_message(m.OUTAGE, po[0]).reason == "injected"


def test_decoders_survive_bad_input_and_mixed_layouts():
    n = 6
    t = _stamps(n)
    w = RNG.normal(size=(n, 3))
    a = m.encode_imu(t, w, w, frame_id="imu").to_list()
    b = m.encode_imu(t, w, w, frame_id="a_longer_frame").to_list()
    msgs = [a[0], b"", b"\x00\x01\x00\x00junk", b[3], a[4][:-1], b"\xff" * 400, a[5], b"\x00\x00\x00\x00" + a[2][4:]]
    out = m.decode_imu(msgs)
    assert out["valid"].tolist() == [True, False, False, True, False, False, True, False]
    np.testing.assert_array_equal(out["omega_ib_b"][[0, 3, 6]], w[[0, 3, 5]])
    np.testing.assert_array_equal(out["stamp_ns"][[0, 3, 6]], t[[0, 3, 5]])
    assert (out["omega_ib_b"][[1, 2, 4, 5, 7]] == 0).all()
    empty = m.decode_navsatfix([])
    assert empty["lat_deg"].shape == (0,) and empty["position_covariance"].shape == (0, 9)


def test_stamp_split_is_floor():
    sec, nsec = m.split_stamp(np.array([-1, 0, 1_999_999_999]))
    assert sec.tolist() == [-1, 0, 1] and nsec.tolist() == [999_999_999, 0, 999_999_999]
    np.testing.assert_array_equal(m.join_stamp(sec[1:], nsec[1:]), [0, 1_999_999_999])
    assert m.join_stamp(sec[0], nsec[0]) == m.STAMP_END_NS - 1     # seconds read unsigned: 1970 to 2106


def test_topics_registry():
    assert m.topic_type("/imu") == m.IMU
    assert m.topic_type("/raw/daq") == m.RAWBYTES
    assert m.topic_type("/fusion/dkf-rbfn/fix") == m.NAVSATFIX
    assert m.topic_type("/fusion/kf/attitude") == m.QUATERNION
    assert m.topic_type("/fusion/kf/std") == m.VECTOR3
    with pytest.raises(KeyError):
        m.topic_type("/fusion/kf/other")
    for type_name in set(m.TOPICS.values()) | set(m.FUSION_SUBTOPICS.values()):
        text = m.schema_text(type_name)
        assert "MSG: std_msgs/Header" in text and "MSG: builtin_interfaces/Time" in text


def test_packed_take_gathers_any_order():
    msgs = [bytes([i % 256]) * (i % 7 + 1) for i in range(1000)]
    idx = np.random.default_rng(0).permutation(1000)[:700]
    for batch in (msgs, [b"abcd" * 3] * 500 + [b"wxyz" * 3] * 500):    # variable and equal lengths
        p = m.Packed.from_list(batch)
        assert p.take(idx).to_list() == [batch[i] for i in idx]
        assert p.take(np.zeros(0, np.int64)).to_list() == []


def test_tf_rows_are_encode_tf_row_by_row():
    rng = np.random.default_rng(3)
    n = 7
    t = 1_700_000_000_123_456_789 + np.arange(n, dtype=np.int64) * 4_999_999
    xyz, q = rng.standard_normal((n, 3)) * 1e3, rng.standard_normal((n, 4))
    xyz2 = rng.standard_normal((n, 3))
    names = [("map", "odom"), ("odom", "base_link_with_a_longer_name")]
    packed = m.encode_tf_rows(t, [(*names[0], xyz, q), (*names[1], xyz2, q[::-1])])
    want = [m.encode_tf(int(t[i]), [(*names[0], xyz[i], q[i]), (*names[1], xyz2[i], q[::-1][i])])
            for i in range(n)]
    assert packed.to_list() == want


def test_tf_and_header_frames_read_as_mcap_ros2_writes_them():
    """decode_tf and header_frame_id against mcap_ros2's encoder: frames of every length mod 8 (the alignment
    before the doubles), any values; each cut of a message and junk raise ValueError, nothing else."""
    frames = ["", "a", "base_link", "imu_link_12", "/gps_antenna"]
    tfs = [[("/" + p, c, RNG.normal(size=3), RNG.normal(size=4)) for p, c in zip(frames[k:], frames[:len(frames) - k])]
           for k in range(3)]
    objs = [{"transforms": [{"header": {"stamp": {"sec": 1_700_000_000 + i, "nanosec": 5}, "frame_id": p},
                             "child_frame_id": c, "transform": {"translation": dict(zip("xyz", xyz.tolist())),
                                                                "rotation": dict(zip("xyzw", q.tolist()))}}
                            for p, c, xyz, q in tf]} for i, tf in enumerate(tfs)]
    payloads = _mcap_ros2_bytes(m.TFMESSAGE, objs)
    for tf, data in zip(tfs, payloads):
        got = m.decode_tf(data)
        assert [(p, c) for p, c, *_ in got] == [(p, c) for p, c, *_ in tf]
        for (*_, xyz, q), (*_, xyz0, q0) in zip(got, tf):
            np.testing.assert_array_equal(xyz, xyz0)
            np.testing.assert_array_equal(q, q0)
        for cut in range(len(data)):
            with pytest.raises(ValueError):
                m.decode_tf(data[:cut])
    for frame in frames:
        imu = _mcap_ros2_bytes(m.IMU, [{"header": {"frame_id": frame}}])[0]
        assert m.header_frame_id(imu) == m.header_frame_id(m.encode_imu(np.array([T0]), np.zeros((1, 3)), np.zeros(
            (1, 3)), frame_id=frame).to_list()[0]) == frame
    for junk in (b"", b"\x00\x00\x00\x00" + payloads[0][4:], b"\x00\x01\x00\x00" + b"\xff" * 40):
        for decode in (m.decode_tf, m.header_frame_id):
            with pytest.raises(ValueError):
                decode(junk)


def test_raw_bytes_of_many_reads_at_once_equal_each_reads():
    """``encode_raws`` gives ``encode_raw``'s bytes for every read (ports and frame ids of every padding, empty
    reads, stamps before 1970 and past 2038), from a batch and from a slice of one (``Packed[i:j]``)."""
    rng = np.random.default_rng(8)
    for frame_id in ("", "a", "gps", "imu_link", "x" * 13):
        for port in ("daq", "gps", "p", "portname"):
            n = 60
            stamp = rng.integers(-2**40, 2**62, n)
            mono = rng.integers(-2**62, 2**62, n)
            data = [rng.bytes(int(k)) for k in rng.integers(0, 200, n)]
            data[3] = b""
            want = [m.encode_raw(int(a), int(b), port, d, frame_id) for a, b, d in zip(stamp, mono, data)]
            assert m.encode_raws(stamp, mono, port, m.Packed.from_list(data), frame_id).to_list() == want
            piece = m.Packed.from_list(data)[7:40]
            assert m.encode_raws(stamp[7:40], mono[7:40], port, piece, frame_id).to_list() == want[7:40]


def test_prefixed_puts_each_head_in_front_of_its_message():
    rng = np.random.default_rng(2)
    msgs = [rng.bytes(int(k)) for k in rng.integers(0, 50, 40)]
    heads = rng.integers(0, 256, (40, 5), dtype=np.uint8)
    got = m.Packed.from_list(msgs).prefixed(heads).to_list()
    assert got == [h.tobytes() + x for h, x in zip(heads, msgs)]
    assert m.Packed.from_list(msgs)[3:3].prefixed(heads[:0]).to_list() == []


def test_raw_bytes_laid_out_in_one_go_equal_the_field_by_field_writer():
    for frame_id in ("", "a", "gps", "imu_link", "x" * 13):
        for port in ("daq", "gps", "can", "p", "portname"):
            for n in (0, 1, 3, 38, 114):
                data = bytes(range(n))
                for stamp, mono in ((1_700_000_000_999_999_999, 5), (-1, 2**62), (0, -7), (2**31 * 10**9, 1)):
                    want = m._Cdr().header(stamp, frame_id).put("q", mono).string(port).octets(data).bytes()
                    assert m.encode_raw(stamp, mono, port, data, frame_id) == want
                    assert m.decode_raw(want) == (stamp % m.STAMP_END_NS, mono, port, data)
