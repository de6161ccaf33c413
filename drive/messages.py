"""The fieldlog data model: ROS 2 message types as CDR bytes, with vectorised encode/decode.

Every message is little-endian CDR (encapsulation header ``00 01 00 00``) exactly as
``mcap-ros2-support`` writes it, stored in MCAP with schema encoding ``ros2msg`` and message
encoding ``cdr``, so rerun, Foxglove and ROS 2 tools read the files as they are.

Fixed-layout types (every field has a fixed size once ``frame_id`` and other per-call strings are
fixed) are built for a whole batch at once through a numpy structured dtype with explicit byte
offsets. A batch is a :class:`Packed`: one contiguous ``uint8`` buffer plus ``n + 1`` offsets.
Variable-length types (NMEA sentences, raw bytes, outages) are low rate and encoded per message; raw bytes of
many reads also at once (``encode_raws``), for the offline writers' blocks of DAQ reads.

Times: stamps are int64 UTC ns since the Unix epoch, split into ``sec`` (floor) and ``nanosec`` (uint32,
0..999_999_999) as ``builtin_interfaces/Time`` requires. Its ``sec`` field is 32 bits wide (``int32``); it holds
the low 32 bits of the seconds and is read back unsigned, so every time from 1970 to 2106-02-07 (``STAMP_END_NS``)
comes back whole, past 2038 included, and a time before 2038 is laid out exactly as an ``int32`` would have it.
The GPS decoders refuse times past that (``acquire.gnss``); the MCAP ``log_time`` is 64 bits anyway.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from functools import lru_cache, wraps
from typing import Any, Callable, Collection, Iterator, Sequence

import numpy as np
from mcap.records import Schema
from mcap.well_known import MessageEncoding, SchemaEncoding

from fieldlog.drive import native

CDR_LE_HEADER = b"\x00\x01\x00\x00"
STAMP_END_NS = 2**32 * 1_000_000_000      # the first time a header stamp cannot carry (2106-02-07T06:28:16Z)
SCHEMA_ENCODING = SchemaEncoding.ROS2  # "ros2msg"
MESSAGE_ENCODING = MessageEncoding.CDR  # "cdr"

# ---------------------------------------------------------------------------------------------
# Message definitions (ros2msg text). Keys are full type names; references inside use pkg/Name.

MSG_DEFS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
    "geometry_msgs/msg/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/msg/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    "geometry_msgs/msg/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    "geometry_msgs/msg/TwistWithCovarianceStamped": (
        "std_msgs/Header header\ngeometry_msgs/TwistWithCovariance twist\n"
    ),
    "geometry_msgs/msg/TwistStamped": "std_msgs/Header header\ngeometry_msgs/Twist twist\n",
    "geometry_msgs/msg/QuaternionStamped": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion quaternion\n"
    ),
    "geometry_msgs/msg/Vector3Stamped": "std_msgs/Header header\ngeometry_msgs/Vector3 vector\n",
    "geometry_msgs/msg/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
    ),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\n"
        "string child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist\n"
    ),
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\n"
        "float64[9] linear_acceleration_covariance\n"
    ),
    "sensor_msgs/msg/NavSatStatus": (
        "int8 STATUS_UNKNOWN=-2\n"
        "int8 STATUS_NO_FIX=-1\n"
        "int8 STATUS_FIX=0\n"
        "int8 STATUS_SBAS_FIX=1\n"
        "int8 STATUS_GBAS_FIX=2\n"
        "uint16 SERVICE_UNKNOWN=0\n"
        "uint16 SERVICE_GPS=1\n"
        "uint16 SERVICE_GLONASS=2\n"
        "uint16 SERVICE_COMPASS=4\n"
        "uint16 SERVICE_GALILEO=8\n"
        "int8 status\n"
        "uint16 service\n"
    ),
    "sensor_msgs/msg/NavSatFix": (
        "uint8 COVARIANCE_TYPE_UNKNOWN=0\n"
        "uint8 COVARIANCE_TYPE_APPROXIMATED=1\n"
        "uint8 COVARIANCE_TYPE_DIAGONAL_KNOWN=2\n"
        "uint8 COVARIANCE_TYPE_KNOWN=3\n"
        "std_msgs/Header header\n"
        "sensor_msgs/NavSatStatus status\n"
        "float64 latitude\n"
        "float64 longitude\n"
        "float64 altitude\n"
        "float64[9] position_covariance\n"
        "uint8 position_covariance_type\n"
    ),
    "sensor_msgs/msg/TimeReference": (
        "std_msgs/Header header\nbuiltin_interfaces/Time time_ref\nstring source\n"
    ),
    "nmea_msgs/msg/Sentence": "std_msgs/Header header\nstring sentence\n",
    # fieldlog's own types: the same text as fieldlog_msgs/msg/*.msg without comments (tests/test_ros_profile.py)
    "fieldlog_msgs/msg/TimeSyncState": (
        "uint8 FREE=0\n"
        "uint8 HOLDOVER=1\n"
        "uint8 LOCKED=2\n"
        "std_msgs/Header header\n"
        "uint8 state\n"
        "float64 rate_ppm\n"
        "float64 residual_us\n"
        "uint32 edges_used\n"
        "uint32 edges_rejected\n"
    ),
    "fieldlog_msgs/msg/RawBytes": (
        "std_msgs/Header header\nint64 mono_ns\nstring port\nuint8[] data\n"
    ),
    "fieldlog_msgs/msg/Outage": (
        "std_msgs/Header header\nint64 start_ns\nint64 end_ns\nstring reason\n"
    ),
    "fieldlog_msgs/msg/WheelSpeeds": (
        "std_msgs/Header header\n"
        "uint32 can_id\n"
        "float64[4] wheel_speed\n"
        "float64 vehicle_speed\n"
        "float64 steering_angle\n"
        "int8 reverse\n"
        "string[] names\n"
        "float64[] values\n"
    ),
    "fieldlog_msgs/msg/SolutionStatus": (
        "uint8 ALIGNING=0\n"
        "uint8 ALIGNED=1\n"
        "uint8 AIDED=2\n"
        "uint8 COASTING=3\n"
        "uint8 DEGRADED=4\n"
        "uint8 DIVERGED=5\n"
        "std_msgs/Header header\n"
        "uint8 status\n"
        "float64 since_update_s\n"
        "float64 sigma_h_m\n"
        "float64 nis\n"
    ),
}

_SEPARATOR = "=" * 80


def _full_name(ref: str) -> str:
    pkg, name = ref.split("/")[0], ref.split("/")[-1]
    return f"{pkg}/msg/{name}"


def _deps(type_name: str) -> list[str]:
    """All message types used by ``type_name``, depth first, each once."""
    out: list[str] = []

    def visit(t: str) -> None:
        for line in MSG_DEFS[t].splitlines():
            ftype = re.split(r"[\s\[]", line.strip(), maxsplit=1)[0]
            if "/" in ftype:
                dep = _full_name(ftype)
                if dep not in out:
                    out.append(dep)
                    visit(dep)

    visit(type_name)
    return out


@lru_cache(maxsize=None)
def schema_text(type_name: str) -> str:
    """Concatenated ros2msg definition (as rosbag2 / mcap_ros2 expect) for ``type_name``.

    Parameters
    ----------
    type_name : a registered type, e.g. "sensor_msgs/msg/Imu"

    Returns
    -------
    str : its definition and those of the types it uses
    """
    parts = [MSG_DEFS[type_name]]
    for dep in _deps(type_name):
        pkg, _, name = dep.split("/")
        parts.append(f"{_SEPARATOR}\nMSG: {pkg}/{name}\n{MSG_DEFS[dep]}")
    return "".join(parts)


# ---------------------------------------------------------------------------------------------
# Topic registry (contract topic names -> type names).

IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
TWIST = "geometry_msgs/msg/TwistWithCovarianceStamped"
QUATERNION = "geometry_msgs/msg/QuaternionStamped"
VECTOR3 = "geometry_msgs/msg/Vector3Stamped"
SENTENCE = "nmea_msgs/msg/Sentence"
TIMEREF = "sensor_msgs/msg/TimeReference"
TIMESYNC = "fieldlog_msgs/msg/TimeSyncState"
RAWBYTES = "fieldlog_msgs/msg/RawBytes"
OUTAGE = "fieldlog_msgs/msg/Outage"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
ODOMETRY = "nav_msgs/msg/Odometry"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
WHEELSPEEDS = "fieldlog_msgs/msg/WheelSpeeds"
SOLUTION_STATUS = "fieldlog_msgs/msg/SolutionStatus"

TOPICS: dict[str, str] = {
    "/raw/daq": RAWBYTES,
    "/raw/gps": RAWBYTES,
    "/raw/can": RAWBYTES,
    "/imu": IMU,
    "/gps/fix": NAVSATFIX,
    "/gps/vel": TWIST,
    "/gps/nmea": SENTENCE,
    "/pps": TIMEREF,
    "/time/sync": TIMESYNC,
    "/truth/imu": IMU,
    "/truth/fix": NAVSATFIX,
    "/truth/vel": TWIST,
    "/truth/attitude": QUATERNION,
    "/truth/imu_bias": IMU,
    "/truth/vehicle/twist": TWIST,
    "/vehicle/twist": TWIST,
    "/vehicle/wheel_speeds": WHEELSPEEDS,
    "/fusion/outage": OUTAGE,
    "/tf_static": TFMESSAGE,
    "/tf": TFMESSAGE,
}
# Receiver messages other than NMEA (UBX, NovAtel OEM ASCII/binary): one checked frame per message, as read;
# RawBytes with port = "<protocol>:<message>", e.g. "ubx:NAV-PVT", "novatel:BESTPOS" (docs/data-model.md).
TOPICS["/gps/receiver"] = RAWBYTES
FUSION_SUBTOPICS: dict[str, str] = {
    "fix": NAVSATFIX,
    "vel": TWIST,
    "attitude": QUATERNION,
    "std": VECTOR3,
    "odom": ODOMETRY,
    "attitude_std": VECTOR3,
    "imu_bias": IMU,
    "datum": NAVSATFIX,
    "status": SOLUTION_STATUS,
}
_FUSION_RE = re.compile(rf"^/fusion/([A-Za-z0-9_-]+)/(?:kf[12]/(fix|vel)|({'|'.join(FUSION_SUBTOPICS)}))$")


def topic_type(topic: str) -> str:
    """Type name of a contract topic, including ``/fusion/<method>/{fix,vel,attitude,std,attitude_std,odom,imu_bias,
    datum,status}``
    and the distributed filter's local solutions ``/fusion/<method>/kf{1,2}/{fix,vel}``.

    Raises KeyError for a topic outside the contract.

    Parameters
    ----------
    topic : a topic name

    Returns
    -------
    str : its type name
    """
    if topic in TOPICS:
        return TOPICS[topic]
    m = _FUSION_RE.match(topic)
    if m is None:
        raise KeyError(f"not a fieldlog topic: {topic!r}")
    return FUSION_SUBTOPICS[m.group(2) or m.group(3)]


# QoS offered by the "publisher" of each topic, as rosbag2 (Jazzy, metadata version 9) records it in the
# channel's ``offered_qos_profiles``: what `ros2 bag play` offers again. /tf_static and the map datum
# (/fusion/<method>/datum) are latched (transient local), so a node that starts after their one message still
# gets it.
_INFINITE = "\n    sec: 9223372036\n    nsec: 854775807"


@lru_cache(maxsize=None)
def offered_qos_profiles(topic: str) -> str:
    """The YAML text rosbag2 writes for one publisher of ``topic`` (reliable; volatile except the latched
    /tf_static and /fusion/<method>/datum).

    Parameters
    ----------
    topic : a topic name

    Returns
    -------
    str : the YAML text
    """
    latched = topic == "/tf_static" or (topic.startswith("/fusion/") and topic.endswith("/datum"))
    durability = "transient_local" if latched else "volatile"
    history, depth = ("keep_last", 1) if latched else ("unknown", 0)
    return (f"- history: {history}\n  depth: {depth}\n  reliability: reliable\n  durability: {durability}\n"
            f"  deadline:{_INFINITE}\n  lifespan:{_INFINITE}\n  liveliness: automatic\n"
            f"  liveliness_lease_duration:{_INFINITE}\n  avoid_ros_namespace_conventions: false")


# ---------------------------------------------------------------------------------------------
# Packed batches


@dataclass(frozen=True)
class Packed:
    """A batch of serialised messages: message i is ``buf[offsets[i]:offsets[i+1]]``."""

    buf: np.ndarray  # uint8, contiguous
    offsets: np.ndarray  # int64, shape (n + 1,)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, i: int | slice) -> "bytes | Packed":
        """Message ``i``, or messages ``i`` as a batch sharing this one's buffer (a slice of step 1)."""
        if isinstance(i, slice):
            lo, hi, step = i.indices(len(self))
            if step != 1:
                raise ValueError("a Packed slice takes every message")
            return Packed(self.buf, self.offsets[lo : max(hi, lo) + 1])
        return self.buf[self.offsets[i] : self.offsets[i + 1]].tobytes()

    def __iter__(self) -> Iterator[bytes]:
        raw = self.buf.tobytes()
        o = self.offsets.tolist()
        return (raw[o[i] : o[i + 1]] for i in range(len(o) - 1))

    def to_list(self) -> list[bytes]:
        """The messages as a list of bytes.

        Returns
        -------
        list[bytes]
        """
        return list(self)

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.offsets)

    def width(self) -> int | None:
        """The common message length, or None when lengths differ (or the batch is empty).

        Returns
        -------
        int | None : bytes
        """
        lens = self.lengths
        if len(lens) == 0 or not np.all(lens == lens[0]):
            return None
        return int(lens[0])

    def matrix(self) -> np.ndarray:
        """(n, width) uint8 view of a batch of equal-length messages.

        Returns
        -------
        (n, width) uint8 array; ValueError when lengths differ
        """
        w = self.width()
        if w is None:
            raise ValueError("messages differ in length")
        return self.buf[self.offsets[0] : self.offsets[-1]].reshape(len(self), w)

    def take(self, idx: np.ndarray) -> "Packed":
        """Messages ``idx`` (any order) as a new batch: one vectorised byte gather, no per-message Python.

        Parameters
        ----------
        idx : (k,) message indexes

        Returns
        -------
        Packed : k messages
        """
        idx = np.asarray(idx, dtype=np.int64)
        if self.width() is not None:
            return Packed.from_matrix(self.matrix()[idx])
        lens = self.lengths[idx]
        offsets = np.zeros(len(idx) + 1, dtype=np.int64)
        np.cumsum(lens, out=offsets[1:])
        # byte j of output message i comes from buf[offsets_in[idx[i]] + j]
        src = np.repeat(self.offsets[idx] - offsets[:-1], lens) + np.arange(offsets[-1], dtype=np.int64)
        return Packed(self.buf[src], offsets)

    def prefixed(self, heads: np.ndarray) -> "Packed":
        """Each message with ``heads[i]`` in front of it, as a new batch, laid out by one compiled loop of two
        copies a message (drive/_chunks.c): no per-message Python.

        Parameters
        ----------
        heads : (n, k) uint8, one head a message

        Returns
        -------
        Packed : n messages, each k bytes longer
        """
        n, k = heads.shape
        heads = np.ascontiguousarray(heads, np.uint8)
        src = np.ascontiguousarray(self.buf)
        offsets = np.ascontiguousarray(self.offsets, np.int64)
        out = np.empty(int(offsets[-1] - offsets[0]) + n * k, np.uint8)
        native.library("fieldlog.drive._chunks", native.CHUNKS).fieldlog_prefix(
            n, k, heads.ctypes.data, src.ctypes.data, offsets.ctypes.data, out.ctypes.data)
        return Packed(out, offsets - offsets[0] + k * np.arange(n + 1, dtype=np.int64))

    @classmethod
    def from_matrix(cls, mat: np.ndarray) -> "Packed":
        """A batch of equal-length messages, one per row of ``mat``.

        Parameters
        ----------
        mat : (n, width) uint8

        Returns
        -------
        Packed : n messages
        """
        n, w = mat.shape
        return cls(np.ascontiguousarray(mat).reshape(-1), np.arange(n + 1, dtype=np.int64) * w)

    @classmethod
    def from_list(cls, msgs: Sequence[bytes]) -> "Packed":
        """A batch of the messages ``msgs``, joined.

        Parameters
        ----------
        msgs : the messages

        Returns
        -------
        Packed : len(msgs) messages
        """
        lens = np.fromiter((len(m) for m in msgs), dtype=np.int64, count=len(msgs))
        offsets = np.zeros(len(msgs) + 1, dtype=np.int64)
        np.cumsum(lens, out=offsets[1:])
        return cls(np.frombuffer(b"".join(msgs), dtype=np.uint8), offsets)


def as_packed(msgs: "Packed | Sequence[bytes]") -> Packed:
    """``msgs`` as a ``Packed`` batch (a Packed as it is, a list joined).

    Parameters
    ----------
    msgs : the messages

    Returns
    -------
    Packed : the batch
    """
    return msgs if isinstance(msgs, Packed) else Packed.from_list(msgs)


# ---------------------------------------------------------------------------------------------
# Fixed layouts: structured dtypes with explicit CDR offsets.

# A field is (name, numpy base format, shape) or (name, "string", None); strings are fixed per
# layout, so each layout is keyed by the string lengths it holds.
_Field = tuple[str, str, tuple[int, ...] | None]

_HEADER: list[_Field] = [("sec", "<i4", ()), ("nanosec", "<u4", ()), ("frame_id", "string", None)]

_FIELDS: dict[str, list[_Field]] = {
    IMU: _HEADER
    + [
        ("orientation", "<f8", (4,)),
        ("orientation_covariance", "<f8", (9,)),
        ("angular_velocity", "<f8", (3,)),
        ("angular_velocity_covariance", "<f8", (9,)),
        ("linear_acceleration", "<f8", (3,)),
        ("linear_acceleration_covariance", "<f8", (9,)),
    ],
    NAVSATFIX: _HEADER
    + [
        ("status", "<i1", ()),
        ("service", "<u2", ()),
        ("latitude", "<f8", ()),
        ("longitude", "<f8", ()),
        ("altitude", "<f8", ()),
        ("position_covariance", "<f8", (9,)),
        ("position_covariance_type", "<u1", ()),
    ],
    TWIST: _HEADER
    + [("linear", "<f8", (3,)), ("angular", "<f8", (3,)), ("covariance", "<f8", (36,))],
    QUATERNION: _HEADER + [("quaternion", "<f8", (4,))],
    ODOMETRY: _HEADER
    + [
        ("child_frame_id", "string", None),
        ("position", "<f8", (3,)),
        ("orientation", "<f8", (4,)),
        ("pose_covariance", "<f8", (36,)),
        ("linear", "<f8", (3,)),
        ("angular", "<f8", (3,)),
        ("twist_covariance", "<f8", (36,)),
    ],
    VECTOR3: _HEADER + [("vector", "<f8", (3,))],
    TIMEREF: _HEADER
    + [("ref_sec", "<i4", ()), ("ref_nanosec", "<u4", ()), ("source", "string", None)],
    TIMESYNC: _HEADER
    + [
        ("state", "<u1", ()),
        ("rate_ppm", "<f8", ()),
        ("residual_us", "<f8", ()),
        ("edges_used", "<u4", ()),
        ("edges_rejected", "<u4", ()),
    ],
    SOLUTION_STATUS: _HEADER
    + [("status", "<u1", ()), ("since_update_s", "<f8", ()), ("sigma_h_m", "<f8", ()), ("nis", "<f8", ())],
}


def _layout(type_name: str, string_lengths: tuple[int, ...]) -> np.dtype:
    """Structured dtype for one fixed layout; ``string_lengths`` are byte lengths without NUL.

    String ``s`` becomes fields ``s_len`` (uint32, length incl. NUL) and ``s`` (bytes incl. NUL).
    """
    return _dtype(tuple(_FIELDS[type_name]), string_lengths)


@lru_cache(maxsize=256)
def _dtype(fields: tuple[_Field, ...], string_lengths: tuple[int, ...]) -> np.dtype:
    """``_layout`` of a field list."""
    names, formats, offsets = ["enc"], [np.dtype(("u1", (4,)))], [0]
    pos = 0  # CDR alignment counts from the end of the encapsulation header
    strings = iter(string_lengths)
    for name, fmt, shape in fields:
        if fmt == "string":
            pos = -(-pos // 4) * 4
            names += [name + "_len", name]
            length = next(strings) + 1
            formats += [np.dtype("<u4"), np.dtype(f"S{length}")]
            offsets += [4 + pos, 8 + pos]
            pos += 4 + length
        else:
            base = np.dtype(fmt)
            pos = -(-pos // base.itemsize) * base.itemsize
            names.append(name)
            formats.append(np.dtype((base, shape)) if shape else base)
            offsets.append(4 + pos)
            pos += base.itemsize * int(np.prod(shape or (1,)))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": 4 + pos})


def split_stamp(stamp_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """int64 ns -> (sec: the low 32 bits of the floor seconds, as int32; nanosec uint32 in [0, 1e9)).

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns

    Returns
    -------
    sec, nanosec : (n,) int32 and uint32
    """
    stamp_ns = np.asarray(stamp_ns, dtype=np.int64)
    sec, nsec = np.divmod(stamp_ns, 1_000_000_000)
    return sec.astype(np.int32), nsec.astype(np.uint32)


def join_stamp(sec: np.ndarray, nanosec: np.ndarray) -> np.ndarray:
    """The inverse of ``split_stamp``: int64 ns from ``sec`` read unsigned (1970 to 2106) and ``nanosec``.

    Parameters
    ----------
    sec, nanosec : (n,) header stamp fields

    Returns
    -------
    (n,) int64 UTC ns
    """
    return (np.asarray(sec).astype(np.int64) & 0xFFFFFFFF) * 1_000_000_000 + np.asarray(nanosec, dtype=np.int64)


def _new(type_name: str, n: int, strings: dict[str, str], stamp_ns: np.ndarray) -> np.ndarray:
    enc = {k: v.encode() for k, v in strings.items()}
    dt = _layout(type_name, tuple(len(b) for b in enc.values()))
    arr = np.zeros(n, dtype=dt)
    arr["enc"] = np.frombuffer(CDR_LE_HEADER, dtype=np.uint8)
    for name, b in enc.items():
        arr[name + "_len"] = len(b) + 1
        arr[name] = b
    arr["sec"], arr["nanosec"] = split_stamp(stamp_ns)
    return arr


def _pack(arr: np.ndarray) -> Packed:
    return Packed(arr.view(np.uint8).reshape(-1), np.arange(len(arr) + 1, dtype=np.int64) * arr.dtype.itemsize)


def _cov(cov: np.ndarray | None, n: int, size: int) -> np.ndarray:
    if cov is None:
        return np.zeros((n, size))
    cov = np.asarray(cov, dtype=np.float64).reshape(-1, size)
    return np.broadcast_to(cov, (n, size))


# ---------------------------------------------------------------------------------------------
# Vectorised encoders


def encode_imu(
    stamp_ns: np.ndarray,
    omega_ib_b: np.ndarray,
    f_b: np.ndarray,
    gyro_cov: np.ndarray | None = None,
    accel_cov: np.ndarray | None = None,
    orientation_xyzw: np.ndarray | None = None,
    frame_id: str = "imu",
) -> Packed:
    """``sensor_msgs/msg/Imu`` batch.

    stamp_ns (n,) int64 UTC ns; omega_ib_b (n,3) rad/s and f_b (n,3) m/s^2 in the body frame
    (right-forward-up); gyro_cov / accel_cov (9,) or (n,9) row-major 3x3 in (rad/s)^2, (m/s^2)^2.
    orientation_xyzw (n,4) body->ENU quaternion; None -> orientation_covariance[0] = -1
    ("orientation unknown", as REP 145 says).

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    omega_ib_b : (n, 3) angular rate, rad/s, body RFU
    f_b : (n, 3) specific force, m/s^2, body RFU
    gyro_cov, accel_cov : (9,) or (n, 9) covariances, (rad/s)^2 and (m/s^2)^2 (None: zeros)
    orientation_xyzw : (n, 4) quaternion body -> ENU (None: unknown)
    frame_id : the IMU's frame

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    n = len(stamp_ns)
    arr = _new(IMU, n, {"frame_id": frame_id}, stamp_ns)
    arr["angular_velocity"] = omega_ib_b
    arr["linear_acceleration"] = f_b
    arr["angular_velocity_covariance"] = _cov(gyro_cov, n, 9)
    arr["linear_acceleration_covariance"] = _cov(accel_cov, n, 9)
    if orientation_xyzw is None:
        arr["orientation_covariance"][:, 0] = -1.0
    else:
        arr["orientation"] = orientation_xyzw
    return _pack(arr)


def encode_navsatfix(
    stamp_ns: np.ndarray,
    lat_deg: np.ndarray,
    lon_deg: np.ndarray,
    alt_m: np.ndarray,
    position_covariance: np.ndarray | None = None,
    covariance_type: int | np.ndarray = 2,
    status: int | np.ndarray = 0,
    service: int | np.ndarray = 1,
    frame_id: str = "gps_antenna",
) -> Packed:
    """``sensor_msgs/msg/NavSatFix`` batch.

    Latitude/longitude in degrees, altitude in metres above the WGS-84 ellipsoid;
    position_covariance (9,) or (n,9) ENU in m^2; covariance_type 0..3 (2 = diagonal known);
    status -1 no fix, 0 fix, 1 SBAS, 2 GBAS; service bit mask (1 = GPS).

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    lat_deg, lon_deg : (n,) geodetic latitude and longitude, deg
    alt_m : (n,) height above the WGS-84 ellipsoid, m
    position_covariance : (9,) or (n, 9) ENU, m^2 (None: zeros)
    covariance_type : 0..3, scalar or (n,)
    status : NavSatStatus status, scalar or (n,)
    service : NavSatStatus service bit mask, scalar or (n,)
    frame_id : the antenna's frame

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    n = len(stamp_ns)
    arr = _new(NAVSATFIX, n, {"frame_id": frame_id}, stamp_ns)
    arr["status"], arr["service"] = status, service
    arr["latitude"], arr["longitude"], arr["altitude"] = lat_deg, lon_deg, alt_m
    arr["position_covariance"] = _cov(position_covariance, n, 9)
    arr["position_covariance_type"] = covariance_type
    return _pack(arr)


def encode_twist(
    stamp_ns: np.ndarray,
    v_n: np.ndarray,
    omega: np.ndarray | None = None,
    covariance: np.ndarray | None = None,
    frame_id: str = "map",
) -> Packed:
    """``geometry_msgs/msg/TwistWithCovarianceStamped`` batch.

    v_n (n,3) ENU velocity in m/s; omega (n,3) rad/s (zeros if None); covariance (36,) or (n,36)
    row-major 6x6 over (vE, vN, vU, wx, wy, wz).

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    v_n : (n, 3) velocity, m/s, in ``frame_id``'s axes (ENU for "map")
    omega : (n, 3) angular rate, rad/s (None: zeros)
    covariance : (36,) or (n, 36) (None: zeros)
    frame_id : the twist's frame

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    n = len(stamp_ns)
    arr = _new(TWIST, n, {"frame_id": frame_id}, stamp_ns)
    arr["linear"] = v_n
    if omega is not None:
        arr["angular"] = omega
    arr["covariance"] = _cov(covariance, n, 36)
    return _pack(arr)


def encode_quaternion(stamp_ns: np.ndarray, q_xyzw: np.ndarray, frame_id: str = "map") -> Packed:
    """``geometry_msgs/msg/QuaternionStamped`` batch: q_xyzw (n,4) rotation body -> ENU (C_bn).

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    q_xyzw : (n, 4) quaternion body -> ENU
    frame_id : the frame it rotates into

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    arr = _new(QUATERNION, len(stamp_ns), {"frame_id": frame_id}, stamp_ns)
    arr["quaternion"] = q_xyzw
    return _pack(arr)


def encode_vector3(stamp_ns: np.ndarray, xyz: np.ndarray, frame_id: str = "map") -> Packed:
    """``geometry_msgs/msg/Vector3Stamped`` batch; xyz (n,3), units set by the topic.

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    xyz : (n, 3) vectors, in the topic's units
    frame_id : their frame

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    arr = _new(VECTOR3, len(stamp_ns), {"frame_id": frame_id}, stamp_ns)
    arr["vector"] = xyz
    return _pack(arr)


def encode_odometry(
    stamp_ns: np.ndarray,
    position: np.ndarray,
    orientation_xyzw: np.ndarray,
    pose_covariance: np.ndarray,
    linear: np.ndarray,
    angular: np.ndarray,
    twist_covariance: np.ndarray,
    frame_id: str = "map",
    child_frame_id: str = "base_link",
) -> Packed:
    """``nav_msgs/msg/Odometry`` batch (REP-105): pose of ``child_frame_id`` in ``frame_id`` (position (n,3) m,
    orientation (n,4) x, y, z, w of child -> frame), twist in ``child_frame_id`` (linear (n,3) m/s, angular (n,3)
    rad/s); covariances (36,) or (n,36), row-major 6x6 over (x, y, z, rotation about x, y, z), m^2, rad^2.

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    position : (n, 3) m, in ``frame_id``
    orientation_xyzw : (n, 4) quaternion child -> frame
    pose_covariance, twist_covariance : (36,) or (n, 36), m^2 and rad^2 (twist: (m/s)^2, (rad/s)^2)
    linear : (n, 3) m/s, in ``child_frame_id``
    angular : (n, 3) rad/s, in ``child_frame_id``
    frame_id, child_frame_id : the REP-105 frames

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    n = len(stamp_ns)
    arr = _new(ODOMETRY, n, {"frame_id": frame_id, "child_frame_id": child_frame_id}, stamp_ns)
    arr["position"], arr["orientation"] = position, orientation_xyzw
    arr["linear"], arr["angular"] = linear, angular
    arr["pose_covariance"] = _cov(pose_covariance, n, 36)
    arr["twist_covariance"] = _cov(twist_covariance, n, 36)
    return _pack(arr)


def encode_time_reference(
    stamp_ns: np.ndarray, time_ref_ns: np.ndarray, source: str = "pps", frame_id: str = "imu"
) -> Packed:
    """``sensor_msgs/msg/TimeReference`` batch (``/pps``): stamp = the edge in UTC ns (the GPS second it marks,
    or the host's estimate for an edge that could not be labelled), time_ref = the edge on the DAQ clock
    (k_edge / fs, ns).

    Parameters
    ----------
    stamp_ns : (n,) int64 the edges, UTC ns
    time_ref_ns : (n,) int64 the edges on the DAQ clock, ns
    source : the reference's name
    frame_id : the header's frame

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    arr = _new(TIMEREF, len(stamp_ns), {"frame_id": frame_id, "source": source}, stamp_ns)
    arr["ref_sec"], arr["ref_nanosec"] = split_stamp(time_ref_ns)
    return _pack(arr)


def encode_time_sync(
    stamp_ns: np.ndarray,
    state: np.ndarray,
    rate_ppm: np.ndarray,
    residual_us: np.ndarray,
    edges_used: np.ndarray,
    edges_rejected: np.ndarray,
    frame_id: str = "imu",
) -> Packed:
    """``fieldlog_msgs/msg/TimeSyncState`` batch; state FREE=0, HOLDOVER=1, LOCKED=2;
    rate_ppm = DAQ oscillator rate error (ppm); residual_us = fit residual RMS (µs).

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    state : (n,) FREE=0, HOLDOVER=1, LOCKED=2
    rate_ppm : (n,) DAQ oscillator rate error, ppm
    residual_us : (n,) µs, the fit's residual RMS
    edges_used, edges_rejected : (n,) PPS edge counts
    frame_id : the header's frame

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    arr = _new(TIMESYNC, len(stamp_ns), {"frame_id": frame_id}, stamp_ns)
    arr["state"], arr["rate_ppm"], arr["residual_us"] = state, rate_ppm, residual_us
    arr["edges_used"], arr["edges_rejected"] = edges_used, edges_rejected
    return _pack(arr)


def encode_solution_status(stamp_ns: np.ndarray, status: np.ndarray, since_update_s: np.ndarray,
                           sigma_h_m: np.ndarray, nis: np.ndarray, frame_id: str = "imu") -> Packed:
    """``fieldlog_msgs/msg/SolutionStatus`` batch: status ALIGNING=0 .. DIVERGED=5 (``fusion.output.STATUS``);
    since_update_s (s) from the last GNSS update, sigma_h_m (m) the horizontal position sigma, nis the mean
    normalised innovation square per degree of freedom of the last updates (NaN where not known).

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    status : (n,) ALIGNING=0 .. DIVERGED=5
    since_update_s : (n,) time since the last GNSS update, s
    sigma_h_m : (n,) horizontal position sigma, m
    nis : (n,) mean NIS per degree of freedom (NaN: not known)
    frame_id : the header's frame

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns)
    arr = _new(SOLUTION_STATUS, len(stamp_ns), {"frame_id": frame_id}, stamp_ns)
    arr["status"], arr["since_update_s"], arr["sigma_h_m"], arr["nis"] = status, since_update_s, sigma_h_m, nis
    return _pack(arr)


TIMESYNC_FREE, TIMESYNC_HOLDOVER, TIMESYNC_LOCKED = 0, 1, 2
COVARIANCE_TYPE_UNKNOWN, COVARIANCE_TYPE_APPROXIMATED, COVARIANCE_TYPE_DIAGONAL_KNOWN = 0, 1, 2
# Unknown covariance, one rule (docs/data-model.md, "Covariances"): where the message definition gives a marker
# it is used (sensor_msgs/Imu: -1 in element 0 of a block without an estimate, REP-145; NavSatFix:
# position_covariance_type UNKNOWN); the others (TwistWithCovariance, PoseWithCovariance, Odometry) define none,
# so a component not measured or not estimated has this variance on its diagonal (its unit squared: (m/s)^2,
# (rad/s)^2, m^2, rad^2) and no correlation. Readers treat any variance above ~1e2 as "no information".
UNKNOWN_VARIANCE = 1e6
STATUS_UNKNOWN, STATUS_NO_FIX, STATUS_FIX, STATUS_SBAS_FIX, STATUS_GBAS_FIX = -2, -1, 0, 1, 2


def fix_status(gga_quality: int) -> int:
    """NMEA GGA fix quality -> NavSatFix status: 0 none, 1 GPS, 2 DGPS/SBAS, 4/5 RTK (ground based).

    Parameters
    ----------
    gga_quality : GGA fix quality, 0..9

    Returns
    -------
    int : NavSatStatus status (-1: no fix)
    """
    return {0: STATUS_NO_FIX, 2: STATUS_SBAS_FIX, 4: STATUS_GBAS_FIX, 5: STATUS_GBAS_FIX}.get(gga_quality,
                                                                                               STATUS_FIX)

# ---------------------------------------------------------------------------------------------
# Per-message encoders for variable-length types


class _Cdr:
    """Minimal little-endian CDR writer for the few variable-length types."""

    def __init__(self) -> None:
        self.parts = [CDR_LE_HEADER]
        self.pos = 0

    def _align(self, size: int) -> None:
        pad = -self.pos % size
        if pad:
            self.parts.append(b"\x00" * pad)
            self.pos += pad

    def put(self, fmt: str, *values: Any) -> "_Cdr":
        self._align(struct.calcsize("<" + fmt[0]))
        b = struct.pack("<" + fmt, *values)
        self.parts.append(b)
        self.pos += len(b)
        return self

    def string(self, s: str) -> "_Cdr":
        b = s.encode() + b"\x00"
        self.put("I", len(b))
        self.parts.append(b)
        self.pos += len(b)
        return self

    def octets(self, data: bytes) -> "_Cdr":
        self.put("I", len(data))
        self.parts.append(bytes(data))
        self.pos += len(data)
        return self

    def header(self, stamp_ns: int, frame_id: str) -> "_Cdr":
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        return self.put("II", sec & 0xFFFFFFFF, nsec).string(frame_id)

    def bytes(self) -> bytes:
        return b"".join(self.parts)


class _CdrReader:
    """Minimal little-endian CDR reader for the few types read field by field (``_Cdr``'s inverse); another
    encapsulation, a message too short or a string not UTF-8 raises ValueError."""

    def __init__(self, data: bytes) -> None:
        if bytes(data[:4]) != CDR_LE_HEADER:
            raise ValueError("not little-endian CDR")
        self.data, self.pos = bytes(data), 0

    def get(self, fmt: str) -> tuple:
        self.pos += -self.pos % struct.calcsize("<" + fmt[0])
        try:
            values = struct.unpack_from("<" + fmt, self.data, 4 + self.pos)
        except struct.error:
            raise ValueError("the message ends early") from None
        self.pos += struct.calcsize("<" + fmt)
        return values

    def string(self) -> str:
        (n,) = self.get("I")
        start = 4 + self.pos
        if n < 1 or start + n > len(self.data):
            raise ValueError("a string runs past the message's end")
        self.pos += n
        try:
            return self.data[start:start + n - 1].decode()
        except UnicodeDecodeError:
            raise ValueError("a string is not UTF-8") from None


def header_frame_id(data: bytes) -> str:
    """The ``frame_id`` of a message whose first field is a ``std_msgs/Header`` (Imu, NavSatFix, any ``*Stamped``).

    Parameters
    ----------
    data : one CDR message

    Returns
    -------
    str : the header's frame (ValueError when the bytes do not hold one)
    """
    r = _CdrReader(data)
    r.get("iI")
    return r.string()


def decode_tf(data: bytes) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """``tf2_msgs/msg/TFMessage`` -> its transforms as ``encode_tf`` takes them (the inverse, stamps left out).

    Parameters
    ----------
    data : one CDR message

    Returns
    -------
    list of (parent frame, child frame, translation (3,) m in the parent frame, rotation (4,) x, y, z, w of
    child -> parent) (ValueError when the bytes are not one)
    """
    r = _CdrReader(data)
    (n,) = r.get("I")
    out = []
    for _ in range(n):  # each takes 64 bytes or more: a count too large ends early
        r.get("iI")
        parent, child = r.string(), r.string()
        out.append((parent, child, np.array(r.get("ddd")), np.array(r.get("dddd"))))
    return out


def encode_sentence(stamp_ns: int, sentence: str, frame_id: str = "gps") -> bytes:
    """``nmea_msgs/msg/Sentence``: one NMEA line without CR/LF, stamp = read time mapped to UTC.

    Parameters
    ----------
    stamp_ns : read time mapped to UTC, ns
    sentence : the NMEA line without CR/LF
    frame_id : the header's frame

    Returns
    -------
    bytes : one CDR message
    """
    return _Cdr().header(stamp_ns, frame_id).string(sentence).bytes()


def encode_raw(stamp_ns: int, mono_ns: int, port: str, data: bytes, frame_id: str = "") -> bytes:
    """``fieldlog_msgs/msg/RawBytes``: bytes exactly as read; stamp = host wall clock at read,
    mono_ns = host monotonic clock at read, port = the port's role ("daq" or "gps").

    Every read of the daemon is one: laid out here in one struct call rather than field by field (``_Cdr``), the
    same bytes (CDR alignment counts from the end of the encapsulation header).

    Parameters
    ----------
    stamp_ns : host wall clock at read, UTC ns
    mono_ns : host monotonic clock at read, ns
    port : the port's role
    data : the bytes read
    frame_id : the header's frame

    Returns
    -------
    bytes : one CDR message
    """
    head, f, p = _raw_head(port, frame_id)
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return head.pack(CDR_LE_HEADER, sec & 0xFFFFFFFF, nsec, len(f), f, mono_ns, len(p), p, len(data)) + bytes(data)


@lru_cache(maxsize=256)
def _raw_head(port: str, frame_id: str) -> tuple[struct.Struct, bytes, bytes]:
    """``encode_raw``'s fields before the data, as one struct for a port and frame (padded as CDR aligns them),
    and the two NUL-terminated strings."""
    f, p = frame_id.encode() + b"\x00", port.encode() + b"\x00"
    pad_mono = -(12 + len(f)) % 8                       # int64 mono_ns after sec, nanosec and the frame id
    pad_data = -len(p) % 4                              # the data's uint32 length after the port string
    return struct.Struct(f"<4sIII{len(f)}s{pad_mono}xqI{len(p)}s{pad_data}xI"), f, p


def encode_raws(stamp_ns: np.ndarray, mono_ns: np.ndarray, port: str, data: Packed, frame_id: str = "") -> Packed:
    """``encode_raw`` of many reads of one port at once, the same bytes: read i's ``data[i]``, read at host wall
    clock ``stamp_ns[i]`` and monotonic clock ``mono_ns[i]`` (ns), its fields before the data laid out as rows of
    one structured array (``_raw_rows``) and put in front of the data in one step (``Packed.prefixed``).

    Parameters
    ----------
    stamp_ns : (n,) int64 host wall clock at each read, UTC ns
    mono_ns : (n,) int64 host monotonic clock at each read, ns
    port : the port's role
    data : the n reads' bytes
    frame_id : the headers' frame

    Returns
    -------
    Packed : n CDR messages
    """
    dtype, template = _raw_rows(port, frame_id)
    rows = np.empty(len(data), dtype)
    rows.view(np.uint8).reshape(len(data), dtype.itemsize)[:] = np.frombuffer(template, np.uint8)
    rows["sec"], rows["nanosec"] = split_stamp(stamp_ns)
    rows["mono_ns"] = mono_ns
    rows["length"] = data.lengths
    return data.prefixed(rows.view(np.uint8).reshape(len(data), dtype.itemsize))


@lru_cache(maxsize=256)
def _raw_rows(port: str, frame_id: str) -> tuple[np.dtype, bytes]:
    """``encode_raw``'s fields before the data as a structured dtype of the fields that differ between reads
    (sec, nanosec, mono_ns and the data's length, at their CDR offsets), and those bytes with the others set."""
    head, f, p = _raw_head(port, frame_id)
    mono_at = 16 + len(f) + -(12 + len(f)) % 8          # after the encapsulation header, sec, nanosec, frame id
    dtype = np.dtype({"names": ["sec", "nanosec", "mono_ns", "length"], "formats": ["<i4", "<u4", "<i8", "<u4"],
                      "offsets": [4, 8, mono_at, head.size - 4], "itemsize": head.size})
    return dtype, head.pack(CDR_LE_HEADER, 0, 0, len(f), f, 0, len(p), p, 0)


def decode_raw(data: bytes) -> tuple[int, int, str, bytes]:
    """``fieldlog_msgs/msg/RawBytes`` -> (wall_ns, mono_ns, port, data); the inverse of ``encode_raw``.

    Parameters
    ----------
    data : one CDR message

    Returns
    -------
    wall_ns, mono_ns, port, data : as ``encode_raw`` took them
    """
    sec, nsec, flen = struct.unpack_from("<III", data, 4)
    pos = 12 + flen
    pos += -pos % 8
    (mono_ns,) = struct.unpack_from("<q", data, 4 + pos)
    pos += 8
    (plen,) = struct.unpack_from("<I", data, 4 + pos)
    port = data[4 + pos + 4: 4 + pos + 4 + plen - 1].decode()
    pos += 4 + plen
    pos += -pos % 4
    (dlen,) = struct.unpack_from("<I", data, 4 + pos)
    return sec * 1_000_000_000 + nsec, mono_ns, port, data[4 + pos + 4: 4 + pos + 4 + dlen]


def encode_wheel_speeds(stamp_ns: int, can_id: int, wheel_speed: Sequence[float], vehicle_speed: float,
                        steering_angle: float, reverse: int, names: Sequence[str], values: Sequence[float],
                        frame_id: str = "base_link") -> bytes:
    """``fieldlog_msgs/msg/WheelSpeeds``: wheel speeds (front left, front right, rear left, rear right) and the
    vehicle speed in m/s, the steering angle in rad (NaN: not known), reverse 1/0 (-1: not known), and the
    configured signals of the frame ``can_id`` by name with their values in the DBC's units.

    Parameters
    ----------
    stamp_ns : UTC ns
    can_id : the CAN frame's id
    wheel_speed : FL, FR, RL, RR, m/s
    vehicle_speed : m/s
    steering_angle : rad (NaN: not known)
    reverse : 1, 0, or -1 (not known)
    names, values : the configured signals and their values, DBC units
    frame_id : the header's frame

    Returns
    -------
    bytes : one CDR message
    """
    w = _Cdr().header(stamp_ns, frame_id).put("I", can_id).put("dddd", *map(float, wheel_speed))
    w.put("dd", float(vehicle_speed), float(steering_angle)).put("b", int(reverse)).put("I", len(names))
    for n in names:
        w.string(n)
    w.put("I", len(values))
    if len(values):
        w.put("d" * len(values), *map(float, values))
    return w.bytes()


def encode_tf(stamp_ns: int, transforms: Sequence[tuple[str, str, Sequence[float], Sequence[float]]]) -> bytes:
    """``tf2_msgs/msg/TFMessage``: transforms (parent frame, child frame, translation x, y, z in m in the parent
    frame, rotation x, y, z, w of child -> parent), all stamped ``stamp_ns`` (UTC ns).

    Parameters
    ----------
    stamp_ns : UTC ns
    transforms : (parent, child, translation (3,) m, rotation (4,) x, y, z, w) each

    Returns
    -------
    bytes : one CDR message
    """
    w = _Cdr().put("I", len(transforms))
    for parent, child, xyz, q_xyzw in transforms:
        w.header(stamp_ns, parent).string(child).put("ddd", *map(float, xyz)).put("dddd", *map(float, q_xyzw))
    return w.bytes()


def encode_tf_rows(stamp_ns: np.ndarray, transforms: Sequence[tuple[str, str, np.ndarray, np.ndarray]]) -> Packed:
    """``encode_tf`` of n rows at once: row i holds every transform (parent frame, child frame, translations
    (n, 3) m, rotations x, y, z, w (n, 4)) at its row i, stamped ``stamp_ns[i]``. The same bytes as
    ``encode_tf`` row by row.

    Parameters
    ----------
    stamp_ns : (n,) int64 UTC ns
    transforms : (parent, child, translations (n, 3) m, rotations (n, 4) x, y, z, w) each

    Returns
    -------
    Packed : n CDR messages
    """
    stamp_ns = np.asarray(stamp_ns, dtype=np.int64)
    fields: list[_Field] = [("count", "<u4", ())]
    lengths = []
    for i, (parent, child, _, _) in enumerate(transforms):
        fields += [(f"sec{i}", "<i4", ()), (f"nanosec{i}", "<u4", ()), (f"parent{i}", "string", None),
                   (f"child{i}", "string", None), (f"xyz{i}", "<f8", (3,)), (f"q{i}", "<f8", (4,))]
        lengths += [len(parent.encode()), len(child.encode())]
    arr = np.zeros(len(stamp_ns), dtype=_dtype(tuple(fields), tuple(lengths)))
    arr["enc"] = np.frombuffer(CDR_LE_HEADER, dtype=np.uint8)
    arr["count"] = len(transforms)
    sec, nsec = split_stamp(stamp_ns)
    for i, (parent, child, xyz, q_xyzw) in enumerate(transforms):
        arr[f"sec{i}"], arr[f"nanosec{i}"] = sec, nsec
        for name, text in ((f"parent{i}", parent), (f"child{i}", child)):
            arr[name + "_len"] = len(text.encode()) + 1
            arr[name] = text.encode()
        arr[f"xyz{i}"] = xyz
        arr[f"q{i}"] = q_xyzw
    return _pack(arr)


def encode_outage(stamp_ns: int, start_ns: int, end_ns: int, reason: str, frame_id: str = "") -> bytes:
    """``fieldlog_msgs/msg/Outage``: GPS outage window [start_ns, end_ns) in UTC ns;
    reason e.g. "injected", "no_fix", "low_quality".

    Parameters
    ----------
    stamp_ns : the header's stamp, UTC ns
    start_ns, end_ns : the window, UTC ns
    reason : why GPS is out
    frame_id : the header's frame

    Returns
    -------
    bytes : one CDR message
    """
    return _Cdr().header(stamp_ns, frame_id).put("qq", start_ns, end_ns).string(reason).bytes()


# ---------------------------------------------------------------------------------------------
# Vectorised decoders (fixed layouts). Rows that are not valid CDR of the type get valid=False
# and zeros; decoders never raise on bad input.


def _decode_fixed(type_name: str, msgs: "Packed | Sequence[bytes]") -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Numeric fields by name (rows that are not valid are zero), and a valid mask (n,). A batch of one layout
    gives views into its payloads (strided): ``_batch_decoder`` copies the fields a caller keeps."""
    p = as_packed(msgs)
    n = len(p)
    common = _common_dtype(type_name)
    starts, lens = p.offsets[:-1], p.lengths
    # Every layout starts with header(sec, nanosec, frame_id): frame_id length at byte 12.
    ok = lens >= 17
    str_lens = [_u32_at(p.buf, np.where(ok, starts + 12, 0)) - 1]
    if type_name == TIMEREF:  # source length after frame_id and the 8-byte time_ref
        pos = 4 + (-(-(13 + str_lens[0]) // 4) * 4) + 8
        ok &= lens >= pos + 4
        str_lens.append(_u32_at(p.buf, np.where(ok, starts + pos, 0)) - 1)
    keys = np.stack(str_lens, axis=1)
    ok &= (keys >= 0).all(axis=1) & (keys < 1 << 20).all(axis=1)
    ok &= _u32_at(p.buf, np.where(ok, starts, 0)) == 0x100  # 00 01 00 00: CDR little-endian
    if not ok.any():
        return {k: np.zeros(n, dtype=common.fields[k][0]) for k in common.names}, ok
    good_rows = np.flatnonzero(ok)
    if (keys[good_rows] == keys[good_rows[0]]).all():  # the usual case: one layout
        uniq, inverse = keys[good_rows[:1]], np.zeros(len(good_rows), dtype=np.int64)
    else:
        uniq, inverse = np.unique(keys[good_rows], axis=0, return_inverse=True)
    out: dict[str, np.ndarray] | None = None
    for g, key in enumerate(uniq):
        dt = _layout(type_name, tuple(int(k) for k in key))
        rows = good_rows[inverse.reshape(-1) == g]
        fits = lens[rows] == dt.itemsize
        ok[rows[~fits]] = False
        rows = rows[fits]
        part = _gather(p, rows, dt)
        if len(rows) == n:
            return {k: part[k] for k in common.names}, ok
        if out is None:
            out = {k: np.zeros(n, dtype=common.fields[k][0]) for k in common.names}
        for k in common.names:
            out[k][rows] = part[k]
    if out is None:
        out = {k: np.zeros(n, dtype=common.fields[k][0]) for k in common.names}
    return out, ok


def _gather(p: Packed, rows: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Rows of ``p`` (all of length dt.itemsize) viewed or copied as a structured array."""
    w = dt.itemsize
    if len(rows) == len(p) and p.width() == w:
        return p.matrix().reshape(-1).view(dt)
    out = np.empty((len(rows), w), dtype=np.uint8)
    step = max(1, (1 << 22) // w)  # bound the index matrix to ~32 MB
    for i in range(0, len(rows), step):
        s = p.offsets[rows[i : i + step]]
        out[i : i + step] = p.buf[s[:, None] + np.arange(w)]
    return out.reshape(-1).view(dt)


def _u32_at(buf: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Little-endian uint32 at each byte position (int64 result; positions clipped in range): its four bytes
    gathered a byte column at a time."""
    if len(buf) < 4:
        return np.zeros(len(pos), dtype=np.int64)
    pos = np.clip(np.asarray(pos, dtype=np.int64), 0, len(buf) - 4)
    out = np.empty((len(pos), 4), np.uint8)
    for i in range(4):
        np.take(buf, pos + i, out=out[:, i])
    return out.view("<u4").ravel().astype(np.int64)


@lru_cache(maxsize=None)
def _common_dtype(type_name: str) -> np.dtype:
    """Aligned (non-CDR) dtype holding a type's numeric fields, for decoded output."""
    fields = [(name, fmt, shape) for name, fmt, shape in _FIELDS[type_name] if fmt != "string"]
    return np.dtype([(name, fmt, shape) if shape else (name, fmt) for name, fmt, shape in fields])


BatchDecoder = Callable[..., dict[str, np.ndarray]]


def _batch_decoder(decoder: Callable[["Packed | Sequence[bytes]"], dict[str, np.ndarray]]) -> BatchDecoder:
    """A decoder over ``_decode_fixed``'s fields as a public one, ``decode_x(msgs, fields=None)``: the keys in
    ``fields`` (all: None) as contiguous arrays; the others are never copied out of the payloads (a reader that
    wants an Imu's rates and forces saves copying its covariances)."""

    @wraps(decoder)
    def decode(msgs: "Packed | Sequence[bytes]", fields: Collection[str] | None = None) -> dict[str, np.ndarray]:
        return {k: np.ascontiguousarray(v) for k, v in decoder(msgs).items() if fields is None or k in fields}

    return decode


@_batch_decoder
def decode_imu(msgs: "Packed | Sequence[bytes]") -> dict[str, np.ndarray]:
    """Imu batch -> stamp_ns (n,) int64, omega_ib_b (n,3), f_b (n,3), orientation_xyzw (n,4),
    gyro_cov / accel_cov / orientation_cov (n,9), valid (n,) bool.

    Parameters
    ----------
    msgs : n Imu messages
    fields : the keys to return (all: None); the others are not copied

    Returns
    -------
    dict[str, np.ndarray]
    """
    a, ok = _decode_fixed(IMU, msgs)
    return {
        "stamp_ns": join_stamp(a["sec"], a["nanosec"]),
        "omega_ib_b": a["angular_velocity"],
        "f_b": a["linear_acceleration"],
        "orientation_xyzw": a["orientation"],
        "gyro_cov": a["angular_velocity_covariance"],
        "accel_cov": a["linear_acceleration_covariance"],
        "orientation_cov": a["orientation_covariance"],
        "valid": ok,
    }


@_batch_decoder
def decode_navsatfix(msgs: "Packed | Sequence[bytes]") -> dict[str, np.ndarray]:
    """NavSatFix batch -> stamp_ns, lat_deg, lon_deg, alt_m, position_covariance (n,9) ENU m^2,
    covariance_type, status, service, valid.

    Parameters
    ----------
    msgs : the NavSatFix batch, n messages in CDR
    fields : the keys to return (all: None); the others are not copied

    Returns
    -------
    dict : n fixes, one row each (degrees, metres)
    """
    a, ok = _decode_fixed(NAVSATFIX, msgs)
    return {
        "stamp_ns": join_stamp(a["sec"], a["nanosec"]),
        "lat_deg": a["latitude"],
        "lon_deg": a["longitude"],
        "alt_m": a["altitude"],
        "position_covariance": a["position_covariance"],
        "covariance_type": a["position_covariance_type"],
        "status": a["status"],
        "service": a["service"],
        "valid": ok,
    }


@_batch_decoder
def decode_twist(msgs: "Packed | Sequence[bytes]") -> dict[str, np.ndarray]:
    """TwistWithCovarianceStamped batch -> stamp_ns, v_n (n,3) ENU m/s, omega (n,3),
    covariance (n,36), valid.

    Parameters
    ----------
    msgs : n twists (CDR)
    fields : the keys to return (all: None); the others are not copied

    Returns
    -------
    dict[str, np.ndarray] : n rows; v_n in m/s
    """
    a, ok = _decode_fixed(TWIST, msgs)
    return {
        "stamp_ns": join_stamp(a["sec"], a["nanosec"]),
        "v_n": a["linear"],
        "omega": a["angular"],
        "covariance": a["covariance"],
        "valid": ok,
    }


@_batch_decoder
def decode_quaternion(msgs: "Packed | Sequence[bytes]") -> dict[str, np.ndarray]:
    """QuaternionStamped batch -> stamp_ns, q_xyzw (n,4), valid.

    Parameters
    ----------
    msgs : QuaternionStamped messages
    fields : the keys to return (all: None); the others are not copied

    Returns
    -------
    dict : q_xyzw is body -> ENU
    """
    a, ok = _decode_fixed(QUATERNION, msgs)
    return {"stamp_ns": join_stamp(a["sec"], a["nanosec"]), "q_xyzw": a["quaternion"], "valid": ok}


@_batch_decoder
def decode_vector3(msgs: "Packed | Sequence[bytes]") -> dict[str, np.ndarray]:
    """Vector3Stamped batch -> stamp_ns, xyz (n,3), valid.

    Parameters
    ----------
    msgs : a batch of n Vector3Stamped
    fields : the keys to return (all: None); the others are not copied

    Returns
    -------
    dict[str, np.ndarray] : xyz in the units of the topic
    """
    a, ok = _decode_fixed(VECTOR3, msgs)
    return {"stamp_ns": join_stamp(a["sec"], a["nanosec"]), "xyz": a["vector"], "valid": ok}


@_batch_decoder
def decode_time_reference(msgs: "Packed | Sequence[bytes]") -> dict[str, np.ndarray]:
    """TimeReference batch -> stamp_ns (the edge in UTC), time_ref_ns (the edge on the DAQ clock), valid.

    Parameters
    ----------
    msgs : n /pps messages
    fields : the keys to return (all: None); the others are not copied

    Returns
    -------
    dict : both times in ns
    """
    a, ok = _decode_fixed(TIMEREF, msgs)
    return {
        "stamp_ns": join_stamp(a["sec"], a["nanosec"]),
        "time_ref_ns": join_stamp(a["ref_sec"], a["ref_nanosec"]),
        "valid": ok,
    }


@_batch_decoder
def decode_time_sync(msgs: "Packed | Sequence[bytes]") -> dict[str, np.ndarray]:
    """TimeSyncState batch -> stamp_ns, state, rate_ppm, residual_us, edges_used,
    edges_rejected, valid.

    Parameters
    ----------
    msgs : the /time/sync batch
    fields : the keys to return (all: None); the others are not copied

    Returns
    -------
    dict[str, np.ndarray] : the state and fit of each record
    """
    a, ok = _decode_fixed(TIMESYNC, msgs)
    out = {"stamp_ns": join_stamp(a["sec"], a["nanosec"])}
    out.update({k: a[k] for k in ("state", "rate_ppm", "residual_us", "edges_used", "edges_rejected")})
    out["valid"] = ok
    return out


@_batch_decoder
def decode_solution_status(msgs: "Packed | Sequence[bytes]") -> dict[str, np.ndarray]:
    """SolutionStatus batch -> stamp_ns, status, since_update_s, sigma_h_m, nis, valid.

    Parameters
    ----------
    msgs : n SolutionStatus messages, as written by ``encode_solution_status``
    fields : the keys to return (all: None); the others are not copied

    Returns
    -------
    dict : n statuses
    """
    a, ok = _decode_fixed(SOLUTION_STATUS, msgs)
    out = {"stamp_ns": join_stamp(a["sec"], a["nanosec"])}
    out.update({k: a[k] for k in ("status", "since_update_s", "sigma_h_m", "nis")})
    out["valid"] = ok
    return out


BATCH_DECODERS: dict[str, BatchDecoder] = {
    IMU: decode_imu,
    NAVSATFIX: decode_navsatfix,
    TWIST: decode_twist,
    QUATERNION: decode_quaternion,
    VECTOR3: decode_vector3,
    TIMEREF: decode_time_reference,
    TIMESYNC: decode_time_sync,
    SOLUTION_STATUS: decode_solution_status,
}

# ---------------------------------------------------------------------------------------------
# Generic decode (any registered type, per message) through mcap_ros2's own decoder.

_schema_ids = {name: i + 1 for i, name in enumerate(MSG_DEFS)}


def schema_record(type_name: str) -> Schema:
    """An mcap Schema record for ``type_name`` (id is a stable local number).

    Parameters
    ----------
    type_name : a registered type

    Returns
    -------
    Schema : the record (ros2msg encoding)
    """
    return Schema(
        id=_schema_ids[type_name],
        name=type_name,
        encoding=SCHEMA_ENCODING,
        data=schema_text(type_name).encode(),
    )


@lru_cache(maxsize=None)
def _factory():
    """mcap_ros2's decoder factory, imported on first use (not by every command's start)."""
    from mcap_ros2.decoder import DecoderFactory

    return DecoderFactory()


def decoder_for(type_name: str) -> Callable[[bytes], Any]:
    """mcap_ros2's decoder for one registered type: bytes -> message object.

    Parameters
    ----------
    type_name : a registered type

    Returns
    -------
    callable : CDR bytes -> message object
    """
    dec = _factory().decoder_for(MESSAGE_ENCODING, schema_record(type_name))
    assert dec is not None
    return dec


def decode_message(type_name: str, data: bytes) -> Any:
    """Decode one message of any registered type (attribute access, e.g. ``m.header.stamp``).

    Parameters
    ----------
    type_name : a registered type
    data : one CDR message

    Returns
    -------
    object : the message
    """
    return decoder_for(type_name)(data)
