"""Pipeline I node: the needle pose from the stereo keypoints by PnP (common/geometry/pnp.py),
``method`` joint (``pnp_joint``) or average (``pnp_average``, the paper's); residual the
reprojection RMS in px. A frame that gives no pose counts ``no_pose.<reason>`` and is said on
``no_pose`` (``NoPoseNotice``, ``nodes/_pose.py``). Inputs, outputs
and params: ``needletrack describe epnp`` ([docs/nodes.md](../docs/nodes.md)).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from common.constraints import PositiveNumber
from common.geometry.observations import NoPose
from common.geometry.pnp import pnp_average, pnp_joint
from common.runtime.messages import Calibration, EcmPose, Keypoints
from common.runtime.node import run
from nodes._pose import StereoPoseNode

METHODS = {"joint": "pnp_joint", "average": "pnp_average"}


class EpnpNode(StereoPoseNode):
    """Pipeline I: PnP per camera (average) or jointly in both cameras -> T_ecm_needle."""

    INPUTS = {"left": Keypoints, "right": Keypoints, "calib": Calibration, "ecm": EcmPose}
    OUTPUTS = ("pose", "no_pose")
    KEEP_ALL = StereoPoseNode.KEEP_ALL

    @dataclass
    class Params(StereoPoseNode.Params):
        method: Literal["joint", "average"] = "joint"   # one pose fitted in both cameras, or EPnP per camera averaged
        # a fit worse than this is not published (joint; null: no gate; average's mean of two
        # disagreeing camera poses reprojects badly by construction, so it has none)
        max_rms_px: float | None = 20.0
        outlier_px: float | None = 10.0   # joint: the worst keypoint is dropped and the fit redone while its residual exceeds this
        refine: bool = True               # average: each camera's EPnP refined by LM (false: raw EPnP, as published)
        # joint: the covariance's keypoint noise is at least this, or the detectors' stated
        # keypoint_sigma_px where larger (the residuals alone miss the errors both cameras share)
        min_sigma_px: PositiveNumber = 0.25

    def setup(self):
        super().setup()
        method = self.p.method
        self.method = method
        self.pose_method = METHODS[method]
        # the mean of two camera poses on different branches of the planar ambiguity reprojects
        # badly by construction: the paper's method is published as it is
        self.max_rms_px = self.p.max_rms_px if method == "joint" or "max_rms_px" in self.params else None
        self.outlier_px = self.p.outlier_px
        self.refine = self.p.refine
        self.min_sigma_px = self.p.min_sigma_px

    def on_pair(self, left, right):
        uv, sc = self.stereo_arrays(left, right)
        try:
            if self.method == "joint":
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
        if self.method == "joint":
            extra = {"covariance": res.covariance, "ambiguous": bool(res.ambiguous)}
        self.publish_pose(self.pose_message(left.seq, left.stamp_ns, self.pose_method,
                                               res.T_ecm_needle, res.rms_px, "px", **extra))


NODE = EpnpNode
if __name__ == "__main__":
    run(NODE)
