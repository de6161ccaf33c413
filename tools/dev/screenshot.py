"""``make screenshot``: docs/viewer.png, the default rerun layout of ``fieldlog view`` on a simulated drive.

    python -m fieldlog.tools.dev.screenshot [--out docs/viewer.png] [--duration 300] [--size 1600x1000]

A figure8 drive is simulated, fused with ``dkf-rbfn`` through a 30 s GPS outage (the ``fieldlog demo``
steps), and logged by ``replay.view.build`` with the default blueprint of ``replay.view.blueprint`` (side
panels collapsed, the time cursor following the newest data, so the whole drive is on screen, the close-up
view tracking the fused vehicle), the map zoomed to the track. The native rerun
viewer renders it under Xvfb on the CPU (Vulkan through Mesa's lavapipe) and writes the PNG itself
(``rerun --screenshot-to``).

Needs, on Debian 12 (not part of ``make test``): ``apt-get install -y xvfb xauth mesa-vulkan-drivers``.
Map tiles come from the internet: without a network the map shows the tracks on a black background.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import rerun as rr

from fieldlog.fusion.methods import DKF_RBFN
from fieldlog.drive import reader
from fieldlog.replay import view as rv

ROOT = Path(__file__).resolve().parents[2]
APT = "xvfb xauth mesa-vulkan-drivers"


def map_zoom(lat_deg: np.ndarray, lon_deg: np.ndarray, points: float = 300.0) -> float:
    """Web-mercator zoom level at which the track's larger extent spans about ``points`` logical points."""
    lat0 = np.radians(np.nanmedian(lat_deg))
    extent_m = max(np.ptp(lat_deg) * 111_320.0, np.ptp(lon_deg) * 111_320.0 * np.cos(lat0), 1.0)
    return float(np.log2(156_543.03 * np.cos(lat0) * points / extent_m))  # m per point at zoom 0 / 2**z


def demo_recording(work: Path, duration_s: float) -> Path:
    """Simulate, fuse dkf-rbfn with a 30 s outage at 180 s, write ``work/viewer.rrd``."""
    from fieldlog.fusion.config import FusionConfig
    from fieldlog.tools.fuse import fuse
    from fieldlog.tools.fuse_settings import parse_outage
    from fieldlog.tools.sim.simulate import simulate

    drive, fused, rrd = work / "figure8.mcap", work / "dkf-rbfn.mcap", work / "viewer.rrd"
    simulate("figure8", duration_s, 1, drive, force=True)     # its own work folder, redone each time
    fuse(drive, DKF_RBFN.name, fused, FusionConfig.from_flat(outages=(parse_outage("180:30"),)), force=True)
    fix = reader.read_topic(drive, "/gps/fix")
    ok = fix["valid"] & (fix["status"] >= 0)
    rec = rr.RecordingStream("fieldlog")
    rec.save(rrd, default_blueprint=rv.blueprint(map_zoom(fix["lat_deg"][ok], fix["lon_deg"][ok]), "fusion/dkf-rbfn"))
    try:
        rv.build(rec, drive, [fused])
    finally:
        rec.flush()
        rec.disconnect()
    return rrd


def render(rrd: Path, out: Path, size: str, timeout_s: float = 300.0) -> None:
    """The native viewer on ``rrd`` -> ``out`` (PNG), under ``xvfb-run`` unless a display is set."""
    rerun = Path(sys.executable).parent / "rerun"
    w, h = (int(x) for x in size.split("x"))
    cmd = [str(rerun), "--port", "auto", "--window-size", size, "--screenshot-to", str(out), str(rrd)]
    if not os.environ.get("DISPLAY"):
        if shutil.which("xvfb-run") is None:
            raise SystemExit(f"xvfb-run not found: apt-get install -y {APT}")
        # the window is 2 pixels per point; a screen over twice its size: the pointer starts at the screen's
        # centre, off the window (no hover tooltip)
        cmd = ["xvfb-run", "-a", "-s", f"-screen 0 {4 * w + 200}x{4 * h + 200}x24", *cmd]
    env = {**os.environ, "WGPU_BACKEND": os.environ.get("WGPU_BACKEND", "vulkan"), "RERUN_ANALYTICS": "0",
           "CI": "1", "XDG_RUNTIME_DIR": os.environ.get("XDG_RUNTIME_DIR", tempfile.gettempdir())}
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s)
    if res.returncode != 0 or not out.is_file():
        raise SystemExit(f"rerun did not write {out} (exit {res.returncode}):\n{res.stderr[-2000:]}")
    from PIL import Image  # pillow comes with matplotlib

    with Image.open(out) as im:  # the viewer renders at 2 pixels per point: back to the window size
        small = im.convert("RGB").resize((w, h), Image.LANCZOS) if im.size != (w, h) else None
    if small is not None:
        small.save(out, optimize=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(ROOT / "docs" / "viewer.png"))
    p.add_argument("--duration", type=float, default=300.0, help="seconds of drive (>= 240: the outage is at 180 s)")
    p.add_argument("--size", default="1600x1000", help="viewer window, logical points")
    p.add_argument("--keep", default=None, metavar="DIR", help="keep the drive, fused file and .rrd here")
    a = p.parse_args()
    out = Path(a.out).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(a.keep) if a.keep else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        rrd = demo_recording(work, a.duration)
        render(rrd, out, a.size)
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
