"""Shared wiring of the stereo pose nodes (``epnp``, ``triangulate``, ``refine``).

``StereoPoseNode`` is a ``Node`` base that hands a stereo frame's inputs (``left``, ``right``
``Keypoints``, ``calib``, ``ecm``) to its frame step (``STEP``, a
``common.pose.stereo.StereoPoseStep``: pairing by ``seq``, the frame's ECM pose, the end
identity read and stated, the solver) and publishes what the step returns; its counters are
the node's. A node that declares the output ``no_pose`` publishes there a ``NoPoseNotice`` for
each paired frame it gives no pose, at once.

``max_wait`` (param, default 30): the frames a pose (a node whose solution needs the ECM pose:
its pair, unsolved) waits for its frame's ECM pose, then goes out without the world pose
(counted ``no_ecm_pose``; ``solved_without_ecm``). End identity: ``common.pose.stereo``.
"""
from __future__ import annotations

from dataclasses import dataclass

from common.frames import CAMERAS
from common.methods import POSE_METHODS
from common.pose.stereo import StereoPoseStep
from common.runtime.messages import Calibration, EcmPose, Keypoints, PoseEstimate
from common.runtime.node import Node, NodeError


class StereoPoseNode(Node):
    """Base of the stereo keypoint -> pose nodes (see the module docstring). A subclass builds
    its step in ``make_step(**wiring)``; params read here: ``min_score`` (0.5, keypoints scoring
    lower are not used), ``max_wait``."""

    INPUTS = {"left": Keypoints, "right": Keypoints, "calib": Calibration, "ecm": EcmPose}
    KEEP_ALL = ("calib", "ecm")

    @dataclass
    class Params:
        min_score: float = 0.5     # keypoints scoring lower are not used
        max_wait: int = 30         # frames a pose (or a pair the solver needs the ECM pose for) waits for its ECM pose

    def setup(self):
        cameras = tuple(c for c in CAMERAS if self.wired(c))
        if not cameras:
            raise NodeError(f"{self.node_id}: wire a camera's keypoints (left, right or both)")
        self.step = self.make_step(max_wait=self.p.max_wait, ecm_wired=self.wired("ecm"),
                                   no_pose_output="no_pose" in self.OUTPUTS, cameras=cameras,
                                   count=self.count, log=self.log)
        self.pairer = self.step.pairer      # the stereo pairer, for what deepens it (a lossless graph's nodes)

    def make_step(self, **wiring) -> StereoPoseStep:
        raise NotImplementedError

    def on_stream_reset(self):
        """A new source stream: pending halves, ECM poses and waiting poses are of the old one."""
        self.publish_all(self.step.reset())

    def on_calib(self, msg: Calibration):
        self.publish_all(self.step.on_calib(msg))

    def on_ecm(self, msg: EcmPose):
        self.publish_all(self.step.on_ecm(msg))

    def on_left(self, msg: Keypoints):
        self.publish_all(self.step.on_keypoints(msg))

    def on_right(self, msg: Keypoints):
        self.publish_all(self.step.on_keypoints(msg))


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
