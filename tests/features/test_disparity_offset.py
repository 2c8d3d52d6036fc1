"""The rig's disparity offset from the frames' own motion (features/disparity_offset.py):
recovered where points lie at many depths, refused where an offset looks like a scale, and
corrected in the feature file by `cvslam extract` when asked."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.features.disparity_offset import (
    apply_disparity_offset,
    estimate_disparity_offset,
)
from cvslam_cli.features.stage import run
from cvslam_cli.io.features_file import load_features
from tests.features.synthetic_frames import CX, frames_of, rig, skewed_rig


@pytest.mark.parametrize("offset_px", [0.0, -1.2, 0.5])
def test_offset_recovered_ahead_of_a_car(offset_px):
    """Points at 3-120 m ahead: the offset is found within 0.05 px and within 4 of its own
    standard deviations (which must not be vacuous: under 0.05 px)."""
    fs, _ = frames_of(offset_px, ahead=True)
    est = estimate_disparity_offset(fs, rig())
    assert est is not None and est.determined
    assert est.pairs == fs.n_frames - 1 and est.points > 3000
    assert abs(est.offset_px - offset_px) < 0.05
    assert 0.0 < est.sigma_px < 0.05
    assert abs(est.offset_px - offset_px) < 4 * est.sigma_px + 0.01


def test_offset_not_determined_over_flat_ground():
    """From above flat ground every disparity is within a few percent of the others: an
    offset and a scale look alike, and the estimate says it is not determined."""
    fs, _ = frames_of(-1.0, ahead=False, frames=6)
    est = estimate_disparity_offset(fs, rig())
    assert est is not None
    assert not est.determined
    assert est.disparity_spread < 0.1


def test_unrectified_rig_and_too_few_frames_give_no_estimate():
    fs, _ = frames_of(0.0, ahead=True, frames=1)
    assert estimate_disparity_offset(fs, rig()) is None
    skew = skewed_rig()
    fs, _ = frames_of(0.0, ahead=True, frames=3)
    assert estimate_disparity_offset(fs, skew) is None


def test_applied_offset_restores_the_depths():
    """Triangulated again with the corrected rig, far points land where they are (their
    depth was 10-40 % off at 60-120 m with an offset of -1.2 px); a positive offset larger
    than a point's disparity drops its match, and the frames' offsets follow."""
    fs, P = frames_of(-1.2, ahead=True, frames=3, noise_px=0.0)
    out, per_frame = apply_disparity_offset(fs, -1.2, max_range_m=400.0, pixel_sigma_px=0.3)
    assert out.rig.K[1, 0, 2] == pytest.approx(CX + 1.2)
    assert np.array_equal(per_frame, np.diff(fs.match_offsets))
    first = out.frame_matches(0)
    truth = P[out.match_landmark_id[first]]
    err = np.linalg.norm(out.match_p_cam_m[first] - truth, axis=1) / truth[:, 2]
    assert err.max() < 1e-4
    plain, _ = apply_disparity_offset(fs, 0.0, max_range_m=400.0, pixel_sigma_px=0.3)
    far = truth[:, 2] > 60
    off = np.abs(plain.match_p_cam_m[first][far, 2] / truth[far, 2] - 1)
    assert far.sum() > 50 and off.min() > 0.1
    # z = f b / (d - offset) behind the camera where d < offset: those matches go
    out, per_frame = apply_disparity_offset(fs, 6.0, max_range_m=np.inf, pixel_sigma_px=0.3)
    small = fs.match_disparity_px < 6.0
    assert small.sum() > 0 and out.match_offsets[-1] == (~small).sum()
    assert np.array_equal(out.match_offsets, np.concatenate([[0], np.cumsum(per_frame)]))
    assert np.all(out.match_p_cam_m[:, 2] > 0)
    assert out.match_cov_cam_m2.shape == (int(out.match_offsets[-1]), 3, 3)


def test_extract_corrects_kitti_clip_b(shared_data, tmp_path):
    """Real data: KITTI clip b, whose stereo depth and ground truth "disagree in scale by
    4-5 %" (data README). `cvslam extract` with the correction finds an offset of about
    -1.2 px and writes it with the corrected rig (BENCHMARKS.md, "Tenth step": with it the
    clip's SE3 error falls from 0.87 to 0.21 m)."""
    from cvslam_cli.io.importers.kitti import import_kitti

    log = tmp_path / "b.mcap"
    import_kitti(shared_data / "kitti_clip_b", log, "car1")
    cfg = load_config(overrides=["extract.stereo.calibrate_disparity_offset=true"])
    run(cfg, [log], tmp_path / "run", workers=2)
    fs, meta = load_features(tmp_path / "run" / "features" / "car1.npz")
    rec = meta["disparity_offset"]
    print(f"\nclip b: offset {rec['offset_px']:.3f} +- {rec['sigma_px']:.3f} px")
    assert -1.5 < rec["offset_px"] < -1.0 and rec["applied_px"] == rec["offset_px"]
    assert rec["disparity_spread"] > 0.5
    assert fs.rig.K[1, 0, 2] - fs.rig.K[0, 0, 2] == pytest.approx(-rec["offset_px"], abs=1e-9)
