"""The needle fitted through a user's clicks: the pose whose projected arc passes through them,
and the labels it gives (keypoints A..E with visibility, box, pose, their stated noise).

Clicks per camera (pixels, as the image file shows them): the tip (A), the tail (E), any number
of points on the wire between them, keypoints marked hidden, or the needle marked not seen in
that camera. The fit is the project's dense arc fit (``common.geometry.refine.DenseRefiner``):
the tip and tail are keypoints A and E, the wire points are centreline points (each pulls the
projected model arc through it, wherever along the arc it lies), every click with the stated
click noise ``sigma_px``. With both cameras clicked the pose is the stereo fit; with one camera
it is that camera's fit (its projection in that camera is sure, its depth is not: no pose is
written then). Starting poses: the chord from tip to tail (or, with an end hidden, from the
other end to the farthest wire point) turned about itself in steps of 30 degrees in each
clicked camera, plus any prior poses given (a detector's proposal, the previous frame's label);
the refinement adds each start's mirror image.

Poses are ``T_ecm_needle`` (m, rad); covariances over ``[rotation vector, translation]`` in the
ECM frame, as ``common.geometry.refine.RefineResult``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.detector.centreline_subpixel import (
    CENTRELINE_CORR_POINTS,
    CENTRELINE_SIGMA_PX,
    refine_centreline,
)
from common.geometry.camera import StereoRig, undistort_pixels
from common.geometry.needle import NeedleModel
from common.geometry.oracle import true_keypoints
from common.geometry.refine import ArcObservation, DenseRefiner, RefineConfig, RefineError
from common.geometry.transforms import make_T, rotvec_to_R, transform_points

CLICK_SIGMA_PX = 1.0          # the stated 1-sigma error of a click per image axis
MAX_WIRE_CLICKS = 32          # wire points per camera
CHORD_TURNS_DEG = tuple(range(0, 360, 30))
CHORD_DEPTHS = (1.0, 0.6)     # the chord's depth as its image length says, and nearer (foreshortened)
MIN_SNAPPED = 8               # wire centreline points a camera's image must give to be fitted
POSE_SIGMA_MM = 1.0           # a pose is written as truth only when stated this sure (largest 1-sigma
POSE_SIGMA_DEG = 2.0          # axis of its position and of its orientation) and not ambiguous


class LabelError(NeedletrackError, ValueError):
    """Clicks that cannot give a label; the text says what is missing."""


class LabelInputError(LabelError):
    """Input that cannot be read (a malformed click, field or index); the text names it."""


@dataclass
class CameraClicks:
    """One camera's clicks: ``tip``, ``tail`` (2,) px or None, ``wire`` (n, 2) px, ``hidden``
    (5,) bool (A..E marked hidden by the user), ``unseen`` (the needle is not in this image)."""

    tip: Optional[np.ndarray] = None
    tail: Optional[np.ndarray] = None
    wire: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    hidden: np.ndarray = field(default_factory=lambda: np.zeros(5, bool))
    unseen: bool = False

    @property
    def count(self) -> int:
        """Points clicked."""
        return (self.tip is not None) + (self.tail is not None) + len(self.wire)

    def to_json(self) -> dict:
        pt = lambda p: None if p is None else [round(float(p[0]), 3), round(float(p[1]), 3)]
        return {"tip": pt(self.tip), "tail": pt(self.tail), "wire": [pt(p) for p in self.wire],
                "hidden": [bool(h) for h in self.hidden], "unseen": bool(self.unseen)}


def _point(v, where: str, size) -> Optional[np.ndarray]:
    if v is None:
        return None
    if not (isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, (int, float))
                                                                  and not isinstance(x, bool) for x in v)):
        raise LabelInputError(f"{where}: expected [u, v] pixels, got {v!r}"[:160])
    p = np.array(v, float)
    w, h = size
    if not (np.all(np.isfinite(p)) and -0.5 <= p[0] <= w - 0.5 and -0.5 <= p[1] <= h - 0.5):
        raise LabelInputError(f"{where}: {p.tolist()} lies outside the {w}x{h} image")
    return p


def clicks_from_json(obj, image_size) -> dict:
    """``{camera: CameraClicks}`` from ``{"left": {...}, "right": {...}}`` (``CameraClicks.to_json``'s
    form; a camera or a key may be left out); LabelError naming the field."""
    if not isinstance(obj, dict):
        raise LabelInputError(f"clicks: expected {{\"left\": ..., \"right\": ...}}, got {type(obj).__name__}")
    extra = set(obj) - set(CAMERAS)
    if extra:
        raise LabelInputError(f"clicks: unknown camera {sorted(extra)[0]!r}"[:120])
    out = {}
    for cam in CAMERAS:
        c = obj.get(cam) or {}
        if not isinstance(c, dict):
            raise LabelInputError(f"clicks.{cam}: expected an object, got {type(c).__name__}")
        bad = set(c) - {"tip", "tail", "wire", "hidden", "unseen"}
        if bad:
            raise LabelInputError(f"clicks.{cam}: unknown field {sorted(bad)[0]!r}"[:120])
        wire = c.get("wire") or []
        if not isinstance(wire, list) or len(wire) > MAX_WIRE_CLICKS:
            raise LabelInputError(f"clicks.{cam}.wire: expected a list of at most {MAX_WIRE_CLICKS} points")
        hidden = c.get("hidden", [False] * 5)
        if not (isinstance(hidden, list) and len(hidden) == 5 and all(isinstance(b, bool) for b in hidden)):
            raise LabelInputError(f"clicks.{cam}.hidden: expected 5 booleans (A..E), got {hidden!r}"[:160])
        unseen = c.get("unseen", False)
        if not isinstance(unseen, bool):
            raise LabelInputError(f"clicks.{cam}.unseen: expected true or false, got {unseen!r}"[:120])
        pts = [_point(p, f"clicks.{cam}.wire[{i}]", image_size) for i, p in enumerate(wire)]
        out[cam] = CameraClicks(_point(c.get("tip"), f"clicks.{cam}.tip", image_size),
                                _point(c.get("tail"), f"clicks.{cam}.tail", image_size),
                                np.array(pts, float).reshape(-1, 2), np.array(hidden, bool), unseen)
    return out


def clicks_from_keypoints(uv: dict, hidden: Optional[dict] = None) -> dict:
    """Clicks that stand for a set of keypoints ``{camera: (5, 2) px or None}``: A as the tip, E
    as the tail, B and D on the wire (a detector's proposal, a projected prior pose); a camera
    without keypoints is left unclicked."""
    out = {}
    for cam in CAMERAS:
        k = uv.get(cam)
        if k is None:
            out[cam] = CameraClicks()
            continue
        k = np.asarray(k, float).reshape(5, 2)
        ok = np.all(np.isfinite(k), axis=1)
        out[cam] = CameraClicks(k[0] if ok[0] else None, k[4] if ok[4] else None,
                                k[[i for i in (1, 3) if ok[i]]].reshape(-1, 2),
                                np.zeros(5, bool) if hidden is None or hidden.get(cam) is None
                                else np.asarray(hidden[cam], bool))
    return out


@dataclass
class LabelFit:
    """A fit's result. ``T_ecm_needle`` the fitted pose; ``stereo`` both cameras clicked;
    ``cameras`` those clicked; ``keypoints`` {camera: (5, 2) px} its projections, ``visible``
    {camera: (5,) bool} (in front, inside the image, not marked hidden, the camera not marked
    unseen), ``bbox`` {camera: [x0, y0, x1, y1] or None} (the projected arc's seen part, widened
    by the wire's radius), ``sigma_px`` {camera: (5,)} each keypoint's stated 1-sigma error per
    axis, ``covariance`` (6, 6), ``ambiguous`` (the images leave another pose nearly as good:
    ``alternatives``, the other poses, best first), ``rms_px`` the fit's RMS residual (the clicks
    and the snapped wire points, px), ``snapped`` the wire's centreline points found in the images and fitted (0: the
    clicks alone). ``pose_sigma_mm``, ``pose_sigma_deg``: the covariance's largest 1-sigma axis
    of position and orientation. ``pose_known``: the pose may be written as truth (stereo, not
    ambiguous, stated within ``POSE_SIGMA_MM`` and ``POSE_SIGMA_DEG``)."""

    T_ecm_needle: np.ndarray
    stereo: bool
    cameras: tuple
    keypoints: dict
    visible: dict
    bbox: dict
    sigma_px: dict
    covariance: np.ndarray
    ambiguous: bool
    rms_px: float
    alternatives: list = field(default_factory=list)
    choice: int = 0
    snapped: int = 0

    @property
    def pose_sigma_mm(self) -> float:
        return 1e3 * math.sqrt(max(float(np.linalg.eigvalsh(self.covariance[3:, 3:]).max()), 0.0))

    @property
    def pose_sigma_deg(self) -> float:
        return math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(self.covariance[:3, :3]).max()), 0.0)))

    @property
    def pose_known(self) -> bool:
        return (self.stereo and not self.ambiguous and self.pose_sigma_mm <= POSE_SIGMA_MM
                and self.pose_sigma_deg <= POSE_SIGMA_DEG)

    def arc(self, rig: StereoRig, needle: NeedleModel, n: int = 48) -> dict:
        """{camera: (m, 2) px} the fitted arc from A to E (points in front of the camera)."""
        out = {}
        for cam in CAMERAS:
            p = transform_points(rig[cam].T_cam_ecm @ self.T_ecm_needle, needle.sample_arc(n))
            out[cam] = rig[cam].project(p[p[:, 2] > 1e-6]) if np.any(p[:, 2] > 1e-6) else np.zeros((0, 2))
        return out


def chord_starts(uv_p, uv_q, camera, needle: NeedleModel, angles_rad=None, turns_deg=CHORD_TURNS_DEG,
                 depths=CHORD_DEPTHS) -> list:
    """Starting poses ``T_ecm_needle`` from two pixels of the needle in one camera, at the arc
    angles ``angles_rad`` (default: the tip A and the tail E): the chord between those two
    points of the arc placed at the depth at which its true length spans the pixels (and nearer,
    by ``depths``: a chord seen obliquely looks shorter), the arc's plane turned about the chord
    by each of ``turns_deg``."""
    K = camera.K
    a = needle.keypoint_angles_rad
    A, E = needle.arc_points([a[0], a[-1]] if angles_rad is None else angles_rad)
    chord_m = float(np.linalg.norm(E - A))
    ends = undistort_pixels(K, camera.dist, np.array([uv_p, uv_q], float))
    rays = [np.linalg.solve(K, np.array([p[0], p[1], 1.0])) for p in ends]
    rays = [r / r[2] for r in rays]
    span_px = float(np.linalg.norm(ends[1] - ends[0]))
    if span_px < 1.0 or chord_m < 1e-9:
        return []
    z0 = K[0, 0] * chord_m / span_px
    d_n = (E - A) / chord_m                       # needle frame: chord, towards the centre, normal
    mid_n = 0.5 * (A + E)
    u_n = -mid_n / max(np.linalg.norm(mid_n), 1e-12) if np.linalg.norm(mid_n) > 1e-9 * needle.radius_m \
        else np.cross([0.0, 0.0, 1.0], d_n)
    B_n = np.stack([d_n, u_n, np.cross(d_n, u_n)], axis=1)
    out = []
    for scale in depths:
        PA, PE = rays[0] * z0 * scale, rays[1] * z0 * scale
        d_c = (PE - PA) / max(np.linalg.norm(PE - PA), 1e-12)
        ref = np.array([0.0, 0.0, 1.0]) if abs(d_c[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        u0 = np.cross(d_c, ref)
        u0 /= np.linalg.norm(u0)
        for turn in turns_deg:
            u_c = rotvec_to_R(d_c * math.radians(turn)) @ u0
            B_c = np.stack([d_c, u_c, np.cross(d_c, u_c)], axis=1)
            R = B_c @ B_n.T
            t = 0.5 * (PA + PE) - R @ mid_n
            out.append(camera.T_ecm_cam @ make_T(R, t))
    return out


def click_starts(c: CameraClicks, camera, needle: NeedleModel) -> list:
    """Starting poses from one camera's clicks: the chord from the tip to the tail; with one end
    hidden, the chord from that end to the wire point farthest from it, that point taken at each
    of the keypoint angles B, C and D in turn (the hidden part of the arc is unknown)."""
    a = needle.keypoint_angles_rad
    if c.tip is not None and c.tail is not None:
        return chord_starts(c.tip, c.tail, camera, needle)
    end, at = (c.tip, a[0]) if c.tip is not None else (c.tail, a[-1])
    if end is None or not len(c.wire):
        return []
    far = c.wire[int(np.argmax(np.linalg.norm(c.wire - end, axis=1)))]
    return [T for k in (1, 2, 3) for T in chord_starts(end, far, camera, needle, [at, a[k]])]


def _keypoint_sigma(cam, T, cov, needle: NeedleModel, eps: float = 1e-6) -> np.ndarray:
    """(5,) 1-sigma per image axis of each keypoint's projection, from the pose covariance over
    [w, v] (``R = exp(w) R0``, ``t = t0 + v``, ECM frame), to first order."""
    P = needle.keypoints()
    base, _ = true_keypoints(cam, T, needle)
    J = np.zeros((5, 2, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        Tk = make_T(rotvec_to_R(d[:3]) @ T[:3, :3], T[:3, 3] + d[3:])
        uv, _ = true_keypoints(cam, Tk, needle)
        J[:, :, k] = (uv - base) / eps
    C = np.einsum("kij,jl,kml->kim", J, cov, J)
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.maximum(np.trace(C, axis1=1, axis2=2) / 2.0, 0.0))


def _seen_bbox(cam, T, needle: NeedleModel, hidden: np.ndarray):
    """The projected arc's box where it is seen: arc samples whose nearest keypoint (in angle) is
    not hidden (``seen_angles``), inside the image, widened by the wire's projected radius; None
    when none."""
    p = transform_points(cam.T_cam_ecm @ T, needle.arc_points(seen_angles(needle, hidden, 64)))
    p = p[p[:, 2] > 1e-6]
    if len(p) == 0:
        return None
    uv = cam.project(p)
    inside = cam.in_image(uv)
    if not inside.any():
        return None
    r_px = 0.5 * needle.wire_diameter_m * cam.K[0, 0] / p[inside, 2]
    lo = (uv[inside] - r_px[:, None]).min(axis=0)
    hi = (uv[inside] + r_px[:, None]).max(axis=0)
    w, h = cam.width, cam.height
    return [float(np.clip(lo[0], -0.5, w - 0.5)), float(np.clip(lo[1], -0.5, h - 0.5)),
            float(np.clip(hi[0], -0.5, w - 0.5)), float(np.clip(hi[1], -0.5, h - 0.5))]


def seen_angles(needle: NeedleModel, hidden, n: int) -> np.ndarray:
    """``n`` arc angles evenly from A to E, less those whose nearest keypoint (in angle) is marked
    ``hidden`` (5,): the part of the arc the user says is seen."""
    a0, a1 = needle.arc_span_rad
    ang = np.linspace(a0, a1, n)
    nearest = np.abs(ang[:, None] - needle.keypoint_angles_rad[None]).argmin(axis=1)
    return ang[~np.asarray(hidden, bool)[nearest]]


def snap_to_wire(image: np.ndarray, camera, T_ecm_needle: np.ndarray, needle: NeedleModel,
                 hidden=np.zeros(5, bool), spacing_px: float = 1.0) -> np.ndarray:
    """The wire's centreline in ``image`` (BGR) near a pose's projected arc: stations about
    ``spacing_px`` apart along the arc's seen part (``seen_angles``: not near a keypoint marked
    ``hidden``, where an instrument's jaw or tissue lies over it), each moved onto the wire's
    centre across the curve (``common.detector.centreline_subpixel.refine_centreline``: the
    whiteness profile's centroid between the wire's edges); stations where the profile is not
    one wire's (hidden, glare, an instrument) and the two at each end of a run are left out.
    (n, 2) px, maybe n = 0."""
    a0, a1 = needle.arc_span_rad
    p = transform_points(camera.T_cam_ecm @ T_ecm_needle, needle.arc_points(np.linspace(a0, a1, 64)))
    if np.any(p[:, 2] <= 1e-6):
        return np.zeros((0, 2))
    length = needle.radius_m * (a1 - a0) * camera.K[0, 0] / float(p[:, 2].min())
    ang = seen_angles(needle, hidden, int(np.clip(length / spacing_px, 8, 2000)))
    step = (a1 - a0) / max(int(np.clip(length / spacing_px, 8, 2000)) - 1, 1)
    out = []
    for run in np.split(ang, np.flatnonzero(np.diff(ang) > 1.5 * step) + 1):
        if len(run) < 8:
            continue
        p = transform_points(camera.T_cam_ecm @ T_ecm_needle, needle.arc_points(run))
        pts, w = refine_centreline(image, camera.project(p), np.ones(len(run)))
        out.append(pts[(w > 0) & camera.in_image(pts)])
    return np.concatenate(out) if out else np.zeros((0, 2))


class LabelFitter:
    """Fits labels for one rig and needle model (set up once; ``fit`` per set of clicks)."""

    def __init__(self, rig: StereoRig, needle: NeedleModel, sigma_px: float = CLICK_SIGMA_PX):
        if not (math.isfinite(sigma_px) and sigma_px > 0):
            raise LabelError(f"click sigma must be a positive number of pixels, got {sigma_px}")
        self.rig, self.needle, self.sigma_px = rig, needle, float(sigma_px)
        cfg = RefineConfig(min_cameras=1, sigma_kp_px=sigma_px, sigma_curve_px=sigma_px, max_iter=60,
                           max_candidates=4)
        self.refiner = DenseRefiner(rig, needle, cfg)

    def fit(self, clicks: dict, images: Optional[dict] = None, priors: Sequence[np.ndarray] = (),
            choice: int = 0, snap: bool = True) -> LabelFit:
        """The label of ``clicks`` ({camera: CameraClicks}). ``images`` ({camera: BGR}) with
        ``snap``: the fit is then redone twice against the wire's centreline found in each
        clicked camera's image near the fitted arc (``snap_to_wire``; the clicks keep the arc's
        ends), dropped where fewer than ``MIN_SNAPPED`` stations are found or where it moves the
        tip or tail more than 3 sigmas from their clicks. ``priors``: more starting poses
        ``T_ecm_needle``; ``choice`` picks among the fit's distinct minima (0: the best; the
        user's pick where the images leave it ambiguous). LabelError says what is missing."""
        seen = tuple(c for c in CAMERAS if c in clicks and not clicks[c].unseen and clicks[c].count)
        if not seen:
            raise LabelError("no clicks: click the tip, the tail and a point on the wire in each camera "
                             "that shows the needle (or mark the frame no needle)")
        starts = [np.asarray(T, float) for T in priors if T is not None]
        for cam in seen:
            starts += click_starts(clicks[cam], self.rig[cam], self.needle)
        if not starts:
            raise LabelError("click the tip or the tail and a point on the wire in one camera at least: "
                             "without them (or a proposal to start from) the arc has no start")
        res = self._refine(self._observations(clicks, seen), starts)
        cands = [T for T, _ in res.candidates]
        choice = int(choice) % len(cands)
        snapped = 0
        if images and snap:
            for _ in range(2):
                lines = {cam: snap_to_wire(images[cam], self.rig[cam], cands[choice], self.needle,
                                           clicks[cam].hidden)
                         for cam in seen if images.get(cam) is not None}
                lines = {cam: p for cam, p in lines.items() if len(p) >= MIN_SNAPPED}
                if not lines:
                    break
                try:
                    res2 = self._refine(self._observations(clicks, seen, lines), [cands[choice]])
                except LabelError:
                    break
                if not res2.rms_kp_px <= 3.0 * self.sigma_px:
                    break
                res, cands, choice = res2, [T for T, _ in res2.candidates], 0
                snapped = sum(len(p) for p in lines.values())
        return self.label(cands[choice], res.covariance, clicks, seen, res.ambiguous, res.rms_px,
                          [T for i, T in enumerate(cands) if i != choice], choice, snapped)

    def _observations(self, clicks: dict, seen: tuple, lines: Optional[dict] = None) -> dict:
        """The fit's ``ArcObservation`` per clicked camera: tip and tail as A and E, the wire
        clicks as centreline points (or, with ``lines``, the wire's snapped centreline)."""
        obs = {}
        for cam in seen:
            c = clicks[cam]
            uv = np.full((5, 2), np.nan)
            if c.tip is not None:
                uv[0] = c.tip
            if c.tail is not None:
                uv[4] = c.tail
            if lines and cam in lines:
                obs[cam] = ArcObservation(uv=uv, scores=np.ones(5), centreline=lines[cam],
                                          centreline_sigma_px=CENTRELINE_SIGMA_PX,
                                          centreline_corr_points=CENTRELINE_CORR_POINTS,
                                          keypoint_sigma_px=self.sigma_px)
            else:
                obs[cam] = ArcObservation(uv=uv, scores=np.ones(5), centreline=c.wire if len(c.wire) else None,
                                          centreline_sigma_px=self.sigma_px, keypoint_sigma_px=self.sigma_px)
        return obs

    def _refine(self, obs: dict, starts: list):
        try:
            return self.refiner.refine(obs, starts)
        except RefineError as exc:
            if exc.reason == "too_few_points":
                raise LabelError(f"too few clicks to fit the arc ({exc}); add points on the wire") from None
            raise LabelError(f"no arc fits these clicks ({exc})") from None

    def label(self, T, cov, clicks: dict, seen: tuple, ambiguous: bool, rms_px: float,
              alternatives: list = (), choice: int = 0, snapped: int = 0) -> LabelFit:
        """The label fields of pose ``T`` in both cameras (see ``LabelFit``)."""
        kps, vis, box, sig = {}, {}, {}, {}
        for cam in CAMERAS:
            camera = self.rig[cam]
            c = clicks.get(cam) or CameraClicks()
            uv, inside = true_keypoints(camera, T, self.needle)
            kps[cam] = uv
            vis[cam] = inside & ~c.hidden & (cam in seen)
            box[cam] = _seen_bbox(camera, T, self.needle, c.hidden) if cam in seen and not c.hidden.all() else None
            sig[cam] = _keypoint_sigma(camera, T, cov, self.needle)
        return LabelFit(T, len(seen) == 2, tuple(seen), kps, vis, box, sig, cov, bool(ambiguous),
                        float(rms_px), list(alternatives), choice, snapped)

