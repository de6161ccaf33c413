"""RTS smoothing (`fieldlog fuse --smooth`) and the outage study (`fieldlog evaluate`) on a short figure-eight."""

import numpy as np
import polars as pl
import pytest

from fusion.engine import FusionConfig
from replay.reader import read_topic
from tools.cli import main as cli_main
from tools.evaluate import QUANTITIES, StudyConfig, outage_errors, place_outages
from tools.fuse import fuse
from tools.sim.simulate import simulate

DURATION = 240.0
OUTAGE = (170.0, 30.0)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    path = tmp_path_factory.mktemp("smooth") / "figure8.mcap"
    simulate("figure8", DURATION, 3, path)
    return path


def _rms(drive, fused, method, window_ns):
    e = outage_errors(drive, fused, method, [window_ns])
    return float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))), float(np.sqrt(np.mean(np.sum(e[:, 3:6] ** 2, 1))))


def test_smoother_shrinks_outage_error_and_does_no_harm_with_gps(drive, tmp_path):
    t0 = int(read_topic(drive, "/imu")["log_time_ns"][0])
    win = (t0 + int(OUTAGE[0] * 1e9), t0 + int(sum(OUTAGE) * 1e9))
    whole = (t0 + int(60e9), t0 + int(DURATION * 1e9))
    res = {}
    for label, cfg, w in (("outage", FusionConfig(outages=(OUTAGE,)), win), ("gps", FusionConfig(), whole)):
        for smooth in (False, True):
            out = fuse(drive, "kf", tmp_path / f"{label}{smooth}.mcap", cfg, smooth=smooth)
            res[label, smooth] = _rms(drive, out.path, "kf", w)
    print(f"30 s outage, 2D RMS inside: forward {res['outage', False][0]:.2f} m, smoothed {res['outage', True][0]:.2f} m;"
          f" GPS throughout: forward {res['gps', False][0]:.2f} m, smoothed {res['gps', True][0]:.2f} m")
    assert res["outage", True][0] < 0.3 * res["outage", False][0]
    assert res["outage", True][1] < 0.3 * res["outage", False][1]
    assert res["gps", True][0] <= res["gps", False][0]
    assert res["gps", True][1] <= res["gps", False][1]
    # the smoothed file keeps the topics and the row count of the forward one
    a, b = (read_topic(tmp_path / f"gps{s}.mcap", "/fusion/kf/fix") for s in (False, True))
    assert np.array_equal(a["log_time_ns"], b["log_time_ns"])


def test_place_outages_stays_in_good_gps_without_overlap():
    t = np.arange(0.0, 600.0)
    good = np.ones(len(t), bool)
    good[(t >= 130) & (t < 150)] = False  # a real outage the study must avoid
    win = place_outages(t, good, 30.0, StudyConfig())
    assert win[0][0] == 150.0 and all(n == 30.0 for _, n in win)
    for (s0, n0), (s1, _) in zip(win, win[1:]):
        assert s1 >= s0 + n0 + 60.0
    assert win[-1][0] + 30.0 <= 595.0
    assert place_outages(t[:140], good[:140], 30.0) == []


def test_evaluate_writes_tables_and_kf_beats_ins(drive, tmp_path):
    rep = tmp_path / "report"
    assert cli_main(["evaluate", str(drive), "--outages", "20", "--methods", "ins,kf,dkf", "--report", str(rep)]) == 0
    md = (rep / "table.md").read_text()
    assert "| quantity | unit | ins 20 s | kf 20 s | dkf 20 s |" in md
    t = pl.read_csv(rep / "table.csv")
    assert t.height == 3 * len(QUANTITIES)
    assert set(t["windows"].to_list()) == {2}  # 120-140 s and 200-220 s
    by = {(r["method"], r["quantity"]): r["mean"] for r in t.iter_rows(named=True)}
    for q in ("longitude", "latitude", "altitude", "vE", "vN", "vU"):
        assert by["kf", q] < by["ins", q], q
        assert by["dkf", q] < by["ins", q], q
    assert len(list((rep / "fused").glob("*.mcap"))) == 3


def test_evaluate_names_the_unknown_methods(drive, tmp_path, capsys):
    assert cli_main(["evaluate", str(drive), "--methods", "kf,rbf,dkf-rbfn,ukf", "--report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "unknown method(s): rbf, ukf" in err
    assert not (tmp_path / "table.md").exists()
