"""The frame step of the stereo pose nodes (``epnp``, ``triangulate``, ``refine``): a stereo
frame's two ``Keypoints`` to a ``PoseEstimate``.

``StereoPoseStep`` keeps the latest ``Calibration``, remembers recent ``EcmPose`` messages by
``seq``, pairs left/right keypoints by ``seq`` and solves each pair (``solve``, a subclass's);
it counts the stereo frames paired (``pairs``) and why a frame gave no pose
(``no_pose.<reason>``), and builds the ``PoseEstimate`` with ``T_world_needle`` when the ECM
pose of that frame is known. With ``no_pose_output`` a frame it gives no pose is said at once
on ``no_pose`` (``NoPoseNotice``: its method, the reason): a node waiting on its poses (the
tracker) need not wait for a later frame to learn that this one has none.

Frame joins (``common.runtime.pairing.FrameJoin``): with ``ecm`` wired a pose waits for its
frame's ECM pose at most ``max_wait`` frames, then goes out without the world pose (counted
``no_ecm_pose``); with ``solve_with_ecm`` the pair itself waits, unsolved, in ``seq`` order
(counted ``solved_without_ecm`` after ``max_wait``), so that a solution that depends on the
ECM pose does not depend on which input a loaded machine delivered first.

End identity (``common.geometry.end_identity``, the policy's one home): when the detectors
state which end is the tip (``Keypoints.end_identity``), the stereo frame's probability
decides: below 0.5 the pair is turned end for end before solving (``end_identity.turned``), so
that the pose is the likelier answer; every pose states its probability
(``PoseEstimate.end_identity``), and below ``TIP_SURE`` it goes out flagged ``ambiguous`` with
a covariance that spans the turned answer (``end_identity.unsure``,
``PoseEstimate.identity_widened``). Without a statement, A is taken as said.

A monocular endoscope (``cameras``: the one camera wired): each of its keypoints is a frame, the
other camera's half said not found (``Keypoints.not_found``, reason ``not_wired``).

Each public method returns the ``(output, message)`` pairs to publish, in order; counters go to
``count(name, n)``.
"""
from __future__ import annotations

import logging
from dataclasses import replace
from typing import Callable

import numpy as np

from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.end_identity import Settled, second_view_news, settle, state, turn_observation
from common.geometry.needle import NeedleModel
from common.geometry.observations import NoPose
from common.geometry.pnp import pnp_average, pnp_joint
from common.geometry.triangulation import triangulate_keypoints, triangulation_pose
from common.runtime.messages import Calibration, EcmPose, Keypoints, NoPoseNotice, Points3D, PoseEstimate
from common.runtime.pairing import FrameJoin, SeqCache, StereoPairer, Wait


class StereoPoseStep:
    """A stereo pose node's frames (module docstring). ``method``: what its poses state
    (``PoseEstimate.method``); ``min_score``: keypoints scoring lower are not used; ``ecm_wired``:
    whether the node takes ECM poses (then its poses wait for them); ``no_pose_output``: whether
    a frame without a pose is said on ``no_pose``."""

    solve_with_ecm = False
    """Whether a frame's solution depends on its ECM pose (a prior in world axes, the needle's
    last world pose): the pair then waits for it (module docstring)."""

    def __init__(self, method: str, *, min_score: float = 0.5, max_wait: int = 30, ecm_wired: bool = True,
                 no_pose_output: bool = True, cameras: tuple = CAMERAS, count: Callable[..., None] | None = None,
                 log: logging.Logger | None = None):
        if not cameras or not set(cameras) <= set(CAMERAS):
            raise ValueError(f"a stereo pose step's cameras are some of {CAMERAS}, got {cameras!r}")
        self.cameras = tuple(c for c in CAMERAS if c in cameras)
        self.method, self.min_score, self.max_wait = method, min_score, max_wait
        self.ecm_wired, self.no_pose_output = ecm_wired, no_pose_output
        self.count = count or (lambda name, n=1: None)    # a counter sink: the node's count
        self.log = log or logging.getLogger(__name__)
        self.calib: Calibration | None = None
        self.rig = self.needle = self.model_points = None
        self.identity = SeqCache()       # seq -> the frame's probability that A is the tip
        self.ecm_poses = SeqCache()
        self.pairer = StereoPairer()
        ecm_in = Wait("ecm", lambda seq, _: seq in self.ecm_poses)
        # (output, pose) waiting for the frame's ECM pose; pairs waiting for it, unsolved
        self.waiting = FrameJoin([ecm_in], max_wait)
        self.solving = FrameJoin([ecm_in] if self.solve_with_ecm and ecm_wired else [], max_wait, in_order=True)
        self._out: list = []

    # ---------------------------------------------------------------- inputs
    def reset(self) -> list:
        """A new source stream: pending halves, ECM poses and waiting poses are of the old one."""
        self.pairer.reset()
        self.ecm_poses.clear()
        self.solving.reset()
        gone = self.waiting.reset()
        if gone:
            self.count("no_pose.source_restart", len(gone))
        self.identity.clear()
        return self._take()

    def on_calib(self, msg: Calibration) -> list:
        if self.calib is None or msg.cameras != self.calib.cameras or msg.needle != self.calib.needle:
            self.rig = StereoRig.from_dict(msg.cameras, msg.image_size)
            self.needle = NeedleModel.from_dict(msg.needle)
            self.model_points = self.needle.keypoints()
            self.calibrated()
        self.calib = msg
        return self._take()

    @property
    def monocular(self) -> bool:
        """Whether one camera alone is wired (module docstring)."""
        return len(self.cameras) == 1

    def calibrated(self) -> None:
        """A new rig or needle is in (``self.rig``, ``self.needle``): what depends on it is rebuilt."""

    def on_ecm(self, msg: EcmPose) -> list:
        self.ecm_poses.put(msg.seq, np.asarray(msg.T_world_ecm, dtype=float))
        self._solve_due()
        self._release()
        return self._take()

    def on_keypoints(self, msg: Keypoints) -> list:
        """One camera's keypoints; a frame whose two halves are in is solved (or held)."""
        if msg.camera not in self.cameras:
            self.count("bad_input")
            return self._take()
        if self.monocular:
            pair = tuple(msg if c == msg.camera else Keypoints.not_found(c, msg.seq, msg.stamp_ns, "", "not_wired")
                         for c in CAMERAS)
        else:
            dropped = self.pairer.dropped
            pair = self.pairer.push(msg.camera, msg.seq, msg)
            if self.pairer.dropped > dropped:
                self.count("unpaired", self.pairer.dropped - dropped)
        self.waiting.see(msg.seq)
        self.solving.see(msg.seq)
        self._release()
        if pair is not None:
            self.count("pairs")
            self.solving.hold(pair[0].seq, pair)
        self._solve_due()
        return self._take()

    # ---------------------------------------------------------------- frames
    def _solve_due(self) -> None:
        """Solve the held pairs whose ECM pose is in, or that waited ``max_wait`` frames."""
        for r in self.solving.due():
            if not r.complete:
                self.count("solved_without_ecm")
            self._solve(r.item)

    def _solve(self, pair: tuple[Keypoints, Keypoints]) -> None:
        if self.rig is None:
            self.no_pose("no_calibration", pair[0])
            return
        self.solve(*self.settle_end_identity(*pair))

    def solve(self, left: Keypoints, right: Keypoints) -> None:
        """The pair's pose, posed by ``publish_pose`` (or ``no_pose``); a subclass's."""
        raise NotImplementedError

    def settle_end_identity(self, left: Keypoints, right: Keypoints) -> tuple[Keypoints, Keypoints]:
        """The pair as the solvers take it, by ``end_identity.settle``; the frame's probability
        is kept for ``publish_pose``, which states it."""
        return self.read_as(settle(*stated_end_identity(left, right), news=stereo_news(left, right)), left, right)

    def read_as(self, settled: Settled, left: Keypoints, right: Keypoints) -> tuple[Keypoints, Keypoints]:
        """The pair read as ``settled`` says (turned end for end or not), its probability kept."""
        if settled.turn:
            self.count("end_identity.turned")
            left, right = turn_keypoints(left), turn_keypoints(right)
        if settled.p is not None:
            self.identity.put(left.seq, settled.p)
        return left, right

    def no_pose(self, reason: str, frame: Keypoints, detail: str = "") -> None:
        """Frame ``frame.seq`` (one of its keypoints) gives no pose: counted ``no_pose.<reason>``,
        and said on ``no_pose`` with ``no_pose_output``."""
        self.count(f"no_pose.{reason}")
        self.log.debug("seq %d: no pose (%s) %s", frame.seq, reason, detail)
        if self.no_pose_output:
            self._out.append(("no_pose", NoPoseNotice(frame.seq, frame.stamp_ns, self.method, reason)))

    def publish_pose(self, pose: PoseEstimate, output: str = "pose") -> None:
        """Publish ``pose`` now, or once its frame's ECM pose is in (module docstring), stating its
        frame's ``end_identity``. A frame whose tip the images could not tell from its tail goes
        out flagged ``ambiguous``, its covariance widened to span the end-for-end turn."""
        p = self.identity.get(pose.seq)
        if p is not None:
            pose.end_identity = float(p)
        stated = state(pose.T_ecm_needle, pose.covariance, self.needle, p)
        pose.covariance, pose.identity_widened = stated.covariance, stated.widened
        if stated.unsure:
            self.count("end_identity.unsure")
            pose.ambiguous = True
        if pose.T_world_ecm is None and self.ecm_wired:
            self.waiting.hold(pose.seq, (output, pose))
            self._release()
        else:
            self._out.append((output, pose))

    def _release(self) -> None:
        for r in self.waiting.due():
            output, pose = r.item
            if r.complete:
                pose.T_world_ecm = self.ecm_poses[pose.seq]
                pose.T_world_needle = pose.T_world_ecm @ pose.T_ecm_needle
            else:
                self.count("no_ecm_pose")
            self._out.append((output, pose))

    def pose_message(self, seq: int, stamp_ns: int, T_ecm_needle, residual: float,
                     residual_unit: str, **extra) -> PoseEstimate:
        """A PoseEstimate of the step's method, with T_world_ecm/T_world_needle when the frame's
        ECM pose is known."""
        T_world_ecm = self.ecm_poses.get(seq)
        T_world_needle = None if T_world_ecm is None else T_world_ecm @ T_ecm_needle
        return PoseEstimate(seq, stamp_ns, self.method, np.asarray(T_ecm_needle, dtype=float),
                            T_world_needle, T_world_ecm, float(residual), residual_unit, **extra)

    def emit(self, output: str, msg) -> None:
        """Another output of the frame, published in turn."""
        self._out.append((output, msg))

    def _take(self) -> list:
        out, self._out = self._out, []
        return out


PNP_METHODS = {"joint": "pnp_joint", "average": "pnp_average"}


class PnpStep(StereoPoseStep):
    """Pipeline I: PnP per camera, averaged (``average``, the paper's), or one pose fitted in
    both cameras (``joint``); residual the reprojection RMS (px). ``max_rms_px``: a fit worse
    than this is not posed (None: no gate); ``outlier_px``: the joint fit drops its worst
    keypoint while its residual exceeds this; ``refine``: average's EPnP refined by LM;
    ``min_sigma_px``: the joint covariance's keypoint noise at least this, or the detectors'
    stated ``keypoint_sigma_px`` where larger."""

    def __init__(self, pnp: str = "joint", *, max_rms_px: float | None = 20.0, outlier_px: float | None = 10.0,
                 refine: bool = True, min_sigma_px: float = 0.25, **kw):
        super().__init__(PNP_METHODS[pnp], **kw)
        self.pnp, self.max_rms_px, self.outlier_px = pnp, max_rms_px, outlier_px
        self.refine, self.min_sigma_px = refine, min_sigma_px

    def solve(self, left, right):
        uv, sc = stereo_arrays(left, right)
        try:
            if self.pnp == "joint":
                stated = [kp.keypoint_sigma_px for kp in (left, right) if kp.found and kp.keypoint_sigma_px]
                res = pnp_joint(uv, self.rig, self.model_points, sc, self.min_score,
                                outlier_px=self.outlier_px, max_rms_px=self.max_rms_px,
                                min_sigma_px=max([self.min_sigma_px, *stated]))
            else:
                res = pnp_average(uv, self.rig, self.model_points, sc, self.min_score,
                                  refine=self.refine, max_rms_px=self.max_rms_px)
        except NoPose as exc:
            self.no_pose(exc.reason, left, exc.detail)
            return
        extra = {}
        if self.pnp == "joint":
            extra = {"covariance": res.covariance, "ambiguous": bool(res.ambiguous)}
        self.publish_pose(self.pose_message(left.seq, left.stamp_ns, res.T_ecm_needle, res.rms_px, "px", **extra))


class TriangulationStep(StereoPoseStep):
    """Pipeline II: DLT triangulation of A..E and Arun's registration of the needle model onto
    them; residual the registration RMS (m), ``points_ecm`` the triangulated points. Every
    calibrated frame also gives ``points`` (``Points3D``, NaN rows where a keypoint was not
    triangulated). ``max_rms_m``: a larger registration residual gives no pose (None: no gate)."""

    def __init__(self, *, max_rms_m: float | None = 0.05, **kw):
        super().__init__("triangulation", **kw)
        self.max_rms_m = max_rms_m

    def solve(self, left, right):
        uv, sc = stereo_arrays(left, right)
        try:
            res = triangulation_pose(uv, self.rig, self.model_points, sc, self.min_score, self.max_rms_m)
            pts, valid = res.points_ecm, res.valid
        except NoPose as exc:
            res = None
            pts, valid, _ = triangulate_keypoints(uv, self.rig, len(self.model_points), sc, self.min_score)
            self.no_pose(exc.reason, left, exc.detail)
        self.emit("points", Points3D(left.seq, left.stamp_ns, pts, np.asarray(valid, dtype=bool)))
        if res is not None:
            self.publish_pose(self.pose_message(left.seq, left.stamp_ns, res.T_ecm_needle, res.rms_m, "m",
                                                points_ecm=res.points_ecm))


def stereo_arrays(left: Keypoints, right: Keypoints) -> tuple[dict, dict]:
    """(uv, scores) maps for the solvers; a camera whose detector found nothing is left out."""
    uv, sc = {}, {}
    for kp in (left, right):
        if kp.found:
            uv[kp.camera] = np.asarray(kp.uv, dtype=float)
            sc[kp.camera] = np.asarray(kp.scores, dtype=float)
    return uv, sc


def stated_end_identity(left: Keypoints, right: Keypoints) -> tuple[float | None, float | None]:
    """Each camera's stated probability that its A is the tip (None: found nothing, or not stated)."""
    return tuple(kp.end_identity if kp.found else None for kp in (left, right))


def stereo_news(left: Keypoints, right: Keypoints) -> float:
    """How much of the second camera's end identity is new (``end_identity.second_view_news``)
    given the detections' stated unfamiliarity."""
    return second_view_news(kp.unfamiliarity for kp in (left, right) if kp.found)


def turn_keypoints(kp: Keypoints) -> Keypoints:
    """A detection read end for end (its E..A as A..E), its end identity turned with it."""
    if not kp.found:
        return kp
    uv, sc, cl, cw = turn_observation(kp.uv, kp.scores, kp.centreline, kp.centreline_w)
    return replace(kp, uv=uv, scores=sc, centreline=cl, centreline_w=cw,
                   on_arc=None if kp.on_arc is None else np.asarray(kp.on_arc)[::-1].copy(),
                   end_identity=None if kp.end_identity is None else 1.0 - kp.end_identity)
