"""Coverage-guided fuzzing of the acquisition path with atheris (long runs; tests/test_fuzz.py is the CI part).

    pip install atheris
    python -m fieldlog.tools.fuzz -max_total_time=3600 out/fuzz-corpus     # any libFuzzer flags

Each input is split in two by its first byte: a GPS byte stream (a few sentences are re-checksummed, so that the
fuzzer gets past the checksum into the field decoding) and a DAQ byte stream, fed as reads through the whole
``Pipeline`` (decoders, epoch assembly, time sync, GPS fix and IMU output) into a sink that drops everything. The
harness fails on any exception escaping ``Pipeline.feed`` and on any processing error the pipeline counted
(``processing_errors``: it would have been caught in the daemon, but it is a bug).
"""
from __future__ import annotations

import re
import sys

NS = 1_000_000_000
_SENTENCE = re.compile(rb"\$([^*$\r\n]{0,120})\*")


class _Drop:
    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        pass

    def write_batch(self, topic: str, log_time_ns, data) -> None:
        pass


def _with_checksums(gps: bytes) -> bytes:
    from fieldlog.acquire import nmea

    return _SENTENCE.sub(lambda m: b"$" + m.group(1) + b"*%02X" % nmea.checksum(m.group(1)), gps)


def one_input(data: bytes) -> None:
    """Feed one fuzzer input through the pipeline; raise on any error."""
    from fieldlog.acquire.pipeline import Pipeline

    if not data:
        return
    cut = 1 + data[0] * max(len(data) - 1, 0) // 255
    gps, daq = _with_checksums(data[1:cut]), data[cut:]
    pipe = Pipeline(_Drop())
    mono, wall = 10 * NS, 1_700_000_000 * NS
    for i in range(0, max(len(gps), len(daq)), 64):
        pipe.feed("daq", mono + i * 1_000_000, wall + i * 1_000_000, daq[i:i + 64])
        pipe.feed("gps", mono + i * 1_000_000 + 1, wall + i * 1_000_000 + 1, gps[i:i + 64])
    pipe.finish()
    if pipe.counters.processing_errors:
        raise RuntimeError(f"{pipe.counters.processing_errors} processing errors (see the log above)")


def main(argv: list[str] | None = None) -> None:
    try:
        import atheris
    except ImportError:
        sys.exit("fieldlog fuzz: atheris is not installed: pip install atheris")
    with atheris.instrument_imports():
        import fieldlog.acquire.daq  # noqa: F401
        import fieldlog.acquire.gnss  # noqa: F401
        import fieldlog.acquire.nmea  # noqa: F401
        import fieldlog.acquire.pipeline  # noqa: F401
        import fieldlog.acquire.timesync  # noqa: F401
    atheris.Setup(sys.argv if argv is None else argv, one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
