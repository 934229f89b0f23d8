"""Dense pose refinement: fit the whole projected needle arc in both cameras at once.

Five keypoints on a small planar arc give an ill-conditioned pose (see
``docs/geometry.md#pose-sensitivity``); the needle's centreline, hundreds of pixels per image,
carries far more. ``refine_pose`` starts from candidate poses (the stereo PnP's solutions) and
minimises, over both cameras, a robust (Cauchy) sum of

- the keypoint term: reprojection error of A..E, weighted by the detector's scores (the tip A
  and the tail E fix the arc's extent along the curve);
- the curve term: for each observed centreline point (up to ``max_curve_points`` per camera,
  even in arc length), its distance to the projected model arc. The point's foot on the arc
  starts at the nearest of a few projected arc samples and takes Newton steps along the exact
  projected circle (no polyline approximation); the residuals are the signed distance to the
  tangent at the foot and, for a point past an end of the arc, its overshoot along the arc
  (together: the distance to that end). Observed -> model: a hidden part of the needle costs
  nothing, and the model arc must cover everything seen, so the curve alone pins its extent.

Levenberg-Marquardt runs on all candidates at once (vectorised numpy, no scipy, analytic
Jacobians) over six parameters: a rotation-vector increment left-multiplied in the ECM frame and
a translation increment in the ECM frame, ``R <- exp(dr) R``, ``t <- t + dt``. The covariance,
``s^2 (J^T W J)^-1`` at the optimum with ``s^2`` the residual variance (and a centreline
point's weight divided by the number of neighbours its error moves with, when the detector
states it), plus the model's own error (``model_sigma_deg``, ``model_sigma_mm`` per axis), is in
that same order and frame: ``[rotation vector (rad), translation (m)]``, as
``PoseEstimate.covariance``.

A planar arc has a two-fold ambiguity (seen edge-on, whether it bulges towards or away from the
camera); every candidate's mirror image about the line of sight is added and refined too. When
other candidates end nearly as good as the best, or the arc is seen nearly edge-on, the result
is flagged ``ambiguous`` and its covariance inflated by the spread of the competitors, so that a
pose that may be wrong is never reported as a confident one. Given the normal of a surface the
needle may rest on, a prior (``common.geometry.rest_prior``) picks between minima the images leave nearly
equal; the flag and the covariance stay as the images say.

Pixels: observations are undistorted first when a camera has distortion; residuals are in
(undistorted) pixels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Optional, Sequence

import numpy as np

from common.geometry.camera import Camera, StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.rest_prior import resting_log_prior
from common.geometry.transforms import (
    R_to_rotvec,
    make_T,
    rotvecs_to_Rs,
    transform_points,
)


class RefineError(ValueError):
    """The observations or candidates cannot give a pose; the text says why (a short reason
    first, e.g. ``no_candidates: ...``, usable as a counter name)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass
class ArcObservation:
    """What one camera saw of the needle (pixels).

    ``uv`` (5, 2) keypoints A..E (NaN where missing), ``scores`` (5,) in [0, 1];
    ``centreline`` (N, 2) points of the needle's projected arc ordered from A to E, with weights
    ``centreline_w`` (N,) in [0, 1] (all ones when None), ``centreline_sigma_px`` the
    centreline's 1-sigma error across the curve (None: ``RefineConfig.sigma_curve_px``);
    ``on_arc`` (5,) true for keypoints the detector placed on its fitted arc rather than observed
    (left out of the fit where the centreline is given); ``centreline_corr_points`` how many
    consecutive centreline points' errors move together (None: independent): in the covariance,
    not the fit, each point then counts for that fraction of an observation;
    ``keypoint_sigma_px`` the keypoints' 1-sigma error per axis (None:
    ``RefineConfig.sigma_kp_px``). Either part may be absent.
    """

    uv: Optional[np.ndarray] = None
    scores: Optional[np.ndarray] = None
    centreline: Optional[np.ndarray] = None
    centreline_w: Optional[np.ndarray] = None
    centreline_sigma_px: Optional[float] = None
    on_arc: Optional[np.ndarray] = None
    centreline_corr_points: Optional[float] = None
    keypoint_sigma_px: Optional[float] = None

    @classmethod
    def from_keypoints(cls, msg) -> "ArcObservation":
        """From a detector's ``Keypoints`` message (``found`` False gives an empty observation)."""
        if not msg.found:
            return cls()
        return cls(np.asarray(msg.uv, float), np.asarray(msg.scores, float),
                   None if msg.centreline is None else np.asarray(msg.centreline, float),
                   None if msg.centreline_w is None else np.asarray(msg.centreline_w, float),
                   msg.centreline_sigma_px, None if msg.on_arc is None else np.asarray(msg.on_arc, bool),
                   msg.centreline_corr_points, msg.keypoint_sigma_px)


@dataclass(frozen=True)
class RefineConfig:
    """Tuning of the fit. Pixel sigmas set the relative weight of the two terms; the robust
    scale is in units of those sigmas."""

    max_curve_points: int = 64      # observed centreline points kept per camera (even in arc length)
    n_samples: int = 24             # projected arc samples that start each point's foot search
    foot_steps: int = 1             # then Newton steps along the projected arc, once per pose
    warm_steps: int = 1             # Newton steps from feet carried over from the previous pose
    research_rad: float = 0.02      # after a step this large (rotation, rad) the feet are searched
    research_m: float = 0.001       # afresh (or translation, m); smaller steps carry them over
    max_step_rad: float = 0.1       # a step turns at most this much (rad) ...
    max_step_m: float = 0.005       # ... and moves at most this much (m)
    sigma_kp_px: float = 1.0        # assumed keypoint noise
    sigma_curve_px: float = 0.5     # assumed centreline noise
    min_score: float = 0.5          # keypoints scored below are left out (as the PnP does)
    # one camera poses the needle only through its arc's apparent size and shape: at 10-25 cm its
    # depth and tilt can be off by centimetres and tens of degrees, so the default needs both
    min_cameras: int = 2
    min_centreline_w: float = 0.05  # centreline points weighted below are left out
    cauchy_scale: float = 3.0       # robust loss scale, in sigmas
    cauchy_scale_end: float = 1.0   # the same for the overshoot past an arc's end (spurs: thread, glare)
    max_iter: int = 30
    step_tol: float = 1.0           # converged after a step worth < this many residual variances
    max_reject: int = 5             # ... or after this many rejected steps in a row
    coarse_iter: int = 3            # iterations every candidate gets before those that met merge
    max_candidates: int = 3         # and the best this many are refined to the end
    add_mirrors: bool = True        # also refine each candidate's mirror image about the line of sight
    merge_mm: float = 5.0           # starting poses closer than this and merge_deg are refined once
    merge_deg: float = 10.0
    ambiguity_chi2: float = 9.0     # a competitor costing < this many residual variances more: ambiguous
    distinct_mm: float = 1.0        # competitors closer than this and distinct_deg are the same solution
    distinct_deg: float = 2.0
    edge_on_deg: float = 10.0       # arc plane within this angle of the line of sight -> ambiguous
    edge_on_chi2: float = 100.0     # and then competitors costing < this many variances more count
    min_depth_m: float = 1e-3       # every point must be this far in front of both cameras
    max_depth_m: float = 2.0        # and the needle nearer than this (a PnP start may run off)
    min_sigma_ratio: float = 0.25   # the covariance assumes at least this fraction of the sigmas
    # The error no image noise explains (the needle's wire, arc, taper and swage against the model,
    # the rig's calibration), 1 sigma per axis, added to the covariance: from the images alone a
    # dense fit is a few hundredths of a millimetre and a tenth of a degree thin near the
    # endoscope, and errors the two nearly alike cameras share go into the pose, not the
    # residuals. Chosen on the end-identity fit folders, not the test sets (NEES medians 4.6-6.4
    # there; docs/geometry.md#covariances-and-nees).
    model_sigma_mm: float = 0.03
    model_sigma_deg: float = 0.25
    # with a support surface's normal given (``refine(support_normal=)``): probability that the
    # needle rests on it, and the spread of its tilt then (common/geometry/rest_prior.py)
    rest_prior: float = 0.5
    rest_sigma_deg: float = 10.0

    def __post_init__(self):
        positive = ("sigma_kp_px", "sigma_curve_px", "cauchy_scale", "cauchy_scale_end", "step_tol", "merge_mm",
                    "merge_deg", "distinct_mm", "distinct_deg", "ambiguity_chi2",
                    "research_rad", "research_m", "max_step_rad", "max_step_m",
                    "min_sigma_ratio", "max_depth_m", "edge_on_chi2", "rest_sigma_deg")
        for name in positive:
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"RefineConfig.{name}: must be a positive number, got {v}")
        for name, lo in (("max_curve_points", 2), ("n_samples", 2), ("max_iter", 1),
                         ("max_candidates", 1), ("max_reject", 1), ("coarse_iter", 0),
                         ("foot_steps", 1), ("warm_steps", 1)):
            if int(getattr(self, name)) < lo:
                raise ValueError(f"RefineConfig.{name}: must be at least {lo}, got {getattr(self, name)}")
        for name in ("model_sigma_mm", "model_sigma_deg"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"RefineConfig.{name}: must be a number >= 0, got {v}")
        if not 0.0 <= self.rest_prior < 1.0:
            raise ValueError(f"RefineConfig.rest_prior: must be in [0, 1), got {self.rest_prior}")


@dataclass
class RefineResult:
    """The refined pose ``T_ecm_needle`` (4x4, m) and what the fit says about it.

    ``covariance`` (6, 6) over [rotation vector (rad), translation (m)] in the ECM frame (inflated
    when ambiguous); ``rms_px`` the RMS of all residuals (px) at the optimum, ``rms_kp_px`` and
    ``rms_curve_px`` per term (NaN when the term is empty); ``ambiguous`` with ``reasons``
    (``competing_candidates``, ``edge_on``); ``view_angle_deg`` the smallest angle between the arc's
    plane and a camera's line of sight (0 = edge-on, 90 = face-on); ``candidates`` every distinct
    converged solution as ``(T_ecm_needle, cost)``, best first; ``competitor_chi2`` how much
    the cost of the nearest of the others differs, in residual variances (inf: no other
    solution; a support surface's prior may pick a minimum that costs a little more);
    ``residual_variance`` the fit's robust residual variance in units of the assumed sigmas
    (0.1-0.5 on the project's renders; well above 1, the images are not the needle model's:
    e.g. a jaw's edge taken for the wire).
    """

    T_ecm_needle: np.ndarray
    covariance: np.ndarray
    rms_px: float
    rms_kp_px: float
    rms_curve_px: float
    cost: float
    ambiguous: bool
    reasons: tuple = ()
    view_angle_deg: float = 90.0
    n_iter: int = 0
    n_residuals: int = 0
    candidates: list = field(default_factory=list)
    competitor_chi2: float = float("inf")
    residual_variance: float = float("nan")


def project_centreline(camera: Camera, needle: NeedleModel, T_ecm_needle: np.ndarray,
                       spacing_px: float = 1.0, max_points: int = 1024) -> np.ndarray:
    """The exact dense observation of a needle pose in one camera: its arc projected to pixels,
    (N, 2) ordered from A to E, about ``spacing_px`` apart (distortion applied as the camera
    has it). Points behind the camera or outside the image are left out, so N may be 0."""
    p = transform_points(camera.T_cam_ecm @ T_ecm_needle, needle.sample_arc(64))
    front = p[:, 2] > 1e-6
    if not front.any():
        return np.zeros((0, 2))
    uv = camera.project(p[front])
    gap = float(np.max(np.linalg.norm(np.diff(uv, axis=0), axis=1))) if len(uv) > 1 else 0.0
    n = int(np.clip(np.ceil(1.05 * 63 * gap / spacing_px) + 1, 2, max_points))   # even in angle
    p = transform_points(camera.T_cam_ecm @ T_ecm_needle, needle.sample_arc(n))
    p = p[p[:, 2] > 1e-6]
    uv = camera.project(p) if len(p) else np.zeros((0, 2))
    return uv[camera.in_image(uv)]


# ------------------------------------------------------------------ the problem, precomputed


class _Static:
    """What does not change between frames: cameras and needle model, shaped to broadcast over
    (P poses, C = 2 cameras, N points)."""

    def __init__(self, rig: StereoRig, needle: NeedleModel, cfg: RefineConfig):
        cams = rig.cameras
        self.cams, self.cfg, self.needle = cams, cfg, needle
        self.Rc = np.stack([c.T_cam_ecm[:3, :3] for c in cams])
        self.tc = np.stack([c.T_cam_ecm[:3, 3] for c in cams])
        Kp = np.stack([c.K[:2, :2] for c in cams])
        kc = np.stack([c.K[:2, 2] for c in cams])
        if np.any(Kp[:, 1, 0] != 0) or np.any(Kp[:, [0, 1], [0, 1]] <= 0) or not np.all(np.isfinite(Kp)):
            raise RefineError("bad_calibration",
                              "camera K must be upper triangular with positive focal lengths")
        self.cam_centres = np.stack([c.T_ecm_cam[:3, 3] for c in cams])
        self.radius = needle.radius_m
        a0, a1 = needle.arc_span_rad
        self.mid, self.half = 0.5 * (a0 + a1), 0.5 * (a1 - a0)
        self.arc_centroid = needle.sample_arc(64).mean(0)
        C, M = len(cams), cfg.max_curve_points
        self.C, self.M = C, M
        col = lambda a: np.asarray(a, float).reshape(1, C, 1)
        self._fx, self._sk, self._fy = col(Kp[:, 0, 0]), col(Kp[:, 0, 1]), col(Kp[:, 1, 1])
        self._cx, self._cy = col(kc[:, 0]), col(kc[:, 1])
        self._Rmid = rotvecs_to_Rs(np.array([[0.0, 0.0, self.mid]]))[0]
        # radius * [e1, e2, e2, -e1] of the needle axes turned so the arc's middle is on +x
        self._W = self.radius * np.stack([self._Rmid[:, 0], self._Rmid[:, 1], self._Rmid[:, 1],
                                          -self._Rmid[:, 0]], axis=1)
        self._cos_half, self._sin_half = np.cos(self.half), np.sin(self.half)
        kp_ang = needle.keypoint_angles_rad - self.mid               # A..E about the middle
        self._kp_cs = np.stack([np.cos(kp_ang), np.sin(kp_ang)], axis=1)   # (5, 2)
        self._end_cs = np.array([[np.cos(self.half), -np.sin(self.half)],
                                 [np.cos(self.half), np.sin(self.half)]])  # A, E
        self._perp = np.array([-1.0, 1.0])           # (cos, sin)[::-1] * perp = d/d angle
        # Jacobian rows (see _Problem.evaluate): for a point at W (camera frame, from the needle
        # origin) with pixel offset (du, dv) from the principal point and 1/depth iz,
        #   d u / d[dr_c, dt_c] = iz (Ku(W) - du m(W)),  d v / d[dr_c, dt_c] = iz (Kv(W) - dv m(W)),
        #   Ku = [-sk W2, fx W2, sk W0 - fx W1, fx, sk, 0], Kv = [-fy W2, 0, fy W0, 0, fy, 0],
        #   m = [W1, -W0, 0, 0, 0, 1]  (rotation part W x a, a = d(u, v)/d point).
        # All three are affine in W: [Ku, Kv, m] = W @ L + L1, with the camera -> ECM map of the
        # increments (block diag(Rc, Rc)) folded in.
        L = np.zeros((C, 3, 18))
        L1 = np.zeros((C, 18))
        fx, sk, fy = Kp[:, 0, 0], Kp[:, 0, 1], Kp[:, 1, 1]
        L[:, 0, 2], L[:, 1, 2], L[:, 2, 0], L[:, 2, 1] = sk, -fx, -sk, fx          # Ku
        L1[:, 3], L1[:, 4] = fx, sk
        L[:, 0, 8], L[:, 2, 6] = fy, -fy                                          # Kv
        L1[:, 10] = fy
        L[:, 0, 13], L[:, 1, 12] = -1.0, 1.0                                      # m
        L1[:, 17] = 1.0
        Bc = np.zeros((C, 6, 6))                                                  # camera -> ECM
        Bc[:, :3, :3] = self.Rc
        Bc[:, 3:, 3:] = self.Rc
        for k in range(3):
            L[:, :, 6 * k:6 * k + 6] = L[:, :, 6 * k:6 * k + 6] @ Bc
            L1[:, 6 * k:6 * k + 6] = (L1[:, None, 6 * k:6 * k + 6] @ Bc)[:, 0]
        self._L, self._L1 = L[None], L1[None, :, None]
        self._out = np.array([-1.0, 1.0])                       # outward along the arc at A, E
        self._cos_end_zone = np.cos(self.half - np.deg2rad(1.0))  # feet within 1 deg of an end
        ang = np.linspace(-self.half, self.half, cfg.n_samples)
        self._samples = np.stack([np.cos(ang), np.sin(ang)], axis=1)       # (S, 2)
        self.is_kp = np.concatenate([np.ones((C, 10), bool), np.zeros((C, 2 * M), bool)], axis=1).ravel()


class _Problem:
    """Observations of one stereo frame, arranged for batched evaluation: per camera 5 keypoints
    and M centreline points (zero weight where absent or left out)."""

    def __init__(self, st: _Static, obs: Mapping[str, ArcObservation]):
        self.__dict__.update(st.__dict__)
        cfg, C, M = st.cfg, st.C, st.M
        U, wU = np.zeros((C, 5, 2)), np.zeros((C, 5))
        O, wO = np.zeros((C, M, 2)), np.zeros((C, M))
        corr = np.ones(C)                 # per camera: centreline points per independent error
        for i, cam in enumerate(st.cams):
            o = obs.get(cam.name)
            if o is None:
                continue
            if o.uv is not None:
                uv = np.asarray(o.uv, float)
                sc = np.ones(5) if o.scores is None else np.asarray(o.scores, float)
                if uv.shape != (5, 2) or sc.shape != (5,):
                    raise RefineError("bad_keypoints", f"{cam.name}: need uv (5, 2) and scores (5,), "
                                      f"got {uv.shape} and {sc.shape}")
                sig = cfg.sigma_kp_px if o.keypoint_sigma_px is None else float(o.keypoint_sigma_px)
                if not (np.isfinite(sig) and sig > 0):
                    raise RefineError("bad_keypoints", f"{cam.name}: keypoint_sigma_px must be positive, got {sig}")
                ok = np.all(np.isfinite(uv), axis=1) & np.isfinite(sc) & (sc >= cfg.min_score)
                U[i, ok] = _undistort(cam, uv[ok])
                wU[i, ok] = np.minimum(sc[ok], 1.0) / sig ** 2
            if o.centreline is not None and len(o.centreline):
                pts, w = _select_curve(cam.name, o.centreline, o.centreline_w, M, cfg.min_centreline_w)
                O[i, :len(pts)] = _undistort(cam, pts)
                sig = cfg.sigma_curve_px if o.centreline_sigma_px is None else float(o.centreline_sigma_px)
                if not (np.isfinite(sig) and sig > 0):
                    raise RefineError("bad_centreline", f"{cam.name}: centreline_sigma_px must be positive, got {sig}")
                wO[i, :len(pts)] = w / sig ** 2
                if o.centreline_corr_points is not None:
                    corr[i] = float(o.centreline_corr_points)
                    if not (np.isfinite(corr[i]) and corr[i] >= 1):
                        raise RefineError("bad_centreline", f"{cam.name}: centreline_corr_points must be "
                                          f"at least 1, got {o.centreline_corr_points}")
                if o.on_arc is not None and np.count_nonzero(w) >= 3:
                    # keypoints a detector placed on its own fitted arc count the curve twice,
                    # with that arc's (weak-perspective) bias along it, which tips the mirror
                    # choice of small, far needles: the curve stands for them
                    on_arc = np.asarray(o.on_arc)
                    if on_arc.shape != (5,):
                        raise RefineError("bad_keypoints", f"{cam.name}: need on_arc (5,), got {on_arc.shape}")
                    wU[i, on_arc.astype(bool)] = 0.0
        self.U, self.wU, self.O, self.wO = U, wU, O, wO
        self.n_kp = int(np.count_nonzero(wU))
        self.n_curve = int(np.count_nonzero(wO))
        self.n_res = 2 * self.n_kp + self.n_curve
        if self.n_res < 6:
            raise RefineError("too_few_points", f"{self.n_kp} keypoints and {self.n_curve} centreline "
                              "points cannot fix 6 pose parameters")
        seen = [cam.name for i, cam in enumerate(st.cams) if wU[i].any() or wO[i].any()]
        if len(seen) < cfg.min_cameras:
            raise RefineError("too_few_cameras", f"the needle is seen by {len(seen)} camera(s) ({', '.join(seen)}), "
                              f"min_cameras is {cfg.min_cameras}")
        # Residual weights in evaluation order, per camera: keypoint u (5), keypoint v (5),
        # curve normal distance (M), curve overshoot beyond the arc's ends (M).
        self.wp = np.concatenate([wU, wU, wO, wO], axis=1).ravel()
        self.used_kp, self.used_curve = (self.wp > 0) & st.is_kp, (self.wp > 0) & ~st.is_kp
        # the weight of each residual in the covariance relative to the fit's
        self.cov_scale = np.concatenate([np.ones((C, 10)), np.repeat(1.0 / corr[:, None], 2 * M, axis=1)],
                                        axis=1).ravel()
        # Cauchy scales (squared, in sigmas) per residual: the overshoot past an arc end has its
        # own, so that a spur past the needle's end (thread, glare) cannot drag the arc along
        c_end = cfg.cauchy_scale_end ** 2
        self._c2 = np.concatenate([np.full((C, 10 + M), cfg.cauchy_scale ** 2), np.full((C, M), c_end)],
                                  axis=1).ravel()
        self._Uu, self._Uv = U[None, :, :, 0], U[None, :, :, 1]
        self._Ou, self._Ov = O[None, :, :, 0], O[None, :, :, 1]
        # the same padded in front with the keypoints, for the feet's Newton steps (which
        # leave the keypoints' angles alone)
        self._Opu = np.concatenate([U[None, :, :, 0], self._Ou], axis=2)
        self._Opv = np.concatenate([U[None, :, :, 1], self._Ov], axis=2)

    def _axes(self, R, t):
        """Needle pose in each camera (P, C, ...): translation, and E (P, C, 2, 6) with rows
        radius * [e1 e2] and radius * [e2 -e1] (needle axes turned so that the arc's middle is
        on +x): [cos, sin] @ E gives an arc point (less the origin) and its tangent."""
        tcam = (self.Rc[None] @ t[:, None, :, None])[..., 0] + self.tc     # (P, C, 3)
        # camera-frame columns [e1, e2, e2, -e1] (times radius); transposed and reshaped: the
        # rows [e1 e2] and [e2 -e1]
        E = np.swapaxes(self.Rc[None] @ (R @ self._W)[:, None], 2, 3).reshape(len(R), self.C, 2, 6)
        return tcam, E

    def _project_arc(self, cs, E, t4, full: bool = False):
        """Pixels (u, v) of arc points (P, C, N) at angles given as (cos, sin) ``cs`` (P, C, N, 2)
        and their derivatives (du, dv) along the arc (per radian); ``t4`` the camera-frame
        origin (P, C, 1, 3). With ``full`` also the depth z, 1/z, normalised x, y and the
        points less the origin."""
        XT = cs @ E
        W = XT[..., :3]
        z = W[..., 2] + t4[..., 2]
        iz = 1.0 / np.maximum(z, 1e-9)
        x, y = (W[..., 0] + t4[..., 0]) * iz, (W[..., 1] + t4[..., 1]) * iz
        dx, dy = (XT[..., 3] - x * XT[..., 5]) * iz, (XT[..., 4] - y * XT[..., 5]) * iz
        out = (self._fx * x + self._sk * y + self._cx, self._fy * y + self._cy,
               self._fx * dx + self._sk * dy, self._fy * dy)
        return out + (z, iz, x, y, W) if full else out

    def nearest_samples(self, E, t4):
        """Starts (P, C, 5 + M, 2) of the feet: (cos, sin) of the angle from the arc's middle of
        the keypoints A..E, then for each observed point the nearest of ``n_samples`` projected
        arc points."""
        X = self._samples @ E[..., :3] + t4                                # (P, C, S, 3)
        iz = 1.0 / np.maximum(X[..., 2], 1e-9)
        x, y = X[..., 0] * iz, X[..., 1] * iz
        u = (self._fx * x + self._sk * y + self._cx)[:, :, None, :]
        v = (self._fy * y + self._cy)[:, :, None, :]
        k = ((u - self._Ou[..., None]) ** 2 + (v - self._Ov[..., None]) ** 2).argmin(axis=3)
        cs = np.empty(k.shape[:2] + (5 + self.M, 2))
        cs[:, :, :5] = self._kp_cs
        cs[:, :, 5:] = self._samples[k]
        return cs

    def _newton(self, cs, E, t4, steps):
        """``steps`` Newton steps of the feet ``cs`` (the part after the 5 keypoints) along the
        projected arc towards the observed points, clamped to the arc."""
        if steps < 1:
            return cs
        c = cs[:, :, 5:]
        for _ in range(steps):
            u, v, tu, tv = self._project_arc(c, E, t4)
            du, dv = u - self._Ou, v - self._Ov
            step = -(tu * du + tv * dv) / np.maximum(tu * tu + tv * tv, 1e-300)
            step = np.minimum(np.maximum(step, -0.5), 0.5)[..., None]
            c = (c + step * c[..., ::-1] * self._perp) / np.sqrt(1.0 + step * step)
            c = np.where(c[..., :1] < self._cos_half, np.where(c[..., 1:] > 0, self._end_cs[1], self._end_cs[0]), c)
        out = np.empty_like(cs)
        out[:, :, :5] = self._kp_cs
        out[:, :, 5:] = c
        return out

    def feet(self, R, t, start=None, axes=None):
        """Feet (K, C, 5 + M, 2) for poses (R, t): (cos, sin) of the arc angles (from the arc's
        middle) of the keypoints and of each observed point's nearest arc point. From
        ``start`` (the feet at a nearby pose: ``warm_steps`` Newton steps) or else from the
        nearest of ``n_samples`` projected arc points (``foot_steps`` Newton steps)."""
        tcam, E = self._axes(R, t) if axes is None else axes
        t4 = tcam[:, :, None, :]
        cs = self.nearest_samples(E, t4) if start is None else start
        return self._newton(cs, E, t4, self.cfg.foot_steps if start is None else self.cfg.warm_steps)

    def evaluate(self, R, t, feet, jacobian: bool = True, axes=None):
        """Residuals (P, n) in px of P poses ``(R (P,3,3), t (P,3))`` with the ``feet`` (P, C,
        5 + M, 2) (see ``feet``) held fixed, their Jacobians (P, n, 6) w.r.t. the
        ECM increment [dr, dt] (None unless ``jacobian``), and whether each pose keeps the
        keypoints and the needle's centre in front of both cameras.

        Per camera: keypoint u (5) and v (5) errors; for each observed point the signed
        distance to the arc's tangent at its foot, and its overshoot past the nearer end of the
        arc along the outward tangent there (a hinge, kept only where the foot is at that end:
        elsewhere the projected arc may curve back past an end's tangent). Together they are
        the point's distance to the arc. The distance's derivative at a foot needs no foot
        derivative (envelope theorem); the overshoot's leaves out the turn of the end's tangent.
        """
        P = len(R)
        tcam, E = self._axes(R, t) if axes is None else axes
        t4 = tcam[:, :, None, :]
        co, si = feet[:, :, 5:, 0], feet[:, :, 5:, 1]
        u, v, tu, tv, z, iz, x, y, W = self._project_arc(feet, E, t4, full=True)
        zc = tcam[..., 2]
        valid = ((z[..., :5].min(axis=(1, 2)) > self.cfg.min_depth_m) & (zc.min(axis=1) > self.cfg.min_depth_m)
                 & (zc.max(axis=1) < self.cfg.max_depth_m))
        ru, rv = u[..., :5] - self._Uu, v[..., :5] - self._Uv
        du, dv = u[..., 5:] - self._Ou, v[..., 5:] - self._Ov
        itn = 1.0 / np.maximum(np.sqrt(tu * tu + tv * tv), 1e-300)
        nx, ny = -tv[..., 5:] * itn[..., 5:], tu[..., 5:] * itn[..., 5:]
        r_n = nx * du + ny * dv
        # outward unit tangents at A (index 0, towards -angle) and E (index 4)
        ox = tu[..., 0:5:4] * itn[..., 0:5:4] * self._out
        oy = tv[..., 0:5:4] * itn[..., 0:5:4] * self._out
        at_e = si > 0
        ex = np.where(at_e, ox[..., 1:], ox[..., :1])
        ey = np.where(at_e, oy[..., 1:], oy[..., :1])
        ov = np.where(at_e,
                      (self._Ou - u[..., 4:5]) * ox[..., 1:] + (self._Ov - v[..., 4:5]) * oy[..., 1:],
                      (self._Ou - u[..., 0:1]) * ox[..., :1] + (self._Ov - v[..., 0:1]) * oy[..., :1])
        at_end = co < self._cos_end_zone
        active = at_end & (ov > 0.0)
        r_t = np.where(at_end, np.maximum(ov, 0.0), 0.0)
        r = np.concatenate([ru, rv, r_n, r_t], axis=2).reshape(P, -1)
        if not jacobian:
            return r, None, valid

        # d(u, v)/d[dr, dt] of every point (see _Static: Ku, Kv, m), in the ECM frame
        Q = W @ self._L + self._L1                                          # (P, C, N, 18)
        izc = iz[..., None]
        Gu = (Q[..., :6] - (u - self._cx)[..., None] * Q[..., 12:]) * izc
        Gv = (Q[..., 6:12] - (v - self._cy)[..., None] * Q[..., 12:]) * izc
        # curve rows: along the normal at the foot; overshoot rows: minus the outward tangent at
        # the end's point (A or E), where active
        rows_n = nx[..., None] * Gu[..., 5:, :] + ny[..., None] * Gv[..., 5:, :]
        cu, cv = np.where(active, -ex, 0.0)[..., None], np.where(active, -ey, 0.0)[..., None]
        at_e4 = at_e[..., None]
        rows_t = (cu * np.where(at_e4, Gu[..., 4:5, :], Gu[..., 0:1, :])
                  + cv * np.where(at_e4, Gv[..., 4:5, :], Gv[..., 0:1, :]))
        J = np.concatenate([Gu[..., :5, :], Gv[..., :5, :], rows_n, rows_t], axis=2).reshape(P, -1, 6)
        return r, J, valid

    def linearise(self, R, t, start=None):
        """Residuals (K, n), Jacobians (K, n, 6) w.r.t. the ECM increment [dr, dt], the observed
        points' feet (a start for nearby poses) and validity of K poses. ``start``: see ``feet``."""
        axes = self._axes(R, t)
        cs = self.feet(R, t, start, axes)
        r, J, valid = self.evaluate(R, t, cs, axes=axes)
        return r, J, cs, valid

    def robust(self, r):
        """Per-residual Cauchy cost and IRLS weight (prior weights included)."""
        c2 = self._c2
        s2 = self.wp * r ** 2
        return c2 * np.log1p(s2 / c2), self.wp / (1.0 + s2 / c2)


def _undistort(cam, uv):
    from common.geometry.camera import undistort_pixels
    return undistort_pixels(cam.K, cam.dist, uv)


def _select_curve(name: str, pts, w, m: int, w_min: float):
    """At most m of the observed centreline points, evenly spaced in arc length. Points are
    picked, not interpolated, so that an exact observation stays exact."""
    pts = np.asarray(pts, float)
    w = np.ones(len(pts)) if w is None else np.asarray(w, float)
    if pts.ndim != 2 or pts.shape[1] != 2 or w.shape != (len(pts),):
        raise RefineError("bad_centreline", f"{name}: need centreline (N, 2) and centreline_w (N,), "
                          f"got {pts.shape} and {w.shape}")
    if not (np.isfinite(pts.sum() + w.sum()) and w.min(initial=1.0) >= w_min):
        ok = np.isfinite(pts).all(axis=1) & np.isfinite(w) & (w >= w_min)
        pts, w = pts[ok], w[ok]
    w = np.minimum(w, 1.0)
    if len(pts) <= m:
        return pts, w
    dp = np.diff(pts, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(dp[:, 0], dp[:, 1]))])
    idx = np.minimum(np.searchsorted(s, s[-1] * np.arange(m) / (m - 1)), len(pts) - 1)
    idx = idx[np.concatenate([[True], idx[1:] > idx[:-1]])]
    return pts[idx], w[idx]


def _orthonormalise(R):
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def tip_for_tail(T_ecm_needle: np.ndarray, needle: NeedleModel) -> np.ndarray:
    """The pose turned end for end: a half turn about the arc's axis of symmetry (the needle-frame
    line through the origin and the arc's middle), which maps the arc onto itself with A and E
    swapped. Without a sure tip or tail it fits a centreline exactly as well."""
    m = 0.5 * sum(needle.arc_span_rad)
    u = np.array([math.cos(m), math.sin(m), 0.0])
    return T_ecm_needle @ make_T(2.0 * np.outer(u, u) - np.eye(3), np.zeros(3))


def mirror_pose(T_ecm_needle: np.ndarray, needle: NeedleModel, eye_ecm=np.zeros(3),
                _centroid=None) -> np.ndarray:
    """The planar arc's mirror solution: reflected about the plane through the arc's centroid
    normal to the line of sight from ``eye_ecm``. Under weak perspective it projects onto the
    same image curve (an arc seen edge-on bulging towards instead of away from the camera)."""
    R, t = T_ecm_needle[:3, :3], T_ecm_needle[:3, 3]
    c = needle.sample_arc(64).mean(0) if _centroid is None else _centroid
    m = R @ c + t
    v = m - eye_ecm
    v = v / np.linalg.norm(v)
    Mref = np.eye(3) - 2.0 * np.outer(v, v)
    return make_T(Mref @ R @ np.diag([1.0, 1.0, -1.0]), m + Mref @ (t - m))


def _pose_delta(T, T_ref):
    """[rotation vector of R R_ref^T, t - t_ref]: T as a left increment of T_ref (ECM frame)."""
    dR = T[:3, :3] @ T_ref[:3, :3].T
    c = (dR[0, 0] + dR[1, 1] + dR[2, 2] - 1.0) / 2.0
    if -0.99 < c < 1.0 - 1e-12:            # away from 0 and pi: the log map directly
        a = math.acos(c)
        w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) * (a / (2 * math.sin(a)))
    else:
        w = R_to_rotvec(dR)
    return np.concatenate([w, T[:3, 3] - T_ref[:3, 3]])


# ------------------------------------------------------------------ the solver

_I6 = np.eye(6)


def _lm(prob: _Problem, R, t, cfg: RefineConfig, n_iter: int, state=None):
    """Batched Levenberg-Marquardt on K poses; returns the state dict (poses, costs, ...).

    A pose is done when the step on offer is far inside its own uncertainty (the step's cost
    change ``dx' H dx`` below ``step_tol`` residual variances), when a step is negligible in
    absolute terms, or after ``max_reject`` rejected steps in a row (a cost at rounding level)."""
    K = len(R)
    if state is None:
        r, J, cs, valid = prob.linearise(R, t)
        rho, wr = prob.robust(r)
        cost = rho.sum(1)
        cost[~(valid & np.isfinite(cost))] = np.inf
        state = dict(R=R, t=t, r=r, J=J, cs=cs, wr=wr, cost=cost, lam=np.full(K, 1e-3),
                     rej=np.zeros(K, int), done=~np.isfinite(cost), iters=0)
    s = state
    dof = max(prob.n_res - 6, 1)
    for _ in range(n_iter):
        act = np.flatnonzero(~s["done"])
        if len(act) == 0:
            break
        s["iters"] += 1
        r, J, wr = s["r"][act], s["J"][act], s["wr"][act]
        JtW = np.swapaxes(J * wr[..., None], 1, 2)
        H = JtW @ J
        g = (JtW @ r[..., None])[..., 0]
        dg = np.maximum(np.diagonal(H, axis1=1, axis2=2), 1e-300)
        # Jacobi scaling: rotation (rad) and translation (m) columns differ by ~1e2.
        sc = 1.0 / np.sqrt(dg)
        A = H * sc[:, :, None] * sc[:, None, :] + s["lam"][act, None, None] * _I6
        try:
            dx = -sc * np.linalg.solve(A, (g * sc)[..., None])[..., 0]
        except np.linalg.LinAlgError:
            dx = -sc * np.stack([np.linalg.lstsq(a, b * c, rcond=None)[0] for a, b, c in zip(A, g, sc)])
        # Trust region: no step turns more than max_step_rad or moves more than max_step_m (a
        # nearly face-on arc leaves its tilt weakly determined; a full step may leap far).
        adx = np.abs(dx)
        rot, tra = adx[:, :3].max(axis=1), adx[:, 3:].max(axis=1)
        shrink = np.minimum(1.0, np.minimum(cfg.max_step_rad / np.maximum(rot, 1e-300),
                                            cfg.max_step_m / np.maximum(tra, 1e-300)))
        dx = dx * shrink[:, None]
        rot, tra = rot * shrink, tra * shrink
        # Converged when the step on offer is far inside the pose's own uncertainty: its cost
        # change below step_tol residual variances (then it is not taken, nor evaluated).
        quad = (dx[:, None, :] @ H @ dx[..., None])[:, 0, 0]
        # (residuals are in sigmas, so a variance above 1 is outliers' doing: not a looser bound)
        within = (shrink == 1.0) & (quad < cfg.step_tol * np.minimum(s["cost"][act] / dof, 1.0))
        if within.any():
            # the small step is still taken, unevaluated (its effect on the fit's residuals and
            # Jacobian, kept for the covariance, is within the same fraction of a variance)
            iw = act[within]
            s["R"][iw] = rotvecs_to_Rs(dx[within, :3]) @ s["R"][iw]
            s["t"][iw] = s["t"][iw] + dx[within, 3:]
            s["done"][iw] = True
            go = ~within
            if not go.any():
                break
            act, dx, rot, tra = act[go], dx[go], rot[go], tra[go]
        Rn = rotvecs_to_Rs(dx[:, :3]) @ s["R"][act]
        tn = s["t"][act] + dx[:, 3:]
        # Feet: carried over from the current poses, searched afresh after a large step.
        big = rot.max() > cfg.research_rad or tra.max() > cfg.research_m
        warm = None if big else s["cs"][act]
        rn, Jn, csn, validn = prob.linearise(Rn, tn, warm)
        rho_n, wr_n = prob.robust(rn)
        cost_n = rho_n.sum(1)
        cost_n[~(validn & np.isfinite(cost_n))] = np.inf
        old = s["cost"][act]
        acc = cost_n <= old
        ia = act[acc]
        new = (("R", Rn), ("t", tn), ("r", rn), ("J", Jn), ("cs", csn), ("wr", wr_n), ("cost", cost_n))
        if len(ia) == K:                       # every pose active and accepted: take them all
            s.update(new)
        else:
            for key, val in new:
                s[key][ia] = val[acc]
        s["lam"][ia] = np.maximum(s["lam"][ia] / 3.0, 1e-9)
        s["lam"][act[~acc]] *= 4.0
        s["rej"][ia] = 0
        s["rej"][act[~acc]] += 1
        small = (rot < 1e-11) & (tra < 1e-12)
        s["done"][act] |= small | (s["rej"][act] >= cfg.max_reject)
    return s


class DenseRefiner:
    """Dense refinement for one rig and needle model (set up once, then ``refine`` per frame)."""

    def __init__(self, rig: StereoRig, needle: NeedleModel, config: RefineConfig | None = None):
        self.config = config or RefineConfig()
        self.rig, self.needle = rig, needle
        self._static = _Static(rig, needle, self.config)

    def refine(self, observations: Mapping[str, ArcObservation],
               candidates: Sequence[np.ndarray], mirrors: bool | None = None,
               support_normal: np.ndarray | None = None) -> RefineResult:
        """See ``refine_pose``; ``mirrors`` overrides ``config.add_mirrors`` for this call."""
        cfg, st = self.config, self._static
        cands = [np.asarray(T, float) for T in candidates
                 if T is not None and np.shape(T) == (4, 4) and np.all(np.isfinite(T))]
        if not cands:
            raise RefineError("no_candidates", "no finite 4x4 initial pose given")
        prob = _Problem(st, observations)

        # Starts closer than merge_mm / merge_deg would converge to the same minimum: keep one.
        starts: list[np.ndarray] = []
        eye = st.cam_centres.mean(0)
        mirrors = ([mirror_pose(T, self.needle, eye, st.arc_centroid) for T in cands]
                   if (cfg.add_mirrors if mirrors is None else mirrors) else [])
        for T in cands + mirrors:
            if not _near_any(T, starts, cfg.merge_mm, cfg.merge_deg):
                starts.append(T)
        R = _orthonormalise(np.stack([T[:3, :3] for T in starts]))
        t = np.stack([T[:3, 3] for T in starts])

        s = _lm(prob, R, t, cfg, cfg.coarse_iter)
        if not np.any(np.isfinite(s["cost"])):
            raise RefineError("no_valid_candidate", "every candidate puts the needle behind a camera")
        # Merge the candidates that met; go on with the best max_candidates.
        keep = np.flatnonzero(np.isfinite(s["cost"]))
        keep = _dedupe(s, keep, cfg.distinct_mm, cfg.distinct_deg)[:cfg.max_candidates]
        s = {k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in s.items()}
        s = _lm(prob, s["R"], s["t"], cfg, cfg.max_iter - cfg.coarse_iter, state=s)
        log_prior = None if support_normal is None else resting_log_prior(
            s["R"], support_normal, cfg.rest_prior, math.radians(cfg.rest_sigma_deg))
        return _result(prob, s, cfg, log_prior)


def refine_pose(rig: StereoRig, needle: NeedleModel, observations: Mapping[str, ArcObservation],
                candidates: Sequence[np.ndarray], config: RefineConfig | None = None,
                support_normal: np.ndarray | None = None) -> RefineResult:
    """Refine ``T_ecm_needle`` against the keypoints and centrelines of both cameras.

    ``observations`` maps ``"left"``/``"right"`` to an ``ArcObservation`` (a camera may be left
    out); ``candidates`` are initial 4x4 ``T_ecm_needle`` (e.g. every solution of the stereo
    PnP). Every candidate (and its mirror image) is refined; the one with the lowest robust cost
    is returned. ``support_normal``: the normal (ECM frame) of a surface the needle may rest on
    (``common.geometry.rest_prior``); then the cost in residual variances less twice the log prior
    decides between the minima. Raises ``RefineError`` when no pose can be computed. For many
    frames of one rig, build a ``DenseRefiner`` once instead.
    """
    return DenseRefiner(rig, needle, config).refine(observations, candidates, support_normal=support_normal)


def _near_any(T, Ts, mm, deg) -> bool:
    """Whether T is within mm and deg of any pose in Ts."""
    d2, cos_tol = (mm * 1e-3) ** 2, math.cos(math.radians(deg))
    R = T[:3, :3].ravel()
    for T2 in Ts:
        d = T[:3, 3] - T2[:3, 3]
        # the angle of R^T R2 from its trace, sum(R * R2)
        if d @ d < d2 and (float(R @ T2[:3, :3].ravel()) - 1.0) / 2.0 > cos_tol:
            return True
    return False


def _dedupe(s, idx, mm, deg):
    order = idx[np.argsort(s["cost"][idx])]
    kept: list[int] = []
    for i in order:
        Ti = make_T(s["R"][i], s["t"][i])
        if not _near_any(Ti, [make_T(s["R"][j], s["t"][j]) for j in kept], mm, deg):
            kept.append(int(i))
    return np.array(kept, int)


def _residual_variance(prob: _Problem, r, wr, cfg: RefineConfig) -> float:
    """Residual variance at an optimum, in units of the assumed sigmas (~1 when they hold). An
    exact fit does not claim infinite certainty: at least min_sigma_ratio of the sigmas."""
    return max(float((wr * r ** 2).sum() / max(prob.n_res - 6, 1)), cfg.min_sigma_ratio ** 2)


def _result(prob: _Problem, s, cfg: RefineConfig, log_prior=None) -> RefineResult:
    """The best minimum: the lowest cost, or with ``log_prior`` (K,) the lowest cost in residual
    variances less twice the log prior. Competitors, the ambiguity and the covariance's
    inflation are judged on the costs alone."""
    order = np.argsort(s["cost"])
    order = order[np.isfinite(s["cost"][order])]
    b = order[0]
    r = s["r"][b]
    _, wr = prob.robust(r)
    s2 = _residual_variance(prob, r, wr, cfg)
    k = 0 if log_prior is None else int(np.argmin(s["cost"][order] / s2 - 2.0 * np.asarray(log_prior)[order]))
    if k:
        order = np.concatenate([order[k:k + 1], np.delete(order, k)])
        b = order[0]
        r = s["r"][b]
        _, wr = prob.robust(r)
        s2 = _residual_variance(prob, r, wr, cfg)
    T0 = make_T(s["R"][b], s["t"][b])
    J = s["J"][b]
    n_res = prob.n_res
    H = J.T @ ((wr * prob.cov_scale)[:, None] * J)
    cov = s2 * _inv_psd(H)
    cov[:3, :3] += math.radians(cfg.model_sigma_deg) ** 2 * np.eye(3)
    cov[3:, 3:] += (cfg.model_sigma_mm * 1e-3) ** 2 * np.eye(3)
    # RMS per keypoint coordinate and per curve point (its two residuals, normal and
    # overshoot, make one distance)
    r2 = r * r
    sq_kp, sq_curve = float(r2[prob.used_kp].sum()), float(r2[prob.used_curve].sum())
    rms = lambda sq, n: math.sqrt(sq / n) if n else float("nan")

    # Competing solutions: other distinct minima, and how much worse they fit.
    cands, reasons = [(T0, float(s["cost"][b]))], []
    competitors = []
    for j in order[1:]:
        Tj = make_T(s["R"][j], s["t"][j])
        if _near_any(Tj, [c[0] for c in cands], cfg.distinct_mm, cfg.distinct_deg):
            continue
        cands.append((Tj, float(s["cost"][j])))
        # judged on the images alone: a prior may pick between minima, not hide one
        competitors.append((Tj, abs(s["cost"][j] - s["cost"][b]) / s2))
    view = _view_angle_deg(prob, T0)
    edge_on = view < cfg.edge_on_deg
    close = [(Tj, dchi) for Tj, dchi in competitors if dchi < cfg.ambiguity_chi2]
    if close:
        reasons.append("competing_candidates")
    if edge_on:
        reasons.append("edge_on")
    # Inflate by the spread of the competitors: fully for those nearly as good (more leniently
    # judged when edge-on), by their relative likelihood for the others.
    full = cfg.edge_on_chi2 if edge_on else cfg.ambiguity_chi2
    for Tj, dchi in competitors:
        a = 1.0 if dchi < full else float(np.exp(-0.5 * dchi))
        if a > 1e-12:
            d = _pose_delta(Tj, T0)
            cov = cov + a * np.outer(d, d)
    cov = 0.5 * (cov + cov.T)
    return RefineResult(
        T_ecm_needle=T0, covariance=cov, rms_px=rms(sq_kp + sq_curve, 2 * prob.n_kp + prob.n_curve),
        rms_kp_px=rms(sq_kp, 2 * prob.n_kp), rms_curve_px=rms(sq_curve, prob.n_curve),
        cost=float(s["cost"][b]), ambiguous=bool(reasons),
        reasons=tuple(reasons), view_angle_deg=view, n_iter=int(s["iters"]),
        n_residuals=n_res, candidates=cands,
        competitor_chi2=float(min((dchi for _, dchi in competitors), default=np.inf)),
        residual_variance=float(s2))


def _inv_psd(H):
    """Inverse of a 6x6 normal matrix with Jacobi scaling; unobservable directions get a huge
    (not infinite) variance."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    dd = np.outer(d, d)
    Hs = H / dd
    try:                                   # well conditioned (the usual case): Cholesky
        L = np.linalg.cholesky(Hs)
        if np.diag(L).min() > 1e-6:
            Li = np.linalg.inv(L)
            return (Li.T @ Li) / dd
    except np.linalg.LinAlgError:
        pass
    w, V = np.linalg.eigh(Hs)
    w = np.maximum(w, 1e-12 * max(w.max(), 1e-300))
    return (V / w) @ V.T / dd


def _view_angle_deg(prob: _Problem, T) -> float:
    """Smallest angle (deg) between the arc's plane and a camera's line of sight to the arc."""
    v = (T[:3, :3] @ prob.arc_centroid + T[:3, 3]) - prob.cam_centres
    s = np.abs(v @ T[:3, 2]) / np.sqrt((v * v).sum(axis=1))
    return math.degrees(math.asin(min(1.0, float(s.min()))))

