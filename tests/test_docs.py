"""The docs name the code as it is: docs/architecture.md's module table lists every module file of the package
and no file that is gone; docs/data-model.md's tables name every metadata record the code writes."""
import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ("drive", "acquire", "fusion", "replay", "tools", "src/fieldlog")


def _table() -> list[tuple[str, str]]:
    """The module table's rows of docs/architecture.md as (first cell, second cell)."""
    rows = []
    for line in (ROOT / "docs" / "architecture.md").read_text().splitlines():
        cells = line.split("|")
        if line.startswith("| `") and len(cells) >= 4:
            rows.append((cells[1], cells[2]))
    return rows


def _module_files() -> list[Path]:
    """Every Python and C source of the package, package markers (``__init__.py``) aside."""
    return [p for folder in PACKAGE for p in sorted((ROOT / folder).rglob("*"))
            if p.suffix in (".py", ".c") and p.name != "__init__.py" and "__pycache__" not in p.parts]


def listed(path: str, rows: list[tuple[str, str]]) -> bool:
    """A module is listed when its path is in a row's first cell, or its folder is there and the row names the file."""
    folder, _, name = path.rpartition("/")
    return any(f"`{path}`" in first or (f"`{folder}/`" in first and f"`{name}`" in job) for first, job in rows)


def test_every_module_is_in_the_architecture_table():
    rows = _table()
    files = _module_files()
    assert len(files) > 100  # the walk sees the package
    missing = [p.relative_to(ROOT).as_posix() for p in files if not listed(p.relative_to(ROOT).as_posix(), rows)]
    assert not missing, "docs/architecture.md's module table lacks: " + ", ".join(missing)


def test_the_architecture_table_names_no_missing_file():
    named = {m for first, _ in _table() for m in re.findall(r"`(\w[\w.]*/[\w/.]*)`", first)}
    assert "fusion/earth.py" in named
    gone = sorted(n for n in named if not (ROOT / n).exists())
    assert not gone, "docs/architecture.md's module table names files that do not exist: " + ", ".join(gone)


def test_a_module_left_out_is_found():
    rows = [("`fusion/earth.py`", "WGS-84"), ("`tools/sim/`", "`trajectory.py` (scenarios)")]
    assert listed("fusion/earth.py", rows) and listed("tools/sim/trajectory.py", rows)
    assert not listed("fusion/ins.py", rows) and not listed("tools/sim/sensors.py", rows)


def _written_records() -> set[str]:
    """The metadata record names written as literals (``add_metadata("name", ...)``) by the package, tools/dev aside."""
    names = set()
    for path in _module_files():
        if path.suffix != ".py" or "dev" in path.relative_to(ROOT).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_metadata"
                    and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
                names.add(node.args[0].value)
    return names


def test_every_metadata_record_written_is_in_the_data_model():
    written = _written_records()
    assert {"fusion", "fusion.config", "drive"} <= written  # the scan sees the writers
    doc = (ROOT / "docs" / "data-model.md").read_text()
    documented = {m.group(1) for m in re.finditer(r"^\| `([\w.]+)`", doc, re.M)}
    missing = sorted(written - documented)
    assert not missing, "metadata records written but not in docs/data-model.md's tables: " + ", ".join(missing)
