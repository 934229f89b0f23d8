"""What ``needletrack finetune`` trains on from a hand-labelled folder: only frames a person
labelled are targets, "no needle" frames negatives, hidden keypoints hidden, a camera neither
clicked nor marked unseen never a negative; whole takes held out; clear errors without labels."""
import json

import numpy as np
import pytest

from common.data.dataset import Dataset, Frame
from common.data.meta import DatasetMeta
from common.data.writer import DatasetWriter
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.oracle import true_keypoints
from common.geometry.transforms import make_T, rotvec_to_R, transform_points
from common.label.fit import CameraClicks, LabelFitter
from common.label.store import LabelStore
from common.label.targets import LabelsError, counts, read_labels, split_held_out, trainable, write_subset

W, H = 960, 540
RIG = StereoRig.default(W, H)
NEEDLE = NeedleModel()
T_NEEDLE = make_T(rotvec_to_R([2.4, 0.5, 0.3]), [0.004, -0.002, -0.08])


def _clicks(cams=("left", "right")):
    out = {}
    for c in cams:
        cam = RIG[c]
        uv, _ = true_keypoints(cam, T_NEEDLE, NEEDLE)
        wire = cam.project(transform_points(cam.T_cam_ecm @ T_NEEDLE, NEEDLE.arc_points(np.deg2rad([45, 90, 135]))))
        out[c] = CameraClicks(uv[0], uv[4], wire)
    return out


def _folder(path, n, sequence_of=lambda i: i // 2, truth_at=()):
    meta = DatasetMeta((W, H), RIG, NEEDLE)
    img = np.full((H, W, 3), 90, np.uint8)
    with DatasetWriter(str(path), meta) as w:
        for i in range(n):
            paths = w.write_images(i, {"left": img, "right": img})
            fr = Frame(index=i, stamp_ns=i * 1000, left=paths["left"], right=paths["right"],
                       sequence=sequence_of(i), step=i % 2, T_world_ecm=np.eye(4))
            if i in truth_at:
                fr.keypoints = {c: true_keypoints(RIG[c], T_NEEDLE, NEEDLE)[0] for c in ("left", "right")}
            w.append(fr)
    return path


def _labelled(path):
    """0: stereo label; 1: no needle; 2: stereo, C hidden in the left camera; 3: the left camera
    clicked, the right neither clicked nor marked; 4: the left clicked, the right marked not seen;
    5: unlabelled; 6: a render's truth."""
    folder = _folder(path, 7, truth_at=(6,))
    store = LabelStore(str(folder))
    fitter = LabelFitter(RIG, NEEDLE)
    store.save(0, fitter.fit(_clicks()), _clicks(), click_sigma_px=1.0)
    store.save(1, None, {c: CameraClicks(unseen=True) for c in ("left", "right")}, click_sigma_px=1.0)
    hid = _clicks()
    hid["left"].hidden[2] = True
    store.save(2, fitter.fit(hid), hid, click_sigma_px=1.0)
    one = _clicks(("left",))
    store.save(3, fitter.fit({**one, "right": CameraClicks()}), {**one, "right": CameraClicks()}, click_sigma_px=1.0)
    unseen = {**_clicks(("left",)), "right": CameraClicks(unseen=True)}
    store.save(4, fitter.fit(unseen), unseen, click_sigma_px=1.0)
    return folder


def test_only_what_a_person_labelled_is_a_target(tmp_path):
    folder = _labelled(tmp_path / "ds")
    kinds = [f.kind for f in read_labels(str(folder))]
    assert kinds == ["target", "no_needle", "target", "one_camera", "target", "unlabelled", "truth"]
    frames = read_labels(str(folder))
    assert [f.hidden for f in frames][:5] == [0, 0, 1, 0, 0]   # C hidden in frame 2's left camera
    c = counts(frames)
    assert c["target"] == 3 and c["no_needle"] == 1 and c["one_camera"] == 1 and c["hidden_keypoints"] == 1
    # trained on: the targets and the negative; never the unlabelled frame, the render's truth or
    # the camera nobody looked at
    assert [f.index for f in trainable([str(folder)])] == [0, 1, 2, 4]


def test_the_subset_folder_holds_the_labels_as_the_trainer_reads_them(tmp_path):
    folder = _labelled(tmp_path / "ds")
    chosen = [f for f in read_labels(str(folder)) if f.index in (1, 2, 4)]
    assert write_subset(chosen, str(tmp_path / "sub")) == 3
    ds = Dataset(str(tmp_path / "sub"))
    assert [fr.index for fr in ds.frames] == [0, 1, 2]
    assert [fr.label["source_index"] for fr in ds.frames] == [1, 2, 4]
    no, hidden, one = ds.frames
    assert no.label["no_needle"] and not any(no.visible["left"]) and no.keypoints is None
    assert hidden.visible["left"].tolist() == [True, True, False, True, True] and hidden.visible["right"].all()
    assert one.visible["left"].all() and not one.visible["right"].any()
    from common.detector.data import load_records
    from common.detector.model import ModelConfig
    recs = load_records(tmp_path / "sub", ModelConfig(), progress=False)
    has = {(r.frame, r.camera): r.has_needle for r in recs}
    assert has == {(0, "left"): False, (0, "right"): False, (1, "left"): True, (1, "right"): True,
                   (2, "left"): True, (2, "right"): False}
    hid = next(r for r in recs if (r.frame, r.camera) == (1, "left"))
    assert hid.vis.tolist() == [True, True, False, True, True]


def test_whole_takes_are_held_out(tmp_path):
    folder = _folder(tmp_path / "ds", 12)              # 6 takes of 2 frames
    store = LabelStore(str(folder))
    fit = LabelFitter(RIG, NEEDLE).fit(_clicks())
    for i in range(12):
        store.save(i, fit, _clicks(), click_sigma_px=1.0)
    frames = trainable([str(folder)])
    train, held = split_held_out(frames, 0.25, seed=3)
    assert len(held) == 4 and len(train) == 8          # about a quarter, whole takes
    assert not {f.sequence for f in train} & {f.sequence for f in held}
    assert split_held_out(frames, 0.25, seed=3) == (train, held)          # seeded
    assert split_held_out(frames, 0.0)[1] == []
    with pytest.raises(ValueError, match="held-out fraction"):
        split_held_out(frames, 1.0)


def test_a_folder_without_labels_is_refused_clearly(tmp_path, capsys):
    folder = _folder(tmp_path / "bare", 3, truth_at=(1,))
    with pytest.raises(LabelsError) as exc:
        trainable([str(folder)])
    msg = str(exc.value)
    assert str(folder) in msg and "3 frames, 0 labelled" in msg and "needletrack label" in msg
    assert "1 with ground truth not made by needletrack label" in msg
    from common.adapt.finetune import main
    assert main(["--labels", str(folder), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no hand-labelled frame" in err and str(folder) in err
    assert not (tmp_path / "out" / "train").exists()
    assert main(["--labels", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out2"), "--quiet"]) == 2
    assert "nowhere" in capsys.readouterr().err


def test_a_fine_tune_keeps_its_split_and_refuses_changed_labels(tmp_path):
    from common.adapt.finetune import prepare_labels
    folder = _labelled(tmp_path / "ds")
    out = tmp_path / "out"
    first = prepare_labels([str(folder)], out, 0.25, 0)
    held = [f for s in first["heldout"] for f in s["frames"]]
    train = [f for s in first["train"] for f in s["frames"]]
    assert sorted(held + train) == [0, 1, 2, 4] and held and train
    assert Dataset(first["train"][0]["folder"]) and len(Dataset(first["heldout"][0]["folder"])) == len(held)
    assert prepare_labels([str(folder)], out, 0.25, 0) == first          # a rerun resumes with the same split
    LabelStore(str(folder)).save(5, LabelFitter(RIG, NEEDLE).fit(_clicks()), _clicks(), click_sigma_px=1.0)
    with pytest.raises(ValueError, match="labels changed"):
        prepare_labels([str(folder)], out, 0.25, 0)
