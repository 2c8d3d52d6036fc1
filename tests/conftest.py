"""Shared fixtures: the real-data folder and a CLI runner with the error boundary."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pytest

from cvslam_cli.cli import main

REPO = Path(__file__).resolve().parent.parent


def shared_data_dir() -> Path:
    return Path(os.environ.get("CVSLAM_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = shared_data_dir()
    if not path.is_dir():
        pytest.skip(f"real data folder {path} not found (set CVSLAM_SHARED_DATA)")
    return path


@dataclass
class CliResult:
    code: int
    out: str
    err: str


@pytest.fixture
def cvslam(capsys: pytest.CaptureFixture[str]):
    """Run `cvslam ARGS...` in-process through `cli.main` (the real error boundary)."""

    def run(*args: object) -> CliResult:
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = int(exc.code or 0)
        captured = capsys.readouterr()
        return CliResult(code, captured.out, captured.err)

    return run
