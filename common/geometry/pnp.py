"""Pipeline I: the needle pose ``T_ecm_needle`` from its keypoints by Perspective-n-Point.

Two methods, both in the ECM frame (m, rad), both on ideal (undistorted) pixels:

- ``pnp_average`` (the paper): per camera, OpenCV EPnP (``SOLVEPNP_EPNP``) on the usable
  keypoints, mapped through ``T_ecm_cam``; the left and right poses are then averaged (chordal
  rotation mean, score-weighted mean translation). The five keypoints are coplanar and EPnP is
  not exact on them even without noise (see docs/geometry.md#pose-sensitivity), so by default
  each camera's EPnP pose is refined by Levenberg-Marquardt in that camera, together with
  the two IPPE solutions of the planar two-fold ambiguity, and the camera keeps the refined
  candidate with the lowest reprojection error in its own image. ``refine=False`` gives raw
  EPnP (the paper as published).
- ``pnp_joint``: one pose refined by Levenberg-Marquardt on the reprojection error in both
  cameras at once, started from every camera's EPnP pose and both IPPE solutions; the local
  minima are kept, deduplicated and sorted by cost, and the best one (the candidate consistent
  with both views) is the pose. ``candidates`` lets a later refinement stage start from all.

Fits are weighted by keypoint score (cost = sum_i w_i |r_i|^2, r_i the pixel residual of point
i); points scoring below ``min_score`` are left out. The reprojection RMS is the weighted RMS of
|r_i| in pixels over the points used.

The reprojection error, its Jacobian, the Levenberg-Marquardt and the covariance, with the
perturbation convention: ``common.geometry.reprojection``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.observations import (
    CameraObs,
    NoPose,
    check_spread,
    stereo_observations,
)
from common.geometry.transforms import (
    make_T,
    pose_error,
    pose_mean,
    rotvec_to_R,
    rotvecs_to_Rs,
)
from common.geometry.reprojection import ReprojectionProblem, pose_covariance

MIN_POINTS = 4


# ------------------------------------------------------------------ per-camera initial poses

# OpenCV returns rotations as rotation vectors, which it computes with a precision loss near a
# half turn (at exactly pi the result can be any rotation; a needle lying face-on and upside
# down in the image is such a pose). IPPE is therefore also run on the model points turned by
# a fixed rotation _Q and its solutions turned back: a pose cannot be a half turn in both
# frames unless its axis is perpendicular to _Q's, a single direction.
_Q = rotvec_to_R(np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81]) * (np.pi / 2))
# A pose within ~1e-7 rad of a half turn came back from IPPE as rotations of 2.68-3.46 rad, 0.4-0.6
# rad off, in both cameras (found by hypothesis): any solution turned this far runs the turned
# model too (about a third of the cameras; its solutions are duplicates unless one was lost).
TURN_ABOVE_RAD = 2.5


def _opencv_poses(obj, img, K, epnp: bool, ippe: bool):
    import cv2
    out = []
    if epnp:
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_EPNP)
            if ok:
                out.append(("epnp", rvec, tvec, np.nan))
        except cv2.error:
            pass
    if ippe:
        try:
            n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE)
            out += [(f"ippe{k}", rvecs[k], tvecs[k], float(np.ravel(errs)[k])) for k in range(n)]
        except cv2.error:
            pass
    return out


def initial_poses(obs: CameraObs, epnp: bool = True, ippe: bool = True) -> list[tuple[str, np.ndarray]]:
    """``[(label, T_ecm_needle)]`` from one camera (n >= 4): both IPPE solutions, the same from
    the turned model (see ``_Q``), then EPnP; near-duplicates (0.5 mm, 0.5 deg) left out.

    Labels: ``ippe0:<camera>``, ``ippe1:<camera>``, ``ippe0q:...``, ``ippe1q:...``,
    ``epnp:<camera>``. Solutions that are not finite or put a point behind the camera are
    left out.
    """
    if obs.n < MIN_POINTS:
        return []
    cam = obs.camera
    K = np.ascontiguousarray(cam.K, dtype=np.float64)
    img = np.ascontiguousarray(obs.uv, dtype=np.float64).reshape(-1, 1, 2)
    sols = []
    for suffix, Q in (("", None), ("q", _Q)):
        # the turned model gives the same solutions unless OpenCV lost one near a half turn;
        # then it returns a rotation far turned (TURN_ABOVE_RAD) or none, or one that reprojects
        # far worse than the other (an exact half turn in both cameras: 0.8 against 47 px at
        # zero noise)
        ippe_sols = [s for s in sols if s[0].startswith("ippe")]
        if Q is not None and len(ippe_sols) == 2 and all(1e-2 < math.hypot(*np.ravel(s[1]).tolist()) < TURN_ABOVE_RAD
                                                         for s in ippe_sols):
            e = sorted(s[4] for s in ippe_sols)
            if e[1] <= 3.0 * e[0] + 2.0:
                break
        pts = obs.points if Q is None else obs.points @ Q.T
        obj = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 1, 3)
        for lab, rvec, tvec, err in _opencv_poses(obj, img, K, epnp and Q is None, ippe):
            sols.append((lab + suffix, rvec, tvec, Q, err))
    order = {"ippe0": 0, "ippe1": 1, "ippe0q": 2, "ippe1q": 3, "epnp": 4}
    sols.sort(key=lambda s: order[s[0]])
    out: list[tuple[str, np.ndarray]] = []
    if not sols:
        return out
    rv = np.array([np.asarray(s[1], float).reshape(3) for s in sols])
    tv = np.array([np.asarray(s[2], float).reshape(3) for s in sols])
    finite = np.all(np.isfinite(rv), axis=1) & np.all(np.isfinite(tv), axis=1)
    Rs = rotvecs_to_Rs(np.where(finite[:, None], rv, 0.0))
    T_ecm_cam = cam.T_ecm_cam
    for (label, _, _, Q, _), R, t, ok in zip(sols, Rs, tv, finite):
        if not ok:
            continue
        if Q is not None:
            R = R @ Q
        if (obs.points @ R[2]).min() + t[2] <= 0:
            continue
        T = T_ecm_cam @ make_T(R, t)
        if _distinct(T, [o[1] for o in out], 5e-4, _HALF_DEG):
            out.append((f"{label}:{cam.name}", T))
    return out


_HALF_DEG = math.radians(0.5)


def _distinct(T, others, tol_m, tol_rad) -> bool:
    """No pose in ``others`` within ``tol_m`` (origin distance) and ``tol_rad`` (rotation)."""
    cos_tol = math.cos(tol_rad)
    for T2 in others:
        d = T[:3, 3] - T2[:3, 3]
        if d @ d <= tol_m * tol_m and (float(T[:3, :3].ravel() @ T2[:3, :3].ravel()) - 1.0) / 2.0 >= cos_tol:
            return False
    return True


# ------------------------------------------------------------------ results

@dataclass
class PoseCandidate:
    """One local minimum of the joint fit (or one camera's solution for ``average``)."""

    T_ecm_needle: np.ndarray
    cost: float
    rms_px: float
    source: str                        # the initial pose it came from, e.g. "ippe1:left"
    jacobian: np.ndarray | None = None
    residuals: np.ndarray | None = None   # (2n,) weighted residuals at the pose (joint only)


@dataclass
class PnpResult:
    """A PnP pose in the ECM frame.

    ``candidates``: for ``pnp_joint`` every distinct local minimum sorted by cost (best first,
    ``candidates[0]`` is the pose); for ``pnp_average`` each camera's own solution.
    ``jacobian``/``covariance``: weighted residual Jacobian (2n, 6) and covariance (6, 6) of
    [w, v] at the pose (joint only). ``ambiguous``: another distinct minimum is nearly as good,
    or the keypoints leave a direction of the pose unfixed (``pose_covariance``).
    ``used``: camera -> indices (into A..E) of the keypoints used.
    """

    T_ecm_needle: np.ndarray
    rms_px: float
    method: str
    candidates: list = field(default_factory=list)
    jacobian: np.ndarray | None = None
    covariance: np.ndarray | None = None
    ambiguous: bool = False
    used: dict = field(default_factory=dict)
    per_camera: dict = field(default_factory=dict)


def _check_observations(obs: dict[str, CameraObs], need_one_camera: bool = True) -> None:
    if not obs or sum(o.n for o in obs.values()) < MIN_POINTS:
        n = sum(o.n for o in obs.values())
        raise NoPose("too_few_points", f"{n} usable keypoints, need {MIN_POINTS}")
    if need_one_camera and max(o.n for o in obs.values()) < MIN_POINTS:
        raise NoPose("too_few_points", f"no camera has {MIN_POINTS} usable keypoints")
    for name, o in obs.items():
        if o.n >= 2:
            check_spread(o.uv, name)
    _check_in_front(obs)


def _check_in_front(obs: dict[str, CameraObs]) -> None:
    """With both cameras, triangulate the shared keypoints: a needle whose median depth is not
    positive is behind the cameras (a single image cannot tell; its pose would be mirrored)."""
    if "left" not in obs or "right" not in obs:
        return
    L, Rr = obs["left"], obs["right"]
    in_right = {k: i for i, k in enumerate(Rr.index.tolist())}
    il = [i for i, k in enumerate(L.index.tolist()) if k in in_right]
    if not il:
        return
    ir = [in_right[k] for k in L.index[il].tolist()]
    depth = sorted(d for d in _ray_depths(L.camera, L.uv[il], Rr.camera, Rr.uv[ir]).tolist() if math.isfinite(d))
    if depth and depth[(len(depth) - 1) // 2] + depth[len(depth) // 2] <= 0:     # the median
        raise NoPose("behind_camera", "keypoints triangulate behind the cameras")


def _ray_depths(cam1, uv1, cam2, uv2) -> np.ndarray:
    """Depth in camera 1 of the closest approach of the rays through the undistorted pixels
    uv1, uv2 (N, 2) of two cameras (midpoint triangulation), NaN for parallel rays. Closed form:
    a third of the DLT's time for the handful of keypoints, whose SVDs this check does not need."""
    rays = []
    for cam, uv in ((cam1, uv1), (cam2, uv2)):
        (fx, sk, cx), (_, fy, cy) = cam.K[0], cam.K[1]
        y = (uv[:, 1] - cy) / fy
        x = (uv[:, 0] - cx - sk * y) / fx
        rays.append(np.stack([x, y, np.ones_like(x)], axis=1) @ cam.T_ecm_cam[:3, :3].T)  # z_cam = 1
    d1, d2 = rays
    w = cam1.T_ecm_cam[:3, 3] - cam2.T_ecm_cam[:3, 3]
    a, b, c = (d1 * d1).sum(1), (d1 * d2).sum(1), (d2 * d2).sum(1)
    den = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 1e-12 * a * c, (b * (d2 @ w) - c * (d1 @ w)) / den, np.nan)


def _residual_check(rms, max_rms_px):
    if not np.isfinite(rms):
        raise NoPose("non_finite", "reprojection error is not finite")
    if max_rms_px is not None and rms > max_rms_px:
        raise NoPose("high_residual", f"reprojection RMS {rms:.2f} px > {max_rms_px} px")


# ------------------------------------------------------------------ Pipeline I, the paper's way

def pnp_camera(obs: CameraObs, refine: bool = True) -> PoseCandidate:
    """One camera's pose ``T_ecm_needle``: EPnP, then (``refine``) LM over EPnP and both IPPE
    solutions in this camera, keeping the lowest reprojection error. Raises NoPose."""
    if obs.n < MIN_POINTS:
        raise NoPose("too_few_points", f"{obs.camera.name}: {obs.n} usable keypoints")
    if not refine:
        inits = initial_poses(obs, epnp=True, ippe=False)
        if not inits:
            raise NoPose("solver_failed", f"{obs.camera.name}: EPnP failed")
        lab, T = inits[0]
        rms = ReprojectionProblem([obs]).rms_px(T)
        return PoseCandidate(T, rms ** 2 * obs.weights.sum(), rms, lab)
    inits = initial_poses(obs)
    fits = ReprojectionProblem([obs]).refine_many([T for _, T in inits])
    best = None
    for (lab, _), fit in zip(inits, fits):
        if fit is not None and fit.merged_into is None and (best is None or fit.cost < best.cost):
            best = PoseCandidate(fit.T_ecm_needle, fit.cost, fit.rms_px, lab, fit.jacobian)
    if best is None:
        raise NoPose("solver_failed", f"{obs.camera.name}: no PnP solution in front of the camera")
    return best


def pnp_average(uv: dict, rig: StereoRig, model_points, scores: dict | None = None,
                min_score: float = 0.5, refine: bool = True,
                max_rms_px: float | None = None) -> PnpResult:
    """Pipeline I as in the paper: per-camera EPnP poses averaged (see module docstring).

    ``uv``: ``{"left": (5, 2), "right": (5, 2)}`` pixels (a camera may be absent; NaN rows are
    missing points), ``scores`` likewise (5,). A camera with fewer than 4 usable keypoints, or
    whose solver finds no pose in front of it, is left out of the mean; with none left, NoPose. Each camera's pose is weighted by the sum of
    its scores. ``rms_px`` is the averaged pose's reprojection RMS in the cameras used.
    """
    obs = stereo_observations(uv, rig, model_points, scores, min_score)
    _check_observations(obs)
    per_cam, failure = {}, None
    for name, o in obs.items():
        if o.n >= MIN_POINTS:
            try:
                per_cam[name] = pnp_camera(o, refine)
            except NoPose as exc:         # the other camera may still give the pose
                failure = exc
    if not per_cam:
        raise failure
    Ts = [c.T_ecm_needle for c in per_cam.values()]
    w = [obs[n].weights.sum() for n in per_cam]
    T = pose_mean(Ts, w) if len(Ts) > 1 else Ts[0]
    rms = ReprojectionProblem([obs[n] for n in per_cam]).rms_px(T)
    if not np.isfinite(rms):
        raise NoPose("behind_camera", "averaged pose puts a keypoint behind a camera")
    _residual_check(rms, max_rms_px)
    return PnpResult(T, rms, "pnp_average", list(per_cam.values()),
                     used={n: obs[n].index for n in per_cam},
                     per_camera={n: c.T_ecm_needle for n, c in per_cam.items()})


# ------------------------------------------------------------------ Pipeline I, joint stereo LM

def joint_candidates(obs: dict[str, CameraObs], inits: Sequence[tuple[str, np.ndarray]] | None = None,
                     dedup_m: float = 1e-4, dedup_rad: float = np.deg2rad(0.05), epnp: bool = True,
                     **lm) -> list[PoseCandidate]:
    """Refine initial poses jointly in all cameras; distinct minima sorted by cost (best first).

    ``inits`` defaults to every camera's ``initial_poses`` (IPPE x2, EPnP; without ``epnp``
    EPnP only where IPPE gives no start). Near-identical
    initial poses (within 0.5 mm and 0.5 deg) are refined once; all are refined together
    (``ReprojectionProblem.refine_many``, ``lm`` its stopping options), a fit heading to a
    minimum already found stopping there; minima closer than ``dedup_m`` and ``dedup_rad``
    count once.
    """
    if inits is None:
        inits = [p for o in obs.values() for p in initial_poses(o, epnp=epnp)]
        if not inits and not epnp:
            inits = [p for o in obs.values() for p in initial_poses(o, ippe=False)]
    seeds: list[tuple[str, np.ndarray]] = []
    for lab, T in inits:
        if _distinct(T, [s[1] for s in seeds], 5e-4, np.deg2rad(0.5)):
            seeds.append((lab, T))
    fits = ReprojectionProblem(list(obs.values())).refine_many([T for _, T in seeds], **lm)
    cands: list[PoseCandidate] = []
    for (lab, _), fit in zip(seeds, fits):
        if fit is None or not np.isfinite(fit.cost) or fit.merged_into is not None:
            continue
        cands.append(PoseCandidate(fit.T_ecm_needle, fit.cost, fit.rms_px, lab, fit.jacobian, fit.residuals))
    cands.sort(key=lambda c: c.cost)
    distinct: list[PoseCandidate] = []
    for c in cands:
        if _distinct(c.T_ecm_needle, [d.T_ecm_needle for d in distinct], dedup_m, dedup_rad):
            distinct.append(c)
    return distinct


def _is_ambiguous(cands: list[PoseCandidate], n_points: int, ratio: float = 2.0,
                  floor_px: float = 0.1) -> bool:
    """A second minimum at least 1 mm / 2 deg away whose cost is within ``ratio`` of the best
    (plus a floor of ``floor_px`` RMS over the points, so exact fits are never ambiguous)."""
    if len(cands) < 2:
        return False
    best = cands[0]
    for c in cands[1:]:
        dt, dr = pose_error(c.T_ecm_needle, best.T_ecm_needle)
        if (dt > 1e-3 or dr > np.deg2rad(2.0)) and c.cost <= ratio * best.cost + n_points * floor_px ** 2:
            return True
    return False


def pnp_joint(uv: dict, rig: StereoRig, model_points, scores: dict | None = None,
              min_score: float = 0.5, outlier_px: float | None = None,
              max_rms_px: float | None = None, min_sigma_px: float = 0.25, max_iter: int = 60,
              rel_tol: float = 1e-7, epnp_starts: bool = True) -> PnpResult:
    """Pipeline I, joint: one pose fitted to the keypoints of both cameras (module docstring).

    ``uv``/``scores`` as in ``pnp_average``. At least one camera needs 4 usable keypoints (to
    start from); the other camera's usable keypoints all join the fit. ``outlier_px``: while the
    worst point's residual exceeds it and more than 6 points remain, that point is dropped and
    the fit redone from the previous minima. ``max_rms_px``: a larger RMS raises NoPose
    ("high_residual"). Covariance: ``pose_covariance`` with ``min_sigma_px`` (a direction it
    leaves unfixed flags the pose ``ambiguous``). ``max_iter`` and
    ``rel_tol``: the fits' stopping rule (``ReprojectionProblem.refine_many``). ``epnp_starts``
    False: start from the IPPE solutions alone (EPnP only where IPPE gives none). EPnP on the
    coplanar keypoints starts far off and its fits crawl for many iterations to minima the IPPE
    starts find anyway: without it the dense refinement's result changed in 2 of 900 random
    frames (README, Dense refinement), for a third less time.
    """
    obs = stereo_observations(uv, rig, model_points, scores, min_score)
    _check_observations(obs)
    cands, obs = _joint_minima(obs, outlier_px, epnp=epnp_starts, max_iter=max_iter, rel_tol=rel_tol)
    best = cands[0]
    _residual_check(best.rms_px, max_rms_px)
    n_pts = sum(o.n for o in obs.values())
    cov, unfixed = pose_covariance(best.jacobian, best.cost, min_sigma_px)
    return PnpResult(best.T_ecm_needle, best.rms_px, "pnp_joint", cands, best.jacobian, cov,
                     unfixed or _is_ambiguous(cands, n_pts), used={n: o.index for n, o in obs.items()})


def _joint_minima(obs: dict[str, CameraObs], outlier_px: float | None, epnp: bool = True, **lm):
    """``joint_candidates`` with ``pnp_joint``'s outlier rejection: (minima, observations kept)."""
    cands = joint_candidates(obs, epnp=epnp, **lm)
    if not cands:
        raise NoPose("solver_failed", "no PnP solution in front of the cameras")
    while outlier_px is not None:
        views = [o for o in obs.values() if o.n > 0]
        r = cands[0].residuals            # weighted, in the cameras' stacked point order
        err = np.linalg.norm(r.reshape(-1, 2), axis=1) / np.concatenate([np.sqrt(o.weights) for o in views])
        worst = int(np.argmax(err))
        if err[worst] <= outlier_px or len(err) <= 6:
            break
        obs = _drop_point(obs, worst)
        cands = joint_candidates(obs, [(c.source, c.T_ecm_needle) for c in cands], **lm)
        if not cands:
            raise NoPose("solver_failed", "no PnP solution after dropping outliers")
    return cands, obs


def refine_starts(uv: dict, rig: StereoRig, model_points, scores: dict | None = None,
                  min_score: float = 0.5, outlier_px: float | None = 10.0) -> list[np.ndarray]:
    """Starting poses ``T_ecm_needle`` for a refinement that fits more than the keypoints
    (``common.geometry.refine``): every minimum of the joint stereo PnP from the IPPE starts, its fits
    stopped early (6 iterations, or a predicted decrease below 1e-3 of the cost): the
    refinement goes on from there with the centreline too, so polishing the keypoint-only
    minima to full precision buys nothing (refined errors on the bench within 0.1 mm of the
    fully converged starts'; 4.5 instead of 6.3 residual evaluations per frame at 1 px noise).
    NoPose as ``pnp_joint`` (too few or degenerate points, needle behind the cameras), whose
    covariance and ambiguity it does not need."""
    obs = stereo_observations(uv, rig, model_points, scores, min_score)
    _check_observations(obs)
    cands, _ = _joint_minima(obs, outlier_px, epnp=False, max_iter=6, rel_tol=1e-3)
    return [c.T_ecm_needle for c in cands]


def unsure_starts(uv: dict, rig: StereoRig, model_points, scores: dict | None = None,
                  min_score: float = 0.01, outlier_px: float | None = 10.0) -> list[np.ndarray]:
    """Starting poses for a needle with fewer than 4 sure keypoints (most of it hidden, e.g. in
    an instrument's jaws): ``refine_starts`` on every keypoint scored at least ``min_score``,
    once in the detector's order and once with the order reversed (tip and tail swapped: unsure
    keypoints on a partly visible arc may have its ends the wrong way round). The fit that
    follows weighs only the sure keypoints and the centreline. NoPose (the reversed order's
    reason) when neither order gives a start."""
    starts: list[np.ndarray] = []
    failure = None
    for order in (slice(None), slice(None, None, -1)):
        u = {c: None if p is None else np.asarray(p, float)[order] for c, p in uv.items()}
        s = None if scores is None else {c: None if v is None else np.asarray(v, float)[order]
                                         for c, v in scores.items()}
        try:
            starts += refine_starts(u, rig, model_points, s, min_score, outlier_px)
        except NoPose as exc:
            failure = exc
    if not starts:
        raise failure
    return starts


def _drop_point(obs: dict[str, CameraObs], k: int) -> dict[str, CameraObs]:
    """Remove the k-th point in stacked order (the cameras' points one after the other)."""
    out = {}
    for name, o in obs.items():
        if 0 <= k < o.n:
            keep = np.arange(o.n) != k
            out[name] = CameraObs(o.camera, o.uv[keep], o.points[keep], o.weights[keep], o.index[keep])
        else:
            out[name] = o
        k -= o.n
    return out
