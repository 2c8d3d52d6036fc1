"""Relocalisation: a vehicle whose pose the map contradicts is found again in the map by
appearance (extension beyond the paper; place recognition, issue 20).

A filter can hold a wrong pose in two ways:
1. it knows: it lost the map (`events.DivergenceMonitor`: most of its recent frames
   matched none of the landmarks predicted in view);
2. it does not: the pose jumped -- an IMU glitch (a bump, a saturated accelerometer), a
   wheel slip -- while its covariance stayed small. The landmarks it sees next fall outside
   their windows, it tracks the few that still fit and maps anew where it believes it is:
   its NIS stays fine, and the trajectory is off by metres from then on (an accelerometer
   4 m/s^2 off for 1 s on the Monte Carlo's loop UAV: 12 m to the end, with a position
   sigma of 0.5 m). Its loops back over old ground are missed too: the windows are where
   it believes. Only the images can tell, by appearance rather than by predicted pixel.

The check (`PlaceRecognition.check`): the frame's stereo matches are paired by descriptor
with the landmarks mapped near the vehicle -- in the state, or out of it (evicted, or a
prior map's; a point mapped twice pairs with its older mapping) -- and its camera located
by PnP inside RANSAC (`localise.localise`, as for an unknown initial pose). Near: within the
95th percentile of the frame's point ranges plus three position sigmas of the filter's
position. Only the map the vehicle has seen, as it was when it last tracked it, takes part:
the landmarks it has observed, first seen by `VehicleRun.tracked_ns` (the last frame that
updated at least `TRACKED_FRACTION` of the landmarks predicted in view). What it mapped
since may have moved with a pose gone wrong, and would agree with it whatever went wrong;
and another vehicle's landmarks it never observed may lie where that vehicle's own error
put them (with uav1 of `uav2_paper` glitched, uav2 checked against uav1's map was declared
lost, relocalised into uav1's error and ended 5.6 m off instead of 1.1 m). A frame is checked
every `interval_ns` (for loops the windows missed), at every frame that did not track the
map (after a jump: the old landmarks still in view, unmatched), and while a disagreement
waits for confirmation. The pose found disagrees with the filter's pose (covariance
P_pose) when

    d^T (P_pose + C_pnp)^-1 d > gate_chi2      (d: position and attitude, 6 dof)

C_pnp is the PnP pose's covariance: from its inliers as if their errors were independent
(Gauss-Newton: (sum_i H_i^T R_i^-1 H_i)^-1, R_i the pixel noise plus the landmark's own
covariance seen in the image), plus on the position the inliers' mean covariance: a map's
errors are mostly common to the landmarks seen together (mapped from the same poses) and
do not average out over them. Without that term the loop UAV of the Monte Carlo, with no
fault at all, was declared lost twice in 60 s (0.5 and 1.2 m off, chi-square 52 and 151).
The landmarks' correlation with the vehicle, left out, would only shrink the sum: the test
errs towards agreeing. A disagreement counts once the same offset from the filter's pose
is found in `localise_confirm_frames` consecutive frames (`localise.PoseConfirmation`): one
PnP fit to look-alikes does not repeat. A check that agrees confirms the vehicle's pose
(`VehicleRun.verified_ns`).

A vehicle too uncertain for its windows (position standard deviation above
`uncertain_sigma_ratio` times the median depth of its frame, `linearisation.too_uncertain`:
after a long blackout) is checked at every frame, and the inliers of a pose its covariance
allows update it at once (`Contradiction.lost` false, with the pose's weight against the
filter's; `UnknownPoseLocaliser.relocalise`, a `recognition` event), in place of the
windows' associations: windows that wide can take look-alikes (the loop UAV after a 45 s
blackout: at 50.2 s the iterated update had it 7 m from the truth at a 27 m sigma, at
50.5 s its windows had taken wrong landmarks and put it 135 m off at 8 m; the check had
found its pose at 50.0 s).

A vehicle lost either way (`Slam._lose`) forgets its pose: its block of the state is made
independent of the rest, and its position, velocity and attitude get the standard
deviations of a lost vehicle (`JointState.forget`, `lost_variances`; biases and turn rates
keep their marginals). What it alone mapped since its pose was last confirmed is forgotten
too (`forget_mapped`). It is then localised again as a vehicle whose initial pose is
unknown (`unknown_pose.py`): at once at the pose the check found, on the check's inliers
still in the map, when there are enough; else among every landmark mapped, evicted ones
included, the pose found confirmed over `localise_confirm_frames` frames. The evicted
inliers come back as for a re-activation. Both are logged (`lost`, with why, and
`relocalisation` events; the timeline's `lost`). A vehicle lost more than
`max_per_vehicle` times diverges instead: a filter lost again and again is wrong (its noise
settings, its calibration), not unlucky.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cvslam_cli.estimation.events import MIN_VISIBLE_FOR_LOST
from cvslam_cli.estimation.frame import FrameMatches
from cvslam_cli.estimation.linearisation import too_uncertain
from cvslam_cli.estimation.localise import Localisation, PoseConfirmation, localise
from cvslam_cli.estimation.mapping import LandmarkBook
from cvslam_cli.estimation.motion.models import MotionModel
from cvslam_cli.estimation.reactivation import MAX_REACTIVATION_STD_M
from cvslam_cli.estimation.settings import RelocalisationSettings, SlamSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.vehicle import VehiclePose, VehicleRun
from cvslam_cli.records.arrays import F64, I64

RANGE_PERCENTILE = 95.0
"""The landmarks near a vehicle: within this percentile of its frame's point ranges ..."""
RANGE_SIGMAS = 3.0
"""... plus this many standard deviations of its position (largest axis)."""
TRACKED_FRACTION = 0.25
"""A frame tracked the map when it updated at least this fraction of the landmarks predicted
in view (of at most the update budget): 0.43-0.93 over the Monte Carlo's loop UAV, below
0.3 for 5 s after the accelerometer glitch of the module docstring (frames with fewer than
`events.MIN_VISIBLE_FOR_LOST` landmarks in view say nothing)."""


def lost_variances(model: MotionModel, s: RelocalisationSettings) -> tuple[I64, F64]:
    """(rows, variances): the rows of `model`'s state a lost vehicle forgets -- its pose, and
    its velocity (a pose gone wrong mostly went wrong through it: an accelerometer glitch)
    -- and their new variances. Its attitude too: the filter's roll and pitch absorb what
    the landmarks it can no longer explain say (1.6 degrees after the glitch of the module
    docstring), and kept, they pulled the relocalised vehicle metres off again."""
    sigma = {name: s.position_sigma_m for name in ("p_n", "p_e", "p_d")}
    sigma |= {name: s.velocity_sigma_m_s for name in ("v_x", "v_y", "v_z", "v_n", "v_e", "v_d")}
    sigma |= {name: s.attitude_sigma_rad for name in ("roll", "pitch", "yaw")}
    rows = [i for i, name in enumerate(model.state_names) if name in sigma]
    var = [sigma[model.state_names[i]] ** 2 for i in rows]
    return np.array(rows, dtype=np.int64), np.array(var)


def mapped_landmarks(state: JointState, book: LandmarkBook) -> tuple[I64, F64]:
    """Every landmark with a known position: (ids (N,), nav positions (N, 3)) -- the state's
    first, in slot order, at their estimates now; then the others (evicted, a prior map's) as
    archived, those known to `MAX_REACTIVATION_STD_M`."""
    out = np.flatnonzero(~book.in_state_mask())
    out = out[book.known(out, MAX_REACTIVATION_STD_M)]
    ids = np.concatenate([book.slot_ids, out]).astype(np.int64)
    m = np.concatenate([state.landmarks().reshape(-1, 3), book.p_nav_m[out]])
    return ids, m


def mapped_covariances(state: JointState, book: LandmarkBook, rows: I64, ids: I64) -> F64:
    """(k, 3, 3) nav covariances of the landmarks at `rows` of `mapped_landmarks`' `ids`: the
    state's marginals for the state's (their rows are their slots), archived for the others."""
    C = book.cov_nav_m2[ids[rows]]  # a copy (fancy indexing)
    in_state = rows < state.n_landmarks
    if in_state.any():
        C[in_state] = state.landmark_covariances(rows[in_state])
    return C


def pose_covariance(
    run: VehicleRun, found: Localisation, m_nav_m: F64, cov_m2: F64, R_pixel: F64
) -> F64:
    """(6, 6) covariance of the PnP pose (p, Psi) from its inliers' landmarks m (k, 3) with
    covariances (k, 3, 3): (sum_i H_i^T R_i^-1 H_i)^-1, R_i = R_pixel + H_m,i C_i H_m,i^T,
    plus the mean C_i on the position (module docstring)."""
    _, H_pose, H_m = run.vin.obs.predict(found.p_nav_m, found.euler_rad, m_nav_m)
    R = R_pixel + H_m @ cov_m2 @ np.swapaxes(H_m, 1, 2)
    info = np.einsum("kai,kab,kbj->ij", H_pose, np.linalg.inv(R), H_pose)
    cov = np.linalg.inv(info)
    cov[:3, :3] += cov_m2.mean(axis=0)
    return cov


def forget_mapped(
    state: JointState,
    book: LandmarkBook,
    run: VehicleRun,
    t_ns: int,
    variance_m2: float,
    interval_ns: int,
) -> int:
    """The landmarks that run's vehicle alone mapped since its pose was last known good are
    as wrong as its pose was: taken out of the state and forgotten (`LandmarkBook.forget`:
    never re-activated nor localised in; in the map with their position's variance
    `variance_m2` on each axis). Known good: the later of the last check that confirmed it
    (`VehicleRun.verified_ns`) and one check `interval_ns` before it last tracked the map
    (`tracked_ns`; a vehicle whose checks never find a pose would forget all it mapped).
    Returns how many."""
    start = run.vin.start_ns
    since = max(
        run.verified_ns if run.verified_ns is not None else start,
        (run.tracked_ns if run.tracked_ns is not None else start) - interval_ns,
    )
    n = book.count
    ids = np.flatnonzero(
        (book.observers[:n] == 1 << run.index) & (book.first_seen_ns[:n] > since)
        & ~book.forgotten[:n]
    )  # fmt: skip
    if not len(ids):
        return 0
    slot_of = np.full(n, -1, dtype=np.int64)
    slot_of[book.slot_ids] = np.arange(len(book.slot_ids))
    slots = slot_of[ids][slot_of[ids] >= 0]
    if len(slots):
        book.evict(
            slots, state.landmarks(slots), state.landmark_covariances(slots), t_ns,
            state.landmark_gauge(slots),
        )  # fmt: skip
        book.keep_slots(state.remove_landmarks(slots))
    book.forget(ids, variance_m2 * np.eye(3))
    return len(ids)


@dataclass(frozen=True, eq=False)
class Contradiction:
    """A check's finding that the map by appearance contradicts a vehicle's pose (`lost`) or
    locates a vehicle too uncertain for its windows (not `lost`): `why` (the lost event's
    text), the pose it found (`found`) and its inliers' book ids `ids` (k,); not lost, the
    `weight` (6, 6) of the pose found against the filter's, P (P + C)^-1 with P the
    filter's pose covariance and C the pose found's (position, Euler angles)."""

    why: str
    found: Localisation
    ids: I64
    lost: bool = True
    weight: F64 | None = None

    def without_forgotten(self, book: LandmarkBook) -> Contradiction:
        """The same, less the inliers `book` has forgotten since (`forget_mapped`)."""
        keep = ~book.forgotten[self.ids]
        f = self.found
        found = replace(f, landmark_rows=f.landmark_rows[keep], match_rows=f.match_rows[keep])
        return Contradiction(self.why, found, self.ids[keep], self.lost, self.weight)


class PlaceRecognition:
    """The check of the module docstring on `state` and `book`, with the filter's pixel
    noise `R_pixel_hat` (4, 4)."""

    def __init__(
        self, state: JointState, book: LandmarkBook, settings: SlamSettings, R_pixel_hat: F64
    ) -> None:
        self.state = state
        self.book = book
        self.settings = settings
        self.R_pixel_hat = R_pixel_hat
        self.confirmation = PoseConfirmation(settings.localise_confirm_frames)
        self._next_ns: dict[str, int] = {}
        self._untracked: set[str] = set()

    @property
    def enabled(self) -> bool:
        return self.settings.relocalisation.enabled

    def tracked(self, run: VehicleRun, t_ns: int, visible: int, updated: int, budget: int) -> None:
        """Note how run's frame at t_ns tracked the map (module docstring): `updated` of the
        `visible` landmarks predicted in view, at most `budget` a frame."""
        if visible < MIN_VISIBLE_FOR_LOST:
            return
        if updated >= TRACKED_FRACTION * min(visible, budget):
            run.tracked_ns = t_ns
            self._untracked.discard(run.vin.name)
        else:
            self._untracked.add(run.vin.name)

    def check(self, run: VehicleRun, frame: FrameMatches) -> Contradiction | None:
        """The map's pose of run's vehicle, if this frame confirms that it disagrees with
        the filter's, or agrees with it while the vehicle is too uncertain for its windows
        (`lost` false; module docstring); None otherwise, or when the frame is not due for a
        check."""
        name = run.vin.name
        if not self.enabled:
            return None
        pose = VehiclePose.of(self.state, run.vin)
        s = self.settings.relocalisation
        uncertain = too_uncertain(pose.cov[:3, :3], frame.p_cam_m, s.uncertain_sigma_ratio)
        due = (
            uncertain
            or name in self._untracked
            or self.confirmation.waiting(name)
            or frame.stamp_ns >= self._next_ns.get(name, frame.stamp_ns)
        )
        if not due:
            return None
        self._next_ns[name] = frame.stamp_ns + s.interval_ns
        located = self._locate(run, frame, pose)
        if located is None:
            self.confirmation.drop(name)
            return None
        found, ids, d, chi2, tol_m, weight = located
        if chi2 <= s.gate_chi2:
            self.confirmation.drop(name)
            if uncertain:  # found by appearance, as an unknown pose in the shared map is
                return Contradiction("", found, ids, lost=False, weight=weight)  # (one frame)
            run.verified_ns = frame.stamp_ns
            return None
        if not self.confirmation.confirmed(name, d[:3], float(d[5]), tol_m):
            return None
        self.confirmation.drop(name)
        why = (
            f"the map by appearance puts it {np.linalg.norm(d[:3]):.1f} m and "
            f"{np.degrees(np.linalg.norm(d[3:])):.1f} deg from the filter's pose (chi-square "
            f"{chi2:.0f}, 6 dof; PnP on {len(found.match_rows)} of {found.candidates} "
            f"descriptor pairs, the same in {self.confirmation.frames} frames)"
        )
        return Contradiction(why, found, ids)

    def _locate(
        self, run: VehicleRun, frame: FrameMatches, pose: VehiclePose
    ) -> tuple[Localisation, I64, F64, float, float, F64] | None:
        """The frame located among the landmarks near the vehicle: (the localisation, its
        inliers' book ids, the offset d (6,) of its pose from the filter's, d's chi-square,
        the confirmation tolerance in metres, the pose's weight against the filter's,
        `Contradiction.weight`); None when PnP finds no pose."""
        s = self.settings
        ids, m = mapped_landmarks(self.state, self.book)
        cov_p = pose.cov
        ranges = np.linalg.norm(frame.p_cam_m, axis=1)
        if not len(ranges) or len(ids) < s.localise_min_inliers:
            return None
        radius = float(np.percentile(ranges, RANGE_PERCENTILE)) + RANGE_SIGMAS * float(
            np.sqrt(np.linalg.eigvalsh(cov_p[:3, :3])[-1])
        )
        # the map the vehicle has seen, as it was when it last tracked it (module docstring)
        since = run.tracked_ns if run.tracked_ns is not None else run.vin.start_ns
        book = self.book
        seen = (book.observers[ids] >> run.index) & 1 == 1
        older = seen & (book.first_seen_ns[ids] <= since)
        near = np.flatnonzero(older & (np.linalg.norm(m - pose.p_nav_m, axis=1) <= radius))
        if len(near) < s.localise_min_inliers:
            return None
        found = localise(
            run.vin.obs, frame.z, frame.desc, m[near], self.book.desc[ids[near]],
            ratio=s.descriptor_ratio, max_descriptor_distance=s.max_descriptor_distance,
            reprojection_px=s.localise_reprojection_px, min_inliers=s.localise_min_inliers,
            seed=len(run.stamps_ns), age=ids[near],
        )  # fmt: skip
        if found is None:
            return None
        rows = near[found.landmark_rows]
        C = mapped_covariances(self.state, self.book, rows, ids)
        C_pnp = pose_covariance(run, found, m[rows], C, self.R_pixel_hat)
        e0 = pose.euler_rad
        d = np.concatenate(
            [found.p_nav_m - pose.p_nav_m, (found.euler_rad - e0 + np.pi) % (2 * np.pi) - np.pi]
        )
        chi2 = float(d @ np.linalg.solve(cov_p + C_pnp, d))
        weight = np.linalg.solve(cov_p + C_pnp, cov_p).T  # P (P + C)^-1, both symmetric
        ranges_in = np.linalg.norm(m[rows] - found.p_nav_m, axis=1)
        return found, ids[rows], d, chi2, self.confirmation.tolerance_m(ranges_in), weight
