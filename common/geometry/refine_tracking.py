"""Frame-to-frame dense refinement: in a video, start each frame from the last frame's solutions.

A cold frame starts ``DenseRefiner.refine`` from every minimum of the keypoint-only stereo PnP
(``common.geometry.pnp.refine_starts``, about half of a cold frame's time). In a video the needle moves
little from one frame to the next, so the previous frame's distinct solutions (the best and its
competitors, each with its mirror image as always) are starts as good as the PnP's and cost
nothing; carrying the competitors along keeps an ambiguous view ambiguous.

A warm fit is tried only when the previous pose still reprojects the keypoints within
``max_start_px`` (a jump, e.g. a new scene, goes cold at once instead of through a long,
failing fit), and kept only when it fits as well as the cold fit it descends from (RMS at most
``max_rms_growth`` times the cold one plus ``rms_slack_px``). Otherwise, after a gap of more
than ``max_gap_s``, after a frame without a pose, and every ``cold_every`` frames (which lets
the PnP bring in solutions the track lacks), the frame is refined cold. A wrong warm start
therefore costs at most one extra refinement, never a wrong pose: the needle jumping or the
detector swapping tip and tail raise the residual and send the frame down the cold path.

A cold frame with fewer than 4 sure keypoints in both cameras (a needle mostly hidden, e.g. in
an instrument's jaws) cannot start the PnP. With ``unsure_starts`` it starts from every keypoint
the detector gave, both ways round (``common.geometry.pnp.unsure_starts``), and the fit, on the sure
keypoints and the centreline alone, is kept only when it is unambiguous and within
``unsure_max_rms_px``: else ``NoPose("unsure_keypoints")``. Such a fit has no sure tip or tail to
tell the arc's ends apart, and nothing else to check it by. In a video such frames are tracked
warm as the others (a cold one costs two to three times a sure frame's), under the same test:
the previous solutions and their end-for-end turns (``common.geometry.refine.tip_for_tail``) are the
starts, with their mirrors, so that the turn competes as it does in a cold fit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Optional

import numpy as np

from common.geometry.observations import NoPose, usable_mask
from common.geometry.pnp import MIN_POINTS, refine_starts, unsure_starts
from common.geometry.refine import (
    ArcObservation,
    DenseRefiner,
    RefineResult,
    tip_for_tail,
)
from common.geometry.transforms import transform_points


@dataclass(frozen=True)
class TrackingConfig:
    """How a frame starts: from the previous one, when that may be (times in s, residuals in
    px), or cold, with or without 4 sure keypoints (module docstring)."""

    enabled: bool = True
    max_gap_s: float = 0.2          # the previous pose is at most this old
    cold_every: int = 30            # and at most this many warm frames in a row
    max_start_px: float = 15.0      # the previous pose reprojects the keypoints within this (RMS)
    max_rms_growth: float = 1.5     # a warm fit's RMS may exceed the last cold one's by this factor ...
    rms_slack_px: float = 0.5       # ... plus this much
    # a warm frame refines the previous pose alone, without its mirror image and the other
    # solutions, when the previous frame's best competitor cost this many residual variances
    # more (or no competitor was found): a minimum that far off does not come within the
    # ambiguity margin in one frame (every cold_every frames all are searched again)
    mirror_chi2: float = 100.0
    unsure_starts: bool = True      # fewer than 4 sure keypoints: start from all, both ways round
    unsure_max_rms_px: float = 2.0  # ... and keep an unambiguous fit within this RMS (2x the
                                    # learned detector's stated keypoint noise)

    def __post_init__(self):
        if not (self.max_gap_s > 0 and self.cold_every >= 1 and self.max_start_px > 0
                and self.max_rms_growth >= 1 and self.rms_slack_px >= 0 and self.mirror_chi2 >= 0
                and self.unsure_max_rms_px > 0):
            raise ValueError(f"TrackingConfig: max_gap_s > 0, cold_every >= 1, max_start_px > 0, "
                             f"max_rms_growth >= 1, rms_slack_px >= 0, mirror_chi2 >= 0 and "
                             f"unsure_max_rms_px > 0 required, got {self}")


class TrackingRefiner:
    """``refine`` per stereo frame, warm from the previous frame's pose when that is safe.

    ``refine`` raises what ``refine_starts`` / ``unsure_starts`` (``NoPose``) and
    ``DenseRefiner.refine`` (``RefineError``) raise on a cold frame, and
    ``NoPose("unsure_keypoints")`` when a frame without 4 sure keypoints gives no sure fit;
    ``last_warm`` says how the last pose was obtained.
    """

    def __init__(self, refiner: DenseRefiner, model_points, min_score: float = 0.5,
                 outlier_px: Optional[float] = 10.0, config: TrackingConfig | None = None):
        self.refiner, self.model_points = refiner, np.asarray(model_points, float)
        self.min_score, self.outlier_px = min_score, outlier_px
        self.config = config or TrackingConfig()
        self.last_warm = False
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame: the next one is refined cold."""
        self._prev: Optional[RefineResult] = None
        self._prev_stamp_ns = 0
        self._cold_rms = np.inf
        self._warm_run = 0

    def refine(self, uv: Mapping[str, np.ndarray], scores: Mapping[str, np.ndarray],
               observations: Mapping[str, ArcObservation], stamp_ns: int,
               support_normal: Optional[np.ndarray] = None,
               expected: Optional[np.ndarray] = None) -> RefineResult:
        """The refined pose of one stereo frame (keypoints ``uv``/``scores`` per camera for the
        PnP starts, ``observations`` for the fit) taken at ``stamp_ns`` (ns); ``support_normal``
        and ``expected`` as in ``DenseRefiner.refine``."""
        cfg = self.config
        res = None
        if (cfg.enabled and self._prev is not None and self._warm_run < cfg.cold_every
                and 0 <= stamp_ns - self._prev_stamp_ns <= cfg.max_gap_s * 1e9
                and self._reprojects(uv, scores, self._prev.T_ecm_needle)):
            prev = self._prev
            unsure = self._unsure(uv, scores)
            near = prev.ambiguous or prev.competitor_chi2 < cfg.mirror_chi2
            try:
                if unsure:    # the cold path's competitors: mirrors and the end-for-end turns
                    starts = [T for T, _ in prev.candidates]
                    starts += [tip_for_tail(T, self.refiner.needle) for T in starts]
                    res = self.refiner.refine(observations, starts, support_normal=support_normal, expected=expected)
                elif near:
                    res = self.refiner.refine(observations, [T for T, _ in prev.candidates],
                                              support_normal=support_normal, expected=expected)
                else:   # cheaper than the candidates and mirrors (needletrack bench refine times both)
                    res = self.refiner.refine(observations, [prev.T_ecm_needle], mirrors=False,
                                              support_normal=support_normal, expected=expected)
            except ValueError:
                res = None
            if res is not None and not res.rms_px <= cfg.max_rms_growth * self._cold_rms + cfg.rms_slack_px:
                res = None
            if res is not None and unsure and not (cfg.unsure_starts and self._sure_enough(res)):
                res = None
        self.last_warm = res is not None
        if res is None:
            self._prev = None                      # a cold frame that raises leaves no start behind
            res = self._cold(uv, scores, observations, support_normal, expected)
            self._cold_rms, self._warm_run = res.rms_px, 0
        else:
            self._warm_run += 1
        self._prev, self._prev_stamp_ns = res, stamp_ns
        return res

    def track(self, stamp_ns: int) -> Optional[np.ndarray]:
        """The previous frame's pose when a frame taken at ``stamp_ns`` may follow it (within
        ``max_gap_s``, tracking on), else None."""
        cfg = self.config
        if cfg.enabled and self._prev is not None and 0 <= stamp_ns - self._prev_stamp_ns <= cfg.max_gap_s * 1e9:
            return self._prev.T_ecm_needle
        return None

    def reprojects(self, uv, scores, T_ecm_needle) -> bool:
        """Whether ``T_ecm_needle`` reprojects the usable keypoints within ``max_start_px``."""
        return self._reprojects(uv, scores, T_ecm_needle)

    def _cold(self, uv, scores, observations, support_normal, expected=None) -> RefineResult:
        """A frame refined from the PnP's minima, or from unsure keypoints (module docstring)."""
        rig, cfg = self.refiner.rig, self.config
        try:
            starts = refine_starts(uv, rig, self.model_points, scores, self.min_score, self.outlier_px)
        except NoPose as exc:
            if not (cfg.unsure_starts and exc.reason == "too_few_points"):
                raise
            starts = unsure_starts(uv, rig, self.model_points, scores, outlier_px=self.outlier_px)
            res = self.refiner.refine(observations, starts, support_normal=support_normal, expected=expected)
            if not self._sure_enough(res):
                why = (", ".join(res.reasons) if res.ambiguous
                       else f"RMS {res.rms_px:.2f} px > unsure_max_rms_px {cfg.unsure_max_rms_px:g}")
                raise NoPose("unsure_keypoints", f"fewer than {MIN_POINTS} sure keypoints and the fit "
                             f"without them is not sure ({why})") from None
            return res
        return self.refiner.refine(observations, starts, support_normal=support_normal, expected=expected)

    def _sure_enough(self, res: RefineResult) -> bool:
        """Whether a fit without 4 sure keypoints may stand: unambiguous, within the RMS bound."""
        return not res.ambiguous and res.rms_px <= self.config.unsure_max_rms_px

    def _unsure(self, uv, scores) -> bool:
        """Whether no camera has the 4 sure keypoints the PnP needs."""
        try:
            return all(int(usable_mask(p, None if scores is None else scores.get(n), self.min_score).sum())
                       < MIN_POINTS for n, p in uv.items() if p is not None)
        except ValueError:
            return True

    def _reprojects(self, uv, scores, T_ecm_needle) -> bool:
        """Whether the pose reprojects the usable keypoints within ``max_start_px`` (RMS weighted
        by the scores, as the PnP's; computed here directly: a ``ReprojectionProblem`` would
        cost a tenth of a warm frame)."""
        sq, w_sum, n = 0.0, 0.0, 0
        for name, pts in uv.items():
            if pts is None:
                continue
            s = None if scores is None else scores.get(name)
            if np.shape(pts) != self.model_points[:, :2].shape:
                return False
            try:
                ok = usable_mask(pts, s, self.min_score)
            except ValueError:
                return False
            if not ok.any():
                continue
            cam = self.refiner.rig[name]
            p = transform_points(cam.T_cam_ecm @ T_ecm_needle, self.model_points[ok])
            if p[:, 2].min() <= 1e-9:
                return False
            d = cam.project(p) - np.asarray(pts, float)[ok]
            w = np.ones(len(d)) if s is None else np.asarray(s, float)[ok]
            sq, w_sum, n = sq + float(w @ (d * d).sum(axis=1)), w_sum + float(w.sum()), n + len(d)
        # any sure keypoint will do: a mostly hidden needle (module docstring) keeps one or two
        return n >= 1 and w_sum > 0 and math.sqrt(sq / w_sum) <= self.config.max_start_px
