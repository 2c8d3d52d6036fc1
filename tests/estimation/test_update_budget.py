"""The landmarks a vehicle's frame updates and keeps tracked (`update_budget.py`)."""

from __future__ import annotations

import pytest

from cvslam_cli.estimation.update_budget import (
    AUTO_WITH_IMU,
    AUTO_WITHOUT_IMU,
    UpdateBudget,
    resolve,
)


@pytest.mark.parametrize(
    ("kind", "n"),
    [
        ("ins", AUTO_WITH_IMU),
        ("odometry", AUTO_WITHOUT_IMU),
        ("constant_velocity", AUTO_WITHOUT_IMU),
    ],
)
def test_auto_goes_by_the_motion_models_of_the_team(kind: str, n: int) -> None:
    budget, why = resolve("auto", "auto", [kind, kind])
    assert budget == UpdateBudget(n, n)
    assert why.startswith("auto")
    # a team with a vehicle with an IMU (a mixed team too) takes the figure with one
    assert resolve("auto", "auto", ["ins", kind])[0].max_updates == AUTO_WITH_IMU


def test_configured_figures_are_kept_and_the_target_follows_the_updates_on_auto() -> None:
    assert resolve(45, "auto", ["ins"])[0] == UpdateBudget(45, 45)
    assert resolve(45, 20, ["odometry"])[0] == UpdateBudget(45, 20)
    assert resolve("auto", 10, ["constant_velocity"])[0] == UpdateBudget(AUTO_WITHOUT_IMU, 10)
    assert resolve(45, "auto", ["ins"])[1] == "fuse.map.max_updates_per_frame"
