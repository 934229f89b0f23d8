"""Shared wiring of the pose nodes: calibration, ECM poses by frame, stereo keypoint pairing.

``StereoPoseNode`` is a ``Node`` base for nodes that turn the two ``Keypoints`` of a stereo
frame into a pose (``epnp``, ``triangulate``): it keeps the latest ``Calibration``, remembers
recent ``EcmPose`` messages by ``seq``, pairs left/right keypoints by ``seq`` and calls
``on_pair(left, right)``; it counts the stereo frames paired (``pairs``) and why a frame gave no
pose (``no_pose.<reason>``), and builds the ``PoseEstimate`` with ``T_world_needle`` when the ECM pose of that frame is known.
A node that declares the output ``no_pose`` publishes there a ``NoPoseNotice`` (its method, the
reason) for each paired frame it gives no pose, at once: a node waiting on its poses (the
tracker) need not wait for a later frame to learn that this one has none.

``publish_pose`` publishes a pose once its frame's ECM pose is in (with ``ecm`` wired): a pose
computed before the ECM pose arrived waits for it, at most ``max_wait`` frames (param, default
30), and then goes out without the world pose (counted ``no_ecm_pose``).

End identity: when the detectors state which end is the tip (``Keypoints.end_identity``), the
stereo frame's probability (``common.geometry.end_identity``) decides: below 0.5 the pair is
turned end for end before solving (``end_identity.turned``), so that the pose is the likelier
answer; every pose states its probability (``PoseEstimate.end_identity``), and below
``min_end_identity`` (0.95) it goes out flagged ``ambiguous`` with a covariance that spans the
turned answer (``end_identity.unsure``). Without a statement, A is taken as said.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.end_identity import TIP_SURE, Settled, second_view_news, settle, state, turn_observation
from common.geometry.needle import NeedleModel
from common.methods import POSE_METHODS
from common.runtime.messages import Calibration, EcmPose, Keypoints, NoPoseNotice, PoseEstimate
from common.runtime.node import Node
from common.runtime.pairing import SeqCache, SeqJoin, StereoPairer


class StereoPoseNode(Node):
    """Base of the stereo keypoint -> pose nodes (see the module docstring).

    Params read here: ``min_score`` (0.5, keypoints scoring lower are not used).
    """

    INPUTS = {"left": Keypoints, "right": Keypoints, "calib": Calibration, "ecm": EcmPose}
    KEEP_ALL = ("calib", "ecm")
    pose_method = ""
    """The method the node's poses state (``PoseEstimate.method``); its ``NoPoseNotice``s say it."""
    SOLVE_WITH_ECM = False
    """Whether a frame's solution depends on its ECM pose (a prior in world axes, the needle's
    last world pose): with ``ecm`` wired, a pair then waits for its frame's ECM pose before it is
    solved (at most ``max_wait`` frames; counted ``solved_without_ecm`` after that), in ``seq``
    order, so that the pose does not depend on which input a loaded machine delivered first."""

    @dataclass
    class Params:
        min_score: float = 0.5     # keypoints scoring lower are not used
        max_wait: int = 30         # frames a pose (SOLVE_WITH_ECM: a pair, unsolved) waits for its ECM pose
        min_end_identity: float = TIP_SURE   # a frame whose tip is surer than this is posed as is

    def setup(self):
        self.min_score = self.p.min_score
        self.waiting = SeqJoin(self.p.max_wait)     # (output, pose) waiting for the frame's ECM pose
        self.calib: Calibration | None = None
        self.rig = None
        self.model_points = None
        self.needle = None
        self.identity = SeqCache()       # seq -> the frame's probability that A is the tip
        self.ecm_poses = SeqCache()
        self.pairer = StereoPairer()
        self.solving = SeqJoin(self.p.max_wait, in_order=True)   # pairs waiting for their ECM pose

    def on_stream_reset(self):
        """A new source stream: pending halves, ECM poses and waiting poses are of the old one."""
        self.pairer.reset()
        self.ecm_poses.clear()
        self.solving.reset()
        gone = self.waiting.reset()
        if gone:
            self.count("no_pose.source_restart", len(gone))
        self.identity.clear()

    # ---------------------------------------------------------------- inputs
    def on_calib(self, msg: Calibration):
        if self.calib is None or msg.cameras != self.calib.cameras or msg.needle != self.calib.needle:
            self.rig = StereoRig.from_dict(msg.cameras, msg.image_size)
            self.needle = NeedleModel.from_dict(msg.needle)
            self.model_points = self.needle.keypoints()
        self.calib = msg

    def on_ecm(self, msg: EcmPose):
        self.ecm_poses.put(msg.seq, np.asarray(msg.T_world_ecm, dtype=float))
        self._solve_due()
        self._release()

    def on_left(self, msg: Keypoints):
        self._push(msg)

    def on_right(self, msg: Keypoints):
        self._push(msg)

    def _push(self, msg: Keypoints):
        if msg.camera not in ("left", "right"):
            self.count("bad_input")
            return
        dropped = self.pairer.dropped
        pair = self.pairer.push(msg.camera, msg.seq, msg)
        if self.pairer.dropped > dropped:
            self.count("unpaired", self.pairer.dropped - dropped)
        self.waiting.see(msg.seq)
        self.solving.see(msg.seq)
        self._release()
        if pair is not None:
            self.count("pairs")
            if self.SOLVE_WITH_ECM and self.wired("ecm"):
                self.solving.hold(pair[0].seq, pair)
            else:
                self._solve(pair)
        self._solve_due()

    def _solve_due(self) -> None:
        """Solve the held pairs whose ECM pose is in, or that waited ``max_wait`` frames."""
        for pair, complete in self.solving.due(lambda seq, _: seq in self.ecm_poses):
            if not complete:
                self.count("solved_without_ecm")
            self._solve(pair)

    def _solve(self, pair: tuple[Keypoints, Keypoints]) -> None:
        if self.rig is None:
            self.no_pose("no_calibration", pair[0])
            return
        self.on_pair(*self.settle_end_identity(*pair))

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

    def on_pair(self, left: Keypoints, right: Keypoints) -> None:
        raise NotImplementedError

    # ---------------------------------------------------------------- helpers
    @staticmethod
    def stereo_arrays(left: Keypoints, right: Keypoints) -> tuple[dict, dict]:
        """(uv, scores) maps for the solvers; a camera whose detector found nothing is left out."""
        uv, sc = {}, {}
        for kp in (left, right):
            if kp.found:
                uv[kp.camera] = np.asarray(kp.uv, dtype=float)
                sc[kp.camera] = np.asarray(kp.scores, dtype=float)
        return uv, sc

    def no_pose(self, reason: str, frame: Keypoints, detail: str = "") -> None:
        """Frame ``frame.seq`` (one of its keypoints) gives no pose: counted ``no_pose.<reason>``,
        and said on ``no_pose`` where the node declares it."""
        self.count(f"no_pose.{reason}")
        self.log.debug("seq %d: no pose (%s) %s", frame.seq, reason, detail)
        if "no_pose" in self.OUTPUTS:
            self.publish("no_pose", NoPoseNotice(frame.seq, frame.stamp_ns, self.pose_method, reason))

    def publish_pose(self, pose: PoseEstimate, output: str = "pose") -> None:
        """Publish ``pose`` now, or once its frame's ECM pose is in (module docstring), stating its
        frame's ``end_identity``. A frame whose tip the images could not tell from its tail goes
        out flagged ``ambiguous``, its covariance widened to span the end-for-end turn."""
        p = self.identity.get(pose.seq)
        if p is not None:
            pose.end_identity = float(p)
        unsure, pose.covariance = state(pose.T_ecm_needle, pose.covariance, self.needle, p,
                                        self.p.min_end_identity)
        if unsure:
            self.count("end_identity.unsure")
            pose.ambiguous = True
        if pose.T_world_ecm is None and self.wired("ecm"):
            self.waiting.hold(pose.seq, (output, pose))
            self._release()
        else:
            self.publish(output, pose)

    def _release(self) -> None:
        for (output, pose), complete in self.waiting.due(lambda seq, _: seq in self.ecm_poses):
            if complete:
                pose.T_world_ecm = self.ecm_poses[pose.seq]
                pose.T_world_needle = pose.T_world_ecm @ pose.T_ecm_needle
            else:
                self.count("no_ecm_pose")
            self.publish(output, pose)

    def pose_message(self, seq: int, stamp_ns: int, method: str, T_ecm_needle, residual: float,
                     residual_unit: str, **extra) -> PoseEstimate:
        """A PoseEstimate, with T_world_ecm/T_world_needle when the frame's ECM pose is known."""
        T_world_ecm = self.ecm_poses.get(seq)
        T_world_needle = None if T_world_ecm is None else T_world_ecm @ T_ecm_needle
        return PoseEstimate(seq, stamp_ns, method, np.asarray(T_ecm_needle, dtype=float),
                            T_world_needle, T_world_ecm, float(residual), residual_unit, **extra)


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




class PoseMethodInputs:
    """Mixin for nodes that take every method's pose (evaluator, monitor): an input named after
    each method in ``POSE_METHODS`` calls ``self.on_pose(method, msg)``."""

    def on_pose(self, method: str, msg: PoseEstimate) -> None:
        raise NotImplementedError


def _pose_handler(method):
    def handler(self, msg):
        self.on_pose(method, msg)
    handler.__name__ = f"on_{method}"
    return handler


for _method in POSE_METHODS:
    setattr(PoseMethodInputs, f"on_{_method}", _pose_handler(_method))
