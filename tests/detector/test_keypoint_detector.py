"""The learned detector at inference: the shipped model on a freshly rendered frame, bad input,
bad weight files, tracking, and the detector-node backend."""
import logging

import numpy as np
import pytest
import torch

from common.detector.backends import BackendError, load_backend
from common.detector.arc_fit import decode_centreline
from common.detector.inference import KEYPOINT_SIGMA_PX, RETRY_EVERY, RETRY_PRESENCE, KeypointDetector
from common.detector.weights import DEFAULT_WEIGHTS, ModelFileError, load_model
from common.detector.model import KeypointModel, ModelConfig
from common.detector.train import save_model
from common.runtime.messages import CameraImage, Keypoints


@pytest.fixture(scope="module")
def detector():
    return KeypointDetector(device="cpu")


@pytest.fixture(scope="module")
def rendered_frames():
    """Three stereo frames freshly rendered by the simulator (test look, a seed used nowhere else)."""
    from common.sim.generate import GenerateConfig, render_sequence
    from common.sim.render import SceneRenderer
    cfg = GenerateConfig(sequences=3, steps=1, seed=987_654, randomise="test", image_format="png")
    renderer = SceneRenderer()
    return [render_sequence(renderer, cfg, s)[0][:2] for s in range(3)]


@pytest.fixture(scope="module")
def rendered(rendered_frames):
    return rendered_frames[0]


def test_shipped_model_finds_the_needle_in_rendered_frames(detector, rendered_frames):
    errors, found = [], 0
    for images, fields in rendered_frames:
        for cam in ("left", "right"):
            detector.reset()
            kp = detector.detect(images[cam], cam, seq=1)
            if not kp.found:
                continue
            found += 1
            assert 0.5 <= kp.confidence <= 1.0 and kp.scores.shape == (5,)
            vis = np.asarray(fields["visible"][cam], bool)
            truth = np.asarray(fields["keypoints"][cam], float)
            errors += list(np.linalg.norm(kp.uv - truth, axis=1)[vis])
            # the dense centreline is ordered from A to E
            w = kp.centreline_w > 0
            assert kp.centreline.shape[1] == 2 and w.sum() >= 10
            assert np.linalg.norm(kp.centreline[0] - kp.uv[0]) < np.linalg.norm(kp.centreline[0] - kp.uv[4])
    assert found >= 3, f"needle found in only {found} of 6 images"
    assert np.median(errors) <= 2.0, f"keypoint errors {np.round(errors, 2)} px"


@pytest.mark.slow
def test_centreline_is_sub_pixel_in_the_full_resolution_image(rendered_frames):
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.geometry.refine import project_centreline
    rig, needle = StereoRig.default(), NeedleModel()
    dist = {}
    for subpixel in (False, True):
        det, d = KeypointDetector(device="cpu", subpixel=subpixel), []
        for images, fields in rendered_frames:
            T_ecm_needle = np.linalg.inv(np.asarray(fields["T_world_ecm"])) @ np.asarray(fields["T_world_needle"])
            for cam in ("left", "right"):
                kp = det.detect(images[cam], cam)
                if not kp.found:
                    continue
                assert (kp.centreline_sigma_px is not None) == subpixel == (kp.centreline_corr_points is not None)
                assert kp.keypoint_sigma_px == KEYPOINT_SIGMA_PX
                # B..D placed on the arc through A and E when both ends are sure, else observed
                assert kp.on_arc is None or list(kp.on_arc) == [False, True, True, True, False]
                arc = project_centreline(rig[cam], needle, T_ecm_needle, spacing_px=0.2)
                pts = kp.centreline[kp.centreline_w > 0]
                d += list(np.linalg.norm(pts[:, None] - arc[None], axis=2).min(1))
        dist[subpixel] = np.median(d)
    assert dist[True] < 0.15 and dist[True] < 0.7 * dist[False], dist


def test_a_centreline_off_an_ellipse_is_no_needle(rendered):
    images, _ = rendered
    # no centreline is that exact
    strict = KeypointDetector(device="cpu", max_ellipse_px=1e-4, keypoints_only_ellipse_px=1e-4)
    kp = strict.detect(images["left"], "left")
    assert not kp.found and "not an ellipse arc" in kp.reason and np.isnan(kp.uv).all()
    assert KeypointDetector(device="cpu", max_ellipse_px=0).detect(images["left"], "left").found


def test_a_centreline_near_an_ellipse_gives_the_keypoints_alone_and_no_track(rendered):
    images, _ = rendered
    exact = KeypointDetector(device="cpu")
    full = exact.detect(images["left"], "left")
    assert full.found and full.centreline is not None and "left" in exact._track
    near = KeypointDetector(device="cpu", max_ellipse_px=1e-4)      # within 1.5 px, not 1e-4
    kp = near.detect(images["left"], "left")
    assert kp.found and kp.centreline is None and kp.centreline_sigma_px is None
    np.testing.assert_allclose(kp.uv, full.uv)
    assert not near._track                                           # the next frame is found cold


def test_collapsed_keypoints_are_no_needle(rendered):
    images, _ = rendered
    det = KeypointDetector(device="cpu", min_extent_px=5000)
    kp = det.detect(images["left"], "left")
    assert not kp.found and "keypoints collapsed" in kp.reason and np.isnan(kp.uv).all()


def test_tracking_reuses_the_box_and_gives_the_same_answer(rendered):
    images, _ = rendered
    det = KeypointDetector(device="cpu", tracking=True)
    a = det.detect(images["left"], "left")
    assert det.last_mode == "cold"
    b = det.detect(images["left"], "left")
    assert det.last_mode == "tracking" and b.found
    assert np.abs(a.uv - b.uv).max() < 2.0
    # a blank frame ends tracking with "no needle"
    c = det.detect(np.full_like(images["left"], 128), "left")
    assert not c.found and "no needle" in c.reason and np.isnan(c.uv).all()



def test_a_cold_frame_found_nowhere_is_searched_again_with_its_hues_turned(rendered):
    """A look the networks read only turned: the frame's hues turned by -120 deg, and stage 2
    made to pass only on crops turned by +120 (which gives the rendered look back). The frame is
    found on that retry with the keypoints of the rendered look, and the camera's tracking frames keep
    the turn; without retries it is not found."""
    from common.detector.data import turn_hue
    images, _ = rendered
    image = turn_hue(images["left"], -120.0)
    det = KeypointDetector(device="cpu", retry_hues=(240.0, 120.0))
    real, calls = det._stage2, []

    def only_turned_back(img, box, ridge=False, hue_deg=0.0):
        calls.append(hue_deg)
        res = real(img, box, ridge, hue_deg)
        if hue_deg != 120.0:
            res["presence"] = 0.0
        return res

    det._stage2 = only_turned_back
    kp = det.detect(image, "left")
    assert kp.found and det.last_mode == "cold" and {0.0, 120.0, 240.0} <= set(calls)
    as_rendered = KeypointDetector(device="cpu").detect(images["left"], "left")
    assert np.linalg.norm(kp.uv - as_rendered.uv, axis=1).max() < 1.0    # read as the render is
    calls.clear()
    assert det.detect(image, "left").found and det.last_mode == "tracking" and calls == [120.0]
    det.reset("left")
    assert det._hue == {}

    # a needle found only turned must be surer than the detection threshold
    unsure = KeypointDetector(device="cpu", retry_hues=(120.0,))
    real_unsure = unsure._stage2
    unsure._stage2 = lambda img, box, ridge=False, hue_deg=0.0: {
        **real_unsure(img, box, ridge, hue_deg), "presence": 0.0 if hue_deg != 120.0 else RETRY_PRESENCE - 0.05}
    assert not unsure.detect(image, "left").found

    off = KeypointDetector(device="cpu", retry_hues=())
    real_off, off_calls = off._stage2, []
    off._stage2 = lambda img, box, ridge=False, hue_deg=0.0: (
        off_calls.append(hue_deg) or {**real_off(img, box, ridge, hue_deg), "presence": 0.0})
    kp = off.detect(image, "left")
    assert not kp.found and "confidence" in kp.reason and set(off_calls) == {0.0}


def test_the_detector_node_counts_and_says_once_a_needle_found_only_turned(rendered, caplog):
    from common.detector.data import turn_hue
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.runtime.messages import Calibration
    from nodes.detector import DetectorNode
    images, _ = rendered
    calib = Calibration(0, np.array([1920, 1080]), StereoRig.default().to_dict(), NeedleModel().to_dict())
    node = DetectorNode.offline({"backend": "learned", "device": "cpu", "threads": 1, "retry_hues": [240, 120],
                                 "tracking": False}, wired=["left", "calib"])
    node.on_calib(calib)
    det = node.backend.detector
    real = det._stage2
    det._stage2 = lambda img, box, ridge=False, hue_deg=0.0: {
        **real(img, box, ridge, hue_deg), **({} if hue_deg == 120.0 else {"presence": 0.0})}
    frame = CameraImage.from_bgr("left", 1, 10, turn_hue(images["left"], -120.0), "png")
    with caplog.at_level(logging.INFO):
        node.on_left(frame)
        node.on_left(frame)
    assert all(kp.found for _, kp in node.published) and len(node.published) == 2
    assert node.counters["found_turned"] == 2
    assert sum("hues turned (120 deg)" in r.getMessage() for r in caplog.records) == 1
    det._stage2 = real
    node.on_left(CameraImage.from_bgr("left", 2, 20, images["left"], "png"))
    assert node.counters["found_turned"] == 2 and det.last_turn == 0.0


def test_after_turns_found_nothing_the_next_cold_frames_are_searched_as_they_are(rendered):
    images, _ = rendered
    det = KeypointDetector(device="cpu", retry_hues=(120.0, 240.0))
    real, calls = det._stage2, []
    det._stage2 = lambda img, box, ridge=False, hue_deg=0.0: (
        calls.append(hue_deg) or {**real(img, box, ridge, hue_deg), "presence": 0.0})
    turned = []
    for _ in range(2 * RETRY_EVERY):
        calls.clear()
        assert not det.detect(images["left"], "left").found
        turned.append(any(calls))
    assert turned == ([True] + [False] * (RETRY_EVERY - 1)) * 2
    det.reset()
    calls.clear()
    det.detect(images["left"], "left")
    assert any(calls)


def test_needle_free_image_is_no_needle(detector):
    rng = np.random.default_rng(0)
    img = np.clip(rng.normal(150, 20, (1080, 1920, 3)), 0, 255).astype(np.uint8)
    img[..., 2] = 200   # pinkish noise, no needle
    detector.reset()
    kp = detector.detect(img, "left")
    assert not kp.found and kp.confidence < 0.5 and np.isnan(kp.uv).all()


@pytest.mark.parametrize("bad", [np.zeros((0, 0, 3), np.uint8), np.zeros((1080, 1920, 3), np.float32),
                                 np.zeros((1080, 1920, 2), np.uint8), np.zeros((4, 4, 3), np.uint8),
                                 None, "image"])
def test_bad_arrays_give_no_needle_with_a_logged_reason(detector, bad, caplog):
    with caplog.at_level(logging.WARNING, logger="needletrack.keypoint_detector"):
        kp = detector.detect(bad, "right", seq=4)
    assert isinstance(kp, Keypoints) and not kp.found and kp.reason.startswith("bad image")
    assert kp.seq == 4 and kp.camera == "right"
    assert "bad image" in caplog.text


def test_corrupt_image_bytes_give_no_needle(detector, caplog):
    msg = CameraImage("left", 9, 0, 1920, 1080, "jpeg", b"\xff\xd8 definitely not a jpeg")
    with caplog.at_level(logging.WARNING, logger="needletrack.keypoint_detector"):
        kp = detector.detect_message(msg)
    assert not kp.found and "corrupt" in kp.reason and "corrupt" in caplog.text


def test_weight_file_errors_say_how_to_retrain(tmp_path):
    with pytest.raises(ModelFileError, match=r"no such weights file.*needletrack train"):
        load_model(tmp_path / "missing.pt")
    bad = tmp_path / "corrupt.pt"
    bad.write_bytes(DEFAULT_WEIGHTS.read_bytes()[:5000])
    with pytest.raises(ModelFileError, match=r"corrupt.*needletrack train"):
        load_model(bad)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(ModelFileError, match=r"not a needletrack.*needletrack train"):
        load_model(other)
    # right format, different architecture than its config says
    mismatched = tmp_path / "mismatched.pt"
    save_model(mismatched, KeypointModel(ModelConfig(crop_widths=(8, 8, 8, 8))), {})
    blob = torch.load(mismatched, weights_only=True)
    blob["config"]["crop_widths"] = [16, 32, 48, 80]
    torch.save(blob, mismatched)
    with pytest.raises(ModelFileError, match=r"do not match.*needletrack train"):
        load_model(mismatched)
    with pytest.raises(BackendError, match="needletrack train"):
        load_backend("learned", {"weights": str(tmp_path / "missing.pt")})


def test_backend_runs_through_the_registry(rendered):
    images, fields = rendered
    b = load_backend("learned", {"device": "cpu", "threshold": 0.5})
    kp = b.detect(images["right"], "right", None, None, seq=3, stamp_ns=5)
    assert kp.found and kp.seq == 3 and kp.stamp_ns == 5 and kp.detector == "learned"


def test_centreline_decoding_finds_a_ridge_at_subcell_precision():
    m = 64
    yy, xx = np.mgrid[0:m, 0:m].astype(np.float32)
    ridge_y = 30.3 + 0.1 * (xx - 32)              # a straight ridge, off the pixel grid
    p = np.exp(-0.5 * ((yy - ridge_y) / 1.0) ** 2) * 0.999
    logit = np.log(p + 1e-7) - np.log(1 - p + 1e-7)
    kp = np.stack([np.linspace(10, 54, 5), 30.3 + 0.1 * (np.linspace(10, 54, 5) - 32) + 1.5], 1)
    pts, w = decode_centreline(logit, kp, n=20)
    assert np.all(w > 0.5)
    err = np.abs(pts[:, 1] - (30.3 + 0.1 * (pts[:, 0] - 32)))
    assert err.max() < 0.3 and np.median(err) < 0.05
    assert pts[0, 0] < pts[-1, 0]                  # ordered like the keypoints


def test_arc_fit_recovers_b_c_d_of_an_affine_arc():
    from common.detector.arc_fit import ARC_ANGLES_DEG, arc_at, fit_arc_affine, refine_along_arc
    from common.detector.model import centreline_target
    c = np.array([60.3, 70.6])
    U = np.array([[30.0, 8.0], [-5.0, -18.0]])      # a tilted, foreshortened circle
    t = np.deg2rad(np.asarray(ARC_ANGLES_DEG))
    kp = c + np.stack([np.cos(t), np.sin(t)], 1) @ U.T
    tt = np.linspace(t[0], t[-1], 200)
    dense = c + np.stack([np.cos(tt), np.sin(tt)], 1) @ U.T
    ridge = centreline_target([dense], 128, 1.0)[0].numpy()
    logit = np.log(ridge + 1e-6) - np.log(1 - ridge + 1e-6)
    fit = fit_arc_affine(kp[0], kp[4], logit)
    assert fit is not None
    pred = arc_at(fit, ARC_ANGLES_DEG)
    assert np.abs(pred - kp).max() < 0.3
    # a flat keypoint heatmap leaves the affine angle; a peaked one pulls the point along the arc
    flat = np.full((128, 128), 1.0 / 128 ** 2)
    assert refine_along_arc(flat, fit, 90.0) == pytest.approx(90.0, abs=0.5)
    peak = np.zeros((128, 128))
    q = c + np.array([np.cos(t[2] + 0.1), np.sin(t[2] + 0.1)]) @ U.T
    peak[int(round(q[1])), int(round(q[0]))] = 1.0
    assert refine_along_arc(peak, fit, 90.0) == pytest.approx(90.0 + np.rad2deg(0.1), abs=2.5)
    # no ridge: no fit
    assert fit_arc_affine(kp[0], kp[4], np.full((128, 128), -9.0)) is None


def test_detector_node_with_the_learned_backend_on_one_camera(rendered):
    """One detector process per camera: only ``left`` wired; a JPEG frame gives keypoints, corrupt
    bytes give "no needle" with the reason, counted, and the node keeps going."""
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.runtime.messages import Calibration, MessageError, decode, encode
    from nodes.detector import DetectorNode
    images, fields = rendered
    calib = Calibration(0, np.array([1920, 1080]), StereoRig.default().to_dict(), NeedleModel().to_dict())
    node = DetectorNode.offline({"backend": "learned", "device": "cpu", "threads": 1}, wired=["left", "calib"])
    node.on_calib(decode(encode(calib), Calibration))
    corrupt = CameraImage("left", 1, 10, 1, 1, "png", b"corrupt")
    with pytest.raises(MessageError, match="not a png"):          # the codec refuses it ...
        decode(encode(corrupt), CameraImage)
    node.on_left(corrupt)                                          # ... a handler given it copes
    node.on_left(decode(encode(CameraImage.from_bgr("left", 2, 20, images["left"], "jpeg")), CameraImage))
    (o1, bad), (o2, good) = node.published
    assert o1 == o2 == "left"
    assert not bad.found and bad.reason.startswith("bad image") and node.counters["bad_image"] == 1
    assert good.found and good.seq == 2 and good.detector == "learned"
    vis = np.asarray(fields["visible"]["left"], bool)
    err = np.linalg.norm(good.uv - np.asarray(fields["keypoints"]["left"]), axis=1)[vis]
    assert np.median(err) < 5.0


def test_each_detection_states_how_unlike_the_training_looks_its_image_is(detector, rendered):
    """The shipped familiarity.json: a test-look render is familiar (about 1), and what the
    detection states is the reference's distance of its crop descriptor (tests/detector/test_familiarity.py
    shows it growing off the reference)."""
    images, _ = rendered
    detector.reset()
    kp = detector.detect(images["left"], "left")
    assert kp.found and 0.3 < kp.unfamiliarity < 2.0
    assert detector.last_evidence.unfamiliarity == pytest.approx(kp.unfamiliarity)
    assert detector.familiarity.unfamiliarity(detector.last_descriptor) == pytest.approx(kp.unfamiliarity)
    detector.reset()


def test_a_familiarity_file_for_other_weights_is_refused(tmp_path):
    import json
    import shutil

    from common.detector.familiarity import FamiliarityFileError
    shutil.copy(DEFAULT_WEIGHTS, tmp_path / "model.pt")
    fam = json.loads(DEFAULT_WEIGHTS.with_name("familiarity.json").read_text())
    fam["mean"] = fam["mean"][:10]
    fam["components"] = [c[:10] for c in fam["components"]]
    (tmp_path / "familiarity.json").write_text(json.dumps(fam))
    with pytest.raises(FamiliarityFileError, match="familiarity.json: a reference of 10 features.*bench familiarity"):
        KeypointDetector(tmp_path / "model.pt", device="cpu")
    (tmp_path / "familiarity.json").unlink()
    assert KeypointDetector(tmp_path / "model.pt", device="cpu").familiarity is None


def test_a_lock_on_a_distractor_that_the_other_camera_and_the_track_disagree_with_is_dropped(rendered):
    """Issue 56 (the right camera locked on a red marker for a whole take): a distractor that stage 1
    ranks first and stage 2 passes as a needle (the real network's result, moved 300 px), and the
    right camera's tracking state pointing at it. Each frame the two cameras' detections and the
    track (the true pose) are checked (``stereo_agreement.LockCheck``); a rejected camera is
    ``reject``-ed with its box. The right camera is dropped, searched cold away from the distractor
    and back on the needle within a few frames; the left camera, and a right lock, are kept."""
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.geometry.stereo_agreement import LockCheck
    from common.geometry.transforms import inv_T
    images, fields = rendered
    rig, needle = StereoRig.default(), NeedleModel()
    T_track = inv_T(np.asarray(fields["T_world_ecm"], float)) @ np.asarray(fields["T_world_needle"], float)
    truth = {c: np.asarray(fields["keypoints"][c], float) for c in ("left", "right")}
    shift = np.array([-300.0, 150.0])

    def with_distractor(det, cam):
        """``det``'s stages see a distractor in ``cam``'s image, ``shift`` from the needle."""
        needle_box = det._box_of({"uv": det.detect(images[cam], cam).uv})
        det.reset()
        real1, real2 = det._stage1, det._stage2
        dx, dy = needle_box[0] + shift[0], needle_box[1] + shift[1]
        half = max(needle_box[2], needle_box[3]) / 2

        def on_distractor(box):
            return abs(box[0] - dx) < half and abs(box[1] - dy) < half

        def stage1(img, hue_deg=0.0):
            real = list(real1(img, hue_deg))
            return ([(0.99, dx, dy, needle_box[2], needle_box[3])] if img is images[cam] else []) + real

        def stage2(img, box, ridge=False, hue_deg=0.0):
            if img is not images[cam] or not on_distractor(box):
                return real2(img, box, ridge, hue_deg)
            back = (box[0] - shift[0], box[1] - shift[1], box[2], box[3])
            res = real2(img, back, ridge, hue_deg)
            return {**res, "uv": res["uv"] + shift, "presence": max(res["presence"], 0.95)}
        det._stage1, det._stage2 = stage1, stage2
        return (dx, dy, needle_box[2], needle_box[3]), needle_box

    def run(det, frames=8):
        check, on_needle, rejected = LockCheck(), [], []
        for seq in range(frames):
            kps = {c: det.detect(images[c], c, seq=seq) for c in ("left", "right")}
            uv = {c: k.uv for c, k in kps.items() if k.found}
            sc = {c: k.scores for c, k in kps.items() if k.found}
            for cam in check.check(rig, needle, uv, sc, T_track).drop:
                rejected.append((seq, cam))
                det.reject(cam, kps[cam].bbox)
            on_needle.append({c: bool(k.found and np.median(np.linalg.norm(k.uv - truth[c], axis=1)) < 10.0)
                              for c, k in kps.items()})
        return on_needle, rejected

    # arc_bcd and the centreline off: the distractor's keypoints are the network's, moved whole
    det = KeypointDetector(device="cpu", tracking=True, arc_bcd=False, centreline=False)
    det._track["right"] = with_distractor(det, "right")[0]         # locked on it from the start
    on_needle, rejected = run(det)
    assert not on_needle[0]["right"] and on_needle[0]["left"]
    assert rejected and all(cam == "right" for _, cam in rejected) and rejected[0][0] <= 2
    back = next(i for i, f in enumerate(on_needle) if f["right"])
    assert back <= 4 and all(f["right"] and f["left"] for f in on_needle[back:]), on_needle
    assert len(rejected) == 1

    # a right lock is kept: the same distractor, the right camera tracking the needle
    det = KeypointDetector(device="cpu", tracking=True, arc_bcd=False, centreline=False)
    det._track["right"] = with_distractor(det, "right")[1]
    on_needle, rejected = run(det, 5)
    assert rejected == [] and all(f["left"] and f["right"] for f in on_needle)
