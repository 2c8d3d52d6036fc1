"""The import layers of DESIGN.md section 6, checked on the source: records below io/ and
every stage, io/ below the stages, the pure evaluation code on records only."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "cvslam_cli"
STAGES = ("features", "estimation", "mosaic", "sim", "evaluation")


def imports(path: Path) -> set[str]:
    """Every module `path` imports (absolute names; also inside functions)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
    return out


def modules(folder: str) -> list[Path]:
    return sorted((PACKAGE / folder).rglob("*.py"))


def within(name: str, *packages: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


def stdlib(name: str) -> bool:
    return name.split(".")[0] in sys.stdlib_module_names


@pytest.mark.parametrize("path", modules("records"), ids=lambda p: p.name)
def test_records_are_the_lowest_floor(path):
    """records/ imports only numpy, errors and itself: every other package builds on it
    (geometry too, for its array aliases and the rig calibration record)."""
    allowed = ("numpy", "cvslam_cli.records", "cvslam_cli.errors")
    bad = {m for m in imports(path) if not stdlib(m) and not within(m, *allowed)}
    assert not bad, f"{path.name} imports {sorted(bad)}"


@pytest.mark.parametrize("path", modules("io"), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_io_imports_no_stage(path):
    bad = {m for m in imports(path) if within(m, *(f"cvslam_cli.{s}" for s in STAGES))}
    assert not bad, f"{path.relative_to(PACKAGE)} imports {sorted(bad)}"


@pytest.mark.parametrize("name", ["metrics", "align", "figures", "report"])
def test_pure_evaluation_code_takes_records_not_files(name):
    bad = {m for m in imports(PACKAGE / "evaluation" / f"{name}.py") if within(m, "cvslam_cli.io")}
    assert not bad, f"evaluation/{name}.py imports {sorted(bad)}"


def test_no_type_checking_import_workaround():
    used = [
        str(p.relative_to(PACKAGE))
        for p in PACKAGE.rglob("*.py")
        if "TYPE_CHECKING" in p.read_text()
    ]
    assert not used, f"TYPE_CHECKING imports (an import circle or a layer crossed): {used}"
