"""A drive as one object: its files opened once, and checked as a whole before any block is read.

``Drive.open(spec)`` takes what a command is given (a file, several files, a session or rosbag2 directory, or a
list mixing them: ``drive.files``), opens every file once (``drive.files.open_drive``: a file is mapped and its
summary read once per process) and holds what the commands ask of a drive: its sources' time ranges, its
metadata records and each file's ``/tf_static``. A ``Drive`` is a list of the paths it was opened from, so every
function that takes a ``DriveSpec`` takes it (and finds its files already open).

Several sources (files or directories given) make one drive only if they agree, which a single file cannot get
wrong and the checks here catch before the long work:

* two files giving different static transforms for the same child frame: ``DriveError`` naming both files and the
  frame, unless ``tf_from`` names the file whose transforms are the drive's, or the frame is ``imu`` and its axes
  are given (``--imu-frame``);
* sources whose log-time ranges are apart by more than ``MAX_GAP_S`` (a boot-relative log anchored at the wrong
  time, a file of another day): ``DriveError`` naming them. The files of one session directory follow each other
  and count as one source.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
import numpy as np

from fieldlog.drive import messages, reader
from fieldlog.drive.files import DriveSpec, drive_files, label, open_drive
from fieldlog.fusion import earth

TF_STATIC = "/tf_static"
IMU_FRAME = "imu"
MAX_GAP_S = 10.0  # sources further apart in log time than this are not one drive
_SAME_M, _SAME_ROT = 1e-6, 1e-6  # transforms closer than this (m; rotation matrix entries) are the same

Transform = tuple[str, np.ndarray, np.ndarray]  # parent frame, translation (3,) m, C_parent_child (3, 3)


class DriveError(ValueError):
    """Files that do not make one drive: one line naming them and what to do."""


@dataclass(frozen=True)
class Source:
    """One item of the drive's spec (a file or a directory): its files and its log-time range, ns (None: no
    messages)."""

    spec: Path
    files: tuple[Path, ...]
    start_ns: int | None
    end_ns: int | None


def file_transforms(path: Path) -> dict[str, Transform]:
    """One file's static transforms: child frame -> (parent frame, translation (3,) m, C_parent_child (3, 3)),
    the last message's for a frame given twice.

    Parameters
    ----------
    path : one MCAP file

    Returns
    -------
    dict[str, Transform] : by child frame
    """
    out: dict[str, Transform] = {}
    for type_name, data in reader.iter_payloads(path, TF_STATIC):
        if type_name != messages.TFMESSAGE:
            continue  # not transforms
        try:
            transforms = messages.decode_tf(data)
        except ValueError as e:
            raise ValueError(f"{path}: a {TF_STATIC} message does not decode ({e}): the file is damaged there and "
                             "its static transforms cannot be read") from None
        for parent, child, t, q_xyzw in transforms:
            out[child.lstrip("/")] = (parent.lstrip("/"), t, earth.quat_to_dcm(q_xyzw))
    return out


def _same(a: Transform, b: Transform) -> bool:
    return a[0] == b[0] and np.allclose(a[1], b[1], atol=_SAME_M) and np.allclose(a[2], b[2], atol=_SAME_ROT)


class Drive(list):
    """The paths a drive was opened from (a ``DriveSpec``), with what ``open`` read of its files.

    sources: each item of the spec with its files and log-time range; transforms: each file's static transforms
    (``file_transforms``); tf_from: the file whose transforms win where files differ (None: none differ, or only
    ``imu`` with its axes given)."""

    sources: list[Source]
    transforms: dict[Path, dict[str, Transform]]
    tf_from: Path | None

    @classmethod
    def open(cls, spec: DriveSpec, tf_from: str | os.PathLike[str] | None = None,
             imu_axes_given: bool = False) -> "Drive":
        """Open every file of ``spec`` once and check the files as one drive (module docstring). ``tf_from``:
        the file (one of the drive's) whose /tf_static wins; ``imu_axes_given``: the IMU's axes are given
        (``--imu-frame``), so files may differ on the ``imu`` frame. Raises DriveError (one line) when the files
        are not one drive, FileNotFoundError for a missing file.

        Parameters
        ----------
        spec : the drive (``drive.files.DriveSpec``)
        tf_from : the file whose transforms win (None: files must agree)
        imu_axes_given : the IMU's axes come from an option

        Returns
        -------
        Drive : the paths of ``spec``, with their sources and transforms
        """
        items = [spec] if isinstance(spec, (str, os.PathLike)) else list(spec)
        d = cls(items)
        open_drive(d)  # every file mapped and its summary read, once
        d.sources = [d._source(Path(s)) for s in items]
        d.transforms = {f.path: file_transforms(f.path) for f in open_drive(d)}  # in log-time order
        d.tf_from = d._tf_from(tf_from) if tf_from is not None else None
        d._check_times()
        d._check_transforms(imu_axes_given)
        return d

    @staticmethod
    def _source(spec: Path) -> Source:
        files = tuple(drive_files(spec))
        starts, ends = [], []
        for f in open_drive(spec):
            if len(f.pieces):
                starts.append(int(f.pieces.start_ns.min()))
                ends.append(int(f.pieces.end_ns.max()))
        return Source(spec, files, min(starts) if starts else None, max(ends) if ends else None)

    def _tf_from(self, path: str | os.PathLike[str]) -> Path:
        want = Path(path).resolve()
        for p in self.transforms:
            if p.resolve() == want:
                return p
        raise DriveError(f"--tf-from {path}: not one of the drive's files ({label(self)})")

    def _check_transforms(self, imu_axes_given: bool) -> None:
        if self.tf_from is not None:
            return
        seen: dict[str, tuple[Path, Transform]] = {}
        for path, tf in self.transforms.items():
            for frame, t in tf.items():
                if frame in seen and not _same(seen[frame][1], t) and not (imu_axes_given and frame == IMU_FRAME):
                    raise DriveError(
                        f"{seen[frame][0]} and {path} give different /tf_static transforms for frame {frame!r}: "
                        f"say which file's to use with --tf-from FILE"
                        + (" (or the IMU's axes with --imu-frame)" if frame == IMU_FRAME else ""))
                seen.setdefault(frame, (path, t))

    def _check_times(self) -> None:
        timed = sorted((s for s in self.sources if s.start_ns is not None), key=lambda s: s.start_ns)
        if not timed:
            return
        last = timed[0]  # the source that reaches latest so far
        for s in timed[1:]:
            gap_s = (s.start_ns - last.end_ns) / 1e9
            if gap_s > MAX_GAP_S:
                raise DriveError(
                    f"{last.spec} and {s.spec} do not overlap in time ({_apart(gap_s)} apart): they are not one "
                    "drive; fuse them separately, or import a boot-relative log again with --align-to DRIVE or "
                    "--start")
            if s.end_ns > last.end_ns:
                last = s

    @property
    def start_ns(self) -> int | None:
        """The first log time of the drive, ns (None: no messages)."""
        starts = [s.start_ns for s in self.sources if s.start_ns is not None]
        return min(starts) if starts else None

    def tf_static(self) -> dict[str, Transform]:
        """The drive's static transforms (child frame -> parent, translation, C_parent_child): every file's, in
        log-time order, ``tf_from``'s last so that it wins.

        Returns
        -------
        dict[str, Transform] : by child frame; translations m, rotations C_parent_child
        """
        out: dict[str, Transform] = {}
        for p in sorted(self.transforms, key=lambda p: p == self.tf_from):
            out.update(self.transforms[p])
        return out


def _apart(seconds: float) -> str:
    return f"{seconds / 86400:.0f} days" if seconds >= 2 * 86400 else f"{seconds:.0f} s"

