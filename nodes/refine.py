"""Dense refinement node: the needle pose fitted to its whole visible arc in both cameras, with
an uncertainty (common/geometry/refine.py).

Inputs, outputs and params: ``needletrack describe refine`` (docs/nodes.md). The keypoints'
``centreline`` is the dense observation; with ``ecm`` a stereo pair waits (at most ``max_wait``
frames) for its frame's ECM pose before it is refined (``StereoPoseNode.SOLVE_WITH_ECM``), and its
pose gets ``T_world_needle``. ``pose``: method ``refined``, ``residual``
the RMS (px) over the keypoints and centreline points used, ``covariance`` over [rotation vector
(rad), translation (m)] in the ECM frame, ``ambiguous`` when competing solutions fit nearly as
well or the arc is seen edge-on (the covariance then spans them), ``arc_seen`` the share of the
arc the pose was fitted to (``common.geometry.arc_support``): below ``min_arc_seen`` the pose is
a partial view (the jaws or the tissue hide the rest), flagged ``ambiguous`` and its covariance
widened (counted ``partial_view``), and states its tip at most ``end_unseen_p_max`` sure
(counted ``end_identity.partial_view``), as does one fitted to an arc with an end no camera saw
(counted ``end_identity.end_unseen``; docs/tracking.md#partial-views); one whose keypoints some camera reads end for end (the fit
rested on a stray keypoint, ``end_identity.camera_readings``) states at most the larger of
``reading_p_max`` and what the cameras' statements, each about the end at its A, give its tip
(counted ``end_identity.reading_turned``).

Per frame: the minima of the joint stereo PnP on the keypoints, from the IPPE starts and
stopped early (``common.geometry.pnp.refine_starts``), are the starting poses; ``DenseRefiner.refine``
fits them, and their mirror images, to keypoints and centrelines of both cameras together and
keeps the best. In tracking mode (``common.geometry.refine_tracking``) a frame that follows a
well-fitted one within ``max_gap_s`` starts from that pose instead and keeps the result only if
it is as good, else it is refined cold (counted ``warm`` and ``cold``). A camera whose detector
found nothing is left out. Frames without any centreline are refined on the keypoints alone
(counted ``keypoints_only``). A frame with fewer than 4 sure keypoints (a needle mostly hidden)
starts from all its keypoints, both ways round, and is posed only when that fit is unambiguous
and within ``unsure_max_rms_px`` (``common.geometry.refine_tracking``).

Params: the node's own (``max_rms_px``, ``max_residual_variance``: a fit whose residuals are
larger than that many times the stated noise's variance is not posed, counted
``no_pose.poor_fit``: e.g. a needle's tail in an instrument's jaws, the centreline running along
the jaw; ``outlier_px``: the joint PnP's outlier rejection), every ``RefineConfig`` field
(``sigma_kp_px``, ``sigma_curve_px``: for detectors that state no noise, a stated
``keypoint_sigma_px`` / ``centreline_sigma_px`` is used instead) and every ``TrackingConfig``
field. ``support_normal_world`` (the normal, world frame, of a surface the needle may rest on,
e.g. ``[0, 0, 1]`` for the simulator's phantom) lets ``common.geometry.rest_prior`` pick between
minima the images leave nearly equal; it needs the ``ecm`` input (a frame whose ECM pose is not
in yet uses the newest one). A frame that gives no pose is counted as ``no_pose.<reason>`` (the
PnP's reasons, or the refinement's: ``too_few_points``, ``no_valid_candidate``,
``bad_centreline``, ``bad_keypoints``, ``high_residual``, ``poor_fit``, ``unsure_keypoints``), and
said on ``no_pose`` (``NoPoseNotice``, method ``refined``, that reason) at once: the tracker
steps such a frame without waiting for a later pose.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.frames import CAMERAS
from common.geometry.arc_support import SUPPORT_PX, arc_support, best_seen, ends_seen, partial_view, shares
from common.constraints import Probability, number_at_least
from common.geometry.end_identity import camera_readings, pose_tip_probability, settle
from common.geometry.needle import NeedleModel
from common.geometry.observations import NoPose
from common.geometry.refine import (
    ArcObservation,
    DenseRefiner,
    RefineConfig,
    RefineError,
    near_expected,
)
from common.geometry.refine_tracking import TrackingConfig, TrackingRefiner
from common.geometry.transforms import inv_T
from common.runtime.messages import Calibration, EcmPose, Keypoints
from common.runtime.node import NodeError, run
from common.runtime.params import config_from, merge_schemas
from nodes._pose import StereoPoseNode, stated_end_identity, stereo_news, turn_keypoints


@dataclass
class _NodeParams(StereoPoseNode.Params):
    max_rms_px: float | None = 20.0       # larger refined RMS gives no pose; null: no gate
    # a fit whose residuals are this many times the stated noise's variance (RefineResult.
    # residual_variance; 0.1-0.5 on well-seen needles) gives no pose; null: no gate
    max_residual_variance: float | None = 1.5
    outlier_px: float | None = 10.0
    support_normal_world: list[float] | None = None
    tracking: bool = True                 # TrackingConfig.enabled
    # a pose fitted to less of the arc than this (arc_seen, its better-seen camera) is a partial
    # view: flagged ambiguous (counted partial_view), its covariance times partial_view_inflation
    min_arc_seen: Probability = 0.6
    partial_view_inflation: number_at_least(1.0) = 4.0
    # a pose fitted to an arc one of whose ends no camera saw states its tip at most this sure
    # (counted end_identity.end_unseen): its tip was read from one end and a cut (jaws, tissue);
    # so does a partial view (counted end_identity.partial_view): it can be tens of degrees off
    end_unseen_p_max: Probability = 0.9
    # a pose whose keypoints some camera reads end for end states its tip at most this sure
    # (counted end_identity.reading_turned): the stated probability was the keypoints', not its
    reading_p_max: Probability = 0.5


class RefineNode(StereoPoseNode):
    """Keypoints + centrelines of a stereo frame -> refined T_ecm_needle with covariance."""

    INPUTS = {"left": Keypoints, "right": Keypoints, "calib": Calibration, "ecm": EcmPose}
    OUTPUTS = ("pose", "no_pose")
    KEEP_ALL = StereoPoseNode.KEEP_ALL
    pose_method = "refined"
    SOLVE_WITH_ECM = True     # the resting prior's normal and the needle's last world pose

    # every RefineConfig and TrackingConfig field is a param of the same name (``tracking`` for
    # TrackingConfig.enabled), beside the node's own
    Params = merge_schemas("RefineParams", RefineConfig, TrackingConfig, _NodeParams, drop=("enabled",))

    def setup(self):
        super().setup()
        try:
            self.config = config_from(RefineConfig, self.p)
            self.tracking = config_from(TrackingConfig, self.p, {"enabled": "tracking"})
            self.support_normal_world = support_normal(self.p.support_normal_world)
        except ValueError as exc:
            raise NodeError(str(exc)) from None
        self.min_score = self.config.min_score
        self.max_rms_px = self.p.max_rms_px
        self.outlier_px = self.p.outlier_px
        self.tracker: TrackingRefiner | None = None
        self._track: tuple[float, float] | None = None   # the tracked needle's end identity (track_identity)
        self._T_world_needle: np.ndarray | None = None    # the tracked needle's last pose in world
        self._T_world_needle_before: np.ndarray | None = None   # ... the one before it
        self._last_flagged = True                                 # whether the last pose was flagged

    def on_calib(self, msg: Calibration):
        changed = self.calib is None or msg.cameras != self.calib.cameras or msg.needle != self.calib.needle
        super().on_calib(msg)
        if changed or self.tracker is None:
            self.needle = NeedleModel.from_dict(msg.needle)
            self.tracker = TrackingRefiner(DenseRefiner(self.rig, self.needle, self.config),
                                           self.model_points, self.min_score, self.outlier_px, self.tracking)

    def on_stream_reset(self):
        super().on_stream_reset()
        if self.tracker is not None:
            self.tracker.reset()          # the last pose is of the old stream
        self._track = None
        self._T_world_needle = self._T_world_needle_before = None
        self._last_flagged = True

    def settle_end_identity(self, left: Keypoints, right: Keypoints) -> tuple[Keypoints, Keypoints]:
        """The frame's end identity read against the tracked needle's (``end_identity.settle``
        with tracking), its probability kept for ``publish_pose``."""
        stated = stated_end_identity(left, right)
        same = self.same_as_track(left, right) if any(p is not None for p in stated) else None
        settled = settle(*stated, tracking=True, track=self._track, same_as_track=same,
                         news=stereo_news(left, right))
        self._track = settled.track
        return self.read_as(settled, left, right)

    def same_as_track(self, left: Keypoints, right: Keypoints) -> bool | None:
        """Whether the frame reads the tracked needle as the track does (its keypoints reproject
        the tracked pose as read, not turned); None when there is no track or it cannot be told.
        The tracked pose is the needle's last world pose seen from this frame's endoscope pose
        (``expected_T_ecm_needle``: a needle at rest keeps its identity over the endoscope's
        moves, so the views of a multi-view group vote), else the last frame's pose."""
        if self.tracker is None or self._track is None:
            return None
        prev = self.expected_T_ecm_needle(left.seq)
        if prev is None:
            prev = self.tracker.track(left.stamp_ns)
        if prev is None:
            return None
        uv, sc = self.stereo_arrays(left, right)
        tuv, tsc = self.stereo_arrays(turn_keypoints(left), turn_keypoints(right))
        as_read, turned = self.tracker.reprojects(uv, sc, prev), self.tracker.reprojects(tuv, tsc, prev)
        return as_read if as_read != turned else None     # the frame relates to the track one way only

    def on_pair(self, left: Keypoints, right: Keypoints):
        uv, sc = self.stereo_arrays(left, right)
        obs = {kp.camera: ArcObservation.from_keypoints(kp) for kp in (left, right) if kp.found}
        if not any(o.centreline is not None and len(o.centreline) for o in obs.values()):
            self.count("keypoints_only")
        try:
            res = self.tracker.refine(uv, sc, obs, left.stamp_ns, self.support_normal_ecm(left.seq),
                                      expected=self.expected_T_ecm_needle(left.seq, confirmed=True))
        except NoPose as exc:
            self.no_pose(exc.reason, left, exc.detail)
            return
        except RefineError as exc:
            self.no_pose(exc.reason, left, str(exc))
            return
        self.count("warm" if self.tracker.last_warm else "cold")
        if self.max_rms_px is not None and not res.rms_px <= self.max_rms_px:
            self.tracker.reset()
            self.no_pose("high_residual", left, f"RMS {res.rms_px:.2f} px > {self.max_rms_px} px")
            return
        if self.p.max_residual_variance is not None and not res.residual_variance <= self.p.max_residual_variance:
            self.tracker.reset()
            self.no_pose("poor_fit", left, f"residual variance {res.residual_variance:.2f} > "
                                           f"{self.p.max_residual_variance} (the images are not the needle model's)")
            return
        if res.ambiguous:
            self.count("ambiguous")
        support = arc_support(self.rig, self.needle, res.T_ecm_needle, obs, SUPPORT_PX,
                              self.config.min_centreline_w, self.config.min_score)
        seen = best_seen(shares(support))
        partial, covariance = partial_view(res.covariance, seen, self.p.min_arc_seen, self.p.partial_view_inflation)
        if partial:
            self.count("partial_view")
        p = self.identity.get(left.seq)
        stated, caps = pose_tip_probability(
            p, ends_seen(support) if support else None,
            camera_readings(self.rig, self.needle, res.T_ecm_needle, uv, sc),
            dict(zip(CAMERAS, stated_end_identity(left, right))),
            end_unseen_p_max=self.p.end_unseen_p_max, reading_p_max=self.p.reading_p_max,
            partial=partial, news=stereo_news(left, right))
        for cap in caps:
            self.count(f"end_identity.{cap}")
        if stated != p:
            self.identity.put(left.seq, stated)
        pose = self.pose_message(left.seq, left.stamp_ns, self.pose_method, res.T_ecm_needle,
                                 res.rms_px, "px", covariance=covariance,
                                 ambiguous=bool(res.ambiguous or partial), arc_seen=seen,
                                 model_sigma_m=self.config.model_sigma_mm * 1e-3 or None,
                                 model_sigma_rad=math.radians(self.config.model_sigma_deg) or None)
        self._T_world_needle_before = self._T_world_needle
        self._T_world_needle = pose.T_world_needle    # None until the frame's ECM pose is known
        self.publish_pose(pose)                       # (which flags an unsure tip)
        self._last_flagged = pose.ambiguous

    def expected_T_ecm_needle(self, seq: int, confirmed: bool = False) -> np.ndarray | None:
        """Where the tracked needle is in frame ``seq``'s ECM frame if it has not moved: its last
        world pose seen from this frame's endoscope pose (None: either is unknown). ``confirmed``
        (what picks between an ambiguous frame's minima): only when the last pose was not flagged
        and the one before agrees with it within ``expected_mm`` / ``expected_deg``, so that a
        wrong pose, or two flagged ones read alike, are not carried on."""
        T_world_ecm = self.ecm_poses.get(seq)
        if self._T_world_needle is None or T_world_ecm is None:
            return None
        if confirmed:
            if self._last_flagged or self._T_world_needle_before is None:
                return None
            if not near_expected(self._T_world_needle, self._T_world_needle_before, self.config):
                return None
        return inv_T(T_world_ecm) @ self._T_world_needle

    def support_normal_ecm(self, seq: int):
        """The support surface's normal in frame ``seq``'s ECM frame (None: not configured, or
        no ECM pose yet)."""
        if self.support_normal_world is None:
            return None
        T_world_ecm = self.ecm_poses.get(seq)
        if T_world_ecm is None and self.ecm_poses:
            # the newest: the prior only weighs near-equal minima, a few frames of motion is nothing
            T_world_ecm = next(reversed(self.ecm_poses.values()))
        if T_world_ecm is None:
            self.count("no_support_prior")
            return None
        return T_world_ecm[:3, :3].T @ self.support_normal_world


def support_normal(value) -> np.ndarray | None:
    """The ``support_normal_world`` param as a unit 3-vector (None stays None)."""
    if value is None:
        return None
    try:
        n = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        n = np.zeros(0)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.linalg.norm(n) > 0:
        raise ValueError(f"refine: params.support_normal_world must be 3 finite numbers, not all zero, "
                         f"got {value!r}")
    return n / np.linalg.norm(n)


NODE = RefineNode
if __name__ == "__main__":
    run(NODE)
