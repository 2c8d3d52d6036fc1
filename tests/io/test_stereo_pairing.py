"""Left/right images paired within the tolerance; the unpaired counted."""

from __future__ import annotations

import numpy as np

from cvslam_cli.config import load_config
from cvslam_cli.io.log_stats import VehicleStats
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.stereo_pairing import StereoPairer
from cvslam_cli.records.log import ImageRecord, PoseRecord, StereoFrame
from tests.synth import write_stereo_log


def _logset(path, overrides=()):
    return LogSet([McapLogSource(path)], load_config(overrides=overrides).logs)


def test_pairing_within_tolerance_and_unpaired_counts(tmp_path):
    synth = write_stereo_log(
        tmp_path / "a.mcap", n_frames=10, right_offset_ns=1_500_000, drop_right=(3, 7)
    )
    logs = _logset(synth.path)
    frames = [r for r in logs.records() if isinstance(r, StereoFrame)]
    assert len(frames) == 8
    assert all(f.pair_offset_ns == 1_500_000 for f in frames)
    st = logs.stats["uav1"]
    assert (st.stereo_pairs, st.unpaired_left, st.unpaired_right) == (8, 2, 0)
    # a tighter tolerance than the offset pairs nothing
    tight = _logset(synth.path, overrides=["logs.stereo_pair_tolerance_ms=1.0"])
    assert not [r for r in tight.records() if isinstance(r, StereoFrame)]
    assert tight.stats["uav1"].unpaired_left == 10
    assert tight.stats["uav1"].unpaired_right == 8


def _image(topic: str, stamp_ns: int) -> ImageRecord:
    return ImageRecord(stamp_ns, np.zeros((2, 2), np.uint8), "mono8", "", topic, "v")


def test_pairer_takes_the_oldest_partner_within_the_tolerance():
    stats = {"v": VehicleStats()}
    role_of = {("v", "/l"): "left_image", ("v", "/r"): "right_image"}
    pairer = StereoPairer(10, stats, role_of)
    gt = PoseRecord("v", 5, "nav", np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
    stream = [
        _image("/l", 0),  # its right partner never comes within 10 ns: unpaired
        gt,
        _image("/r", 30),
        _image("/r", 32),
        _image("/l", 35),  # pairs with the right image at 30 (the oldest within 10 ns)
        _image("/l", 50),  # the right image at 32 is too old by now: unpaired
        _image("/r", 55),
    ]
    out = [r for rec in stream for r in pairer.push(rec)]
    pairer.finish()
    assert out[0] is gt
    frames = [(f.left.stamp_ns, f.right.stamp_ns) for f in out[1:]]
    assert frames == [(35, 30), (50, 55)]
    vs = stats["v"]
    assert (vs.stereo_pairs, vs.unpaired_left, vs.unpaired_right) == (2, 1, 1)
    assert vs.max_pair_offset_ns == 5
    tail = StereoPairer(10, {"v": VehicleStats()}, role_of)
    assert not list(tail.push(_image("/r", 0)))
    tail.finish()  # the queued image is counted at the end
    assert tail.stats["v"].unpaired_right == 1
