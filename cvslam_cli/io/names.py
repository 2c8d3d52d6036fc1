"""Topic and frame names cvslam writes for one vehicle (DESIGN.md section 4).

They come from the default topic map and rig of `configs/default.yaml`, so a log written by
an importer or the simulator is read back with no config at all.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from cvslam_cli.config import RigConfig, TopicMap
from cvslam_cli.errors import CvslamError

NAV_FRAME_ID = "nav"
TF_STATIC_TOPIC = "/tf_static"
_VEHICLE_RE = re.compile(r"^[A-Za-z0-9_]+$")


@dataclass(frozen=True)
class VehicleNames:
    """`topics`: the default topic map resolved for `vehicle`; frames for TF and headers."""

    vehicle: str
    topics: TopicMap
    body_frame: str
    left_frame: str
    right_frame: str


def vehicle_names(vehicle: str, error: type[CvslamError] = CvslamError) -> VehicleNames:
    """Names for `vehicle`, which becomes part of topic names: letters, digits, underscores."""
    if not _VEHICLE_RE.match(vehicle):
        raise error(
            f"vehicle name {vehicle!r}: expected letters, digits and underscores "
            "only (it becomes part of the topic names)"
        )
    return VehicleNames(
        vehicle,
        TopicMap().resolve(vehicle),
        body_frame=RigConfig().body_frame.replace("{vehicle}", vehicle),
        left_frame=f"{vehicle}/left_camera_optical",
        right_frame=f"{vehicle}/right_camera_optical",
    )
