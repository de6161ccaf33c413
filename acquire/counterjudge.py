"""Sample counters as evidence: the sample index k of each decoded DAQ frame, judged against its neighbours.

A frame whose CRC matches can still carry a wrong counter (a CRC-16 collision in a damaged frame, 1 in 65536, or
a board glitch). Taking such a counter as it is moves every later sample by the jump, sizes arrays by it and
throws the time sync's fit away, so the counter is checked before anyone sees k (contract: docs/daq-protocol.md,
"Counter judging"):

* A step from the last believed frame (the *reference*) is *explained* when it is 1 or no more than the frame
  slots its bytes leave room for: ``1 <= step <= ceil(distance in bytes / 38)`` (frames damaged in between keep
  their 38 bytes in the stream). A step of 1 from the frame just before, and any other explained step the next
  frame's step continues, are taken as they are, all at once in the usual read; an explained gap the next frame does not continue is taken unless
  the next frame is explained from the reference and the frame after it continues that one rather than this
  one (then this counter alone is wrong, as below).
* Any other step (a repeat, a backward step, a jump of any size) waits for the next two frames (held over to
  the next read if needed, never more than two frames):
  - the next frame is explained from the reference: this frame's counter alone is wrong. It is counted
    (``counter_implausible``) and its samples are *placed* at the slot its byte distance from a neighbour gives,
    or dropped when no free slot follows from the bytes;
  - the next two frames continue this frame's counter: the counter really stepped. A forward step within what
    the host clock allows (frames lost when bytes were: ``host_time_scale * fs`` per host second since the
    reference's read plus ``slack_s`` of host read latency, or ``max_gap_s`` without host times) is a gap; anything
    else (a board reset, a counter register that jumped) is counted as implausible and the new counter is *re-based*
    onto k at the slot its byte distance gives, so k never goes back and never jumps by more than time allows;
  - neither: the frame is dropped and counted.
  A frame *continues* another when its counter steps forward by no more than the bytes between them explain or
  the host clock allows (the same bound as a gap): a board whose transmit path is slower than its ADC drops
  samples itself (its ring overruns) and sends the rest back to back, so its gaps leave no bytes missing and
  come close together; a genuine gap must not need gap-free frames after it to be believed. The first reference
  is the first frame one of whose next two frames it explains, or whose next two frames continue it.
So k strictly increases, and a step of k is bounded by the bytes and the host time, whatever the counter says.

Repeats. A frame whose counter steps back to (or stays at) the counter of a frame taken among the last
``REPEAT_HISTORY`` frames, with the same sample bytes (counts, PPS flag and latch, temperature), is that frame
delivered again (a DAQ read handed over twice: a merge of overlapping captures, a replaying adapter): it is
dropped and counted in ``repeated``, and the reference stays where it was, so the frames after the repeated run
continue from it and k has no duplicated sample. A repeat's counter is not a wrong counter: it is not counted in
``counter_repeats``, ``counter_backwards`` or ``counter_implausible``.

Counting: ``counter_gaps`` is the times the judged k advanced by more than 1; ``lost_frames`` the sample slots
such gaps skipped less the frames received inside them that the judge dropped (those arrived and are counted
in ``frames`` and ``counter_implausible``), so no sample is counted in both ``frames`` and ``lost_frames``.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from fieldlog.acquire.daq import FRAME_SIZE, DaqFrames, DaqStats, counts_on

_M32 = 0xFFFFFFFF
_BACK = 2**31                    # a counter step of 2**31 or more modulo 2**32 is a backward step
_FIELDS = ("k", "counts", "pps", "latch", "latch_valid", "temperature_c", "end_offset")
_CONTENT = ("counts", "pps", "latch", "latch_valid", "temperature_c")
REPEAT_HISTORY = 4096            # frames taken that a frame stepping back is compared with (8 s at 500 Hz)


@dataclass
class JudgeConfig:
    """How far a counter may step without byte evidence. Seconds of data, except ``slack_s``: host seconds."""

    fs_hz: float = 500.0
    host_time_scale: float = 1.0    # data seconds per host second (simulator playback only; see TimeSyncConfig)
    # host read latency allowed on top of the host time since the reference's read, scaled by host_time_scale
    # with it: a read late on the host holds host_time_scale times as much data in simulator playback
    slack_s: float = 1.0
    max_gap_s: float = 60.0         # the largest step believed when the reads carry no host time (imports)


@dataclass
class _Ref:
    counter: int
    k: int
    start: int          # absolute stream offset of the frame's first byte
    mono_ns: int | None


def _select(fr: DaqFrames, idx) -> DaqFrames:
    return DaqFrames(*(getattr(fr, f)[idx] for f in _FIELDS))


def _concat(parts: list[DaqFrames]) -> DaqFrames:
    return DaqFrames(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))


def _explained(c_from: int, s_from: int, c_to: int, s_to: int) -> bool:
    """The counter step from one frame to a later one fits the byte distance between them."""
    step = (c_to - c_from) & _M32
    return 1 <= step <= max(1, -(-(s_to - s_from) // FRAME_SIZE))


class CounterJudge:
    """``judge(frames, stream_base, mono_ns) -> frames`` with judged k; ``flush()`` at the end of the stream.

    ``frames`` are what ``DaqDecoder.feed`` returned for a chunk starting at absolute stream offset
    ``stream_base`` (``stats.bytes_in`` before the call); their k is only read modulo 2**32 (the counter). The
    frames returned are in stream order with strictly increasing k; frames held over from an earlier call come
    first, their ``end_offset`` relative to this call's chunk (so <= 0). Updates the counter fields of ``stats``
    (``counter_gaps``, ``lost_frames``, ``counter_repeats``, ``counter_backwards``, ``counter_implausible``,
    ``repeated``).
    """

    def __init__(self, stats: DaqStats, cfg: JudgeConfig | None = None) -> None:
        self.stats = stats
        self.cfg = cfg or JudgeConfig()
        self._ref: _Ref | None = None
        self._held: DaqFrames | None = None
        self._held_start = np.zeros(0, np.int64)
        self._held_mono: int | None = None
        self._base = 0
        self._last_out: int | None = None     # k of the last frame returned
        self._dropped = 0                     # frames decided and dropped since the last frame returned
        self._recent: deque[tuple[np.ndarray, DaqFrames]] = deque()  # (counters, frames) taken, newest last
        self._recent_n = 0
        self.stuck_run = 0                    # frames in a row, up to the last one fed, carrying one counter
        self.last_counter: int | None = None

    @property
    def held(self) -> int:
        """Frames waiting for the next frames' counters (at most 2)."""
        return 0 if self._held is None else len(self._held)

    def judge(self, fr: DaqFrames, stream_base: int, mono_ns: int | None = None) -> DaqFrames:
        usual = self.usual(fr, stream_base, mono_ns)
        if usual is not None:
            return usual
        self._count_stuck(fr.k & _M32)
        start = stream_base + fr.end_offset - FRAME_SIZE
        if self._held is not None:
            fr = _concat([self._held, fr])
            start = np.concatenate([self._held_start, start])
            self._held = None
        self._base = stream_base
        return self._run(fr, start, mono_ns, final=False)

    def usual(self, fr: DaqFrames, stream_base: int, mono_ns: int | None = None) -> DaqFrames | None:
        """``judge`` of the usual read, else None (and nothing changed): every frame steps 1 from the one before,
        back to back in the bytes after the last frame taken, so each is taken as it is (what ``_run`` decides
        for such frames, without its per-frame bookkeeping). The frames of several reads in a row, given as one
        chunk, are usual exactly when each read is usual in turn (a read without frames changes nothing), and
        the judge is then left as those reads one by one would leave it (``mono_ns``: the last one's with
        frames)."""
        ref, n = self._ref, len(fr)
        if not (n and self._held is None and ref is not None and self._dropped == 0 and self._last_out == ref.k):
            return None
        counters, ends = fr.k.tolist(), fr.end_offset.tolist()
        first = stream_base + ends[0] - FRAME_SIZE
        if (first != ref.start + FRAME_SIZE or ends != list(range(ends[0], ends[0] + n * FRAME_SIZE, FRAME_SIZE))
                or not counts_on(ref.counter, counters)):
            return None
        self._ref = _Ref(counters[-1] & _M32, ref.k + n, first + (n - 1) * FRAME_SIZE, mono_ns)
        self._remember(fr.k & _M32, fr)
        self.stuck_run, self.last_counter = 1, counters[-1] & _M32
        self._base = stream_base
        self._last_out = ref.k + n
        return DaqFrames(np.arange(ref.k + 1, ref.k + n + 1, dtype=np.int64), fr.counts, fr.pps, fr.latch,
                         fr.latch_valid, fr.temperature_c, fr.end_offset)

    def flush(self) -> DaqFrames:
        """The held frames, judged with what there is (end of stream)."""
        if self._held is None:
            return DaqFrames(np.zeros(0, np.int64), np.zeros((0, 6), np.int32), np.zeros(0, bool),
                             np.zeros(0, np.uint16), np.zeros(0, bool), np.zeros(0), np.zeros(0, np.int64))
        fr, start, self._held = self._held, self._held_start, None
        return self._run(fr, start, self._held_mono, final=True)

    # ------------------------------------------------------------------------------------------------
    def _run(self, fr: DaqFrames, start: np.ndarray, mono_ns: int | None, final: bool) -> DaqFrames:
        n = len(fr)
        out_k = np.full(n, -1, np.int64)          # -1: dropped
        counter = (fr.k & _M32).astype(np.int64)
        i = 0
        if self._ref is None and n:
            i = self._start(counter, start, mono_ns, final, out_k)
        if self._ref is not None and i < n:
            i = self._walk(fr, counter, start, mono_ns, final, out_k, i)
        if i < n:                                  # waiting for the next frames' counters
            self._held = _select(fr, slice(i, n))
            self._held_start = start[i:].copy()
            self._held_mono = mono_ns
        keep = np.flatnonzero(out_k[:i] >= 0)
        kk = out_k[keep]
        if kk.size:   # placed frames never collide with their neighbours (a safety net: the rules ensure it)
            floor = np.concatenate(([-1 if self._last_out is None else self._last_out], kk[:-1]))
            keep = keep[kk > np.maximum.accumulate(floor)]
        res = _select(fr, keep)
        if keep.size:
            self._remember(counter[keep], res)
        res.k = out_k[keep]
        res.end_offset = start[keep] + FRAME_SIZE - self._base
        # frames dropped between each frame returned and the one before it (held frames are not decided yet)
        dropped = np.diff(keep, prepend=-1) - 1
        if keep.size:
            dropped[0] += self._dropped
            self._dropped = i - 1 - int(keep[-1])
        else:
            self._dropped += i
        self._count_gaps(res.k, dropped)
        return res

    def _start(self, counter: np.ndarray, start: np.ndarray, mono_ns: int | None, final: bool,
               out_k: np.ndarray) -> int:
        """The first reference: the first frame one of whose next two frames it explains, or whose next two
        frames continue it (k = its counter)."""
        n = counter.size
        for i in range(n):
            if i + 2 >= n and not final:
                return i
            nxt = [(int(counter[j]), int(start[j])) for j in range(i + 1, min(n, i + 3))]
            c, s = int(counter[i]), int(start[i])
            if any(_explained(c, s, *f) for f in nxt) or self._corroborated(c, s, nxt, mono_ns):
                out_k[i] = c
                self._ref = _Ref(c, c, s, mono_ns)
                return i + 1
            self.stats.counter_implausible += 1
        return n

    def _walk(self, fr: DaqFrames, counter: np.ndarray, start: np.ndarray, mono_ns: int | None, final: bool,
              out_k: np.ndarray, i: int) -> int:
        """Judge frames i.. against the reference; returns the first frame not decided (held)."""
        n = counter.size
        ref = self._ref
        while i < n:
            # the usual case, vectorised: every step from here on explained by the bytes
            prev_c = np.concatenate(([ref.counter], counter[i:n - 1]))
            prev_s = np.concatenate(([ref.start], start[i:n - 1]))
            step = (counter[i:] - prev_c) & _M32
            dist = start[i:] - prev_s
            room = np.maximum(1, -(-dist // FRAME_SIZE))
            explained = (step >= 1) & (step <= room)
            # a step other than 1 from the frame just before needs the next frame to continue it: a wrong
            # counter can fall within the room too
            plain = (step == 1) & (dist == FRAME_SIZE)
            bad = np.flatnonzero(~plain & ~(explained & np.append(explained[1:], final)))
            j = i + (int(bad[0]) if bad.size else n - i)
            if j > i:
                out_k[i:j] = ref.k + np.cumsum(step[:j - i])
                ref = self._ref = _Ref(int(counter[j - 1]), int(out_k[j - 1]), int(start[j - 1]), mono_ns)
                i = j
            if i >= n:
                break
            if i + 2 >= n and not final:
                return i                            # hold: the next two frames decide
            i = self._decide(fr, counter, start, mono_ns, out_k, i)
            ref = self._ref
        return i

    def _decide(self, fr: DaqFrames, counter: np.ndarray, start: np.ndarray, mono_ns: int | None,
                out_k: np.ndarray, i: int) -> int:
        """Frame i's step from the reference is not explained; its next frames decide. Returns i + 1."""
        ref, st, n = self._ref, self.stats, counter.size
        c, s = int(counter[i]), int(start[i])
        step = (c - ref.counter) & _M32
        if (step == 0 or step >= _BACK) and self._repeat(fr, counter, out_k, i):
            st.repeated += 1                        # delivered twice: dropped, the reference stays
            return i + 1
        st.counter_repeats += step == 0
        st.counter_backwards += step >= _BACK
        nxt = [(int(counter[j]), int(start[j])) for j in range(i + 1, min(n, i + 3))]
        next_from_ref = bool(nxt) and _explained(ref.counter, ref.start, *nxt[0])
        if _explained(ref.counter, ref.start, c, s) and next_from_ref and len(nxt) == 2:
            # both fit the reference but not each other: the one the frame after them continues is right
            next_from_ref = not (_explained(c, s, *nxt[1]) and not _explained(*nxt[0], *nxt[1]))
        if _explained(ref.counter, ref.start, c, s) and not next_from_ref:
            out_k[i] = ref.k + step                 # a gap the bytes explain (the next frame is decided next)
            self._ref = _Ref(c, int(out_k[i]), s, mono_ns)
            return i + 1
        if next_from_ref:
            st.counter_implausible += 1             # this counter alone is wrong: place by the neighbours
            c1, s1 = nxt[0]
            k1 = ref.k + ((c1 - ref.counter) & _M32)
            k = None
            if (s - ref.start) % FRAME_SIZE == 0:
                k = ref.k + (s - ref.start) // FRAME_SIZE
            elif (s1 - s) % FRAME_SIZE == 0:
                k = k1 - (s1 - s) // FRAME_SIZE
            if k is not None and ref.k < k < k1:
                out_k[i] = k
            return i + 1
        if not self._corroborated(c, s, nxt, mono_ns):
            st.counter_implausible += 1             # no neighbour agrees with it either: dropped
            return i + 1
        if step < _BACK and step <= self._allowed(ref.start, s, mono_ns):
            k = ref.k + step                        # a real gap: frames lost with their bytes, or never sent
        else:
            st.counter_implausible += 1             # the counter was re-based (board reset, jumped register)
            k = ref.k + max(1, -(-(s - ref.start) // FRAME_SIZE))
        out_k[i] = k
        self._ref = _Ref(c, k, s, mono_ns)
        return i + 1

    def _count_stuck(self, counters: np.ndarray) -> None:
        """``stuck_run`` after the frames with these counters: a counter that does not advance (a stuck board
        counter) gives a long run, and the judge can place none of its frames."""
        if not len(counters):
            return
        change = np.flatnonzero(counters[1:] != counters[:-1])
        if change.size:
            self.stuck_run = len(counters) - 1 - int(change[-1])
        else:
            self.stuck_run = len(counters) + (self.stuck_run if counters[0] == self.last_counter else 0)
        self.last_counter = int(counters[-1])

    def _remember(self, counters: np.ndarray, frames: DaqFrames) -> None:
        """Frames taken (their counters and bytes), kept for ``_repeat``: the last ``REPEAT_HISTORY`` or more."""
        self._recent.append((counters, frames))
        self._recent_n += len(counters)
        while self._recent_n - len(self._recent[0][0]) >= REPEAT_HISTORY:
            self._recent_n -= len(self._recent.popleft()[0])

    def _repeat(self, fr: DaqFrames, counter: np.ndarray, out_k: np.ndarray, i: int) -> bool:
        """Frame i of ``fr`` has the counter and the sample bytes of a frame taken before it: one taken in this
        call (``out_k`` >= 0) or among the recent ones."""
        c = counter[i]
        same = [(fr, j) for j in np.flatnonzero((counter[:i] == c) & (out_k[:i] >= 0))[::-1].tolist()]
        for counters, frames in reversed(self._recent):
            same += [(frames, j) for j in np.flatnonzero(counters == c)[::-1].tolist()]
        return any(all(np.array_equal(getattr(other, f)[j], getattr(fr, f)[i], equal_nan=True) for f in _CONTENT)
                   for other, j in same)

    def _allowed(self, s_from: int, s_to: int, mono_ns: int | None) -> float:
        """The largest counter step the bytes and the host clock allow from a frame at stream offset ``s_from``
        to one at ``s_to`` (both at or after the reference's), read at ``mono_ns``: frames whose bytes lie
        between them, or the frames the host time since the reference's read holds (``max_gap_s`` of them
        without host times or a reference)."""
        cfg, ref = self.cfg, self._ref
        by_bytes = -(-(s_to - s_from) // FRAME_SIZE)
        if mono_ns is None or ref is None or ref.mono_ns is None:
            return max(by_bytes, cfg.max_gap_s * cfg.fs_hz)
        host_s = max(0, mono_ns - ref.mono_ns) / 1e9
        return max(by_bytes, math.ceil((host_s * 1.001 + cfg.slack_s) * cfg.host_time_scale * cfg.fs_hz))

    def _corroborated(self, c: int, s: int, nxt: list[tuple[int, int]], mono_ns: int | None) -> bool:
        """The next frames ``nxt`` ((counter, stream offset), up to two) each continue the one before them,
        starting from the frame (``c``, ``s``): every counter step forward and within ``_allowed``. Not only
        within the bytes: a board that drops samples itself sends the frames around the gaps back to back."""
        chain = [(c, s), *nxt]
        return all(1 <= (c1 - c0) & _M32 <= self._allowed(s0, s1, mono_ns)
                   for (c0, s0), (c1, s1) in zip(chain, chain[1:]))

    def _count_gaps(self, k: np.ndarray, dropped: np.ndarray) -> None:
        """``counter_gaps`` and ``lost_frames`` for the frames returned, k in order. ``dropped[j]``: frames received
        between frame j and the one returned before it that the judge dropped. Such a frame arrived (it is in
        ``frames``) and its slot lies in the gap around it, so it is not a lost frame too."""
        if not k.size:
            return
        d = np.diff(k, prepend=k[0] - 1 if self._last_out is None else self._last_out)
        gap = d > 1
        self.stats.counter_gaps += int(gap.sum())
        self.stats.lost_frames += int(np.maximum(0, d[gap] - 1 - dropped[gap]).sum())
        self._last_out = int(k[-1])
