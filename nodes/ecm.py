"""ECM kinematics node: joint states -> endoscope pose ``T_world_ecm`` (common/geometry/ecm_kinematics.py).

Inputs: ``joints`` (EcmJoints, every message is used), ``calib`` (Calibration, optional),
``measured`` (EcmPose, optional: a measured endoscope pose, e.g. a dVRK's or AMBF's
``measured_cp`` played from a bag or a dataset without joints: passed on with the cameras' poses
added; a source sends a frame either joints or a measured pose).
Output: ``pose`` (EcmPose with the same ``seq``/``stamp_ns`` and ``q``; with a calibration, also
the cameras' poses ``T_world_left`` and ``T_world_right``).

The arm model (``T_world_base`` 4x4, ``L_rcc`` m, ``L_scopelen`` m) comes from the node's params
when any of them is given, else from the calibration's ``ecm`` mapping (the dataset's), else the
default arm (base at the world origin, zero lengths). With ``calib`` wired, joint states that
arrive before the first calibration are counted ``no_pose.no_calibration`` and skipped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.transforms import is_rigid
from common.runtime.messages import Calibration, EcmJoints, EcmPose
from common.runtime.node import Node, NodeError, run

ARM_KEYS = ("T_world_base", "L_rcc", "L_scopelen")


def arm_from_params(params: dict) -> EcmArm | None:
    """The arm from node params, or None when they give none of its keys; raises ValueError."""
    if not any(k in params for k in ARM_KEYS):
        return None
    try:
        arm = EcmArm.from_dict({k: params[k] for k in ARM_KEYS if k in params})
    except (TypeError, ValueError) as exc:
        raise ValueError(f"ecm: bad arm params: {exc}") from None
    if not is_rigid(arm.T_world_base):
        raise ValueError(f"ecm: params.T_world_base is not a 4x4 rigid transform: {arm.T_world_base.tolist()}")
    if not (np.isfinite(arm.L_rcc) and np.isfinite(arm.L_scopelen)):
        raise ValueError("ecm: params.L_rcc / L_scopelen must be finite")
    return arm


class EcmNode(Node):
    """Forward kinematics of the endoscope arm at the rate joint states arrive."""

    INPUTS = {"joints": EcmJoints, "calib": Calibration, "measured": EcmPose}
    OUTPUTS = ("pose",)
    KEEP_ALL = ("joints", "calib", "measured")

    @dataclass
    class Params:
        T_world_base: list[list[float]] | None = None   # 4x4; with L_rcc, L_scopelen: the arm model
        L_rcc: float | None = None                      # (m); none given: the calibration's arm
        L_scopelen: float | None = None

    def setup(self):
        try:
            self.param_arm = arm_from_params({k: v for k, v in vars(self.p).items() if v is not None})
        except ValueError as exc:
            raise NodeError(str(exc)) from None
        self.calib_arm = None
        self.have_calib = False
        self.T_ecm_cams: dict = {}

    def on_calib(self, msg: Calibration):
        self.have_calib = True
        self.T_ecm_cams = {c.name: c.T_ecm_cam for c in StereoRig.from_dict(msg.cameras, msg.image_size).cameras}
        if msg.ecm is not None:
            try:
                self.calib_arm = EcmArm.from_calibration(msg.ecm)
            except (KeyError, TypeError, ValueError) as exc:
                self.count("bad_calibration")
                self.log.error("calibration ecm mapping unusable: %s", exc)

    def arm(self) -> EcmArm | None:
        if self.param_arm is not None:
            return self.param_arm
        if self.wired("calib") and not self.have_calib:
            return None
        return self.calib_arm or EcmArm()

    def on_joints(self, msg: EcmJoints):
        arm = self.arm()
        if arm is None:
            self.count("no_pose.no_calibration")
            return
        try:
            T = arm.T_world_ecm(msg.q)
        except ValueError as exc:
            self.count("no_pose.bad_joints")
            self.log.warning("seq %d: %s", msg.seq, exc)
            return
        cams = {f"T_world_{name}": T @ T_cam for name, T_cam in self.T_ecm_cams.items()}
        self.publish("pose", EcmPose(msg.seq, msg.stamp_ns, T, np.asarray(msg.q, dtype=float), **cams))

    def on_measured(self, msg: EcmPose):
        if self.wired("calib") and not self.have_calib:
            self.count("no_pose.no_calibration")
            return
        T = np.asarray(msg.T_world_ecm, dtype=float)
        cams = {f"T_world_{name}": T @ T_cam for name, T_cam in self.T_ecm_cams.items()}
        self.publish("pose", EcmPose(msg.seq, msg.stamp_ns, T, msg.q, **cams))


NODE = EcmNode
if __name__ == "__main__":
    run(NODE)
