"""A drive as polars tables: ``drive_frames(path)`` for notebooks, ``fieldlog export DRIVE... --out DIR``; its
tracks as KML or GPX (``--format kml|gpx``, below).

A drive of several files (a rotated session, a rosbag2 directory: ``drive.files``) gives one table per topic.

One table per topic, one row per MCAP message, in ``log_time`` order; ``fieldlog export`` writes ``/raw/*``
in recorded order instead (the same unless the host wall clock stepped back), streaming. Written as
``DIR/<topic>.parquet`` (or ``.csv``), the topic's path kept: ``/gps/fix`` -> ``DIR/gps/fix.parquet``,
``/fusion/kf/std`` -> ``DIR/fusion/kf/std.parquet``.

Columns. Every table starts with ``log_time_ns`` (int64, the MCAP log time: UTC ns for derived topics, host
wall clock for ``/raw/*``; see docs/data-model.md), ``stamp_ns`` (int64, ``header.stamp`` in ns) and
``valid`` (bool, False for a payload that could not be decoded; its other columns are then 0 / null).
Units and frames are those of docs/data-model.md (SI, ENU, body right-forward-up).

==============================  ====================================================================================
type                            further columns
==============================  ====================================================================================
``sensor_msgs/Imu``             ``omega_ib_b_x/y/z`` rad/s, ``f_b_x/y/z`` m/s^2 (specific force),
                                ``orientation_x/y/z/w``, ``gyro_cov``, ``accel_cov``, ``orientation_cov`` (9 each)
``sensor_msgs/NavSatFix``       ``lat_deg``, ``lon_deg``, ``alt_m`` (ellipsoidal), ``position_covariance`` (9, ENU m^2,
                                row-major), ``covariance_type``, ``status`` (-1 = no fix), ``service``
``TwistWithCovarianceStamped``  ``v_east``, ``v_north``, ``v_up`` m/s, ``omega_x/y/z`` rad/s, ``covariance`` (36)
``QuaternionStamped``           ``q_x``, ``q_y``, ``q_z``, ``q_w`` (body RFU -> ENU)
``Vector3Stamped``              ``x``, ``y``, ``z`` (``/fusion/<m>/std``: position sigma E, N, U in m)
``sensor_msgs/TimeReference``   ``stamp_ns`` (the edge in UTC: the GPS second it marks), ``time_ref_ns`` (the edge
                                on the DAQ clock, k_edge / fs), ``source``
``TimeSyncState``               ``state`` (0 free, 1 holdover, 2 locked), ``rate_ppm``, ``residual_us``,
                                ``edges_used``, ``edges_rejected``
``nmea_msgs/Sentence``          ``frame_id``, ``sentence``
``RawBytes``                    ``mono_ns`` (host monotonic at read), ``port``, ``data`` (binary)
``Outage``                      ``start_ns``, ``end_ns`` (UTC), ``reason``
``nav_msgs/Odometry``           ``frame_id``, ``child_frame_id``, ``x``, ``y``, ``z`` m and ``q_x/y/z/w`` (pose in
                                ``map``), ``v_x/y/z`` m/s and ``omega_x/y/z`` rad/s (twist in ``base_link``),
                                ``pose_covariance``, ``twist_covariance`` (36 each)
``tf2_msgs/TFMessage``          one row per transform (so several per message in ``/tf_static``): ``frame_id``
                                (parent), ``child_frame_id``, ``x``, ``y``, ``z`` m, ``q_x/y/z/w``
==============================  ====================================================================================

Covariances are fixed-size list columns (``pl.Array``) in Parquet. CSV cannot hold lists or bytes, so there
each covariance becomes ``<name>_0`` ... ``<name>_8`` (or ``_35``) and ``data`` is written as hex.

Tracks (``--format kml`` or ``gpx``: ``DIR/tracks.kml``, ``DIR/tracks.gpx``). Every ``sensor_msgs/NavSatFix``
topic of the drive is one track (``track_kind``: ``gnss`` for a receiver's, whatever the logger named it,
``fused`` for ``/fusion/<method>/fix`` and a distributed method's local ``kf1``/``kf2`` fixes, not the
``datum``; ``truth`` for the simulator's ``/truth/fix``), named by its topic: its messages with a fix (valid,
status >= 0, finite latitude and longitude), each at its ``header.stamp`` (UTC, written to the microsecond),
latitude and longitude in WGS-84 degrees as Python writes a float (the shortest text that reads back as the
same float64), height ellipsoidal in m. Each ``/fusion/outage`` window (of every file given) gives every fused
track one more track of its rows inside the window, named ``<topic> outage <reason> <start UTC>``, in the
outage style.

- KML 2.2 (OGC): a Document with a Folder ``tracks`` (one Placemark per topic, its ``gx:Track`` of ``when`` and
  ``gx:coord``) and a Folder ``outages`` (a Placemark per fused track and window, ``#outage`` style: red,
  wide); tracks are drawn clamped to the ground, since KML's absolute heights are above the geoid while the
  drive's are above the ellipsoid (the height is written all the same, 0 where the fix has none). Written with
  fastkml: it writes and reads KML 2.2 with Google's ``gx:`` extension, writes schema-valid documents (the
  OGC schema, which it ships, checks them) and is kept up; simplekml, the other writer on PyPI, writes
  element ids that are not XML ids and ``gx:Track`` children out of the schema's order.
- GPX 1.1: one ``trk`` per track (``type``: its kind, ``outage`` for an outage window's), one ``trkseg``, each
  ``trkpt`` with ``time`` and, where the fix has one, ``ele`` (the ellipsoidal height). Written with gpxpy
  (Apache-2.0, no dependencies, widely used), which also reads GPX 1.0 and 1.1 back (``gpxpy.parse``).
"""

from __future__ import annotations

import datetime
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Callable, Iterator, Sequence

import numpy as np
import polars as pl

from fieldlog.drive import messages, outputs, reader
from fieldlog.drive.files import DriveSpec, drive_files, label
from fieldlog.replay import solutions


def _xyz(prefix: str, a: np.ndarray, names: Sequence[str] = ("x", "y", "z")) -> dict[str, np.ndarray]:
    return {f"{prefix}{n}": a[:, i] for i, n in enumerate(names)}


def _array(a: np.ndarray) -> pl.Series:
    return pl.Series(values=np.ascontiguousarray(a, dtype=np.float64), dtype=pl.Array(pl.Float64, a.shape[1]))


def _stamp(msg) -> int:
    return int(messages.join_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec))


def _generic(d: dict, fields: dict[str, Callable]) -> dict[str, object]:
    msgs = d["msgs"]
    cols: dict[str, object] = {"stamp_ns": pl.Series([_stamp(m) if m is not None else None for m in msgs],
                                                     dtype=pl.Int64)}
    for name, get in fields.items():
        cols[name] = [get(m) if m is not None else None for m in msgs]
    return cols


def _pps_sources(path: DriveSpec, topic: str) -> list[str | None]:
    dec = messages.decoder_for(messages.TIMEREF)
    out = []
    for data in reader.read_payloads(path, topic)[2]:
        try:
            out.append(dec(data).source)
        except Exception:  # bad payload: it is already marked invalid by the batch decoder
            out.append(None)
    return out


def _binary(p: messages.Packed) -> pl.Series:
    """A batch of byte strings as a Binary column, built from its buffers (no per-message Python)."""
    import pyarrow as pa

    buf = p.buf[p.offsets[0]:p.offsets[-1]] if len(p) else np.zeros(0, np.uint8)
    arr = pa.LargeBinaryArray.from_buffers(pa.large_binary(), len(p), [
        None, pa.py_buffer(np.ascontiguousarray(p.offsets - p.offsets[0], np.int64)), pa.py_buffer(buf)])
    return pl.from_arrow(arr).cast(pl.Binary)


def topic_frame(path: DriveSpec, topic: str, type_name: str) -> pl.DataFrame:
    """One topic as a DataFrame (columns: module docstring)."""
    d = reader.read_raw(path, topic) if type_name == messages.RAWBYTES else reader.read_topic(path, topic)
    return _frame(d, type_name, path, topic)


EXPORT_BLOCK_S = 60.0  # export streams the large topics in blocks of this much log time
_STREAMED = (messages.IMU, messages.NAVSATFIX, messages.TWIST, messages.QUATERNION, messages.VECTOR3,
             messages.TIMESYNC)


def topic_batches(path: DriveSpec, topic: str, type_name: str) -> Iterator[pl.DataFrame]:
    """One topic as consecutive DataFrames, so that memory holds one block: ``/raw/*`` one MCAP chunk at a
    time in recorded order, the typed sensor topics ``EXPORT_BLOCK_S`` of log time at a time, the small
    ones (sentences, PPS, outages) whole."""
    if type_name == messages.RAWBYTES:
        batches: Iterator[dict] = reader.iter_raw_batches(path, topic)
    elif type_name in _STREAMED:
        batches = (b.data[topic] for b in reader.iter_blocks(path, [topic], EXPORT_BLOCK_S))
    else:
        batches = iter([reader.read_topic(path, topic)])
    for d in batches:
        if len(d["log_time_ns"]):
            yield _frame(d, type_name, path, topic)


def _frame(d: dict, type_name: str, path: DriveSpec, topic: str) -> pl.DataFrame:
    cols: dict[str, object] = {"log_time_ns": d["log_time_ns"]}
    if type_name == messages.IMU:
        cols["stamp_ns"] = d["stamp_ns"]
        cols.update(_xyz("omega_ib_b_", d["omega_ib_b"]))
        cols.update(_xyz("f_b_", d["f_b"]))
        cols.update(_xyz("orientation_", d["orientation_xyzw"], ("x", "y", "z", "w")))
        cols.update(gyro_cov=_array(d["gyro_cov"]), accel_cov=_array(d["accel_cov"]),
                    orientation_cov=_array(d["orientation_cov"]))
    elif type_name == messages.NAVSATFIX:
        cols.update({k: d[k] for k in ("stamp_ns", "lat_deg", "lon_deg", "alt_m")})
        cols["position_covariance"] = _array(d["position_covariance"])
        cols.update({k: d[k] for k in ("covariance_type", "status", "service")})
    elif type_name == messages.TWIST:
        cols["stamp_ns"] = d["stamp_ns"]
        cols.update(_xyz("v_", d["v_n"], ("east", "north", "up")))
        cols.update(_xyz("omega_", d["omega"]))
        cols["covariance"] = _array(d["covariance"])
    elif type_name == messages.QUATERNION:
        cols["stamp_ns"] = d["stamp_ns"]
        cols.update(_xyz("q_", d["q_xyzw"], ("x", "y", "z", "w")))
    elif type_name == messages.VECTOR3:
        cols["stamp_ns"] = d["stamp_ns"]
        cols.update(_xyz("", d["xyz"]))
    elif type_name == messages.TIMEREF:
        cols.update(stamp_ns=d["stamp_ns"], time_ref_ns=d["time_ref_ns"], source=_pps_sources(path, topic))
    elif type_name == messages.TIMESYNC:
        cols.update({k: d[k] for k in ("stamp_ns", "state", "rate_ppm", "residual_us", "edges_used",
                                       "edges_rejected")})
    elif type_name == messages.SOLUTION_STATUS:
        cols.update({k: d[k] for k in ("stamp_ns", "status", "since_update_s", "sigma_h_m", "nis")})
    elif type_name == messages.SENTENCE:
        cols.update(_generic(d, {"frame_id": lambda m: m.header.frame_id, "sentence": lambda m: m.sentence}))
    elif type_name == messages.RAWBYTES:
        ok = pl.Series(d["valid"])
        cols.update(stamp_ns=d["stamp_ns"], mono_ns=d["mono_ns"],
                    port=pl.Series(d["port"], dtype=pl.String).zip_with(ok, pl.Series([None], dtype=pl.String)),
                    data=_binary(d["data"]).zip_with(ok, pl.Series([None], dtype=pl.Binary)))
    elif type_name == messages.OUTAGE:
        cols.update(_generic(d, {"start_ns": lambda m: int(m.start_ns), "end_ns": lambda m: int(m.end_ns),
                                 "reason": lambda m: m.reason}))
        cols["start_ns"] = pl.Series(cols["start_ns"], dtype=pl.Int64)
        cols["end_ns"] = pl.Series(cols["end_ns"], dtype=pl.Int64)
    elif type_name == messages.ODOMETRY:
        pose, twist = (lambda m: m.pose.pose), (lambda m: m.twist.twist)
        fields = {"frame_id": lambda m: m.header.frame_id, "child_frame_id": lambda m: m.child_frame_id}
        fields.update({c: (lambda m, c=c: getattr(pose(m).position, c)) for c in "xyz"})
        fields.update({f"q_{c}": (lambda m, c=c: getattr(pose(m).orientation, c)) for c in "xyzw"})
        fields.update({f"v_{c}": (lambda m, c=c: getattr(twist(m).linear, c)) for c in "xyz"})
        fields.update({f"omega_{c}": (lambda m, c=c: getattr(twist(m).angular, c)) for c in "xyz"})
        cols.update(_generic(d, fields))
        zeros = [0.0] * 36
        for name in ("pose", "twist"):
            cov = [list(getattr(m, name).covariance) if m is not None else zeros for m in d["msgs"]]
            cols[f"{name}_covariance"] = _array(np.array(cov, dtype=np.float64).reshape(-1, 36))
    elif type_name == messages.TFMESSAGE:
        rows = [(t_log, tf) for t_log, m in zip(d["log_time_ns"].tolist(), d["msgs"]) if m is not None
                for tf in m.transforms]
        tr = [tf.transform for _, tf in rows]
        return pl.DataFrame({
            "log_time_ns": pl.Series([t for t, _ in rows], dtype=pl.Int64),
            "stamp_ns": pl.Series([_stamp(tf) for _, tf in rows], dtype=pl.Int64),
            "frame_id": pl.Series([tf.header.frame_id for _, tf in rows], dtype=pl.String),
            "child_frame_id": pl.Series([tf.child_frame_id for _, tf in rows], dtype=pl.String),
            **{c: pl.Series([getattr(x.translation, c) for x in tr], dtype=pl.Float64) for c in "xyz"},
            **{f"q_{c}": pl.Series([getattr(x.rotation, c) for x in tr], dtype=pl.Float64) for c in "xyzw"},
            "valid": pl.Series([True] * len(rows), dtype=pl.Boolean)})
    else:
        raise KeyError(f"{topic}: no table layout for type {type_name!r}")
    cols["valid"] = d["valid"]
    return pl.DataFrame(cols)


def _topic_types(path: DriveSpec, topics: Sequence[str] | None) -> list[tuple[str, str]]:
    infos = reader.topics(path)
    if topics is not None:
        known = {t.topic for t in infos}
        missing = [t for t in topics if t not in known]
        if missing:
            raise KeyError(f"not in {path}: {', '.join(missing)}")
        infos = [t for t in infos if t.topic in topics]
    return [(t.topic, t.type) for t in infos]


def drive_frames(path: DriveSpec, topics: Sequence[str] | None = None) -> dict[str, pl.DataFrame]:
    """A drive as ``{topic: DataFrame}`` (all topics, or ``topics``); columns in the module docstring."""
    return {topic: topic_frame(path, topic, type_name) for topic, type_name in _topic_types(path, topics)}


def csv_ready(df: pl.DataFrame) -> pl.DataFrame:
    """Array columns -> ``<name>_<i>`` columns, binary -> hex text (CSV holds neither)."""
    exprs = []
    for name, dtype in df.schema.items():
        if isinstance(dtype, pl.Array):
            exprs += [pl.col(name).arr.get(i).alias(f"{name}_{i}") for i in range(dtype.size)]
        elif dtype == pl.Binary:
            exprs.append(pl.col(name).bin.encode("hex"))
        else:
            exprs.append(pl.col(name))
    return df.select(exprs)


def table_path(out: Path, topic: str, fmt: str) -> Path:
    """``out/<topic>.<fmt>``, the topic's '/' levels kept as directories. A topic name comes from the drive, so
    it is cleaned: characters other than letters, digits, '_', '-' and '.' become '_', empty levels are dropped
    and a level of dots ('.', '..') becomes underscores; the path always stays under ``out``."""
    parts = [re.sub(r"[^A-Za-z0-9_.-]", "_", p) for p in topic.split("/") if p]
    parts = [p if p.strip(".") else "_" * len(p) for p in parts] or ["_"]
    return out.joinpath(*parts[:-1], f"{parts[-1]}.{fmt}")


FORMATS = ("parquet", "csv", "kml", "gpx")
TRACK_FORMATS = ("kml", "gpx")


def export(path: DriveSpec, out: str | os.PathLike[str], fmt: str = "parquet",
           topics: Sequence[str] | None = None,
           progress: Callable[[float], None] | None = None, force: bool = False) -> dict[str, tuple[Path, int]]:
    """Write one table per topic under ``out``, streamed (``topic_batches``), or the NavSatFix topics as tracks
    in one KML or GPX file (``export_tracks``). -> {topic: (file, rows)}. Every file is new (unless ``force``),
    and ``out`` and the folders made in it are never symbolic links (``drive.outputs``). On an error (a full disk) the tables written so far are removed: all or nothing."""
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    drive_files(path)  # FileNotFoundError naming a missing file
    todo = _topic_types(path, topics)
    if fmt in TRACK_FORMATS:
        return export_tracks(path, out, fmt, [t for t, type_name in todo if type_name == messages.NAVSATFIX],
                             progress, force)
    out = outputs.out_dir(out)
    dests: list[Path] = []
    for topic, _ in todo:
        dest, n = table_path(out, topic, fmt), 1
        while dest in dests:                      # two topics cleaned to the same name: number the later ones
            n += 1
            dest = table_path(out, f"{topic}~{n}", fmt)
        outputs.check_new(dest, force)            # every table refused before the first is written
        dests.append(dest)
    written: dict[str, tuple[Path, int]] = {}
    try:
        for i, ((topic, type_name), dest) in enumerate(zip(todo, dests)):
            with outputs.create(dest, force, root=out) as f:
                written[topic] = (dest, _write(topic_batches(path, topic, type_name), f, fmt,
                                               lambda: topic_frame(path, topic, type_name)))
            if progress:
                progress((i + 1) / len(todo))
    except Exception:
        for dest, _ in written.values():
            dest.unlink(missing_ok=True)
        raise
    return written


def _write(frames: Iterator[pl.DataFrame], f: BinaryIO, fmt: str, empty: Callable[[], pl.DataFrame]) -> int:
    """Append the frames to one Parquet or CSV file open in ``f``; rows written. ``empty`` gives the (empty) table
    of a topic without messages, for its schema."""
    import pyarrow.parquet as pq

    rows, writer = 0, None
    for df in frames:
        if fmt == "csv":
            csv_ready(df).write_csv(f, include_header=rows == 0)
        else:
            tbl = df.to_arrow()
            if writer is None:
                writer = pq.ParquetWriter(f, tbl.schema, compression="zstd")
            writer.write_table(tbl.cast(writer.schema))
        rows += df.height
    if writer is not None:
        writer.close()
    if rows == 0:
        df = empty()
        if fmt == "parquet":
            df.write_parquet(f, compression="zstd")
        else:
            csv_ready(df).write_csv(f)
    return rows


# ---------------------------------------------------------------------------------------------
# Tracks: KML and GPX


@dataclass
class GeoTrack:
    """One NavSatFix topic's fixes (module docstring, "Tracks")."""

    name: str  # the topic, or its outage window's name
    kind: str  # gnss, fused, truth or outage
    stamp_ns: np.ndarray  # (n,) int64 header stamps, UTC ns
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray  # ellipsoidal, NaN where the fix has no height

    def take(self, sel: np.ndarray, name: str, kind: str) -> "GeoTrack":
        return GeoTrack(name, kind, self.stamp_ns[sel], self.lat_deg[sel], self.lon_deg[sel], self.alt_m[sel])


KML_COLORS = {"gnss": "ff008cff", "truth": "ff14a014", "outage": "c81e1ee6"}  # aabbggrr
FUSED_KML_COLORS = ("ffff641e", "ffd23c96", "ffbeaf00", "ff0078c8", "ffa03ce6")


def track_kind(topic: str) -> str:
    """``fused`` (``/fusion/...``), ``truth`` (``/truth/...``) or ``gnss`` (any other NavSatFix topic)."""
    return "fused" if topic.startswith(solutions.PREFIX) else "truth" if topic.startswith("/truth/") else "gnss"


def geo_tracks(path: DriveSpec, fix_topics: Sequence[str]) -> list[GeoTrack]:
    """The tracks of ``fix_topics`` (NavSatFix topics of ``path``), then the outage windows' tracks of the fused
    ones; topics without a fix give none, and neither does a fused file's ``datum`` (its map frame's origin)."""
    tracks = []
    for topic in fix_topics:
        if track_kind(topic) == "fused" and not topic.endswith("/fix"):
            continue
        d = reader.read_topic(path, topic)
        ok = d["valid"] & (d["status"] >= 0) & np.isfinite(d["lat_deg"]) & np.isfinite(d["lon_deg"])
        if ok.any():
            tracks.append(GeoTrack(topic, track_kind(topic), d["stamp_ns"][ok], d["lat_deg"][ok], d["lon_deg"][ok],
                                   d["alt_m"][ok]))
    windows = []
    if any(t.kind == "fused" for t in tracks) and any(t.topic == solutions.OUTAGE for t in reader.topics(path)):
        windows = sorted((int(m.start_ns), int(m.end_ns), m.reason)
                         for m in reader.read_topic(path, solutions.OUTAGE)["msgs"] if m is not None)
    outages = []
    for trk in (t for t in tracks if t.kind == "fused"):
        for start, end, reason in windows:
            inside = (trk.stamp_ns >= start) & (trk.stamp_ns <= end)
            if inside.any():
                outages.append(trk.take(inside, f"{trk.name} outage {reason} {_utc(start).isoformat()}", "outage"))
    return tracks + outages


def _utc(t_ns: int) -> datetime.datetime:
    """UTC ns -> an aware datetime, rounded to the microsecond (the finest a datetime holds)."""
    return datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc) + datetime.timedelta(
        microseconds=(int(t_ns) + 500) // 1000)


def write_kml(tracks: Sequence[GeoTrack], title: str, f: BinaryIO) -> None:
    """The tracks as one KML 2.2 document (module docstring) into the binary file ``f``."""
    import pygeoif
    from fastkml import containers, enums, features, gx, kml, styles
    from fastkml.times import KmlDateTime

    style_ids = {"gnss": "gnss", "truth": "truth", "outage": "outage"}
    fused = [t.name for t in tracks if t.kind == "fused"]
    style_ids.update({name: f"fused{i}" for i, name in enumerate(fused)})
    colors = {**KML_COLORS, **{f"fused{i}": FUSED_KML_COLORS[i % len(FUSED_KML_COLORS)] for i in range(len(fused))}}
    folders: dict[str, list] = {"tracks": [], "outages": []}
    for t in tracks:
        alt = np.where(np.isfinite(t.alt_m), t.alt_m, 0.0).tolist()
        items = [gx.TrackItem(when=KmlDateTime(_utc(ns)), coord=pygeoif.Point(lon, lat, h))
                 for ns, lat, lon, h in zip(t.stamp_ns.tolist(), t.lat_deg.tolist(), t.lon_deg.tolist(), alt)]
        style = style_ids[t.name if t.kind == "fused" else t.kind]
        folders["outages" if t.kind == "outage" else "tracks"].append(features.Placemark(
            name=t.name, description=f"{t.kind}: {len(items)} fixes", style_url=styles.StyleUrl(url=f"#{style}"),
            kml_geometry=gx.Track(altitude_mode=enums.AltitudeMode.clamp_to_ground, track_items=items)))
    doc = containers.Document(
        name=title, styles=[styles.Style(id=i, styles=[styles.LineStyle(color=c, width=6.0 if i == "outage" else 3.0)])
                            for i, c in colors.items()],
        features=[containers.Folder(name=k, features=v) for k, v in folders.items() if v])
    f.write(b'<?xml version="1.0" encoding="UTF-8"?>\n')
    f.write(kml.KML(features=[doc]).to_string(prettyprint=True).encode("utf-8"))


def write_gpx(tracks: Sequence[GeoTrack], title: str, f: BinaryIO) -> None:
    """The tracks as one GPX 1.1 document (module docstring) into the binary file ``f``."""
    import gpxpy.gpx

    doc = gpxpy.gpx.GPX()
    doc.creator, doc.name = "fieldlog", title
    for t in tracks:
        seg = gpxpy.gpx.GPXTrackSegment([
            gpxpy.gpx.GPXTrackPoint(lat, lon, elevation=h if np.isfinite(h) else None, time=_utc(ns))
            for ns, lat, lon, h in zip(t.stamp_ns.tolist(), t.lat_deg.tolist(), t.lon_deg.tolist(), t.alt_m.tolist())])
        trk = gpxpy.gpx.GPXTrack(name=t.name)
        trk.type = t.kind
        trk.segments.append(seg)
        doc.tracks.append(trk)
    f.write(doc.to_xml(version="1.1").encode("utf-8"))


def export_tracks(path: DriveSpec, out: str | os.PathLike[str], fmt: str, fix_topics: Sequence[str],
                  progress: Callable[[float], None] | None = None, force: bool = False) -> dict[str, tuple[Path, int]]:
    """``fix_topics`` of ``path`` as ``out/tracks.kml`` or ``out/tracks.gpx`` (module docstring, "Tracks"), a new
    file unless ``force``. -> {track name: (file, fixes)}; ValueError when no topic has a fix."""
    tracks = geo_tracks(path, fix_topics)
    if not tracks:
        raise ValueError(f"{label(path)}: no GNSS or fused fixes (sensor_msgs/NavSatFix) to write as {fmt.upper()}")
    if progress:
        progress(0.5)
    dest = outputs.out_dir(out) / f"tracks.{fmt}"
    with outputs.create(dest, force, root=out) as f:
        (write_kml if fmt == "kml" else write_gpx)(tracks, label(path), f)
    if progress:
        progress(1.0)
    return {t.name: (dest, len(t.stamp_ns)) for t in tracks}
