"""Shared fixtures: the real-data folder and a CLI runner with the error boundary."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pytest

from cvslam_cli.cli import main
from tests.scenarios import small_uav_scenario

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


@pytest.fixture(scope="session")
def small_image_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 s of two simulated UAVs with images (376 x 240), extracted and fused (cooperative
    NH-infinity), made once per session; tests copy it before changing anything."""
    tmp = tmp_path_factory.mktemp("small_image_run")
    camera = {"width": 376, "height": 240, "fx": 225.0, "fy": 225.0, "cx": 187.5, "cy": 119.5}
    sc = small_uav_scenario(
        tmp,
        duration_s=8.0,
        mode="images",
        **{f"vehicles.{v}.camera.{k}": x for v in ("uav1", "uav2") for k, x in camera.items()},
        **{"terrain.texture_px_per_m": 4.0},
    )
    run = tmp / "run"
    steps = (
        lambda: ["-q", "simulate", str(sc), "-o", str(run)],
        lambda: ["-q", "extract", *map(str, sorted(run.glob("*.mcap"))), "-o", str(run)],
        lambda: ["-q", "fuse", str(run)],
    )
    for step in steps:
        args = step()
        with pytest.raises(SystemExit) as exc:
            main(args)
        assert exc.value.code in (0, None), args
    return run
