"""One distribution, one import name: the wheel holds only `fieldlog` (not the development tools of
`fieldlog.tools.dev`), and both installs import it from outside."""
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from fieldlog.tools.commands.common import KERNELS

ROOT = Path(__file__).resolve().parents[1]


def _run(args, cwd, **env):
    import os

    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=600, env={**os.environ, **env})


def test_wheel_holds_only_fieldlog(tmp_path):
    # built from a copy without the checkout's build/ (setuptools' build/lib keeps the files of earlier builds,
    # moved or deleted ones too, and packs them into the next wheel)
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", ".venv", "build", "dist", "*.egg-info", "out",
                                                              "__pycache__", ".pytest_cache", ".hypothesis"))
    r = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"), str(src)],
             tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("fieldlog-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"fieldlog"}
    assert "fieldlog/tools/sim/scenarios/figure8.toml" in names   # scenario data travels with the code
    assert "fieldlog/tools/templates/report.html.j2" in names     # so does the report's page template
    assert "fieldlog/tools/evaluation/evaluate.py" in names
    dev = [n for n in names if n.startswith("fieldlog/tools/dev/")
           or n.rpartition("/")[2] in ("bench.py", "fuzz.py", "layouts.py", "screenshot.py")]
    assert not dev, dev                                           # the development tools stay in the checkout
    built = {n.split(".")[0].replace("/", ".") for n in names if n.endswith(".so")}
    assert built == set(KERNELS), built                           # the compiled kernels setup.py builds

    # the wheel, unpacked on its own path, imported from a directory outside the checkout
    site = tmp_path / "site"
    r = _run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel)], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    probe = ("import fieldlog, fieldlog.fusion, fieldlog.drive, fieldlog.acquire, fieldlog.replay, fieldlog.tools.cli; "
             "print(fieldlog.fusion.__file__)")
    r = _run([sys.executable, "-c", probe], tmp_path, PYTHONPATH=str(site))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().startswith(str(site))
    r = _run([sys.executable, "-c", "import tools"], tmp_path, PYTHONPATH=str(site))
    assert r.returncode != 0 and "No module named 'tools'" in r.stderr
    r = _run([sys.executable, "-m", "fieldlog", "--version"], tmp_path, PYTHONPATH=str(site))
    import tomllib

    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert r.returncode == 0 and r.stdout.strip() == f"fieldlog {version}", r.stdout + r.stderr


def test_editable_install_imports_fieldlog_only(tmp_path):
    """The test environment is the editable install (`make setup`): outside the checkout only `fieldlog` imports."""
    r = _run([sys.executable, "-c", "import fieldlog.fusion; print(fieldlog.fusion.__file__)"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()).resolve() == ROOT / "fusion" / "__init__.py"
    for name in ("tools", "acquire", "fusion", "replay"):
        r = _run([sys.executable, "-c", f"import {name}"], tmp_path)
        assert r.returncode != 0, name
    exe = Path(sys.executable).parent / "fieldlog"
    r = _run([str(exe), "--version"], tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("fieldlog "), r.stderr


@pytest.mark.parametrize("kernel, argv", [("fieldlog.drive._chunks", ["info"]),
                                          ("fieldlog.fusion._ins", ["fuse", "--out", "{tmp}/f.mcap"]),
                                          ("fieldlog.fusion._cycles", ["fuse", "--out", "{tmp}/f.mcap"])])
def test_an_install_without_its_kernels_says_to_reinstall(simulated, monkeypatch, capsys, tmp_path, kernel, argv):
    """A checkout used without `pip install -e .` (or a build that lost a kernel): one line naming the kernel and
    what to do, exit code 2."""
    import importlib.util

    from fieldlog.drive import native
    from fieldlog.fusion import errmodel, ins, kernels
    from fieldlog.tools.cli import main

    drive = simulated("figure8", 60, 1)
    find = importlib.util.find_spec
    monkeypatch.setattr(native, "_libs", {})
    monkeypatch.setattr(kernels, "_loaded", {})
    for loader in (errmodel.cycle_kernel, ins._kernel):  # their functions' types are set once per process
        loader.cache_clear()
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == kernel else find(name, *a))
    capsys.readouterr()
    rc = main([argv[0], str(drive), *(x.format(tmp=tmp_path) for x in argv[1:])])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and kernel in err[0] and "reinstall" in err[0], err
