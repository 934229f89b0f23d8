"""Lens distortion wherever a pixel meets geometry: the solvers' undistortion converges, the
detector's ellipse test runs on ideal pixels, and a strongly distorted dataset evaluates as
exactly as its pinhole twin with the oracle."""
import pytest
import json

import cv2
import numpy as np

from common.cli import dataset_main
from common.data.check import check_dataset
from common.data.dataset import Dataset
from common.detector.centreline_subpixel import ellipse_residual
from common.detector.learned import _undistorter
from common.evaluation.cli import main as eval_main
from common.geometry.camera import StereoRig, undistort_pixels
from common.geometry.needle import NeedleModel
from common.geometry.refine import project_centreline
from common.geometry.transforms import make_T, rotvec_to_R
from common.ros.synth import distort_dataset
from common.runtime.messages import Calibration

STRONG = np.array([-0.35, 0.15, 0.001, 0.001, 0.0])


def test_undistortion_converges_at_the_corners_of_a_strongly_distorted_image():
    cam = StereoRig.default(1920, 1080).left
    cam.dist = STRONG
    x = np.random.default_rng(0).uniform([-0.9, -0.5], [0.9, 0.5], (500, 2))
    p = np.c_[x, np.ones(len(x))]
    uv = cam.project(p)
    ideal = p[:, :2] @ cam.K[:2, :2].T + cam.K[:2, 2]
    assert np.abs(undistort_pixels(cam.K, cam.dist, uv) - ideal).max() < 1e-6
    # OpenCV's default (5 iterations) is what the solvers used before: off by more than 0.01 px
    default = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K).reshape(-1, 2)
    assert np.abs(default - ideal).max() > 0.01


def test_the_ellipse_test_sees_the_needle_through_the_lens():
    cam = StereoRig.default(1920, 1080).left
    cam.dist = STRONG
    T_cam_needle = make_T(rotvec_to_R(np.array([0.5, 0.3, 0.2])), np.array([0.055, 0.028, 0.08]))
    uv = project_centreline(cam, NeedleModel(), cam.T_ecm_cam @ T_cam_needle, 2.0)
    assert len(uv) > 50
    calib = Calibration(stamp_ns=0, image_size=np.array([1920, 1080]),
                        cameras={c: {"K": cam.K.tolist(), "dist": STRONG.tolist(), "T_ecm_cam": np.eye(4).tolist()}
                                 for c in ("left", "right")}, needle=NeedleModel().to_dict())
    und = _undistorter(calib, "left")
    raw_med, _ = ellipse_residual(uv)
    ideal_med, share = ellipse_residual(und(uv))
    assert ideal_med < 1e-3 and share > 0.99
    assert raw_med > 5 * ideal_med
    calib.cameras["left"]["dist"] = [0.0] * 5
    assert _undistorter(calib, "left") is None


@pytest.mark.graph
def test_a_strongly_distorted_dataset_evaluates_exactly_with_the_oracle(tmp_path):
    rc = dataset_main(["generate", "--out", str(tmp_path / "pinhole"), "--sequences", "2", "--steps", "2",
                       "--width", "640", "--height", "480", "--seed", "11", "--randomise", "none", "--jobs", "1",
                       "--quiet"])
    assert rc == 0
    distort_dataset(str(tmp_path / "pinhole"), str(tmp_path / "distorted"), STRONG.tolist())
    ds = Dataset(tmp_path / "distorted")
    assert check_dataset(ds).ok
    src = Dataset(tmp_path / "pinhole")
    moved = max(np.abs(a.keypoints["left"] - b.keypoints["left"]).max() for a, b in zip(src, ds))
    assert moved > 0.2                      # the lens moves the keypoints (needles near the centre here)
    rc = eval_main(["--dataset", str(tmp_path / "distorted"), "--detector", "oracle", "--out", str(tmp_path / "ev"),
                    "--quiet", "--timeout", "240"])
    assert rc == 0
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    for m in ("pnp_average", "pnp_joint", "triangulation", "multiview", "refined", "multiview_refined"):
        d = res["pose"][m]
        assert d["n"] >= 1, m
        assert d["position_mm"]["max"] < 1e-4 and d["orientation_deg"]["max"] < 1e-3, m
