"""Look-alikes in a vehicle's own frames: whether its images hold repeated textures at all,
for `fuse.association.other_vehicle_lookalikes_per_mpx` auto (`association.lookalike_gates`).

A look-alike is a keypoint that passes the descriptor tests asked of another vehicle's
landmark (distance below `max_distance`, below `ratio` times the next one) without being
its point: on a repeated texture (bricks, tiles, a row of windows) a landmark's twin does.
Where the point itself is not re-detected, its twin is the one match left, and no descriptor
test can tell. Within one frame, a stereo match whose nearest other match passes those tests
against it is a look-alike pair: on the simulated images of the teams 5-7 % of the matches
have one, on KITTI 2 %, in the landmark-mode simulation (synthetic descriptors, distinct by
construction) none (BENCHMARKS.md, "Fuse: another vehicle's landmark, inside a window that
a look-alike would fill").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cvslam_cli.estimation.association import descriptor_distances
from cvslam_cli.records.features import FeatureSet


@dataclass(frozen=True)
class LookalikeSample:
    """Stereo matches examined (`matches`) and those with a look-alike in their own frame
    (`with_lookalike`), over `frames` frames."""

    frames: int
    matches: int
    with_lookalike: int

    @property
    def share(self) -> float:
        return self.with_lookalike / self.matches if self.matches else 0.0


def sample_lookalikes(
    fs: FeatureSet, ratio: float, max_distance: float, every: int = 10
) -> LookalikeSample:
    """Every `every`-th frame of `fs`: its stereo matches whose nearest other match of the
    frame (by descriptor) is closer than `max_distance` and than `ratio` times the next."""
    frames = matches = found = 0
    for f in range(0, len(fs.frame_stamp_ns), every):
        desc = fs.left_desc[fs.match_left[fs.frame_matches(f)]]
        if len(desc) < 3:
            continue
        D = descriptor_distances(desc, desc).astype(float)
        np.fill_diagonal(D, np.inf)
        nearest = np.partition(D, 1, axis=1)
        found += int(
            np.sum((nearest[:, 0] < max_distance) & (nearest[:, 0] < ratio * nearest[:, 1]))
        )
        matches += len(desc)
        frames += 1
    return LookalikeSample(frames, matches, found)


def pooled(samples: Sequence[LookalikeSample]) -> LookalikeSample:
    """Several vehicles' samples as one."""
    return LookalikeSample(
        sum(s.frames for s in samples),
        sum(s.matches for s in samples),
        sum(s.with_lookalike for s in samples),
    )
