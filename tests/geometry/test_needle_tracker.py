"""The needle tracker (common/geometry/needle_tracker.py) on exact synthetic takes: the motion
scripts of common/sim/motion.py give the needle's and the jaws' true poses frame by frame; the
measurements are those poses with drawn noise of a stated covariance."""
import dataclasses
import math

import numpy as np
import pytest

from common.evaluation.metrics import pose_nees
from common.bench.tracker_bench import stated_covariance
from common.geometry.needle import NeedleModel
from common.geometry.needle_tracker import (
    Jaw,
    Measurement,
    NeedleTracker,
    TrackerConfig,
    jaw_holds,
    retract,
    turned_end_for_end,
)
from common.geometry.transforms import inv_T, make_T, pose_error, rotvec_to_R
from common.sim.motion import FPS, script_take

NEEDLE = NeedleModel()
DT_NS = int(round(1e9 / FPS))


def take(motion: str, seed: int):
    return script_take(motion, np.random.default_rng(seed), NEEDLE, NEEDLE.wire_diameter_m / 2).frames


def jaws_of(frame) -> dict:
    """What the system measures of the instruments: pose and opening, never ``holds``."""
    return {n: Jaw(T, jaw) for n, (T, jaw, _holds) in frame.instruments.items()}


def measure(rng, T_true, C, end_identity=None) -> Measurement:
    return Measurement(retract(T_true, rng.multivariate_normal(np.zeros(6), C)), C, end_identity)


def run(frames, rng, C, drop=lambda k: False, tracker=None, noise=True, **kw):
    tr = tracker or NeedleTracker(NEEDLE, TrackerConfig(**kw))
    out = []
    for k, fr in enumerate(frames):
        m = None if drop(k) else (measure(rng, fr.T_world_needle, C) if noise
                                  else Measurement(fr.T_world_needle, C))
        out.append(tr.step(k * DT_NS, jaws_of(fr), m))
    return tr, out


def errors(frames, out, start=0):
    e = np.array([pose_error(o.T_world_needle, f.T_world_needle) for f, o in zip(frames[start:], out[start:])])
    return e[:, 0] * 1e3, np.degrees(e[:, 1])


def nees(frames, out):
    return np.array([pose_nees(o.T_world_needle, o.covariance, f.T_world_needle) for f, o in zip(frames, out)])


def true_holder(frame):
    return next((n for n, (_, _, h) in sorted(frame.instruments.items()) if h), None)


def test_pickup_is_held_from_the_grasp_on_and_gives_the_grasp():
    frames = take("pickup", 2)
    rng = np.random.default_rng(0)
    C = stated_covariance(rng)
    tr, out = run(frames, rng, C)
    modes = [o.mode for o in out]
    assert modes[0] == "rest" and modes[-1] == "held" and out[-1].holder == "psm1"
    first_held = next(k for k, f in enumerate(frames) if true_holder(f))
    grasped = next(k for k, o in enumerate(out) if o.mode == "held")
    # decided from the jaws (closed below closed_rad, a few frames before the script's jaws
    # stop), not the truth
    assert first_held - 10 <= grasped <= first_held + 3
    assert [o.event for o in out].count("grasp:psm1") == 1
    pos, rot = errors(frames, out)
    assert pos.mean() < 0.35 and rot.mean() < 1.2
    # the in-hand pose, from the 10th held frame on, against the true grasp
    T_jn_true = [inv_T(f.instruments["psm1"][0]) @ f.T_world_needle for f in frames]
    e = np.array([pose_error(o.T_jaw_needle, T) for o, T in zip(out[grasped + 9:], T_jn_true[grasped + 9:])])
    assert e[:, 0].mean() * 1e3 < 0.3 and np.degrees(e[:, 1]).mean() < 1.0
    assert np.all(np.isfinite(out[-1].jaw_covariance)) and np.linalg.eigvalsh(out[-1].jaw_covariance).min() > 0


def test_a_held_needle_unseen_follows_the_jaws():
    """No measurement for a second while the jaws carry the needle: the track is the jaws'."""
    frames = take("pickup", 3)
    rng = np.random.default_rng(1)
    C = stated_covariance(rng)
    first_held = next(k for k, f in enumerate(frames) if true_holder(f))
    hidden = range(first_held + 15, first_held + 45)
    tr, out = run(frames, rng, C, drop=lambda k: k in hidden)
    assert all(out[k].mode == "held" and out[k].used is None for k in hidden)
    pos, rot = errors(frames, out)
    assert pos[list(hidden)].max() < 0.6 and rot[list(hidden)].max() < 2.0
    # the truth moved meanwhile: the jaws did carry it
    moved = np.linalg.norm(frames[hidden[-1]].T_world_needle[:3, 3] - frames[hidden[0]].T_world_needle[:3, 3])
    assert moved > 0.003


def test_handover_passes_the_needle_to_the_second_instrument():
    frames = take("handover", 1)
    rng = np.random.default_rng(2)
    C = stated_covariance(rng)
    tr, out = run(frames, rng, C)
    assert out[0].mode == "held" and out[0].holder == "psm1"
    assert "handover:psm2" in [o.event for o in out]
    assert out[-1].mode == "held" and out[-1].holder == "psm2"
    pos, rot = errors(frames, out)
    assert pos.mean() < 0.35 and rot.mean() < 1.2
    T_jn = inv_T(frames[-1].instruments["psm2"][0]) @ frames[-1].T_world_needle
    dt, dr = pose_error(out[-1].T_jaw_needle, T_jn)
    assert dt < 0.3e-3 and dr < math.radians(1.0)


def test_throw_lets_go_and_the_needle_stays_in_the_tissue():
    frames = take("throw", 4)
    rng = np.random.default_rng(3)
    C = stated_covariance(rng)
    tr, out = run(frames, rng, C)
    events = [o.event for o in out]
    released = events.index("release")
    assert out[released].mode == "rest" and out[-1].mode == "rest"      # left in the tissue
    assert all(o.mode == "held" for o in out[:released])
    pos, rot = errors(frames, out)
    assert pos.mean() < 0.4 and rot.mean() < 1.5


def free_frames(n=60, v=(0.012, -0.006, 0.003), w=(0.0, 0.6, 0.3)):
    """A needle flying at constant velocity, no instrument near it."""
    T0 = make_T(rotvec_to_R([0.3, -0.2, 0.1]), [0.0, 0.0, 0.1])

    class F:
        def __init__(self, T):
            self.T_world_needle, self.instruments = T, {}
    return [F(make_T(rotvec_to_R(np.asarray(w) * k / FPS) @ T0[:3, :3], T0[:3, 3] + np.asarray(v) * k / FPS))
            for k in range(n)]


def test_a_moving_needle_without_jaws_is_tracked_free():
    frames = free_frames()
    rng = np.random.default_rng(4)
    C = stated_covariance(rng)
    tr, out = run(frames, rng, C)
    assert out[-1].mode == "free" and "restart" in [o.event for o in out]
    pos, rot = errors(frames, out, start=15)
    raw = np.array([pose_error(measure(rng, f.T_world_needle, C).T_world_needle, f.T_world_needle)
                    for f in frames[15:]])
    assert pos.mean() < 0.9 * raw[:, 0].mean() * 1e3 and rot.mean() < 0.9 * np.degrees(raw[:, 1]).mean()
    assert np.mean([o.mode == "free" for o in out[5:]]) > 0.8


def test_nees_is_consistent_on_noisy_measurements():
    """The stated covariance is honest where the model is the world's (the scripts' grasps do not
    slip, their needles at rest do not move, each frame's measurement errs on its own:
    ``corr_frames`` 1): NEES near chi-square(6)'s median 5.35. The default process noise (a real
    grasp slips) makes it smaller here."""
    vals = []
    exact = dict(rest_sigma_m=1e-7, rest_sigma_rad=1e-6, slip_sigma_m=1e-7, slip_sigma_rad=1e-6,
                 jaw_sigma_m=1e-7, jaw_sigma_rad=1e-6, corr_frames=1.0)
    for motion, seed in (("pickup", 5), ("handover", 6), ("throw", 7)):
        frames = take(motion, seed)
        rng = np.random.default_rng(seed)
        C = stated_covariance(rng)
        _, out = run(frames, rng, C, **exact)
        vals.append(nees(frames, out)[5:])
        _, out = run(frames, rng, C, corr_frames=1.0)
        assert 1.0 < np.median(nees(frames, out)) < 9.0
    v = np.concatenate(vals)
    assert 3.0 <= np.median(v) <= 9.0, np.median(v)
    assert np.mean(v > 22.46) < 0.05


def test_an_outlier_is_gated_and_three_in_a_row_restart_the_track():
    frames = take("handover", 8)
    rng = np.random.default_rng(8)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    for k in range(20):
        o = tr.step(k * DT_NS, jaws_of(frames[k]), measure(rng, frames[k].T_world_needle, C))
    wild = make_T(np.eye(3), [0.01, 0, 0]) @ frames[20].T_world_needle
    o = tr.step(20 * DT_NS, jaws_of(frames[20]), Measurement(wild, C))
    assert o.used is False and pose_error(o.T_world_needle, frames[20].T_world_needle)[0] < 0.6e-3
    for k in (21, 22):
        o = tr.step(k * DT_NS, jaws_of(frames[k]), Measurement(make_T(np.eye(3), [0.01, 0, 0]) @ frames[k].T_world_needle, C))
    assert o.event == "restart" and o.used is True


def test_a_turned_reading_is_evidence_against_the_track_not_a_new_truth():
    frames = take("handover", 9)
    rng = np.random.default_rng(9)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    turned_in = set(range(30, 200, 7))
    for k, fr in enumerate(frames):
        m = measure(rng, fr.T_world_needle, C, end_identity=0.97)
        if k in turned_in:       # the detector read this frame end for end, fairly sure of it
            m = Measurement(turned_end_for_end(m.T_world_needle, NEEDLE), C, 0.9)
        o = tr.step(k * DT_NS, jaws_of(fr), m)
        assert pose_error(o.T_world_needle, fr.T_world_needle)[1] < math.radians(10), k
        if k in turned_in:
            assert o.turned and o.used
    assert o.end_identity > 0.9


def test_strong_evidence_turns_the_track():
    """A track started on a wrong tip (p=0.6) turns once frames say otherwise, surely."""
    frames = take("pickup", 10)
    rng = np.random.default_rng(10)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    first = measure(rng, frames[0].T_world_needle, C)
    tr.step(0, jaws_of(frames[0]), Measurement(turned_end_for_end(first.T_world_needle, NEEDLE), C, 0.6))
    events = []
    for k, fr in enumerate(frames[1:40], 1):
        o = tr.step(k * DT_NS, jaws_of(fr), measure(rng, fr.T_world_needle, C, end_identity=0.99))
        events.append(o.event)
    assert "flip" in events and pose_error(o.T_world_needle, frames[39].T_world_needle)[1] < math.radians(5)


def needle_between_jaws():
    """A needle at rest and jaws whose axis (world z) crosses its arc 3 mm from the pivot."""
    T_needle = make_T(np.eye(3), [0.0, 0.0, 0.1])
    p = T_needle[:3, 3] + NEEDLE.radius_m * np.array([0.0, 1.0, 0.0])       # a point of the arc
    return T_needle, make_T(np.eye(3), p - [0.0, 0.0, 0.003])


def test_jaws_that_close_but_leave_the_needle_behind_do_not_hold_it():
    """The jaws close by the needle and move off without it: the grasp is undone."""
    T_needle, T_jaw0 = needle_between_jaws()
    rng = np.random.default_rng(11)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    assert jaw_holds(Jaw(T_jaw0, 0.06), T_needle, NEEDLE, tr.cfg)
    assert not jaw_holds(Jaw(T_jaw0, 0.9), T_needle, NEEDLE, tr.cfg)      # open jaws hold nothing
    events = []
    for k in range(40):
        lift = make_T(np.eye(3), [0.0, 0.0, 0.0004 * max(0, k - 10)])    # closed at 0, lifting from 10
        o = tr.step(k * DT_NS, {"psm1": Jaw(lift @ T_jaw0, 0.06)}, measure(rng, T_needle, C))
        events.append(o.event)
    assert events[0] == "start" and "ungrasp" in events and o.mode == "rest"
    assert pose_error(o.T_world_needle, T_needle)[0] < 0.3e-3


def test_a_grasp_undone_too_early_is_tried_again_as_the_jaws_carry_the_needle():
    """Jaws reported closed while they still close in on the wire (a real arm's jaw angle is
    degrees off): the needle stays while they move, the grasp is undone; once they have moved
    ``regrasp_travel_m`` from there they are tried again, and as they lift it the needle is held."""
    T_needle, T_jaw0 = needle_between_jaws()
    rng = np.random.default_rng(12)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    events, err = [], []
    for k in range(110):
        side = max(0.0, 0.0018 * (1 - k / 18))            # 1.8 mm beside the wire, closing in over 18 frames
        lift = 0.0004 * max(0, k - 30)                     # on the wire from 18, lifting it from 30
        T_true = make_T(np.eye(3), [0.0, 0.0, lift]) @ T_needle
        o = tr.step(k * DT_NS, {"psm1": Jaw(make_T(np.eye(3), [side, 0.0, lift]) @ T_jaw0, 0.06)},
                    measure(rng, T_true, C))
        events.append(o.event)
        err.append(pose_error(o.T_world_needle, T_true)[0])
    assert "ungrasp" in events[:30] and "grasp:psm1" in events[30:40]
    assert o.mode == "held" and o.holder == "psm1" and max(err[-10:]) < 0.6e-3
    # with the jaws refused until they open (the old rule), the needle was left 13 mm behind


def test_one_view_does_not_settle_a_grasp_trial():
    """A grasp on trial and one view that fits the needle left behind: no single frame's
    evidence settles the trial (``trial_frame_llr``); the views after it do."""
    T_needle, T_jaw0 = needle_between_jaws()
    rng = np.random.default_rng(13)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    for k in range(12):
        lift = make_T(np.eye(3), [0.0, 0.0, 0.0004 * k])
        m = Measurement(T_needle, C) if k == 4 else measure(rng, lift @ T_needle, C)   # frame 4: the old place
        o = tr.step(k * DT_NS, {"psm1": Jaw(lift @ T_jaw0, 0.06)}, m)
        assert o.mode == "held" and o.event != "ungrasp", k
    assert tr.trial is None                    # settled: the needle moves with the jaws


def test_config_refuses_nonsense():
    with pytest.raises(ValueError, match="closed_rad"):
        TrackerConfig(closed_rad=0.5, open_rad=0.4)
    with pytest.raises(ValueError, match="slip_sigma_m"):
        TrackerConfig(slip_sigma_m=-1.0)


def test_the_error_every_measurement_shares_is_not_averaged_away():
    frames = take("pickup", 12)
    rng = np.random.default_rng(12)
    C = stated_covariance(rng)
    common = (0.3e-3, math.radians(1.0))
    C_all = C + np.diag([common[1] ** 2] * 3 + [common[0] ** 2] * 3)
    tr = NeedleTracker(NEEDLE)
    for k, fr in enumerate(frames[:60]):
        m = measure(rng, fr.T_world_needle, C)
        o = tr.step(k * DT_NS, jaws_of(fr), Measurement(m.T_world_needle, C_all, None, *common))
    # the track's position variance never drops below the shared part, however many frames
    assert np.linalg.eigvalsh(o.covariance[3:, 3:]).min() >= common[0] ** 2
    assert np.linalg.eigvalsh(o.covariance[:3, :3]).min() >= common[1] ** 2


def test_the_bench_prints_its_figures(tmp_path, capsys):
    import json

    from common.bench.tracker_bench import main
    assert main(["--takes", "4", "--json", str(tmp_path / "t.json")]) == 0
    res = json.loads((tmp_path / "t.json").read_text())
    for run in ("seen", "hidden"):
        r = res[run]
        assert r["swaps"] == 0 and r["in_hand"]["wrong_holder"] == 0 and r["position_mm"] < 0.5
    assert "T_jaw_needle from the 10th held frame" in capsys.readouterr().out


def test_the_bench_s_replay_refuses_what_it_cannot_use(tmp_path, capsys):
    """``--replay`` needs ``--dataset``; a recording that did not finish, a folder that is not a
    dataset and a param the tracker does not have are clear errors."""
    from common.bench.tracker_bench import main
    rec = tmp_path / "rec.jsonl"
    rec.write_text('{"kind": "pose", "seq": 0}\n')                      # no end line: unfinished
    assert main(["--replay", str(rec)]) == 2
    assert "go together" in capsys.readouterr().err
    assert main(["--replay", str(rec), "--dataset", str(tmp_path)]) == 2
    assert "dataset.yaml: file missing" in capsys.readouterr().err
    assert main(["--replay", str(rec), "--dataset", str(tmp_path), "--tracker-param", "no_such=1"]) == 2
    assert "no_such" in capsys.readouterr().err


def test_a_settled_track_outlasts_a_run_of_biased_fits_and_restarts_only_after_reset_after_held():
    """A needle at rest for a second: the jaws or the tissue hiding part of its arc can bias the
    fit for many frames in a row; three rejected do not restart the track, ``reset_after_held`` do."""
    frames = take("pickup", 8)         # grasped at frame 79
    rng = np.random.default_rng(8)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    settle = TrackerConfig().reset_after_held + 2
    assert not any(holds for fr in frames[:settle + 30] for _T, _jaw, holds in fr.instruments.values())
    for k in range(settle):
        o = tr.step(k * DT_NS, jaws_of(frames[k]), measure(rng, frames[k].T_world_needle, C))
    assert o.mode == "rest"
    events = []
    for k in range(settle, settle + TrackerConfig().reset_after_held):
        o = tr.step(k * DT_NS, jaws_of(frames[k]), Measurement(make_T(np.eye(3), [0.004, 0, 0]) @ frames[k].T_world_needle, C))
        events.append(o.event)
        if o.event != "restart":
            assert o.used is False and pose_error(o.T_world_needle, frames[k].T_world_needle)[0] < 0.6e-3
    assert events.count("restart") == 1 and events[-1] == "restart"


def test_no_track_starts_from_a_partial_view_alone():
    """A pose fitted to a short part of its arc (the jaws hide the rest) can be tens of degrees
    off and still fit: the track starts only from one fitted to ``start_arc_seen`` of the arc."""
    frames = take("pickup", 8)
    rng = np.random.default_rng(8)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    for k in range(5):
        m = measure(rng, frames[k].T_world_needle, C)
        assert tr.step(k * DT_NS, jaws_of(frames[k]), Measurement(m.T_world_needle, C, arc_seen=0.3)) is None
    o = tr.step(5 * DT_NS, jaws_of(frames[5]), Measurement(measure(rng, frames[5].T_world_needle, C).T_world_needle, C, arc_seen=0.8))
    assert o is not None and o.event == "start"


def test_a_run_of_partial_views_that_agree_starts_the_track():
    """Partial views fitted to at least ``start_run_arc_seen`` of the arc are tracked apart; the
    track starts once ``start_run`` of them in a row agree, and one far off starts the run again."""
    frames = take("pickup", 8)
    rng = np.random.default_rng(9)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE, TrackerConfig(start_run=10))
    far = make_T(rotvec_to_R([0.0, 0.0, math.radians(60)]), [0.0, 0.0, 0.0])
    out = []
    for k in range(30):
        T = measure(rng, frames[k].T_world_needle, C).T_world_needle
        if k == 5:
            T = T @ far                              # a fit 60 deg off: the run starts again
        out.append(tr.step(k * DT_NS, jaws_of(frames[k]), None if k == 8 else Measurement(T, C, arc_seen=0.5)))
    # the run: 0..4, broken at 5 (far) and at 6 (far from 5), then 6..16 less frame 8 (no pose)
    assert all(o is None for o in out[:16])
    assert out[16] is not None and out[16].event == "start"
    assert all(o is not None for o in out[16:])
    pos, rot = errors(frames[16:], out[16:])
    assert pos.max() < 2.0 and rot.max() < 5.0
    lone = NeedleTracker(NEEDLE, TrackerConfig(start_run=10))
    assert all(lone.step(k * DT_NS, jaws_of(frames[k]), Measurement(
        measure(rng, frames[k].T_world_needle, C).T_world_needle, C, arc_seen=0.3)) is None for k in range(30))


def test_a_measurement_counts_for_a_fraction_of_a_frame_where_consecutive_fits_err_together():
    C = np.diag([1e-4] * 3 + [1e-8] * 3)
    m = Measurement(np.eye(4), C, common_sigma_m=1e-5, common_sigma_rad=1e-3)
    assert np.allclose(m.own(5.0).covariance, 5.0 * m.own().covariance)
    assert TrackerConfig().corr_frames == 5.0
    with pytest.raises(ValueError, match="corr_frames"):
        TrackerConfig(corr_frames=0.5)


def test_fits_that_err_together_over_frames_are_stated_honestly_with_corr_frames():
    """Consecutive fits of a held needle share their error (the same jaws hide the same part):
    a bias drawn anew every 10 frames. Counting each as a whole frame's news makes the track
    too sure; ``corr_frames`` (the default) keeps its NEES near chi-square(6)'s median."""
    frames = take("handover", 6)
    C = stated_covariance(np.random.default_rng(6))
    medians = {}
    for corr in (1.0, 5.0):
        rng = np.random.default_rng(60)
        tr, out = NeedleTracker(NEEDLE, TrackerConfig(corr_frames=corr)), []
        for k, fr in enumerate(frames):
            if k % 10 == 0:
                bias = rng.multivariate_normal(np.zeros(6), C)
            T = retract(fr.T_world_needle, bias + rng.multivariate_normal(np.zeros(6), 0.2 * C))
            out.append(tr.step(k * DT_NS, jaws_of(fr), Measurement(T, 1.2 * C)))
        medians[corr] = float(np.median(nees(frames, out)[20:]))
    assert medians[5.0] < medians[1.0] and medians[5.0] < 9.0, medians


def test_one_camera_s_views_weigh_no_grasp_trial():
    """The same jaws that leave the needle behind, seen by one camera only: its views update the
    track but never undo (or settle) the grasp: one view cannot tell near from far."""
    T_needle, T_jaw0 = needle_between_jaws()
    rng = np.random.default_rng(11)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    events = [tr.step(0, {"psm1": Jaw(T_jaw0, 0.06)}, measure(rng, T_needle, C)).event]
    for k in range(1, 40):
        lift = make_T(np.eye(3), [0.0, 0.0, 0.0004 * max(0, k - 10)])
        m = dataclasses.replace(measure(rng, T_needle, C), one_camera=True)
        events.append(tr.step(k * DT_NS, {"psm1": Jaw(lift @ T_jaw0, 0.06)}, m).event)
    assert events[0] == "start" and "ungrasp" not in events and tr.trial is not None and tr.mode == "held"


def test_a_track_its_measurements_disagree_with_says_so():
    """A needle at rest, then measured 5 mm away in partial views (which may not restart the track):
    from the reset_after-th rejection on the track is disputed, flagged with a covariance that spans
    the measurements, until one is taken again."""
    rng = np.random.default_rng(3)
    C = stated_covariance(rng)
    tr = NeedleTracker(NEEDLE)
    T0 = make_T(np.eye(3), [0.0, 0.0, 0.1])
    for k in range(40):
        assert not tr.step(k * DT_NS, {}, Measurement(T0, C, 0.99)).disputed
    T1 = make_T(np.eye(3), [0.005, 0.0, 0.1])
    outs = [tr.step((40 + k) * DT_NS, {}, Measurement(T1, C, 0.99, arc_seen=0.4)) for k in range(5)]
    assert [o.used for o in outs] == [False] * 5 and [o.disputed for o in outs] == [False, False, True, True, True]
    assert pose_nees(outs[-1].T_world_needle, outs[-1].covariance, T1) < 2.0      # spans the measured pose
    assert not tr.step(45 * DT_NS, {}, Measurement(T0, C, 0.99)).disputed          # taken again: settled
