"""The dataset spec: round trip, folders written by other tools, and broken folders."""
import json
import os

import cv2
import numpy as np
import pytest
import yaml

from common.data.check import check_dataset, project_keypoints
from common.data.dataset import Dataset, DatasetError, DatasetMeta, Frame
from common.data.writer import DatasetWriter, truncate_torn_tail
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


# ---------------------------------------------------------------- instruments and moving takes

I4 = np.eye(4).tolist()


@pytest.mark.parametrize("inst, expect", [
    ({"psm1": {"T_world_jaw": [[1, 0, 0, 0]] * 4, "jaw_rad": 0.1}},
     "frames.jsonl:2: instruments.psm1.T_world_jaw: last row"),
    ({"psm1": {"jaw_rad": 0.1}}, "frames.jsonl:2: instruments.psm1.T_world_jaw: required field missing"),
    ({"psm2": {"T_world_jaw": I4}}, "frames.jsonl:2: instruments.psm2.jaw_rad: required field missing"),
    ({"psm1": {"T_world_jaw": I4, "jaw_rad": -0.2}}, "frames.jsonl:2: instruments.psm1.jaw_rad: must be an opening"),
    ({"psm1": {"T_world_jaw": I4, "jaw_rad": 0.1, "holds_needle": 1}},
     "frames.jsonl:2: instruments.psm1.holds_needle: expected true or false"),
    ({"psm1": [1]}, "frames.jsonl:2: instruments.psm1: expected a map"),
    ({"": {"T_world_jaw": I4, "jaw_rad": 0.1}}, "frames.jsonl:2: instruments.'': not an instrument name"),
    ([I4], "frames.jsonl:2: instruments: expected a map"),
])
def test_broken_instruments_are_rejected_with_file_line_field(tmp_path, inst, expect):
    _foreign(tmp_path, [GOOD, {**GOOD, "index": 1, "instruments": inst}])
    with pytest.raises(DatasetError) as exc:
        Dataset(tmp_path)
    assert expect in str(exc.value), str(exc.value)


def test_needle_at_rest_must_be_a_bool(tmp_path):
    _foreign(tmp_path, [GOOD, {**GOOD, "index": 1, "needle_at_rest": "no"}])
    with pytest.raises(DatasetError, match="frames.jsonl:2: needle_at_rest: expected true or false"):
        Dataset(tmp_path)


def _moving(meta, n=4, slip=0.0, mixed=False):
    """A take whose needle moves with psm1's jaws (``slip`` m: the needle slides in them at frame 2)."""
    frames = []
    T_jn = make_T(rotvec_to_R([0.1, 0.4, -0.2]), [0.0, -0.01, 0.002])
    for i in range(n):
        fr = _frame(meta, i, seq=0, step=i)
        T_wj = fr.T_world_needle @ np.linalg.inv(T_jn) @ make_T(rotvec_to_R([0, 0, 0.05 * i]), [0.001 * i, 0, 0])
        T_wn = T_wj @ T_jn
        if i >= 2:
            T_wn = T_wn @ make_T(np.eye(3), [slip, 0, 0])
        from common.data.instruments import InstrumentPose
        fr.T_world_needle = T_wn
        fr.keypoints = project_keypoints(meta, fr.T_world_ecm, T_wn)
        fr.visible = {c: np.zeros(5, bool) for c in ("left", "right")}
        fr.needle_at_rest = True if (mixed and i == 3) else False
        fr.instruments = {"psm1": InstrumentPose(T_wj, 0.0, True),
                          "psm2": InstrumentPose(make_T(np.eye(3), [0.02, 0, 0.03]), 0.6, False)}
        frames.append(fr)
    return frames


def _write_frames(folder, meta, frames):
    img = np.zeros((H, W, 3), np.uint8)
    with DatasetWriter(folder, meta) as w:
        for fr in frames:
            w.write_images(fr.index, {"left": img, "right": img})
            w.append(fr)


def test_a_moving_take_round_trips_and_is_no_multiview_group(tmp_path):
    meta = _meta()
    frames = _moving(meta)
    _write_frames(tmp_path, meta, frames)
    ds = Dataset(tmp_path)
    rep = check_dataset(ds)
    assert rep.ok, rep.errors
    fr = ds[2]
    assert fr.needle_at_rest is False and not fr.at_rest and fr.multiview_group is None
    assert fr.instruments["psm1"].holds_needle is True and fr.instruments["psm2"].jaw_rad == 0.6
    assert np.array_equal(fr.instruments["psm1"].T_world_jaw, frames[2].instruments["psm1"].T_world_jaw)
    assert list(ds.sequences()) == [0] and ds.multiview_groups() == {}
    rest = Dataset(_write(tmp_path / "rest", 4) and tmp_path / "rest")
    assert sorted(rest.multiview_groups()) == [0, 1] and rest[0].at_rest and rest[0].multiview_group == 0
    from common.runtime.messages import GroundTruth
    assert GroundTruth.from_frame(fr, 2, 3).needle_at_rest is False


def test_check_finds_a_needle_that_slips_in_the_jaws_and_a_take_half_at_rest(tmp_path):
    meta = _meta()
    _write_frames(tmp_path / "slip", meta, _moving(meta, slip=1e-4))
    errs = check_dataset(Dataset(tmp_path / "slip")).errors
    assert len(errs) == 1 and "frames.jsonl:3: instruments.psm1: holds_needle" in errs[0] and "0.1000 mm" in errs[0]
    _write_frames(tmp_path / "mixed", meta, _moving(meta, mixed=True))
    errs = check_dataset(Dataset(tmp_path / "mixed")).errors
    assert any("frames.jsonl:4: needle_at_rest: True in sequence 0" in e for e in errs), errs
    # a needle that moves in a sequence not marked moving is still an error
    frames = _moving(meta)
    for fr in frames:
        fr.needle_at_rest = None
    _write_frames(tmp_path / "unmarked", meta, frames)
    errs = check_dataset(Dataset(tmp_path / "unmarked")).errors
    assert errs and "the needle must be at rest" in errs[0]


def _doc_fields(text: str, heading: str) -> set:
    """The first column of the tables under ``heading`` in docs/dataset.md (up to the next ##)."""
    part = text.split(heading, 1)[1].split("\n## ", 1)[0]
    cells = [ln.split("|")[1] for ln in part.splitlines() if ln.startswith("| `")]
    return {name for cell in cells for name in cell.split("`")[1::2]}


def test_the_docs_page_is_the_spec_and_lists_what_the_reader_parses():
    from pathlib import Path

    from common.data.dataset import _FRAME_FIELDS, EXTENSION_FIELDS, parse_frame
    root = Path(__file__).resolve().parents[2]
    text = (root / "docs" / "dataset.md").read_text()
    shared = root.parent / "shared" / "specs" / "dataset.md"            # the project's contract, beside main
    for spec in (shared, Path("/work/shared/specs/dataset.md")):
        if spec.is_file():
            assert spec.read_text() == text, f"docs/dataset.md differs from {spec}"
    fields = _doc_fields(text, "## frames.jsonl")
    inst_fields = {"T_world_jaw", "jaw_rad", "holds_needle", "T_world_jaw_truth", "jaw_rad_truth"}
    assert {"instruments", "needle_at_rest"} | inst_fields <= fields
    assert fields - inst_fields == _FRAME_FIELDS
    assert not EXTENSION_FIELDS & fields                                 # ours, documented in datasets.md
    ours = (root / "docs" / "datasets.md").read_text()
    assert all(f"`{f}`" in ours for f in EXTENSION_FIELDS)
    fr = parse_frame({**GOOD, "arc_visible": {"left": 0.25, "right": 1}})
    assert fr.arc_visible == {"left": 0.25, "right": 1.0} and fr.to_json()["arc_visible"] == fr.arc_visible
    with pytest.raises(DatasetError, match=r"frames.jsonl:3: arc_visible: right: expected a share in \[0, 1\], got 1\.5"):
        parse_frame({**GOOD, "arc_visible": {"left": 0.25, "right": 1.5}}, 3)
    seen = {"left": [True, False, True], "right": [False, False, True]}
    fr = parse_frame({**GOOD, "arc_seen": seen})
    assert fr.arc_seen["left"].tolist() == seen["left"] and fr.to_json()["arc_seen"] == seen
    with pytest.raises(DatasetError, match=r"frames.jsonl:4: arc_seen: left: expected a list of at least 2 booleans"):
        parse_frame({**GOOD, "arc_seen": {"left": [1, 0], "right": [True, True]}}, 4)


def test_a_generation_of_takes_of_their_own_lengths_resumes_after_the_last_whole_take(tmp_path):
    from common.data.writer import resume_generation
    cfg = {"motion": "throw", "seed": 1}
    assert resume_generation(str(tmp_path), "gen.json", cfg, 3, 1, "gen", lengths=[3, 5, 2]) == (False, 0)
    lines = [json.dumps({**GOOD, "index": i, "sequence": s, "step": k})
             for i, (s, k) in enumerate([(0, 0), (0, 1), (0, 2), (1, 0), (1, 1)])]
    (tmp_path / "frames.jsonl").write_text("\n".join(lines) + "\n" + '{"index": 5, "sta')   # torn in take 1
    assert resume_generation(str(tmp_path), "gen.json", cfg, 3, 1, "gen", lengths=[3, 5, 2]) == (True, 1)
    assert len((tmp_path / "frames.jsonl").read_text().splitlines()) == 3


def test_reported_jaws_with_an_arms_error_pass_when_the_truth_is_rigid(tmp_path):
    """A take whose reported jaw poses carry an arm's error (2 mm / 2 deg, changing per frame) beside
    the true ones (``T_world_jaw_truth``) loads and checks: the needle is rigid in the true jaws.
    A needle that slips in the true jaws is still found."""
    from common.data.dataset import parse_frame
    meta = _meta()
    frames = _moving(meta)
    rng = np.random.default_rng(3)
    for fr in frames:
        for inst in fr.instruments.values():
            inst.T_world_jaw_truth = np.array(inst.T_world_jaw, float)
            inst.jaw_rad_truth = inst.jaw_rad
            inst.T_world_jaw = inst.T_world_jaw_truth @ make_T(rotvec_to_R(rng.normal(0, 0.02, 3)),
                                                               rng.normal(0, 0.002, 3))
    _write_frames(tmp_path / "err", meta, frames)
    ds = Dataset(tmp_path / "err")
    assert check_dataset(ds).ok, check_dataset(ds).errors
    inst = ds[2].instruments["psm1"]
    assert np.allclose(inst.T_world_jaw_true, frames[2].instruments["psm1"].T_world_jaw_truth)
    assert not np.allclose(inst.T_world_jaw, inst.T_world_jaw_true)
    slip = _moving(meta, slip=1e-4)
    for fr in slip:
        for inst in fr.instruments.values():
            inst.T_world_jaw_truth = np.array(inst.T_world_jaw, float)
    _write_frames(tmp_path / "slip", meta, slip)
    errs = check_dataset(Dataset(tmp_path / "slip")).errors
    assert len(errs) == 1 and "0.1000 mm" in errs[0]
    with pytest.raises(DatasetError, match=r"instruments.psm1.jaw_rad_truth: must be an opening angle"):
        parse_frame({**GOOD, "instruments": {"psm1": {"T_world_jaw": np.eye(4).tolist(), "jaw_rad": 0.1,
                                                        "jaw_rad_truth": -1}}}, 2)
