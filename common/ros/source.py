"""What the ROS sources (``rosbag``, ``ros2``) publish for a ``StereoSample``: the images, the
measured ECM pose, the ground truth, the instruments (``InstrumentState`` per arm) and the calibration, in the graph's messages (shared so the
two sources agree to the byte)."""
from __future__ import annotations

import json

import numpy as np

from common.frames import CAMERAS
from common.runtime.messages import Calibration, CameraImage, EcmPose, GroundTruth, InstrumentState



def calibration_of(sample, needle, source: str, ecm: dict | None = None) -> Calibration:
    """The Calibration message of a StereoSample's rig."""
    cams = {c: {"K": np.asarray(sample.cameras[c]["K"], float).tolist(),
                "dist": [float(x) for x in sample.cameras[c]["dist"]],
                "T_ecm_cam": np.asarray(sample.cameras[c]["T_ecm_cam"], float).tolist()} for c in CAMERAS}
    return Calibration(stamp_ns=0, image_size=np.array(sample.image_size), cameras=cams,
                       needle=needle.to_dict(), ecm=ecm, source=source)


def _rig_key(s) -> bytes:
    return b"".join(np.asarray(s.cameras[c][k], float).tobytes() for c in CAMERAS for k in ("K", "dist", "T_ecm_cam"))


class SamplePublisher:
    """Publishes StereoSamples from a camera source node (``node.publish``, ``node.calib``,
    ``node._publish_calib``): the rig's Calibration first and again whenever it changes."""

    def __init__(self, node, needle, source: str, ecm: dict | None = None, encoding: str = "bgr8"):
        from common.ros.convert import RestGroups
        self.node, self.needle, self.source, self.ecm, self.encoding = node, needle, source, ecm, encoding
        self.rig_key = None
        self.rig = None
        self.groups = RestGroups()

    def calibrate(self, s) -> None:
        """Make ``s``'s rig the node's calibration, published at once when it is new."""
        from common.geometry.camera import StereoRig
        key = _rig_key(s)
        if key != self.rig_key:
            self.rig_key = key
            self.node.calib = calibration_of(s, self.needle, self.source, self.ecm)
            self.rig = StereoRig.from_dict(self.node.calib.cameras, self.node.calib.image_size)
            self.node._publish_calib(force=True)

    def publish(self, s, seq: int, stamp_ns: int, sequence_offset: int = 0) -> None:
        from common.ros.convert import truth_projections
        self.calibrate(s)
        node = self.node
        for c in CAMERAS:
            # the sample's arrays are fresh and not modified after: no copy for raw bgr8
            node.publish(c, CameraImage.from_bgr(c, seq, stamp_ns, s.images[c], self.encoding, copy=False))
        if s.T_world_ecm is not None:
            node.publish("measured", EcmPose(seq, stamp_ns, np.asarray(s.T_world_ecm, float),
                                             None if s.ecm_joints is None else np.asarray(s.ecm_joints, float)))
        if s.T_world_needle is not None and s.T_world_ecm is not None:
            kp, vis, box = truth_projections(self.rig, self.needle, s.T_world_ecm, s.T_world_needle)
            sequence, step = self.groups(s.T_world_needle)
            node.publish("truth", GroundTruth(
                seq=seq, stamp_ns=stamp_ns, sequence=sequence + sequence_offset, step=step,
                ecm_joints=s.ecm_joints, T_world_ecm=s.T_world_ecm, T_world_needle=s.T_world_needle,
                keypoints=None if kp is None else {c: np.asarray(kp[c], float) for c in CAMERAS},
                visible=None if vis is None else {c: np.asarray(vis[c], bool) for c in CAMERAS},
                bbox=None if box is None else {c: None if box[c] is None else np.asarray(box[c], float)
                                               for c in CAMERAS}))
        for name, pose in (s.instruments or {}).items():
            node.publish("instruments", InstrumentState.from_pose(name, pose, seq, stamp_ns))
        node._publish_calib()


def topics_param(value):
    """A node's ``topics`` param: a topic-map file path, a mapping, or JSON text of one."""
    if isinstance(value, str) and value.strip().startswith("{"):
        return json.loads(value)
    return value
