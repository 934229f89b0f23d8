"""``ros2``: a live ROS 2 system, on Zenoh or on DDS, as a stereo camera source (no ROS installed).

Subscribes, on its own Zenoh session (``connect``: the rmw_zenoh router or the
zenoh-bridge-ros2dds, ``tcp/127.0.0.1:7447`` by default), to the topics of a topic map
(presets ``ambf``/``dvrk``, ``topics``; docs/ros.md), by bridge keys or rmw_zenoh keys
(``keys``), decodes the CDR samples with ``rosbags``, pairs the stereo images by header stamp
and publishes as ``rosbag`` does (``common/ros/source.py``): ``left``/``right``, ``measured``,
``truth``, ``instruments`` (``InstrumentState`` of each arm whose pose and jaw topics speak), ``calib``. ``seq`` counts the stereo pairs; ``stamp_ns`` is the images' header stamp.

params: ``preset``, ``topics`` (file or mapping), ``rig`` (the dVRK preset's ``{rig}``, e.g.
``jhu_daVinci``), ``keys`` (bridge | rmw_zenoh), ``distro`` (humble | jazzy | kilted | rolling:
the publishers' distribution; rmw_zenoh keys of any type hash are taken, a sample whose hash is of
another distribution is logged once), ``domain_id`` (0), ``namespace`` (the bridge's
key prefix), ``connect`` (endpoints), ``mode`` (peer | client), ``types`` ({topic: msgtype}
where bridge keys do not carry it and the role's default does not fit), ``encoding`` (bgr8),
``max_queue`` (samples waiting to be decoded; older ones are dropped and counted ``dropped``).
A sample that does not decode (CDR with at most the padding a ROS 2 writer leaves, common/ros/cdr.py)
or cannot serve its topic's role (wrong type, non-finite calibration or pose, oversized arrays, an
image header over 16384 px) is refused: counted ``bad_samples``, logged at most once a second per
topic; the source goes on without back-off.

``transport: dds`` speaks ROS 2's own DDS topics instead (``rt/<topic>``, Cyclone DDS;
``common/ros/dds.py``) in DDS domain ``domain_id``, with ``dds_config`` (Cyclone XML or a file
URI; default ``CYCLONEDDS_URI``), reading best effort (matches every publisher) or, with
``dds_reliability: reliable``, reliable (reliable publishers only; lost fragments are resent);
the message types are those of bridge keys (role, ``types``).
The samples are decoded by the same code on both transports.
"""
from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Literal

from common.frames import CAMERAS
from common.runtime.camera_source import CameraSourceNode
from common.runtime.node import NodeError, run

DEFAULT_TYPES = {"camera_info": "sensor_msgs/msg/CameraInfo", "ecm_joints": "sensor_msgs/msg/JointState",
                 "ecm_pose": "geometry_msgs/msg/PoseStamped", "camera_frame": "ambf_msgs/msg/RigidBodyState",
                 "camera_state": "ambf_msgs/msg/CameraState", "instrument_pose": "geometry_msgs/msg/PoseStamped",
                 "instrument_jaw": "sensor_msgs/msg/JointState", "instrument_base": "ambf_msgs/msg/RigidBodyState"}


def open_session(connect: list, mode: str = "peer"):
    """A Zenoh session to a ROS 2 system: ``connect`` endpoints, no multicast scouting."""
    import zenoh
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if mode != "client":
        c.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    return zenoh.open(c)


def role_type(role: str, topic: str, m: dict) -> str:
    """The message type a role's topic carries when the key does not say (bridge keys)."""
    if role == "image":
        return "sensor_msgs/msg/CompressedImage" if topic.endswith("/compressed") else "sensor_msgs/msg/Image"
    if role == "needle_pose":
        return "ambf_msgs/msg/RigidBodyState" if m.get("needle_frame") == "ambf" else "geometry_msgs/msg/PoseStamped"
    return DEFAULT_TYPES[role]


class Ros2Node(CameraSourceNode):
    """Live ROS 2 (over Zenoh) camera source."""

    OUTPUTS = ("left", "right", "measured", "truth", "instruments", "calib")

    @dataclass
    class Params:
        preset: str | None = None
        topics: str | dict | None = None
        rig: str = ""
        keys: Literal["bridge", "rmw_zenoh"] = "bridge"
        distro: Literal["humble", "jazzy", "kilted", "rolling"] = "jazzy"   # the ROS 2 system's (rmw_zenoh keys)
        transport: Literal["zenoh", "dds"] = "zenoh"   # dds: ROS 2's DDS topics (Cyclone DDS), no bridge
        dds_config: str = ""     # transport dds: Cyclone XML or a file URI (default: CYCLONEDDS_URI)
        dds_reliability: Literal["best_effort", "reliable"] = "best_effort"   # reliable: reliable publishers only
        domain_id: int = 0
        namespace: str = ""
        connect: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
        mode: Literal["peer", "client"] = "peer"
        types: dict = field(default_factory=dict)
        encoding: Literal["bgr8", "jpeg", "png"] = "bgr8"
        max_queue: int = 16

    def setup(self):
        from common.ros.bag import StereoAssembler
        from common.ros.instruments import instrument_topics
        from common.ros.live import topic_key
        from common.ros.source import SamplePublisher, topics_param
        from common.ros.topicmap import (
            TopicMapError,
            candidates,
            load_topic_map,
            resolve_rig_name,
        )
        p = self.p
        try:
            m = load_topic_map(p.preset, topics_param(p.topics))
        except TopicMapError as exc:
            raise NodeError(str(exc)) from None
        if p.rig:
            m = resolve_rig_name(m, p.rig)
        if "{rig}" in json.dumps(m["images"]) + json.dumps(m.get("camera_info")):
            raise NodeError("the dvrk preset's topics name the stereo rig: set param 'rig' (e.g. jhu_daVinci) "
                            "or give images/camera_info topics in a topic map")
        if p.preset == "ambf" and m.get("unit") == "auto" and not m.get("camera_states"):
            raise NodeError("unit: auto needs the cameras' State topics; set unit in the topic map")
        # every alternative topic of every role is subscribed; the first to speak is used
        roles = {}
        for c in CAMERAS:
            for t in candidates(m["images"][c]):
                roles[t] = ("image", c)
            for t in candidates((m.get("camera_info") or {}).get(c)):
                roles[t] = ("camera_info", c)
            for t in candidates((m.get("camera_states") or {}).get(c)):
                roles[t] = ("camera_state", c)
        for role in ("ecm_joints", "ecm_pose", "needle_pose", "camera_frame"):
            for t in candidates(m.get(role)):
                roles[t] = (role, None)
        for t, role, arm in instrument_topics(m):
            roles[t] = (role, arm)
        self.map = m
        via = f"dds domain {p.domain_id}" if p.transport == "dds" else p.keys
        self.asm = StereoAssembler(m, f"ros2 ({via})", roles, report=self._refused)
        self.last_bad_log: dict = {}
        self.distro_noted: set = set()
        self.queue: queue.Queue = queue.Queue(maxsize=max(1, p.max_queue))
        self.qlock = threading.Lock()
        self.subs = []
        self.keys = {}
        if p.transport == "dds":
            self._subscribe_dds(roles)
        else:
            try:
                self.session = open_session(p.connect, p.mode)
            except Exception as exc:
                raise NodeError(f"cannot open a Zenoh session to {p.connect}: {exc}") from None
            for t in roles:
                key = topic_key(t, None, p.keys, p.domain_id, p.namespace, wildcard_type=True)
                self.keys[t] = key
                self.subs.append(self.session.declare_subscriber(key, self._callback(t)))
        where = via if p.transport == "dds" else f"{p.keys} {','.join(p.connect)}"
        self.out = SamplePublisher(self, self.asm.needle_model(), f"ros2 {where}", m.get("ecm"), p.encoding)
        self.seq = 0
        self.log.info("ros2: subscribed %s", sorted(self.keys.values()))

    def _subscribe_dds(self, roles: dict) -> None:
        from common.ros.dds import DdsError, DdsLink, dds_topic_name
        p = self.p
        try:
            self.dds = DdsLink(p.domain_id, p.dds_config or None)
            for t in roles:
                self.keys[t] = dds_topic_name(t)
                self.dds.subscribe(t, self._msgtype(t, ""), self._dds_callback(t), depth=max(1, p.max_queue),
                                   reliable=p.dds_reliability == "reliable")
        except (DdsError, ValueError) as exc:
            raise NodeError(f"ros2 (dds): {exc}") from None

    def _enqueue(self, item) -> None:
        with self.qlock:
            while True:
                try:
                    self.queue.put_nowait(item)
                    return
                except queue.Full:
                    try:
                        self.queue.get_nowait()
                        self.count("dropped")
                    except queue.Empty:
                        pass

    def _callback(self, topic: str):
        from common.ros.bag import MAX_STATE_BYTES
        small = self.asm.topic_role[topic][0] != "image"

        def cb(sample):
            n = len(sample.payload)
            # an oversized state is not copied: its size goes to step, which refuses it
            payload = n if small and n > MAX_STATE_BYTES else bytes(sample.payload.to_bytes())
            self._enqueue((topic, str(sample.key_expr), payload, time.time_ns()))
        return cb

    def _dds_callback(self, topic: str):
        from common.ros.bag import MAX_STATE_BYTES
        key, small = self.keys[topic], self.asm.topic_role[topic][0] != "image"

        def cb(cdr, _stamp):
            # as on Zenoh: an oversized state goes to step as its size, which refuses it
            self._enqueue((topic, key, len(cdr) if small and len(cdr) > MAX_STATE_BYTES else cdr, time.time_ns()))
        return cb

    def _msgtype(self, topic: str, key: str) -> str:
        from common.ros.live import distro_of_key, topic_of_key
        if self.p.transport == "zenoh" and self.p.keys == "rmw_zenoh" and topic not in self.distro_noted:
            seen = distro_of_key(key)
            if seen is not None and (seen == "humble") != (self.p.distro == "humble"):
                self.distro_noted.add(topic)
                self.log.warning("ros2: %s: key %s has a %s type hash but distro is %s: the samples are read, "
                                 "but set distro to the ROS 2 system's so that ros2_out's keys match it", topic, key,
                                 "Humble" if seen == "humble" else "REP 2011", self.p.distro)
        if topic in self.p.types:
            return self.p.types[topic]
        if self.p.keys == "rmw_zenoh" and self.p.transport == "zenoh":
            _, t = topic_of_key(key, "rmw_zenoh")
            if t:
                return t
        return role_type(self.asm.topic_role[topic][0], topic, self.map)

    def _refused(self, topic: str, reason: str) -> None:
        """A sample the assembler refused: counted, logged at most once a second per topic."""
        self.count("bad_samples")
        now = time.monotonic()
        if now - self.last_bad_log.get(topic, -1e9) >= 1.0:
            self.last_bad_log[topic] = now
            self.log.error("ros2: %s: sample refused (%d on this topic so far): %s", topic,
                           self.asm.refused.get(topic, 0), reason)

    def step(self):
        from common.ros.bag import BagError
        try:
            topic, key, payload, _t_rx = self.queue.get(timeout=0.1)
        except queue.Empty:
            if self.calib is not None:
                self._publish_calib()
            return True
        msgtype = self._msgtype(topic, key)
        if isinstance(payload, int):
            self.asm.refuse_oversized(topic, payload, msgtype)
            return True
        try:
            samples = self.asm.feed_bytes(topic, payload, msgtype)
        except BagError as exc:               # the rig cannot make a sample (e.g. sizes differ)
            self.asm.refuse(topic, str(exc))
            return True
        except Exception as exc:              # nothing a peer sends may stop the source
            self.asm.refuse(topic, f"{msgtype} on {key}: {type(exc).__name__}: {exc}")
            return True
        for s in samples:
            self.out.publish(s, self.seq, s.stamp_ns)
            self.seq += 1
        return True

    def teardown(self):
        for s in getattr(self, "subs", []):
            try:
                s.undeclare()
            except Exception:
                pass
        if getattr(self, "session", None) is not None:
            self.session.close()
        if getattr(self, "dds", None) is not None:
            self.dds.close()


NODE = Ros2Node
if __name__ == "__main__":
    run(NODE)
