"""The oracle detector: keypoints from ground truth, with configurable, seeded imperfections.

True keypoints are the exact projections of the model's A..E through ``T_ecm_needle`` and the
camera (distortion included). A keypoint is visible when it lies in front of the camera, inside
the image and, when the ground truth says so, not occluded. Then, independently per keypoint:
it goes missing with probability ``missing_prob``; or becomes a gross outlier with probability
``outlier_prob`` (moved by ``outlier_px`` * U(0.5, 1) in a uniformly random direction); every
reported point gets Gaussian noise of ``noise_px`` per coordinate. Reported points score 1,
missing or invisible ones are NaN with score 0.

Randomness is seeded per frame and camera (``seed``, ``seq``, camera), so a frame gives the same
keypoints whatever the order or number of frames processed before it.

The dense observation (``centreline``): the needle's arc projected about one point per pixel
(``common.geometry.refine.project_centreline``), each point moved along the curve's normal by Gaussian
noise of ``centreline_noise_px`` (default: half of ``noise_px``), on a random stream of its own
(the keypoints do not change when it is used).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from common.geometry.camera import Camera, StereoRig
from common.constraints import NonNegativeNumber, Probability, check_fields
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points

CAMERA_INDEX = {"left": 0, "right": 1}


def true_keypoints(camera: Camera, T_ecm_needle: np.ndarray, model: NeedleModel):
    """(uv (5, 2), visible (5,)): exact projections of A..E; NaN where behind the camera."""
    p_cam = transform_points(camera.T_cam_ecm @ T_ecm_needle, model.keypoints())
    front = p_cam[:, 2] > 1e-6
    uv = np.full((len(p_cam), 2), np.nan)
    if np.any(front):
        uv[front] = camera.project(p_cam[front])
    visible = front & camera.in_image(np.nan_to_num(uv, nan=-1e9))
    return uv, visible


def arc_bbox(camera: Camera, T_ecm_needle: np.ndarray, model: NeedleModel, n: int = 64):
    """[x0, y0, x1, y1] of the projected arc's in-front samples, clipped to the image; None
    when no sample is in front of the camera or inside the image."""
    p_cam = transform_points(camera.T_cam_ecm @ T_ecm_needle, model.sample_arc(n))
    p_cam = p_cam[p_cam[:, 2] > 1e-6]
    if len(p_cam) == 0:
        return None
    uv = camera.project(p_cam)
    uv = uv[camera.in_image(uv)]
    if len(uv) == 0:
        return None
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])


@dataclass
class Oracle:
    """Oracle keypoint generator (see the module docstring). Pixel sizes in px."""

    noise_px: NonNegativeNumber = 0.0
    missing_prob: Probability = 0.0
    outlier_prob: Probability = 0.0
    outlier_px: NonNegativeNumber = 30.0
    seed: int = 0
    centreline_noise_px: Optional[NonNegativeNumber] = None      # None: noise_px / 2

    def __post_init__(self):
        check_fields(self, "oracle: {name} {why}")

    def rng(self, seq: int, camera: str) -> np.random.Generator:
        return np.random.default_rng([abs(int(self.seed)), abs(int(seq)), CAMERA_INDEX.get(camera, 2)])

    def corrupt(self, uv_true, visible, seq: int, camera: str):
        """Apply the imperfections to true pixels -> (uv (5, 2) with NaN rows, scores (5,))."""
        rng = self.rng(seq, camera)
        n = len(uv_true)
        # draw everything up front so one setting does not shift another's random stream
        missing = rng.random(n) < self.missing_prob
        outlier = rng.random(n) < self.outlier_prob
        ang = rng.uniform(0.0, 2 * np.pi, n)
        mag = self.outlier_px * rng.uniform(0.5, 1.0, n)
        noise = rng.normal(0.0, 1.0, (n, 2)) * self.noise_px
        uv = np.asarray(uv_true, dtype=float) + noise
        uv[outlier] += (mag[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1))[outlier]
        keep = np.asarray(visible, dtype=bool) & ~missing
        uv[~keep] = np.nan
        return uv, keep.astype(float)

    def keypoints(self, camera: Camera, T_ecm_needle, model: NeedleModel, seq: int,
                  visible=None):
        """(uv (5, 2), scores (5,)) for one camera; ``visible`` (5,) adds occlusion info."""
        uv, vis = true_keypoints(camera, np.asarray(T_ecm_needle, dtype=float), model)
        if visible is not None:
            vis &= np.asarray(visible, dtype=bool)
        return self.corrupt(np.nan_to_num(uv), vis, seq, camera.name)

    def centreline(self, camera: Camera, T_ecm_needle, model: NeedleModel, seq: int):
        """(points (N, 2), weights (N,)): the projected arc A..E in this camera with noise along
        its normal (see the module docstring); N is 0 when none of it is in the image."""
        from common.geometry.observations import curve_normals
        from common.geometry.refine import project_centreline
        c = project_centreline(camera, model, np.asarray(T_ecm_needle, dtype=float))
        sigma = self.noise_px / 2 if self.centreline_noise_px is None else self.centreline_noise_px
        if sigma > 0 and len(c) > 1:
            rng = np.random.default_rng([abs(int(self.seed)), abs(int(seq)),
                                         CAMERA_INDEX.get(camera.name, 2), 1])
            c = c + curve_normals(c) * rng.normal(0.0, sigma, (len(c), 1))
        return c, np.ones(len(c))

    def stereo(self, rig: StereoRig, T_ecm_needle, model: NeedleModel, seq: int) -> tuple[dict, dict]:
        """``({camera: uv}, {camera: scores})`` for both cameras, as the pose solvers take them."""
        uv, sc = {}, {}
        for cam in rig.cameras:
            uv[cam.name], sc[cam.name] = self.keypoints(cam, T_ecm_needle, model, seq)
        return uv, sc

    def stereo_arcs(self, rig: StereoRig, T_ecm_needle, model: NeedleModel, seq: int):
        """``({camera: uv}, {camera: scores}, {camera: ArcObservation})`` for both cameras: the
        keypoints as the PnP takes them and, with the centreline, as the refinement does."""
        from common.geometry.refine import ArcObservation
        uv, sc = self.stereo(rig, T_ecm_needle, model, seq)
        obs = {}
        for cam in rig.cameras:
            c, w = self.centreline(cam, T_ecm_needle, model, seq)
            obs[cam.name] = ArcObservation(uv[cam.name], sc[cam.name], c, w)
        return uv, sc, obs


def truth_T_ecm_needle(truth) -> np.ndarray | None:
    """``T_ecm_needle`` from a GroundTruth (None when its poses are not both known)."""
    if truth is None or truth.T_world_ecm is None or truth.T_world_needle is None:
        return None
    return inv_T(np.asarray(truth.T_world_ecm, float)) @ np.asarray(truth.T_world_needle, float)


# ---------------------------------------------------------------------- test-bed poses

def perturb_pose(T_ecm_needle: np.ndarray, rng: np.random.Generator, mm: float, deg: float) -> np.ndarray:
    """The pose moved by exactly ``mm`` and turned by exactly ``deg`` about the needle origin,
    both along random ECM-frame axes (a start for a fit, or the next frame of a video)."""
    axis, way = rng.normal(size=3), rng.normal(size=3)
    dR = rotvec_to_R(axis / np.linalg.norm(axis) * np.deg2rad(deg))
    return make_T(dR @ T_ecm_needle[:3, :3], T_ecm_needle[:3, 3] + way / np.linalg.norm(way) * mm * 1e-3)


def needle_pose_in_view(distance_m: float, direction_xy, quat) -> np.ndarray:
    """``T_ecm_needle`` with the needle's origin ``distance_m`` from the ECM origin along the
    viewing direction ``[x, y, 1]`` of the built-in endoscope's cameras (which look along
    -z_ecm, y_cam = -y_ecm), and orientation from the quaternion [w, x, y, z] (normalised)."""
    from common.geometry.transforms import make_T, quat_to_R
    d = np.array([direction_xy[0], -direction_xy[1], -1.0])
    return make_T(quat_to_R(np.asarray(quat, dtype=float)), distance_m * d / np.linalg.norm(d))


def view_tilt_rad(T_ecm_needle: np.ndarray, eye_ecm=np.zeros(3)) -> float:
    """Angle (rad, [0, pi/2]) between the needle plane's normal and the line of sight from
    ``eye_ecm`` to the needle's origin: 0 is face-on, pi/2 edge-on."""
    los = T_ecm_needle[:3, 3] - np.asarray(eye_ecm, dtype=float)
    c = abs(T_ecm_needle[:3, 2] @ los) / np.linalg.norm(los)
    return float(np.arccos(min(1.0, c)))


def random_needle_pose(rng: np.random.Generator, rig: StereoRig, model: NeedleModel,
                       distance_m=(0.10, 0.25), max_tilt_rad: float = np.deg2rad(75.0),
                       max_offaxis: float = 0.35, margin_px: float = 20.0) -> np.ndarray:
    """A random ``T_ecm_needle`` of the test protocol: the needle 10-25 cm away, uniformly
    random orientation not seen within ``pi/2 - max_tilt_rad`` of edge-on (where the arc
    degenerates to a line in the image), every keypoint inside both images by ``margin_px``."""
    for _ in range(10000):
        T = needle_pose_in_view(rng.uniform(*distance_m), rng.uniform(-max_offaxis, max_offaxis, 2),
                                rng.normal(size=4))
        if view_tilt_rad(T) > max_tilt_rad:
            continue
        if all(_inside(cam, T, model, margin_px) for cam in rig.cameras):
            return T
    raise RuntimeError("random_needle_pose: no pose found in view; check the rig and limits")


def _inside(cam: Camera, T, model, margin_px) -> bool:
    uv, vis = true_keypoints(cam, T, model)
    return bool(np.all(vis) and np.all(uv >= margin_px)
                and np.all(uv[:, 0] <= cam.width - 1 - margin_px)
                and np.all(uv[:, 1] <= cam.height - 1 - margin_px))
