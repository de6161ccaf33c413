"""A drive's work on the second core: a generator or an object run in a forked worker process beside its caller.

Reading a drive (zstd, the CDR decode, the input mapping), training an outage predictor and what lies between
(the fusion loop, the viewer's logging) are each Python-bound, so threads would take turns on one core under
the GIL; a forked worker runs beside the caller instead. What crosses between them is pickled (protocol 5)
down a pipe, each message after an 8-byte little-endian length. A blocking pipe is the flow control: a worker
is at most about one message and the pipe's ``PIPE_BYTES`` ahead of its caller, so memory holds about two.

- :class:`Ahead`: a generator in the worker, its items consumed here (``fuse``'s input blocks, ``view``'s
  drive pass).
- :class:`Remote`: an object in the worker, its methods called from here, without waiting or for an answer
  (``fuse``'s outage predictor); the calls sent without waiting go down the pipe in batches.

Both pass exceptions back (as the same type where they pickle, else ``RuntimeError`` with their text), ignore
SIGINT in the worker (the caller decides), end the worker through ``os._exit`` (nothing of the caller's, no
buffer and no atexit handler, runs twice) and reap it. Without ``os.fork``, with other threads running
(forking them is unsafe: a batch worker, the live player), or with one CPU to run on, the work runs in the
caller's process instead, with the same results, on one core.
"""
from __future__ import annotations

import os
import pickle
import signal
import struct
import threading
from typing import Callable, Generator, Generic, TypeVar

from fieldlog.drive.reader import cpus

T = TypeVar("T")
R = TypeVar("R")

_HEADER = struct.Struct("<Q")
PIPE_BYTES = 1 << 20  # the read-ahead pipe's size: Linux's default largest (/proc/sys/fs/pipe-max-size)
_ITEM, _RETURN, _ERROR = 0, 1, 2


class Ahead(Generic[T, R]):
    """``produce()`` started in a forked worker at construction (module docstring); iterate it once, in a
    ``with`` block (leaving the block ends a worker still running)."""

    def __init__(self, produce: Callable[[], Generator[T, None, R]]) -> None:
        self._produce: Callable[[], Generator[T, None, R]] | None = produce
        self._pid = 0
        self._pipe = None
        if _can_fork():
            r, w = os.pipe()
            _widen(w)
            pid = os.fork()
            if pid == 0:  # the worker: never returns
                os.close(r)
                _work(produce, w)
            os.close(w)
            self._pid, self._pipe, self._produce = pid, os.fdopen(r, "rb"), None

    def __iter__(self) -> Generator[T, None, R]:
        if self._produce is not None:  # no worker: here, on this core
            produce, self._produce = self._produce, None
            return (yield from produce())
        if self._pipe is None:
            raise RuntimeError("a drive read ahead is iterated once")
        try:
            while True:
                kind, value = _receive(self._pipe)
                if kind == _ITEM:
                    yield value
                    continue
                self._reap(kill=False)
                if kind == _ERROR:
                    raise value
                return value
        finally:
            self.close()

    def close(self) -> None:
        """End the worker if it still runs, and reap it."""
        self._reap(kill=True)

    def _reap(self, kill: bool) -> None:
        self._pid = _end(self._pid, kill)
        if self._pipe is not None:
            self._pipe.close()
            self._pipe = None

    def __enter__(self) -> "Ahead[T, R]":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _work(produce: Callable[[], Generator], fd: int) -> None:
    """The worker's whole life: run the generator, send each item, then its return value or its exception;
    leave through ``os._exit`` so that nothing of the parent's (buffers, atexit handlers) runs twice."""
    code = 0
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        gen = produce()
        try:
            while True:
                _send(fd, _ITEM, next(gen))
        except StopIteration as stop:
            _send(fd, _RETURN, stop.value)
        except BaseException as e:  # noqa: BLE001 - every failure goes to the consumer
            _send(fd, _ERROR, _picklable(e))
    except BrokenPipeError:  # the consumer has gone
        code = 1
    except BaseException:  # noqa: BLE001 - nothing may unwind into the parent's code in this process
        code = 1
    finally:
        os._exit(code)


def _widen(fd: int) -> None:
    """Make the pipe of ``fd`` hold ``PIPE_BYTES`` where the system allows (Linux; else it stays as it is, 64 KiB
    on Linux by default): an input block of a few MB then crosses in a few writes and reads, not a hundred."""
    try:
        import fcntl

        fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    except (ImportError, AttributeError, OSError):  # not Linux, or above /proc/sys/fs/pipe-max-size
        pass


def _picklable(e: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(e, protocol=5))
        return e
    except Exception:  # noqa: BLE001 - any exception that does not survive pickling is sent as its text
        return RuntimeError(f"{type(e).__name__}: {e}")


def _send(fd: int, kind: int, value: object) -> None:
    body = pickle.dumps((kind, value), protocol=5)
    for data in (memoryview(_HEADER.pack(len(body))), memoryview(body)):
        while data:
            data = data[os.write(fd, data):]


def _receive(pipe) -> tuple[int, object]:
    head = pipe.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise RuntimeError("the drive's reading worker ended without a result")
    (n,) = _HEADER.unpack(head)
    body = pipe.read(n)
    if len(body) < n:
        raise RuntimeError("the drive's reading worker ended mid-item")
    return pickle.loads(body)


class Remote:
    """An object made by ``make()`` in a forked worker: ``send`` calls one of its methods there without waiting,
    ``ask`` calls one and returns its result, both in the order given (so an answer reflects every call sent
    before it). Sent calls are held here until ``SEND_BATCH`` of them, or an ``ask``, go down the pipe together:
    one message, not one per call. A call that raises in the worker ends it; its exception is raised here by a
    later ``send`` or ``ask``. ``close`` ends the worker (calls still held are dropped). Without ``os.fork``, or
    with other threads running, the object lives in this process and each call runs at once."""

    SEND_BATCH = 32

    def __init__(self, make: Callable[[], object]) -> None:
        self._obj: object | None = None
        self._pid = 0
        self._calls = -1
        self._results = None
        self._held: list[tuple[str, tuple]] = []
        if not _can_fork():
            self._obj = make()
            return
        cr, cw = os.pipe()
        rr, rw = os.pipe()
        pid = os.fork()
        if pid == 0:  # the worker: never returns
            os.close(cw)
            os.close(rr)
            _host(make, cr, rw)
        os.close(cr)
        os.close(rw)
        self._pid, self._calls, self._results = pid, cw, os.fdopen(rr, "rb")

    def send(self, name: str, *args: object) -> None:
        """``obj.name(*args)``, without waiting for it."""
        if self._obj is not None:
            getattr(self._obj, name)(*args)
            return
        self._held.append((name, args))
        if len(self._held) >= self.SEND_BATCH:
            self._put(_ITEM)

    def ask(self, name: str, *args: object) -> object:
        """``obj.name(*args)``, after every call sent before it; its result."""
        if self._obj is not None:
            return getattr(self._obj, name)(*args)
        self._held.append((name, args))
        self._put(_RETURN)
        return self._answer()

    def close(self) -> None:
        """End the worker (it holds no state worth keeping) and reap it."""
        if self._pid:
            self._pid = _end(self._pid, kill=True)
            os.close(self._calls)
            self._results.close()

    def _put(self, kind: int) -> None:
        """The held calls down the pipe, as one message (``_RETURN``: the last one's result is wanted)."""
        if not self._pid:
            raise RuntimeError("the worker has been closed")
        calls, self._held = self._held, []
        try:
            _send(self._calls, kind, calls)
        except BrokenPipeError:  # the worker ended on an error: raise it
            self._answer()
            raise RuntimeError("the worker ended early") from None

    def _answer(self) -> object:
        try:
            kind, value = _receive(self._results)
        except RuntimeError:
            kind, value = _ERROR, RuntimeError("the worker ended without an answer")
        if kind == _ERROR:
            self.close()
            raise value
        return value

    def __enter__(self) -> "Remote":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _host(make: Callable[[], object], calls: int, results: int) -> None:
    """The worker of a :class:`Remote`: make the object, then run the calls as they come until the pipe ends; a
    message of kind ``_RETURN`` is answered with its last call's result."""
    code = 0
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with os.fdopen(calls, "rb") as pipe:
            try:
                obj = make()
            except BaseException as e:  # noqa: BLE001 - reported at the first call
                _send(results, _ERROR, _picklable(e))
                raise SystemExit(1) from None
            while code == 0:
                try:
                    kind, batch = _receive(pipe)
                except RuntimeError:  # the caller has gone
                    break
                for name, args in batch:
                    try:
                        value = getattr(obj, name)(*args)
                    except BaseException as e:  # noqa: BLE001 - every failure goes to the caller
                        _send(results, _ERROR, _picklable(e))
                        code = 1
                        break
                else:
                    if kind == _RETURN:
                        _send(results, _RETURN, value)
    except BaseException:  # noqa: BLE001 - nothing may unwind into the parent's code in this process
        code = 1
    finally:
        os._exit(code)


def _can_fork() -> bool:
    """Whether a worker is forked: the platform has fork, no other Python thread runs (forking one is unsafe), and
    the process may run on a second CPU (on one, a worker would only take turns with its caller, and pickle what
    crosses between them: ``taskset -c 0``). A library's native threads are not seen here: a caller that starts
    them (a WebSocket server, ``tools.foxglove_live.serve``) reads in its own process."""
    return hasattr(os, "fork") and threading.active_count() == 1 and cpus() > 1


def _end(pid: int, kill: bool) -> int:
    """Reap worker ``pid`` (0: none), killed first if ``kill``; returns 0, the pid of no worker."""
    if pid:
        if kill:
            os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    return 0
