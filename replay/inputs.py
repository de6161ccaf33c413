"""Which topics of a drive feed fusion, in which body frame: fieldlog's own drives and other loggers' bags.

A drive from another logger names its topics its own way (``/imu/data``, ``/ublox/fix``, ``/sensors/imu``) and
writes its IMU in REP-103 FLU (forward, left, up) or FRD; fusion runs on the body RFU frame (right, forward,
up). :func:`resolve` picks the topics and the IMU frame:

- topics: the ones given (``--imu-topic``/``--fix-topic``/``--vel-topic`` or the ``[input]`` config table),
  else fieldlog's own (``/imu``, ``/gps/fix``, ``/gps/vel``), else the drive's only ``sensor_msgs/msg/Imu``
  and only ``sensor_msgs/msg/NavSatFix`` topics (auto-detection by message type; several of a type: an error
  asking for the option). A velocity topic is only taken when named or fieldlog's own: without one, fusion
  updates position only (``fusion.engine``);
- IMU frame: the one given (``--imu-frame rfu|flu|frd``), else the rotation of the Imu messages' frame_id in
  ``/tf_static`` (``tf2_msgs/msg/TFMessage``; the chain of static transforms up to its root, taken as the
  REP-103 FLU vehicle body), else RFU for fieldlog's own topics and FLU (REP-103) for any other;
- lever arm: from ``/tf_static`` too when it holds both the IMU and the NavSatFix frame_id.

:class:`InputStream` streams the drive in blocks as the engine's ``ImuBlock`` and ``GpsBlock``, on the messages'
header stamps (the sensor's time; a bag's log time is when the logger received the message): IMU samples are
rotated to RFU, sorted, repeated stamps dropped, gaps (dropped samples: a step above 1.5 sample periods) counted
and bridged by the INS over the longer step. :class:`Resequencer` holds every topic's rows of the last ``HOLD_S``
of each block for the next, so a fix logged late (its stamp in the previous block) still arrives before the INS
passes it; ``fuse``, ``replay`` and ``view`` all read a drive through it (``canonical_blocks``).
"""

from __future__ import annotations

import contextlib
import math
import os
import pickle
import tempfile
from dataclasses import dataclass, field
from typing import IO, TYPE_CHECKING, Generator, Iterator

import numpy as np

from fieldlog.drive import messages
from fieldlog.fusion import earth  # numpy only: reading a drive never loads the fusion stack
from fieldlog.fusion.median import median
from fieldlog.drive import reader
from fieldlog.drive.drive import Drive, file_transforms
from fieldlog.drive.files import DriveSpec, label, open_drive
from fieldlog.replay.ahead import Ahead

if TYPE_CHECKING:
    from fieldlog.fusion.types import GpsBlock, ImuBlock, OdomBlock

NATIVE = ("/imu", "/gps/fix", "/gps/vel")  # fieldlog's own topics (body RFU)
ENGINE_IMU_FIELDS = ("stamp_ns", "omega_ib_b", "f_b", "valid")  # the decoded Imu keys the engine's blocks read
_COUNTERS = ("samples", "gaps", "missing", "repeated", "_last_t", "_period_ns", "_first_t", "_dev_sq", "_steps",
             "longest_gap_ns", "longest_gap_at_ns")  # InputStream's
ODOM = "/vehicle/twist"  # fieldlog's own wheel-speed odometry (forward speed in base_link, linear.x)
WHEEL_SPEEDS = "/vehicle/wheel_speeds"  # the four wheel speeds beside ODOM (``acquire.canbus``), same stamps
ODOM_TYPES = (messages.TWIST, messages.ODOMETRY, messages.TWIST_STAMPED)  # what --odom-topic reads: linear.x
TF_STATIC = "/tf_static"
HOLD_S = 1.0  # rows held back per block (Resequencer): longer than a fix's logging latency
RATE_HZ = (100.0, 1000.0)  # the IMU rates fusion is built for
CLOCK_TOL = 0.02  # an IMU's own oscillator is within this fraction of its nominal rate (internal RC: percents)
JITTER_MAX = 0.25  # stamp jitter (RMS step deviation) over the period worth a warning: gap counting needs less
FIELDS = ("imu_topic", "fix_topic", "vel_topic", "imu_frame", "odom_topic")  # of InputSpec


@dataclass
class InputSpec:
    """What to read, from ``--imu-topic`` etc. or a config's ``[input]`` table; None: resolved from the drive."""

    imu_topic: str | None = None
    fix_topic: str | None = None
    vel_topic: str | None = None  # "" or "none": no velocity topic even when the drive has /gps/vel
    imu_frame: str | None = None  # rfu, flu or frd
    odom_topic: str | None = None  # "" or "none": no odometry even when the drive has /vehicle/twist

    def merged(self, over: "InputSpec") -> "InputSpec":
        """This spec with the fields ``over`` sets replacing its own."""
        return InputSpec(*(getattr(over, k) if getattr(over, k) is not None else getattr(self, k) for k in FIELDS))

    def given(self) -> list[str]:
        """The fields this spec sets."""
        return [k for k in FIELDS if getattr(self, k) is not None]


@dataclass
class InputMap:
    """The resolved input: topics, C_rfu_imu (3, 3) (IMU frame -> body RFU), its name, the lever arm IMU ->
    antenna in body RFU from /tf_static (None without), and where each came from (``sources``)."""

    imu_topic: str
    fix_topic: str
    vel_topic: str | None
    C_rfu_imu: np.ndarray
    imu_frame: str
    lever_arm_b: np.ndarray | None = None
    sources: dict[str, str] = field(default_factory=dict)
    odom_topic: str | None = None  # the forward speed (ODOM_TYPES), None: no odometry

    @property
    def native(self) -> bool:
        """fieldlog's own topics (a drive our daemon or simulator wrote)."""
        return (self.imu_topic, self.fix_topic) == NATIVE[:2]

    @property
    def topics(self) -> tuple[str, ...]:
        return (self.imu_topic, self.fix_topic) + ((self.vel_topic,) if self.vel_topic else ())

    def describe(self) -> str:
        """One line: each input and where it came from."""
        s = self.sources
        vel = f"{self.vel_topic} ({s['vel_topic']})" if self.vel_topic else f"none ({s['vel_topic']})"
        odom = f", odometry {self.odom_topic} ({s['odom_topic']})" if self.odom_topic else ""
        return (f"input: IMU {self.imu_topic} ({s['imu_topic']}) in {self.imu_frame} ({s['imu_frame']}), "
                f"fixes {self.fix_topic} ({s['fix_topic']}), velocity {vel}{odom}")


def detect(infos: list[reader.TopicCount], type_name: str, native: str) -> str | None:
    """The topic of one input without an option: fieldlog's own (``native``), else the only one of ``type_name``
    with messages; None when there is none or several."""
    of_type = [t.topic for t in infos if t.type == type_name and t.count]
    return native if native in of_type else of_type[0] if len(of_type) == 1 else None


def _pick(spec: str | None, infos: list[reader.TopicCount], type_name: str, native: str, option: str,
          path: str | os.PathLike[str]) -> tuple[str, str]:
    """(topic, source) of one input."""
    of_type = [t.topic for t in infos if t.type == type_name]
    if not spec and (found := detect(infos, type_name, native)):
        return found, "fieldlog's own" if found == native else f"the only {type_name.rsplit('/', 1)[-1]} topic"
    if spec:
        found = [t for t in infos if t.topic == spec]
        if not found:
            raise ValueError(f"{path}: no topic {spec} ({option}); its {type_name} topics: "
                             f"{', '.join(of_type) or 'none'}")
        if found[0].type != type_name:
            raise ValueError(f"{path}: {spec} is {found[0].type}, not {type_name} ({option})")
        return spec, option
    if not of_type:
        raise ValueError(f"{path}: no {type_name} topic; name one with {option}")
    raise ValueError(f"{path}: several {type_name} topics ({', '.join(of_type)}): choose one with {option}")


def _first_frame_id(path: DriveSpec, topic: str) -> str:
    """The header's frame of ``topic``'s first message ("" when it has none)."""
    for _, data in reader.iter_payloads(path, topic):
        try:
            return messages.header_frame_id(data)
        except ValueError as e:
            raise ValueError(f"{label(path)}: the first {topic} message does not decode ({e}): the file is "
                             "damaged there; give the IMU's axes instead (--imu-frame, or [input] imu_frame)") from None
    return ""


def tf_static(path: DriveSpec) -> dict[str, tuple[str, np.ndarray, np.ndarray]]:
    """The drive's static transforms: child frame -> (parent frame, translation (3,) m, C_parent_child (3, 3)).
    A ``drive.drive.Drive``'s are checked across its files (``Drive.tf_static``); for a path, every file's in
    log-time order, a later file's winning."""
    if isinstance(path, Drive):
        return path.tf_static()
    out: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}
    for f in open_drive(path):
        out.update(file_transforms(f.path))
    return out


def _to_root(tf: dict[str, tuple[str, np.ndarray, np.ndarray]], frame: str) -> tuple[str, np.ndarray, np.ndarray]:
    """(root frame, position (3,) of ``frame``'s origin in the root, C_root_frame) along the static chain."""
    C, r, seen = np.eye(3), np.zeros(3), set()
    while frame in tf and frame not in seen:
        seen.add(frame)
        parent, t, C_pc = tf[frame]
        C, r = C_pc @ C, C_pc @ r + t
        frame = parent
    return frame, r, C


def _frame_name(C: np.ndarray) -> str:
    for name, M in earth.BODY_FRAMES.items():
        if np.allclose(C, M, atol=1e-6):
            return name
    return "rotated " + ", ".join(f"{x:.3f}" for x in C.ravel())


def resolve(path: str | os.PathLike[str], spec: InputSpec | None = None, given: dict[str, str] | None = None
            ) -> InputMap:
    """The input of a drive (module docstring); ValueError with one line naming the problem. ``given``: where a
    field of ``spec`` was given, for the sources (e.g. a config's ``[input]`` table; default: its option)."""
    spec = spec or InputSpec()
    where = {k: (given or {}).get(k, "--" + k.replace("_", "-")) for k in FIELDS}
    infos = [t for t in reader.topic_counts(path) if t.count]
    imu, s_imu = _pick(spec.imu_topic, infos, messages.IMU, NATIVE[0], where["imu_topic"], path)
    fix, s_fix = _pick(spec.fix_topic, infos, messages.NAVSATFIX, NATIVE[1], where["fix_topic"], path)
    if spec.vel_topic is not None and spec.vel_topic.lower() in ("", "none"):
        vel, s_vel = None, f"{where['vel_topic']} none"
    elif spec.vel_topic:
        vel, s_vel = _pick(spec.vel_topic, infos, messages.TWIST, NATIVE[2], where["vel_topic"], path)
    elif any(t.topic == NATIVE[2] and t.type == messages.TWIST for t in infos):
        vel, s_vel = NATIVE[2], "fieldlog's own"
    else:
        vel, s_vel = None, "no velocity topic: position-only GPS updates"
    if spec.odom_topic is not None and spec.odom_topic.lower() in ("", "none"):
        odom, s_odom = None, f"{where['odom_topic']} none"
    elif spec.odom_topic:
        odom = next((t.topic for t in infos if t.topic == spec.odom_topic), None)
        kind = next((t.type for t in infos if t.topic == spec.odom_topic), None)
        if odom is None or kind not in ODOM_TYPES:
            what = "has no such topic" if odom is None else f"has it as {kind}"
            raise ValueError(f"{where['odom_topic']} {spec.odom_topic}: {os.fspath(path)} {what}; give a "
                             f"{', '.join(ODOM_TYPES)} topic")
        s_odom = where["odom_topic"]
    elif any(t.topic == ODOM and t.type == messages.TWIST for t in infos):
        odom, s_odom = ODOM, "fieldlog's own"
    else:
        odom, s_odom = None, "none"
    tf = tf_static(path) if any(t.topic == TF_STATIC for t in infos) else {}
    lever = None
    if spec.imu_frame:
        C, frame, s_frame = earth.C_rfu_from(spec.imu_frame), spec.imu_frame.lower(), where["imu_frame"]
    else:
        imu_id = _first_frame_id(path, imu).lstrip("/") if tf else ""
        if imu_id in tf:
            root, r_imu, C_root_imu = _to_root(tf, imu_id)
            C = earth.BODY_FRAMES["flu"] @ C_root_imu  # the root is the REP-103 vehicle body, FLU
            frame, s_frame = _frame_name(C), f"{TF_STATIC}: {imu_id} in {root} (REP-103 FLU)"
            C = earth.BODY_FRAMES.get(frame, C)  # a named frame exactly, without the quaternion's rounding
            gps_id = _first_frame_id(path, fix).lstrip("/")
            if gps_id in tf and _to_root(tf, gps_id)[0] == root:
                lever = C @ C_root_imu.T @ (_to_root(tf, gps_id)[1] - r_imu)
        elif (imu, fix) == NATIVE[:2]:
            C, frame, s_frame = np.eye(3), "rfu", "fieldlog's own"
        else:
            C, frame, s_frame = earth.BODY_FRAMES["flu"], "flu", "REP-103 default for another logger's drive"
    return InputMap(imu, fix, vel, C, frame, lever,
                    dict(imu_topic=s_imu, fix_topic=s_fix, vel_topic=s_vel, imu_frame=s_frame, odom_topic=s_odom),
                    odom)


def _stamps(d: dict) -> np.ndarray:
    """Header stamps (ns), the log time where a message has none (zero)."""
    st = np.asarray(d.get("stamp_ns", d["log_time_ns"]), np.int64)
    return np.where(st > 0, st, d["log_time_ns"])


def by_stamp(d: dict) -> dict:
    """A decoded block re-timed on its header stamps, valid rows only, sorted."""
    if not len(d.get("log_time_ns", ())):
        return {}
    ok = np.asarray(d["valid"], bool)
    t = _stamps(d)
    if ok.all():  # the usual block: every row valid and in stamp order, taken as it is
        sel = None if np.all(t[1:] >= t[:-1]) else np.argsort(t, kind="stable")
    else:
        sel = np.flatnonzero(ok)
        sel = sel[np.argsort(t[sel], kind="stable")]
    out = {k: v if sel is None else v[sel] for k, v in d.items() if isinstance(v, np.ndarray) and len(v) == len(ok)}
    out["log_time_ns"] = t if sel is None else t[sel]
    return out


class Resequencer:
    """Blocks of a drive re-timed on their header stamps and released in stamp order ``HOLD_S`` behind each
    block's end: what another logger wrote late (a fix logged after IMU samples later than its stamp, a sample
    that arrived out of order) is still in its place when a consumer (the fusion engine, the viewer) passes it.
    Every topic is held alike, so a released block holds every topic's rows up to the same stamp. The one
    re-sequencing step of ``fuse``, ``replay`` and ``view`` (``InputStream``, ``canonical_blocks``)."""

    def __init__(self, hold_s: float = HOLD_S) -> None:
        self.hold_ns = int(hold_s * 1e9)
        self._held: dict[str, dict] = {}

    def push(self, t1_ns: int, data: dict[str, dict]) -> dict[str, dict]:
        """``data`` (decoded rows per topic, as ``reader.iter_blocks`` gives them) of a block ending at log time
        ``t1_ns``; -> the rows, of this and earlier blocks, stamped before ``t1_ns - hold``, sorted."""
        return self._release(data, t1_ns - self.hold_ns)

    def flush(self) -> dict[str, dict]:
        """Every row still held."""
        return self._release({}, None)

    def _release(self, data: dict[str, dict], cut_ns: int | None) -> dict[str, dict]:
        out = {}
        for topic in {*self._held, *data}:
            d = _join(self._held.pop(topic, {}), by_stamp(data.get(topic, {})))
            if not d:
                continue
            k = len(d["log_time_ns"]) if cut_ns is None else int(np.searchsorted(d["log_time_ns"], cut_ns))
            out[topic] = {f: v[:k] for f, v in d.items()}
            if k < len(d["log_time_ns"]):
                self._held[topic] = {f: v[k:] for f, v in d.items()}
        return out


def _join(a: dict, b: dict) -> dict:
    """Two stamp-sorted row sets of one topic as one, sorted (stable: ``a``'s rows first at equal stamps)."""
    if not a or not b:
        return a or b
    d = {f: np.concatenate([a[f], b[f]]) for f in a if f in b}
    ta, tb = a["log_time_ns"], b["log_time_ns"]
    if not len(ta) or not len(tb) or ta[-1] <= tb[0]:  # b follows a: already the stable order
        return d
    order = np.argsort(d["log_time_ns"], kind="stable")
    return {f: v[order] for f, v in d.items()}


@dataclass
class InputBlock:
    t0_ns: int  # the block's log-time span
    t1_ns: int
    imu: ImuBlock
    gps: GpsBlock
    odom: OdomBlock | None = None
    data: dict[str, dict] | None = None  # the block's rows per topic (``reader.Block.data``), when kept


class InputStream:
    """A drive's fusion input in blocks (module docstring): the mapped topics under fieldlog's own names
    (``/imu`` in body RFU, ``/gps/fix``, ``/gps/vel``) re-sequenced on their stamps (``Resequencer``), IMU rows
    with a repeated stamp dropped; counts the IMU's gaps as it goes. ``blocks()`` gives them as
    ``reader.Block``s (for the viewer and the player, plus the ``extra`` topics), iterating gives the engine's
    ``ImuBlock`` and ``GpsBlock``. ``span_s`` > 0: the drive's first blocks alone, those that begin less than
    ``span_s`` after the first (a span rounded up to whole blocks), the rows held for re-sequencing at the
    cut given with the last."""

    def __init__(self, path: str | os.PathLike[str], imap: InputMap, block_s: float,
                 extra: tuple[str, ...] = (), keep: bool = False, span_s: float = 0.0) -> None:
        self.path, self.imap, self.block_s, self.keep, self.span_s = path, imap, block_s, keep, span_s
        self._kept: IO[bytes] | None = None  # keep: the engine's blocks of the first pass to the end, pickled
        self._ahead: Ahead | None = None  # the worker :meth:`start` began, not yet iterated
        self.extra = tuple(t for t in extra if t not in imap.topics and t != imap.odom_topic)
        self._start_counting()

    def _start_counting(self) -> None:
        """The counters (``_COUNTERS``) as before any sample: each read of the drive counts from here."""
        self.samples = 0
        self.gaps = 0  # steps longer than 1.5 sample periods (exact while the stamps jitter by < 1/4 period)
        self.missing = 0  # samples those steps lack, at the sample period
        self.repeated = 0  # samples dropped for a stamp not after the previous one
        self._last_t: int | None = None
        self._period_ns: float | None = None  # the sample period, from the first 100 steps
        self._first_t: int | None = None
        self._dev_sq = 0.0  # squared deviations of the steps that are no gap from the period, ns^2
        self._steps = 0  # their number
        self.longest_gap_ns = 0  # the longest gap's step, ns, and where it ends (log time, ns)
        self.longest_gap_at_ns = 0

    @property
    def rate_hz(self) -> float:
        """The IMU's sample rate, Hz (NaN before it is known)."""
        return 1e9 / self._period_ns if self._period_ns else float("nan")

    @property
    def imu_span_s(self) -> float:
        """From the first IMU sample read to the last, s (0 before two are read)."""
        return (self._last_t - self._first_t) * 1e-9 if self._first_t is not None and self._last_t is not None else 0.0

    def warnings(self) -> list[str]:
        """What is wrong with the IMU's timing, one line each (none for a good IMU): gaps (how many, the samples
        they lack, the longest and where, s from the first sample), stamp jitter above ``JITTER_MAX`` of the
        period, and a rate outside ``RATE_HZ`` by more than an oscillator's error (``CLOCK_TOL``): a 100 Hz IMU
        whose clock runs 257 ppm slow is a 100 Hz IMU."""
        out = []
        if self.gaps:
            at_s = (self.longest_gap_at_ns - (self._first_t or 0)) * 1e-9
            out.append(f"IMU: {self.gaps} gaps, {self.missing} samples missing; the longest "
                       f"{self.longest_gap_ns * 1e-9:.3g} s, ending {at_s:.1f} s after the first sample")
        if self._steps and self._period_ns:
            jitter = math.sqrt(self._dev_sq / self._steps)
            if jitter > JITTER_MAX * self._period_ns:
                out.append(f"IMU: stamps jitter by {jitter * 1e-6:.3g} ms RMS, more than {JITTER_MAX:g} of the "
                           f"{self._period_ns * 1e-6:.3g} ms period")
        lo, hi = RATE_HZ
        rate = self.rate_hz
        if math.isfinite(rate) and not lo * (1.0 - CLOCK_TOL) <= rate <= hi * (1.0 + CLOCK_TOL):
            out.append(f"IMU rate {rate:.5g} Hz is outside {lo:g}-{hi:g} Hz")
        return out

    def blocks(self, engine_only: bool = False) -> Iterator[reader.Block]:
        """The drive's blocks under fieldlog's names, re-sequenced; a last block (``t0 == t1``, the drive's end)
        with the rows still held. The counters start again (a read left early counts nothing of the next).
        ``engine_only``: the IMU's rows with the fields the engine reads (``ENGINE_IMU_FIELDS``) alone."""
        self._start_counting()
        names = dict(zip(self.imap.topics, NATIVE))
        odom = (self.imap.odom_topic,) if self.imap.odom_topic else ()
        if odom:
            names[odom[0]] = ODOM
        wheels = (WHEEL_SPEEDS,) if odom == (ODOM,) and WHEEL_SPEEDS not in self.extra else ()
        seq = Resequencer()
        t1 = None
        fields = {self.imap.imu_topic: ENGINE_IMU_FIELDS} if engine_only else None
        end = None  # log time (ns) the span's blocks begin before
        read = reader.iter_blocks(self.path, (*self.imap.topics, *odom, *wheels, *self.extra), self.block_s,
                                  fields=fields)
        with contextlib.closing(read):  # closed at the span's end: its read-ahead thread stops
            for b in read:
                if end is None and self.span_s > 0:
                    end = b.t0_ns + int(round(self.span_s * 1e9))
                if end is not None and b.t0_ns >= end:
                    break
                t1 = b.t1_ns
                data = dict(b.data)
                w = data.pop(WHEEL_SPEEDS, {}) if wheels else None
                if odom and odom[0] in data:
                    data[odom[0]] = odom_rows(data[odom[0]], w)
                yield reader.Block(b.t0_ns, b.t1_ns, self._canonical(seq.push(b.t1_ns, data), names))
        if t1 is not None:
            yield reader.Block(t1, t1, self._canonical(seq.flush(), names))

    def __iter__(self) -> Iterator[InputBlock]:
        """The engine's blocks, read on the second core (``replay.ahead``); the counters are this object's
        again once the drive has been read to its end. With ``keep``, the first pass to the end reads in this
        process and pickles the blocks into an anonymous temporary file (about 1.2 times the IMU's rows as
        float64; a worker would pickle each block once more to hand it over), and each later pass reads them back
        from it instead of decoding the drive again (the same blocks; :meth:`close` deletes it)."""
        if self._kept is not None:
            self._kept.seek(0)
            return (yield from _unpickled(self._kept))
        if not self.keep:
            ahead, self._ahead = self._ahead or Ahead(self._input_blocks), None
            with ahead as blocks:
                self.__dict__.update((yield from blocks))
            return
        kept = tempfile.TemporaryFile()  # noqa: SIM115 (lives as long as this stream)
        try:
            self.__dict__.update((yield from _pickled(self._input_blocks(), kept)))
        except BaseException:
            kept.close()
            raise
        self._kept = kept

    def start(self) -> None:
        """Begin reading the drive on the second core now, not at the first iteration (without ``keep``): the
        worker decodes the first blocks while the caller gets ready (its imports, its output file), and the
        next iteration takes them. Before any other thread starts: a worker is forked only then
        (``replay.ahead``)."""
        if not self.keep and self._ahead is None:
            import fieldlog.fusion.types  # noqa: F401 - before the fork: the worker's blocks are made of its
            # classes, and the caller, unpickling them, loads it anyway
            self._ahead = Ahead(self._input_blocks)

    def close(self) -> None:
        """Delete the kept blocks (``keep``), a later pass reads the drive again; end a worker :meth:`start`
        began that was not iterated."""
        if self._ahead is not None:
            self._ahead.close()
            self._ahead = None
        if self._kept is not None:
            self._kept.close()
            self._kept = None

    def inputs(self, keep_data: bool = False) -> Iterator[InputBlock]:
        """The engine's blocks, read in this process (``blocks()`` as ``input_block``s); ``keep_data``: each
        with its rows per topic, for a viewer."""
        return (input_block(b, keep_data) for b in self.blocks(engine_only=not keep_data))

    def _input_blocks(self) -> Generator[InputBlock, None, dict]:
        yield from self.inputs()
        return {k: getattr(self, k) for k in _COUNTERS}

    def _canonical(self, data: dict[str, dict], names: dict[str, str]) -> dict[str, dict]:
        out = {names.get(k, k): v for k, v in data.items()}
        imu = out.get(NATIVE[0])
        if imu:
            C = self.imap.C_rfu_imu
            out[NATIVE[0]] = imu = self._count({**imu, "omega_ib_b": imu["omega_ib_b"] @ C.T,
                                                "f_b": imu["f_b"] @ C.T})
            if not len(imu["log_time_ns"]):
                del out[NATIVE[0]]
        return out

    def _count(self, imu: dict) -> dict:
        """Drop repeated stamps, count the samples and gaps."""
        t = imu["log_time_ns"]
        keep = np.ones(len(t), bool)
        keep[1:] = t[1:] > t[:-1]
        if self._last_t is not None:
            keep &= t > self._last_t
        if not keep.all():
            self.repeated += int((~keep).sum())
            imu = {k: v[keep] for k, v in imu.items()}
        t = imu["log_time_ns"]
        steps = np.diff(t if self._last_t is None else np.concatenate([[self._last_t], t]))
        if self._period_ns is None and len(steps) >= 100:
            med = median(steps)  # the mean of the steps near it: less noisy, and no gap or jitter biases it
            self._period_ns = float(np.mean(steps[(steps >= 0.5 * med) & (steps <= 1.5 * med)]))
        if self._period_ns is not None:
            long = steps > 1.5 * self._period_ns
            self.gaps += int(long.sum())
            self.missing += int(np.round(steps[long] / self._period_ns).sum()) - int(long.sum())
            self._dev_sq += float(np.sum((steps[~long] - self._period_ns) ** 2))
            self._steps += int((~long).sum())
            if long.any() and steps[long].max() > self.longest_gap_ns:
                i = int(np.argmax(np.where(long, steps, 0)))
                ends = t[1:] if self._last_t is None else t
                self.longest_gap_ns, self.longest_gap_at_ns = int(steps[i]), int(ends[i])
        if len(t):
            if self._first_t is None:
                self._first_t = int(t[0])
            self._last_t = int(t[-1])
        self.samples += len(t)
        return imu


def _pickled(items: Generator[InputBlock, None, dict], file: IO[bytes]) -> Generator[InputBlock, None, dict]:
    """``items``, each also pickled into ``file``; their generator's return value."""
    while True:
        try:
            item = next(items)
        except StopIteration as stop:
            return stop.value
        pickle.dump(item, file, protocol=pickle.HIGHEST_PROTOCOL)
        yield item


def _unpickled(file: IO[bytes]) -> Iterator[InputBlock]:
    """The blocks :func:`_pickled` wrote into ``file``, from its position to its end."""
    while True:
        try:
            yield pickle.load(file)
        except EOFError:
            return


def input_block(b: reader.Block, keep_data: bool = False) -> InputBlock:
    """A block under fieldlog's topic names as the engine's inputs (``NATIVE``, ``ODOM`` rows of ``odom_rows``).

    Parameters
    ----------
    b : drive.reader.Block
        The block: ``/imu`` in body RFU, ``/gps/fix``, ``/gps/vel`` and ``/vehicle/twist`` rows when it has them.
    keep_data : bool
        Keep ``b.data`` in the result (``InputBlock.data``).

    Returns
    -------
    InputBlock
        Its span, ImuBlock, GpsBlock and OdomBlock (None without wheel speeds).
    """
    d = b.data
    return InputBlock(b.t0_ns, b.t1_ns, imu_block(d.get(NATIVE[0])),
                      reader.gps_block(d.get(NATIVE[1], {}), d.get(NATIVE[2], {})), odom_block(d.get(ODOM)),
                      d if keep_data else None)


def imu_block(imu: dict | None) -> ImuBlock:
    """A block's valid ``/imu`` rows as the engine's ImuBlock (empty without)."""
    from fieldlog.fusion.types import ImuBlock
    if not imu or not len(imu.get("log_time_ns", ())):
        return ImuBlock(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    ok = imu["valid"]
    return ImuBlock(imu["log_time_ns"][ok], imu["omega_ib_b"][ok], imu["f_b"][ok])


def odom_rows(d: dict, wheel_speeds: dict | None = None) -> dict:
    """A decoded odometry batch (``ODOM_TYPES``) as rows: stamp_ns (header), v (forward speed, linear.x, m/s),
    var (its covariance[0]; NaN when the type has none or it is not positive), valid; with ``wheel_speeds`` (the
    decoded ``WHEEL_SPEEDS`` batch of the same block), wheels (n, 4) FL, FR, RL, RR m/s, signed as v, of the
    wheel-speed message with the row's stamp (NaN where none has it)."""
    if "v_n" in d:   # TwistWithCovarianceStamped, batch-decoded
        var = d["covariance"][:, 0].copy()
        rows = {"log_time_ns": d["log_time_ns"], "stamp_ns": d["stamp_ns"], "valid": d["valid"],
                "v": d["v_n"][:, 0].copy(), "var": np.where(var > 0, var, np.nan)}
        if wheel_speeds is not None:
            rows["wheels"] = _wheels_at(rows["stamp_ns"], rows["v"], wheel_speeds)
        return rows
    n = len(d["log_time_ns"])
    stamp, v, var = np.zeros(n, np.int64), np.full(n, np.nan), np.full(n, np.nan)
    for i, m in enumerate(d.get("msgs", [])):
        if m is None:
            continue
        stamp[i] = messages.join_stamp(m.header.stamp.sec, m.header.stamp.nanosec)
        tw = m.twist.twist if hasattr(m.twist, "twist") else m.twist          # Odometry / TwistStamped
        v[i] = tw.linear.x
        cov = getattr(m.twist, "covariance", None)
        var[i] = cov[0] if cov is not None and cov[0] > 0 else np.nan
    return {"log_time_ns": d["log_time_ns"], "stamp_ns": stamp, "valid": np.asarray(d["valid"], bool) & np.isfinite(v),
            "v": v, "var": var}


def _wheels_at(stamp_ns: np.ndarray, v: np.ndarray, d: dict) -> np.ndarray:
    """(n, 4) the wheel speeds (m/s, signed as v) of the ``WHEEL_SPEEDS`` messages of ``d`` stamped as
    ``stamp_ns`` (the last such message; NaN where none)."""
    out = np.full((len(stamp_ns), 4), np.nan)
    msgs = [m for m in d.get("msgs", []) if m is not None]
    if not msgs:
        return out
    t = np.array([messages.join_stamp(m.header.stamp.sec, m.header.stamp.nanosec) for m in msgs], np.int64)
    order = np.argsort(t, kind="stable")
    t, w = t[order], np.array([m.wheel_speed for m in msgs], float)[order]
    i = np.searchsorted(t, stamp_ns, side="right") - 1
    hit = (i >= 0) & (t[np.maximum(i, 0)] == stamp_ns)
    out[hit] = np.abs(w[i[hit]]) * np.where(v[hit] < 0, -1.0, 1.0)[:, None]
    return out


def odom_block(rows: dict | None) -> OdomBlock | None:
    """A block's odometry rows (``odom_rows``, re-sequenced) as the engine's OdomBlock; None without."""
    from fieldlog.fusion.types import OdomBlock
    if not rows or not len(rows.get("log_time_ns", ())):
        return None
    return OdomBlock(rows["log_time_ns"], rows["v"], rows["var"], rows.get("wheels"))


def canonical_blocks(path: str | os.PathLike[str], imap: InputMap, block_s: float, extra: tuple[str, ...] = ()
                     ) -> Iterator[reader.Block]:
    """``InputStream.blocks``: the mapped inputs under fieldlog's own names, re-sequenced as ``fuse`` reads them,
    plus the ``extra`` topics; for the viewer and the player."""
    return InputStream(path, imap, block_s, extra).blocks()
