"""Output files are created, never followed: the one way the daemon and the tools make a file or folder.

Every output is opened with ``O_CREAT | O_EXCL | O_NOFOLLOW``, so a name that exists (a file, a directory, a
symbolic link, dangling or not) is never written through: a planted link cannot redirect a drive, a report or a
table onto another file. An existing regular file is replaced only when the caller says so (``force``: the
user's ``--force``), by removing the name and creating it afresh; a symbolic link is refused even then (one
line naming it: remove it, or choose another name).

Folders: an output folder given by the user may not be a symbolic link; folders made inside it (``create``
with ``root``) are walked one component at a time through directory file descriptors opened with
``O_NOFOLLOW``, so a link planted as a subfolder of ``--out`` is refused instead of followed, whatever happens
between the check and the write.

Libraries that write only by path (rerun's ``save``) write into ``staged``: a fresh private folder (mode 0700,
random name) next to the destination, whose file is then linked into place (``os.link`` fails on an existing
name; ``force``: ``os.replace``, which replaces a name without following it).

A file made by ``create`` is an ``Output``: an OSError from writing it (a full disk) names the file, and a
``with`` block left on an error (not Ctrl-C) closes and removes it, so a failed command leaves no half-written
file behind.

``Refused`` is a ``ValueError``: every command reports it in one line with exit code 2.
"""
from __future__ import annotations

import contextlib
import io
import os
import shutil
import stat
import tempfile
from pathlib import Path
from typing import Callable, Iterator, Self

CREATE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
DIRECTORY = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC


class Refused(ValueError):
    """An output name that is not written: it exists (without ``force``) or it is a symbolic link."""


def named(e: OSError, path: str | os.PathLike[str]) -> OSError:
    """``e`` with the file ``path`` named in it when it names none (write errors such as ENOSPC do not).

    Parameters
    ----------
    e : the error
    path : the file written

    Returns
    -------
    OSError : ``e``, or a copy naming ``path``
    """
    return e if e.filename is not None or not e.errno else OSError(e.errno, e.strerror, str(path))


class Output(io.BufferedWriter):
    """A new output file open for binary writing (``create``): its OSErrors name it (``named``); leaving a ``with``
    block on an error other than Ctrl-C, or failing to close at its end, ``discard``s it."""

    def __init__(self, fd: int, path: Path) -> None:
        super().__init__(io.FileIO(fd, "wb"))
        self.path = path
        st = os.fstat(fd)
        self._id = (st.st_dev, st.st_ino)

    def write(self, b) -> int:
        """Write ``b``; an OSError names the file.

        Parameters
        ----------
        b : bytes-like

        Returns
        -------
        int : bytes written
        """
        try:
            return super().write(b)
        except OSError as e:
            raise named(e, self.path) from None

    def flush(self) -> None:
        try:
            super().flush()
        except OSError as e:
            raise named(e, self.path) from None

    def close(self) -> None:
        try:
            super().close()
        except OSError as e:
            raise named(e, self.path) from None

    def discard(self) -> None:
        """Close without writing what is buffered and remove the file, if its name is still this file."""
        self.raw.close()
        with contextlib.suppress(OSError):
            now = os.lstat(self.path)
            if (now.st_dev, now.st_ino) == self._id:
                os.unlink(self.path)

    def __exit__(self, kind, value, tb) -> None:
        end(kind, self.close, self.discard)


class Closing:
    """An output used in a ``with`` block: ``close``d at its end, or ``discard``ed on an error other than Ctrl-C, in
    the block or in closing (``end``). The class defines ``close`` and ``discard``."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, kind, value, tb) -> None:
        end(kind, self.close, self.discard)


def end(kind: type[BaseException] | None, close: Callable[[], None], discard: Callable[[], None]) -> None:
    """How an output's ``with`` block ends (``kind``: the exception leaving it, or None): ``close``d, or
    ``discard``ed on an error other than Ctrl-C (which keeps what was written), in the block or in closing.

    Parameters
    ----------
    kind : the exception's type leaving the block, or None
    close, discard : the output's
    """
    if kind is not None and not issubclass(kind, KeyboardInterrupt):
        discard()
        return
    try:
        close()
    except Exception:
        discard()
        raise


def _link_text(path: Path) -> str:
    try:
        return f" (to {os.readlink(path)})"
    except OSError:
        return ""


def _refuse_link(path: Path, what: str = "") -> None:
    raise Refused(f"{path} is a symbolic link{_link_text(path)}{what}: refused, an output is never written "
                  f"through a link; remove it or choose another name")


def _may_replace(st_mode: int, path: Path, force: bool) -> None:
    """Raise unless the existing name ``path`` (of ``st_mode``) may be replaced: a regular file, and ``force``."""
    if stat.S_ISLNK(st_mode):
        _refuse_link(path)
    if stat.S_ISDIR(st_mode):
        raise IsADirectoryError(21, "Is a directory", str(path))
    if not force:
        raise Refused(f"{path} exists: it is left as it is; give --force to replace it, or choose another name")


def check_new(path: str | os.PathLike[str], force: bool = False) -> None:
    """Raise ``Refused`` now (before any work) unless ``path`` can be created: it does not exist, or it is a
    regular file and ``force``.

    Parameters
    ----------
    path : the output
    force : a regular file may be replaced
    """
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    _may_replace(st.st_mode, Path(path), force)


def _open(name: str | os.PathLike[str], shown: Path, force: bool, mode: int, dir_fd: int | None) -> int:
    """``os.open`` of a new file ``name`` (in ``dir_fd``); an existing regular one removed first when ``force``."""
    try:
        return os.open(name, CREATE, mode, dir_fd=dir_fd)
    except FileExistsError:
        _may_replace(os.lstat(name, dir_fd=dir_fd).st_mode, shown, force)
    os.unlink(name, dir_fd=dir_fd)
    return os.open(name, CREATE, mode, dir_fd=dir_fd)


def create(path: str | os.PathLike[str], force: bool = False, root: str | os.PathLike[str] | None = None,
           mode: int = 0o644) -> Output:
    """A new file at ``path``, open for binary writing (``Refused`` if the name exists, unless it is a regular
    file and ``force``; always if it is a symbolic link). ``root``: ``path`` lies inside this output folder
    (``out_dir``), and the folders between are made as needed, each refused if it is a symbolic link.

    Parameters
    ----------
    path : the new file
    force : a regular file there may be replaced
    root : the output folder ``path`` lies in (None: its parent is made by the caller)
    mode : permission bits of a new file

    Returns
    -------
    Output : the file, open
    """
    p = Path(path)
    if root is None:
        return Output(_open(p, p, force, mode, None), p)
    r = Path(root)
    rel = p.relative_to(r)
    fd = _walk(open_dir(r), rel.parts[:-1], r)
    try:
        return Output(_open(rel.parts[-1], p, force, mode, fd), p)
    finally:
        os.close(fd)


def _walk(fd: int, parts: tuple[str, ...], root: Path) -> int:
    """The folder ``parts`` below the open folder ``fd`` (each made if missing, refused if a symbolic link), open;
    ``fd`` and the folders on the way are closed."""
    for name in parts:
        try:
            try:
                os.mkdir(name, 0o755, dir_fd=fd)
            except FileExistsError:
                pass
            try:
                nxt = os.open(name, DIRECTORY, dir_fd=fd)
            except OSError:
                if stat.S_ISLNK(os.lstat(name, dir_fd=fd).st_mode):
                    raise Refused(f"a folder {name!r} inside the output folder {root} is a symbolic link: refused, "
                                  f"an output is never written through a link; remove it or choose another "
                                  f"folder") from None
                raise
        finally:
            os.close(fd)
        fd = nxt
    return fd


def write_bytes(path: str | os.PathLike[str], data: bytes, force: bool = False,
                root: str | os.PathLike[str] | None = None) -> Path:
    """``data`` as the new file ``path`` (``create``); returns ``path``.

    Parameters
    ----------
    path : the new file
    data : its content
    force, root : as ``create``'s

    Returns
    -------
    Path : ``path``
    """
    with create(path, force, root) as f:
        f.write(data)
    return Path(path)


def open_dir(path: str | os.PathLike[str]) -> int:
    """A directory file descriptor of the output folder ``path`` (``Refused`` if it is a symbolic link).

    Parameters
    ----------
    path : the output folder

    Returns
    -------
    int : the descriptor (the caller closes it)
    """
    p = Path(path)
    try:
        return os.open(p, DIRECTORY)
    except OSError:
        if p.is_symlink():
            _refuse_link(p, " where the output folder should be")
        raise


def out_dir(path: str | os.PathLike[str], *parts: str) -> Path:
    """The output folder ``path`` (its parents made as needed), and ``parts`` inside it, made if missing;
    ``Refused`` if ``path`` or one of ``parts`` is a symbolic link (the folders above ``path`` are the user's).

    Parameters
    ----------
    path : the output folder
    parts : folders inside it, one in the other

    Returns
    -------
    Path : the innermost folder
    """
    p = Path(path)
    if p.is_symlink():
        _refuse_link(p, " where the output folder should be")
    p.mkdir(parents=True, exist_ok=True)
    os.close(_walk(open_dir(p), parts, p))
    return p.joinpath(*parts)


@contextlib.contextmanager
def staged(path: str | os.PathLike[str], force: bool = False) -> Iterator[Path]:
    """A path for a writer that takes only a path: in a fresh private folder next to ``path``; when the block
    ends without an error (or on Ctrl-C: what was written so far is kept), its file is put at ``path``
    (``Refused`` if the name was taken meanwhile, unless ``force`` and a regular file), and the folder removed in
    any case.

    Parameters
    ----------
    path : the final file
    force : a regular file there may be replaced

    Returns
    -------
    Iterator[Path] : yields the temporary path to write
    """
    p = Path(path)
    check_new(p, force)
    tmp = Path(tempfile.mkdtemp(prefix=f".{p.name}.", dir=p.parent))
    try:
        work = tmp / p.name
        try:
            yield work
        except KeyboardInterrupt:
            if work.exists():
                publish(work, p, force)
            raise
        publish(work, p, force)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def publish(tmp: str | os.PathLike[str], path: str | os.PathLike[str], force: bool = False) -> None:
    """Put the finished file ``tmp`` at ``path`` (same folder): a new name (``os.link``; ``Refused`` if it exists),
    or with ``force`` in place of a regular file (``os.replace``, which never follows a link at ``path``); ``tmp``
    is removed.

    Parameters
    ----------
    tmp : the finished file
    path : its final name
    force : a regular file there may be replaced
    """
    p = Path(path)
    if force and os.path.lexists(p):
        check_new(p, force)
        os.replace(tmp, p)
        return
    try:
        os.link(tmp, p, follow_symlinks=False)
    except FileExistsError:
        check_new(p, force)
        raise
    os.unlink(tmp)
