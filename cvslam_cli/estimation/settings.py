"""The settings of the central filter's loop (`slam.py`), from the config's `fuse` section
(`stage.slam_settings`), and the bound on landmarks in the state that follows from them."""

from __future__ import annotations

from dataclasses import dataclass, field

from cvslam_cli.estimation.filters import FilterSettings
from cvslam_cli.estimation.gauge import ConstrainedSetting
from cvslam_cli.estimation.landmark_coordinates import CoordinatesSetting
from cvslam_cli.estimation.octave_noise import OctaveSetting
from cvslam_cli.estimation.update_budget import UpdatesSetting


@dataclass(frozen=True)
class WindowSettings:
    """window: clones kept per vehicle (0: no window, no tracks); max_tracks: live tracks
    per vehicle at most (new ones spread over the image); gate_chi2[d]: the
    chi-square gate of a track's d null-space rows; iterations: Gauss-Newton steps of the
    point fit; the association's gate, ratio and distance for continuing tracks."""

    window: int = 0
    max_tracks: int = 60
    gate_chi2: tuple[float, ...] = ()
    iterations: int = 2
    match_gate_chi2: float = 18.47
    descriptor_ratio: float = 0.8
    max_descriptor_distance: float = 350.0


@dataclass(frozen=True)
class RelocalisationSettings:
    """relocalisation.py: `enabled`; a vehicle's frame located in the map by appearance every
    `interval_ns`; `gate_chi2` (6 dof) the disagreement with the filter's pose that counts;
    a lost vehicle's forgotten position, velocity and attitude have standard deviations
    `position_sigma_m`, `velocity_sigma_m_s`, `attitude_sigma_rad` (each axis);
    `max_per_vehicle` losses before the next is a divergence."""

    enabled: bool = True
    interval_ns: int = 1_000_000_000
    gate_chi2: float = 38.26  # chi2 with 6 dof at 1 - 1e-6
    position_sigma_m: float = 20.0
    velocity_sigma_m_s: float = 5.0
    attitude_sigma_rad: float = 0.2
    max_per_vehicle: int = 5
    uncertain_sigma_ratio: float = 0.1  # found by appearance, not by its windows, above


@dataclass(frozen=True)
class SlamSettings:
    filter: FilterSettings = field(default_factory=FilterSettings)
    pixel_sigma_px: float = 0.5
    gate_chi2: float = 18.47  # chi2 with 4 dof at 0.999
    consistency_chi2: float = 18.47  # chi2 with 4 dof at 0.999
    descriptor_ratio: float = 0.8
    other_vehicle_descriptor_ratio: float = 0.7  # landmarks the vehicle has not seen yet
    # ... whose ratio test's second-best is over the whole frame (`association.associate`)
    other_vehicle_ratio_over_frame: bool = True
    # pixel noise of an observation of a landmark another vehicle has observed (0: as
    # pixel_sigma_px; never below it): `association.noise_scale`
    other_vehicle_pixel_sigma_px: float = 0.0
    # a landmark the vehicle has not observed yet is looked for only from within this factor
    # of the distance it was observed from (0: no limit): `LandmarkBook.ids_within_distance`
    other_vehicle_max_distance_ratio: float = 4.0
    # ... and inside a window small enough for a look-alike to be unlikely there: d2 + ln det
    # S_l below this (inf: no bound; `association.lookalike_gates`)
    other_vehicle_lookalike_bound: float = float("inf")
    max_descriptor_distance: float = 350.0
    # the bearing noise variance of a keypoint by its octave, relative (octave_noise.py)
    octave_bearing_variance: OctaveSetting = "auto"
    iterate_sigma_ratio: float = 0.05  # linearisation.too_uncertain (0: never iterate)
    iterate_bearing_sigma_rad: float = 0.0  # linearisation.bearings_too_uncertain (0: never)
    max_update_iterations: int = 5  # update.VisualUpdater.iterated_update
    max_landmarks: int = 150  # with one vehicle in the filter ...
    landmarks_per_added_vehicle: int = 100  # ... plus this many per other vehicle ...
    max_landmarks_total: int = 400  # ... up to this many in all
    # a vehicle's frame: at most this many landmarks updated, new ones while fewer were
    # (update_budget.resolve: auto by the motion models of the vehicles in the filter)
    max_updates_per_frame: UpdatesSetting = "auto"
    target_tracked: UpdatesSetting = "auto"
    max_new_per_frame: int = 15
    max_new_depth_sigma_ratio: float = 0.25
    new_landmark_priority: str = "previous_frame"  # or "current_frame" (new_landmarks.py)
    landmark_coordinates: CoordinatesSetting = "auto"  # landmark_coordinates.resolve
    anchor_span_ns: int = 0  # new landmarks share a vehicle's anchor this long
    reanchor_max_landmarks: int = 8  # reanchoring.py: lighter anchors hand theirs over
    loop_closure_gap_ns: int = 20_000_000_000
    loop_closure_min_landmarks: int = 3
    event_merge_ns: int = 5_000_000_000
    joint_initialisation: bool = True  # cooperation.Cooperation.joint_initialisation
    joint_init_window_ns: int = 200_000_000
    reactivation: bool = True  # evicted landmarks brought back (reactivation.py)
    observability_constrained: ConstrainedSetting = "auto"  # gauge.constrained
    reactivation_inflation: float = 16.0
    prior_map_inflation: float = 16.0  # a prior map's landmarks (prior_map.py)
    refined_prior_map_inflation: float = 1.0  # ... when cvslam refine made the map
    reactivation_min_absence_ns: int = 20_000_000_000
    reactivation_min_landmarks: int = 3
    max_reactivated_per_frame: int = 15
    nis_window: int = 20
    nis_per_dof_max: float = 10.0
    max_view_angle_rad: float = 1.3963  # 80 degrees
    others_tracking_ns: int = 0  # mapping.LandmarkBook.eviction_order
    localise_min_inliers: int = 12
    localise_reprojection_px: float = 2.0
    localise_prior_chi2: float = 16.27  # chi2 with 3 dof at 0.999
    localise_confirm_frames: int = 3  # in a prior map: frames that must agree (prior_map.py)
    window: WindowSettings = field(default_factory=WindowSettings)
    relocalisation: RelocalisationSettings = field(default_factory=RelocalisationSettings)

    @property
    def other_vehicle_noise_ratio(self) -> float:
        """The pixel noise variance of an observation of another vehicle's landmark over the
        filter's (>= 1; 1 when other_vehicle_pixel_sigma_px is 0 or below pixel_sigma_px)."""
        return max(1.0, (self.other_vehicle_pixel_sigma_px / self.pixel_sigma_px) ** 2)


def landmark_bound(s: SlamSettings, n_vehicles: int) -> int:
    """Landmarks the state holds at most with n vehicles: `max_landmarks` for the first
    vehicle, `landmarks_per_added_vehicle` for each other, up to `max_landmarks_total`. Each
    vehicle needs room for the landmarks it tracks; the older map, kept for loop closures
    and re-observations, is shared (BENCHMARKS.md, "Fuse: cooperative")."""
    grown = s.max_landmarks + (n_vehicles - 1) * s.landmarks_per_added_vehicle
    return min(grown, max(s.max_landmarks_total, s.max_landmarks))
