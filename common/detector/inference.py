"""Inference with the learned keypoint detector: image -> ``Keypoints`` (A..E, scores, centreline).

Two stages (see ``common.detector.model``): stage 1 on the downscaled image finds the needle
and its box and gives the confidence; stage 2 on a full-resolution crop around the box gives A..E
at sub-pixel precision, per-point scores, a presence confidence and the centreline (then moved
onto the wire's centre in the full-resolution image, ``common.detector.centreline_subpixel``). Cold frames
run stage 2 twice: the second time on the box of the first pass's keypoints, which puts the crop
at the scale and centring the network knows best; when A's and E's heatmaps there both peak at
one end of the needle, A and E are taken from the centreline ridge's ends
(``common.detector.ridge_ends``) and the frame states no end identity. In tracking mode (per camera) the previous
frame's box is reused and stage 1 is skipped while stage 2's presence confidence stays at or above
the threshold; otherwise the frame is processed cold. Below the threshold (0.5 by default, as in
the paper) the result is "no needle" (``Keypoints.not_found``) with a reason; points are never
guessed. A cold frame where no proposal passes is searched again with the image's hues turned
(``RETRY_HUES_DEG``): the networks read tissue of a colour no render has (a silicone pad, blue or
green) best turned towards the colours they were trained on; a needle found so must be surer
(``RETRY_PRESENCE``), and the turn that found it is kept for the camera's tracking frames. A camera's
tracked crop that a stereo pose node rejects (``reject``: the other camera and the track disagree
with it, ``common.geometry.stereo_agreement``) is dropped and searched cold, away from the
rejected box first (``AVOID_FRAMES``).

Weights are loaded with ``torch.load(..., weights_only=True)``; a missing, corrupt or mismatched
file raises ``ModelFileError`` saying how to retrain.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import cv2
import numpy as np
import torch

from common.detector.centreline_subpixel import (
    CENTRELINE_CORR_POINTS,
    CENTRELINE_SIGMA_PX,
    ellipse_residual,
    refine_centreline,
)
from common.detector.arc_fit import (
    ARC_ANGLES_DEG,
    ARC_MIN_SCORE,
    arc_at,
    decode_centreline,
    fit_arc_affine,
    ideal_peak_mass,
    refine_along_arc,
    unseen_on_arc_scores,
)
from common.detector.cut_ends import blunt_tip_scores, cut_end_scores
from common.detector.end_identity import EndEvidence, network_evidence, polyline_length, shape_evidence
from common.detector.model import (
    CropWithFeatures,
    FrozenForInference,
    apply_affine,
    crop_affine,
    crop_side,
    decode_global_topk,
    decode_heatmaps,
    global_size,
    invert_affine,
    visibility_logits,
)
from common.detector.config import RETRY_HUES_DEG, DetectorConfig
from common.detector.familiarity import FamiliarityFileError, familiarity_path, load_familiarity
from common.detector.data import global_input, turn_hue
from common.detector.ridge_ends import ends_on_ridge
from common.detector.weights import DEFAULT_WEIGHTS, load_end_coefficients, load_model, pick_device
from common.detector.presence_gate import DEFAULT_THRESHOLD, load_presence_gate
from common.runtime.messages import CameraImage, Keypoints, MessageError

MIN_ELLIPSE_SHARE = 0.5      # of the centreline points on that ellipse (a jaw may bend the rest)
MIN_ELLIPSE_POINTS = 8       # fewer (a needle mostly hidden) are not judged
# The keypoints' 1-sigma error per image axis as a stereo fit should take it (stated in every
# message): a little above the error needletrack bench detector measures on the test set,
# because the two cameras' nearly identical images give nearly alike errors, which a stereo fit
# absorbs (its residuals are smaller than that error). With it pnp_joint's covariance is honest
# (its NEES median in needletrack eval's results near chi-square(6)'s 5.35; from its residuals
# alone about ten times that); the dense fit assumes 1 px as well.
KEYPOINT_SIGMA_PX = 1.0
RETRY_EVERY = 5
"""After a cold frame where neither the image nor its turns gave a needle, only every this many-th
cold frame of that camera that nothing passes as it is is searched turned: the turns triple a
needle-free frame's cost (19 -> 61 ms on the test look's needle-free renders; 28 ms with this)."""
RETRY_PRESENCE = 0.8
"""The presence a needle found only with the image's hues turned must reach (above the detection
threshold): on 80 needle-free renders of the test look (``needletrack bench detector
--make-negatives 40``) the turned searches' best presences were under it in all but one image,
and the turns added no false detection (12 of 80 as they are); at the detection threshold (0.5),
9 of the first 20 gave a needle, against 2 as they are."""
AVOID_FRAMES = 30
"""After a camera's tracked crop is rejected (``reject``: the other camera and the track disagree
with it), its cold searches try stage 1's proposals away from the rejected box first for this
many frames (1 s at 30 Hz): a distractor that stage 1 ranks above the needle is not taken again
at once; with nothing else passing, the rejected box may still be found."""
log = logging.getLogger("needletrack.keypoint_detector")


def image_problem(img) -> str | None:
    """Why an array cannot be a camera image (None if it can be)."""
    if not isinstance(img, np.ndarray):
        return f"image is a {type(img).__name__}, not an array"
    if img.size == 0:
        return f"empty image (shape {img.shape})"
    if img.dtype != np.uint8:
        return f"image dtype {img.dtype}, expected uint8"
    if img.ndim == 2:
        return None
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        return f"image shape {img.shape}, expected (h, w, 3) BGR"
    if min(img.shape[:2]) < 16:
        return f"image too small ({img.shape[1]}x{img.shape[0]})"
    return None


def as_bgr(img: np.ndarray) -> np.ndarray:
    """A grey, one-channel or BGRA image as 3-channel BGR (a BGR image as it is)."""
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 1:
        return cv2.cvtColor(img[:, :, 0], cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def _centred_in(cx: float, cy: float, box) -> bool:
    """Whether the point (cx, cy) lies in the box [x0, y0, x1, y1]."""
    return bool(box[0] <= cx <= box[2] and box[1] <= cy <= box[3])


def _moved(box, new_box, tol: float = 0.1) -> bool:
    """Whether the needle's box (cx, cy, w, h) moved by more than ``tol`` of its larger side
    (centre or size): the tracked crop no longer frames it."""
    side = max(box[2], box[3], 1.0)
    return (abs(new_box[0] - box[0]) > tol * side or abs(new_box[1] - box[1]) > tol * side
            or abs(max(new_box[2], new_box[3]) - side) > tol * side)


class KeypointDetector:
    """The learned two-stage detector; one instance keeps a tracking state per camera name."""

    name = "learned"

    def __init__(self, weights=None, device: str = "auto", threads: int | None = None,
                 familiarity: bool = True, config: DetectorConfig | None = None, **settings):
        """``config``: the detector's settings, ``settings`` any of its fields set anew
        (``KeypointDetector(tracking=False)``); ``threads``: torch's threads."""
        self.config = c = dataclasses.replace(config or DetectorConfig(), **settings)
        self.device = pick_device(device)
        if threads:
            torch.set_num_threads(int(threads))
        self.weights = Path(weights or DEFAULT_WEIGHTS)
        self.model, self.meta = load_model(self.weights, self.device)
        self._glob = FrozenForInference(self.model.glob)
        self._crop = FrozenForInference(CropWithFeatures(self.model.crop))
        self.cfg = self.model.cfg
        self.presence_gate = load_presence_gate(self.weights) if c.threshold is None else None
        self.threshold = float(c.threshold if c.threshold is not None else
                               self.presence_gate.threshold if self.presence_gate else DEFAULT_THRESHOLD)
        self.tracking = bool(c.tracking)
        self.refine = bool(c.refine)
        self.centreline = bool(c.centreline)
        self.arc_bcd = bool(c.arc_bcd)
        self.along_arc = bool(c.along_arc)
        self.proposal_threshold = float(c.proposal_threshold)
        self.proposals = max(1, int(c.proposals))
        self.subpixel = bool(c.subpixel)
        self.min_extent_px = float(c.min_extent_px)
        self.max_ellipse_px = float(c.max_ellipse_px)
        self.keypoints_only_ellipse_px = float(c.keypoints_only_ellipse_px)
        self.ridge_ends = bool(c.ridge_ends)
        # None: RETRY_HUES_DEG; empty: a cold frame is searched as it is only
        self.retry_hues = tuple(float(h) % 360.0 for h in (RETRY_HUES_DEG if c.retry_hues is None else c.retry_hues))
        self._track: dict[str, tuple] = {}
        self._hue: dict[str, float] = {}    # the hue turn each tracked camera's needle was found at
        self._retry_wait: dict[str, int] = {}   # cold frames each camera searches unturned (_retry)
        self._avoid: dict[str, list] = {}       # camera -> [rejected box (x0, y0, x1, y1), frames left]
        self.last_mode = ""
        self.last_turn = 0.0    # the hue turn (deg) the last detection was found at; 0: as it is
        self.end_coef = load_end_coefficients(self.weights)
        self.familiarity = load_familiarity(self.weights) if familiarity else None
        size = self.cfg.descriptor_size
        if self.familiarity is not None and self.familiarity.mean.size != size:
            raise FamiliarityFileError(f"{familiarity_path(self.weights)}: a reference of {self.familiarity.mean.size} "
                                       f"features, these weights' descriptor has {size}: refit it with "
                                       f"`needletrack bench familiarity --fit`")
        self.last_evidence: EndEvidence | None = None
        self.last_descriptor: np.ndarray | None = None   # the last detection's (CropNet.forward_features)

    def reset(self, camera: str | None = None) -> None:
        """Forget the tracking box (of one camera, or all; all: also when the hues were last turned
        in vain, ``RETRY_EVERY``)."""
        if camera is None:
            self._track.clear()
            self._hue.clear()
            self._retry_wait.clear()
            self._avoid.clear()
        else:
            self._track.pop(camera, None)
            self._hue.pop(camera, None)

    def reject(self, camera: str, bbox=None) -> None:
        """Camera ``camera``'s tracked crop is a wrong lock (the other camera and the track
        disagree with it): dropped, and for ``AVOID_FRAMES`` frames its cold searches try the
        proposals away from ``bbox`` ([x0, y0, x1, y1] px, the rejected detection's; None:
        anywhere) first."""
        self.reset(camera)
        if bbox is not None:
            b = np.asarray(bbox, float).reshape(-1)
            if b.shape == (4,) and np.isfinite(b).all():
                self._avoid[camera] = [b, AVOID_FRAMES]

    def _avoided(self, camera: str):
        """The box this camera's cold searches avoid this frame (None: none); counts the frame."""
        a = self._avoid.get(camera)
        if a is None:
            return None
        a[1] -= 1
        if a[1] <= 0:
            del self._avoid[camera]
        return a[0]

    # ------------------------------------------------------------ stages
    def _tensor(self, arr: np.ndarray) -> torch.Tensor:
        t = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1)[None]
        return t.to(self.device).contiguous(memory_format=torch.channels_last)

    @torch.inference_mode()
    def _stage1(self, img: np.ndarray, hue_deg: float = 0.0):
        """Stage 1's proposals on the image, its hues turned by ``hue_deg`` first."""
        h, w = img.shape[:2]
        ws, hs, ds, box_scale = global_size(self.cfg, w, h)
        small = cv2.resize(img, (ws, hs), interpolation=cv2.INTER_AREA)
        if hue_deg:
            small = turn_hue(small, hue_deg)
        out = self._glob(self._tensor(global_input(small)))
        return decode_global_topk(out.float().cpu(), ds, self.proposals, self.proposal_threshold,
                                  box_scale=box_scale)

    @torch.inference_mode()
    def _stage2(self, img: np.ndarray, box, ridge: bool = False, hue_deg: float = 0.0):
        """Stage 2 on the crop of ``box`` (its hues turned by ``hue_deg``): keypoints in the image,
        scores, presence, the ridge, the heatmaps and the crop's descriptor."""
        cx, cy, bw, bh = box
        M = crop_affine(cx, cy, crop_side(self.cfg, bw, bh), self.cfg.crop)
        crop = cv2.warpAffine(img, M, (self.cfg.crop, self.cfg.crop), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
        if hue_deg:
            crop = turn_hue(crop, hue_deg)
        heat, pres, feat = self._crop(self._tensor(crop))
        heat = heat.float().cpu()
        uv, score = decode_heatmaps(heat[:, :5], self.cfg.out_stride)
        uv_crop = uv[0].numpy().astype(np.float64)
        sc = np.clip(score[0].numpy() / ideal_peak_mass(self.cfg.kp_sigma), 0.0, 1.0)
        line = heat[0, 5].numpy()
        on_arc = self._ends_from_ridge(uv_crop, sc, heat, line) if ridge else None
        Minv = invert_affine(M)
        res = {"M": M, "Minv": Minv, "uv": apply_affine(Minv, uv_crop), "uv_crop": uv_crop, "scores": sc,
               "presence": float(torch.sigmoid(pres[0])), "line": line, "heat": heat,
               "feat": feat[0].float().cpu().numpy(), "hue": hue_deg}
        if on_arc is not None:
            res["on_arc"], res["ends_from_ridge"] = on_arc, True
        if self.cfg.visibility:
            res["visibility"] = torch.sigmoid(visibility_logits(heat))[0].numpy().astype(np.float64)
        return res

    def _retry(self, img: np.ndarray, camera: str, best, avoid=None):
        """A cold frame that ``best`` (``_search``'s, or None) did not find searched with its hues
        turned (``retry_hues``): the turned result with the highest presence if it reaches
        ``RETRY_PRESENCE``, else ``best``. After a frame where the turns found nothing either, the
        camera's next ``RETRY_EVERY - 1`` cold frames that nothing passes as they are are not
        turned (a needle out of view)."""
        wait = self._retry_wait.get(camera, 0)
        if wait > 0:
            self._retry_wait[camera] = wait - 1
            return best
        turned = None
        for hue in self.retry_hues:
            r = self._search(img, hue, first=False, avoid=avoid)
            if r is not None and r[0]["presence"] >= max(self.threshold, RETRY_PRESENCE) \
                    and (turned is None or r[0]["presence"] > turned[0]["presence"]):
                turned = r
        if turned is None:
            self._retry_wait[camera] = RETRY_EVERY - 1
        return best if turned is None else turned

    def _search(self, img: np.ndarray, hue_deg: float, first: bool, avoid=None):
        """Stage 2 on each of stage 1's proposals, the image's hues turned by ``hue_deg``: (the
        result with the highest presence, its proposal's confidence), or None without a proposal.
        ``first``: stop at the first proposal whose presence passes the threshold. ``avoid``
        (a rejected box [x0, y0, x1, y1], ``reject``): proposals centred in it are tried last,
        and a result centred in it is taken only when none away from it passes."""
        best, best_key = None, None
        props = self._stage1(img, hue_deg)
        if avoid is not None:
            props = sorted(props, key=lambda p: _centred_in(p[1], p[2], avoid))    # stable
        for c1, cx, cy, bw, bh in props:
            r = self._stage2(img, (cx, cy, bw, bh), self.ridge_ends, hue_deg)
            if self.refine and r["presence"] >= self.proposal_threshold:
                r = self._stage2(img, self._box_of(r), self.ridge_ends, hue_deg)
            passes = r["presence"] >= self.threshold
            if avoid is not None and passes:
                passes = not _centred_in(*self._box_of(r)[:2], avoid)
            key = (passes, r["presence"])
            if best is None or key > best_key:
                best, best_key = (r, c1), key
            if first and passes:
                break
        return best

    def _ends_from_ridge(self, uv_crop, sc, heat, line):
        """A and E moved (in place) to the centreline ridge's ends when the heatmaps put both on
        one end (``common.detector.ridge_ends``), and B..D onto the arc through them and the
        ridge, scored as the weaker end; returns the ``on_arc`` flags then (all False when no arc
        fits), else None."""
        s = self.cfg.out_stride
        cells = (uv_crop - (s - 1) / 2.0) / s
        found = ends_on_ridge(heat[0, :5].numpy(), line, cells[0], cells[4], ideal_peak_mass(self.cfg.kp_sigma),
                              ARC_MIN_SCORE)
        if found is None:
            return None
        a, e, sc[0], sc[4] = found
        uv_crop[0], uv_crop[4] = a * s + (s - 1) / 2.0, e * s + (s - 1) / 2.0
        fit = fit_arc_affine(a, e, line)
        if fit is None:
            return np.zeros(5, bool)
        own = sc[1:4].copy()
        uv_crop[1:4] = arc_at(fit, ARC_ANGLES_DEG[1:4]) * s + (s - 1) / 2.0
        sc[1:4] = unseen_on_arc_scores(np.full(3, min(sc[0], sc[4])), own, line, (uv_crop[1:4] - (s - 1) / 2.0) / s)
        return np.array([False, True, True, True, False])

    def _place_bcd(self, res) -> None:
        """B, C, D of the chosen crop on the arc through A and E (see fit_arc_affine), when A and
        E are sure (an occluded end is a guess, and the arc pinned on it would drag B..D along).
        Done once per frame, on the final crop only: the fit costs more than the heatmaps."""
        sc, uv_crop, heat = res["scores"], res["uv_crop"], res["heat"]
        if not self.arc_bcd or min(sc[0], sc[4]) < ARC_MIN_SCORE:
            return
        st = self.cfg.out_stride
        cells = (uv_crop - (st - 1) / 2.0) / st
        fit = fit_arc_affine(cells[0], cells[4], res["line"])
        if fit is None:
            return
        t = np.asarray(ARC_ANGLES_DEG[1:4], float)
        if self.along_arc:
            m = heat.shape[-1]
            prob = torch.softmax(heat[0, 1:4].reshape(3, -1), -1).reshape(3, m, m).numpy()
            t = np.array([refine_along_arc(prob[i], fit, t[i]) for i in range(3)])
        own = sc[1:4].copy()
        uv_crop[1:4] = arc_at(fit, t) * st + (st - 1) / 2.0
        # B..D now rest on A, E and the ridge, not on their own (along-arc diffuse) heatmaps;
        # one over a stretch with no ridge (hidden) keeps its own, lower score
        sc[1:4] = unseen_on_arc_scores(np.full(3, min(sc[0], sc[4])), own, res["line"],
                                       (uv_crop[1:4] - (st - 1) / 2.0) / st)
        res["on_arc"] = np.array([False, True, True, True, False])
        res["uv"] = apply_affine(res["Minv"], uv_crop)

    def _box_of(self, res) -> tuple:
        pts = res["uv"]
        if res.get("centreline") is not None:
            cl, cw = res["centreline"], res["centreline_w"]
            pts = np.vstack([pts, cl[cw > 0]])
        lo, hi = pts.min(0), pts.max(0)
        return ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[0] - lo[0] + 4, hi[1] - lo[1] + 4)

    def _finish(self, res, img: np.ndarray) -> None:
        """The centreline: decoded from the crop's ridge, then (``subpixel``) moved onto the wire's
        centre in the full-resolution image (``common.detector.centreline_subpixel``)."""
        res["centreline"], res["centreline_w"], res["centreline_sigma"] = None, None, None
        if not self.centreline:
            return
        s = self.cfg.out_stride
        kp_cells = (res["uv_crop"] - (s - 1) / 2.0) / s
        pts_cells, w = decode_centreline(res["line"], kp_cells)
        res["centreline"] = apply_affine(res["Minv"], pts_cells * s + (s - 1) / 2.0)
        res["centreline_w"] = w
        if self.subpixel:
            res["centreline"], res["centreline_w"] = refine_centreline(img, res["centreline"], w)
            res["centreline_sigma"] = CENTRELINE_SIGMA_PX

    def _end_evidence(self, res, img: np.ndarray) -> EndEvidence:
        """Which end is the tip, from the wire's taper in the image and the network's heatmaps."""
        s = self.cfg.out_stride
        cells = (res["uv_crop"] - (s - 1) / 2.0) / s
        net = network_evidence(res["heat"][0, :5].numpy(), cells)
        length = polyline_length(res["uv"])
        far = self.unfamiliarity(res)
        if res.get("centreline") is None:
            return EndEvidence(float("nan"), net, length_px=length, unfamiliarity=far)
        shape, r_a, r_e = shape_evidence(img, res["centreline"])
        return EndEvidence(shape, net, r_a, r_e, length, far)

    def unfamiliarity(self, res) -> float:
        """How unlike the training looks the crop is (``common.detector.familiarity``; about 1
        when familiar); NaN without a familiarity file beside the weights."""
        if self.familiarity is None:
            return float("nan")
        return self.familiarity.unfamiliarity(res["feat"])

    def _p_a_is_tip(self, res) -> float | None:
        """The stated probability that A is the tip: None without coefficients; 0.5 (the image
        cannot tell) when A and E were taken from the ridge's ends, after the heatmaps had put
        both on one end (their naming and the weak taper cue are then all there is)."""
        if self.end_coef is None:
            return None
        if res.get("ends_from_ridge"):
            return 0.5
        return self.last_evidence.p_a_is_tip(self.end_coef)

    def _ellipse_check(self, res, undistort=None) -> tuple[str | None, bool]:
        """(Why the sub-pixel centreline is not the image of a circle, or None; whether only the
        keypoints may be stated). None, False: within ``max_ellipse_px``, or it cannot be judged
        (no sub-pixel centreline, fewer than MIN_ELLIPSE_POINTS stations). None, True: within
        ``keypoints_only_ellipse_px`` only. ``undistort`` (observed pixels -> ideal pinhole
        pixels) first takes out the lens distortion, under which a circle's image is no ellipse."""
        if not (self.max_ellipse_px > 0 and res.get("centreline_sigma") is not None):
            return None, False
        pts = res["centreline"][res["centreline_w"] > 0]
        pts = pts[np.isfinite(pts).all(axis=1)]
        if undistort is not None and len(pts):
            pts = undistort(pts)
        if len(pts) < MIN_ELLIPSE_POINTS:
            return None, False
        med, share = ellipse_residual(pts)
        if share >= MIN_ELLIPSE_SHARE and med <= max(self.max_ellipse_px, self.keypoints_only_ellipse_px):
            return None, med > self.max_ellipse_px
        return (f"centreline is not an ellipse arc (median {med:.2f} px from its best ellipse over "
                f"{share:.0%} of it; max_ellipse_px {self.max_ellipse_px:g}, keypoints only up to "
                f"{self.keypoints_only_ellipse_px:g})"), False

    # ------------------------------------------------------------ public
    @torch.inference_mode()
    def detect(self, image, camera: str = "left", seq: int = 0, stamp_ns: int = 0,
               undistort=None) -> Keypoints:
        """Keypoints of one BGR image (h, w, 3) uint8, in the image's own (distorted) pixels;
        "no needle" with a reason when the image is unusable or the confidence is below the
        threshold. ``undistort`` (pixels -> ideal pinhole pixels, for a camera with distortion)
        is used where the detector's checks assume a pinhole (the ellipse test)."""
        self.last_turn = 0.0
        problem = image_problem(image)
        if problem:
            self.reset(camera)
            log.warning("camera %s seq %d: bad image: %s", camera, seq, problem)
            return Keypoints.not_found(camera, seq, stamp_ns, self.name, f"bad image: {problem}")
        img = as_bgr(image)
        res, conf = None, 0.0
        box = self._track.get(camera) if self.tracking else None
        if box is not None:
            res = self._stage2(img, box, hue_deg=self._hue.get(camera, 0.0))
            self.last_mode = "tracking"
            conf = res["presence"]
            # a needle that moved in the image is cut by the old crop and its keypoints go wrong
            # (the crop still shows enough needle to score high): then find it anew, cold
            if conf < self.threshold or _moved(box, self._box_of({"uv": res["uv"]})):
                res = None
        if res is None:
            self.last_mode = "cold"
            # stage 1 proposes (Keypoint R-CNN's RPN role, a low threshold); stage 2's presence
            # on the re-centred crop decides, against the detection threshold
            avoid = self._avoided(camera)
            best = self._search(img, 0.0, first=True, avoid=avoid)
            if best is None or best[0]["presence"] < self.threshold:
                best = self._retry(img, camera, best, avoid)
            if best is None:
                self.reset(camera)
                return Keypoints.not_found(camera, seq, stamp_ns, self.name,
                                           f"no needle: no proposal >= {self.proposal_threshold:.2f}")
            res, c1 = best
            conf = res["presence"]
            if conf < self.threshold:
                self.reset(camera)
                return Keypoints.not_found(camera, seq, stamp_ns, self.name,
                                           f"no needle: confidence {conf:.2f} < {self.threshold:.2f} "
                                           f"(proposal {c1:.2f})", conf)
        self._place_bcd(res)
        extent = float(np.linalg.norm(res["uv"][:, None] - res["uv"][None], axis=2).max())
        if not extent >= self.min_extent_px:
            # a needle within ~40 cm spans >= 10 px in any view: the points collapsed on one spot
            self.reset(camera)
            return Keypoints.not_found(camera, seq, stamp_ns, self.name,
                                       f"no needle: keypoints collapsed ({extent:.1f} px apart "
                                       f"< min_extent_px {self.min_extent_px:g})", conf)
        self._finish(res, img)
        not_ellipse, keypoints_only = self._ellipse_check(res, undistort)
        if not_ellipse:
            self.reset(camera)
            return Keypoints.not_found(camera, seq, stamp_ns, self.name, f"no needle: {not_ellipse}", conf)
        # an end where something covers the wire is a cut, not the needle's end (cut_ends)
        res["scores"] = cut_end_scores(img, res["uv"], res["scores"], res["centreline"], res.get("on_arc"))
        self.last_evidence = self._end_evidence(res, img)
        res["scores"] = blunt_tip_scores(res["scores"], self.last_evidence.r_a)
        visibility = res.get("visibility")
        if visibility is not None:   # a point the network sees hidden is never stated sure
            res["scores"] = np.minimum(res["scores"], visibility)
        self.last_descriptor = res["feat"]
        cx, cy, bw, bh = self._box_of(res)
        if keypoints_only:
            self.reset(camera)
            res["centreline"] = res["centreline_w"] = res["centreline_sigma"] = None
        else:
            self._track[camera] = self._box_of({"uv": res["uv"]})   # as _moved compares it
            self._hue[camera] = res["hue"]
        self.last_turn = res["hue"]
        far = self.last_evidence.unfamiliarity
        return Keypoints(camera, seq, stamp_ns, True, res["uv"].astype(np.float64),
                         res["scores"].astype(np.float64), float(conf),
                         bbox=np.array([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2]), detector=self.name,
                         centreline=res["centreline"], centreline_w=res["centreline_w"],
                         centreline_sigma_px=res["centreline_sigma"], on_arc=res.get("on_arc"),
                         centreline_corr_points=None if res["centreline_sigma"] is None else CENTRELINE_CORR_POINTS,
                         keypoint_sigma_px=KEYPOINT_SIGMA_PX, end_identity=self._p_a_is_tip(res),
                         unfamiliarity=far if np.isfinite(far) else None, visibility=visibility)

    def detect_message(self, msg: CameraImage) -> Keypoints:
        """Keypoints of a ``CameraImage``; corrupt or inconsistent image data -> "no needle"."""
        try:
            img = msg.to_bgr()
        except (MessageError, ValueError) as exc:
            self.reset(msg.camera)
            log.warning("camera %s seq %d: %s", msg.camera, msg.seq, exc)
            return Keypoints.not_found(msg.camera, msg.seq, msg.stamp_ns, self.name, f"bad image: {exc}")
        return self.detect(img, msg.camera, msg.seq, msg.stamp_ns)
