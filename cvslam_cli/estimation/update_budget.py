"""How many landmarks a vehicle's frame updates, and how many it keeps tracked.

A frame's update takes at most `fuse.map.max_updates_per_frame` of the landmarks it
associated (spread over the image, the longest-unseen first: `Slam._associate`), and new
landmarks are mapped while fewer than `fuse.map.target_tracked` were updated
(`NewLandmarks.wanted`). More landmarks a frame constrain the pose more and keep more of the
map in view, at a cost: the update is O(n^2 m) in the state size n and the rows m (3 a
landmark with a rectified rig, 4 otherwise), and every landmark tracked costs its share of
association and mapping (BENCHMARKS.md, "Fuse: the same estimates in less time").

`auto` (the default of both), by the motion models of the vehicles in one filter:
AUTO_WITH_IMU (60) when a vehicle has an IMU (`motion.models.inertial_team`),
AUTO_WITHOUT_IMU (30) otherwise;
`target_tracked` auto is `max_updates_per_frame`. Measured in BENCHMARKS.md ("Fuse: 60
landmarks a frame for a team with IMUs"): the UAV teams (IMU, cameras looking down) gained in
accuracy at 60 (`uav2_paper` images seeds 1-30, both encounter failures gone; the
landmark-mode Monte Carlo), at a third more time; the car of the KITTI clips (constant
velocity) lost; a team of UAVs with ground robots lost with the UAVs at 60 and the rest of
a ground team's settings (`mixed_yard` seed 1, every vehicle but one), and gained with 60
and the rest of an aerial team's ("Fuse: a mixed team mapped the aerial way"). Teams in
landmark mode (perfect associations) lost too (`uav4_team` 11 %): what it costs is listed
there. The same line as the landmark coordinates' and the bearing noise's `auto`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from cvslam_cli.estimation.motion.models import inertial_team

UpdatesSetting = Literal["auto"] | int
# the landmarks a frame updates with `auto` (module docstring, BENCHMARKS.md)
AUTO_WITH_IMU = 60
AUTO_WITHOUT_IMU = 30


@dataclass(frozen=True)
class UpdateBudget:
    """Each vehicle's frame updates at most `max_updates` landmarks and maps new ones while
    fewer than `target_tracked` were updated."""

    max_updates: int
    target_tracked: int


def resolve(
    max_updates: UpdatesSetting, target_tracked: UpdatesSetting, motion_kinds: Sequence[str]
) -> tuple[UpdateBudget, str]:
    """The budget the settings give each frame of a team whose vehicles have motion models
    `motion_kinds`, and why (module docstring)."""
    if max_updates == "auto":
        imu = inertial_team(motion_kinds)
        n = AUTO_WITH_IMU if imu else AUTO_WITHOUT_IMU
        why = "auto: " + ("a vehicle has an IMU" if imu else "no vehicle has an IMU")
    else:
        n, why = int(max_updates), "fuse.map.max_updates_per_frame"
    target = n if target_tracked == "auto" else int(target_tracked)
    return UpdateBudget(n, target), why
