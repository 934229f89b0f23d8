"""A live graph's stereo frames: a camera whose detector lags at start-up and a detector that
hears frames before the calibration beacon lose no frame, and per-camera detectors that cannot
keep up pick the same frames (common/runtime/pairing.py, nodes/detector.py)."""
from dataclasses import dataclass

import numpy as np
import pytest

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.oracle import random_needle_pose
from common.runtime.messages import Calibration, CameraImage, GroundTruth
from common.runtime.node import Node
from common.runtime.pairing import StereoPairer
from common.runtime.params import merge_schemas
from nodes.detector import DetectorNode

RIG = StereoRig.default()
MODEL = NeedleModel()
CALIB = Calibration(0, np.array([1920, 1080]), RIG.to_dict(), MODEL.to_dict())


def test_a_camera_lagging_at_start_up_loses_no_frame():
    p = StereoPairer()
    assert all(p.push("left", s, f"L{s}") is None for s in range(40))   # right is 40 frames late
    pairs = [p.push("right", s, f"R{s}") for s in range(40)]
    assert pairs == [(f"L{s}", f"R{s}") for s in range(40)]
    assert p.dropped == 0 and len(p) == 0


def test_halves_whose_partner_was_skipped_are_discarded():
    p = StereoPairer()
    for s in (0, 1, 2, 3):
        p.push("left", s, s)
    assert p.push("right", 2, "r2") == (2, "r2")            # right skipped 0 and 1
    assert p.dropped == 2 and len(p) == 1                   # left 3 waits for right 3
    assert p.push("right", 1, "late") is None and p.dropped == 3   # older than a paired frame
    p.push("right", 5, "r5")                                # right skipped 3 and 4: left 3 can never pair
    assert p.dropped == 4 and len(p) == 1
    assert p.push("left", 4, 4) is None and p.dropped == 5  # right is past 4 already
    assert p.push("left", 5, 5) == (5, "r5")
    # a camera that stops altogether: the other one's halves are bounded by depth
    p = StereoPairer(depth=8)
    for s in range(100):
        p.push("left", s, s)
    assert len(p) == 8 and p.dropped == 92


def test_pairing_order_within_a_frame_does_not_matter():
    p = StereoPairer()
    out = []
    for s in range(10):
        first, second = ("left", "right") if s % 2 else ("right", "left")
        assert p.push(first, s, (first, s)) is None
        out.append(p.push(second, s, (second, s)))
    assert out == [(("left", s), ("right", s)) for s in range(10)] and p.dropped == 0


def _truth(seq, T):
    return GroundTruth(seq, seq * 1000, T_world_ecm=np.eye(4), T_world_needle=T)


def _image(cam, seq):
    return CameraImage(cam, seq, seq * 1000, 2, 2, "bgr8", bytes(12))


def test_detector_frames_before_the_calibration_wait_for_it():
    T = random_needle_pose(np.random.default_rng(0), RIG, MODEL)
    # every input keeping every message (an evaluation): every frame is detected once calibrated
    Lossless = type("Lossless", (DetectorNode,), {"KEEP_ALL": tuple(DetectorNode.INPUTS)})
    det = Lossless.offline({"backend": "oracle"})
    for s in range(5):
        det.on_truth(_truth(s, T))
        det.on_left(_image("left", s))
        det.on_right(_image("right", s))
    assert det.published == []
    det.on_calib(CALIB)
    assert sorted((o, k.seq) for o, k in det.published) == sorted(
        (c, s) for c in ("left", "right") for s in range(5))
    assert all(k.found for _, k in det.published) and det.counters["no_calibration"] == 0

    # live (newest-only images): the newest image of each camera waits, the older ones are superseded
    det = DetectorNode.offline({"backend": "oracle"})
    for s in range(5):
        det.on_truth(_truth(s, T))
        det.on_left(_image("left", s))
    det.on_right(_image("right", 3))
    det.on_calib(CALIB)
    assert sorted((o, k.seq) for o, k in det.published) == [("left", 4), ("right", 3)]
    assert det.counters["superseded"] == 4 and det.counters["no_calibration"] == 0

    # ground truth alone (no image wired): every frame waits for the calibration
    det = DetectorNode.offline({"backend": "oracle"}, wired=["truth", "calib"])
    for s in range(3):
        det.on_truth(_truth(s, T))
    det.on_calib(CALIB)
    assert sorted((o, k.seq) for o, k in det.published) == sorted(
        (c, s) for c in ("left", "right") for s in range(3))


def test_detector_without_a_calibration_gives_up_after_max_wait_frames():
    det = DetectorNode.offline({"backend": "oracle", "max_wait": 3}, wired=["truth", "calib"])
    T = random_needle_pose(np.random.default_rng(1), RIG, MODEL)
    for s in range(6):
        det.on_truth(_truth(s, T))
    assert det.published == [] and det.counters["no_calibration"] == 2 * 3   # seqs 0..2 given up
    det.on_calib(CALIB)
    assert sorted({k.seq for _, k in det.published}) == [3, 4, 5]
    assert issubclass(DetectorNode, Node)


class _TimedDetector(DetectorNode):
    """A detector whose detections take ``busy_s`` of a simulated clock."""

    @dataclass
    class Timing:
        busy_s: float = 0.0

    @classmethod
    def param_schema(cls, raw):
        return merge_schemas("TimedParams", super().param_schema(raw), cls.Timing)

    def setup(self):
        super().setup()
        self.now = 0.0
        self.clock = lambda: self.now

    def _detect_image(self, msg):
        self.now += self.p.busy_s
        super()._detect_image(msg)


def _camera_run(busy_s, camera, frames=60, period_s=1 / 30):
    det = _TimedDetector.offline({"backend": "oracle", "busy_s": busy_s}, wired=[camera, "truth", "calib"])
    det.on_calib(CALIB)
    T = random_needle_pose(np.random.default_rng(2), RIG, MODEL)
    for s in range(frames):
        det.on_truth(_truth(s, T))
        getattr(det, f"on_{camera}")(CameraImage(camera, s, int(s * period_s * 1e9), 2, 2, "bgr8", bytes(12)))
    return det, [k.seq for _, k in det.published]


def test_stride_follows_sustained_detection_times_not_spikes():
    from common.runtime.frame_stride import FrameStride
    fs = FrameStride(1, adaptive=True)
    for s in range(90):                    # 30 Hz; a cold detection of 100 ms every 6th frame
        fs.frame(s, int(s / 30 * 1e9))
        fs.detected(0.100 if s % 6 == 3 else 0.020)
        assert fs.stride == 1
    for s in range(90, 120):               # slower for good: 45 ms = 1.35 frame intervals
        fs.frame(s, int(s / 30 * 1e9))
        fs.detected(0.045)
    assert fs.stride == 2
    for s in range(120, 150):              # fast again: 20 ms < 0.75 interval
        fs.frame(s, int(s / 30 * 1e9))
        fs.detected(0.020)
    assert fs.stride == 1


def test_per_camera_detectors_pick_the_same_frames_whatever_their_speed():
    left, l_seqs = _camera_run(0.045, "left")           # 1.35 frame intervals per detection
    right, r_seqs = _camera_run(0.050, "right")
    assert left.stride == right.stride == 2
    late = [s for s in l_seqs if s >= 20]
    assert late and late == [s for s in r_seqs if s >= 20] and all(s % 2 == 0 for s in late)
    assert left.counters["stride_skipped"] > 20
    # a faster detector strides less, and its frames include the slower one's: all of those pair
    fast, f_seqs = _camera_run(0.020, "right")
    slow, s_seqs = _camera_run(0.110, "left")            # 3.3 intervals: stride 4
    assert fast.stride == 1 and slow.stride == 4
    assert set(s for s in s_seqs if s >= 20) <= set(f_seqs)
    # both cameras in one process, or a fixed stride: no adaptation
    both = DetectorNode.offline({"backend": "oracle"})
    assert both.stride == 1 and not both.auto_stride
    assert DetectorNode.offline({"backend": "oracle", "stride": 2}, wired=["left", "calib"]).stride == 2
    with pytest.raises(ValueError, match="stride"):
        DetectorNode.offline({"backend": "oracle", "stride": 3}, wired=["left", "calib"])
