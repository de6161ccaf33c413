"""`fieldlog view`: the position sigma where the car is (ellipsoids along the ENU trajectory, discs on the map)
and the outages shaded in the time plots, read back from the `.rrd` (rerun.chunk.RrdReader)."""

import numpy as np
import pytest
from rerun.chunk import RrdReader

from fieldlog.replay import view as rview
from fieldlog.drive.reader import read_topic
from fieldlog.tools.cli import main as cli_main
from test_view_export import _rerun, drives  # noqa: F401 - the fixture: a drive with a no-fix outage, fused kf


@pytest.fixture(scope="module")
def recording(drives, tmp_path_factory):  # noqa: F811
    sim, kf = drives
    rrd = tmp_path_factory.mktemp("sigma") / "view.rrd"
    assert cli_main(["view", str(sim), str(kf), "--rrd", str(rrd)]) == 0
    assert "1 file verified without error" in _rerun("verify", str(rrd))
    cols: dict[str, dict[str, list]] = {}
    for ch in RrdReader(rrd).stream():
        if ch.is_static:
            continue
        rb = ch.to_record_batch()
        into = cols.setdefault(ch.entity_path, {})
        for name in rb.schema.names:
            col = rb.column(name)
            into.setdefault(name, []).extend((col.cast("int64") if name == "gps_time" else col).to_pylist())
    return sim, kf, cols


def _t_ns(col: list) -> np.ndarray:
    return np.array(col, dtype=np.int64)


def test_sigma_ellipsoids_along_the_trajectory(recording):
    sim, kf, cols = recording
    fix, std = read_topic(kf, "/fusion/kf/fix"), read_topic(kf, "/fusion/kf/std")
    e = cols["/enu/fusion/kf/sigma"]
    t = _t_ns(e["gps_time"])
    half = np.array([r[0] for r in e["Ellipsoids3D:half_sizes"]])
    centers = np.array([r[0] for r in e["Ellipsoids3D:centers"]])
    # decimated: one per SIGMA_PERIOD_S of the 10 Hz solution, the first row of each period
    span_s = (fix["log_time_ns"][-1] - fix["log_time_ns"][0]) * 1e-9
    assert len(t) == int(span_s // rview.SIGMA_PERIOD_S) + 1
    step_s = np.diff(t) * 1e-9
    assert np.all(np.abs(step_s - rview.SIGMA_PERIOD_S) <= 0.1 + 1e-6)  # within one solution period
    assert np.isin(t, fix["log_time_ns"]).all()
    # half sizes: sigma E, N, U of /fusion/kf/std at those rows (float32 in the recording)
    at = np.searchsorted(std["log_time_ns"], t)
    np.testing.assert_allclose(half, std["xyz"][at], rtol=1e-6)
    for m in read_topic(kf, "/fusion/outage")["msgs"]:  # the horizontal sigma grows through each outage
        inside = (t >= m.start_ns) & (t <= m.end_ns)
        assert half[inside, :2].max() > 1.1 * half[t < m.start_ns][-1, :2].max(), m.reason
    # centred on the trajectory: the end points of the ENU strips at the same times
    strip_t = _t_ns(cols["/enu/fusion/kf"]["gps_time"])
    ends = np.array([s[0][-1] for s in cols["/enu/fusion/kf"]["LineStrips3D:strips"]])
    np.testing.assert_allclose(centers, ends[np.searchsorted(strip_t, t)], atol=1e-3)
    assert "/enu/gps/sigma" not in cols  # the 3D view shows the fused sigma alone


def test_sigma_discs_on_the_map(recording):
    sim, kf, cols = recording
    std = read_topic(kf, "/fusion/kf/std")
    m = cols["/map/fusion/kf/sigma"]
    assert len(m["gps_time"]) == len(std["log_time_ns"])  # every solution row: the disc follows the car
    np.testing.assert_allclose([r[0] for r in m["GeoPoints:radii"]], std["xyz"][:, :2].max(axis=1), rtol=1e-6)
    fix = read_topic(sim, "/gps/fix")
    ok = (fix["status"] >= 0) & np.isfinite(fix["lat_deg"])
    assert (fix["covariance_type"][ok] > 0).all()
    g = cols["/map/gps/sigma"]
    want = np.sqrt(fix["position_covariance"][ok][:, [0, 4]].max(axis=1))  # the receiver's, m
    np.testing.assert_allclose([r[0] for r in g["GeoPoints:radii"]], want, rtol=1e-6)
    np.testing.assert_allclose([r[0] for r in g["GeoPoints:positions"]],
                               np.stack([fix["lat_deg"][ok], fix["lon_deg"][ok]], axis=1), rtol=0, atol=1e-12)


def test_outages_shaded_in_the_time_plots(recording):
    sim, kf, cols = recording
    windows = sorted((m.start_ns, m.end_ns) for m in read_topic(kf, "/fusion/outage")["msgs"])
    assert len(windows) == 2  # the forced outage and the receiver's, disjoint
    for group, names in rview.BAND_PLOTS:
        for name in names:
            band = cols[f"/{group}/{name}/outage"]
            t = _t_ns(band["gps_time"])
            y = np.array([r[0] for r in band["Scalars:scalars"]])
            assert t.tolist() == [x for s, e in windows for x in (s, e, e + 1)]
            np.testing.assert_array_equal(y, np.tile([0.0, 0.0, np.nan], len(windows)))
