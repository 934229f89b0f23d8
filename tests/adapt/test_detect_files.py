"""``needletrack detect``: the detector on image files, folders, videos and dataset folders, without
a graph or truth: one JSON line per image, an overlay per image, corrupt files reported and
passed over, bad arguments refused with the path named."""
import json

import cv2
import numpy as np
import pytest

from common.adapt.detect_files import main
from common.detector.detections_file import DetectionRecord, DetectionsFileError, read_detections
from common.runtime.messages import Keypoints

TOL_PX = 3.0
FIELDS = set(DetectionRecord.__struct_fields__)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A dataset folder of three stereo frames freshly rendered (test look, a seed used nowhere
    else); frames 1 and 2 show the needle whole, frame 0 held in the jaws."""
    from common.sim.generate import GenerateConfig, generate
    folder = tmp_path_factory.mktemp("detect") / "ds"
    generate(str(folder), GenerateConfig(sequences=3, steps=1, seed=31337, randomise="test", image_format="png"),
             jobs=1, progress=False)
    from common.data.dataset import Dataset
    return Dataset(str(folder))


def truth(ds, frame, cam):
    fr = ds[frame]
    return np.asarray(fr.keypoints[cam], float), np.asarray(fr.visible[cam], bool)


def run(args, capsys):
    rc = main([str(a) for a in args] + ["--quiet"])
    out, err = capsys.readouterr()
    return rc, out, err


def lines(out_dir):
    text = (out_dir / "detections.jsonl").read_text().splitlines()
    return [json.loads(t) for t in text]


def uv_of(rec):
    return np.array([[rec["keypoints"][k]["u"], rec["keypoints"][k]["v"]] for k in "ABCDE"])


def assert_near(rec, uv_true, visible):
    assert rec["found"], rec["reason"]
    err = np.linalg.norm(uv_of(rec) - uv_true, axis=1)[visible]
    assert err.max() <= TOL_PX, f"{rec['name']}: keypoint errors {np.round(err, 2)} px"
    assert 0.5 <= rec["presence"] <= 1 and all(0 <= rec["keypoints"][k]["score"] <= 1 for k in "ABCDE")


def test_dataset_folder_gives_a_line_and_an_overlay_per_camera_image(dataset, tmp_path, capsys):
    rc, out, _ = run([dataset.path, "--out", tmp_path], capsys)
    assert rc == 0
    recs = lines(tmp_path)
    assert [(r["frame"], r["camera"]) for r in recs] == [(f, c) for f in range(3) for c in ("left", "right")]
    for r in recs:
        assert set(r) == FIELDS
        assert (r["width"], r["height"]) == (1920, 1080) and r["error"] is None and r["ms"] > 0
        assert (tmp_path / "overlays" / f"{r['name']}.png").is_file()
        if r["frame"] > 0:
            assert_near(r, *truth(dataset, r["frame"], r["camera"]))
            assert r["unfamiliarity"] is not None and r["unfamiliarity"] > 0
            assert r["end_identity"] is not None and 0 <= r["end_identity"] <= 1
    overlay = cv2.imread(str(tmp_path / "overlays" / f"{recs[2]['name']}.png"))
    assert overlay.shape[:2] == (720, 1280)
    found = sum(r["found"] for r in recs)
    assert f"6 images: 6 read, 0 unreadable; needle found in {found}" in out
    assert "unfamiliarity of the found needles" in out
    # the records read back through the declared record
    assert [r.name for r in read_detections(tmp_path / "detections.jsonl")] == [r["name"] for r in recs]


def test_folder_reports_a_corrupt_image_and_goes_on(dataset, tmp_path, capsys):
    folder = tmp_path / "pictures"
    folder.mkdir()
    cv2.imwrite(str(folder / "01_needle.png"), dataset.image(1, "left"))
    (folder / "02_corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    cv2.imwrite(str(folder / "03_blank.png"), np.full((1080, 1920, 3), 90, np.uint8))
    cv2.imwrite(str(folder / "04_needle.jpg"), dataset.image(2, "right"), [cv2.IMWRITE_JPEG_QUALITY, 95])
    (folder / "notes.txt").write_text("not an image")
    rc, out, err = run([folder, "--out", tmp_path / "out"], capsys)
    assert rc == 0
    recs = lines(tmp_path / "out")
    assert [r["name"] for r in recs] == ["01_needle", "02_corrupt", "03_blank", "04_needle"]
    needle1, corrupt, blank, needle2 = recs
    assert_near(needle1, *truth(dataset, 1, "left"))
    assert_near(needle2, *truth(dataset, 2, "right"))
    assert needle1["frame"] is None and needle1["camera"] is None
    assert not corrupt["found"] and corrupt["width"] is None and "02_corrupt.png" in corrupt["error"]
    assert "02_corrupt.png" in err
    assert not blank["found"] and blank["keypoints"] is None and blank["reason"] and blank["error"] is None
    made = sorted(p.name for p in (tmp_path / "out" / "overlays").iterdir())
    assert made == ["01_needle.png", "03_blank.png", "04_needle.png"]
    assert "4 images: 3 read, 1 unreadable; needle found in 2" in out


@pytest.fixture(scope="module")
def video(dataset, tmp_path_factory):
    """A Motion-JPEG video: frame 1's left image, a needle-free grey frame, frame 2's left image."""
    path = tmp_path_factory.mktemp("video") / "take.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (1920, 1080))
    assert w.isOpened()
    for img in (dataset.image(1, "left"), np.full((1080, 1920, 3), 90, np.uint8), dataset.image(2, "left")):
        w.write(img)
    w.release()
    return path


@pytest.mark.parametrize("extra, frames", [([], [0, 1, 2]), (["--every", "2"], [0, 2]),
                                           (["--max-frames", "2"], [0, 1]), (["--tracking"], [0, 1, 2])])
def test_video_frames_in_order(dataset, video, tmp_path, capsys, extra, frames):
    rc, _, _ = run([video, "--out", tmp_path] + extra, capsys)
    assert rc == 0
    recs = lines(tmp_path)
    assert [r["frame"] for r in recs] == frames
    assert all(r["source"] == str(video) and set(r) == FIELDS for r in recs)
    for r in recs:
        if r["frame"] == 1:
            assert not r["found"]
        else:
            assert_near(r, *truth(dataset, {0: 1, 2: 2}[r["frame"]], "left"))
        assert (tmp_path / "overlays" / f"{r['name']}.png").is_file()


def test_a_truncated_video_is_reported_after_its_readable_frames(tmp_path, capsys):
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (320, 240))
    rng = np.random.default_rng(0)
    for _ in range(20):
        w.write(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
    w.release()
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])
    rc, out, err = run([path, "--out", tmp_path / "out", "--no-overlays"], capsys)
    assert rc == 0
    recs = lines(tmp_path / "out")
    assert 5 <= len(recs) <= 15 and [r["frame"] for r in recs] == list(range(len(recs)))
    assert all(r["error"] is None for r in recs[:-1])
    assert "truncated or damaged" in recs[-1]["error"] and "clip.avi" in recs[-1]["error"]
    assert "clip.avi" in err and "1 unreadable" in out


def test_side_by_side_stereo_is_split(dataset, tmp_path, capsys):
    path = tmp_path / "sbs.png"
    cv2.imwrite(str(path), np.hstack([dataset.image(2, "left"), dataset.image(2, "right")]))
    rc, _, _ = run([path, "--out", tmp_path / "out", "--split-stereo", "--no-overlays"], capsys)
    assert rc == 0
    left, right = lines(tmp_path / "out")
    assert (left["camera"], right["camera"]) == ("left", "right") and left["width"] == 1920
    assert_near(left, *truth(dataset, 2, "left"))
    assert_near(right, *truth(dataset, 2, "right"))
    assert not (tmp_path / "out" / "overlays").exists() or not any((tmp_path / "out" / "overlays").iterdir())


def test_bad_input_is_refused_naming_the_path(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "empty").mkdir()
    (tmp_path / "broken.mp4").write_bytes(b"not a video at all" * 10)
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(50))
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.full((64, 64, 3), 90, np.uint8))
    cases = [([tmp_path / "notes.txt"], "notes.txt: unknown file extension '.txt'"),
             ([tmp_path / "missing.png"], "missing.png: does not exist"),
             ([tmp_path / "empty"], "empty: a folder without images"),
             ([tmp_path / "broken.mp4"], "broken.mp4"),
             ([tmp_path / "broken.png"], "no image could be read"),
             ([grey, "--every", "0"], "--every 0"),
             ([grey, "--weights", tmp_path / "nope.pt"], "nope.pt: no such file"),
             ([grey, "--backend", "nope"], "backend 'nope' is unknown"),
             ([grey, "--backend", "oracle"], "needs ground truth"),
             ([grey, "--backend", "classical", "--tracking"], "no tracking mode"),
             ([grey, "--param", "threads"], "expected KEY=VALUE"),
             ([grey, "--threshold", "2"], "--threshold 2.0: must be in [0, 1]")]
    for args, said in cases:
        rc, _, err = run(args + ["--out", tmp_path / "out"], capsys)
        assert rc == 1 and "error:" in err and said in err, (args, err)


def test_classical_backend_runs_through_the_same_interface(dataset, tmp_path, capsys):
    rc, _, _ = run([dataset.path, "--out", tmp_path, "--backend", "classical", "--max-frames", "1",
                    "--no-overlays"], capsys)
    assert rc == 0
    recs = lines(tmp_path)
    assert len(recs) == 2 and all(r["detector"] == "classical" for r in recs)


def test_read_detections_names_a_bad_line(tmp_path):
    path = tmp_path / "detections.jsonl"
    path.write_text('{"source": "a.png"}\n')
    with pytest.raises(DetectionsFileError, match=r"detections.jsonl:1"):
        read_detections(path)


def test_overlay_colours_points_by_score_and_says_no_needle():
    from common.viewer.draw import draw_detection, score_bgr
    img = np.zeros((1080, 1920, 3), np.uint8)
    uv = np.array([[400.0, 500.0], [500, 450], [600, 430], [700, 450], [800, 500]])
    scores = np.array([1.0, 0.5, 0.5, 0.5, 0.0])
    kp = Keypoints("left", 0, 0, True, uv, scores, 0.9, detector="test")
    pic = draw_detection(img, kp, zoom_frac=0.0)
    assert pic.shape[:2] == (720, 1280)
    s = 1280 / 1920
    for k in (0, 4):
        x, y = ((uv[k] + 0.5) * s - 0.5).round().astype(int)
        assert np.abs(pic[y, x].astype(int) - score_bgr(scores[k])).max() <= 40
    assert score_bgr(1.0)[1] > 200 and score_bgr(0.0)[2] > 200     # green sure, red unsure
    none = draw_detection(img, Keypoints.not_found("left", 0, 0, "test", "no needle: confidence 0.10"))
    assert none.any() and not none[:, 1000:].any()           # text on the left, nothing drawn elsewhere
