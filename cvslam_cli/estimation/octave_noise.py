"""A keypoint's bearing noise by the SIFT octave it was found at.

SIFT places a keypoint to a fraction of its octave's pixels, so a keypoint found at a coarser
scale is placed less precisely in the image, and its error changes more slowly along a track
(the texture that decides it is larger than the view's change between frames). A stereo
match's disparity is measured between two keypoints of one scale on one row, whose errors
are largely common, and does not grow so. Measured with the simulator's truth and on KITTI's
frames in BENCHMARKS.md, "Fuse: the bearing noise by octave".

The filter's pixel noise (`fuse.association.pixel_sigma_px`, measured from consecutive
frames or configured) is one figure for all keypoints; consecutive frames see little of an
error that drifts slowly. `fuse.association.octave_bearing_variance` scales the bearing part
of a landmark observation's noise in the frame's update (the part both images' keypoints
share: `observation.BEARING_ROWS`, `update.py`; the sliding window's track rows, joint
initialisation and localisation keep the one figure) by the keypoint's octave: the o-th
number for octave o, the last for every coarser one, the first for octaves below 0 (an
upsampled image's). `auto`'s octave 0 number is 1, so the finest keypoints keep the measured
noise, and a run whose keypoints are all of octave 0 (the landmark-mode simulator's, whose
noise is one sigma for every keypoint) is the filter without it.

`auto` (the default): AUTO_FACTORS when a vehicle of the team has an IMU
(`motion.models.inertial_team`), every octave alike otherwise. Where it was measured, the
UAV teams (IMU, cameras looking down) gained in accuracy and consistency, and the vehicles
without an IMU, with forward cameras, lost: the car of the KITTI clips (constant velocity)
on both clips, the ground robots of `ugv2_yard` (wheel odometry) on two seeds of three, one
of them badly; why is not known. With UAVs in the team (`mixed_yard`) the ground robots too
gained, with the rest of an aerial team's settings. The same line as the landmark
coordinates' and the update budget's `auto`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from cvslam_cli.estimation.motion.models import inertial_team
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import FeatureSet

OctaveSetting = Literal["auto"] | tuple[float, ...]
# the factors `auto` gives a team whose vehicles all have an IMU (BENCHMARKS.md)
AUTO_FACTORS = (1.0, 4.0, 8.0)


def resolve(setting: OctaveSetting, motion_kinds: Sequence[str]) -> tuple[tuple[float, ...], str]:
    """The factors fuse.association.octave_bearing_variance gives a team whose vehicles have
    motion models `motion_kinds`, and why (module docstring)."""
    if setting != "auto":
        return tuple(setting), "fuse.association.octave_bearing_variance"
    if inertial_team(motion_kinds):
        return AUTO_FACTORS, "auto: a vehicle has an IMU"
    return (), "auto: no vehicle has an IMU"


@dataclass(frozen=True, eq=False)
class OctaveBearingNoise:
    """factors (g,): the bearing noise variance over the filter's of keypoints of octave o
    (factors[min(o, g - 1)]; octaves below 0, an upsampled image's, as octave 0)."""

    factors: F64

    @classmethod
    def of(cls, factors: Sequence[float], octaves: Sequence[I64]) -> OctaveBearingNoise | None:
        """The configured `factors` for a run whose stereo matches are of these octaves (one
        array per vehicle); None when no match gets a factor other than 1."""
        f = np.asarray(factors, dtype=float)
        if not len(f):
            return None
        used = _groups(np.concatenate([np.asarray(o).ravel() for o in octaves]), len(f))
        if np.all(f[used] == 1.0):
            return None
        return cls(f)

    def scale(self, octave: I64) -> F64:
        """(k,) the bearing noise variance factors of keypoints of these octaves (k,)."""
        return self.factors[_groups(octave, len(self.factors))]


def match_octaves(fs: FeatureSet) -> I64:
    """(M,) the octave of each stereo match's left keypoint in `fs`."""
    return fs.left_octave[fs.match_left]


def _groups(octave: I64, n_groups: int) -> I64:
    return np.clip(np.asarray(octave, dtype=np.int64), 0, n_groups - 1)
