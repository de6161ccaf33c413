"""The emulated DAQ board: the firmware (firmware/boards/qemu) under ``qemu-system-arm -M netduinoplus2``, fed
by the simulator.

The simulator stands in for what the real board's ADC and timer deliver: one input record per sample period
(firmware/core/input.h, 33 bytes) with the six ADC counts, the board timer's capture of the sample-clock edge,
the PPS capture when an edge came in that period, and the temperature, written to a pty that is QEMU's
standard input, which the firmware reads with ARM semihosting. The firmware numbers, latches, frames and
transmits them; its USART1 is the DAQ pseudo-terminal the daemon reads. Each record is one sample, so the
emulated board's sample clock is the simulator's (the ``[clock]`` model of ``tools/sim/clock.py``), paced by
when the records are written.

The board timer (TIM2 of the real board) runs at ``TIMER_HZ`` with its own crystal error ``TIMER_PPM``; it
starts ``TIMER_WRAP_AFTER_S`` before its 32-bit wrap, so a drive longer than that crosses the wrap.
"""
from __future__ import annotations

import fcntl
import os
import re
import select
import shutil
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np

from fieldlog.acquire import daq

RECORD_SIZE = 33
SYNC = (0x5A, 0xA5)
FLAG_PPS, FLAG_TEMP = 0x01, 0x02
TIMER_HZ = 84e6               # TIM2: APB1 timer clock of the real board
TIMER_PPM = -17.0             # its crystal's rate error (not the ADC's: the latch ratio cancels it)
TIMER_WRAP_AFTER_S = 20.0
READY = b"fieldlog-fw emulated ready\n"
READY_TIMEOUT_S = 20.0
DRAIN_QUIET_S = 0.3           # the reader has taken the board's frames once its pty stays empty this long
IMAGE = Path(__file__).resolve().parents[2] / "firmware" / "build" / "qemu" / "fieldlog-qemu.elf"

RECORD_DTYPE = np.dtype([("sync", "u1", (2,)), ("flags", "u1"), ("counts", "u1", (6, 3)),
                         ("sample_ticks", "<u4"), ("pps_ticks", "<u4"), ("temp_cc", "<i2"), ("crc", "<u2")])
assert RECORD_DTYPE.itemsize == RECORD_SIZE


class BoardError(ValueError):
    """The emulated board cannot run here (no QEMU, no image, no ready line): one line saying what to do."""


def timer_ticks(t_s: np.ndarray) -> np.ndarray:
    """The board timer's count (uint32) at true times ``t_s`` (s since the drive start)."""
    start = 2**32 - TIMER_WRAP_AFTER_S * TIMER_HZ
    ticks = np.floor(start + np.asarray(t_s, np.float64) * TIMER_HZ * (1 + TIMER_PPM * 1e-6))
    return np.mod(ticks.astype(np.int64), 2**32).astype(np.uint32)


def encode_records(counts: np.ndarray, sample_ticks: np.ndarray, pps: np.ndarray, pps_ticks: np.ndarray,
                   temperature_c: np.ndarray | None) -> np.ndarray:
    """n input records as an (n, RECORD_SIZE) uint8 array (core/input.h). counts: (n, 6) signed 24-bit;
    pps_ticks is written where ``pps`` (0 elsewhere); temperature in centi-degrees, valid where finite."""
    n = len(sample_ticks)
    counts = np.asarray(counts, np.int64)
    if n and (counts.min() < daq.COUNTS_MIN or counts.max() > daq.COUNTS_MAX):
        raise ValueError("ADC counts outside the signed 24-bit range")
    rec = np.zeros(n, RECORD_DTYPE)
    rec["sync"] = SYNC
    c = np.mod(counts, 2**24).astype("<u4").view(np.uint8).reshape(n, 6, 4)
    rec["counts"] = c[:, :, :3]
    rec["sample_ticks"] = sample_ticks
    pps = np.asarray(pps, bool)
    rec["pps_ticks"] = np.where(pps, pps_ticks, 0)
    flags = np.where(pps, FLAG_PPS, 0)
    if temperature_c is not None:
        t = np.asarray(temperature_c, np.float64)
        ok = np.isfinite(t)
        rec["temp_cc"] = np.where(ok, np.clip(np.round(np.where(ok, t, 0.0) * 100), -32768, 32767), 0)
        flags |= np.where(ok, FLAG_TEMP, 0)
    rec["flags"] = flags
    rows = rec.view(np.uint8).reshape(n, RECORD_SIZE)
    rec["crc"] = daq.crc16_columns(rows[:, 2:RECORD_SIZE - 2])
    return rows


def pps_times(t_k: np.ndarray, pps: np.ndarray, latch: np.ndarray, edges) -> np.ndarray:
    """True time of the PPS edge captured in each flagged sample period: the receiver's edge for a real one
    (``edges``, a clock.PpsTruth), for a glitch the middle of the latch step the simulator drew for it
    (``latch``, clock.pps_frames in 'latch' mode); 0 where no flag."""
    t = np.zeros(len(t_k))
    real = edges.k >= 0
    t[edges.k[real]] = edges.t_s[real]
    glitch = np.flatnonzero(pps)
    glitch = glitch[~np.isin(glitch, edges.k[real])]
    t[glitch] = t_k[glitch - 1] + (latch[glitch] + 0.5) / 65536 * (t_k[glitch] - t_k[glitch - 1])
    return t


def input_records(truth: dict) -> np.ndarray:
    """The records of a simulated drive made in 'latch' mode (``simulate.make_reads``'s truth: sample times,
    ADC counts, PPS flags, latches and edges, temperature), one per DAQ sample."""
    t_k = truth["t_k"]
    t_pps = pps_times(t_k, truth["pps"], truth["latch"], truth["edges"])
    return encode_records(truth["counts"], timer_ticks(t_k), truth["pps"], timer_ticks(t_pps), truth["temp_c"])


def qemu_command(image: Path) -> list[str]:
    """qemu-system-arm for the netduinoplus2 (STM32F405): USART1 (the first -serial) on a new pty, the DAQ
    port; semihosting on, its console being QEMU's stdin (the simulator's records) and stdout."""
    return ["qemu-system-arm", "-M", "netduinoplus2", "-kernel", str(image), "-nodefaults", "-display", "none",
            "-monitor", "none", "-chardev", "pty,id=daq", "-serial", "chardev:daq",
            "-semihosting-config", "enable=on,target=native"]


class EmulatedBoard:
    """A running QEMU with the firmware: ``daq_path`` is its USART1 pty. ``start`` returns once the firmware
    has written its ready line (on its semihosting console: QEMU's stdout).
    The DAQ pty is held open here, never read, to see (``FIONREAD``) whether the reader has taken every
    frame: stopping QEMU closes the pty and would discard what is still queued."""

    def __init__(self, image: str | Path | None = None) -> None:
        self.image = Path(image) if image else IMAGE
        if shutil.which("qemu-system-arm") is None:
            raise BoardError("--board emulated needs qemu-system-arm: apt-get install qemu-system-arm")
        if not self.image.is_file():
            raise BoardError(f"{self.image}: no firmware image; build it with `make firmware`")
        self.proc: subprocess.Popen[bytes] | None = None
        self.daq_path = ""
        self.daq_fd = -1
        self._empty_since: float | None = None

    def start(self, input_fd: int) -> None:
        """Start QEMU reading the records from ``input_fd`` (a pty slave in raw mode)."""
        self.proc = subprocess.Popen(qemu_command(self.image), stdin=input_fd, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, bufsize=0)   # unbuffered: select sees every line
        lines = self._lines_until(lambda line: b"(label daq)" in line)
        m = re.search(rb"(/dev/pts/\d+) \(label daq\)", lines[-1] if lines else b"")
        if not m:
            self.stop()
            raise BoardError("qemu-system-arm did not start the board: "
                             f"{b' '.join(lines).decode(errors='replace').strip() or 'no output'}")
        self.daq_path = m.group(1).decode()
        self.daq_fd = os.open(self.daq_path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        if READY not in self._lines_until(lambda line: line == READY):
            self.stop()
            raise BoardError(f"{self.image}: the firmware sent no ready line in {READY_TIMEOUT_S:g} s")
        threading.Thread(target=self._forward, daemon=True).start()

    def _lines_until(self, done: Callable[[bytes], bool]) -> list[bytes]:
        """QEMU's output lines up to the first for which ``done`` holds (all of them if none does within
        READY_TIMEOUT_S or before QEMU exits)."""
        out: list[bytes] = []
        deadline = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < deadline:
            if not select.select([self.proc.stdout], [], [], 0.1)[0]:
                continue
            line = self.proc.stdout.readline()
            if not line:
                break
            out.append(line)
            if done(line):
                break
        return out

    def drained(self) -> bool:
        """True once the DAQ pty's input queue has stayed empty for DRAIN_QUIET_S (call repeatedly)."""
        unread = int.from_bytes(fcntl.ioctl(self.daq_fd, termios.FIONREAD, b"\0\0\0\0"), sys.byteorder)
        now = time.monotonic()
        if unread or self._empty_since is None:
            self._empty_since = None if unread else now
            return False
        return now - self._empty_since >= DRAIN_QUIET_S

    def _forward(self) -> None:
        for line in self.proc.stdout:
            print(f"qemu: {line.decode(errors='replace').rstrip()}", file=sys.stderr, flush=True)

    def stop(self) -> None:
        if self.daq_fd >= 0:
            os.close(self.daq_fd)
            self.daq_fd = -1
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
