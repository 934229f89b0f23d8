"""The dataset spec: round trip, folders written by other tools, and broken folders."""
import json
import os

import cv2
import numpy as np
import pytest
import yaml

from common.data.dataset import (
    Dataset,
    DatasetError,
    DatasetMeta,
    DatasetWriter,
    Frame,
    check_dataset,
    project_keypoints,
    truncate_torn_tail,
)
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.transforms import make_T, rotvec_to_R

W, H = 160, 90


def _meta(arm=True):
    return DatasetMeta((W, H), StereoRig.default(W, H), NeedleModel(),
                       EcmArm(make_T(rotvec_to_R([0.2, 0, 0]), [0, -0.1, 0.25])) if arm else None, "test")


def _frame(meta, i, seq=None, step=None):
    q = np.array([0.05 * i, -0.03, 0.1, 0.02])
    T_we = meta.arm.T_world_ecm(q)
    i0 = i if seq is None else 2 * seq  # the needle is at rest within a sequence
    T_cn = make_T(rotvec_to_R([0.3, 0.1, 0.2 * i0]), [0.003, -0.002, 0.12])
    T_wn = meta.arm.T_world_ecm([0.05 * i0, -0.03, 0.1, 0.02]) @ meta.rig.left.T_ecm_cam @ T_cn
    kp = project_keypoints(meta, T_we, T_wn)
    vis = {c: np.array([True, True, False, True, True]) for c in ("left", "right")}
    return Frame(index=i, stamp_ns=i * 33_333_333, left=f"images/left/{i:06d}.jpg",
                 right=f"images/right/{i:06d}.jpg", sequence=seq, step=step, ecm_joints=q,
                 T_world_ecm=T_we, T_world_needle=T_wn, keypoints=kp, visible=vis,
                 bbox={"left": [10.0, 20.0, 60.5, 70.5], "right": None})


def _write(folder, n=4, meta=None):
    meta = meta or _meta()
    img = np.zeros((H, W, 3), np.uint8)
    with DatasetWriter(folder, meta) as w:
        for i in range(n):
            w.write_images(i, {"left": img, "right": img})
            w.append(_frame(meta, i, seq=i // 2, step=i % 2))
    return meta


def test_round_trip(tmp_path):
    meta = _write(tmp_path, 4)
    ds = Dataset(tmp_path)
    assert len(ds) == 4 and ds.meta.image_size == (W, H)
    assert np.allclose(ds.rig.left.K, meta.rig.left.K) and np.allclose(ds.arm.T_world_base, meta.arm.T_world_base)
    for i, fr in enumerate(ds):
        ref = _frame(meta, i, i // 2, i % 2)
        for k in ("ecm_joints", "T_world_ecm", "T_world_needle"):
            assert np.array_equal(getattr(fr, k), getattr(ref, k))  # exact: JSON keeps full precision
        assert np.array_equal(fr.keypoints["left"], ref.keypoints["left"])
        assert fr.visible["right"].tolist() == [True, True, False, True, True]
        assert fr.bbox["right"] is None and fr.bbox["left"] == [10.0, 20.0, 60.5, 70.5]
        assert fr.line == i + 1
    assert ds.image(0, "left").shape == (H, W, 3)
    assert sorted(ds.sequences()) == [0, 1]
    rep = check_dataset(ds)
    assert rep.ok, rep.errors
    assert rep.max_reproj_px < 1e-9 and rep.with_truth == 4 and rep.images_checked == 8


def _foreign(folder, frames_lines, meta_dict=None, image=True):
    """A folder as another tool might write it: PNG, no ecm, optional fields absent or null."""
    rig = StereoRig.default(W, H)
    meta = meta_dict or {"format": "needle-dataset", "version": 1, "image_size": [W, H],
                         "cameras": {c: {"K": rig[c].K.tolist(), "dist": [0, 0, 0, 0, 0],
                                         "T_ecm_cam": rig[c].T_ecm_cam.tolist()} for c in ("left", "right")},
                         "needle": {"radius_m": 0.01018, "keypoint_angles_deg": [30, 60, 90, 120, 150]}}
    os.makedirs(folder / "img", exist_ok=True)
    (folder / "dataset.yaml").write_text(yaml.safe_dump(meta) if isinstance(meta, dict) else meta)
    if image:
        rgb = np.zeros((H, W, 3), np.uint8)
        rgb[..., 0] = 200  # red in the file
        cv2.imwrite(str(folder / "img" / "a.png"), rgb[..., ::-1])
        cv2.imwrite(str(folder / "img" / "b.JPG"), rgb[..., ::-1])
    (folder / "frames.jsonl").write_text("".join(
        (ln if isinstance(ln, str) else json.dumps(ln)) + "\n" for ln in frames_lines))


def test_foreign_folder_loads(tmp_path):
    _foreign(tmp_path, [
        {"index": 0, "stamp_ns": 5, "left": "img/a.png", "right": "img/b.JPG"},
        {"index": 1, "stamp_ns": 5, "left": "img/a.png", "right": "img/b.JPG", "sequence": None,
         "keypoints": None, "T_world_needle": None, "bbox": {"left": None, "right": None}},
    ])
    for name in ("dataset.yaml", "frames.jsonl"):  # Windows tools: BOM and CRLF
        p = tmp_path / name
        p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes().replace(b"\n", b"\r\n"))
    ds = Dataset(tmp_path)
    assert ds.arm is None and len(ds) == 2
    assert ds[0].keypoints is None and ds[1].sequence is None
    img = ds.image(0, "left")
    assert img[0, 0].tolist()[2] > 190 and img[0, 0].tolist()[0] < 10  # BGR: red is the last channel
    assert ds.image(0, "right")[0, 0, 2] > 180  # JPEG
    assert check_dataset(ds).ok


GOOD = {"index": 0, "stamp_ns": 0, "left": "img/a.png", "right": "img/a.png"}


@pytest.mark.parametrize("line, expect", [
    ('{"index": 0, "stamp_ns": 0, "left": "img/a.png"', "frames.jsonl:2: (line): not valid JSON"),
    ({**GOOD, "right": None}, "frames.jsonl:2: right: required field missing"),
    ({**GOOD, "index": 3}, "frames.jsonl:2: index: expected 1"),
    ({**GOOD, "index": 1, "stamp_ns": -5}, "frames.jsonl:2: stamp_ns"),
    ({**GOOD, "index": 1, "left": "/abs/a.png"}, "frames.jsonl:2: left: must be relative"),
    ({**GOOD, "index": 1, "left": "../a.png"}, "frames.jsonl:2: left: must stay inside"),
    ({**GOOD, "index": 1, "left": "img/a.bmp"}, "frames.jsonl:2: left: must be a PNG or JPEG"),
    ({**GOOD, "index": 1, "left": "img/missing.png"}, "frames.jsonl:2: left: image file"),
    ({**GOOD, "index": 1, "ecm_joints": [0, 0, 0]}, "frames.jsonl:2: ecm_joints"),
    ({**GOOD, "index": 1, "T_world_ecm": [[1, 0, 0, 0]] * 4}, "frames.jsonl:2: T_world_ecm: last row"),
    ({**GOOD, "index": 1, "T_world_needle": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
     "frames.jsonl:2: T_world_needle: rotation part"),
    ({**GOOD, "index": 1, "keypoints": {"left": [[0, 0]] * 5}}, "frames.jsonl:2: keypoints: right: missing"),
    ({**GOOD, "index": 1, "keypoints": {"left": [[0, 0]] * 4, "right": [[0, 0]] * 5}},
     "frames.jsonl:2: keypoints: left: expected 5 rows"),
    ({**GOOD, "index": 1, "keypoints": {"left": [[0, "x"]] * 5, "right": [[0, 0]] * 5}},
     "frames.jsonl:2: keypoints: left: [0][1]: expected a number"),
    ({**GOOD, "index": 1, "visible": {"left": [1, 1, 1, 1, 1], "right": [True] * 5}},
     "frames.jsonl:2: visible: left: expected a list of 5 booleans"),
    ({**GOOD, "index": 1, "bbox": {"left": [5, 5, 1, 1], "right": None}}, "frames.jsonl:2: bbox: left"),
    ({**GOOD, "index": 1, "step": -1}, "frames.jsonl:2: step"),
    ("[1, 2]", "frames.jsonl:2: (line): expected a JSON object"),
])
def test_broken_frames_are_rejected_with_file_line_field(tmp_path, line, expect):
    _foreign(tmp_path, [GOOD, line])
    with pytest.raises(DatasetError) as exc:
        Dataset(tmp_path)
    assert expect in str(exc.value), str(exc.value)


def _meta_text(**change):
    rig = StereoRig.default(W, H)
    d = {"format": "needle-dataset", "version": 1, "image_size": [W, H],
         "cameras": {c: {"K": rig[c].K.tolist(), "dist": [0, 0, 0, 0, 0],
                         "T_ecm_cam": rig[c].T_ecm_cam.tolist()} for c in ("left", "right")},
         "needle": {"radius_m": 0.01018, "keypoint_angles_deg": [30, 60, 90, 120, 150]}}
    for path, v in change.items():
        keys = path.split("__")
        t = d
        for k in keys[:-1]:
            t = t[k]
        if v is None:
            del t[keys[-1]]
        else:
            t[keys[-1]] = v
    return yaml.safe_dump(d, sort_keys=False)


@pytest.mark.parametrize("text, expect", [
    (_meta_text(format="other"), "dataset.yaml:1: format: must be 'needle-dataset'"),
    (_meta_text(version=2), "dataset.yaml:2: version: unknown version 2"),
    (_meta_text(image_size=[W]), "dataset.yaml:3: image_size"),
    (_meta_text(cameras__right=None), "cameras.right: required field missing"),
    (_meta_text(cameras__left__K=[[1, 0, 0], [0, 1, 0]]), "cameras.left.K: expected 3 rows"),
    (_meta_text(cameras__left__dist=[0, 0, 0]), "cameras.left.dist: OpenCV distortion"),
    (_meta_text(needle__radius_m=-1), "needle.radius_m: must be positive"),
    (_meta_text(needle__keypoint_angles_deg=[30, 60]), "needle.keypoint_angles_deg"),
    ("format: needle-dataset\nversion: [1\n", "dataset.yaml:3: not valid YAML"),
])
def test_broken_meta_is_rejected(tmp_path, text, expect):
    _foreign(tmp_path, [GOOD], meta_dict=text)
    with pytest.raises(DatasetError) as exc:
        Dataset(tmp_path)
    assert expect in str(exc.value), str(exc.value)


def test_meta_line_numbers_point_at_the_field(tmp_path):
    text = _meta_text(needle__radius_m=-1)
    _foreign(tmp_path, [GOOD], meta_dict=text)
    with pytest.raises(DatasetError) as exc:
        Dataset(tmp_path)
    line = int(str(exc.value).split(":")[1])
    assert "radius_m" in text.splitlines()[line - 1]


def test_check_finds_inconsistent_ground_truth(tmp_path):
    meta = _write(tmp_path, 3)
    lines = (tmp_path / "frames.jsonl").read_text().splitlines()
    obj = json.loads(lines[1])
    obj["keypoints"]["left"][2][0] += 0.6  # C moved by 0.6 px
    lines[1] = json.dumps(obj)
    obj = json.loads(lines[2])
    obj["ecm_joints"][0] += 0.01  # joints that do not give T_world_ecm
    lines[2] = json.dumps(obj)
    (tmp_path / "frames.jsonl").write_text("\n".join(lines) + "\n")
    rep = check_dataset(Dataset(tmp_path))
    assert not rep.ok
    assert any("frames.jsonl:2: keypoints" in e and "0.600 px" in e for e in rep.errors), rep.errors
    assert any("frames.jsonl:3: T_world_ecm" in e for e in rep.errors), rep.errors
    assert meta is not None


def test_check_finds_a_corrupt_image_and_a_moving_needle(tmp_path):
    _write(tmp_path, 2)
    (tmp_path / "images" / "right" / "000001.jpg").write_bytes(b"not a jpeg")
    lines = (tmp_path / "frames.jsonl").read_text().splitlines()
    obj = json.loads(lines[1])
    obj["T_world_needle"][0][3] += 0.001
    obj["keypoints"] = None
    lines[1] = json.dumps(obj)
    (tmp_path / "frames.jsonl").write_text("\n".join(lines) + "\n")
    rep = check_dataset(Dataset(tmp_path))
    assert any("000001.jpg: not a readable" in e for e in rep.errors), rep.errors
    assert any("frames.jsonl:2: T_world_needle: differs from the first frame of sequence 0" in e
               for e in rep.errors), rep.errors


def test_torn_tail_is_dropped_on_resume(tmp_path):
    meta = _write(tmp_path, 3)
    with open(tmp_path / "frames.jsonl", "a") as f:
        f.write('{"index": 3, "stamp')
    assert truncate_torn_tail(str(tmp_path / "frames.jsonl")) == 3
    with DatasetWriter(tmp_path, meta, resume=True) as w:
        assert w.n_frames == 3
        img = np.zeros((H, W, 3), np.uint8)
        w.write_images(3, {"left": img, "right": img})
        w.append(_frame(meta, 3))
    assert len(Dataset(tmp_path)) == 4
    with pytest.raises(DatasetError):
        DatasetWriter(tmp_path, _meta(arm=False), resume=True)
