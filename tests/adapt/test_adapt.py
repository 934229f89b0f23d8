"""``needletrack adapt``: folders without ground truth, pseudo-labels that geometry confirms (and
the reasons for what it drops), the end identity never trusted beyond the shipped weights, and
the whole command through the real graph on a tiny folder."""
import json
import os

import numpy as np
import pytest
import yaml

from common.cli import dataset_main
from common.data.check import check_dataset
from common.data.dataset import Dataset
from common.data.writer import TRUTH_FIELDS, without_truth
from common.adapt.adapt_calibration import safe_scale, sure_share, sure_wrong
from common.evaluation.recording import FrameOutputs, read_recording, recording_complete
from common.adapt.pseudo_labels import LabelConfig, keypoint_sigma_px, score_against_truth, write_labels
from common.frames import CAMERAS
from common.geometry.refine import tip_for_tail
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points


def _generate(path, width, height, sequences=4, steps=4, seed=5):
    rc = dataset_main(["generate", "--out", str(path), "--sequences", str(sequences), "--steps", str(steps),
                       "--width", str(width), "--height", str(height), "--seed", str(seed),
                       "--jobs", "1", "--quiet"])
    assert rc == 0
    return path


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    root = tmp_path_factory.mktemp("adapt")
    truth = _generate(root / "truth", 480, 270)
    bare = root / "bare"
    without_truth(str(truth), str(bare))
    return truth, bare


def test_a_folder_without_truth_is_a_valid_folder_the_reader_accepts(small):
    truth, bare = small
    ds = Dataset(str(bare))
    rep = check_dataset(ds, images=True)
    assert rep.ok and rep.with_truth == 0
    assert len(ds) == len(Dataset(str(truth)))
    lines = [json.loads(l) for l in (bare / "frames.jsonl").read_text().splitlines()]
    assert not any(k in l for l in lines for k in TRUTH_FIELDS)
    assert all("T_world_ecm" in l and "sequence" in l for l in lines)   # the endoscope's poses stay
    with pytest.raises(ValueError, match="exists"):
        without_truth(str(truth), str(bare))


COV = np.diag([np.radians(0.5) ** 2] * 3 + [0.0002 ** 2] * 3)


def _outputs(truth_ds, plan: dict) -> dict:
    """Refined poses and detections as the pipeline would record them, from the truth: ``plan``
    maps a sequence to (per-view pose function, per-view end identity)."""
    rng = np.random.default_rng(0)
    out = {}
    for fr in truth_ds.frames:
        moved, p = plan[fr.sequence]
        T_true = inv_T(fr.T_world_ecm) @ fr.T_world_needle
        T = moved(fr.step, T_true)
        noise = make_T(rotvec_to_R(rng.normal(0, 1e-3, 3)), rng.normal(0, 5e-5, 3))
        T = noise @ T
        fo = FrameOutputs(fr.index)
        fo.pose = {"T_ecm_needle": T, "T_world_ecm": np.asarray(fr.T_world_ecm), "covariance": COV,
                   "end_identity": p(fr.step), "ambiguous": False, "model_sigma_m": 1e-4,
                   "model_sigma_rad": 1e-3}
        for c in CAMERAS:
            uv = np.asarray(fr.keypoints[c])
            fo.keypoints[c] = {"found": True, "uv": uv, "scores": np.ones(5),
                               "bbox": [*(uv.min(0) - 2), *(uv.max(0) + 2)]}
        out[fr.index] = fo
    return out


def test_groups_are_kept_only_when_geometry_confirms_them_and_drops_are_named(small, tmp_path):
    truth, _ = small
    ds = Dataset(str(truth))
    needle = ds.meta.needle
    same = lambda step, T: T
    plan = {0: (same, lambda s: 0.99),                                      # agrees: kept
            1: (lambda s, T: make_T(T[:3, :3], T[:3, 3] + [0.02, 0, 0]) if s < 2 else T,
                lambda s: 0.99),                                            # two views elsewhere
            2: (same, lambda s: 0.7),                                       # tip not decided
            3: (lambda s, T: tip_for_tail(T, needle) if s == 0 else T,     # one view turned, weakly
                lambda s: 0.6 if s == 0 else 0.99)}
    outputs = _outputs(ds, plan)
    out = tmp_path / "labels"
    rep = write_labels([(str(truth), outputs)], out, LabelConfig(fit_every=0), progress=False)
    by = {v["group"]: v for v in rep["verdicts"]}
    assert by["seq0"]["kept"] and by["seq3"]["kept"]
    assert by["seq1"]["reason"] == "views_disagree"
    assert by["seq2"]["reason"] == "tip_undecided"
    assert rep["dropped_groups"]["views_disagree"] == 1 and rep["dropped_frames"]["tip_undecided"] == 4
    assert rep["kept_frames"] == 8 and rep["train_frames"] == 8 and rep["fit_frames"] == 0
    lab = Dataset(str(out / "train"))
    assert check_dataset(lab, images=True).ok
    assert all(f.keypoints is not None and f.T_world_needle is not None for f in lab.frames)
    score = score_against_truth(out, {str(truth): str(truth)})
    assert score["scored_frames"] == 8 and score["tip_right"] == 1.0      # the turned view was outvoted
    assert score["keypoint_px"]["mean"] < 1.0
    # resumable: a finished labelling is kept as it is
    t = os.stat(out / "labels.json").st_mtime_ns
    assert write_labels([(str(truth), {})], out, progress=False)["kept_groups"] == 2
    assert os.stat(out / "labels.json").st_mtime_ns == t


def test_groups_too_few_views_or_too_unsure_are_dropped(small, tmp_path):
    truth, _ = small
    ds = Dataset(str(truth))
    outputs = _outputs(ds, {s: (lambda st, T: T, lambda st: 0.99) for s in range(4)})
    for fo in outputs.values():
        fr = ds.frames[fo.seq]
        if fr.sequence == 0 and fr.step > 0:
            fo.pose = None                                  # posed once: no multi-view group
        if fr.sequence == 1:
            fo.pose["covariance"] = COV * 1e4               # 20 mm, 50 deg sigma
    rep = write_labels([(str(truth), outputs)], tmp_path / "l", LabelConfig(fit_every=2), progress=False)
    by = {v["group"]: v for v in rep["verdicts"]}
    assert by["seq0"]["reason"] == "too_few_poses" and by["seq1"]["reason"] == "uncertain"
    assert rep["kept_groups"] == 2 and rep["fit_frames"] == 4 and rep["train_frames"] == 4
    assert check_dataset(Dataset(str(tmp_path / "l" / "fit")), images=False).ok
    # the dropped groups' images are kept as boxes only: the teacher's inputs, never labels
    teacher = Dataset(str(tmp_path / "l" / "teacher"))
    assert check_dataset(teacher, images=True).ok and len(teacher) == 8 and rep["teacher_images"] == 16
    assert all(f.keypoints is None and f.T_world_needle is None and f.bbox["left"] is not None
               for f in teacher.frames)


def test_the_label_check_is_in_pixels_a_far_needles_depth_moves_no_keypoint(small):
    truth, _ = small
    ds = Dataset(str(truth))
    fr = ds.frames[0]
    cam = ds.meta.rig["left"]
    R_world_cam = fr.T_world_ecm[:3, :3] @ cam.T_ecm_cam[:3, :3]
    p_cam = transform_points(cam.T_cam_ecm @ inv_T(fr.T_world_ecm) @ fr.T_world_needle, ds.meta.needle.keypoints())
    sigma = 1e-3                                            # 1 mm along one camera axis
    def cov_along(axis):
        d = R_world_cam[:, axis]
        cov = np.zeros((6, 6))
        cov[3:, 3:] = sigma ** 2 * np.outer(d, d)
        return cov
    lateral = keypoint_sigma_px(ds.meta, [fr.T_world_ecm], fr.T_world_needle, cov_along(0))
    assert lateral == pytest.approx(cam.K[0, 0] * sigma / p_cam[:, 2].min(), rel=0.05)
    depth = keypoint_sigma_px(ds.meta, [fr.T_world_ecm], fr.T_world_needle, cov_along(2))
    assert depth < 0.2 * lateral                            # along the line of sight: little in the image
    assert keypoint_sigma_px(ds.meta, [fr.T_world_ecm], fr.T_world_needle, None) == float("inf")


def test_the_end_identity_is_never_surer_than_the_shipped_weights_allow():
    rng = np.random.default_rng(1)
    y = (rng.random(400) < 0.9).astype(float)
    X = np.column_stack([np.where(y == 1, 1.0, -1.0) + rng.normal(0, 1.5, 400), rng.normal(0, 1, 400)])
    coef = np.array([6.0, 0.0])                      # overconfident: sure, and often wrong
    assert sure_wrong(X, y, coef) > 0.02
    s = safe_scale(X, y, coef, bound=0.01)
    assert s < 1.0 and sure_wrong(X, y, s * coef) <= 0.01
    assert safe_scale(X, y, coef, bound=0.0) >= 0.0 and sure_wrong(X, y, 0.0 * coef) == 0.0
    assert safe_scale(X, y, np.array([0.5, 0.0]), bound=0.0) == 1.0   # never sure: kept whole
    # never surer than the shipped weights, even where no error shows
    right = np.column_stack([np.where(y == 1, 3.0, -3.0), np.zeros(400)])
    assert sure_wrong(right, y, coef) == 0.0 and sure_share(right, coef) == 1.0
    s = safe_scale(right, y, coef, bound=0.0, max_sure=0.5)
    assert s < 1.0 and sure_share(right, s * coef) <= 0.5


def test_an_unfinished_recording_is_refused(tmp_path):
    from common.evaluation.recording import RecordingError
    p = tmp_path / "r.jsonl"
    p.write_text('{"kind":"keypoints","seq":0,"camera":"left","found":false}\n')
    assert not recording_complete(p)
    with pytest.raises(RecordingError, match="did not finish"):
        read_recording(p)
    # finished: each frame's pose, one-camera pose and keypoints
    p.write_text('{"kind":"keypoints","seq":0,"camera":"left","found":false}\n'
                 '{"kind":"one_camera","seq":0,"method":"refined_one_camera","T_ecm_needle":[[1,0,0,0],[0,1,0,0],[0,0,1,0.1],[0,0,0,1]]}\n'
                 '{"kind":"pose","seq":1,"method":"refined"}\n{"kind":"end","frames":2}\n')
    rec = read_recording(p)
    assert rec[0].pose is None and rec[0].one_camera["T_ecm_needle"][2, 3] == 0.1 and "left" in rec[0].keypoints
    assert rec[1].pose["method"] == "refined" and rec[1].one_camera is None


@pytest.mark.slow
@pytest.mark.graph
def test_adapt_runs_the_pipeline_labels_trains_and_resumes(tmp_path):
    from common.adapt.adapt import main
    truth = _generate(tmp_path / "truth", 960, 540, sequences=3, steps=4, seed=6)
    bare = tmp_path / "bare"
    without_truth(str(truth), str(bare))
    cfg = yaml.safe_load(open(os.path.join(os.path.dirname(__file__), "..", "..", "models", "finetune.yaml")))
    cfg["train"].update(epochs=1, steps_per_epoch=2, batch=4, global_batch=4, hard_negatives=0,
                        val_fraction=0.0, threads=1, warmup_steps=1)
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    args = ["--data", str(bare), "--out", str(out), "--config", str(tmp_path / "tiny.yaml"),
            "--support-normal", "0,0,1", "--truth", str(truth), "--rehearse", "2", "--quiet"]
    rc = main(args)
    rep = json.loads((out / "adapt.json").read_text())
    labels = rep["labels"]
    assert labels["groups"] == 3
    assert labels["kept_groups"] + sum(labels["dropped_groups"].values()) == 3
    if labels["train_frames"] == 0:
        assert rc == 1                       # nothing confirmed: said, nothing trained
        return
    assert rc == 0 and (out / "model.pt").is_file() and (out / "end_identity.json").is_file()
    assert rep["labels_score"]["keypoint_px"]["mean"] < 3.0
    # the built-in scene's frames, with their truth, rendered and trained on beside the labels
    assert rep["rehearsal"]["frames"] == 2 and len(Dataset(str(out / "rehearsal"))) == 2
    assert check_dataset(Dataset(str(out / "rehearsal")), images=False).ok
    import torch
    meta = torch.load(out / "train" / "model.pt", map_location="cpu", weights_only=True)["meta"]
    assert meta["data"] == [str(out / "labels" / "train"), str(out / "rehearsal")]
    rec = next((out / "pipeline").glob("*.jsonl"))
    t = os.stat(rec).st_mtime_ns
    assert main(args) == 0                   # resumes: the pipeline's recording is kept
    assert os.stat(rec).st_mtime_ns == t
