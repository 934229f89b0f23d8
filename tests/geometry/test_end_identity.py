"""Which end is the tip (common/geometry/end_identity.py) and how the pose nodes use a detector's
statement of it (common/pose/stereo.py): turned when sure of the other end, flagged when unsure."""
import dataclasses

import numpy as np
import pytest

from common.geometry.camera import StereoRig
from common.geometry.end_identity import (
    TIP_SURE,
    TRACK_CAP,
    end_for_end_delta,
    identity_covariance,
    logit,
    fitted_tip_probability,
    reads_as_keypoints,
    settle,
    sigmoid,
    state,
    stereo_end_identity,
    track_identity,
    turn_observation,
    with_reading,
)
from common.geometry.needle import NeedleModel
from common.geometry.oracle import random_needle_pose, true_keypoints
from common.geometry.refine import tip_for_tail
from common.geometry.transforms import R_to_rotvec, pose_error
from common.runtime.messages import Calibration, Keypoints
from nodes.epnp import EpnpNode

RIG = StereoRig.default()
MODEL = NeedleModel()
CALIB = Calibration(0, np.array([1920, 1080]), RIG.to_dict(), MODEL.to_dict())


def test_two_cameras_agreeing_are_surer_than_one_but_not_twice_as_sure():
    assert stereo_end_identity(None, None) is None
    assert stereo_end_identity(0.9, None) == pytest.approx(0.9)
    both = stereo_end_identity(0.9, 0.9)
    one_sure = 1 / (1 + (0.1 / 0.9) ** 2)        # as if the cameras were independent
    assert 0.9 < both < one_sure
    assert stereo_end_identity(0.9, 0.1) == pytest.approx(0.5)
    assert stereo_end_identity(0.2, 0.3) < 0.5


def test_a_turned_observation_is_the_observation_of_the_turned_pose():
    T = random_needle_pose(np.random.default_rng(3), RIG, MODEL)
    for cam in RIG.cameras:
        uv, _ = true_keypoints(cam, T, MODEL)
        uv_turned, _ = true_keypoints(cam, tip_for_tail(T, MODEL), MODEL)
        t_uv, t_sc, _, _ = turn_observation(uv, np.arange(5.0))
        assert np.allclose(t_uv, uv_turned, atol=1e-9) and list(t_sc) == [4, 3, 2, 1, 0]


def test_the_turn_delta_and_the_covariance_that_spans_it():
    T = random_needle_pose(np.random.default_rng(4), RIG, MODEL)
    d = end_for_end_delta(T, MODEL)
    T2 = tip_for_tail(T, MODEL)
    dt, dr = pose_error(T2, T)
    assert dt < 1e-12 and dr == pytest.approx(np.pi)
    # the rotation vector between them is the stated delta (up to the sign of a half turn)
    w = R_to_rotvec(T2[:3, :3] @ T[:3, :3].T)
    assert min(np.linalg.norm(w - d[:3]), np.linalg.norm(w + d[:3])) < 1e-6
    C = np.diag([1e-4] * 3 + [1e-8] * 3)
    for p in (0.5, 0.8, 0.95):
        Cw = identity_covariance(T, C, MODEL, p)
        # the turned truth's error is d: its NEES is 1 / (1 - p) at most, never thousands
        assert d @ np.linalg.solve(Cw, d) <= 1.0 / (1.0 - p) + 1e-6
        assert np.allclose(Cw, Cw.T) and np.linalg.eigvalsh(Cw).min() > 0
    assert np.allclose(identity_covariance(T, C, MODEL, 1.0), C)


def _pair(T, p, turned=False):
    """The stereo keypoints of pose T as a detector reports them: read end for end when
    ``turned``, with ``end_identity`` p on both cameras."""
    out = []
    for cam in RIG.cameras:
        uv, vis = true_keypoints(cam, T, MODEL)
        sc = np.ones(5)
        if turned:
            uv, sc, _, _ = turn_observation(uv, sc)
        out.append(Keypoints(cam.name, 7, 7000, True, uv, sc, 0.99, end_identity=p))
    return out


def _pose(params, pair):
    node = EpnpNode.offline({"method": "joint", **params}, wired=["left", "right", "calib"])
    node.on_calib(CALIB)
    for kp in pair:
        getattr(node, f"on_{kp.camera}")(kp)
    (_, pose), = node.published
    return node, pose


def test_a_pair_the_detector_says_is_turned_is_posed_the_right_way_round():
    T = random_needle_pose(np.random.default_rng(5), RIG, MODEL)
    node, pose = _pose({}, _pair(T, 0.01, turned=True))
    dt, dr = pose_error(pose.T_ecm_needle, T)
    assert dt < 1e-6 and dr < 1e-6 and not pose.ambiguous
    assert node.counters["end_identity.turned"] == 1


def test_an_undecided_pair_is_published_flagged_with_a_covariance_that_spans_both_answers():
    T = random_needle_pose(np.random.default_rng(6), RIG, MODEL)
    node, sure = _pose({}, _pair(T, 0.99, turned=True))
    dt, dr = pose_error(sure.T_ecm_needle, T)
    assert dr == pytest.approx(np.pi, abs=1e-6) and not sure.ambiguous   # a confident detector is believed
    node, unsure = _pose({}, _pair(T, 0.7, turned=True))
    assert unsure.ambiguous and node.counters["end_identity.unsure"] == 1
    assert np.allclose(unsure.T_ecm_needle, sure.T_ecm_needle, atol=1e-9)
    # the turned truth (the right answer here) is within the stated covariance
    d = end_for_end_delta(unsure.T_ecm_needle, MODEL)
    p = stereo_end_identity(0.7, 0.7)
    assert 0.7 < p < 0.95
    assert d @ np.linalg.solve(unsure.covariance, d) < 1.0 / (1.0 - p) + 1e-6
    assert d @ np.linalg.solve(sure.covariance, d) > 1e4        # a confident pose excludes the turn
    assert unsure.end_identity == pytest.approx(p) and sure.end_identity > 0.95


def test_a_pair_more_likely_turned_is_posed_turned_and_flagged_with_its_probability():
    T = random_needle_pose(np.random.default_rng(8), RIG, MODEL)
    node, pose = _pose({}, _pair(T, 0.3, turned=True))        # A as read is the tip with 0.3 only
    dt, dr = pose_error(pose.T_ecm_needle, T)
    assert dt < 1e-6 and dr < 1e-6 and node.counters["end_identity.turned"] == 1
    assert pose.ambiguous and pose.end_identity == pytest.approx(1.0 - stereo_end_identity(0.3, 0.3))


def test_without_a_statement_a_is_taken_as_said():
    T = random_needle_pose(np.random.default_rng(7), RIG, MODEL)
    pair = [dataclasses.replace(kp, end_identity=None) for kp in _pair(T, 0.5)]
    node, pose = _pose({}, pair)
    assert not pose.ambiguous and "end_identity.unsure" not in node.counters


def test_identity_is_the_tracked_needles_not_one_frames():
    """track_identity: alone a frame decides by itself; against a sure track its weak contrary
    evidence does not turn the needle (the frame is turned to the track's reading), strong
    evidence does; weak but consistent frames keep the track steady but not surer than they are
    (their errors share a cause)."""
    weak = np.log(0.7 / 0.3)
    turn, (z, w) = track_identity(0.3, None, None)            # no track: the frame's own call
    assert turn and z == pytest.approx(weak) and w == 1.0
    turn, (z, w) = track_identity(0.3, (5.0, 3.0), None)      # cannot relate it to the track
    assert turn and z == pytest.approx(weak) and w == 1.0
    # the frame reads the needle the other way round than the sure track, with weak evidence
    turn, (z, w) = track_identity(0.7, (5.0, 3.0), False)
    assert turn and w == pytest.approx(3.4) and z == pytest.approx((0.8 * 3.0 * 5.0 - weak) / 3.4)
    # strong contrary evidence wins
    assert not track_identity(0.9999, (1.0, 1.0), False)[0]
    track = None
    for _ in range(40):                                        # weak, consistent: as sure as a frame
        turn, track = track_identity(0.7, track, True if track is not None else None)
        assert not turn
    assert track[0] == pytest.approx(weak) and track[1] == pytest.approx(5.0, abs=1e-3)
    # one contrary frame as weak as the others does not turn it, and leaves it less sure
    turn, (z, _) = track_identity(0.7, track, False)
    assert turn and 0 < z < weak
    assert track_identity(1.0 - 1e-12, (TRACK_CAP, 5.0), True)[1][0] == TRACK_CAP


def test_settle_alone_turns_below_one_half_and_states_the_likelier_reading():
    assert settle(None, None) == settle(None, None, tracking=True)
    assert settle(None, None).turn is False and settle(None, None).p is None
    s = settle(0.2, 0.3)
    assert s.turn and s.p == pytest.approx(1.0 - stereo_end_identity(0.2, 0.3)) and s.track is None
    s = settle(0.8, None)
    assert not s.turn and s.p == pytest.approx(0.8)
    assert settle(0.5, 0.5).p == pytest.approx(0.5) and not settle(0.5, 0.5).turn


def test_settle_with_tracking_is_the_tracks_call_and_states_the_tracks_probability():
    s = settle(0.3, None, tracking=True)                     # no track yet: the frame's own call
    assert s.turn and s.track is not None and s.p == pytest.approx(0.7)
    strong = (logit(0.99), 5.0)
    s = settle(0.7, None, tracking=True, track=strong, same_as_track=False)
    turn, track = track_identity(0.7, strong, False)
    assert (s.turn, s.track) == (turn, track) and s.turn     # weak contrary evidence: read as the track reads it
    assert s.p == pytest.approx(sigmoid(track[0])) and s.p > 0.5
    assert settle(None, None, tracking=True, track=strong, same_as_track=True).track is None


def test_state_flags_below_the_floor_and_spans_the_turn():
    rng = np.random.default_rng(3)
    T = random_needle_pose(rng, RIG, MODEL)
    C = np.diag([1e-4] * 3 + [1e-8] * 3)
    assert state(T, C, MODEL, None) == (False, C)
    unsure, C_sure = state(T, C, MODEL, TIP_SURE)
    assert not unsure and C_sure is C
    unsure, C_unsure = state(T, C, MODEL, 0.8)
    assert unsure and np.allclose(C_unsure, identity_covariance(T, C, MODEL, 0.8))
    assert state(T, None, MODEL, 0.8) == (True, None)
    assert state(T, C, MODEL, 0.8, min_p=0.75)[0] is False


def test_sigmoid_inverts_logit_and_does_not_overflow():
    for p in (1e-6, 0.1, 0.5, 0.93, 1 - 1e-6):
        assert sigmoid(logit(p)) == pytest.approx(p, rel=1e-6)
    assert 0.0 < sigmoid(-1e6) < 1e-12 and 1.0 - 1e-12 < sigmoid(1e6) <= 1.0


def test_the_turn_term_taken_out_gives_the_reading_covariance_back():
    from common.geometry.end_identity import identity_covariance, without_identity_covariance
    from common.geometry.needle import NeedleModel
    from common.geometry.transforms import make_T, rotvec_to_R
    needle = NeedleModel()
    T = make_T(rotvec_to_R([0.3, -0.2, 0.5]), [0.01, 0.0, 0.1])
    C = np.diag([1e-4, 2e-4, 3e-4, 1e-8, 2e-8, 4e-8])
    wide = identity_covariance(T, C, needle, 0.9)
    assert np.allclose(without_identity_covariance(T, wide, needle, 0.9), C, atol=1e-12)
    # a covariance the turn was never added to is left as it is
    assert np.array_equal(without_identity_covariance(T, C, needle, 0.9), C)


def test_reads_as_keypoints_tells_a_pose_from_its_turn_by_every_cameras_keypoints():
    """Keypoints as the pose puts them read it; the pose turned end for end reads them the other
    way; one camera reading it turned is enough; low scores count, weighted; a needle too small
    in the image to tell the ends apart by 5 px says nothing against the pose."""
    rng = np.random.default_rng(4)
    T = random_needle_pose(rng, RIG, MODEL)
    uv = {c.name: true_keypoints(c, T, MODEL)[0] for c in RIG.cameras}
    low = {name: np.full(5, 0.2) for name in uv}
    assert reads_as_keypoints(RIG, MODEL, T, uv, low) is True
    T_turn = tip_for_tail(T, MODEL)
    assert reads_as_keypoints(RIG, MODEL, T_turn, uv, low) is False
    one = {"left": uv["left"], "right": true_keypoints(RIG["right"], T_turn, MODEL)[0]}
    assert reads_as_keypoints(RIG, MODEL, T_turn, one, low) is False
    assert reads_as_keypoints(RIG, MODEL, T, one, low) is False
    assert reads_as_keypoints(RIG, MODEL, T, {}, {}) is None
    far = T.copy()
    far[:3, 3] *= 40.0
    uv_far = {c.name: true_keypoints(c, far, MODEL)[0] for c in RIG.cameras}
    assert reads_as_keypoints(RIG, MODEL, tip_for_tail(far, MODEL), uv_far, low) is True
    assert with_reading(0.99, False) == 0.5 and with_reading(0.99, True) == 0.99
    assert with_reading(None, False) is None and with_reading(0.3, False) == 0.3


def test_a_fitted_pose_states_its_tip_under_both_caps_and_names_them():
    """The end-unseen cap, then the keypoints' reading cap, each named where it lowered p."""
    caps = dict(end_unseen_p_max=0.9, reading_p_max=0.5)
    assert fitted_tip_probability(0.99, (True, True), True, **caps) == (0.99, ())
    assert fitted_tip_probability(0.99, (True, False), True, **caps) == (0.9, ("end_unseen",))
    assert fitted_tip_probability(0.99, None, False, **caps) == (0.5, ("reading_turned",))
    assert fitted_tip_probability(0.99, (False, True), False, **caps) == (0.5, ("end_unseen", "reading_turned"))
    # a probability already under a cap is not lowered by it, and nothing stated stays so
    assert fitted_tip_probability(0.7, (False, True), True, **caps) == (0.7, ())
    assert fitted_tip_probability(None, (False, False), False, **caps) == (None, ())


def test_a_camera_whose_a_lies_at_the_poses_tail_reads_it_turned_whatever_its_e():
    """A collapsed detection (E fallen onto A's end, B..D strewn along the wire) states its tip
    at its A: at the pose's tail, it reads the pose turned, though the mean over all five
    keypoints is even; at the pose's tip, it reads the pose as fitted."""
    rng = np.random.default_rng(7)
    T = random_needle_pose(rng, RIG, MODEL)
    uv = {c.name: true_keypoints(c, T, MODEL)[0] for c in RIG.cameras}
    collapsed = {}
    for name, pts in uv.items():
        pts = pts.copy()
        pts[4] = pts[0] + np.array([3.0, 1.0])          # E a few px from A, at the tip
        pts[1:4] = pts[2]                                # B..D on the middle: they read both ways
        collapsed[name] = pts
    low = {name: np.full(5, 0.3) for name in uv}
    assert reads_as_keypoints(RIG, MODEL, T, collapsed, low) is True
    assert reads_as_keypoints(RIG, MODEL, tip_for_tail(T, MODEL), collapsed, low) is False
    # one camera's A at the tail is enough
    one = {"left": collapsed["left"], "right": uv["right"]}
    assert reads_as_keypoints(RIG, MODEL, tip_for_tail(T, MODEL), one, low) is False


def test_the_cameras_statements_are_taken_about_the_end_at_their_a():
    """A camera reading the pose turned speaks of its tail: its probability turns; an unsure one
    takes little from a sure one, a sure one splits the evidence; the reading cap is at least
    reading_p_max and never raises a probability."""
    from common.geometry.end_identity import read_tip_probability
    assert read_tip_probability({"left": 0.9, "right": 0.9}, {"left": True, "right": True}) > 0.9
    split = read_tip_probability({"left": 0.93, "right": 0.86}, {"left": False, "right": True})
    assert split < 0.5
    mild = read_tip_probability({"left": 0.55, "right": 0.99}, {"left": False, "right": True})
    assert 0.95 < mild < 0.99
    assert read_tip_probability({"left": None, "right": 0.8}, {"left": False}) is None
    caps = dict(end_unseen_p_max=0.9, reading_p_max=0.5)
    assert fitted_tip_probability(0.99, None, False, p_read=split, **caps) == (0.5, ("reading_turned",))
    assert fitted_tip_probability(0.99, None, False, p_read=mild, **caps) == (mild, ("reading_turned",))
    assert fitted_tip_probability(0.9, None, False, p_read=0.97, **caps) == (0.9, ())


def test_one_cameras_reading_gives_that_cameras_statement():
    """Issue 56: with one camera's keypoints only (the other blocked, or its detector lost the
    needle), the pose's tip probability is that camera's statement taken about the end at its A,
    whichever camera it is; a camera name outside the rig is refused."""
    from common.geometry.end_identity import pose_tip_probability, read_tip_probability
    assert read_tip_probability({"left": 0.8}, {"left": True}) == pytest.approx(0.8)
    assert read_tip_probability({"right": 0.8}, {"right": False}) == pytest.approx(0.2)
    assert read_tip_probability({"left": None, "right": 0.7}, {"left": True, "right": True}) == pytest.approx(0.7)
    assert read_tip_probability({"left": 0.9, "right": 0.6}, {"left": False}) == pytest.approx(0.1)
    p, caps = pose_tip_probability(0.95, None, {"right": False}, {"left": None, "right": 0.9},
                                   end_unseen_p_max=0.9, reading_p_max=0.5)
    assert p == 0.5 and caps == ("reading_turned",)
    with pytest.raises(ValueError, match="centre"):
        read_tip_probability({"centre": 0.8}, {"centre": True})


def test_a_partial_view_states_no_sure_tip():
    from common.geometry.end_identity import fitted_tip_probability
    p, caps = fitted_tip_probability(0.99, (True, True), True, end_unseen_p_max=0.9, partial=True)
    assert p == 0.9 and caps == ("partial_view",)
    p, caps = fitted_tip_probability(0.99, (True, False), True, end_unseen_p_max=0.9, partial=True)
    assert p == 0.9 and caps == ("end_unseen",)
    assert fitted_tip_probability(0.99, (True, True), True, end_unseen_p_max=0.9) == (0.99, ())


def test_a_second_camera_adds_nothing_on_an_unfamiliar_look():
    from common.geometry.end_identity import CAMERA_CORRELATION, second_view_news, stereo_end_identity
    assert second_view_news([1.0, 0.8, None]) == CAMERA_CORRELATION       # like the training looks
    assert second_view_news([1.0, 2.5]) == 0.0                            # one an octave or more unlike
    assert second_view_news([2 ** 0.5, 1.0]) == pytest.approx(CAMERA_CORRELATION / 2)
    sure = stereo_end_identity(0.9, 0.88)
    alone = stereo_end_identity(0.9, 0.88, news=second_view_news([1.33, 1.32]))
    assert sure > 0.95 > alone > 0.9          # two agreeing views of an unfamiliar look: not sure
    assert stereo_end_identity(0.9, 0.9, news=0.0) == pytest.approx(0.9)


def test_what_a_pose_says_of_its_covariance_decides_what_is_taken_out():
    """reading_covariance: the widening over the turn is taken out where the pose says it was
    widened; a pose that does not say is read as the policy would have stated it (TIP_SURE)."""
    from common.geometry.end_identity import (
        identity_covariance,
        reading_covariance,
        state,
        was_widened,
    )
    from common.geometry.transforms import make_T, rotvec_to_R
    needle = NeedleModel()
    T = make_T(rotvec_to_R([0.3, -0.2, 0.1]), [0.0, 0.01, 0.1])
    C = np.diag([1e-4] * 3 + [1e-7] * 3)
    stated = state(T, C, needle, 0.8)
    assert stated.unsure and stated.widened and np.allclose(stated.covariance, identity_covariance(T, C, needle, 0.8))
    assert not state(T, None, needle, 0.8).widened and state(T, None, needle, 0.8).unsure
    assert not state(T, C, needle, TIP_SURE).widened
    assert np.allclose(reading_covariance(T, stated.covariance, needle, 0.8, True), C)
    assert reading_covariance(T, stated.covariance, needle, 0.8, False) is stated.covariance   # said: not widened
    assert np.allclose(reading_covariance(T, stated.covariance, needle, 0.8, None), C)         # not said: the policy
    assert reading_covariance(T, C, needle, None, None) is C
    assert was_widened(0.9, None) and not was_widened(0.99, None) and not was_widened(None, None)
    assert was_widened(0.99, True) and not was_widened(0.5, False)
