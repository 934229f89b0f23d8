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
pose that may be wrong is never reported as a confident one. A direction of the pose that the
images leave unfixed (a short stretch of arc, no keypoint observed: the normal matrix nearly
singular), or a spread of competitors beyond knowing nothing, is given the widest honest
variance (``common.geometry.covariance_bound``) and flagged ``ambiguous`` (``unobservable``),
never an arbitrarily large one. Given the normal of a surface the
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

from common.geometry import lm
from common.constraints import NonNegativeNumber, PositiveNumber, at_least, check_fields, in_range
from common.geometry.camera import Camera, StereoRig
from common.geometry.covariance_bound import bounded_covariance, bounded_inverse, within_bound
from common.geometry.needle import NeedleModel
from common.geometry.rest_prior import resting_log_prior
from common.geometry.arc_problem import ArcProblem, ArcStatic, RefineError
from common.geometry.transforms import (
    make_T,
    pose_delta,
    project_to_SO3,
    skew,
    symmetrise,
    transform_points,
)


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
    scale is in units of those sigmas. Each field's constraint is on its type
    (``common.constraints``)."""

    max_curve_points: at_least(2) = 64      # observed centreline points kept per camera (even in arc length)
    n_samples: at_least(2) = 24             # projected arc samples that start each point's foot search
    foot_steps: at_least(1) = 1             # then Newton steps along the projected arc, once per pose
    warm_steps: at_least(1) = 1             # Newton steps from feet carried over from the previous pose
    research_rad: PositiveNumber = 0.02      # after a step this large (rotation, rad) the feet are searched
    research_m: PositiveNumber = 0.001       # afresh (or translation, m); smaller steps carry them over
    max_step_rad: PositiveNumber = 0.1       # a step turns at most this much (rad) ...
    max_step_m: PositiveNumber = 0.005       # ... and moves at most this much (m)
    sigma_kp_px: PositiveNumber = 1.0        # assumed keypoint noise
    sigma_curve_px: PositiveNumber = 0.5     # assumed centreline noise
    min_score: float = 0.5          # keypoints scored below are left out (as the PnP does)
    # one camera poses the needle only through its arc's apparent size and shape: at 10-25 cm its
    # depth and tilt can be off by centimetres and tens of degrees, so the default needs both
    min_cameras: int = 2
    min_centreline_w: float = 0.05  # centreline points weighted below are left out
    cauchy_scale: PositiveNumber = 3.0       # robust loss scale, in sigmas
    cauchy_scale_end: PositiveNumber = 1.0   # the same for the overshoot past an arc's end (spurs: thread, glare)
    max_iter: at_least(1) = 30
    step_tol: PositiveNumber = 1.0           # converged after a step worth < this many residual variances
    max_reject: at_least(1) = 5             # ... or after this many rejected steps in a row
    coarse_iter: at_least(0) = 3            # iterations every candidate gets before those that met merge
    max_candidates: at_least(1) = 3         # and the best this many are refined to the end
    add_mirrors: bool = True        # also refine each candidate's mirror image about the line of sight
    merge_mm: PositiveNumber = 5.0           # starting poses closer than this and merge_deg are refined once
    merge_deg: PositiveNumber = 10.0
    ambiguity_chi2: PositiveNumber = 9.0     # a competitor costing < this many residual variances more: ambiguous
    distinct_mm: PositiveNumber = 1.0        # competitors closer than this and distinct_deg are the same solution
    distinct_deg: PositiveNumber = 2.0
    edge_on_deg: float = 10.0       # arc plane within this angle of the line of sight -> ambiguous
    edge_on_chi2: PositiveNumber = 100.0     # and then competitors costing < this many variances more count
    # Of an ambiguous frame's minima (within ambiguity_chi2, edge_on_chi2 edge-on), the one alone
    # within these of the needle's expected pose (its last pose seen from this frame's endoscope
    # pose: the other views of a multi-view group, the previous frame of a video) is the pose
    expected_mm: PositiveNumber = 3.0
    expected_deg: PositiveNumber = 10.0      # (and two poses in a row this close confirm the expected one)
    min_depth_m: float = 1e-3       # every point must be this far in front of both cameras
    max_depth_m: PositiveNumber = 2.0        # and the needle nearer than this (a PnP start may run off)
    min_sigma_ratio: PositiveNumber = 0.25   # the covariance assumes at least this fraction of the sigmas
    # The error no image noise explains (the needle's wire, arc, taper and swage against the model,
    # the rig's calibration), 1 sigma per axis, added to the covariance: from the images alone a
    # dense fit is a few hundredths of a millimetre and a tenth of a degree thin near the
    # endoscope, and errors the two nearly alike cameras share go into the pose, not the
    # residuals. Chosen on the end-identity fit folders, not the test sets, for a NEES median
    # near chi-square(6)'s 5.35 there (needletrack eval; docs/geometry.md#covariances-and-nees).
    model_sigma_mm: NonNegativeNumber = 0.03
    model_sigma_deg: NonNegativeNumber = 0.25
    # with a support surface's normal given (``refine(support_normal=)``): probability that the
    # needle rests on it, and the spread of its tilt then (common/geometry/rest_prior.py)
    rest_prior: in_range(0.0, 1.0) = 0.5
    rest_sigma_deg: PositiveNumber = 10.0

    def __post_init__(self):
        check_fields(self)


@dataclass
class RefineResult:
    """The refined pose ``T_ecm_needle`` (4x4, m) and what the fit says about it.

    ``covariance`` (6, 6) over [rotation vector (rad), translation (m)] in the ECM frame (inflated
    when ambiguous, and no wider than ``common.geometry.covariance_bound``'s bound);
    ``rms_px`` the RMS of all residuals (px) at the optimum, ``rms_kp_px`` and
    ``rms_curve_px`` per term (NaN when the term is empty); ``ambiguous`` with ``reasons``
    (``competing_candidates``, ``edge_on``, ``unobservable``: some direction of the pose spread
    to the bound, which the images do not fix); ``view_angle_deg`` the smallest angle between the arc's
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


def mirror_covariance(T_ecm_needle: np.ndarray, covariance: np.ndarray, needle: NeedleModel,
                      eye_ecm=np.zeros(3), _centroid=None) -> np.ndarray:
    """A [w, v] covariance (ECM frame) at ``T_ecm_needle`` carried to its ``mirror_pose``, to first
    order with the line of sight held: the mirror's rotation increment is ``-M w`` (``M`` the
    reflection) and its origin moves by ``v - (I - M) [R c]x w`` (``c`` the arc's centroid)."""
    R, t = T_ecm_needle[:3, :3], T_ecm_needle[:3, 3]
    c = needle.sample_arc(64).mean(0) if _centroid is None else _centroid
    Rc = R @ c
    v = Rc + t - eye_ecm
    v = v / np.linalg.norm(v)
    M = np.eye(3) - 2.0 * np.outer(v, v)
    J = np.zeros((6, 6))
    J[:3, :3] = -M
    J[3:, :3] = -(np.eye(3) - M) @ skew(Rc)
    J[3:, 3:] = np.eye(3)
    return J @ np.asarray(covariance, float) @ J.T


# ------------------------------------------------------------------ the solver

def _linearise(prob: ArcProblem, R, t, prev=None):
    """``lm.run``'s view of the fit: residuals, Jacobians, IRLS weights, robust costs (inf for
    an invalid pose) and the observed points' feet, carried over from ``prev`` when given."""
    r, J, cs, valid = prob.linearise(R, t, None if prev is None else prev["cs"])
    rho, wr = prob.robust(r)
    cost = rho.sum(1)
    cost[~(valid & np.isfinite(cost))] = np.inf
    return r, J, wr, cost, {"cs": cs}


def _lm(prob: ArcProblem, fits: lm.Fits, cfg: RefineConfig, n_iter: int) -> lm.Fits:
    """The batched Levenberg-Marquardt (``lm.run``) on K poses.

    A pose is done when the step on offer is far inside its own uncertainty (the step's cost
    change ``dx' H dx`` below ``step_tol`` residual variances; then it is taken unevaluated: its
    effect on the residuals and Jacobian kept for the covariance is within the same fraction of
    a variance), when a step is negligible in absolute terms, or after ``max_reject`` rejected
    steps in a row (a cost at rounding level). No step turns more than ``max_step_rad`` or
    moves more than ``max_step_m`` (a nearly face-on arc leaves its tilt weakly determined; a
    full step may leap far); after a step above ``research_rad``/``research_m`` the feet are
    searched afresh, else carried over."""
    def stop(dx, acc, pred, c1, c0, fits, act):
        adx = np.abs(dx)
        small = (adx[:, :3].max(axis=1) < 1e-11) & (adx[:, 3:].max(axis=1) < 1e-12)
        return small | (fits.rej[act] >= cfg.max_reject)
    return lm.run(fits, lambda R, t, prev: _linearise(prob, R, t, prev), n_iter, stop, damping="thirds",
                  max_step=(cfg.max_step_rad, cfg.max_step_m), settle_tol=cfg.step_tol,
                  dof=max(prob.n_res - 6, 1), relinearise=(cfg.research_rad, cfg.research_m))


class DenseRefiner:
    """Dense refinement for one rig and needle model (set up once, then ``refine`` per frame)."""

    def __init__(self, rig: StereoRig, needle: NeedleModel, config: RefineConfig | None = None):
        self.config = config or RefineConfig()
        self.rig, self.needle = rig, needle
        self._static = ArcStatic(rig, needle, self.config)

    def refine(self, observations: Mapping[str, ArcObservation],
               candidates: Sequence[np.ndarray], mirrors: bool | None = None,
               support_normal: np.ndarray | None = None,
               expected: np.ndarray | None = None) -> RefineResult:
        """See ``refine_pose``; ``mirrors`` overrides ``config.add_mirrors`` for this call;
        ``expected`` (4x4 ``T_ecm_needle`` or None) picks between near-equal minima
        (``RefineConfig.expected_mm``)."""
        cfg, st = self.config, self._static
        cands = [np.asarray(T, float) for T in candidates
                 if T is not None and np.shape(T) == (4, 4) and np.all(np.isfinite(T))]
        if not cands:
            raise RefineError("no_candidates", "no finite 4x4 initial pose given")
        prob = ArcProblem(st, observations)

        # Starts closer than merge_mm / merge_deg would converge to the same minimum: keep one.
        starts: list[np.ndarray] = []
        eye = st.cam_centres.mean(0)
        mirrors = ([mirror_pose(T, self.needle, eye, st.arc_centroid) for T in cands]
                   if (cfg.add_mirrors if mirrors is None else mirrors) else [])
        for T in cands + mirrors:
            if not _near_any(T, starts, cfg.merge_mm, cfg.merge_deg):
                starts.append(T)
        R = project_to_SO3(np.stack([T[:3, :3] for T in starts]))
        t = np.stack([T[:3, 3] for T in starts])

        s = _lm(prob, lm.Fits(R, t, _linearise(prob, R, t)), cfg, cfg.coarse_iter)
        if not np.any(np.isfinite(s.cost)):
            raise RefineError("no_valid_candidate", "every candidate puts the needle behind a camera")
        # Merge the candidates that met; go on with the best max_candidates.
        keep = np.flatnonzero(np.isfinite(s.cost))
        keep = _dedupe(s, keep, cfg.distinct_mm, cfg.distinct_deg)[:cfg.max_candidates]
        s = _lm(prob, s.take(keep), cfg, cfg.max_iter - cfg.coarse_iter)
        log_prior = None if support_normal is None else resting_log_prior(
            s.R, support_normal, cfg.rest_prior, math.radians(cfg.rest_sigma_deg))
        return _result(prob, s, cfg, log_prior, expected)


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
    order = idx[np.argsort(s.cost[idx])]
    kept: list[int] = []
    for i in order:
        Ti = make_T(s.R[i], s.t[i])
        if not _near_any(Ti, [make_T(s.R[j], s.t[j]) for j in kept], mm, deg):
            kept.append(int(i))
    return np.array(kept, int)


def _residual_variance(prob: ArcProblem, r, wr, cfg: RefineConfig) -> float:
    """Residual variance at an optimum, in units of the assumed sigmas (~1 when they hold). An
    exact fit does not claim infinite certainty: at least min_sigma_ratio of the sigmas."""
    return max(float((wr * r ** 2).sum() / max(prob.n_res - 6, 1)), cfg.min_sigma_ratio ** 2)


def near_expected(T_ecm_needle: np.ndarray, expected: np.ndarray, cfg: RefineConfig) -> bool:
    """Whether a pose lies within ``expected_mm`` / ``expected_deg`` of an expected one (4x4 each)."""
    return _near_any(T_ecm_needle, [expected], cfg.expected_mm, cfg.expected_deg)


def _expected_minimum(prob: ArcProblem, s, order: np.ndarray, s2: float, cfg: RefineConfig,
                      expected: np.ndarray) -> int:
    """Position in ``order`` of the one minimum near-equal to the best (within ambiguity_chi2
    residual variances, edge_on_chi2 when the best is seen edge-on) that lies within
    expected_mm / expected_deg of ``expected``; 0 (the best) when none or several distinct ones do."""
    b = order[0]
    full = cfg.edge_on_chi2 if _view_angle_deg(prob, make_T(s.R[b], s.t[b])) < cfg.edge_on_deg else cfg.ambiguity_chi2
    hits = [i for i, j in enumerate(order) if abs(s.cost[j] - s.cost[b]) / s2 < full
            and near_expected(make_T(s.R[j], s.t[j]), expected, cfg)]
    if not hits:
        return 0
    first = make_T(s.R[order[hits[0]]], s.t[order[hits[0]]])
    same = all(_near_any(make_T(s.R[order[i]], s.t[order[i]]), [first], cfg.distinct_mm, cfg.distinct_deg)
               for i in hits)
    return hits[0] if same else 0


def _promote(prob: ArcProblem, s, order: np.ndarray, k: int, cfg: RefineConfig):
    """``order`` with its ``k``-th minimum first, and that minimum's index, residuals, robust
    weights and residual variance: (order, b, r, wr, s2)."""
    if k:
        order = np.concatenate([order[k:k + 1], np.delete(order, k)])
    b = order[0]
    r = s.r[b]
    _, wr = prob.robust(r)
    return order, b, r, wr, _residual_variance(prob, r, wr, cfg)


def _result(prob: ArcProblem, s, cfg: RefineConfig, log_prior=None, expected=None) -> RefineResult:
    """The best minimum: the lowest cost, or with ``log_prior`` (K,) the lowest cost in residual
    variances less twice the log prior; then, with ``expected`` (4x4), the near-equal minimum
    alone near it (``_expected_minimum``). Competitors, the ambiguity and the covariance's
    inflation are judged on the costs alone."""
    order = np.argsort(s.cost)
    order, b, r, wr, s2 = _promote(prob, s, order[np.isfinite(s.cost[order])], 0, cfg)
    k = 0 if log_prior is None else int(np.argmin(s.cost[order] / s2 - 2.0 * np.asarray(log_prior)[order]))
    if k:
        order, b, r, wr, s2 = _promote(prob, s, order, k, cfg)
    k = 0 if expected is None else _expected_minimum(prob, s, order, s2, cfg, np.asarray(expected, float))
    if k:
        order, b, r, wr, s2 = _promote(prob, s, order, k, cfg)
    T0 = make_T(s.R[b], s.t[b])
    J = s.J[b]
    n_res = prob.n_res
    H = J.T @ ((wr * prob.cov_scale)[:, None] * J)
    cov = s2 * _inv_psd(H)
    # a direction the images leave unfixed: the bound's variance, not an arbitrarily large one
    unobservable = not within_bound(cov)
    if unobservable:
        cov = bounded_inverse(H / s2)
    cov[:3, :3] += math.radians(cfg.model_sigma_deg) ** 2 * np.eye(3)
    cov[3:, 3:] += (cfg.model_sigma_mm * 1e-3) ** 2 * np.eye(3)
    # RMS per keypoint coordinate and per curve point (its two residuals, normal and
    # overshoot, make one distance)
    r2 = r * r
    sq_kp, sq_curve = float(r2[prob.used_kp].sum()), float(r2[prob.used_curve].sum())
    rms = lambda sq, n: math.sqrt(sq / n) if n else float("nan")

    # Competing solutions: other distinct minima, and how much worse they fit.
    cands, reasons = [(T0, float(s.cost[b]))], []
    competitors = []
    for j in order[1:]:
        Tj = make_T(s.R[j], s.t[j])
        if _near_any(Tj, [c[0] for c in cands], cfg.distinct_mm, cfg.distinct_deg):
            continue
        cands.append((Tj, float(s.cost[j])))
        # judged on the images alone: a prior may pick between minima, not hide one
        competitors.append((Tj, abs(s.cost[j] - s.cost[b]) / s2))
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
            d = pose_delta(Tj, T0)
            cov = cov + a * np.outer(d, d)
    cov, spread = bounded_covariance(symmetrise(cov))
    if unobservable or spread:
        reasons.append("unobservable")
    return RefineResult(
        T_ecm_needle=T0, covariance=cov, rms_px=rms(sq_kp + sq_curve, 2 * prob.n_kp + prob.n_curve),
        rms_kp_px=rms(sq_kp, 2 * prob.n_kp), rms_curve_px=rms(sq_curve, prob.n_curve),
        cost=float(s.cost[b]), ambiguous=bool(reasons),
        reasons=tuple(reasons), view_angle_deg=view, n_iter=int(s.rounds),
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


def _view_angle_deg(prob: ArcProblem, T) -> float:
    """Smallest angle (deg) between the arc's plane and a camera's line of sight to the arc."""
    v = (T[:3, :3] @ prob.arc_centroid + T[:3, 3]) - prob.cam_centres
    s = np.abs(v @ T[:3, 2]) / np.sqrt((v * v).sum(axis=1))
    return math.degrees(math.asin(min(1.0, float(s.min()))))

