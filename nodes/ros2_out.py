"""``ros2_out``: publishes the tracked needle pose to ROS 2 over Zenoh or DDS (no ROS installed).

Input ``pose`` (PoseEstimate; ``calib``, optional, is needed for ``frame: left``). Each pose goes
out as ``geometry_msgs/PoseStamped`` on ``topic`` and, when it has a covariance,
``geometry_msgs/PoseWithCovarianceStamped`` on ``cov_topic`` (empty: not published), CDR-encoded,
on bridge keys or rmw_zenoh keys (``keys``; with rmw_zenoh, every sample carries rmw_zenoh's
attachment, ``attachment``: ``positional`` (rmw_zenoh 0.1.2+ Humble, 0.2.4+ Jazzy, 0.6+ Kilted)
or ``keyed`` (older releases), with the publisher's GID derived as rmw_zenoh derives it, and the
node declares the liveliness tokens of a node ``node_name`` and its two publishers, so that
``ros2 topic list`` / ``ros2 node list`` see them). ``distro`` (humble | jazzy | kilted |
rolling) selects the type hash in rmw_zenoh keys and tokens (Humble: ``TypeHashNotSupported``).
``transport: dds`` publishes on ROS 2's own DDS topics instead (``rt/<topic>``, Cyclone DDS,
ROS 2's default QoS: reliable, volatile, keep last 10; ``common/ros/dds.py``) in DDS domain
``domain_id``, with ``dds_config`` (Cyclone XML or a file URI; default ``CYCLONEDDS_URI``).

Frames (``frame``): ``ecm`` (default): ``T_ecm_needle``, header ``frame_id`` = ``frame_ids.ecm``
(the ECM tip: dVRK's ECM end effector, AMBF's CameraFrame); ``left``: the left camera's OpenCV
optical frame (x right, y down, z forward; ``frame_ids.left``); ``world``: ``T_world_needle``
when the pose has it (else the pose is skipped, counted ``no_world_pose``; ``frame_ids.world``).
The pose is the dataset needle frame (docs/dataset.md: origin at the arc's centre, z its normal,
the tip A at 30 deg): ``T_frame_needle``. Positions in ``unit`` (m; ``dm`` for the 2021-22 AMBF
challenge's scene units). The covariance is ROS's: 6x6 row-major over (x, y, z, rotation about
x, y, z) in the header frame, from the PoseEstimate's [rotation vector, translation] in the ECM
frame (rotated into the header frame; scaled by the unit). Header stamp = the pose's
``stamp_ns`` (the source image's stamp).

Input ``in_hand`` (optional; the tracker's ``InHandPose``, docs/tracking.md): while an instrument
holds the needle, ``T_jaw_needle`` goes out as ``geometry_msgs/PoseWithCovarianceStamped`` on
``in_hand_topic``, header ``frame_id`` the instrument's jaw frame (``psm1_jaw``, ``psm2_jaw``:
the message's ``frame_id``), the covariance in those axes.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from common.constraints import text_matching
from common.ros.conventions import ros_covariance
from common.runtime.messages import Calibration, InHandPose, PoseEstimate
from common.runtime.node import Node, NodeError, run

UNITS = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001}


RosName = text_matching(r"^/", "an absolute ROS name")


class Ros2OutNode(Node):
    """PoseEstimate -> ROS 2 PoseStamped / PoseWithCovarianceStamped over Zenoh."""

    INPUTS = {"pose": PoseEstimate, "calib": Calibration, "in_hand": InHandPose}
    OUTPUTS = ()
    KEEP_ALL = ("calib",)

    @dataclass
    class Params:
        topic: RosName = "/needletrack/needle_pose"
        cov_topic: str = "/needletrack/needle_pose_with_covariance"
        in_hand_topic: RosName = "/needletrack/needle_in_jaw"   # the in_hand input's (when wired)
        frame: Literal["ecm", "left", "world"] = "ecm"
        frame_ids: dict = field(default_factory=lambda: {"ecm": "ECM", "left": "left_camera_optical",
                                                         "world": "world"})
        unit: Literal["m", "dm", "cm", "mm"] = "m"
        keys: Literal["bridge", "rmw_zenoh"] = "bridge"
        distro: Literal["humble", "jazzy", "kilted", "rolling"] = "jazzy"   # the ROS 2 system's (rmw_zenoh keys)
        attachment: Literal["positional", "keyed"] = "positional"   # keyed: rmw_zenoh 0.1.0-0.1.1, 0.2.0-0.2.3
        transport: Literal["zenoh", "dds"] = "zenoh"   # dds: ROS 2's DDS topics (Cyclone DDS), no bridge
        dds_config: str = ""     # transport dds: Cyclone XML or a file URI (default: CYCLONEDDS_URI)
        domain_id: int = 0
        namespace: str = ""
        connect: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
        mode: Literal["peer", "client"] = "peer"
        node_name: str = "needletrack"

    def setup(self):
        from common.ros.live import entity_gid, liveliness_token, topic_key
        from nodes.ros2 import open_session
        p = self.p
        if p.frame == "left" and not self.wired("calib"):
            raise NodeError("frame: left needs the calib input wired (the left camera's pose in the ECM)")
        self.scale = UNITS[p.unit]
        self.T_ecm_left = None
        self.pubs = {}
        self.tokens = []
        targets = [("pose", p.topic, "geometry_msgs/msg/PoseStamped")]
        if p.cov_topic:
            targets.append(("cov", p.cov_topic, "geometry_msgs/msg/PoseWithCovarianceStamped"))
        if self.wired("in_hand"):
            targets.append(("in_hand", p.in_hand_topic, "geometry_msgs/msg/PoseWithCovarianceStamped"))
        self.sent = {name: 0 for name, _, _ in targets}
        if p.transport == "dds":
            from common.ros.dds import DdsError, DdsLink
            try:
                self.dds = DdsLink(p.domain_id, p.dds_config or None)
                self.pubs = {name: self.dds.publisher(topic, msgtype) for name, topic, msgtype in targets}
            except (DdsError, ValueError) as exc:
                raise NodeError(f"ros2_out (dds): {exc}") from None
            self.log.info("ros2_out: DDS domain %d: %s", p.domain_id, [t for _, t, _ in targets])
            return
        try:
            self.session = open_session(p.connect, p.mode)
        except Exception as exc:
            raise NodeError(f"cannot open a Zenoh session to {p.connect}: {exc}") from None
        zid = str(self.session.zid())
        if p.keys == "rmw_zenoh":
            self.tokens.append(self.session.liveliness().declare_token(
                liveliness_token("NN", zid, p.node_name, domain_id=p.domain_id)))
        self.gid = {}
        for i, (name, topic, msgtype) in enumerate(targets, start=1):
            key = topic_key(topic, msgtype, p.keys, p.domain_id, p.namespace, distro=p.distro)
            self.pubs[name] = self.session.declare_publisher(key)
            self.gid[name] = os.urandom(16)
            if p.keys == "rmw_zenoh":
                token = liveliness_token("MP", zid, p.node_name, domain_id=p.domain_id, entity_id=i, topic=topic,
                                         msgtype=msgtype, distro=p.distro)
                self.gid[name] = entity_gid(token)           # as rmw_zenoh derives a publisher's GID
                self.tokens.append(self.session.liveliness().declare_token(token))
        self.log.info("ros2_out: %s", {n: str(pb.key_expr) for n, pb in self.pubs.items()})

    def on_calib(self, msg: Calibration):
        self.T_ecm_left = np.asarray(msg.cameras["left"]["T_ecm_cam"], float)

    def _put(self, name: str, msg) -> None:
        from common.ros.cdr import encode
        from common.ros.live import attachment
        data = encode(msg)
        self.sent[name] += 1
        if self.p.transport == "dds":
            self.pubs[name].put(data)
        elif self.p.keys == "rmw_zenoh":
            self.pubs[name].put(data, attachment=attachment(self.sent[name], time.time_ns(), self.gid[name],
                                                            self.p.attachment))
        else:
            self.pubs[name].put(data)
        self.count(f"sent.{name}")

    def on_pose(self, msg: PoseEstimate):
        from common.geometry.transforms import inv_T
        from common.ros import build
        from common.ros.types import typestore
        p = self.p
        T = np.asarray(msg.T_ecm_needle, float)
        R_frame_ecm = np.eye(3)
        if p.frame == "world":
            if msg.T_world_needle is None or msg.T_world_ecm is None:
                self.count("no_world_pose")
                return
            T = np.asarray(msg.T_world_needle, float)
            R_frame_ecm = np.asarray(msg.T_world_ecm, float)[:3, :3]
        elif p.frame == "left":
            if self.T_ecm_left is None:
                self.count("no_calibration")
                return
            T_left_ecm = inv_T(self.T_ecm_left)
            T = T_left_ecm @ T
            R_frame_ecm = T_left_ecm[:3, :3]
        st = typestore(2)
        frame_id = str(p.frame_ids.get(p.frame, p.frame))
        hdr = build.header(st, msg.stamp_ns, frame_id)
        pose = build.pose(st, T, self.scale)
        self._put("pose", build.make(st, "geometry_msgs/msg/PoseStamped", header=hdr, pose=pose))
        if "cov" in self.pubs and msg.covariance is not None:
            cov = ros_covariance(msg.covariance, R_frame_ecm, self.scale)
            pwc = build.make(st, "geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=cov.reshape(-1))
            self._put("cov", build.make(st, "geometry_msgs/msg/PoseWithCovarianceStamped", header=hdr, pose=pwc))

    def on_in_hand(self, msg: InHandPose):
        """The needle in the jaws, in the jaw frame ``msg.frame_id``, with its covariance."""
        from common.ros import build
        from common.ros.types import typestore
        st = typestore(2)
        hdr = build.header(st, msg.stamp_ns, msg.frame_id)
        pose = build.pose(st, np.asarray(msg.T_jaw_needle, float), self.scale)
        cov = ros_covariance(msg.covariance, np.eye(3), self.scale)
        pwc = build.make(st, "geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=cov.reshape(-1))
        self._put("in_hand", build.make(st, "geometry_msgs/msg/PoseWithCovarianceStamped", header=hdr, pose=pwc))

    def teardown(self):
        for t in getattr(self, "tokens", []):
            try:
                t.undeclare()
            except Exception:
                pass
        if getattr(self, "session", None) is not None:
            self.session.close()
        if getattr(self, "dds", None) is not None:
            self.dds.close()


NODE = Ros2OutNode
if __name__ == "__main__":
    run(NODE)
