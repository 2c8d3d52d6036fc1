"""The stereo rigs' right principal points, estimated by a calibration pass of the filter
(`fuse.calibration.estimate_right_cx`).

A rectified rig whose right camera's principal point u0 is off along x by du pixels measures
every disparity short by du, so its depths fx b / d come out too long by (d + du) / d, far
points most: KITTI's calibrations leave ~0.2 px on clip a and ~0.9 px on clip b, the "4-5 %
scale disagreement" of clip b (BENCHMARKS.md, "Refine: the right camera's principal point").

du is a constant of the log, which a batch solution estimates well and a filter badly: with
du a state of each vehicle's block from the first frame (`motion/calibration.py`), its first
estimates come from a few frames whose motion and depths trade off with it, a pixel and more
off, and what the trajectory and the landmarks took from them stays (on KITTI clip a every
prior and landmark coordinates tried ended less accurate than no estimate at all:
BENCHMARKS.md, "Fuse: the right camera's principal point, estimated by a calibration
pass"). So the filter runs twice:

1. the calibration pass: every vehicle with du in its block (prior N(0, sigma^2)), no
   sliding window (its clones' tracks would not see du) and the landmarks in anchored
   inverse depth, whatever `fuse.map.landmark_coordinates` says: a Cartesian point from one
   stereo pair starts with its depth biased long (the mean of fx b / d over a noisy
   disparity), which du then absorbs (measured on clip a against the batch solution, and
   on a simulated rig with no offset);
2. the run itself, each rig corrected by its estimate (`VehicleInput.with_right_cx`), the
   estimate taken as known.

A vehicle the pass did not determine keeps its rig as calibrated, and the stage says why: its
pass diverged (in one filter, every vehicle of it), or du's standard deviation is still more
than half its prior (`UNDETERMINED_RATIO`: a vehicle never localised, or that saw too little).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

from cvslam_cli.estimation.settings import SlamSettings, WindowSettings
from cvslam_cli.estimation.slam import Slam
from cvslam_cli.estimation.vehicle import VehicleInput
from cvslam_cli.records.landmark_archive import LandmarkArchive

UNDETERMINED_RATIO = 0.5  # du's std over its prior above which the pass did not determine it


@dataclass(frozen=True)
class RightCxEstimates:
    """The calibration pass's estimates: per vehicle (du, its standard deviation) in px;
    `not_estimated`: per vehicle without one, why."""

    right_cx_px: dict[str, tuple[float, float]]
    not_estimated: dict[str, str] = field(default_factory=dict)

    def corrected(self, vehicles: list[VehicleInput]) -> list[VehicleInput]:
        """The vehicles with their rigs corrected by their estimates."""
        return [
            v.with_right_cx(self.right_cx_px[v.name][0]) if v.name in self.right_cx_px else v
            for v in vehicles
        ]


def estimate_right_cx(
    vehicles: list[VehicleInput],
    settings: SlamSettings,
    sigma_px: float,
    single: bool,
    prior: LandmarkArchive | None = None,
    progress: Callable[[int], None] | None = None,
) -> RightCxEstimates:
    """The calibration pass (module docstring) over `vehicles` as the run will filter them:
    in one filter, or each alone (`single`); du's prior standard deviation sigma_px."""
    calibrating = [v.with_right_cx_state(sigma_px) for v in vehicles]
    pass_settings = replace(
        settings, landmark_coordinates="inverse_depth", window=WindowSettings(window=0)
    )
    groups = [[v] for v in calibrating] if single else [calibrating]
    found: dict[str, tuple[float, float]] = {}
    why: dict[str, str] = {}
    for group in groups:
        res = Slam(group, pass_settings, progress=progress, prior=prior).run()
        d = res.divergence
        if d is not None:
            t_s = (d.stamp_ns - min(v.start_ns for v in group)) * 1e-9
            why |= {v.name: f"the calibration pass diverged ({d.vehicle} at {t_s:.1f} s: "
                            f"{d.reason})" for v in group}  # fmt: skip
            continue
        for name, (du, sd) in res.right_cx_px.items():
            if sd > UNDETERMINED_RATIO * sigma_px:
                why[name] = (
                    f"not determined by the calibration pass (+- {sd:.3f} px of a {sigma_px:g} "
                    "px prior: never localised, or too few observations)"
                )
            else:
                found[name] = (du, sd)
    return RightCxEstimates(found, why)
