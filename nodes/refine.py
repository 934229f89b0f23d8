"""Dense refinement node: the needle pose fitted to its whole visible arc in both cameras, with
an uncertainty (common/geometry/refine.py); its frame step, gates and end-identity caps are
``common.pose.refine_step.RefineStep``.

Inputs, outputs and params: ``needletrack describe refine`` (docs/nodes.md). The keypoints'
``centreline`` is the dense observation; with ``ecm`` a stereo pair waits (at most ``max_wait``
frames) for its frame's ECM pose before it is refined, and its pose gets ``T_world_needle``.
``pose``: method ``refined``, ``residual`` the RMS (px) over the keypoints and centreline points
used, ``covariance`` over [rotation vector (rad), translation (m)] in the ECM frame,
``ambiguous`` when competing solutions fit nearly as well or the arc is seen edge-on (the
covariance then spans them), ``arc_seen`` the share of the arc the pose was fitted to
(``common.geometry.arc_support``): below ``min_arc_seen`` the pose is a partial view (the jaws
or the tissue hide the rest), flagged ``ambiguous`` and its covariance widened (counted
``partial_view``), and states its tip at most ``end_unseen_p_max`` sure (counted
``end_identity.partial_view``), as does one fitted to an arc with an end no camera saw (counted
``end_identity.end_unseen``; docs/tracking.md#partial-views); one whose keypoints some camera
reads end for end states at most the larger of ``reading_p_max`` and what the cameras'
statements, each about the end at its A, give its tip (counted ``end_identity.reading_turned``).
In tracking mode a frame that follows a well-fitted one starts from that pose (counted ``warm``
and ``cold``); frames without any centreline are refined on the keypoints alone (counted
``keypoints_only``).

Params: the node's own (``max_rms_px``, ``max_residual_variance``: a fit whose residuals are
larger than that many times the stated noise's variance is not posed, counted
``no_pose.poor_fit``; ``outlier_px``: the joint PnP's outlier rejection), every ``RefineConfig``
field (``sigma_kp_px``, ``sigma_curve_px``: for detectors that state no noise, a stated
``keypoint_sigma_px`` / ``centreline_sigma_px`` is used instead) and every ``TrackingConfig``
field. ``support_normal_world`` (the normal, world frame, of a surface the needle may rest on,
e.g. ``[0, 0, 1]`` for the simulator's phantom) lets ``common.geometry.rest_prior`` pick between
minima the images leave nearly equal; it needs the ``ecm`` input (a frame whose ECM pose is not
in yet uses the newest one). A frame that gives no pose is counted as ``no_pose.<reason>`` (the
PnP's reasons, or the refinement's: ``too_few_points``, ``no_valid_candidate``,
``bad_centreline``, ``bad_keypoints``, ``high_residual``, ``poor_fit``, ``unsure_keypoints``), and
said on ``no_pose`` (``NoPoseNotice``, method ``refined``, that reason) at once: the tracker
steps such a frame without waiting for a later pose.

Wrong locks (``lock_check``, default on): a camera whose keypoints the other camera's disagree with
and that lie off the track while the other camera's lie on it, two frames in a row, is said on
``lock`` (``LockRejected`` with its box, counted ``lock_rejected.<camera>``); wired to the
detectors' ``lock`` input, the detector drops that camera's tracked crop and searches it cold
(``common.geometry.stereo_agreement``). The track is the node's own last pose, else the tracker's
pose fed back on ``track`` (a feedback input: the tracker carries a held needle when no pose is
refined).

One camera (``one_camera``, default off; docs/tracking.md#one-camera): a frame whose needle one camera alone sees (the other
blocked, or its detector lost it) is fitted to that camera from the track (the tracker's pose fed
back, or the node's last pose) and said on ``one_camera`` (method ``refined_one_camera``, flagged
``ambiguous``, its covariance wide along the depth one view leaves; counted ``one_camera``) for the
tracker; ``pose`` gives that frame none (``no_pose.one_camera``; without a track
``no_pose.one_camera_untracked``). Wire only ``left`` (or only ``right``) for a monocular
endoscope (graphs/monocular.yaml): every frame is fitted so, cold from its PnP minima while there
is no track.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.constraints import Probability, number_at_least
from common.geometry.refine import RefineConfig
from common.geometry.refine_tracking import TrackingConfig
from common.pose.refine_step import RefineGates, RefineStep
from common.geometry.stereo_agreement import LockCheckConfig
from common.runtime.messages import Calibration, EcmPose, Keypoints, PoseEstimate
from common.runtime.node import NodeError, run
from common.runtime.params import config_from, merge_schemas
from nodes._pose import StereoPoseNode


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
    # a camera whose detections the other camera's and the track disagree with is said on lock
    # (LockRejected, counted lock_rejected.<camera>) for its detector to search it cold
    lock_check: bool = True
    # a frame whose needle one camera alone sees is fitted to that camera from the track and said on
    # one_camera (method refined_one_camera, its covariance wide in depth) for the tracker; off by
    # default (on the arm set it confirmed tracks already off: docs/tracking.md#one-camera);
    # one camera wired (a monocular endoscope): every frame so, whatever this says
    one_camera: bool = False


class RefineNode(StereoPoseNode):
    """Keypoints + centrelines of a stereo frame -> refined T_ecm_needle with covariance
    (``common.pose.refine_step.RefineStep``)."""

    INPUTS = {"left": Keypoints, "right": Keypoints, "calib": Calibration, "ecm": EcmPose, "track": PoseEstimate}
    OUTPUTS = ("pose", "no_pose", "lock", "one_camera")
    KEEP_ALL = StereoPoseNode.KEEP_ALL
    FEEDBACK = ("track",)

    # every RefineConfig and TrackingConfig field is a param of the same name (``tracking`` for
    # TrackingConfig.enabled), beside the node's own
    Params = merge_schemas("RefineParams", RefineConfig, TrackingConfig, _NodeParams, drop=("enabled",))

    def make_step(self, **wiring) -> RefineStep:
        try:
            config = config_from(RefineConfig, self.p)
            tracking = config_from(TrackingConfig, self.p, {"enabled": "tracking"})
            normal = support_normal(self.p.support_normal_world)
        except ValueError as exc:
            raise NodeError(str(exc)) from None
        return RefineStep(config, tracking, config_from(RefineGates, self.p), outlier_px=self.p.outlier_px,
                          support_normal_world=normal,
                          lock_check=LockCheckConfig(min_score=self.p.min_score) if self.p.lock_check else None,
                          one_camera=self.p.one_camera, **wiring)

    def on_track(self, msg: PoseEstimate):
        self.publish_all(self.step.on_track(msg))


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
