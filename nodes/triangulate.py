"""Pipeline II node: DLT triangulation of the keypoint pairs and Arun's registration
(common/triangulation.py).

Inputs: ``left``, ``right`` (Keypoints, paired by ``seq``), ``calib``, ``ecm`` (EcmPose,
optional: adds ``T_world_ecm``/``T_world_needle``; when wired, a pose waits for its frame's ECM
pose, at most ``max_wait`` frames, default 30). Outputs: ``pose`` (PoseEstimate, method
``triangulation``, residual = registration RMS in m, ``points_ecm`` the triangulated points)
and ``points`` (Points3D, published for every frame with a valid calibration, NaN rows where a
keypoint was not triangulated).

Params: ``min_score`` (0.5); ``max_rms_m`` (0.05: a registration worse than this, larger than
the needle itself, means the points are not a needle and no pose is published; with 1 px
keypoint noise the RMS is typically 8 mm, at most 4 cm).
"""
from __future__ import annotations

import numpy as np

from common.messages import Calibration, EcmPose, Keypoints, Points3D
from common.node import run
from common.observations import NoPose
from common.pose_node import StereoPoseNode
from common.triangulation import triangulate_keypoints, triangulation_pose


class TriangulateNode(StereoPoseNode):
    """Pipeline II: triangulate A..E, register the needle model onto them -> T_ecm_needle."""

    INPUTS = {"left": Keypoints, "right": Keypoints, "calib": Calibration, "ecm": EcmPose}
    OUTPUTS = ("pose", "points")
    KEEP_ALL = StereoPoseNode.KEEP_ALL

    def setup(self):
        super().setup()
        v = self.params.get("max_rms_m", 0.05)
        self.max_rms_m = None if v is None else float(v)

    def on_pair(self, left, right):
        uv, sc = self.stereo_arrays(left, right)
        n = len(self.model_points)
        try:
            res = triangulation_pose(uv, self.rig, self.model_points, sc, self.min_score, self.max_rms_m)
            pts, valid = res.points_ecm, res.valid
        except NoPose as exc:
            res = None
            pts, valid, _ = triangulate_keypoints(uv, self.rig, n, sc, self.min_score)
            self.no_pose(exc.reason, left.seq, exc.detail)
        self.publish("points", Points3D(left.seq, left.stamp_ns, pts, np.asarray(valid, dtype=bool)))
        if res is not None:
            self.publish_pose(self.pose_message(left.seq, left.stamp_ns, "triangulation",
                                                   res.T_ecm_needle, res.rms_m, "m",
                                                   points_ecm=res.points_ecm))


NODE = TriangulateNode
if __name__ == "__main__":
    run(NODE)
