"""Look-alikes within a vehicle's own frames (`lookalikes.py`): what
`fuse.association.other_vehicle_lookalikes_per_mpx` auto reads."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cvslam_cli.estimation.lookalikes import pooled, sample_lookalikes
from tests.features.synthetic_frames import frames_of


def test_a_twin_in_the_same_frame_is_a_lookalike_and_distinct_descriptors_are_none():
    """Unique random descriptors (as the landmark-mode simulator's): no look-alike. Ten pairs
    per frame made twins (one descriptor copied onto another, a few levels of noise): both
    of each pair have one, in every frame sampled; a third copy makes the ratio test fail
    (two equally near), so the three are not counted."""
    fs, _ = frames_of(0.0, ahead=True, frames=12)
    distinct = sample_lookalikes(fs, 0.7, 350.0, every=1)
    assert distinct.frames == 12 and distinct.matches > 1000
    assert distinct.with_lookalike == 0 and distinct.share == 0.0

    rng = np.random.default_rng(3)
    desc = fs.left_desc.copy()
    for f in range(12):
        rows = fs.match_left[fs.frame_matches(f)]
        noise = rng.integers(-3, 4, size=(10, 128))
        desc[rows[1:20:2]] = np.clip(desc[rows[0:20:2]].astype(int) + noise, 0, 255)
        desc[rows[21]] = desc[rows[20]]  # a triple: rows 20, 21 and 22
        desc[rows[22]] = desc[rows[20]]
    twins = replace(fs, left_desc=desc)
    every_fifth = sample_lookalikes(twins, 0.7, 350.0, every=5)  # frames 0, 5 and 10
    assert every_fifth.frames == 3 and every_fifth.with_lookalike == 3 * 20
    assert 0 < every_fifth.share < 0.1
    assert sample_lookalikes(twins, 0.7, 10.0, every=5).with_lookalike == 0  # beyond the distance
    both = pooled([distinct, every_fifth])
    assert (both.frames, both.matches, both.with_lookalike) == (
        15, distinct.matches + every_fifth.matches, 60
    )  # fmt: skip
