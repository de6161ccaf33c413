"""``fieldlog report``: the page of a simulated drive (with its CAN bus and a fused solution) and of another
logger's drive without most topics (an IMU gap and a GNSS silence injected), each opened in headless Chromium
through the DevTools protocol: it loads with no console error and no request beyond the file itself, every
section is there, the screenshot is a real picture, and the verdict lists the injected faults, or says
"nothing found" on the clean drive."""

from __future__ import annotations

import asyncio
import base64
import json
import re
import shutil
import subprocess
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.report import SECTIONS

from foreign_drives import Foreign, write_foreign

websockets = pytest.importorskip("websockets")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (apt-get install "
                                                             "chromium)")
GAP = (50.0, 1000)  # the IMU gap: 1000 samples (2 s at 500 Hz) dropped from 50 s on
SILENT = (70.0, 30.0)  # the GNSS silence, s from the first IMU sample


def _browse(page: Path, png: Path) -> dict:
    """``page`` opened in headless Chromium over the DevTools protocol: its console errors and exceptions, every
    URL it requested, the section ids, the verdict's text and links, and a full-page screenshot into ``png``."""
    proc = subprocess.Popen([CHROMIUM, "--headless", "--disable-gpu", "--no-sandbox", "--no-first-run",
                             "--remote-debugging-port=0", "--user-data-dir=" + str(png.parent / "profile"),
                             "about:blank"], stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stderr:
            m = re.search(r"DevTools listening on ws://([^/]+)/", line)
            if m:
                break
        else:
            raise AssertionError("chromium gave no DevTools address")
        with urllib.request.urlopen(f"http://{m.group(1)}/json/list", timeout=30) as r:
            target = next(t for t in json.load(r) if t["type"] == "page")
        return asyncio.run(_session(target["webSocketDebuggerUrl"], page.resolve().as_uri(), png))
    finally:
        proc.kill()
        proc.wait(30)


async def _session(ws_url: str, url: str, png: Path) -> dict:
    got: dict = {"errors": [], "requests": []}
    async with websockets.connect(ws_url, max_size=None) as ws:
        ids = iter(range(1, 1 << 30))
        pending: dict[int, asyncio.Future] = {}
        loaded = asyncio.get_running_loop().create_future()

        async def pump():
            async for frame in ws:
                msg = json.loads(frame)
                if "id" in msg and msg["id"] in pending:
                    pending.pop(msg["id"]).set_result(msg)
                    continue
                method, params = msg.get("method"), msg.get("params", {})
                if method == "Runtime.consoleAPICalled" and params["type"] in ("error", "assert"):
                    got["errors"].append(str(params["args"]))
                elif method == "Runtime.exceptionThrown":
                    got["errors"].append(params["exceptionDetails"].get("text", "exception"))
                elif method == "Log.entryAdded" and params["entry"]["level"] == "error":
                    got["errors"].append(params["entry"]["text"])
                elif method == "Network.requestWillBeSent":
                    got["requests"].append(params["request"]["url"])
                elif method == "Page.loadEventFired" and not loaded.done():
                    loaded.set_result(True)

        async def call(method: str, **params) -> dict:
            i = next(ids)
            pending[i] = asyncio.get_running_loop().create_future()
            await ws.send(json.dumps({"id": i, "method": method, "params": params}))
            reply = await asyncio.wait_for(pending[i], 60)
            assert "error" not in reply, reply
            return reply["result"]

        task = asyncio.create_task(pump())
        for domain in ("Page", "Runtime", "Log", "Network"):
            await call(f"{domain}.enable")
        await call("Page.navigate", url=url)
        await asyncio.wait_for(loaded, 60)

        async def js(expr: str):
            return (await call("Runtime.evaluate", expression=expr, returnByValue=True))["result"]["value"]

        got["sections"] = await js("[...document.querySelectorAll('section')].map(s => s.id)")
        got["verdict"] = await js("document.querySelector('#verdict').innerText")
        got["links"] = await js("[...document.querySelectorAll('#verdict a')].map(a => a.getAttribute('href'))")
        got["svgs"] = await js("document.querySelectorAll('svg').length")
        height = await js("document.documentElement.scrollHeight")
        await call("Emulation.setDeviceMetricsOverride", width=1200, height=min(int(height), 16000),
                   deviceScaleFactor=1, mobile=False)
        shot = await call("Page.captureScreenshot", format="png")
        png.write_bytes(base64.b64decode(shot["data"]))
        task.cancel()
    return got


def _picture(png: Path) -> np.ndarray:
    """The screenshot as an RGB array (matplotlib's PNG reader)."""
    from matplotlib.image import imread

    return imread(png)[..., :3]


def _check_page(got: dict, png: Path, methods: list[str]) -> None:
    assert got["errors"] == [], got["errors"]
    assert all(u.startswith(("file:", "data:", "about:")) for u in got["requests"]), got["requests"]
    want = [sid for sid, _ in SECTIONS]
    assert [s for s in got["sections"] if s in want] == want
    assert all(f"fusion-{m}" in got["sections"] for m in methods)
    assert all(link.lstrip("#") in got["sections"] for link in got["links"])
    img = _picture(png)
    assert img.shape[0] > 2000 and img.shape[1] == 1200
    assert img.std() > 0.05 and (img < 0.5).mean() > 0.005  # text and plots on it, not a blank page


@pytest.fixture(scope="module")
def clean(simulated, tmp_path_factory):
    """The simulated figure8 drive with its CAN bus, and its kf solution."""
    drive = simulated("figure8", 120.0, 1, can=True)
    fused = tmp_path_factory.mktemp("report") / "kf.mcap"
    assert cli_main(["fuse", str(drive), "--method", "kf", "-q", "--out", str(fused)]) == 0
    return drive, fused


@needs_chromium
def test_clean_drive_nothing_found(clean, tmp_path):
    drive, fused = clean
    page = tmp_path / "report.html"
    assert cli_main(["report", str(drive), str(fused), "--out", str(page)]) == 0
    text = page.read_text()
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", text)  # nothing to fetch: the page is the file
    got = _browse(page, tmp_path / "clean.png")
    _check_page(got, tmp_path / "clean.png", ["kf"])
    assert got["verdict"].strip().endswith("nothing found") and got["links"] == []
    assert got["svgs"] >= 7  # map, GNSS, time sync, IMU, CAN, kf status and sigma, kf errors
    assert "no data" not in text  # a fieldlog drive with CAN and a fused file fills every section
    assert "against the truth: horizontal RMS" in text


@needs_chromium
def test_foreign_drive_with_missing_topics_lists_the_faults(clean, tmp_path):
    """Another logger's drive: IMU and fixes only (no time sync, no CAN, no raw bytes, no velocity), an IMU gap
    and a GNSS silence; the sections without topics say "no data", the verdict names both faults and links to
    their sections."""
    native, _ = clean
    drive = write_foreign(native, tmp_path / "foreign.mcap", Foreign(drop_runs=(GAP,), silent=(SILENT,)))
    fused = tmp_path / "kf.mcap"
    assert cli_main(["fuse", str(drive), "--method", "kf", "-q", "--out", str(fused)]) == 0
    page = tmp_path / "report.html"
    assert cli_main(["report", str(drive), str(fused), "--out", str(page)]) == 0
    got = _browse(page, tmp_path / "foreign.png")
    _check_page(got, tmp_path / "foreign.png", ["kf"])
    text = page.read_text()
    for sid in ("timesync", "can"):
        section = text[text.index(f'<section id="{sid}">'):]
        assert "no data:" in section[:section.index("</section>")], sid
    gap_s = GAP[1] / 500.0
    m = re.search(r"gap\(s\) in the IMU samples, the longest ([0-9.]+) s", got["verdict"])
    assert m and abs(float(m.group(1)) - gap_s) < 0.01, got["verdict"]
    m = re.search(r"GNSS outage of ([0-9.]+) s", got["verdict"])
    assert m and SILENT[1] <= float(m.group(1)) <= SILENT[1] + 2.0, got["verdict"]
    assert {"#imu", "#gnss"} <= set(got["links"])
    m = re.search(r"longest without a GNSS update</th><td>([0-9.]+) s", text)  # the status topic's coasting
    assert m and SILENT[1] - 1.0 <= float(m.group(1)) <= SILENT[1] + 2.0


def test_a_drive_without_gnss_or_imu_gets_no_data_sections(clean, tmp_path):
    """A drive of /time/sync and /pps only (``fieldlog filter``): every section is there, most say no data."""
    drive, _ = clean
    part = tmp_path / "sync.mcap"
    assert cli_main(["filter", str(drive), "--topics", "/time/sync,/pps", "--out", str(part), "-q"]) == 0
    page = tmp_path / "report.html"
    assert cli_main(["report", str(part), "--out", str(page)]) == 0
    text = page.read_text()
    for sid, _ in SECTIONS:
        assert f'<section id="{sid}">' in text
    for sid in ("map", "gnss", "imu", "can", "fusion"):
        section = text[text.index(f'<section id="{sid}">'):]
        assert "no data:" in section[:section.index("</section>")], sid
