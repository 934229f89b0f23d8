"""Training the keypoint detector: a short run on a tiny drawn dataset lowers the loss, resumes,
and rejects bad configurations and data folders with clear messages."""
import json

import numpy as np
import pytest
import torch
import yaml

from common.detector.batches import crop_batch, global_batch
from common.detector.data import (
    AugConfig,
    DatasetError,
    _global_window,
    crop_sample,
    load_records,
    make_record,
    read_dataset,
)
from common.detector.synthetic import write_synthetic_dataset
from common.detector.model import (
    KeypointModel,
    ModelConfig,
    apply_affine,
    crop_affine,
    crop_side,
)
from common.detector.train import DEFAULT_TRAIN, distillation_losses, load_config, losses, main, train

pytestmark = pytest.mark.training

TINY_MODEL = {"crop": 64, "crop_widths": [8, 16, 16, 24], "global_widths": [8, 8, 16], "crop_min": 40.0}


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("kp") / "syn", 10, seed=5, n_empty=1)


def _config(tmp_path, epochs, **train):
    t = {"epochs": epochs, "batch": 8, "global_batch": 4, "steps_per_epoch": 12, "warmup_steps": 2,
         "lr": 0.004, "threads": 1, "val_fraction": 0.2}
    t.update(train)
    p = tmp_path / f"train{epochs}.yaml"
    p.write_text(yaml.safe_dump({"seed": 3, "model": TINY_MODEL, "train": t}))
    return p


def test_records_hold_consistent_ground_truth(tiny_data):
    cfg = ModelConfig.from_dict(TINY_MODEL)
    recs = load_records(tiny_data, cfg, progress=False)
    assert len(recs) == 20 and sum(r.has_needle for r in recs) == 18
    rng = np.random.default_rng(0)
    for r in recs[:6]:
        img, kp_cells, w, arc, pres = crop_sample(r, cfg, None, rng)
        assert img.shape == (64, 64, 3) and pres == 1.0 and np.all(w == 1.0)
        M = crop_affine(*r.box[:2], crop_side(cfg, *r.box[2:]), cfg.crop)
        assert np.allclose(kp_cells, apply_affine(M, r.kp), atol=1e-4)   # out_stride 1
    neg = crop_sample(recs[-1], cfg, AugConfig(), rng)
    assert neg[4] == 0.0 and not np.any(neg[2])


def test_the_rendered_arc_visibility_sets_presence_box_and_centreline():
    """A jaw over the arc: only E of the keypoints is seen, but 40% of the arc (the dataset's
    ``arc_seen``) is; a positive whose box and centreline are that seen stretch. Under 10% seen
    is "no needle". Without ``arc_seen``, a needle with one keypoint seen is no positive."""
    cfg = ModelConfig.from_dict(TINY_MODEL)
    rng = np.random.default_rng(0)
    img = np.full((240, 320, 3), 90, np.uint8)
    t = np.linspace(0, 4, 96)
    arc = np.stack([100 + 30 * t, 120 + 4 * (t - 2) ** 2], 1)
    kp = arc[[0, 24, 48, 71, 95]]
    vis = [False, False, False, False, True]
    seen = np.zeros(49, bool)
    seen[29:] = True                                   # C..E's side, 20 of 49 points
    r = make_record(img, kp, vis, arc, cfg, rng, arc_seen=seen)
    assert r.has_needle
    x0, x1 = r.box[0] - r.box[2] / 2, r.box[0] + r.box[2] / 2
    assert x0 == pytest.approx(arc[np.isfinite(r.arc).all(1), 0].min() - 2) and x1 == pytest.approx(222, abs=0.5)
    assert np.isnan(r.arc[:50]).all() and np.isfinite(r.arc[-38:]).all()
    sample = crop_sample(r, cfg, None, rng)
    assert sample[4] == 1.0 and np.isnan(sample[3]).any(axis=1).sum() == np.isnan(r.arc).any(axis=1).sum()
    few = np.zeros(49, bool)
    few[-3:] = True                                    # 6% of the arc
    assert not make_record(img, kp, vis, arc, cfg, rng, arc_seen=few).has_needle
    assert not make_record(img, kp, vis, arc, cfg, rng).has_needle
    with pytest.raises(ValueError, match="arc_seen: expected a list of at least 2 booleans"):
        make_record(img, kp, vis, arc, cfg, rng, arc_seen=[1, 0, 1])


def test_short_training_lowers_the_loss_and_resumes(tiny_data, tmp_path):
    out = tmp_path / "model"
    logs = []
    train([tiny_data], out, _config(tmp_path, 1), log=logs.append, progress=False)
    assert (out / "model.pt").is_file() and (out / "checkpoint.pt").is_file()
    assert (out / "curves.png").is_file()
    # resume: the same command with more epochs continues after epoch 1
    last = train([tiny_data], out, _config(tmp_path, 3, hard_negatives=1, hard_mining_at=[0.5, 0.8],
                                           hard_mining_images=6), log=logs.append, progress=False)
    assert any("resuming" in line for line in logs)
    assert sum("hard negatives mined" in line for line in logs) == 2   # half-way, then at 80%
    metrics = [json.loads(l) for l in (out / "metrics.jsonl").read_text().splitlines()]
    assert [m["epoch"] for m in metrics] == [1, 2, 3] and last["epoch"] == 3
    assert "gtbox_mean_px" in metrics[-1]["val"]

    # the trained weights have a lower loss than the seeded initial ones on a fixed batch
    cfg = ModelConfig.from_dict(TINY_MODEL)
    recs = load_records(tiny_data, cfg, progress=False)
    torch.manual_seed(3)
    initial = KeypointModel(cfg)
    trained = KeypointModel(cfg)
    trained.load_state_dict(torch.load(out / "checkpoint.pt", weights_only=True)["state_dict"])
    w = DEFAULT_TRAIN["loss_weights"]

    def loss_of(model):
        rng = np.random.default_rng(11)
        cb = crop_batch(recs, np.arange(16) % len(recs), cfg, None, rng)
        gb = global_batch(recs, np.arange(8), cfg, None, rng)
        model.eval()
        with torch.no_grad():
            return {k: float(v) for k, v in losses(model, cb, gb, w).items()}
    before, after = loss_of(initial), loss_of(trained)
    assert after["total"] < 0.9 * before["total"]
    assert after["kp"] < before["kp"]


def _boxes_only(src, dst):
    """``src``'s frames as a folder of boxes only (no keypoints, no poses), as ``adapt`` writes its
    teacher folder."""
    import shutil
    shutil.copytree(src, dst)
    lines = []
    for line in (dst / "frames.jsonl").read_text().splitlines():
        fr = json.loads(line)
        lines.append(json.dumps({k: v for k, v in fr.items() if k not in ("keypoints", "visible", "T_world_needle")}))
    (dst / "frames.jsonl").write_text("\n".join(lines) + "\n")
    return dst


def test_boxes_only_records_are_inputs_without_targets(tiny_data, tmp_path):
    cfg = ModelConfig.from_dict(TINY_MODEL)
    with_kp = load_records(tiny_data, cfg, progress=False)
    boxes = load_records(_boxes_only(tiny_data, tmp_path / "boxes"), cfg, progress=False, boxes_only=True)
    assert 0 < len(boxes) <= len(with_kp)
    for r in boxes:
        assert r.has_needle and not r.vis.any() and np.isnan(r.kp).all() and r.region.size
    # read as labels, the same folder has no needle: a box alone never becomes a target
    assert not any(r.has_needle for r in load_records(tmp_path / "boxes", cfg, progress=False))


def test_distillation_pulls_the_outputs_towards_the_teachers(tiny_data):
    cfg = ModelConfig.from_dict(TINY_MODEL)
    recs = [r for r in load_records(tiny_data, cfg, progress=False) if r.has_needle]
    torch.manual_seed(1)
    teacher = KeypointModel(cfg).eval()
    with torch.no_grad():                    # a teacher sure of a needle everywhere: far from the student
        teacher.crop.presence.bias += 3.0
        teacher.glob.head.bias[0] += 2.0
    torch.manual_seed(2)
    student = KeypointModel(cfg)
    rng = np.random.default_rng(4)
    cb = crop_batch(recs, np.arange(8), cfg, None, rng)
    gb = global_batch(recs, np.arange(4), cfg, None, rng)
    w = DEFAULT_TRAIN["loss_weights"]

    def gap():
        student.eval()
        with torch.no_grad():
            (h, p), (th, tp) = student.crop(cb[0]), teacher.crop(cb[0])
            g, tg = student.glob(gb[0]), teacher.glob(gb[0])
        return (float((torch.sigmoid(p) - torch.sigmoid(tp)).abs().mean()),
                float((torch.sigmoid(g[:, 0]) - torch.sigmoid(tg[:, 0])).abs().mean()))
    before = gap()
    opt = torch.optim.Adam(student.parameters(), lr=1e-2)
    for _ in range(80):
        student.train()
        D = distillation_losses(student, teacher, cb, gb, w)
        opt.zero_grad()
        D["total"].backward()
        opt.step()
    assert set(D) == {"presence", "global", "box", "global_presence", "total"}   # no keypoints copied
    assert all(p.grad is None for p in teacher.parameters())          # the teacher stays as it is
    after = gap()
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1]


def test_training_with_a_teacher_folder_needs_the_weights_to_keep(tiny_data, tmp_path):
    boxes = _boxes_only(tiny_data, tmp_path / "boxes")
    with pytest.raises(ValueError, match="--init"):
        train([tiny_data], tmp_path / "a", _config(tmp_path, 1), progress=False, teacher_dirs=[str(boxes)])
    first = tmp_path / "first"
    train([tiny_data], first, _config(tmp_path, 1), progress=False)
    logs = []
    train([tiny_data], tmp_path / "b", _config(tmp_path, 1), log=logs.append, progress=False,
          init=str(first / "model.pt"), teacher_dirs=[str(boxes)])
    assert any("distillation: 18 images" in line for line in logs)
    metrics = [json.loads(l) for l in (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()]
    assert metrics[-1]["train"]["distill"] > 0


def test_stage1_windows_keep_the_box_on_the_same_pixels():
    aug = AugConfig(global_window=(48, 32), window_needle=0.5)
    rng = np.random.default_rng(1)
    small = np.zeros((90, 160, 3), np.uint8)
    small[70, 100] = 255                              # the needle centre, at downscale 4
    box = np.array([4 * 100 + 1.5, 4 * 70 + 1.5, 40.0, 30.0])
    seen = 0
    for _ in range(40):
        win, b = _global_window(small, box, 4, aug, rng)
        assert win.shape == (32, 48, 3)
        ys, xs = np.nonzero(win[..., 0])
        if np.isfinite(b).all():
            seen += 1
            assert (xs[0] * 4 + 1.5, ys[0] * 4 + 1.5) == (b[0], b[1]) and tuple(b[2:]) == (40.0, 30.0)
        else:
            assert len(xs) == 0
    assert 10 < seen < 40


def test_a_hidden_keypoint_weighs_occluded_weight_in_the_loss():
    """``train.occluded_weight`` (default ``OCCLUDED_WEIGHT``): the weight of a hidden keypoint in
    the crop's targets, under a seen one's 1; no weight outside the crop."""
    from common.detector.data import OCCLUDED_WEIGHT
    cfg = ModelConfig.from_dict(TINY_MODEL)
    img = np.full((240, 320, 3), 90, np.uint8)
    t = np.linspace(0, 4, 96)
    arc = np.stack([100 + 30 * t, 120 + 4 * (t - 2) ** 2], 1)
    r = make_record(img, arc[[0, 24, 48, 71, 95]], [True, True, True, False, False], arc, cfg,
                    np.random.default_rng(0))
    for w in (OCCLUDED_WEIGHT, 0.9, 0.0):
        valid = crop_batch([r] * 6, np.arange(6), cfg, None, np.random.default_rng(1), occluded_weight=w)[2].numpy()
        assert set(np.unique(valid[:, :3])) <= {0.0, 1.0} and (valid[:, :3] == 1.0).any()
        hidden = valid[:, 3:]
        assert np.all(np.isclose(hidden, 0.0) | np.isclose(hidden, w)) and np.isclose(hidden, w).any()
    assert DEFAULT_TRAIN["occluded_weight"] == OCCLUDED_WEIGHT == 0.3


def test_config_errors_name_the_file_and_field(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("train: {epoks: 3}\n")
    with pytest.raises(ValueError, match=r"bad.yaml.*epoks"):
        load_config(str(p))
    p.write_text("model: {crop: 128, depth: 3}\n")
    with pytest.raises(ValueError, match=r"bad.yaml.*depth"):
        load_config(str(p))
    p.write_text("seed: [unclosed\n")
    with pytest.raises(ValueError, match="bad.yaml"):
        load_config(str(p))
    for w in ("1.0", "heavy", "-0.1"):      # a hidden point weighs less than a seen one
        p.write_text(f"train: {{occluded_weight: {w}}}\n")
        with pytest.raises(ValueError, match=r"bad.yaml: train: occluded_weight must be in \[0, 1\)"):
            load_config(str(p))
    p.write_text("train: {occluded_weight: 0.9}\n")
    assert load_config(str(p))["train"]["occluded_weight"] == 0.9


def test_broken_data_folders_are_rejected_with_file_and_line(tiny_data, tmp_path, capsys):
    with pytest.raises(DatasetError, match="dataset.yaml: missing"):
        read_dataset(tmp_path)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "dataset.yaml").write_text((tiny_data / "dataset.yaml").read_text())
    lines = (tiny_data / "frames.jsonl").read_text().splitlines()
    (bad / "frames.jsonl").write_text(lines[0] + "\n{not json\n")
    with pytest.raises(DatasetError, match=r"frames.jsonl:2"):
        read_dataset(bad)
    rc = main(["--data", str(bad), "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2 and "frames.jsonl:2" in capsys.readouterr().err


def test_hidden_keypoints_train_towards_a_diffuse_heatmap_whose_score_is_under_the_gate():
    """``train.hidden_sigma``: a hidden keypoint's target is wide, so a network that fits it
    states a score (peak mass) under the pose nodes' 0.5 gate; a seen one's stays sharp."""
    import torch

    from common.detector.model import decode_heatmaps, gaussian_targets
    m = 48
    uv = torch.tensor([[[20.3, 25.6], [30.0, 10.0]]])
    valid = torch.tensor([[1.0, 0.3]])
    sigma = torch.where((valid > 0) & (valid < 1), 4.0, 1.5)
    t = gaussian_targets(uv, valid, m, sigma)
    assert torch.allclose(t.sum((-2, -1)), valid)
    _, score = decode_heatmaps(torch.log((t / valid[..., None, None]).clamp_min(1e-12)), 1)
    assert score[0, 0] > 0.75 and score[0, 1] < 0.3
    same = gaussian_targets(uv, valid, m, 1.5)
    assert torch.allclose(same[0, 0], t[0, 0]) and not torch.allclose(same[0, 1], t[0, 1])


def test_motion_blur_and_hue_augmentations_keep_the_image_and_move_no_mass():
    from common.detector.data import motion_blur, turn_hue
    img = np.zeros((41, 41, 3), np.uint8)
    img[20, 20] = 250
    b = motion_blur(img, 9.0, 0.0)
    row = b[20, :, 0]
    assert (row > 0).sum() >= 7 and b[:, 20, 0].astype(int).sum() == row[20]   # spread along x only
    assert abs(int(b[..., 0].astype(int).sum()) - 250) < 12
    assert motion_blur(img, 0.5, 0.3) is img
    red = np.full((4, 4, 3), (30, 30, 200), np.uint8)
    assert np.array_equal(turn_hue(turn_hue(red, 120), 240), red)
    g = turn_hue(red, 120)[0, 0]
    assert g[1] > g[0] and g[1] > g[2]                                         # red -> green


def test_keypoint_distillation_keeps_the_teachers_heatmaps():
    torch.manual_seed(0)
    cfg = ModelConfig(crop=32, crop_widths=(4, 8, 8, 8), global_widths=(4, 8, 8))
    teacher, student = KeypointModel(cfg).eval(), KeypointModel(cfg).eval()
    student.load_state_dict(teacher.state_dict())
    x = torch.rand(2, 3, 32, 32)
    w = DEFAULT_TRAIN["loss_weights"]
    assert "kp" not in distillation_losses(student, teacher, (x,), None, w)   # presence only, by default
    same = distillation_losses(student, teacher, (x,), None, w, keypoints=True)
    assert same["kp"].item() == pytest.approx(0.0, abs=1e-5)
    with torch.no_grad():
        for p in student.crop.parameters():
            p.add_(0.3 * torch.randn_like(p))
    moved = distillation_losses(student, teacher, (x,), None, w, keypoints=True)
    assert moved["kp"].item() > 1e-3 and moved["line"].item() > same["line"].item()


def test_negative_regions_are_centred_on_the_jaws_in_their_share():
    """``jaw_share`` 1: a needle-free region is a square around the instrument's jaws (away from the
    needle); 0: random, as before (the same draws)."""
    cfg = ModelConfig.from_dict(TINY_MODEL)
    img = np.random.default_rng(1).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    kp = np.array([[100, 100], [110, 95], [120, 92], [130, 95], [140, 100]], float)
    jaw = np.array([[450.0, 300.0]])
    for seed in range(5):
        r = make_record(img, kp, [True] * 5, None, cfg, np.random.default_rng(seed), jaws=jaw, jaw_share=1.0)
        side = r.neg.shape[0]
        assert 96 <= side < 160 and np.allclose(r.neg_origin + side / 2, jaw[0], atol=1)
        plain = make_record(img, kp, [True] * 5, None, cfg, np.random.default_rng(seed))
        again = make_record(img, kp, [True] * 5, None, cfg, np.random.default_rng(seed), jaws=jaw, jaw_share=0.0)
        assert np.array_equal(plain.neg_origin, again.neg_origin)
    near = make_record(img, kp, [True] * 5, None, cfg, np.random.default_rng(0), jaws=kp[2:3], jaw_share=1.0)
    assert not np.allclose(near.neg_origin + near.neg.shape[0] / 2, kp[2], atol=1)   # on the needle: not used


def test_jaw_pixels_project_the_true_jaws_where_the_frame_has_them():
    from common.detector.data import JAW_CENTRE_M, jaw_pixels
    from common.geometry.camera import StereoRig
    from common.geometry.transforms import inv_T
    rig = StereoRig.default(640, 480)
    T_jaw = np.eye(4)
    T_jaw[:3, 3] = rig.left.T_ecm_cam[:3, :3] @ [0.01, 0.0, 0.1 - JAW_CENTRE_M] + rig.left.T_ecm_cam[:3, 3]
    T_jaw[:3, :3] = rig.left.T_ecm_cam[:3, :3]        # jaw z along the camera's axis
    off = T_jaw.copy()
    off[:3, 3] += 0.02                                 # the reported pose, 2 cm off
    fr = {"T_world_ecm": np.eye(4).tolist(),
          "instruments": {"psm1": {"T_world_jaw": off.tolist(), "T_world_jaw_truth": T_jaw.tolist()}}}
    uv = jaw_pixels(rig, "left", fr)
    want = rig.left.project((inv_T(rig.left.T_ecm_cam) @ np.r_[T_jaw[:3, 3] + T_jaw[:3, 2] * JAW_CENTRE_M, 1])[None, :3])
    assert uv.shape == (1, 2) and np.allclose(uv, want)
    assert jaw_pixels(rig, "left", {"T_world_ecm": np.eye(4).tolist()}).shape == (0, 2)
