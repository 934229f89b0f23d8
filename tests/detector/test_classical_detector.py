"""The classical (OpenCV-only) backend: finds a drawn needle, rejects blank and bad images."""
import numpy as np

from common.detector.backends import load_backend
from common.detector.classical import ClassicalDetector
from common.detector.synthetic import _background, render_synthetic
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import make_T, rotvec_to_R, transform_points


def _drawn_needle(seed=0):
    """A 1280x720 image with a needle drawn face-on 8 cm away, and its true keypoints."""
    rng = np.random.default_rng(seed)
    rig = StereoRig.default(1280, 720)
    needle = NeedleModel()
    T_left = make_T(rotvec_to_R(np.array([0.2, -0.1, 0.4])), np.array([0.0, 0.0, 0.08]))
    T = {"left": T_left}
    bg = _background(rng, 720, 1280)
    img = render_synthetic(rig, needle, T, rng, "left", bg)
    kp = rig.left.project(transform_points(T_left, needle.keypoints()))
    return img, kp


def test_finds_a_drawn_needle():
    """A baseline, not a precise detector: it finds the needle and its arc lies on it (the
    placement of A..E is coarse; `needletrack bench detector --backend classical` measures it)."""
    img, kp = _drawn_needle()
    det = ClassicalDetector()
    r = det.detect(img, "left", seq=2)
    assert r.found, r.reason
    lo, hi = kp.min(0) - 10, kp.max(0) + 10
    assert np.all((r.uv >= lo - 60) & (r.uv <= hi + 60))
    assert r.centreline is not None and len(r.centreline) == len(r.centreline_w)
    # the middle of the fitted arc lies on the drawn wire
    mid = r.centreline[len(r.centreline) // 4: 3 * len(r.centreline) // 4]
    dense = np.concatenate([np.linspace(kp[i], kp[i + 1], 30) for i in range(4)])
    d = np.linalg.norm(mid[:, None] - dense[None], axis=2).min(1)
    assert np.median(d) < 6.0


def test_blank_and_bad_images_are_no_needle():
    det = ClassicalDetector()
    rng = np.random.default_rng(1)
    blank = _background(rng, 720, 1280)
    assert not det.detect(blank, "left").found
    for bad in (np.zeros((0, 0, 3), np.uint8), np.zeros((720, 1280, 3), np.float32), None):
        r = det.detect(bad, "right", seq=5)
        assert not r.found and r.reason.startswith("bad image") and r.seq == 5


def test_registered_as_a_detector_backend():
    img, kp = _drawn_needle(3)
    b = load_backend("classical", {"threshold": 0.5})
    r = b.detect(img, "left", None, None, seq=1, stamp_ns=2)
    assert r.detector == "classical" and r.seq == 1
