"""Frame-to-frame refinement (common/geometry/refine_tracking.py): warm starts in a video, the cold path
whenever the warm fit is not as good."""
import numpy as np
import pytest

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.oracle import Oracle, random_needle_pose
from common.geometry.pnp import refine_starts
from common.geometry.refine import ArcObservation, DenseRefiner
from common.geometry.refine_tracking import TrackingConfig, TrackingRefiner
from common.geometry.transforms import make_T, pose_error, rotvec_to_R, transform_points

RIG = StereoRig.default()
MODEL = NeedleModel()
FRAME_NS = 33_333_333


def video(n, seed=5, step_mm=0.3, step_deg=0.5, max_tilt_deg=60.0):
    """n frames of a needle drifting by about step_mm / step_deg per frame: (T, uv, sc, obs)."""
    rng = np.random.default_rng(seed)
    oracle = Oracle(noise_px=0.5, seed=seed)
    T = random_needle_pose(rng, RIG, MODEL, max_tilt_rad=np.radians(max_tilt_deg))
    axis, way = rng.normal(size=3), rng.normal(size=3)
    dR = rotvec_to_R(np.radians(step_deg) * axis / np.linalg.norm(axis))
    dt = 1e-3 * step_mm * way / np.linalg.norm(way)
    frames = []
    for i in range(n):
        frames.append((T, *oracle.stereo_arcs(RIG, T, MODEL, i)))
        T = make_T(dR @ T[:3, :3], T[:3, 3] + dt)
    return frames


def cold(uv, sc, obs, refiner):
    return refiner.refine(obs, refine_starts(uv, RIG, MODEL.keypoints(), sc))


@pytest.fixture()
def refiner():
    return DenseRefiner(RIG, MODEL)


def test_a_video_is_tracked_warm_and_as_accurately_as_cold(refiner):
    tracker = TrackingRefiner(refiner, MODEL.keypoints())
    warm = []
    for i, (T, uv, sc, obs) in enumerate(video(12)):
        res = tracker.refine(uv, sc, obs, i * FRAME_NS)
        warm.append(tracker.last_warm)
        ref = cold(uv, sc, obs, refiner)
        dt, dr = pose_error(res.T_ecm_needle, ref.T_ecm_needle)
        assert dt < 1e-4 and np.degrees(dr) < 0.1, i       # the same minimum as the cold fit
        dt, dr = pose_error(res.T_ecm_needle, T)
        assert dt < 3e-3 and np.degrees(dr) < 3.0, i
    assert not warm[0] and sum(warm) >= 9


def test_a_jump_a_gap_and_cold_every_fall_back_to_the_cold_fit(refiner):
    tracker = TrackingRefiner(refiner, MODEL.keypoints(), config=TrackingConfig(cold_every=3))
    a, b = video(2, seed=1), video(1, seed=2)     # b: another needle pose altogether
    tracker.refine(*a[0][1:], 0)
    res = tracker.refine(*b[0][1:], FRAME_NS)
    assert not tracker.last_warm
    assert np.allclose(res.T_ecm_needle, cold(*b[0][1:], refiner).T_ecm_needle, atol=1e-12)
    tracker.reset()
    tracker.refine(*a[0][1:], 0)
    tracker.refine(*a[1][1:], int(0.5e9))          # half a second later: too old to start from
    assert not tracker.last_warm
    frames = video(6, seed=3)
    tracker.reset()
    kinds = []
    for i, (T, uv, sc, obs) in enumerate(frames):
        tracker.refine(uv, sc, obs, i * FRAME_NS)
        kinds.append(tracker.last_warm)
    assert kinds == [False, True, True, True, False, True]


def test_swapped_tip_and_tail_are_not_tracked_into_a_wrong_pose(refiner):
    tracker = TrackingRefiner(refiner, MODEL.keypoints())
    (T0, uv0, sc0, obs0), (T1, uv1, sc1, obs1) = video(2, seed=4)
    tracker.refine(uv0, sc0, obs0, 0)
    # a detector that mistakes the tail for the tip: keypoints and centreline reversed
    uv1 = {k: v[::-1] for k, v in uv1.items()}
    obs1 = {k: ArcObservation(o.uv[::-1], o.scores[::-1], o.centreline[::-1], o.centreline_w[::-1])
            for k, o in obs1.items()}
    res = tracker.refine(uv1, sc1, obs1, FRAME_NS)
    assert not tracker.last_warm
    assert np.allclose(res.T_ecm_needle, cold(uv1, sc1, obs1, refiner).T_ecm_needle, atol=1e-12)


def test_tracking_off_and_bad_config():
    tracker = TrackingRefiner(DenseRefiner(RIG, MODEL), MODEL.keypoints(), config=TrackingConfig(enabled=False))
    for i, (T, uv, sc, obs) in enumerate(video(3)):
        tracker.refine(uv, sc, obs, i * FRAME_NS)
        assert not tracker.last_warm
    with pytest.raises(ValueError, match="cold_every"):
        TrackingConfig(cold_every=0)


def test_a_warm_frame_leaves_out_the_mirror_only_when_it_was_far_worse(refiner):
    """mirror_chi2: the previous frame's competitor decides whether a warm frame refines the
    mirror image (and the other solutions) too; ambiguity is still found near the margin."""
    calls = []
    real = refiner.refine

    def spy(obs, cands, mirrors=None, support_normal=None, expected=None):
        calls.append((len(cands), mirrors))
        return real(obs, cands, mirrors, support_normal, expected)

    refiner.refine = spy
    frames = video(3, seed=4)
    for mirror_chi2, expect in ((0.0, (1, False)), (np.inf, (None, None))):
        tracker = TrackingRefiner(refiner, MODEL.keypoints(), config=TrackingConfig(mirror_chi2=mirror_chi2))
        calls.clear()
        first = tracker.refine(*frames[0][1:], 0)
        res = tracker.refine(*frames[1][1:], FRAME_NS)
        assert tracker.last_warm
        n, mirrors = calls[-1]
        if expect[0] is None:                       # every previous solution, mirrors added
            assert n == len(first.candidates) and mirrors is None and np.isfinite(res.competitor_chi2)
        else:                                       # the previous pose alone
            assert (n, mirrors) == expect and res.competitor_chi2 == np.inf
        dt, dr = pose_error(res.T_ecm_needle, cold(*frames[1][1:], refiner).T_ecm_needle)
        assert dt < 1e-4 and np.degrees(dr) < 0.1


def hidden(frame, sure=(0,), hide_from=0.5, kp_err_px=3.0, seed=0):
    """A needle mostly hidden (as in an instrument's jaws): only the keypoints ``sure`` scored
    0.9, the others 0.3 and ``kp_err_px`` off, the centreline from ``hide_from`` of its length
    on (towards E) unseen."""
    rng = np.random.default_rng(seed)
    T, uv, sc, obs = frame
    uv2, sc2, obs2 = {}, {}, {}
    for cam, o in obs.items():
        s = np.full(5, 0.3)
        s[list(sure)] = 0.9
        u = o.uv + np.where(s[:, None] < 0.5, rng.normal(0, kp_err_px, (5, 2)), 0.0)
        w = np.asarray(o.centreline_w, float).copy()
        w[int(hide_from * len(w)):] = 0.0
        uv2[cam], sc2[cam] = u, s
        obs2[cam] = ArcObservation(u, s, o.centreline, w)
    return T, uv2, sc2, obs2


def test_a_mostly_hidden_needle_is_posed_from_its_arc_and_one_sure_end(refiner):
    """Fewer than 4 sure keypoints: started from all of them both ways round, kept when sure."""
    from common.geometry.observations import NoPose
    T, uv, sc, obs = hidden(video(1, seed=11)[0])
    with pytest.raises(NoPose) as e:
        refine_starts(uv, RIG, MODEL.keypoints(), sc)
    assert e.value.reason == "too_few_points"
    res = TrackingRefiner(refiner, MODEL.keypoints()).refine(uv, sc, obs, 0)
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert not res.ambiguous and dt < 2e-3 and np.degrees(dr) < 5.0, (dt, np.degrees(dr))
    # the old behaviour, and a fit held to a residual it cannot meet
    for cfg in (TrackingConfig(unsure_starts=False), TrackingConfig(unsure_max_rms_px=0.01)):
        with pytest.raises(NoPose) as e:
            TrackingRefiner(refiner, MODEL.keypoints(), config=cfg).refine(uv, sc, obs, 0)
        assert e.value.reason == ("too_few_points" if not cfg.unsure_starts else "unsure_keypoints")
    with pytest.raises(ValueError, match="unsure_max_rms_px"):
        TrackingConfig(unsure_max_rms_px=0.0)


def test_a_needle_without_a_sure_end_gives_no_pose(refiner):
    """No sure keypoint: the whole arc fits its tip-for-tail turned pose exactly as well (the arc
    is symmetric about C), so no pose rather than a coin flip."""
    from common.geometry.observations import NoPose
    T, uv, sc, obs = hidden(video(1, seed=7)[0], sure=(), hide_from=1.0)
    tracker = TrackingRefiner(refiner, MODEL.keypoints())
    with pytest.raises(NoPose) as e:
        tracker.refine(uv, sc, obs, 0)
    assert e.value.reason == "unsure_keypoints" and "competing_candidates" in str(e.value)
    assert tracker._prev is None


def test_a_mostly_hidden_needle_is_tracked_warm_under_the_same_test(refiner):
    from common.geometry.observations import NoPose
    frames = [hidden(f, seed=i) for i, f in enumerate(video(8, seed=11))]
    tracker = TrackingRefiner(refiner, MODEL.keypoints())
    warm = []
    for i, (T, uv, sc, obs) in enumerate(frames):
        res = tracker.refine(uv, sc, obs, i * FRAME_NS)
        warm.append(tracker.last_warm)
        dt, dr = pose_error(res.T_ecm_needle, T)
        assert not res.ambiguous and dt < 3e-3 and np.degrees(dr) < 5.0, (i, dt, np.degrees(dr))
    # (a warm fit that finds a competitor within the margin goes cold: 2 of these 7)
    assert not warm[0] and sum(warm) >= 5
    # switched off: neither cold nor warm (after a frame with every keypoint sure)
    off = TrackingRefiner(refiner, MODEL.keypoints(), config=TrackingConfig(unsure_starts=False))
    sure = video(2, seed=11)
    off.refine(*sure[0][1:], 0)
    with pytest.raises(NoPose) as e:
        off.refine(*hidden(sure[1])[1:], FRAME_NS)
    assert e.value.reason == "too_few_points"


def test_a_warm_frame_whose_sure_keypoint_cannot_tell_the_ends_apart_gives_no_pose(refiner):
    """Only C sure (the arc's middle, which the end-for-end turn keeps in place): the turned
    pose fits as well, warm as cold, so no pose rather than an unambiguous-looking one."""
    from common.geometry.observations import NoPose
    from common.geometry.refine import tip_for_tail
    frames = video(3, seed=11)
    T = frames[0][0]
    assert np.allclose(tip_for_tail(tip_for_tail(T, MODEL), MODEL), T)
    P = MODEL.keypoints()
    turned = tip_for_tail(T, MODEL)
    assert np.allclose(transform_points(turned, P), transform_points(T, P)[::-1])
    tracker = TrackingRefiner(refiner, MODEL.keypoints())
    tracker.refine(*frames[0][1:], 0)                 # every keypoint sure: posed cold
    for i in (1, 2):
        _, uv, sc, obs = hidden(frames[i], sure=(2,), hide_from=1.0, seed=i)
        with pytest.raises(NoPose) as e:
            tracker.refine(uv, sc, obs, i * FRAME_NS)
        assert e.value.reason == "unsure_keypoints"
