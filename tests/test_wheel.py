"""The package as users install it: a wheel holds the shipped configs and scenarios, and,
installed in a fresh virtual environment (outside the source tree), runs the demo scenario.

The wheel is built from a copy of the sources (nothing written into the repository) with pip
in its default isolated build (setuptools and wheel from the package index, as `make install`
uses it). The fresh venv gets the wheel alone (`--no-deps`); its dependencies come from this
interpreter's site-packages through a .pth file, so the test needs no download of them.
Building the wheel is in `make test` (~5-10 s); installing it and running the scenario
(simulate with images, then every stage: ~70 s on 2 busy cores) only with
CVSLAM_WHEEL_TEST=1.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
CONFIGS = REPO / "cvslam_cli" / "configs"

# 6 s of the paper's mission at its own speeds (uav2 from 0.5 s), images at half size;
# `--duration 5` would fly the 60 s mission 12x faster (150 m/s)
SMALL_CAMERA = {"width": 376, "height": 240, "fx": 225.0, "fy": 225.0, "cx": 187.5, "cy": 119.5}
SIM_SETS = [
    "duration_s=6",
    "vehicles.uav2.start_s=0.5",
    *(f"vehicles.{v}.camera.{k}={x}" for v in ("uav1", "uav2") for k, x in SMALL_CAMERA.items()),
]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    shutil.copytree(
        REPO / "cvslam_cli", src / "cvslam_cli", ignore=shutil.ignore_patterns("__pycache__")
    )
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-q", "-w", str(tmp)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    (path,) = tmp.glob("cvslam-*.whl")
    return path


def test_the_wheel_holds_every_shipped_config_and_scenario(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = sorted(p for p in CONFIGS.rglob("*") if p.is_file())
    assert len(shipped) >= 6
    for p in shipped:
        assert f"cvslam_cli/{p.relative_to(REPO / 'cvslam_cli')}" in names, p
    assert any(n.endswith("entry_points.txt") for n in names)


@pytest.mark.skipif(
    os.environ.get("CVSLAM_WHEEL_TEST") != "1",
    reason="installs the wheel in a fresh venv and runs every stage (~70 s): CVSLAM_WHEEL_TEST=1",
)
def test_the_installed_wheel_runs_the_demo_scenario(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    pip = [sys.executable, "-m", "pip", "--python", str(py)]
    subprocess.run([*pip, "install", "--no-deps", "--no-index", "-q", str(wheel)], check=True)
    site = subprocess.run(
        [py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (Path(site) / "_cvslam_test_deps.pth").write_text("\n".join(sorted(ours)) + "\n")
    cvslam = venv / "bin" / "cvslam"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # not the source tree

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        proc = subprocess.run(
            [str(cvslam), *args], cwd=tmp_path, env=env, capture_output=True, text=True
        )
        assert proc.returncode == 0, (args, proc.stderr)
        return proc

    where = subprocess.run(
        [py, "-c", "import cvslam_cli.config as c; print(c.CONFIG_DIR)"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    assert Path(where).is_relative_to(venv), where  # the installed copy, not the sources
    run("simulate", "uav2_paper", "-o", "sim", *(a for s in SIM_SETS for a in ("--set", s)))
    shown = run("info", "sim/uav1.mcap", "sim/uav2.mcap").stdout
    assert "vehicle uav1" in shown and "vehicle uav2" in shown
    run("run", "sim/uav1.mcap", "sim/uav2.mcap", "-o", "run", "--config", "paper")
    metrics = yaml.safe_load((tmp_path / "run" / "eval" / "metrics.json").read_text())
    assert {e["vehicle"] for e in metrics["estimates"]} == {"uav1", "uav2"}
    shown = run("config", "show", "fuse.hinf.gamma").stdout
    assert "gamma: 30.0  # default" in shown and "# Bound gamma" in shown
