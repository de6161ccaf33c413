"""The package's import graph: no module imports itself back through others (no import cycle), and the layers point
one way (tools -> replay -> acquire -> drive; fusion imports nothing of ours, the drive layer nothing above it).

Every import counts, wherever it stands (module level, inside a function, under ``TYPE_CHECKING``): a cycle that
only a lazy import keeps working is still a cycle to whoever reads the code."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"drive": "fieldlog.drive", "acquire": "fieldlog.acquire", "fusion": "fieldlog.fusion",
           "replay": "fieldlog.replay", "tools": "fieldlog.tools", "src/fieldlog": "fieldlog"}


def _modules() -> dict[str, Path]:
    out = {}
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join([package, *parts])] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The fieldlog modules that module ``name`` imports (a package's own ``__init__`` only when named alone)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            for a in node.names:
                out.add(f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base)
    return {m for m in out if m in modules and m != name}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_graph_is_read():
    graph = _graph()
    assert "fieldlog.fusion.engine" in graph["fieldlog.tools.fuse"]
    assert "fieldlog.fusion.earth" in graph["fieldlog.fusion.errmodel"]  # `from fieldlog.fusion import earth`
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle():
    cycles = _cycles(_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_layers_point_one_way():
    allowed = {"fieldlog.fusion": {"fieldlog.fusion"}, "fieldlog.drive": {"fieldlog.drive", "fieldlog.fusion"},
               "fieldlog.acquire": {"fieldlog.acquire", "fieldlog.drive", "fieldlog.fusion"},
               "fieldlog.replay": {"fieldlog.replay", "fieldlog.acquire", "fieldlog.drive", "fieldlog.fusion"}}
    bad = []
    for name, deps in _graph().items():
        layer = ".".join(name.split(".")[:2])
        for d in deps:
            if layer in allowed and d != "fieldlog" and ".".join(d.split(".")[:2]) not in allowed[layer]:
                bad.append(f"{name} -> {d}")
    assert not bad, "imports against the layers: " + ", ".join(sorted(bad))


def _third_party(path: Path) -> set[str]:
    """The top-level names of every module that ``path`` imports, wherever the import stands."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            out.add(node.module.split(".")[0])
    return out


def test_only_the_drive_layer_imports_mcap():
    """The MCAP library is the drive layer's: the layers above read and write drives through it
    (``fieldlog.drive.records`` names the library's records, reader and writer for them)."""
    modules = _modules()
    users = {name for name, path in modules.items() if "mcap" in _third_party(path)}
    assert "fieldlog.drive.recorder" in users  # the scan sees the imports
    outside = sorted(u for u in users if not u.startswith("fieldlog.drive."))
    assert not outside, "modules importing mcap outside fieldlog.drive: " + ", ".join(outside)
