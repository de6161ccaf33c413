"""A drive cut short, made complete: ``fieldlog recover`` and the daemon's recovery on start.

``recorder.recover`` keeps every complete chunk. The derived topics lag the raw reads (``/imu`` by about half the
time-sync window, a minute with a sampled PPS), so a crash leaves the tail's raw bytes without their derived
messages. ``TailDeriver`` re-derives them as ``fieldlog rebuild`` does: every kept raw read goes through the
pipeline, in file order (the order the daemon processed them), with the drive's calibration and time-sync
settings, and of what the pipeline writes only the messages later than the last kept one of their topic are
added. The tail is then stamped as at the end of a drive (``Pipeline.finish``).
"""
from __future__ import annotations

import os

import numpy as np

from fieldlog.acquire import messages, recorder
from fieldlog.acquire.pipeline import Pipeline


class TailDeriver:
    """``recorder.recover``'s ``extend``: a Pipeline fed the kept raw reads, whose output is held per topic and
    kept only past the last message of that topic in the kept chunks."""

    def __init__(self) -> None:
        self.pipe: Pipeline | None = None
        self.last: dict[str, int] = {}
        self.held: dict[str, list[tuple[np.ndarray, messages.Packed]]] = {}

    # the pipeline's sink: /raw is already in the kept chunks
    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        if not topic.startswith("/raw/"):
            self.write_batch(topic, np.array([log_time_ns], np.int64), [data])

    def write_batch(self, topic: str, log_time_ns: np.ndarray, data) -> None:
        t = np.asarray(log_time_ns, np.int64)
        keep = np.flatnonzero(t > self.last.get(topic, -1))
        if len(keep):
            self.held.setdefault(topic, []).append((t[keep], messages.as_packed(data).take(keep)))

    def chunk(self, rec: recorder.Recorder, cm: recorder.ChunkMessages, metadata: dict[str, dict[str, str]]) -> None:
        topics = {cid: ch.topic for cid, ch in rec._channels.items()}
        raw = np.array([topics.get(int(c), "").startswith("/raw/") for c in cm.channel_id], bool)
        if raw.any():
            if self.pipe is None:
                cal, sync, cfg = Pipeline.settings_from_metadata(metadata)
                self.pipe = Pipeline(self, cal, sync, cfg)
            for payload in cm.select(raw).packed():
                _stamp, mono_ns, port, data = messages.decode_raw(payload)
                self.pipe.feed(port, mono_ns, _stamp, data)
        for cid in np.unique(cm.channel_id[~raw]).tolist():
            topic = topics.get(cid, "")
            self.last[topic] = max(self.last.get(topic, -1), int(cm.log_time[cm.channel_id == cid].max()))
        self._prune()

    def _prune(self) -> None:
        for topic, parts in list(self.held.items()):
            lim = self.last.get(topic, -1)
            kept = [(t[t > lim], p.take(np.flatnonzero(t > lim))) for t, p in parts if t[-1] > lim]
            self.held[topic] = [(t, p) for t, p in kept if len(t)]

    def finish(self, rec: recorder.Recorder) -> dict[str, int]:
        """Finish the pipeline and write what it derived past the kept chunks; messages per topic."""
        if self.pipe is None:
            return {}
        self.pipe.finish()
        self._prune()
        out = {}
        for topic, parts in self.held.items():
            for t, p in parts:
                rec.write_batch(topic, t, p)
                out[topic] = out.get(topic, 0) + len(t)
        return out


def recover_drive(src: str | os.PathLike[str], dst: str | os.PathLike[str], force: bool = False
                  ) -> recorder.RecoverReport:
    """The complete recovery of ``src`` into ``dst``: its complete chunks, then the derived tail. A complete file
    (one with a damaged chunk) has no tail: its chunks are copied without feeding the pipeline (several times
    faster: ``make bench`` recover), unless the walk stops before its data end (a damaged record):
    then it goes again with the pipeline (replacing the first copy). ``force``: as ``recorder.recover``."""
    if recorder.has_footer(src):
        rep = recorder.recover(src, dst, force=force)
        if rep.had_summary:
            return rep
        force = True
    return recorder.recover(src, dst, TailDeriver(), force=force)
