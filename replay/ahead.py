"""Read a drive on the second core: a generator run in a forked worker process beside its consumer.

Reading a drive (zstd, the CDR decode, the input mapping) and what consumes it (the fusion loop, the viewer's
logging) are each Python-bound, so threads would take turns on one core under the GIL; a forked worker runs the
generator beside the consumer instead. Items and the generator's return value cross a pipe pickled (protocol 5),
each after an 8-byte little-endian length. The blocking pipe is the flow control: the worker computes the next
item while the last one is consumed, then waits until it is taken, so memory holds about two items.

Contract: ``Ahead(produce)`` starts the worker at once; iterating it (once) yields what ``produce()`` yields and
returns what it returns, in order, equal up to pickling; an exception raised in the worker is raised again in
the consumer (as the same type where it pickles, else ``RuntimeError`` with its text). The worker is killed when
the consumer stops early (``close``, leaving its ``with`` block, an exception, Ctrl-C); it ignores SIGINT itself,
the consumer decides. Without ``os.fork``, or with other threads running (forking them is unsafe), ``produce()``
runs in the consumer's process instead: the same items, on one core.
"""
from __future__ import annotations

import os
import pickle
import signal
import struct
import threading
from typing import Callable, Generator, Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_HEADER = struct.Struct("<Q")
_ITEM, _RETURN, _ERROR = 0, 1, 2


class Ahead(Generic[T, R]):
    """``produce()`` started in a forked worker at construction (module docstring); iterate it once, in a
    ``with`` block (leaving the block ends a worker still running)."""

    def __init__(self, produce: Callable[[], Generator[T, None, R]]) -> None:
        self._produce: Callable[[], Generator[T, None, R]] | None = produce
        self._pid = 0
        self._pipe = None
        if hasattr(os, "fork") and threading.active_count() == 1:
            r, w = os.pipe()
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
        if self._pid:
            if kill:
                os.kill(self._pid, signal.SIGKILL)
            os.waitpid(self._pid, 0)
            self._pid = 0
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
