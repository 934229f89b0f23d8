"""Whether a stereo frame's two detections and the track agree (common/geometry/stereo_agreement.py):
a camera locked on a distractor that the other camera and the track disagree with is dropped after
``frames`` frames in a row; a right lock is kept, and without a track nothing is dropped (issue 56:
a detector stuck on a red marker for a whole take)."""
import numpy as np
import pytest

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.oracle import random_needle_pose
from common.geometry.stereo_agreement import LockCheck, LockCheckConfig, epipolar_px, track_px
from common.geometry.transforms import transform_points

RIG = StereoRig.default()
NEEDLE = NeedleModel()
ONES = {"left": np.ones(5), "right": np.ones(5)}


def views(T, noise=0.3, seed=0):
    rng = np.random.default_rng(seed)
    P = transform_points(T, NEEDLE.keypoints())
    return {c.name: c.project_from_ecm(P) + rng.normal(0, noise, (5, 2)) for c in RIG.cameras}


def distractor(uv, shift=(-260.0, 140.0)):
    """A marker elsewhere in the image: a small blob of five points."""
    centre = uv.mean(axis=0) + shift
    return centre + np.array([[-6, 0], [-3, 3], [0, 4], [3, 3], [6, 0]], float)


def test_two_views_of_the_needle_agree_either_way_round_and_a_distractor_does_not():
    T = random_needle_pose(np.random.default_rng(1), RIG, NEEDLE)
    uv = views(T)
    assert epipolar_px(RIG, uv, ONES) < 2.0
    turned = {"left": uv["left"], "right": uv["right"][::-1]}          # the right camera read end for end
    assert epipolar_px(RIG, turned, ONES) < 2.0
    assert epipolar_px(RIG, {**uv, "right": distractor(uv["right"])}, ONES) > 50.0
    assert epipolar_px(RIG, {"left": uv["left"]}, ONES) is None          # one camera: nothing to compare
    low = {"left": np.array([1, 0.1, 0.1, 0.1, 0.1]), "right": np.ones(5)}
    assert epipolar_px(RIG, uv, low) is None                             # fewer than 2 usable pairs
    assert track_px(RIG, NEEDLE, T, "right", uv["right"][::-1], None) < 2.0
    assert track_px(RIG, NEEDLE, T, "right", distractor(uv["right"]), None) > 100.0


def test_a_lock_on_a_distractor_is_dropped_after_the_frames_in_a_row_and_a_right_lock_kept():
    rng = np.random.default_rng(2)
    check = LockCheck(LockCheckConfig(frames=2))
    T = random_needle_pose(rng, RIG, NEEDLE)
    uv = views(T)
    stuck = {**uv, "right": distractor(uv["right"])}
    v = check.check(RIG, NEEDLE, stuck, ONES, T)
    assert v.wrong == ("right",) and v.drop == () and v.track_px["left"] < 2.0
    v = check.check(RIG, NEEDLE, stuck, ONES, T)
    assert v.drop == ("right",)                                          # the second frame in a row
    assert check.check(RIG, NEEDLE, stuck, ONES, T).drop == ()           # counted afresh after a drop
    left_stuck = {**uv, "left": distractor(uv["left"], (300.0, -90.0))}
    assert check.check(RIG, NEEDLE, left_stuck, ONES, T).wrong == ("left",)
    # a right lock: both cameras on the needle, whatever the track says (a stale one)
    check.reset()
    stale = T.copy()
    stale[:3, 3] += [0.02, 0.01, 0.0]
    for _ in range(3):
        assert check.check(RIG, NEEDLE, uv, ONES, stale).drop == ()
    # no track: two disagreeing cameras do not say which one is wrong
    for _ in range(3):
        v = check.check(RIG, NEEDLE, stuck, ONES, None)
        assert v.drop == () and v.wrong == () and v.epipolar_px > 50.0
    # both off the track (the track lost, the cameras disagreeing): nothing dropped
    for _ in range(3):
        assert check.check(RIG, NEEDLE, stuck, ONES, stale).drop == ()
    with pytest.raises(ValueError, match="frames >= 1"):
        LockCheckConfig(frames=0)
