"""The share of a fitted arc that the observations support (common/geometry/arc_support.py)."""
import numpy as np

from common.geometry.arc_support import arc_seen, best_seen
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.refine import ArcObservation, project_centreline
from common.geometry.transforms import make_T, rotvec_to_R

RIG = StereoRig.default()
NEEDLE = NeedleModel()
T = RIG.left.T_ecm_cam @ make_T(rotvec_to_R([0.4, 0.2, 0.1]), [0.005, 0.002, 0.12])   # in front of the endoscope


def observation(camera, keep=slice(None), keypoints=False):
    c = project_centreline(RIG[camera], NEEDLE, T)[keep]
    uv = RIG[camera].project((RIG[camera].T_cam_ecm @ T @ np.c_[NEEDLE.keypoints(), np.ones(5)].T).T[:, :3])
    return ArcObservation(uv if keypoints else None, np.ones(5) if keypoints else None, None if keypoints else c)


def test_a_whole_arc_is_seen_a_half_is_half_and_a_wrong_pose_is_not_supported():
    whole = {c: observation(c) for c in ("left", "right")}
    assert all(s > 0.97 for s in arc_seen(RIG, NEEDLE, T, whole, 3.0).values())
    n = len(project_centreline(RIG["left"], NEEDLE, T))
    half = {"left": observation("left", slice(0, n // 2)), "right": observation("right", slice(0, n // 4))}
    shares = arc_seen(RIG, NEEDLE, T, half, 3.0)
    assert abs(shares["left"] - 0.5) < 0.06 and abs(shares["right"] - 0.25) < 0.06
    assert best_seen(shares) == shares["left"] and best_seen({}) is None
    moved = T @ make_T(np.eye(3), [0.0, 0.0, 0.003])                # a pose 3 mm off what was seen
    assert arc_seen(RIG, NEEDLE, moved, whole, 3.0)["left"] < 0.3


def test_keypoints_alone_support_only_the_arc_near_them_and_low_weights_do_not_count():
    kp = arc_seen(RIG, NEEDLE, T, {"left": observation("left", keypoints=True)}, 3.0)["left"]
    assert 0.1 <= kp <= 0.4                       # five points: the samples near each
    o = observation("left")
    weak = ArcObservation(centreline=o.centreline, centreline_w=np.full(len(o.centreline), 0.01))
    assert arc_seen(RIG, NEEDLE, T, {"left": weak}, 3.0, min_weight=0.05)["left"] == 0.0


def test_a_partial_view_is_flagged_and_its_covariance_widened_a_whole_one_is_left_alone():
    from common.geometry.arc_support import partial_view
    C = np.diag([1e-4] * 3 + [1e-8] * 3)
    assert partial_view(C, 0.9, 0.6, 4.0) == (False, C)
    flag, wide = partial_view(C, 0.4, 0.6, 4.0)
    assert flag and np.allclose(wide, 4.0 * C)
    assert partial_view(None, 0.4, 0.6, 4.0) == (True, None) and partial_view(C, None, 0.6, 4.0)[0] is False


def test_the_ends_seen_are_those_some_camera_supports():
    from common.geometry.arc_support import arc_support, ends_seen, shares
    n = len(project_centreline(RIG["left"], NEEDLE, T))
    whole = {c: observation(c) for c in ("left", "right")}
    assert ends_seen(arc_support(RIG, NEEDLE, T, whole, 3.0)) == (True, True)
    head = {"left": observation("left", slice(0, n // 2)), "right": observation("right", slice(0, n // 3))}
    support = arc_support(RIG, NEEDLE, T, head, 3.0)
    assert ends_seen(support) == (True, False)                     # E's end under the jaws
    assert shares(support) == arc_seen(RIG, NEEDLE, T, head, 3.0)
    tail = {"left": observation("left", slice(n // 2, None))}
    assert ends_seen(arc_support(RIG, NEEDLE, T, {**head, **tail}, 3.0)) == (True, True)   # one camera each
    assert ends_seen({}) == (False, False)
