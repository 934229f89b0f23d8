"""Evaluation library on synthetic messages: known errors in, the same errors out."""
import json
from dataclasses import replace

import numpy as np
import pytest

from common.evaluation.overlays import select_overlay_frames
from common.evaluation.report import report_markdown, write_outputs
from common.evaluation.collect import Collected, evaluate
from common.evaluation.metrics import keypoint_errors_2d, last_steps, pearson, pose_nees, summary
from common.evaluation.results import RESULT_KEYS, build_results, check_results, to_jsonable
from common.methods import REPORTED_METHODS as METHODS
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points
from common.runtime.messages import (
    Calibration,
    EndOfStream,
    GroundTruth,
    Keypoints,
    NodeStats,
    Points3D,
    PoseEstimate,
    decode,
    encode,
)

RIG = StereoRig.default(480, 270)
NEEDLE = NeedleModel()


def random_rotation(rng):
    v = rng.normal(size=3)
    return rotvec_to_R(v / np.linalg.norm(v) * rng.uniform(0, np.pi))


def needle_in_view(rng, dist):
    """A needle pose in the ECM frame ``dist`` m in front of the endoscope (along -z_ecm),
    tilted at most 60 deg from facing the cameras."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = np.diag([1.0, -1.0, -1.0]) @ rotvec_to_R(axis * rng.uniform(0, np.radians(60)))
    return make_T(R, [rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), -dist])


def perturb(T, d_m, angle_rad, rng):
    """T moved by exactly d_m and rotated by exactly angle_rad (about a random axis)."""
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    return make_T(T[:3, :3] @ rotvec_to_R(a * angle_rad), T[:3, 3] + u * d_m)


def synthetic(n_seq=4, steps=3, pos_err=0.001, ang_err=np.radians(2.0), px_noise=0.0,
              p3_err=0.0005, drop=(), seed=0):
    """A Collected as the evaluator would gather it, with exact known errors.

    Every single-frame method is off by ``pos_err`` m and ``ang_err`` rad, multiview by half of
    that; detector keypoints are the truth plus ``px_noise`` px (exact distance); triangulated
    points are off by ``p3_err`` m. ``drop``: (method, seq) pairs with no pose.
    """
    rng = np.random.default_rng(seed)
    col = Collected()
    col.add_calib(Calibration(0, np.array([RIG.left.width, RIG.left.height]), RIG.to_dict(),
                              NEEDLE.to_dict()))
    seq = 0
    for sq in range(n_seq):
        T_world_needle = make_T(random_rotation(rng), rng.normal(size=3) * 0.05)
        for st in range(steps):
            T_ecm_needle = needle_in_view(rng, rng.uniform(0.10, 0.25))
            T_world_ecm = T_world_needle @ inv_T(T_ecm_needle)
            kps, vis = {}, {}
            for cam in ("left", "right"):
                kps[cam] = RIG[cam].project_from_ecm(transform_points(T_ecm_needle, NEEDLE.keypoints()))
                vis[cam] = np.ones(5, bool)
            gt = GroundTruth(seq, 1000 + seq, sq, st, None, T_world_ecm, T_world_needle, kps, vis)
            col.add_truth(decode(encode(gt), GroundTruth), gt.stamp_ns)   # the truth comes when the frame is sent
            for cam in ("left", "right"):
                d = rng.normal(size=(5, 2))
                d = d / np.linalg.norm(d, axis=1, keepdims=True) * px_noise
                col.add_keypoints(Keypoints(cam, seq, gt.stamp_ns, True, kps[cam] + d, np.ones(5),
                                            1.0, None, "oracle"), 0)
            truth_pts = transform_points(T_ecm_needle, NEEDLE.keypoints())
            off = rng.normal(size=(5, 3))
            off = off / np.linalg.norm(off, axis=1, keepdims=True) * p3_err
            col.add_points3d(Points3D(seq, gt.stamp_ns, truth_pts + off, np.ones(5, bool)), 0)
            for m in ("pnp_average", "pnp_joint", "triangulation", "multiview"):
                if (m, seq) in drop:
                    continue
                scale = 0.5 if m == "multiview" else 1.0
                T = perturb(T_ecm_needle, pos_err * scale, ang_err * scale, rng)
                col.add_pose(m, PoseEstimate(seq, gt.stamp_ns, m, T, n_views=st + 1),
                             gt.stamp_ns + 20_000_000)
            seq += 1
    col.add_eos(EndOfStream(seq, 0))
    col.add_stats(NodeStats("epnp", "epnp", 1, 0, 1.0, {}, {}, 1.5, 3.0))
    return col


def test_summary_and_pearson():
    s = summary([1.0, 2.0, np.nan, 6.0])
    assert s == pytest.approx({"mean": 3.0, "median": 2.0, "std": np.std([1, 2, 6]), "max": 6.0})
    assert summary([]) == {"mean": None, "median": None, "std": None, "max": None}
    assert pearson([1, 2, 3, 4], [2, 4, 6, 8.5]) > 0.99
    assert pearson([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    assert pearson([1, 1, 1, 1], [1, 2, 3, 4]) is None
    assert pearson([1, 2], [1, 2]) is None


def test_known_pose_errors_are_recovered():
    col = synthetic(pos_err=0.001, ang_err=np.radians(2.0))
    ev = evaluate(col)
    for m in ("pnp_average", "pnp_joint", "triangulation"):
        t = ev.pose[m]
        assert len(t["seqs"]) == 12
        np.testing.assert_allclose(t["position_m"], 0.001, rtol=1e-9)
        np.testing.assert_allclose(np.degrees(t["orientation_rad"]), 2.0, rtol=1e-6)
    mv = ev.pose["multiview"]
    assert mv["seqs"] == [2, 5, 8, 11]  # the last step of each sequence
    np.testing.assert_allclose(mv["position_m"], 0.0005, rtol=1e-9)
    np.testing.assert_allclose(np.degrees(mv["orientation_rad"]), 1.0, rtol=1e-6)
    assert np.all((mv["distance_m"] > 0.099) & (mv["distance_m"] < 0.26))


def test_zero_error_inputs_give_zero():
    col = synthetic(pos_err=0.0, ang_err=0.0, px_noise=0.0, p3_err=0.0)
    res = build_results(col, dataset="d", detector="oracle")
    for m in METHODS:
        assert res["pose"][m]["position_mm"]["max"] < 1e-9
        assert res["pose"][m]["orientation_deg"]["max"] < 1e-5
    assert res["keypoints_2d_px"]["all"]["mean"] < 1e-9
    assert res["keypoints_3d_mm"]["all"]["mean"] < 1e-9
    assert res["correlation_2d_3d"]["all"] is None  # no spread: no correlation


def test_keypoint_and_point_errors():
    col = synthetic(px_noise=0.75, p3_err=0.0005)
    res = build_results(col, dataset="d", detector="oracle")
    for k in ("A", "B", "C", "D", "E", "all"):
        assert res["keypoints_2d_px"][k]["mean"] == pytest.approx(0.75, rel=1e-9)
        assert res["keypoints_2d_px"][k]["std"] == pytest.approx(0.0, abs=1e-9)
        assert res["keypoints_3d_mm"][k]["mean"] == pytest.approx(0.5, rel=1e-9)
    assert res["keypoints_2d_px"]["all"]["n"] == 12 * 2 * 5
    assert res["detection_rate"] == 1.0


def test_invisible_and_missing_keypoints_are_left_out():
    uv_true = np.arange(10.0).reshape(5, 2)
    kp = Keypoints("left", 0, 0, True, uv_true + [3.0, 4.0], np.ones(5), 1.0)
    kp.uv[1] = np.nan
    err = keypoint_errors_2d(kp, uv_true, [True, True, True, False, True])
    np.testing.assert_allclose(err, [5, np.nan, 5, np.nan, 5])
    assert np.all(np.isnan(keypoint_errors_2d(Keypoints.not_found("left", 0, 0, "x", "r"), uv_true)))


def test_failures_are_counted():
    drop = {("pnp_joint", 0), ("pnp_joint", 4), ("multiview", 5), ("triangulation", 1)}
    col = synthetic(drop=drop)
    del col.keypoints[("right", 3)]
    res = build_results(col, dataset="d", detector="oracle")
    assert res["pose"]["pnp_joint"]["n"] == 10 and res["pose"]["pnp_joint"]["failures"] == 2
    assert res["pose"]["multiview"]["n"] == 3 and res["pose"]["multiview"]["expected"] == 4
    assert res["failure_rate"]["multiview"] == pytest.approx(0.25)
    assert res["pose"]["pnp_average"]["failure_rate"] == 0.0
    assert res["detection_rate"] == pytest.approx(23 / 24)


def test_no_pose_at_all_still_gives_typed_results():
    col = synthetic(n_seq=1, steps=2)
    col.poses.clear()
    col.arrivals_ns.clear()
    res = to_jsonable(build_results(col, dataset="d", detector="learned"))
    assert check_results(res) == []
    assert res["pose"]["multiview"]["n"] == 0
    assert res["pose"]["pnp_joint"]["position_mm"]["mean"] is None
    assert res["timing"]["throughput_hz"] is None


@pytest.mark.slow
def test_results_keys_and_types(tmp_path):
    col = synthetic(px_noise=0.3)
    col.add_pose("refined", PoseEstimate(0, 1000, "refined", col.truths[0].T_world_needle), 1)
    res = write_outputs(tmp_path, col, dataset="data/x", detector="oracle")
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert on_disk == res
    for k in RESULT_KEYS:
        assert k in on_disk
    assert check_results(on_disk) == []
    assert isinstance(on_disk["frames"], int) and on_disk["frames"] == 12
    assert set(on_disk["pose"]) == {*METHODS, "refined"}
    assert on_disk["pose"]["refined"]["n"] == 1 and on_disk["pose"]["refined"]["expected"] == 12
    t = on_disk["timing"]
    assert t["final_method"] == "multiview"
    assert t["latency_ms"]["p50"] == pytest.approx(20.0)
    assert t["per_node_ms"] == {"epnp": 1.5}
    assert (tmp_path / "error_vs_distance.png").stat().st_size > 10_000
    rows = (tmp_path / "per_frame.csv").read_text().splitlines()
    assert len(rows) == 13 and rows[0].startswith("seq,sequence,step,distance_mm")
    assert rows[3].split(",")[rows[0].split(",").index("multiview_mm")] == "0.5000"   # last step
    assert rows[1].split(",")[rows[0].split(",").index("multiview_mm")] == ""         # not scored
    assert len(list((tmp_path / "overlays").glob("*.png"))) >= 3
    md = (tmp_path / "report.md").read_text()
    assert "Table II" in md and "Table III" in md and "2.26 / 6.74" in md and "5.58" in md


def test_check_results_catches_wrong_types():
    res = to_jsonable(build_results(synthetic(n_seq=1), dataset="d", detector="oracle"))
    assert check_results(res) == []
    bad = json.loads(json.dumps(res))
    bad["frames"] = "12"
    del bad["pose"]["multiview"]["position_mm"]["median"]
    bad["timing"]["latency_ms"] = None
    problems = check_results(bad)
    assert any(p.startswith("frames") for p in problems)
    assert any("pose.multiview.position_mm.median" in p for p in problems)
    assert any("timing.latency_ms" in p for p in problems)


def test_last_steps_and_overlay_choice():
    col = synthetic(n_seq=3, steps=4, drop={("pnp_joint", 6)})
    truths = col.truths
    assert last_steps(truths) == [3, 7, 11]
    moving = {s: replace(gt, needle_at_rest=False) if gt.sequence == 1 else gt for s, gt in truths.items()}
    assert last_steps(moving) == [3, 4, 5, 6, 7, 11]       # a moving take: every frame a view of its own
    ev = evaluate(col)
    chosen = dict(select_overlay_frames(ev))
    assert chosen[6] == "nopose_pnp_joint"
    assert any(v.startswith("worst_multiview") for v in chosen.values())


def test_report_lists_every_method():
    res = to_jsonable(build_results(synthetic(n_seq=2), dataset="d", detector="classical"))
    md = report_markdown(res)
    for m in METHODS:
        assert f"| {m} |" in md
    assert "| all |" in md


def test_nees_of_a_stated_covariance():
    """The truth as a left increment of the estimate, in the covariance's metric."""
    T_true = make_T(rotvec_to_R([0.1, -0.2, 0.3]), [0.01, 0.02, 0.15])
    d = np.array([0.02, 0.0, 0.0, 0.0, 0.001, 0.0])           # 20 mrad about x, 1 mm along y
    T_est = make_T(rotvec_to_R(-d[:3]) @ T_true[:3, :3], T_true[:3, 3] - d[3:])
    cov = np.diag([0.01 ** 2] * 3 + [0.001 ** 2] * 3)
    assert pose_nees(T_est, cov, T_true) == pytest.approx(2.0 ** 2 + 1.0 ** 2, rel=1e-6)
    assert np.isnan(pose_nees(T_est, None, T_true)) and np.isnan(pose_nees(T_est, np.eye(3), T_true))
    # in the tables: a method whose poses carry covariances gets its NEES, the others none
    col = synthetic(pos_err=0.001, ang_err=0.0)
    for p in col.poses["pnp_joint"].values():
        p.covariance, p.ambiguous = np.diag([1e-4] * 3 + [0.001 ** 2] * 3), False
    res = build_results(col, dataset="d", detector="oracle")
    assert res["pose"]["pnp_joint"]["nees"]["median"] == pytest.approx(1.0, rel=1e-6)
    assert res["pose"]["pnp_joint"]["ambiguous_share"] == 0.0 and "nees" not in res["pose"]["triangulation"]
    assert check_results(res) == [] and "| pnp_joint | 1.0 | 0% | 0% |" in report_markdown(res)


@pytest.mark.slow
def test_the_nees_picture_is_drawn_when_covariances_are_stated(tmp_path):
    from common.evaluation.report import chi2_6_cdf
    assert chi2_6_cdf(5.348) == pytest.approx(0.5, abs=1e-3) and chi2_6_cdf(16.81) == pytest.approx(0.99, abs=1e-3)
    col = synthetic(pos_err=0.001, ang_err=0.0)
    write_outputs(tmp_path / "none", col, dataset="d", detector="oracle")
    assert not (tmp_path / "none" / "nees.png").exists()      # no method states a covariance
    for p in col.poses["pnp_joint"].values():
        p.covariance, p.ambiguous = np.diag([1e-4] * 3 + [0.001 ** 2] * 3), False
    write_outputs(tmp_path / "cov", col, dataset="d", detector="oracle")
    assert (tmp_path / "cov" / "nees.png").stat().st_size > 10_000
    assert "(nees.png)" in (tmp_path / "cov" / "report.md").read_text()
    for p in col.poses["pnp_joint"].values():
        p.covariance = None
    write_outputs(tmp_path / "cov", col, dataset="d", detector="oracle")   # the same folder again
    assert not (tmp_path / "cov" / "nees.png").exists()


def test_pose_table_scores_the_unflagged_poses_apart():
    from types import SimpleNamespace
    from common.evaluation.collect import pose_table
    t = {"seqs": [0, 1, 2, 3], "position_m": np.array([0.001, 0.002, 0.010, np.nan]),
         "orientation_rad": np.radians([1.0, 3.0, 179.0, np.nan]), "distance_m": np.full(4, 0.15),
         "n_views": np.ones(4), "nees": np.array([4.0, 6.0, 1.0, np.nan]),
         "ambiguous": np.array([0.0, 0.0, 1.0, np.nan])}
    d = pose_table(SimpleNamespace(pose={"refined": t}))["refined"]
    assert d["n"] == 3 and d["end_for_end"] == {"share": pytest.approx(1 / 3), "confident_share": 0.0}
    assert d["sure"]["n"] == 2
    assert d["sure"]["position_mm"]["mean"] == pytest.approx(1.5)
    assert d["sure"]["orientation_deg"]["mean"] == pytest.approx(2.0)


def test_pose_table_sets_the_stated_end_identity_against_the_turned_poses():
    from types import SimpleNamespace

    from common.evaluation.report import _tip
    from common.evaluation.collect import pose_table
    t = {"seqs": [0, 1, 2, 3, 4], "position_m": np.array([0.001, 0.002, 0.001, 0.001, np.nan]),
         "orientation_rad": np.radians([1.0, 179.0, 2.0, 1.0, np.nan]), "distance_m": np.full(5, 0.15),
         "n_views": np.ones(5), "nees": np.array([4.0, 1.0, 5.0, 3.0, np.nan]),
         "ambiguous": np.array([1.0, 1.0, 0.0, 0.0, np.nan]),
         "end_identity": np.array([0.6, 0.6, 0.99, np.nan, 0.9])}
    d = pose_table(SimpleNamespace(pose={"refined": t}))["refined"]
    assert d["end_for_end"] == {"share": pytest.approx(1 / 4), "confident_share": 0.0}
    t["end_identity"][1] = 0.97          # flagged (a mirror image), but sure of its tip: confident
    assert pose_table(SimpleNamespace(pose={"refined": t}))["refined"]["end_for_end"]["confident_share"] == 0.25
    t["end_identity"][1] = 0.6
    e = d["end_identity"]
    assert e["all"] == {"n": 3, "stated": pytest.approx((0.4 + 0.4 + 0.01) / 3), "measured": pytest.approx(1 / 3)}
    assert e["flagged"] == {"n": 2, "stated": pytest.approx(0.4), "measured": pytest.approx(0.5)}
    assert _tip({"end_identity": e}) == "all 27.0% / 33.3%; flagged 40.0% / 50.0%"


def test_pose_table_counts_confident_swaps_undecided_tips_the_nearer_reading_and_sure_and_right():
    from types import SimpleNamespace

    from common.evaluation.collect import pose_table
    # 0: undecided and turned (its other reading 1 deg off); 1: undecided, right; 2: sure, right;
    # 3: sure but 3 mm off; 4: turned and unflagged: a confident swap; 5: no pose
    t = {"seqs": list(range(6)), "position_m": np.array([0.001, 0.001, 0.001, 0.003, 0.001, np.nan]),
         "orientation_rad": np.radians([178.0, 2.0, 1.0, 1.0, 177.0, np.nan]),
         "orientation_turned_rad": np.radians([1.0, 178.0, 179.0, 179.0, 3.0, np.nan]),
         "distance_m": np.full(6, 0.15), "n_views": np.ones(6), "nees": np.full(6, 4.0),
         "ambiguous": np.array([1.0, 1.0, 0.0, 0.0, 0.0, np.nan]),
         "end_identity": np.array([0.6, 0.7, 0.99, 0.98, 0.97, np.nan])}
    d = pose_table(SimpleNamespace(pose={"refined": t}))["refined"]
    assert d["confident_swaps"] == 1
    assert d["undecided"] == {"n": 2, "share": pytest.approx(2 / 5), "turned": 1}
    # modulo the turn the undecided turned pose counts 1 deg, the confident swap keeps its 177
    assert d["modulo_turn"]["orientation_deg"]["max"] == pytest.approx(177.0)
    assert d["modulo_turn"]["orientation_deg"]["median"] == pytest.approx(1.0)
    assert d["sure_and_right"] == pytest.approx(1 / 6)          # frame 2 only, over all 6 frames
    rel = {(r["p_from"], r["p_to"]): r for r in d["reliability"]}
    assert rel[(0.6, 0.7)]["n"] == 1 and rel[(0.6, 0.7)]["measured"] == 1.0
    assert rel[(0.6, 0.7)]["within_bound"] is False                 # stated 40% turned, found 100%
    assert rel[(0.7, 0.8)]["within_bound"] is True
    top = rel[(0.95, 0.99)]
    assert top["n"] == 2 and top["measured"] == 0.5 and top["within_bound"] is False


def test_the_calibration_bound_and_bins():
    from common.evaluation.metrics import reliability_table, within_calibration_bound
    assert within_calibration_bound(0.1, 0.17) and not within_calibration_bound(0.1, 0.18)
    assert within_calibration_bound(0.0, 0.02)
    rows = reliability_table(np.array([1.0, 0.995, 0.5]), np.array([False, False, True]))
    assert [(r["p_from"], r["n"]) for r in rows] == [(0.5, 1), (0.99, 2)]


def test_a_run_ended_before_the_graph_answered_every_frame_is_named():
    """``needletrack eval`` warns when a pose node answered fewer frames than the run had (the
    evaluator's drain ended it on a loaded machine: seen on a 2,467-frame run cut at 1,869)."""
    from common.evaluation.cli import unanswered
    res = {"frames": 2467, "node_counters": {
        "refine": {"out.pose": 648, "out.no_pose": 1221}, "tracker": {"out.pose": 1854, "out.no_pose": 15},
        "epnp_joint": {"out.pose": 552, "out.no_pose": 1915}, "detector_left": {"out.left": 2467},
        "fusion": {"out.pose": 468}}}
    assert unanswered(res) == {"refine": 1869, "tracker": 1869}
    res["node_counters"]["refine"]["out.no_pose"] = 1819
    res["node_counters"]["tracker"]["out.no_pose"] = 613
    assert unanswered(res) == {}
