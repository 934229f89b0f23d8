"""Geometry: from keypoints to needle poses. Imports nothing of the rest of ``common``.

Conventions: 4x4 ``T_a_b`` maps frame b to frame a (``p_a = T_a_b @ p_b``), metres and radians
(degrees only in names ending ``_deg``); OpenCV cameras (x right, y down, z forward). Frames:
``world``, ``ecm``, ``left``, ``right``, ``needle`` (docs/dataset.md).

``transforms`` (rigid transforms, rotations, means, errors), ``camera`` (pinhole + distortion,
the stereo rig), ``needle`` (the arc model and keypoints A..E), ``ecm_kinematics`` (the
endoscope arm), ``observations`` (usable keypoints, ``NoPose``), ``lm`` (the batched Levenberg-Marquardt of
the PnP and the dense fit), ``reprojection`` (the PnP's cost and fit), ``pnp`` (EPnP per camera and
the joint stereo PnP, Pipeline I), ``triangulation`` (DLT + Arun, Pipeline II), ``fusion``
(multi-view), ``refine`` and ``refine_tracking`` (the dense arc fit, cold and warm),
``rest_prior`` (the needle resting on a surface), ``oracle`` (true keypoints with simulated
detector errors).

The entry points are re-exported here (``from common.geometry import pnp_joint``), each
imported when first used.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "make_T": "transforms", "inv_T": "transforms", "transform_points": "transforms",
    "pose_error": "transforms", "Camera": "camera", "StereoRig": "camera", "NeedleModel": "needle",
    "EcmArm": "ecm_kinematics", "NoPose": "observations", "pnp_average": "pnp", "pnp_joint": "pnp",
    "triangulation_pose": "triangulation", "DenseRefiner": "refine", "refine_pose": "refine",
    "RefineConfig": "refine",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
