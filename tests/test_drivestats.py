"""drive.drivestats' streaming figures (bounded memory) against the whole-array computation they replace, on
stamps with gaps, jitter and missing GPS epochs, written by a third-party writer (mcap_ros2's Writer, scanned)
and by the recorder in small batches (the record); and the quantised median's independence of batching."""
from __future__ import annotations

import numpy as np
import pytest
from mcap_ros2.writer import Writer

from fieldlog.drive import messages, recorder
from fieldlog.drive.drivestats import QuantisedMedian
from fieldlog.tools.info import drive_info

from foreign_drives import FIX_DEF, IMU_DEF, _stamp

NS = 1_000_000_000


def reference(imu_ns: np.ndarray, fix_ns: np.ndarray, status: np.ndarray) -> tuple[int, float, int, int]:
    """The figures as the whole arrays gave them before (median step; steps > 1.5 of it; missing epochs)."""
    d = np.diff(imu_ns) / NS
    gaps = d > 1.5 * np.median(d)
    df = np.diff(fix_ns) / NS
    return (int(gaps.sum()), float(d.max()) if gaps.any() else 0.0,
            int(np.sum(np.round(df / np.median(df)) - 1)), int(np.count_nonzero(status < 0)))


@pytest.fixture(scope="module")
def stamps():
    """A 200 Hz IMU for 150 s with +-40 us jitter and 6 dropped runs; a 5 Hz receiver with 4 silent stretches
    and NO_FIX epochs."""
    rng = np.random.default_rng(7)
    t0 = 1_700_000_000 * NS
    imu = t0 + np.arange(30_000, dtype=np.int64) * 5_000_000 + rng.integers(-40_000, 40_001, 30_000)
    keep = np.ones(len(imu), bool)
    for i, n in ((1000, 1), (4000, 3), (9000, 2), (15_000, 40), (22_000, 7), (29_000, 1)):
        keep[i:i + n] = False
    fix = t0 + np.arange(750, dtype=np.int64) * 200_000_000
    fkeep = np.ones(len(fix), bool)
    for i, n in ((100, 2), (300, 25), (500, 1), (640, 4)):
        fkeep[i:i + n] = False
    status = np.where(rng.random(fkeep.sum()) < 0.1, -1, 0).astype(np.int8)
    return imu[keep], fix[fkeep], status


def test_streamed_figures_equal_the_whole_array_ones(stamps, tmp_path):
    imu, fix, status = stamps
    want = reference(imu, fix, status)
    assert want[0] == 6 and want[2] == 32 and want[3] > 20      # the stamps do hold what is counted

    foreign = tmp_path / "foreign.mcap"           # another logger's topics, scanned by info
    with open(foreign, "wb") as fh:
        wr = Writer(fh)
        s_imu, s_fix = wr.register_msgdef("sensor_msgs/msg/Imu", IMU_DEF), wr.register_msgdef(
            "sensor_msgs/msg/NavSatFix", FIX_DEF)
        events = sorted([(int(t), 0, i) for i, t in enumerate(imu)] + [(int(t), 1, i) for i, t in enumerate(fix)])
        for t, kind, i in events:
            if kind == 0:
                wr.write_message("/vehicle/imu_raw", s_imu, {"header": {"stamp": _stamp(t), "frame_id": "imu"}}, t, t)
            else:
                wr.write_message("/vehicle/gnss", s_fix, {"header": {"stamp": _stamp(t), "frame_id": "gnss"},
                                                          "status": {"status": int(status[i]), "service": 1},
                                                          "latitude": 45.0, "longitude": 7.0}, t, t)
        wr.finish()
    scanned = drive_info(foreign)

    ours = tmp_path / "ours.mcap"                 # the recorder, fed in batches of 37 and 3: the record
    with recorder.Recorder(ours, fsync=False) as rec:
        for i in range(0, len(imu), 37):
            rec.write_batch("/imu", imu[i:i + 37], messages.encode_imu(imu[i:i + 37], np.zeros((len(imu[i:i + 37]), 3)),
                                                                       np.zeros((len(imu[i:i + 37]), 3))))
        for i in range(0, len(fix), 3):
            t = fix[i:i + 3]
            rec.write_batch("/gps/fix", t, messages.encode_navsatfix(t, np.full(len(t), 45.0), np.full(len(t), 7.0),
                                                                     np.zeros(len(t)), status=status[i:i + 3]))
    recorded = drive_info(ours)
    assert scanned.scanned and not recorded.scanned
    for info in (scanned, recorded, drive_info(ours, scan=True)):
        assert (info.imu_gaps, info.imu_longest_gap_s, info.gps_missing_epochs, info.gps_no_fix) == want


def test_quantised_median_is_exact_and_independent_of_batching():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(2.0, 0.05, 5000), rng.uniform(0, 100, 300)])
    a, b = QuantisedMedian(1e-3), QuantisedMedian(1e-3)
    a.add(x)
    for part in np.array_split(x, 97):
        b.add(part)
    assert a.counts == b.counts and a.shift == 0
    assert a.median() == pytest.approx(np.median(np.round(x / 1e-3) * 1e-3), abs=1e-12)
    # past MAX_KEYS the quantum doubles; the table is the same however the values came, and the median stays
    # within the final quantum
    small = [QuantisedMedian(1e-3) for _ in range(3)]
    for q in small:
        q.MAX_KEYS = 64
    small[0].add(x)
    for part in np.array_split(x, 11):
        small[1].add(part)
    for v in x:
        small[2].add(np.array([v]))
    assert small[0].counts == small[1].counts == small[2].counts and small[0].shift > 0
    assert len(small[0].counts) <= 64
    assert abs(small[0].median() - np.median(x)) <= (1 << small[0].shift) * 1e-3
