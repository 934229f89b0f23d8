"""Pipeline II node: DLT triangulation of the keypoint pairs and Arun's registration
(common/geometry/triangulation.py).

Inputs: ``left``, ``right`` (Keypoints, paired by ``seq``), ``calib``, ``ecm`` (EcmPose,
optional: adds ``T_world_ecm``/``T_world_needle``; when wired, a pose waits for its frame's ECM
pose, at most ``max_wait`` frames, default 30). Outputs: ``pose`` (PoseEstimate, method
``triangulation``, residual = registration RMS in m, ``points_ecm`` the triangulated points)
and ``points`` (Points3D, published for every frame with a valid calibration, NaN rows where a
keypoint was not triangulated), and ``no_pose`` (``NoPoseNotice``: a frame without a pose,
``common/pose/stereo.py``, the frame step).

Params: ``min_score`` (0.5); ``max_rms_m`` (0.05: a registration worse than this, larger than
the needle itself, means the points are not a needle and no pose is published; with 1 px
keypoint noise the RMS is typically 8 mm, at most 4 cm).
"""
from __future__ import annotations

from dataclasses import dataclass

from common.pose.stereo import TriangulationStep
from common.runtime.messages import Calibration, EcmPose, Keypoints
from common.runtime.node import run
from nodes._pose import StereoPoseNode


class TriangulateNode(StereoPoseNode):
    """Pipeline II: triangulate A..E, register the needle model onto them -> T_ecm_needle
    (``common.pose.stereo.TriangulationStep``)."""

    INPUTS = {"left": Keypoints, "right": Keypoints, "calib": Calibration, "ecm": EcmPose}
    OUTPUTS = ("pose", "points", "no_pose")
    KEEP_ALL = StereoPoseNode.KEEP_ALL

    @dataclass
    class Params(StereoPoseNode.Params):
        max_rms_m: float | None = 0.05    # larger Arun residuals give no pose; null: no gate

    def make_step(self, **wiring) -> TriangulationStep:
        return TriangulationStep(max_rms_m=self.p.max_rms_m, min_score=self.p.min_score, **wiring)


NODE = TriangulateNode
if __name__ == "__main__":
    run(NODE)
