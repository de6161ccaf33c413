"""The shape of the code, read with ``ast``: classes and functions small enough to read, and the public functions
of ``fusion/`` and the drive layer documented as CONTRIBUTING says (numpydoc ``Parameters``, and ``Returns`` when
they return something). Each test lists every offender in its failure message."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ("drive", "acquire", "fusion", "replay", "tools", "src/fieldlog")
MAX_METHODS = 15  # defs directly in a class body, in the folders of SMALL_CLASSES
SMALL_CLASSES = ("acquire", "fusion", "drive")
MAX_LINES = 80  # end_lineno - lineno + 1 of any function, nested ones included, outside tools/dev
DOCUMENTED = ("fusion", "drive")


def _files(folders: tuple[str, ...]) -> list[Path]:
    return [p for f in folders for p in sorted((ROOT / f).rglob("*.py")) if ".venv" not in p.parts]


def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), str(path))


def _where(path: Path, node: ast.AST) -> str:
    return f"{path.relative_to(ROOT).as_posix()}:{node.lineno}"


def _functions(node: ast.AST):
    """Every function definition under ``node``, nested ones included."""
    return (n for n in ast.walk(node) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)))


def shape_offenders() -> list[str]:
    """Classes with more than ``MAX_METHODS`` methods (in ``SMALL_CLASSES``) and functions longer than
    ``MAX_LINES`` lines (outside tools/dev), one line each."""
    out = []
    for path in _files(SMALL_CLASSES):
        for cls in (n for n in ast.walk(_tree(path)) if isinstance(n, ast.ClassDef)):
            n = sum(isinstance(b, (ast.FunctionDef, ast.AsyncFunctionDef)) for b in cls.body)
            if n > MAX_METHODS:
                out.append(f"{_where(path, cls)} class {cls.name}: {n} methods (at most {MAX_METHODS})")
    for path in _files(PACKAGE):
        if path.relative_to(ROOT).parts[:2] == ("tools", "dev"):
            continue
        for fn in _functions(_tree(path)):
            n = fn.end_lineno - fn.lineno + 1
            if n > MAX_LINES:
                out.append(f"{_where(path, fn)} function {fn.name}: {n} lines (at most {MAX_LINES})")
    return out


def _public_defs(tree: ast.Module):
    """(function, its class or None) for the module's public functions and the public methods of its public
    classes (a class nested in a function is not public)."""
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            yield node, None
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for b in node.body:
                if isinstance(b, (ast.FunctionDef, ast.AsyncFunctionDef)) and not b.name.startswith("_"):
                    yield b, node


def _parameters(fn: ast.FunctionDef, cls: ast.ClassDef | None) -> list[str]:
    """The parameters a caller gives (``self``/``cls`` of a method left out)."""
    a = fn.args
    names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    names += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
    static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in fn.decorator_list)
    if cls is not None and not static and names[:1] in (["self"], ["cls"]):
        names = names[1:]
    return names


def _returns_value(fn: ast.FunctionDef) -> bool:
    """Whether the return annotation says the function returns something (not None, not absent)."""
    r = fn.returns
    return r is not None and not (isinstance(r, ast.Constant) and r.value in (None, "None"))


def _section(doc: str, name: str) -> bool:
    """Whether numpydoc section ``name`` (its title, then a line of dashes) is in ``doc``."""
    lines = [x.strip() for x in doc.splitlines()]
    return any(a == name and b.startswith("---") for a, b in zip(lines, lines[1:]))


def doc_offenders() -> list[str]:
    """Public functions and methods of ``DOCUMENTED`` taking parameters without a numpydoc Parameters section, or
    annotated to return a value without a Returns section (a property is documented as the attribute it is)."""
    out = []
    for path in _files(DOCUMENTED):
        for fn, cls in _public_defs(_tree(path)):
            if any(isinstance(d, ast.Name) and d.id == "property" for d in fn.decorator_list):
                continue
            doc = ast.get_docstring(fn) or ""
            name = f"{cls.name}.{fn.name}" if cls is not None else fn.name
            missing = [s for s, need in (("Parameters", bool(_parameters(fn, cls))), ("Returns", _returns_value(fn)))
                       if need and not _section(doc, s)]
            if missing:
                out.append(f"{_where(path, fn)} {name}: no {' or '.join(missing)} section")
    return out


def test_classes_and_functions_are_small():
    bad = shape_offenders()
    assert not bad, f"{len(bad)} classes or functions too big:\n" + "\n".join(bad)


def test_public_functions_have_numpydoc_sections():
    bad = doc_offenders()
    assert not bad, f"{len(bad)} public functions undocumented:\n" + "\n".join(bad)


@pytest.mark.parametrize("offenders", [shape_offenders, doc_offenders], ids=["shape", "docs"])
def test_drive_layer_keeps_the_rules(offenders):
    """The drive layer keeps the rules (the other folders follow once their owners are done)."""
    bad = [x for x in offenders() if x.startswith("drive/")]
    assert not bad, "\n".join(bad)
