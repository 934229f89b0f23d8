"""The frame step of the dense refinement (the ``refine`` node): the needle pose fitted to its
whole visible arc in both cameras, with an uncertainty (``common.geometry.refine``).

Per frame: the minima of the joint stereo PnP on the keypoints are the starting poses;
``DenseRefiner.refine`` fits them, and their mirror images, to keypoints and centrelines of both
cameras together and keeps the best. In tracking mode (``common.geometry.refine_tracking``) a
frame that follows a well-fitted one starts from that pose instead and keeps the result only if
it is as good, else it is refined cold (counted ``warm`` and ``cold``). Frames without any
centreline are refined on the keypoints alone (counted ``keypoints_only``).

Gates (``RefineGates``): a fit whose RMS exceeds ``max_rms_px`` (``no_pose.high_residual``) or
whose residuals exceed ``max_residual_variance`` times the stated noise's variance
(``no_pose.poor_fit``: e.g. a needle's tail in the jaws, the centreline running along the jaw)
gives no pose and restarts the tracking. A pose fitted to less of its arc than ``min_arc_seen``
(``arc_seen``, ``common.geometry.arc_support``) is a partial view: flagged ``ambiguous``, its
covariance times ``partial_view_inflation`` (counted ``partial_view``). A fit whose images
leave a direction of the pose unfixed (a short stretch of arc, its keypoints placed on it rather
than seen) states the widest honest covariance there (``common.geometry.covariance_bound``:
nothing known of the orientation, the position within the working volume), flagged
``ambiguous`` (counted ``unobservable``): every covariance a pose states is one a message may
carry. Its tip
(``end_identity.pose_tip_probability``): at most ``end_unseen_p_max`` sure when an end of the
fitted arc no camera saw or a partial view (``end_identity.end_unseen``,
``end_identity.partial_view``), at most the larger of ``reading_p_max`` and what the cameras'
statements give when some camera's keypoints read the pose end for end
(``end_identity.reading_turned``).

The frame's end identity is read against the tracked needle's (``end_identity.settle`` with
tracking): whether the frame reads the needle as the track does is told by reprojecting the
tracked pose (``same_as_track``). A frame's pose waits for its ECM pose before it is solved
(``solve_with_ecm``): the resting prior's normal (``support_normal_world``, the normal of a
surface the needle may rest on, e.g. the phantom's ``[0, 0, 1]``: ``common.geometry.rest_prior``)
and the needle's last world pose (``expected_T_ecm_needle``, which picks between an ambiguous
frame's minima) are in world axes.

Wrong locks (``check_locks``, ``common.geometry.stereo_agreement``): a detector tracks a crop per
camera and can stay locked on a distractor (a red marker) while the other camera sees the needle.
A camera whose keypoints the other camera's disagree with (epipolar) and that lie off the track
while the other camera's lie on it, ``LockCheckConfig.frames`` frames in a row, is said on
``lock`` (``LockRejected``, counted ``lock_rejected.<camera>``): its detector drops the crop and
searches cold. The track: this step's own last pose, else the tracker's (``on_track``, fed back).

One camera (``one_camera``, default off: measured, docs/tracking.md#one-camera): a frame whose needle one camera alone sees (the other
blocked by an instrument, or its detector lost it) is fitted to that camera alone
(``RefineConfig.min_cameras`` 1), from the track only (the tracker's pose fed back, at most
``TRACKED_MAX_AGE`` frames old, and this step's last pose within ``TrackingConfig.max_gap_s``),
never cold: one view fixes the needle's depth only through its arc's apparent size and shape,
and cold fits of such frames were centimetres off (docs/design-decisions.md). Its pose goes out
on ``one_camera`` (method ``refined_one_camera``, flagged ``ambiguous``, its covariance the fit's:
wide along the depth one view leaves) for the tracker to update the track with; ``pose`` gives
that frame no pose (``no_pose.one_camera``), so that ``refined`` stays a stereo method. Without a
track such a frame has no pose (``no_pose.one_camera_untracked``). A monocular endoscope (one
camera wired, ``cameras``) fits every frame so, cold from that camera's PnP minima when there is
no track.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from common.frames import CAMERAS
from common.geometry.arc_support import SUPPORT_PX, arc_support, best_seen, ends_seen, partial_view, shares
from common.geometry.end_identity import camera_readings, pose_tip_probability, settle
from common.geometry.observations import NoPose
from common.geometry.pnp import refine_starts
from common.geometry.refine import ArcObservation, DenseRefiner, RefineConfig, RefineError, near_expected
from common.geometry.refine_tracking import TrackingConfig, TrackingRefiner
from common.geometry.stereo_agreement import LockCheck, LockCheckConfig
from common.geometry.transforms import inv_T
from common.pose.stereo import StereoPoseStep, stated_end_identity, stereo_arrays, stereo_news, turn_keypoints
from common.runtime.messages import Keypoints, LockRejected, PoseEstimate


TRACKED_MAX_AGE = 30
"""The tracker's pose stands for the track (``RefineStep.track_pose``) at most this many frames on."""

ONE_CAMERA_DEPTH_SIGMA = 0.05
"""A one-camera pose's depth is stated at least this share of its distance uncertain (1 sigma):
one view's depth follows the arc's apparent size, which the detector misreads by a few per cent
in every frame of a take alike (cold one-camera fits were 3-4 mm off at 10-25 cm, median)."""

ONE_CAMERA_METHOD = "refined_one_camera"
"""The method of a pose fitted to one camera's view (module docstring), on output ``one_camera``."""


@dataclass(frozen=True)
class RefineGates:
    """What a refined fit must be to be posed, and what a partial view states (module docstring).
    Pixels, shares of the arc and probabilities; None: no gate."""
    max_rms_px: float | None = 20.0
    max_residual_variance: float | None = 1.5
    min_arc_seen: float = 0.6
    partial_view_inflation: float = 4.0
    end_unseen_p_max: float = 0.9
    reading_p_max: float = 0.5


class RefineStep(StereoPoseStep):
    """Keypoints + centrelines of a stereo frame -> refined T_ecm_needle with covariance (module
    docstring). ``config``: the fit's; ``tracking``: warm starts; ``gates``; ``outlier_px``: the
    joint PnP's outlier rejection; ``support_normal_world``: a unit 3-vector or None."""

    solve_with_ecm = True     # the resting prior's normal and the needle's last world pose

    def __init__(self, config: RefineConfig = RefineConfig(), tracking: TrackingConfig = TrackingConfig(),
                 gates: RefineGates = RefineGates(), *, outlier_px: float | None = 10.0,
                 support_normal_world: np.ndarray | None = None,
                 lock_check: LockCheckConfig | None = LockCheckConfig(), one_camera: bool = False, **kw):
        kw["min_score"] = config.min_score
        super().__init__("refined", **kw)
        self.config, self.tracking, self.gates = config, tracking, gates
        self.outlier_px = outlier_px
        self.support_normal_world = support_normal_world
        self.tracker: TrackingRefiner | None = None
        self._track: tuple[float, float] | None = None   # the tracked needle's end identity (track_identity)
        self._T_world_needle: np.ndarray | None = None    # the tracked needle's last pose in world
        self._T_world_needle_before: np.ndarray | None = None   # ... the one before it
        self._last_flagged = True                                 # whether the last pose was flagged
        self.locks = None if lock_check is None else LockCheck(lock_check)
        self._tracked: tuple[int, np.ndarray] | None = None      # (seq, T_world_needle) of the tracker's last pose
        self.one_camera = one_camera or self.monocular
        self.one_camera_refiner: DenseRefiner | None = None

    def calibrated(self) -> None:
        self.tracker = TrackingRefiner(DenseRefiner(self.rig, self.needle, self.config),
                                       self.model_points, self.min_score, self.outlier_px, self.tracking)
        self.one_camera_refiner = DenseRefiner(self.rig, self.needle, replace(self.config, min_cameras=1))

    def reset(self) -> list:
        out = super().reset()
        if self.tracker is not None:
            self.tracker.reset()          # the last pose is of the old stream
        self._track = None
        self._T_world_needle = self._T_world_needle_before = None
        self._last_flagged = True
        self._tracked = None
        if self.locks is not None:
            self.locks.reset()
        return out

    def on_track(self, msg: PoseEstimate) -> list:
        """The tracker's pose of a frame (``tracked``, fed back): where the track is when this
        step has no pose of its own to go by (``track_pose``)."""
        if msg.T_world_needle is not None and (self._tracked is None or msg.seq >= self._tracked[0]):
            self._tracked = (msg.seq, np.asarray(msg.T_world_needle, float))
        return self._take()

    def track_pose(self, seq: int, stamp_ns: int) -> np.ndarray | None:
        """The tracked needle in frame ``seq``'s ECM frame: this step's own (``expected_T_ecm_needle``,
        else its last frame's pose), else the tracker's latest pose (``on_track``) at most
        ``TRACKED_MAX_AGE`` frames old, seen from this frame's endoscope pose; None: no track."""
        T = self.expected_T_ecm_needle(seq)
        if T is None and self.tracker is not None:
            T = self.tracker.track(stamp_ns)
        T_world_ecm = self.ecm_poses.get(seq)
        if T is None and self._tracked is not None and T_world_ecm is not None \
                and 0 <= seq - self._tracked[0] <= TRACKED_MAX_AGE:
            T = inv_T(T_world_ecm) @ self._tracked[1]
        return T

    def check_locks(self, left: Keypoints, right: Keypoints) -> None:
        """A camera whose detection the other camera and the track disagree with, frames in a
        row (``stereo_agreement.LockCheck``), is a wrong lock: said on ``lock`` (``LockRejected``,
        its box) for the detector to search it cold; counted ``lock_rejected.<camera>``."""
        if self.locks is None or self.rig is None:
            return
        uv, sc = stereo_arrays(left, right)
        verdict = self.locks.check(self.rig, self.needle, uv, sc, self.track_pose(left.seq, left.stamp_ns))
        for kp in (left, right):
            if kp.camera in verdict.drop:
                self.count(f"lock_rejected.{kp.camera}")
                self.log.info("seq %d: %s camera's detection is a wrong lock (%.0f px off the other camera's, "
                              "%.0f px off the track)", kp.seq, kp.camera, verdict.epipolar_px,
                              verdict.track_px[kp.camera])
                self.emit("lock", LockRejected(kp.seq, kp.stamp_ns, kp.camera, "wrong_lock", bbox=kp.bbox))

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
        uv, sc = stereo_arrays(left, right)
        tuv, tsc = stereo_arrays(turn_keypoints(left), turn_keypoints(right))
        as_read, turned = self.tracker.reprojects(uv, sc, prev), self.tracker.reprojects(tuv, tsc, prev)
        return as_read if as_read != turned else None     # the frame relates to the track one way only

    def solve(self, left: Keypoints, right: Keypoints) -> None:
        g = self.gates
        self.check_locks(left, right)
        uv, sc = stereo_arrays(left, right)
        obs = {kp.camera: ArcObservation.from_keypoints(kp) for kp in (left, right) if kp.found}
        one = len(obs) == 1 and self.one_camera
        if one:
            res = self.fit_one_camera(left if left.found else right, uv, sc, obs)
            if res is None:
                return
        else:
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
        fails = self.gate(res)
        if fails is not None:
            if not one:
                self.tracker.reset()
            self.no_pose(fails[0], left, fails[1])
            return
        if res.ambiguous:
            self.count("ambiguous")
        if "unobservable" in res.reasons:
            self.count("unobservable")         # a direction at the covariance's bound
        support = arc_support(self.rig, self.needle, res.T_ecm_needle, obs, SUPPORT_PX,
                              self.config.min_centreline_w, self.config.min_score)
        seen = best_seen(shares(support))
        partial, covariance = partial_view(res.covariance, seen, g.min_arc_seen, g.partial_view_inflation)
        if one:
            covariance = self.one_camera_depth(covariance, res.T_ecm_needle, next(iter(obs)))
        if partial:
            self.count("partial_view")
        p = self.identity.get(left.seq)
        stated, caps = pose_tip_probability(
            p, ends_seen(support) if support else None,
            camera_readings(self.rig, self.needle, res.T_ecm_needle, uv, sc),
            dict(zip(CAMERAS, stated_end_identity(left, right))),
            end_unseen_p_max=g.end_unseen_p_max, reading_p_max=g.reading_p_max,
            partial=partial, news=stereo_news(left, right))
        for cap in caps:
            self.count(f"end_identity.{cap}")
        if stated != p:
            self.identity.put(left.seq, stated)
        pose = self.pose_message(left.seq, left.stamp_ns, res.T_ecm_needle,
                                 res.rms_px, "px", covariance=covariance,
                                 ambiguous=bool(res.ambiguous or partial or one), arc_seen=seen,
                                 model_sigma_m=self.config.model_sigma_mm * 1e-3 or None,
                                 model_sigma_rad=math.radians(self.config.model_sigma_deg) or None)
        if one:
            pose.method = ONE_CAMERA_METHOD
            self.count("one_camera")
            self.publish_pose(pose, "one_camera")
            self.no_pose("one_camera", left, "one camera sees the needle: its pose is on one_camera")
            return
        self._T_world_needle_before = self._T_world_needle
        self._T_world_needle = pose.T_world_needle    # None until the frame's ECM pose is known
        self.publish_pose(pose)                       # (which flags an unsure tip)
        self._last_flagged = pose.ambiguous

    def gate(self, res) -> tuple[str, str] | None:
        """(reason, detail) when a fit may not be posed (``RefineGates``: its RMS, its residuals
        against the stated noise), else None."""
        g = self.gates
        if g.max_rms_px is not None and not res.rms_px <= g.max_rms_px:
            return "high_residual", f"RMS {res.rms_px:.2f} px > {g.max_rms_px} px"
        if g.max_residual_variance is not None and not res.residual_variance <= g.max_residual_variance:
            return "poor_fit", (f"residual variance {res.residual_variance:.2f} > {g.max_residual_variance} "
                                f"(the images are not the needle model's)")
        return None

    def one_camera_depth(self, covariance: np.ndarray, T_ecm_needle: np.ndarray, camera: str) -> np.ndarray:
        """A one-camera fit's covariance with its depth at least ``ONE_CAMERA_DEPTH_SIGMA`` of the
        distance, 1 sigma along the camera's ray to the needle (ECM axes): the fit's own covariance
        counts the pixels' noise, not the detector's error of the arc's apparent size, which its
        depth follows and which every frame of a take shares."""
        centre = T_ecm_needle[:3, 3]
        ray = centre - self.rig[camera].T_ecm_cam[:3, 3]
        dist = float(np.linalg.norm(ray))
        ray = ray / dist
        out = np.array(covariance, float)
        out[3:, 3:] += (ONE_CAMERA_DEPTH_SIGMA * dist) ** 2 * np.outer(ray, ray)
        return out

    def one_camera_starts(self, seq: int, stamp_ns: int) -> list[np.ndarray]:
        """Where a one-camera fit of frame ``seq`` starts (module docstring): the tracker's pose
        at most ``TRACKED_MAX_AGE`` frames old and this step's last pose within ``max_gap_s``,
        in this frame's ECM frame; [] without a track."""
        starts = []
        T_world_ecm = self.ecm_poses.get(seq)
        if self._tracked is not None and T_world_ecm is not None and 0 <= seq - self._tracked[0] <= TRACKED_MAX_AGE:
            starts.append(inv_T(T_world_ecm) @ self._tracked[1])
        own = None if self.tracker is None else self.tracker.track(stamp_ns)
        if own is not None:
            starts.append(own)
        return starts

    def fit_one_camera(self, kp: Keypoints, uv: dict, sc: dict, obs: dict):
        """The fit of a frame one camera alone sees (module docstring); None after ``no_pose``."""
        starts = self.one_camera_starts(kp.seq, kp.stamp_ns)
        if not starts and not self.monocular:
            self.no_pose("one_camera_untracked", kp, "one camera sees the needle and there is no track to fit it from")
            return None
        try:
            if not starts:          # a monocular endoscope's first frame: that camera's PnP minima
                starts = refine_starts(uv, self.rig, self.model_points, sc, self.min_score, self.outlier_px)
            return self.one_camera_refiner.refine(obs, starts, support_normal=self.support_normal_ecm(kp.seq),
                                                  expected=starts[0])
        except NoPose as exc:
            self.no_pose(exc.reason, kp, exc.detail)
        except RefineError as exc:
            self.no_pose(exc.reason, kp, str(exc))
        return None

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
        no ECM pose yet: counted ``no_support_prior``)."""
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
