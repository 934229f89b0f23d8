"""The tracker node (nodes/tracker.py) offline: a scripted handover (common/sim/motion.py) seen
by a still endoscope, refined poses drawn around the truth with their covariance."""
import numpy as np
import pytest

from common.geometry.camera import StereoRig
from common.evaluation.metrics import pose_nees
from common.geometry.needle import NeedleModel
from common.geometry.needle_tracker import retract
from common.geometry.transforms import inv_T, make_T, pose_error
from common.runtime.messages import (
    Calibration,
    EcmPose,
    EndOfStream,
    GroundTruth,
    InHandPose,
    InstrumentState,
    NoPoseNotice,
    PoseEstimate,
    decode,
    encode,
)
from common.runtime.node import NodeError
from common.sim.motion import FPS, script_take
from nodes.tracker import TrackerNode

NEEDLE = NeedleModel()
CALIB = Calibration(0, np.array([1920, 1080]), StereoRig.default().to_dict(), NEEDLE.to_dict())
DT_NS = int(round(1e9 / FPS))


def handover():
    frames = script_take("handover", np.random.default_rng(1), NEEDLE, NEEDLE.wire_diameter_m / 2).frames
    centre = frames[0].T_world_needle[:3, 3]
    T_world_ecm = make_T(np.diag([1.0, -1.0, -1.0]), centre + [0.0, 0.0, 0.12])   # looking down at it
    return frames, T_world_ecm


def feed(node, frames, T_world_ecm, rng, skip=()):
    C = np.diag([np.radians(0.5) ** 2] * 3 + [0.2e-3 ** 2] * 2 + [0.6e-3 ** 2])   # ECM axes
    node.on_calib(CALIB)
    for k, fr in enumerate(frames):
        node.on_truth(GroundTruth(k, k * DT_NS, sequence=0, needle_at_rest=False))
        for name, (T, jaw, holds) in fr.instruments.items():
            node.on_instruments(InstrumentState(name, k, k * DT_NS, T, jaw, holds))
        node.on_ecm(EcmPose(k, k * DT_NS, T_world_ecm))
        if k in skip:
            continue
        T_ecm = retract(inv_T(T_world_ecm) @ fr.T_world_needle, rng.multivariate_normal(np.zeros(6), C))
        node.on_pose(PoseEstimate(k, k * DT_NS, "refined", T_ecm, covariance=C, end_identity=0.99))


def test_the_node_tracks_a_handover_and_publishes_the_needle_in_the_jaws():
    frames, T_world_ecm = handover()
    node = TrackerNode.offline({"corr_frames": 1.0})   # the poses fed err frame by frame on their own
    skip = set(range(40, 60))                      # the refine node posed nothing: predicted
    feed(node, frames, T_world_ecm, np.random.default_rng(0), skip)
    poses = {m.seq: m for o, m in node.published if o == "pose"}
    in_hand = [m for o, m in node.published if o == "in_hand"]
    assert sorted(poses) == list(range(len(frames)))
    assert node.counters["coasted"] == len(skip) and node.counters["events.handover"] == 1
    for seq, m in poses.items():
        decode(encode(m), PoseEstimate)            # a valid message
        assert m.method == "tracked" and m.residual_unit == "chi2"
        assert pose_error(m.T_world_needle, frames[seq].T_world_needle)[0] < 1e-3
        assert np.allclose(T_world_ecm @ m.T_ecm_needle, m.T_world_needle)
    assert {m.frame_id for m in in_hand} == {"psm1_jaw", "psm2_jaw"}
    # each pose states the track's mode (what the fusion reads): held wherever it is in the jaws
    assert {poses[m.seq].mode for m in in_hand} == {"held"}
    assert {m.mode for m in poses.values()} <= {"rest", "held", "free"}
    last = decode(encode(in_hand[-1]), InHandPose)
    fr = frames[last.seq]
    T_jn = inv_T(fr.instruments["psm2"][0]) @ fr.T_world_needle
    assert last.name == "psm2" and pose_error(last.T_jaw_needle, T_jn)[0] < 0.3e-3
    # the covariance is stated in ECM axes: honest against the truth seen from the endoscope
    nees = [pose_nees(m.T_ecm_needle, m.covariance, inv_T(T_world_ecm) @ frames[s].T_world_needle)
            for s, m in poses.items()]
    assert 1.0 < np.median(nees) < 9.0


def test_a_late_pose_is_dropped_and_a_new_take_starts_a_new_track():
    frames, T_world_ecm = handover()
    node = TrackerNode.offline(params={"max_wait": 2})
    rng = np.random.default_rng(1)
    feed(node, frames[:30], T_world_ecm, rng, skip={10})
    node.on_pose(PoseEstimate(10, 10 * DT_NS, "refined", inv_T(T_world_ecm) @ frames[10].T_world_needle,
                              covariance=np.eye(6) * 1e-8))
    assert node.counters["late_pose"] == 1
    node.on_truth(GroundTruth(30, 30 * DT_NS, sequence=1, needle_at_rest=False))
    node.on_ecm(EcmPose(30, 30 * DT_NS, T_world_ecm))
    far = make_T(np.eye(3), [0.05, 0, 0]) @ frames[30].T_world_needle
    node.on_pose(PoseEstimate(30, 30 * DT_NS, "refined", inv_T(T_world_ecm) @ far, covariance=np.eye(6) * 1e-8))
    assert node.step.stepped == 29                      # its pose is in; its instruments' states are not
    for name, (T, jaw, holds) in frames[30].instruments.items():
        node.on_instruments(InstrumentState(name, 30, 30 * DT_NS, T, jaw, holds))
    assert node.counters["resets.sequence"] == 1
    last = [m for o, m in node.published if o == "pose"][-1]
    assert last.seq == 30 and pose_error(last.T_world_needle, far)[0] < 1e-6


def test_a_late_pose_is_filtered_in_by_stepping_again_from_its_frame():
    """Every pose two frames late, the node waiting one frame for each: each frame is published
    predicted, each pose filtered in when it comes; the track ends exactly where it ends when
    every pose is in time."""
    frames, T_world_ecm = handover()
    C = np.diag([np.radians(0.5) ** 2] * 3 + [0.2e-3 ** 2] * 2 + [0.6e-3 ** 2])
    rng = np.random.default_rng(5)
    poses = [PoseEstimate(k, k * DT_NS, "refined",
                          retract(inv_T(T_world_ecm) @ fr.T_world_needle, rng.multivariate_normal(np.zeros(6), C)),
                          covariance=C, end_identity=0.99) for k, fr in enumerate(frames)]
    in_time, late = TrackerNode.offline({"max_wait": 50}), TrackerNode.offline({"max_wait": 1, "replay": 15})
    for node in (in_time, late):
        node.on_calib(CALIB)
    for k in range(len(frames)):
        for node in (in_time, late):
            frame_inputs(node, frames, T_world_ecm, k)
        in_time.on_pose(poses[k])
        if k >= 2:
            late.on_pose(poses[k - 2])
        assert late.step.stepped == k - 1                   # stepped when the next frame came, no pose yet
    for pose in poses[-2:]:
        late.on_pose(pose)
    for node in (in_time, late):
        node.on_eos(EndOfStream(len(frames), 0))
    assert late.counters["replayed"] == len(frames) - 1 and "late_pose" not in late.counters
    assert in_time.counters["events.handover"] == 1
    events = {c: {k: v for k, v in n.counters.items() if k.startswith(("events.", "rejected", "turned"))}
              for c, n in (("in_time", in_time), ("late", late))}
    assert events["late"] == events["in_time"]     # what the steps found, counted once
    a, b = in_time.step.tracker, late.step.tracker
    assert (a.mode, a.holder, a.age) == (b.mode, b.holder, b.age)
    assert np.allclose(a.T, b.T) and np.allclose(a.P, b.P) and np.allclose(a.identity, b.identity)
    published = {m.seq: m for o, m in late.published if o == "pose"}
    assert sorted(published) == list(range(2, len(frames)))      # 0 and 1: no track yet, said
    assert [m.seq for o, m in late.published if o == "no_pose"] == [0, 1]
    # what was published before its pose came: the track predicted (a held needle follows its jaws)
    errors = [pose_error(m.T_world_needle, frames[s].T_world_needle)[0] for s, m in published.items() if s > 5]
    assert np.median(errors) < 1e-3
    # too late for the window: dropped, counted
    late.on_pose(poses[len(frames) - 20])
    assert late.counters["late_pose"] == 1 and late.counters["replayed"] == len(frames) - 1


def frame_inputs(node, frames, T_world_ecm, k):
    """Frame ``k``'s truth, instruments' states and ECM pose (no pose)."""
    node.on_truth(GroundTruth(k, k * DT_NS, sequence=0, needle_at_rest=False))
    for name, (T, jaw, holds) in frames[k].instruments.items():
        node.on_instruments(InstrumentState(name, k, k * DT_NS, T, jaw, holds))
    node.on_ecm(EcmPose(k, k * DT_NS, T_world_ecm))


def test_a_frame_the_refine_node_says_has_no_pose_is_stepped_at_once():
    frames, T_world_ecm = handover()
    rng = np.random.default_rng(2)
    told, untold = (TrackerNode.offline({"max_wait": 5}) for _ in range(2))
    for node in (told, untold):
        feed(node, frames[:20], T_world_ecm, rng)
        frame_inputs(node, frames, T_world_ecm, 20)
    notice = decode(encode(NoPoseNotice(20, 20 * DT_NS, "refined", "too_few_points")), NoPoseNotice)
    told.on_no_pose(notice)
    assert told.step.stepped == 20 and told.counters["coasted"] == 1    # no later frame needed
    assert untold.step.stepped == 19                                    # waits for a later pose
    # a notice may come before the frame's other inputs: stepped as soon as they are in
    told.on_no_pose(NoPoseNotice(21, 21 * DT_NS, "refined", "poor_fit"))
    assert told.step.stepped == 20
    frame_inputs(told, frames, T_world_ecm, 21)
    assert told.step.stepped == 21 and told.counters["coasted"] == 2
    # a frame without a notice still waits for its pose, and a late one (within max_wait) is used
    for k in (22, 23):
        frame_inputs(told, frames, T_world_ecm, k)
    assert told.step.stepped == 21
    T_ecm = inv_T(T_world_ecm) @ frames[22].T_world_needle
    told.on_pose(PoseEstimate(22, 22 * DT_NS, "refined", T_ecm, covariance=np.eye(6) * 1e-8))
    assert told.step.stepped == 22 and told.counters["coasted"] == 2 and "late_pose" not in told.counters
    told.on_no_pose(NoPoseNotice(21, 21 * DT_NS, "refined", "poor_fit"))     # stepped already: nothing
    assert told.step.stepped == 22
    poses = [m for o, m in told.published if o == "pose"]
    assert pose_error(poses[-1].T_world_needle, frames[22].T_world_needle)[0] < 1e-3
    # a frame the refine node never saw (the detectors dropped it): a later frame's notice says
    # the refine node is past it
    frame_inputs(told, frames, T_world_ecm, 24)
    assert told.step.stepped == 22
    told.on_no_pose(NoPoseNotice(24, 24 * DT_NS, "refined", "too_few_points"))
    assert told.step.stepped == 24 and told.counters["coasted"] == 4
    poses = [m for o, m in told.published if o == "pose"]
    assert [m.seq for m in poses] == list(range(25)) and not [m for o, m in told.published if o == "no_pose"]


def test_a_frame_without_a_track_is_said_on_no_pose():
    frames, T_world_ecm = handover()
    node = TrackerNode.offline()
    node.on_calib(CALIB)
    for k in range(3):                                  # nothing posed yet: no track
        frame_inputs(node, frames, T_world_ecm, k)
        node.on_no_pose(NoPoseNotice(k, k * DT_NS, "refined", "too_few_points"))
    said = [decode(encode(m), NoPoseNotice) for o, m in node.published if o == "no_pose"]
    assert [(m.seq, m.stamp_ns, m.method, m.reason) for m in said] == [
        (k, k * DT_NS, "tracked", "no_track") for k in range(3)]
    assert node.counters["no_pose.no_track"] == 3 and not [m for o, m in node.published if o == "pose"]


def test_the_node_refuses_what_cannot_work():
    with pytest.raises(NodeError, match="ecm"):
        TrackerNode.offline(wired=["pose", "instruments"])
    with pytest.raises(NodeError, match="closed_rad"):
        TrackerNode.offline(params={"closed_rad": 1.0, "open_rad": 0.5})


def test_poses_far_behind_the_instruments_still_find_their_jaws():
    """As in a lossless run: the source's messages come 100 frames ahead of the refined poses."""
    frames, T_world_ecm = handover()
    frames = frames[:150]
    node = TrackerNode.offline(params={"max_wait": 120})
    node.on_calib(CALIB)
    C = np.diag([np.radians(0.5) ** 2] * 3 + [0.2e-3 ** 2] * 3)
    rng = np.random.default_rng(3)
    for k, fr in enumerate(frames):
        for name, (T, jaw, holds) in fr.instruments.items():
            node.on_instruments(InstrumentState(name, k, k * DT_NS, T, jaw, holds))
        node.on_ecm(EcmPose(k, k * DT_NS, T_world_ecm))
        j = k - 100
        if j >= 0 and j % 3 == 0:             # every third frame posed, 100 frames late
            T_ecm = retract(inv_T(T_world_ecm) @ frames[j].T_world_needle, rng.multivariate_normal(np.zeros(6), C))
            node.on_pose(PoseEstimate(j, j * DT_NS, "refined", T_ecm, covariance=C))
    node.on_eos(EndOfStream(len(frames), 0))
    poses = {m.seq: m for o, m in node.published if o == "pose"}
    assert sorted(poses) == list(range(len(frames)))
    assert node.counters["events.handover"] == 1 and "events.release" not in node.counters
    assert len([m for o, m in node.published if o == "in_hand"]) == len(frames)
    err = [pose_error(m.T_world_needle, frames[s].T_world_needle)[0] for s, m in poses.items()]
    assert max(err) < 1e-3


def test_instruments_that_go_quiet_make_room_and_hold_nothing_up():
    """Eight names heard once (junk) fill the table; once they are quiet for max_wait frames the
    real instruments get in again, and frames no longer wait for them."""
    frames, T_world_ecm = handover()
    node = TrackerNode.offline(params={"max_wait": 5})
    T = frames[0].instruments["psm1"][0]
    for i in range(8):
        node.on_instruments(InstrumentState(f"junk{i}", 0, 0, T, 0.5))
    assert node.counters["instruments.too_many"] == 0
    feed(node, frames[:40], T_world_ecm, np.random.default_rng(4))
    assert {"psm1", "psm2"} <= set(node.step.jaws.states) and node.counters["instruments.too_many"] > 0
    assert node.step.stepped == 39


def test_an_in_hand_pose_that_breaks_its_contract_is_refused_by_field():
    from common.runtime.messages import MessageError
    T = make_T(np.eye(3), [0.0, 0.0, 0.004])
    ok = InHandPose("psm1", 1, 2, "psm1_jaw", T, np.eye(6) * 1e-8, 0.9)
    assert decode(encode(ok), InHandPose).frame_id == "psm1_jaw"
    for bad, field in ((InHandPose("psm1", 1, 2, "psm1_jaw", T, -np.eye(6), None), "covariance"),
                       (InHandPose("psm1", 1, 2, "psm1_jaw", 2 * T, np.eye(6), None), "T_jaw_needle"),
                       (InHandPose("psm1", 1, 2, "", T, np.eye(6), None), "frame_id"),
                       (InHandPose("psm1", 1, 2, "psm1_jaw", T, np.eye(6), 1.5), "end_identity")):
        with pytest.raises(MessageError, match=f"InHandPose.{field}"):
            decode(encode(bad), InHandPose)
