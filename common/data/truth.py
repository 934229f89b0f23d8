"""A frame's true poses from its ground truth (``GroundTruth``): the endoscope's ``T_world_ecm``
and the needle's ``T_ecm_needle``, 4x4, metres. Used by the evaluation, the viewer and the monitor.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from common.geometry.transforms import inv_T
from common.runtime.messages import GroundTruth


def true_T_world_ecm(gt: GroundTruth, arm=None) -> Optional[np.ndarray]:
    """The true endoscope pose of a frame: the truth's ``T_world_ecm``, else ``arm`` (an
    ``EcmArm``) at the truth's joints; None when neither is known."""
    if gt.T_world_ecm is not None:
        return np.asarray(gt.T_world_ecm, float)
    if arm is not None and gt.ecm_joints is not None:
        return np.asarray(arm.T_world_ecm(gt.ecm_joints), float)
    return None


def true_T_ecm_needle(gt: GroundTruth, arm=None) -> Optional[np.ndarray]:
    """The true needle pose in the ECM frame of a frame, or None when the truth lacks it
    (``T_world_ecm``: ``true_T_world_ecm``)."""
    if gt.T_world_needle is None:
        return None
    T_world_ecm = true_T_world_ecm(gt, arm)
    if T_world_ecm is None:
        return None
    return inv_T(np.asarray(T_world_ecm, float)) @ np.asarray(gt.T_world_needle, float)
