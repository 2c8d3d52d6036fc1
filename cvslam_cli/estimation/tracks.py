"""Feature tracks: the stereo points a vehicle follows from frame to frame without mapping
them, for the sliding-window update (`window_update.py`; the MSCKF of Mourikis &
Roumeliotis 2007, OpenVINS's "MSCKF features").

Each frame's free matches (neither a landmark's observation nor a new landmark) continue a
track when they match its last point (predicted into the frame at the vehicle's pose, gated,
descriptor test: `association.associate`, as new landmarks are confirmed) or start one.
Every observation names the window clone of the pose it was taken from (`JointState`
anchors, pinned while in the window). A track is used once, when it ends: lost, or its first
clone about to leave the window; so no measurement counts twice and none is also a
landmark's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.association import LandmarkPrediction, associate, in_view_rows
from cvslam_cli.estimation.frame import FrameMatches
from cvslam_cli.estimation.vehicle import VehicleInput, VehiclePose
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import DESCRIPTOR_SIZE


@dataclass(frozen=True, eq=False)
class TrackObservations:
    """Observations of T ended tracks, flattened: track (K,) in 0..T-1, clone (K,) the key
    of the window clone each was taken from, z (K, 4) the stereo pixels; m (T, 3) each
    track's last point (nav, from its last stereo pair: a starting guess)."""

    track: I64
    clone: I64
    z: F64
    m: F64

    @property
    def n_tracks(self) -> int:
        return len(self.m)


@dataclass(eq=False)
class TrackBook:
    """One vehicle's live tracks: for each, its descriptor (latest), its last point m (3,)
    with covariance (3, 3) in nav for the next match, and its observations as (clone key,
    z (4,)) pairs in time order."""

    desc: NDArray[np.uint8] = field(
        default_factory=lambda: np.zeros((0, DESCRIPTOR_SIZE), dtype=np.uint8)
    )
    m: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    cov: F64 = field(default_factory=lambda: np.zeros((0, 3, 3)))
    obs: list[list[tuple[int, F64]]] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.obs)

    def match(
        self,
        vin: VehicleInput,
        pose: VehiclePose,
        frame: FrameMatches,
        rows: I64,
        R_pixel: F64,
        gate_chi2: float,
        ratio: float,
        max_distance: float,
    ) -> tuple[I64, I64]:
        """(track indices, frame rows among `rows`) of the tracks this frame continues."""
        none = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        if not len(self) or not len(rows):
            return none
        ok = in_view_rows(vin, pose.p_nav_m, pose.euler_rad, self.m)
        if not len(ok):
            return none
        z, _, H_m = vin.obs.predict(pose.p_nav_m, pose.euler_rad, self.m[ok])
        S = H_m @ self.cov[ok] @ np.swapaxes(H_m, 1, 2) + R_pixel
        pred = LandmarkPrediction(ok, z, H_m, H_m, S)
        a = associate(
            pred, self.desc[ok], frame.z[rows], frame.desc[rows], gate_chi2, ratio, max_distance
        )
        return ok[a.pred_index], rows[a.match_index]

    def extend(
        self, tracks: I64, rows: I64, clone_key: int, frame: FrameMatches, m: F64, cov: F64
    ) -> None:
        """Add frame rows `rows` (observed from clone `clone_key`; their nav points m (k, 3),
        cov (k, 3, 3)) to `tracks`."""
        for t, r in zip(tracks.tolist(), rows.tolist(), strict=True):
            self.obs[t].append((clone_key, frame.z[r]))
        self.desc[tracks] = frame.desc[rows]
        self.m[tracks] = m
        self.cov[tracks] = cov

    def start(self, rows: I64, clone_key: int, frame: FrameMatches, m: F64, cov: F64) -> None:
        """New tracks from frame rows `rows`."""
        self.desc = np.concatenate([self.desc, frame.desc[rows]])
        self.m = np.concatenate([self.m, m])
        self.cov = np.concatenate([self.cov, cov])
        self.obs.extend([[(clone_key, frame.z[r])] for r in rows.tolist()])

    def first_clones(self) -> I64:
        """(T,) the clone key of each track's first observation."""
        return np.array([o[0][0] for o in self.obs], dtype=np.int64)

    def lengths(self) -> I64:
        return np.array([len(o) for o in self.obs], dtype=np.int64)

    def take(self, which: NDArray[np.bool_], min_length: int = 2) -> TrackObservations:
        """Remove the tracks `which` (T,) and return the observations of those with at
        least `min_length` observations (the rest are dropped unused)."""
        taken = [o for o, w in zip(self.obs, which, strict=True) if w]
        used = np.array([len(o) >= min_length for o in taken], dtype=bool)
        m_used = self.m[which][used] if len(taken) else np.zeros((0, 3))
        keep = ~which
        self.desc, self.m, self.cov = self.desc[keep], self.m[keep], self.cov[keep]
        self.obs = [o for o, w in zip(self.obs, which, strict=True) if not w]
        kept = [o for o, u in zip(taken, used, strict=True) if u]
        track = np.repeat(np.arange(len(kept)), [len(o) for o in kept]).astype(np.int64)
        clone = np.array([c for o in kept for c, _ in o], dtype=np.int64)
        z = np.array([zz for o in kept for _, zz in o], dtype=float).reshape(-1, 4)
        return TrackObservations(track, clone, z, m_used)
