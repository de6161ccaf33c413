"""Drives as another logger writes them, made by a third-party writer (mcap_ros2's ``Writer``) from a simulated
drive: other topic names, a REP-103 FLU or an FRD IMU, another IMU rate, stamps that jitter and lag their log
times, dropped IMU samples, silent GPS gaps, no velocity topic, an optional /tf_static. The message definitions
are the standard ROS 2 ones, written out here (not taken from fieldlog)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap_ros2.writer import Writer

from fieldlog.drive import reader

TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
VECTOR3 = "float64 x\nfloat64 y\nfloat64 z\n"
QUAT = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
SEP = "=" * 80 + "\n"


def _msgdef(body: str, *deps: tuple[str, str]) -> str:
    return body + "".join(f"{SEP}MSG: {name}\n{text}" for name, text in deps)


IMU_DEF = _msgdef(
    "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
    "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
    "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n",
    ("std_msgs/Header", HEADER), ("builtin_interfaces/Time", TIME), ("geometry_msgs/Quaternion", QUAT),
    ("geometry_msgs/Vector3", VECTOR3))
FIX_DEF = _msgdef(
    "uint8 COVARIANCE_TYPE_UNKNOWN=0\nuint8 COVARIANCE_TYPE_APPROXIMATED=1\nuint8 COVARIANCE_TYPE_DIAGONAL_KNOWN=2\n"
    "uint8 COVARIANCE_TYPE_KNOWN=3\nstd_msgs/Header header\nsensor_msgs/NavSatStatus status\nfloat64 latitude\n"
    "float64 longitude\nfloat64 altitude\nfloat64[9] position_covariance\nuint8 position_covariance_type\n",
    ("std_msgs/Header", HEADER), ("builtin_interfaces/Time", TIME),
    ("sensor_msgs/NavSatStatus", "int8 STATUS_NO_FIX=-1\nint8 STATUS_FIX=0\nint8 status\nuint16 service\n"))
TF_DEF = _msgdef(
    "geometry_msgs/TransformStamped[] transforms\n",
    ("geometry_msgs/TransformStamped", "std_msgs/Header header\nstring child_frame_id\n"
                                       "geometry_msgs/Transform transform\n"),
    ("std_msgs/Header", HEADER), ("builtin_interfaces/Time", TIME),
    ("geometry_msgs/Transform", "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n"),
    ("geometry_msgs/Vector3", VECTOR3), ("geometry_msgs/Quaternion", QUAT))
TWIST = "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n"
ODOM_DEFS = {
    "nav_msgs/msg/Odometry": _msgdef(
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist\n",
        ("std_msgs/Header", HEADER), ("builtin_interfaces/Time", TIME),
        ("geometry_msgs/PoseWithCovariance", "geometry_msgs/Pose pose\nfloat64[36] covariance\n"),
        ("geometry_msgs/Pose", "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n"),
        ("geometry_msgs/Point", VECTOR3), ("geometry_msgs/Quaternion", QUAT),
        ("geometry_msgs/TwistWithCovariance", "geometry_msgs/Twist twist\nfloat64[36] covariance\n"),
        ("geometry_msgs/Twist", TWIST), ("geometry_msgs/Vector3", VECTOR3)),
    "geometry_msgs/msg/TwistStamped": _msgdef(
        "std_msgs/Header header\ngeometry_msgs/Twist twist\n", ("std_msgs/Header", HEADER),
        ("builtin_interfaces/Time", TIME), ("geometry_msgs/Twist", TWIST), ("geometry_msgs/Vector3", VECTOR3)),
}

# C_x_rfu: body RFU -> the logger's frame
TO_FRAME = {"rfu": np.eye(3), "flu": np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]),
            "frd": np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])}
# the IMU frame's orientation in base_link (FLU) as a quaternion x, y, z, w, for /tf_static
TF_QUAT = {"flu": (0.0, 0.0, 0.0, 1.0), "frd": (1.0, 0.0, 0.0, 0.0),
           "rfu": (0.0, 0.0, -np.sqrt(0.5), np.sqrt(0.5))}


@dataclass
class Foreign:
    imu_topic: str = "/sensors/imu"
    fix_topic: str = "/sensors/gnss/fix"
    frame: str = "flu"
    imu_rate_hz: float | None = None  # resample the IMU to this rate (means over each sample's interval)
    silent: tuple[tuple[float, float], ...] = ()  # (start_s, length_s) from the first IMU sample: no fix messages
    drop_every: int = 0  # drop every n-th IMU sample (0: none)
    drop_runs: tuple[tuple[float, int], ...] = ()  # (start_s, n): drop n consecutive IMU samples from start_s
    jitter_ns: int = 0  # IMU stamp jitter (uniform +-), ns
    log_lag_ns: int = 2_000_000  # IMU log time = stamp + this
    fix_lag_s: tuple[float, float] = (0.05, 0.3)  # fix log time = stamp + uniform(this), s
    tf_static: bool = False  # write /tf_static with the IMU frame (and then no frame option is needed)
    imu_frame_id: str = "imu_link"
    imu_at: tuple[float, float, float] = (0.0, 0.0, 0.0)  # /tf_static: IMU and antenna ("gnss") origins in
    antenna_at: tuple[float, float, float] | None = None  # base_link (FLU), m; None: no antenna transform
    max_s: float | None = None  # only the first max_s seconds
    seed: int = 0
    odom_topic: str | None = None  # the native /vehicle/twist's forward speed on this topic (None: none)
    odom_type: str = "nav_msgs/msg/Odometry"  # or geometry_msgs/msg/TwistStamped (no covariance)
    frame_after: tuple[float, str] | None = None  # (start_s, frame): from start_s the IMU in this frame instead


def _stamp(t_ns: int) -> dict:
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def _resample(t: np.ndarray, w: np.ndarray, f: np.ndarray, rate_hz: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The IMU at ``rate_hz`` as an integrating IMU outputs it: each sample the mean rate and specific force over
    the sample period centred on its stamp (the integral's differences), so the noise density is kept whether the
    rate is lower (a point sample of every n-th row would not) or higher than the drive's."""
    period = int(round(1e9 / rate_hz))
    tn = np.arange(t[0] + period, t[-1] - period, period, dtype=np.int64)
    dt = np.diff(t) * 1e-9
    edges = np.concatenate([tn - period // 2, [tn[-1] + period - period // 2]])

    def means(x: np.ndarray) -> np.ndarray:
        integral = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (x[1:] + x[:-1]) * dt[:, None], axis=0)])
        at = np.stack([np.interp(edges, t, integral[:, i]) for i in range(3)], axis=1)
        return np.diff(at, axis=0) / (np.diff(edges)[:, None] * 1e-9)

    return tn, means(w), means(f)


def write_foreign(native: Path, out: Path, spec: Foreign) -> Path:
    """``native`` (a simulated fieldlog drive) rewritten as another logger's drive ``out``; no velocity topic."""
    rng = np.random.default_rng(spec.seed)
    imu = reader.read_topic(native, "/imu")
    fix = reader.read_topic(native, "/gps/fix")
    t, w, f = imu["log_time_ns"], imu["omega_ib_b"], imu["f_b"]
    if spec.max_s:
        n = int(np.searchsorted(t, t[0] + int(spec.max_s * 1e9)))
        t, w, f = t[:n], w[:n], f[:n]
        fix = {k: v[fix["log_time_ns"] < t[-1]] for k, v in fix.items() if isinstance(v, np.ndarray)}
    if spec.imu_rate_hz:
        t, w, f = _resample(t, w, f, spec.imu_rate_hz)
    keep = np.ones(len(t), bool)
    if spec.drop_every:
        keep[spec.drop_every - 1::spec.drop_every] = False
    for start_s, n in spec.drop_runs:
        i = int(np.searchsorted(t, t[0] + int(start_s * 1e9)))
        keep[i:i + n] = False
    C = np.broadcast_to(TO_FRAME[spec.frame], (len(t), 3, 3)).copy()
    if spec.frame_after is not None:  # a logger whose IMU frame changes mid-drive (a wrong frame from then on)
        C[t >= t[0] + int(spec.frame_after[0] * 1e9)] = TO_FRAME[spec.frame_after[1]]
    w, f = np.einsum("nij,nj->ni", C, w), np.einsum("nij,nj->ni", C, f)
    st = t + (rng.integers(-spec.jitter_ns, spec.jitter_ns + 1, len(t)) if spec.jitter_ns else 0)
    t0 = int(t[0])
    with open(out, "wb") as fh:
        wr = Writer(fh)
        s_imu, s_fix = wr.register_msgdef("sensor_msgs/msg/Imu", IMU_DEF), wr.register_msgdef(
            "sensor_msgs/msg/NavSatFix", FIX_DEF)
        if spec.tf_static:
            s_tf = wr.register_msgdef("tf2_msgs/msg/TFMessage", TF_DEF)
            x, y, z, qw = TF_QUAT[spec.frame]
            trs = [(spec.imu_frame_id, spec.imu_at, (x, y, z, qw))]
            if spec.antenna_at is not None:
                trs.append(("gnss", spec.antenna_at, (0.0, 0.0, 0.0, 1.0)))
            msg = {"transforms": [{"header": {"stamp": _stamp(t0), "frame_id": "base_link"}, "child_frame_id": c,
                                   "transform": {"translation": dict(zip("xyz", map(float, at))),
                                                 "rotation": dict(zip("xyzw", map(float, q)))}}
                                  for c, at, q in trs]}
            wr.write_message("/tf_static", s_tf, msg, log_time=t0, publish_time=t0)
        events = [(int(st[i]) + spec.log_lag_ns, 0, i) for i in np.flatnonzero(keep)]
        quiet = [(t0 + int(a * 1e9), t0 + int((a + n) * 1e9)) for a, n in spec.silent]
        for j in range(len(fix["log_time_ns"])):
            tj = int(fix["log_time_ns"][j])
            if not any(a <= tj < b for a, b in quiet):
                events.append((tj + int(rng.uniform(*spec.fix_lag_s) * 1e9), 1, j))
        events.sort()
        odom = None
        if spec.odom_topic:
            s_odom = wr.register_msgdef(spec.odom_type, ODOM_DEFS[spec.odom_type])
            t_od, _, p_od = reader.read_payloads(native, "/vehicle/twist")
            from fieldlog.drive import messages

            odom = messages.decode_twist(p_od)
            events += [(int(odom["stamp_ns"][j]) + 3_000_000, 2, j) for j in range(len(t_od))
                       if spec.max_s is None or odom["stamp_ns"][j] < t[-1]]
            events.sort()
        for log_t, kind, i in events:
            if kind == 2:
                v = {"linear": {"x": float(odom["v_n"][i, 0]), "y": 0.0, "z": 0.0},
                     "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}
                head = {"stamp": _stamp(int(odom["stamp_ns"][i])), "frame_id": "odom"}
                if spec.odom_type == "nav_msgs/msg/Odometry":
                    cov = [float(odom["covariance"][i, 0])] + [0.0] * 35
                    msg = {"header": head, "child_frame_id": "base_link",
                           "pose": {"pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                             "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                                    "covariance": [0.0] * 36},
                           "twist": {"twist": v, "covariance": cov}}
                else:
                    msg = {"header": {**head, "frame_id": "base_link"}, "twist": v}
                wr.write_message(spec.odom_topic, s_odom, msg, log_time=log_t, publish_time=log_t)
            elif kind == 0:
                msg = {"header": {"stamp": _stamp(int(st[i])), "frame_id": spec.imu_frame_id},
                       "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                       "orientation_covariance": [-1.0] + [0.0] * 8,
                       "angular_velocity": dict(zip("xyz", map(float, w[i]))), "angular_velocity_covariance": [0.0] * 9,
                       "linear_acceleration": dict(zip("xyz", map(float, f[i]))),
                       "linear_acceleration_covariance": [0.0] * 9}
                wr.write_message(spec.imu_topic, s_imu, msg, log_time=log_t, publish_time=log_t)
            else:
                tj = int(fix["log_time_ns"][i])
                msg = {"header": {"stamp": _stamp(tj), "frame_id": "gnss"},
                       "status": {"status": int(fix["status"][i]), "service": 1},
                       "latitude": float(fix["lat_deg"][i]), "longitude": float(fix["lon_deg"][i]),
                       "altitude": float(fix["alt_m"][i]),
                       "position_covariance": [float(x) for x in fix["position_covariance"][i]],
                       "position_covariance_type": 2}
                wr.write_message(spec.fix_topic, s_fix, msg, log_time=log_t, publish_time=log_t)
        wr.finish()
    return out
