"""Whether a stereo frame's two detections are of one needle, and the track's: a detector that
tracks a crop from frame to frame (one camera each) can stay locked on a distractor (a red marker)
for a whole take while the other camera and the track see the needle elsewhere.

``epipolar_px``: the two cameras' keypoints A..E, each pair triangulated (DLT) and reprojected
into both images: the median distance (undistorted px) of the better of the two readings (as
labelled, or one camera's read end for end: each camera states its own tip), inf for a point
that lands behind a camera or beyond ``MAX_DEPTH_M``. ``track_px``: a camera's keypoints against
the projection of the tracked pose (the better reading again). ``LockCheck`` judges a frame: a
camera whose detection disagrees with the other camera's (``epipolar_px`` above its bound) and
with the track (``track_px`` above its bound) while the other camera's agrees with the track is
a wrong lock; after ``frames`` such frames in a row its crop is to be dropped and searched cold
(``common.detector.inference.KeypointDetector.reject``). Without a track, or with both cameras
off it, nothing is dropped: two cameras that disagree say only that one of them is wrong.
Pixels are the images' own; keypoints (5, 2) with scores (5,), those below ``min_score`` unused.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.observations import undistort_pixels, usable_mask
from common.geometry.transforms import transform_points
from common.geometry.triangulation import triangulate_dlt

MAX_DEPTH_M = 2.0
"""A keypoint pair that triangulates farther than this from a camera is no match (the dense
refinement's ``max_depth_m``)."""
MIN_PAIRS = 2
"""Fewer keypoints usable in both cameras tell nothing (two, the needle's ends, place it)."""


def epipolar_px(rig: StereoRig, uv: Mapping[str, np.ndarray], scores: Mapping[str, np.ndarray],
                min_score: float = 0.5) -> float | None:
    """How far (median, px) the two cameras' keypoints are from being views of the same points
    (module docstring); None when fewer than ``MIN_PAIRS`` are usable in both."""
    if not all(c in uv and uv[c] is not None for c in CAMERAS):
        return None
    L, R = (np.asarray(uv[c], float).reshape(-1, 2) for c in CAMERAS)
    okL, okR = (usable_mask(uv[c], scores.get(c), min_score) for c in CAMERAS)
    best = None
    for turned in (False, True):
        r, ok_r = (R[::-1], okR[::-1]) if turned else (R, okR)
        ok = okL & ok_r
        if ok.sum() < MIN_PAIRS:
            continue
        d = _pair_distances(rig, L[ok], r[ok])
        m = float(np.median(d))
        best = m if best is None else min(best, m)
    return best


def _pair_distances(rig: StereoRig, uv_left: np.ndarray, uv_right: np.ndarray) -> np.ndarray:
    ul, ur = undistort_pixels(rig.left, uv_left), undistort_pixels(rig.right, uv_right)
    X = triangulate_dlt(ul, ur, rig.left.P_ecm, rig.right.P_ecm)
    d = np.zeros(len(X))
    for cam, u in ((rig.left, ul), (rig.right, ur)):
        p = transform_points(cam.T_cam_ecm, X)
        z = p[:, 2]
        bad = ~np.isfinite(z) | (z <= 0) | (z > MAX_DEPTH_M)
        proj = p[:, :2] / np.where(bad, 1.0, z)[:, None] @ cam.K[:2, :2].T + cam.K[:2, 2]
        d = np.maximum(d, np.where(bad, np.inf, np.linalg.norm(proj - u, axis=1)))
    return d


def track_px(rig: StereoRig, needle: NeedleModel, T_ecm_needle: np.ndarray, camera: str, uv: np.ndarray,
             scores: np.ndarray | None, min_score: float = 0.5) -> float | None:
    """How far (median, px) a camera's usable keypoints lie from the tracked pose's projection,
    the better of the two readings; None when fewer than ``MIN_PAIRS`` are usable."""
    pts = np.asarray(uv, float).reshape(-1, 2)
    ok = usable_mask(uv, scores, min_score)
    if ok.sum() < MIN_PAIRS:
        return None
    cam = rig[camera]
    proj = cam.project_from_ecm(transform_points(T_ecm_needle, needle.keypoints()))
    return float(min(np.median(np.linalg.norm(pts[ok] - p[ok], axis=1)) for p in (proj, proj[::-1])))


@dataclass(frozen=True)
class LockCheckConfig:
    """``max_epipolar_px``: two detections farther apart than this (``epipolar_px``) disagree;
    ``max_track_px``: a detection farther than this from the track's projection (``track_px``)
    is off the track; ``frames``: a camera judged a wrong lock this many stereo frames in a row
    is dropped; ``min_score``: keypoints scored lower are not used."""
    max_epipolar_px: float = 8.0
    max_track_px: float = 30.0
    frames: int = 2
    min_score: float = 0.5

    def __post_init__(self):
        if not (self.max_epipolar_px > 0 and self.max_track_px > 0 and self.frames >= 1):
            raise ValueError(f"LockCheckConfig: max_epipolar_px > 0, max_track_px > 0 and frames >= 1 required, "
                             f"got {self}")


@dataclass(frozen=True)
class LockVerdict:
    """A frame's judgement: ``drop``, the cameras whose crops are to be dropped now; ``wrong``,
    those judged a wrong lock this frame (dropped once ``frames`` in a row); the distances it
    rests on (None: not measured)."""
    drop: tuple[str, ...] = ()
    wrong: tuple[str, ...] = ()
    epipolar_px: float | None = None
    track_px: Mapping[str, float | None] | None = None


class LockCheck:
    """Per stereo frame, which camera's tracked detection is a wrong lock (module docstring);
    keeps each camera's count of wrong frames in a row."""

    def __init__(self, config: LockCheckConfig = LockCheckConfig()):
        self.config = config
        self.run = {c: 0 for c in CAMERAS}

    def reset(self) -> None:
        self.run = {c: 0 for c in CAMERAS}

    def check(self, rig: StereoRig, needle: NeedleModel, uv: Mapping[str, np.ndarray],
              scores: Mapping[str, np.ndarray], T_track: np.ndarray | None) -> LockVerdict:
        """The frame's verdict from both cameras' keypoints (a camera that found nothing is left
        out of ``uv``) and the track's pose in this frame's ECM frame (None: no track)."""
        cfg = self.config
        epi = epipolar_px(rig, uv, scores, cfg.min_score)
        wrong: tuple[str, ...] = ()
        far = None
        if epi is not None and epi > cfg.max_epipolar_px and T_track is not None:
            far = {c: track_px(rig, needle, T_track, c, uv[c], scores.get(c), cfg.min_score) for c in CAMERAS}
            off = {c: d is not None and d > cfg.max_track_px for c, d in far.items()}
            on = {c: d is not None and d <= cfg.max_track_px for c, d in far.items()}
            wrong = tuple(c for c in CAMERAS if off[c] and on[_other(c)])
        for c in CAMERAS:
            self.run[c] = self.run[c] + 1 if c in wrong else 0
        drop = tuple(c for c in wrong if self.run[c] >= cfg.frames)
        for c in drop:
            self.run[c] = 0
        return LockVerdict(drop, wrong, epi, far)


def _other(camera: str) -> str:
    return CAMERAS[1 - CAMERAS.index(camera)]
