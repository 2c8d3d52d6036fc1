"""The README's "From the paper to the code" table points at code that exists: every file it
names is in the package and every function or class it names is defined in one of the
row's files (a renamed or moved function fails here, not in a newcomer's search)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGE = REPO / "cvslam_cli"


def _table_rows() -> list[tuple[str, list[str], list[str]]]:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("## From the paper to the code", 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 3 or cells[0] in ("paper", "---"):
            continue
        files = re.findall(r"`([\w/]+\.py)`", cells[1])
        names = re.findall(r"`([\w.]+)`", cells[2])
        rows.append((cells[0], files, names))
    return rows


def _defined(path: Path) -> set[str]:
    """Top-level functions and classes of a module, and its methods as Class.method and
    (for a row that lists a class's methods after it) method."""
    out: set[str] = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.FunctionDef | ast.ClassDef):
            out.add(node.name)
        if isinstance(node, ast.ClassDef):
            methods = [m.name for m in node.body if isinstance(m, ast.FunctionDef)]
            out.update(methods)
            out.update(f"{node.name}.{m}" for m in methods)
    return out


def test_every_function_in_the_paper_table_exists_where_it_says():
    rows = _table_rows()
    assert len(rows) >= 15
    for what, files, names in rows:
        assert files and names, f"row {what!r}: no file or no function"
        defined: set[str] = set()
        for f in files:  # relative to cvslam_cli/
            path = PACKAGE / f
            assert path.exists(), f"row {what!r}: {f} not found"
            defined |= _defined(path)
        for name in names:
            assert name in defined, f"row {what!r}: {name} not in {files}"
