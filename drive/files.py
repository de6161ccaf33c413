"""Which files make a drive, opened and in order.

A drive is given as one MCAP file, several files, a directory of a rotated ``fieldlog acquire`` session
(``<session start>_0001.mcap``, ``_0002.mcap``, ...), or a rosbag2 directory (``metadata.yaml`` lists its
files in ``relative_file_paths``). ``drive_files`` resolves any of these (or a list mixing them) to the
files; ``open_drive`` opens them (``drive.mcapfile.McapFile``) ordered by their first log time, so they
read as one drive. In a session or rosbag2 directory, ``NAME.recovered.mcap`` (``fieldlog recover``, or the daemon on
restart) stands in for the cut-short (or damaged) ``NAME.mcap`` next to it.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path
from typing import Sequence, Union

from fieldlog.drive.bagdir import METADATA, session_files, stand_in
from fieldlog.drive.mcapfile import McapFile

DriveSpec = Union[str, os.PathLike, Sequence[Union[str, os.PathLike]]]
_OPEN: "OrderedDict[tuple, McapFile]" = OrderedDict()  # recently opened files, by path and version
_OPEN_MAX = 64


def _rosbag2_files(d: Path) -> list[Path]:
    """The files a rosbag2 ``metadata.yaml`` lists (bounded: ``tables.load_yaml``); ValueError in one line naming
    the file and the key when it is not one, or when it names a file outside its directory."""
    from fieldlog.drive import tables

    name = str(d / METADATA)
    doc = tables.load_yaml(tables.read_text(d / METADATA, "rosbag2 metadata file"), name)
    meta = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(meta, dict):
        raise ValueError(f"{name}: no rosbag2_bagfile_information mapping: not a rosbag2 metadata file")
    storage = meta.get("storage_identifier", "mcap")
    if storage != "mcap":
        raise ValueError(f"{d}: rosbag2 storage {storage!r}; only mcap is read (ros2 bag convert it to mcap)")
    if meta.get("relative_file_paths"):
        names, key = meta["relative_file_paths"], "relative_file_paths"
    else:
        files = meta.get("files") or []
        if not isinstance(files, list) or not all(isinstance(f, dict) for f in files):
            raise ValueError(f"{name}: files is not a list of mappings: not a rosbag2 metadata file")
        names, key = [f.get("path") for f in files], "files[].path"
    if not isinstance(names, list):
        raise ValueError(f"{name}: {key} is not a list of file names: not a rosbag2 metadata file")
    out = []
    for i, n in enumerate(names):
        if not isinstance(n, str) or not n or "\0" in n:
            raise ValueError(f"{name}: {key} entry {i} ({type(n).__name__} {str(n)[:40]!r}) is not a file name: not "
                             f"a rosbag2 metadata file")
        p = Path(n)
        if p.is_absolute() or ".." in p.parts:
            raise ValueError(f"{name}: {key} entry {i} ({n[:80]!r}) lies outside the bag's directory: refused, a "
                             f"rosbag2 directory lists only its own files")
        out.append(d / p)
    return out


def _dir_files(d: Path) -> list[Path]:
    """A directory's files (a rosbag2's in its metadata order, else ``*.mcap`` by name), each ``NAME.mcap``
    replaced by ``NAME.recovered.mcap`` when that stands in for it (``bagdir.stand_in``)."""
    if not (d / METADATA).is_file():
        files = session_files(d)
    else:
        files = [stand_in(f) for f in _rosbag2_files(d)]
    if not files:
        raise FileNotFoundError(f"{d}: no .mcap files in the directory")
    return files


def drive_files(spec: DriveSpec) -> list[Path]:
    """The files of a drive (module docstring), in the order given; FileNotFoundError naming what is missing.

    Parameters
    ----------
    spec : a file, a session or rosbag2 directory, or a list of them

    Returns
    -------
    list[Path] : the MCAP files
    """
    if isinstance(spec, (str, os.PathLike)):
        spec = [spec]
    out: list[Path] = []
    for s in spec:
        p = Path(s)
        if p.is_dir():
            out += _dir_files(p)
        elif p.is_file():
            out.append(p)
        else:
            raise FileNotFoundError(f"{p} does not exist")
    for p in out:
        if not p.is_file():
            raise FileNotFoundError(f"{p} does not exist")
    if not out:
        raise FileNotFoundError("no drive file given")
    return out


def label(spec: DriveSpec) -> str:
    """A drive as text: its path, or its paths joined by spaces.

    Parameters
    ----------
    spec : the drive

    Returns
    -------
    str : for messages to the user
    """
    if isinstance(spec, (str, os.PathLike)):
        return str(spec)
    return " ".join(str(s) for s in spec)


def open_file(path: Path) -> McapFile:
    """``McapFile(path)``, reused while the file is unchanged (a command reads a drive several times).

    Parameters
    ----------
    path : an MCAP file

    Returns
    -------
    McapFile : the open file (``ValueError`` subclasses when it is not a whole MCAP file)
    """
    st = path.stat()
    key = (str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns)
    f = _OPEN.get(key)
    if f is None:
        f = _OPEN[key] = McapFile(path)
        if len(_OPEN) > _OPEN_MAX:
            _OPEN.popitem(last=False)
    _OPEN.move_to_end(key)
    return f


def open_drive(spec: DriveSpec) -> list[McapFile]:
    """The drive's files, opened, ordered by their first log time (then as given).

    Parameters
    ----------
    spec : the drive

    Returns
    -------
    list[McapFile] : its files
    """
    files = [open_file(p) for p in drive_files(spec)]
    first = [int(f.pieces.start_ns.min()) if len(f.pieces) else 0 for f in files]
    return [f for _, _, f in sorted(zip(first, range(len(files)), files), key=lambda x: x[:2])]
