"""The tracker's frame step (common/pose/tracker_step.py) driven directly: a scripted handover
(common/sim/motion.py) seen by a still endoscope, refined poses drawn around the truth."""
import numpy as np

from common.geometry.end_identity import identity_covariance
from common.geometry.needle import NeedleModel
from common.geometry.needle_tracker import TrackerConfig, retract
from common.geometry.refine import mirror_pose
from common.geometry.transforms import inv_T, make_T, pose_delta, pose_error
from common.pose.tracker_step import InstrumentTable, TrackerStep
from common.runtime.messages import EcmPose, EndOfStream, GroundTruth, InstrumentState, NoPoseNotice, PoseEstimate
from common.sim.arm_error import ARM_ERRORS, draw_arm_errors
from common.sim.motion import FPS, script_take

NEEDLE = NeedleModel()
DT_NS = int(round(1e9 / FPS))
C = np.diag([np.radians(0.5) ** 2] * 3 + [0.2e-3 ** 2] * 2 + [0.6e-3 ** 2])   # ECM axes


def handover():
    frames = script_take("handover", np.random.default_rng(1), NEEDLE, NEEDLE.wire_diameter_m / 2).frames
    centre = frames[0].T_world_needle[:3, 3]
    return frames, make_T(np.diag([1.0, -1.0, -1.0]), centre + [0.0, 0.0, 0.12])


def frame_inputs(step, frames, T_world_ecm, k) -> list:
    out = step.on_truth(GroundTruth(k, k * DT_NS, sequence=0, needle_at_rest=False))
    for name, (T, jaw, holds) in frames[k].instruments.items():
        out += step.on_instruments(InstrumentState(name, k, k * DT_NS, T, jaw, holds))
    return out + step.on_ecm(EcmPose(k, k * DT_NS, T_world_ecm))


def measured(frames, T_world_ecm, rng):
    return [PoseEstimate(k, k * DT_NS, "refined", retract(inv_T(T_world_ecm) @ fr.T_world_needle,
                                                         rng.multivariate_normal(np.zeros(6), C)),
                         covariance=C, end_identity=0.99) for k, fr in enumerate(frames)]


def test_each_frame_is_stepped_once_in_order_when_its_inputs_are_in():
    frames, T_world_ecm = handover()
    poses = measured(frames, T_world_ecm, np.random.default_rng(0))
    step = TrackerStep(max_wait=1)
    out = []
    for k in range(40):
        out += frame_inputs(step, frames, T_world_ecm, k)
        assert step.stepped == k - 1                         # the frame waits for its pose
        out += step.on_pose(poses[k])
        assert step.stepped == k
    tracked = [m for o, m in out if o == "pose"]
    assert [m.seq for m in tracked] == list(range(40)) and {m.method for m in tracked} == {"tracked"}
    assert all(m.identity_widened is False and not m.ambiguous for m in tracked)   # the tip stays sure
    assert {o for o, _ in out} <= {"pose", "in_hand"} and any(o == "in_hand" for o, _ in out)


def test_a_late_pose_is_replayed_to_the_same_track_as_in_time():
    frames, T_world_ecm = handover()
    poses = measured(frames, T_world_ecm, np.random.default_rng(1))
    counts = {}
    in_time, late = TrackerStep(), TrackerStep(count=lambda n, k=1: counts.__setitem__(n, counts.get(n, 0) + k))
    for k in range(30):
        for step in (in_time, late):
            frame_inputs(step, frames, T_world_ecm, k)
        in_time.on_pose(poses[k])
        if k >= 2:
            late.on_pose(poses[k - 2])                       # two frames late: predicted, then replayed
    for k in (28, 29):
        late.on_pose(poses[k])
    assert counts["replayed"] > 0
    a, b = in_time.tracker, late.tracker
    assert (a.mode, a.holder, a.age) == (b.mode, b.holder, b.age)
    assert np.allclose(a.T, b.T) and np.allclose(a.P, b.P)


def test_a_frame_without_a_track_is_said_and_the_stream_end_releases_every_frame():
    frames, T_world_ecm = handover()
    step = TrackerStep(max_wait=5)
    out = frame_inputs(step, frames, T_world_ecm, 0) + step.on_no_pose(NoPoseNotice(0, 0, "refined", "too_few_points"))
    assert [(o, m.reason) for o, m in out] == [("no_pose", "no_track")]      # stepped at once, no track yet
    for k in (1, 2):
        assert frame_inputs(step, frames, T_world_ecm, k) == []             # waiting for their poses
    out = step.on_eos(EndOfStream(3, 0))
    assert [m.seq for _, m in out] == [1, 2] and step.stepped == 2


def test_a_pose_that_says_its_covariance_spans_the_turn_is_measured_without_it():
    frames, T_world_ecm = handover()
    step = TrackerStep()
    T = inv_T(T_world_ecm) @ frames[0].T_world_needle
    wide = identity_covariance(T, C, NEEDLE, 0.8)
    said = step.measurement(PoseEstimate(0, 0, "refined", T, covariance=wide, end_identity=0.8,
                                         identity_widened=True), T_world_ecm)
    plain = step.measurement(PoseEstimate(0, 0, "refined", T, covariance=C, end_identity=0.8), T_world_ecm)
    kept = step.measurement(PoseEstimate(0, 0, "refined", T, covariance=wide, end_identity=0.8,
                                         identity_widened=False), T_world_ecm)
    assert np.allclose(said.covariance, plain.covariance)                   # the turn taken out, as said
    assert not np.allclose(kept.covariance, plain.covariance)               # said not widened: kept


def test_the_instrument_table_holds_a_bounded_set_of_live_names():
    from common.data.instruments import MAX_INSTRUMENTS
    table = InstrumentTable(max_age=5, keep=16)
    state = lambda name, seq: InstrumentState(name, seq, 0, np.eye(4), 0.1, False)   # noqa: E731
    for i in range(MAX_INSTRUMENTS):
        assert table.put(state(f"psm{i}", 0))
    assert not table.put(state("extra", 3))                                 # every name still live
    assert table.put(state("extra", 6))                                     # one quiet 6 frames makes room
    assert "extra" in table.states and len(table.states) == MAX_INSTRUMENTS
    assert set(table.at(6)) == {"extra"} and sorted(table.heard()) == [0] * (MAX_INSTRUMENTS - 1) + [6]


def test_with_arm_correction_each_arm_s_error_is_said_and_the_needle_is_in_the_corrected_jaws():
    frames, T_world_ecm = handover()
    errs = draw_arm_errors(ARM_ERRORS["dvrk"], (3, 0), {n: T for n, (T, _, _) in frames[0].instruments.items()})
    poses = measured(frames, T_world_ecm, np.random.default_rng(2))
    step, out = TrackerStep(TrackerConfig(arm_correction=True), max_wait=1), []
    for k in range(60):
        out += step.on_truth(GroundTruth(k, k * DT_NS, sequence=0, needle_at_rest=False))
        for name, (T, jaw, holds) in frames[k].instruments.items():
            T_rep, jaw_rep = errs[name].report(T, jaw, k)
            out += step.on_instruments(InstrumentState(name, k, k * DT_NS, T_rep, jaw_rep, holds))
        out += step.on_ecm(EcmPose(k, k * DT_NS, T_world_ecm)) + step.on_pose(poses[k])
    said = [m for o, m in out if o == "arm_correction"]
    assert {(m.seq, m.name) for m in said} == {(k, n) for k in range(60) for n in ("psm1", "psm2")}
    for m in said:     # the corrected jaws are the correction applied to the report
        T_rep = errs[m.name].report(frames[m.seq].instruments[m.name][0], 0.0, m.seq)[0]
        assert np.allclose(m.T_world_jaw, m.T_correction @ T_rep)
    # the held needle is stated in the corrected jaw frame: with the tracked pose, it gives the
    # corrected jaws of that frame
    held = {m.seq: m for o, m in out if o == "in_hand"}
    tracked = {m.seq: m for o, m in out if o == "pose"}
    corrected = {(m.seq, m.name): m.T_world_jaw for m in said}
    for seq, m in held.items():
        T_jaw = tracked[seq].T_world_needle @ inv_T(m.T_jaw_needle)
        assert max(pose_error(T_jaw, corrected[(seq, m.name)])) < 1e-9
    # off: the reports as exact, nothing said on arm_correction
    step = TrackerStep(max_wait=1)
    out = []
    for k in range(5):
        out += frame_inputs(step, frames, T_world_ecm, k) + step.on_pose(poses[k])
    assert not [o for o, _ in out if o == "arm_correction"]


def one_camera_poses(frames, T_world_ecm, rng):
    """Poses as one camera gives them: 20x the stereo position error along the view (ECM z)."""
    wide = C.copy()
    wide[5, 5] *= 400.0
    return [PoseEstimate(k, k * DT_NS, "refined_one_camera", retract(inv_T(T_world_ecm) @ fr.T_world_needle,
                                                                     rng.multivariate_normal(np.zeros(6), wide)),
                         covariance=wide, end_identity=0.99, ambiguous=True) for k, fr in enumerate(frames)]


def test_a_one_camera_pose_starts_no_track_but_keeps_one_going():
    """The held needle tracked on stereo poses, then 20 frames on one camera's: each updates the
    track (none is rejected, none coasts) and the track stays within the stereo measurement's
    error; a one-camera pose alone starts no track (unless start_one_camera: a monocular scope)."""
    frames, T_world_ecm = handover()
    rng = np.random.default_rng(4)
    stereo, one = measured(frames, T_world_ecm, rng), one_camera_poses(frames, T_world_ecm, rng)
    counts = {}
    step = TrackerStep(one_camera_wired=True, count=lambda n, k=1: counts.__setitem__(n, counts.get(n, 0) + k))
    tracked = []
    for k in range(40):
        frame_inputs(step, frames, T_world_ecm, k)
        if k < 20:
            out = step.on_pose(stereo[k])
        else:     # the refine node's order: the one-camera pose, then its notice (or the notice first)
            notice = NoPoseNotice(k, k * DT_NS, "refined", "one_camera")
            out = step.on_no_pose(notice) if k % 2 else []
            assert step.stepped == k - 1                     # the notice does not step the frame
            out += step.on_pose(one[k], one_camera=True) + ([] if k % 2 else step.on_no_pose(notice))
        tracked += [m for o, m in out if o == "pose"]
    assert [m.seq for m in tracked] == list(range(40))
    assert counts["one_camera"] == 20 and "coasted" not in counts and "rejected" not in counts
    for m in tracked[20:]:
        dt, dr = pose_error(m.T_world_needle, frames[m.seq].T_world_needle)
        assert dt < 2e-3 and np.degrees(dr) < 3.0

    def depth_share(m):       # the position's variance along the view (ECM z) against across it
        P = np.asarray(m.covariance)
        return P[5, 5] / P[3, 3]
    assert depth_share(tracked[39]) > 1.2 * depth_share(tracked[19])     # one view leaves the depth open

    alone = TrackerStep(one_camera_wired=True)
    out = frame_inputs(alone, frames, T_world_ecm, 0) + alone.on_pose(one[0], one_camera=True)
    assert [(o, m.reason) for o, m in out] == [("no_pose", "no_track")]
    mono = TrackerStep(TrackerConfig(start_one_camera=True), one_camera_wired=True)
    out = frame_inputs(mono, frames, T_world_ecm, 0) + mono.on_pose(one[0], one_camera=True)
    first = [m for o, m in out if o == "pose"][0]
    # one view cannot tell the arc from its mirror image: flagged, the covariance spans the mirror
    assert first.ambiguous
    d = pose_delta(mirror_pose(first.T_ecm_needle, NEEDLE), first.T_ecm_needle)
    assert d @ np.linalg.solve(np.asarray(first.covariance), d) < 4.0
    out = frame_inputs(mono, frames, T_world_ecm, 1) + mono.on_pose(stereo[1])
    assert not [m for o, m in out if o == "pose"][0].ambiguous               # a stereo view settles it
