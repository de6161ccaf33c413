"""The error contract at its edges: times past 2038, hostile TOML and YAML, full disks, planted files.

Every case ends in exit 0, or exit 2 with one line naming the file; never an internal error (exit 1)."""
from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import gnss, messages, nmea, novatel
from fieldlog.replay import reader
from fieldlog.tools.cli import main

NS = 1_000_000_000


def cli(capsys, *args: str) -> tuple[int, list[str]]:
    """``fieldlog ARGS`` in this process: the exit code and the lines on stderr."""
    code = main([*args, "-q"])
    return code, capsys.readouterr().err.strip().splitlines()


# ------------------------------------------------------------------------------------------- 64-bit times

def nmea_log(day: dt.date, zda_year: int | None = None, n: int = 20) -> bytes:
    """``n`` one-second epochs (RMC, GGA, ZDA) at noon of ``day``; the ZDA says ``zda_year`` if given."""
    out = b""
    for i in range(n):
        t = f"1200{i:02d}.00"
        out += nmea.sentence(f"GPRMC,{t},A,4807.038,N,01131.000,E,0.0,0.0,{day:%d%m%y},,,A")
        out += nmea.sentence(f"GPGGA,{t},4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")
        out += nmea.sentence(f"GPZDA,{t},{day:%d},{day:%m},{zda_year or day.year},00,00")
    return out


def novatel_log(week: int, n: int = 20) -> bytes:
    return b"".join(novatel.format_timea(week, 100.0 + i, 18, (2040, 1, 1, 0, 0, 0))
                    + novatel.format_bestposa(week, 100.0 + i, 48.1, 11.5, 500.0, 47.0, (1.0, 1.0, 2.0), 10)
                    + novatel.format_bestvela(week, 100.0 + i, (0.0, 0.0, 0.0)) for i in range(n))


def test_header_stamps_carry_every_time_to_2106_and_lay_out_earlier_ones_as_int32() -> None:
    t = np.array([0, 1_700_000_000 * NS + 5, (2**31 - 1) * NS, 2**31 * NS + 7, messages.STAMP_END_NS - 1])
    sec, nsec = messages.split_stamp(t)
    assert np.array_equal(messages.join_stamp(sec, nsec), t)
    assert sec.dtype == np.int32 and np.array_equal(sec[:3], t[:3] // NS)       # int32 as before 2038
    for stamp in t.tolist():
        raw = messages.encode_raw(stamp, 42, "gps", b"$x")
        assert messages.decode_raw(raw)[:2] == (stamp, 42)
        batch = reader.decode_raw_batch(messages.Packed.from_list([raw]))
        assert batch["stamp_ns"][0] == stamp and batch["valid"][0]
        s = messages.encode_sentence(stamp, "$GPGGA")
        assert s[4:12] == raw[4:12]                                              # the same header layout
    assert (messages.STAMP_END_NS - 1) // NS // 86400 // 365 + 1970 >= gnss.YEAR_MAX


@pytest.mark.parametrize("case", ["nmea-2040", "zda-2200", "novatel-3100", "novatel-4000", "novatel-9999"])
def test_gps_times_past_2038_import_or_are_refused_in_one_line(tmp_path: Path, capsys, case: str) -> None:
    """A receiver in 2040 (past int32 seconds) records its true times; a year or week no header can carry (2200,
    week 9999) is counted in bad_fields and refused, the rest of the log kept."""
    kind, value = case.split("-")
    year = int(value)
    log = tmp_path / "gps.log"
    if kind == "novatel":
        log.write_bytes(novatel_log(year))
        utc0 = novatel.utc_ns_of(year, 100_000, 18)
    else:
        day = dt.date(2040, 1, 1)
        log.write_bytes(nmea_log(day, zda_year=year if kind == "zda" else None))
        utc0 = gnss.utc_ns(day, 12 * 3600.0)
    out = tmp_path / "d.mcap"
    code, err = cli(capsys, "import", "--gps", str(log), "--out", str(out))
    if year > gnss.WEEK_MAX and kind == "novatel":
        assert code == 2 and len(err) == 1 and str(log) in err[0], err
        assert not out.exists()
        return
    assert code == 0, err
    assert utc0 > 2**31 * NS
    fix = reader.read_topic(out, "/gps/fix")
    assert len(fix["stamp_ns"]) == 20 and fix["stamp_ns"][0] == utc0
    assert np.array_equal(fix["stamp_ns"], fix["log_time_ns"])
    raw = reader.read_raw(out, "/raw/gps")
    assert np.array_equal(raw["stamp_ns"], raw["log_time_ns"]) and raw["stamp_ns"][0] >= utc0
    counters = reader.read_metadata(out)["acquire.counters"]
    assert int(counters["nmea.bad_fields"]) == (20 if kind == "zda" else 0)
    rebuilt = tmp_path / "r.mcap"
    assert cli(capsys, "rebuild", str(out), "--out", str(rebuilt))[0] == 0
    assert np.array_equal(reader.read_topic(rebuilt, "/gps/fix")["stamp_ns"], fix["stamp_ns"])
