"""rosbag2 directories: ``metadata.yaml`` next to MCAP files, so a session or an output opens as a bag.

``ros2 bag info/play`` and rosbags' ``Reader`` open a directory through its ``metadata.yaml``
(``rosbag2_bagfile_information``, version 9 as rosbag2 Jazzy writes it): the storage (``mcap``), the files in
order (``relative_file_paths``, and ``files`` with each file's start, duration and message count), every
topic with its type, serialization format (``cdr``), offered QoS and message count, and the bag's start,
duration and message total. rosbags matches a topic of the metadata with the MCAP channel by topic, type,
serialization format and QoS, so the QoS given here is parsed from the channel's own ``offered_qos_profiles``.
Durations are last minus first log time (ns), as rosbag2 writes them. Compression is none at the rosbag2 level:
the MCAP chunks are compressed inside the storage.

Everything is read from each file's MCAP summary (statistics and channels), so only finished files can be
listed: the daemon lists a session's closed files at each rotation and all of them on close;
``fieldlog recover`` writes it again from the files on disk. ``write_metadata`` writes a new file and renames
it over ``metadata.yaml`` (atomic; a symlink planted at that name is replaced, never followed).
"""
from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path

from fieldlog.drive import outputs, tables

METADATA = "metadata.yaml"
RECOVERED = ".recovered.mcap"     # ``fieldlog recover``'s output stands in for the cut-short NAME.mcap
VERSION = 9
ROS_DISTRO = "jazzy"


@dataclass(frozen=True)
class TopicInfo:
    name: str
    type: str
    serialization_format: str
    offered_qos_profiles: list
    type_description_hash: str
    message_count: int


@dataclass(frozen=True)
class FileInfo:
    """One MCAP file's share of the bag (log times in ns since the Unix epoch; counts 0 for an empty file)."""

    path: Path
    start_ns: int
    end_ns: int
    message_count: int
    topics: tuple[TopicInfo, ...]


def file_info(path: Path) -> FileInfo:
    """What the metadata says of one finished MCAP file, from its summary; ValueError when it has none.

    Parameters
    ----------
    path : a finished MCAP file

    Returns
    -------
    FileInfo : its path, duration and per-topic counts
    """
    from mcap.reader import make_reader  # here, not at the top: it would add to every command's start-up

    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - mcap's reader raises its own kinds on a file cut short or damaged
            summary = None
    if summary is None or summary.statistics is None:
        raise ValueError(f"{path}: no MCAP summary with statistics (an unfinished file: run `fieldlog recover`)")
    st = summary.statistics
    topics = []
    for cid, ch in sorted(summary.channels.items()):
        schema = summary.schemas.get(ch.schema_id)
        qos = tables.load_yaml(ch.metadata.get("offered_qos_profiles", "") or "[]",
                               f"{path}: channel {ch.topic} offered_qos_profiles") or []
        topics.append(TopicInfo(ch.topic, schema.name if schema else "", ch.message_encoding, qos,
                                ch.metadata.get("topic_type_hash", ""),
                                int(st.channel_message_counts.get(cid, 0))))
    n = int(st.message_count)
    return FileInfo(path, int(st.message_start_time) if n else 0, int(st.message_end_time) if n else 0, n,
                    tuple(topics))


def metadata(files: list[FileInfo], custom_data: dict[str, str] | None = None) -> dict:
    """The ``metadata.yaml`` content for ``files`` (in bag order, all in one directory).

    Parameters
    ----------
    files : the bag's files, in bag order
    custom_data : rosbag2's ``custom_data`` (None: none)

    Returns
    -------
    dict : the YAML document
    """
    with_msgs = [f for f in files if f.message_count]
    start = min((f.start_ns for f in with_msgs), default=0)
    end = max((f.end_ns for f in with_msgs), default=0)
    topics: dict[tuple[str, str], dict] = {}
    for f in files:
        for t in f.topics:
            key = (t.name, t.type)
            if key not in topics:
                topics[key] = {"topic_metadata": {"name": t.name, "type": t.type,
                                                  "serialization_format": t.serialization_format,
                                                  "offered_qos_profiles": t.offered_qos_profiles,
                                                  "type_description_hash": t.type_description_hash},
                               "message_count": 0}
            topics[key]["message_count"] += t.message_count
    return {"rosbag2_bagfile_information": {
        "version": VERSION,
        "storage_identifier": "mcap",
        "relative_file_paths": [f.path.name for f in files],
        "duration": {"nanoseconds": end - start},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": sum(f.message_count for f in files),
        "topics_with_message_count": list(topics.values()),
        "compression_format": "",
        "compression_mode": "",
        "files": [{"path": f.path.name, "starting_time": {"nanoseconds_since_epoch": f.start_ns},
                   "duration": {"nanoseconds": f.end_ns - f.start_ns}, "message_count": f.message_count}
                  for f in files],
        "custom_data": custom_data or None,
        "ros_distro": ROS_DISTRO,
    }}


def write_metadata(directory: Path, files: list[FileInfo], custom_data: dict[str, str] | None = None,
                   fsync: bool = True) -> Path:
    """Write ``directory/metadata.yaml`` for ``files`` atomically: a new file (never an existing path or a
    symlink: O_EXCL | O_NOFOLLOW), fsynced, renamed over the old one. Returns its path.

    Parameters
    ----------
    directory : the bag directory
    files : its files, in bag order
    custom_data : rosbag2's ``custom_data`` (None: none)
    fsync : fsync the file and the directory

    Returns
    -------
    Path : ``directory/metadata.yaml``
    """
    import yaml

    text = yaml.safe_dump(metadata(files, custom_data), sort_keys=False, default_flow_style=False)
    dst = directory / METADATA
    tmp = directory / f".{METADATA}.{os.getpid()}.tmp"
    try:
        tmp.unlink()                  # a leftover of a killed writer with this pid (unlink never follows)
    except FileNotFoundError:
        pass
    try:
        with outputs.create(tmp) as f:
            f.write(text.encode())
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return dst


def session_files(directory: Path) -> list[Path]:
    """A directory's MCAP files on disk by name (a session's in rotation order), each ``NAME.mcap`` replaced by
    ``NAME.recovered.mcap`` when that stands in for it (``stand_in``).

    Parameters
    ----------
    directory : a session or rosbag2 directory

    Returns
    -------
    list[Path] : its MCAP files
    """
    names = sorted({f.with_name(f.name[: -len(RECOVERED)] + ".mcap") if f.name.endswith(RECOVERED) else f
                    for f in directory.glob("*.mcap")})
    return [stand_in(f) for f in names]


def stand_in(f: Path) -> Path:
    """``NAME.recovered.mcap`` in place of ``f`` (``NAME.mcap``) when it is a regular file (a symbolic link never
    stands in) at least as new as ``f``; else ``f``.

    Parameters
    ----------
    f : a session's file, ``NAME.mcap``

    Returns
    -------
    Path : the file that stands for it
    """
    r = f.with_name(f.stem + RECOVERED)
    try:
        st = os.lstat(r)
    except OSError:
        return f
    if not stat.S_ISREG(st.st_mode):
        return f
    try:
        return f if st.st_mtime_ns < os.stat(f).st_mtime_ns else r
    except OSError:
        return r


def rewrite_metadata(directory: Path) -> tuple[Path, list[Path]]:
    """``metadata.yaml`` of a session directory written again from its files on disk (``session_files``);
    files without a summary (not recovered yet) are left out and returned.

    Parameters
    ----------
    directory : the session directory

    Returns
    -------
    path : the ``metadata.yaml`` written
    left_out : the files without a summary
    """
    infos, unfinished = [], []
    for f in session_files(directory):
        try:
            infos.append(file_info(f))
        except ValueError:
            unfinished.append(f)
    return write_metadata(directory, infos), unfinished


def bag_file(out: Path) -> Path:
    """The MCAP file of a one-file bag ``out`` (``--bag``): ``out/<name>.mcap``, ``name`` = ``out`` without a
    ``.mcap`` suffix; the directory is made as every output folder is (``outputs.out_dir``: a symbolic link there
    is refused, ``outputs.Refused``; a file there raises ValueError).

    Parameters
    ----------
    out : the bag directory (``--out``)

    Returns
    -------
    Path : the MCAP file inside it
    """
    d = out.with_suffix("") if out.suffix == ".mcap" else out
    if not d.is_symlink() and d.exists() and not d.is_dir():
        raise ValueError(f"{d}: exists and is not a directory; --bag writes a rosbag2 directory there")
    outputs.out_dir(d)
    return d / f"{d.name}.mcap"


def write_bag_metadata(mcap: Path) -> Path:
    """``metadata.yaml`` for the one-file bag whose file ``bag_file`` gave.

    Parameters
    ----------
    mcap : the bag's finished MCAP file

    Returns
    -------
    Path : the ``metadata.yaml`` beside it
    """
    return write_metadata(mcap.parent, [file_info(mcap)])
