"""Pipeline I node: the needle pose from the stereo keypoints by PnP (common/geometry/pnp.py),
``method`` joint (``pnp_joint``) or average (``pnp_average``, the paper's); residual the
reprojection RMS in px. A frame that gives no pose counts ``no_pose.<reason>`` and is said on
``no_pose`` (``NoPoseNotice``; the frame step: ``common/pose/stereo.py``). Inputs, outputs
and params: ``needletrack describe epnp`` ([docs/nodes.md](../docs/nodes.md)).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from common.constraints import PositiveNumber
from common.pose.stereo import PnpStep
from common.runtime.messages import Calibration, EcmPose, Keypoints
from common.runtime.node import run
from nodes._pose import StereoPoseNode


class EpnpNode(StereoPoseNode):
    """Pipeline I: PnP per camera (average) or jointly in both cameras -> T_ecm_needle
    (``common.pose.stereo.PnpStep``)."""

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

    def make_step(self, **wiring) -> PnpStep:
        p = self.p
        # the mean of two camera poses on different branches of the planar ambiguity reprojects
        # badly by construction: the paper's method is published as it is
        max_rms_px = p.max_rms_px if p.method == "joint" or "max_rms_px" in self.params else None
        return PnpStep(p.method, max_rms_px=max_rms_px, outlier_px=p.outlier_px, refine=p.refine,
                       min_sigma_px=p.min_sigma_px, min_score=p.min_score, **wiring)


NODE = EpnpNode
if __name__ == "__main__":
    run(NODE)
