"""The tracker's frame step (common/pose/tracker_step.py) driven directly: a scripted handover
(common/sim/motion.py) seen by a still endoscope, refined poses drawn around the truth."""
import numpy as np

from common.geometry.end_identity import identity_covariance
from common.geometry.needle import NeedleModel
from common.geometry.needle_tracker import retract
from common.geometry.transforms import inv_T, make_T
from common.pose.tracker_step import InstrumentTable, TrackerStep
from common.runtime.messages import EcmPose, EndOfStream, GroundTruth, InstrumentState, NoPoseNotice, PoseEstimate
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
