"""A real ROS 2 peer for the tests: rclpy (ROS 2 Jazzy, rmw_fastrtps_cpp), run as its own process
so that rclpy and its libraries never load into the test process.

``python tests/ros_peer.py bytes`` reads a JSON list of ``{"type", "values", "cdr"}`` on stdin
(``values``: a message as plain data, see ``plain``; ``cdr``: hex of the project's bytes of it)
and prints, for each, ``{"cdr": hex of rclpy's serialisation of values, "values": rclpy's
deserialisation of cdr, as plain data}``.

``python tests/ros_peer.py live DATASET OUT.json --rig R --frames N --timeout S`` is an rclpy
node (run it in a network namespace: DDS discovery multicasts) that publishes the dataset's frames
on the dVRK topics (``/<rig>/{left,right}/image_raw`` bgr8, ``camera_info``, ``/ECM/measured_js``
positions only, ``/needle/measured_cp``) and subscribes ``/needletrack/needle_pose``
(PoseStamped; and ``.../needle_pose_with_covariance``) until a pose came back for each of the first N frames or S seconds passed; writes
the poses received to OUT.json. Frame i is stamped ``STAMP_BASE_NS + k * CYCLE_NS + stamp_ns``
of the dataset on the k-th pass over the frames (stamps only grow, as a live system's do);
the left camera is published with rclpy's default QoS (reliable), the right one with the sensor
data QoS (best effort), as camera drivers do.

``python tests/ros_peer.py talk TOPIC SECONDS`` publishes a JointState on TOPIC ten times a
second for SECONDS (discovery as the environment says: ``ROS_AUTOMATIC_DISCOVERY_RANGE``).

Plain data: a message is a dict of its fields; uint8 arrays are ``{"b64": ...}``; other arrays
lists; floats exact (JSON keeps a float64).
"""
from __future__ import annotations

import array
import base64
import importlib
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def msg_class(msgtype: str):
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def fill(msg, d: dict):
    """Set an rclpy message's fields from plain data."""
    for name in msg.get_fields_and_field_types():
        v = d[name]
        if isinstance(v, dict) and "b64" in v:
            setattr(msg, name, array.array("B", base64.b64decode(v["b64"])))
        elif isinstance(v, dict):
            fill(getattr(msg, name), v)
        else:
            setattr(msg, name, v)
    return msg


def plain(msg) -> dict:
    """An rclpy message as plain data."""
    import numpy as np
    out = {}
    for name in msg.get_fields_and_field_types():
        v = getattr(msg, name)
        if hasattr(v, "get_fields_and_field_types"):
            out[name] = plain(v)
        elif (isinstance(v, array.array) and v.typecode == "B") or (isinstance(v, np.ndarray) and v.dtype == np.uint8):
            out[name] = {"b64": base64.b64encode(bytes(v)).decode()}
        elif isinstance(v, (array.array, np.ndarray)):
            out[name] = v.tolist()
        elif isinstance(v, list):
            out[name] = [plain(x) if hasattr(x, "get_fields_and_field_types") else x for x in v]
        else:
            out[name] = v
    return out


CYCLE_NS = 10**12           # the stamp step between passes over the frames (longer than any dataset)


def frame_of(stamp_ns: int, ds) -> int:
    """The frame index a ``live`` stamp stands for."""
    from common.ros.synth import STAMP_BASE_NS
    rel = (int(stamp_ns) - STAMP_BASE_NS) % CYCLE_NS
    return next((fr.index for fr in ds.frames if int(fr.stamp_ns) == rel), -1)


def bytes_main() -> int:
    from rclpy.serialization import deserialize_message, serialize_message
    out = []
    for item in json.load(sys.stdin):
        cls = msg_class(item["type"])
        ours = deserialize_message(bytes.fromhex(item["cdr"]), cls)
        out.append({"cdr": serialize_message(fill(cls(), item["values"])).hex(), "values": plain(ours)})
    print(json.dumps(out))
    return 0


def live_main(argv: list) -> int:
    import argparse

    import numpy as np
    import rclpy
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image, JointState

    from common.data.dataset import Dataset
    from common.ros.conventions import T_to_pose_fields
    from common.ros.synth import DVRK_JOINTS, STAMP_BASE_NS
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("out")
    ap.add_argument("--rig", default="jhu_daVinci")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--timeout", type=float, default=120)
    ap.add_argument("--hz", type=float, default=4.0)
    args = ap.parse_args(argv)
    ds = Dataset(args.dataset)
    frames = ds.frames[:args.frames]
    want = set(range(len(frames)))
    rclpy.init()
    node = Node("needletrack_test_peer")
    got: list = []

    def on_pose(m):
        got.append({"stamp_ns": m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
                    "frame_id": m.header.frame_id, "position": [m.pose.position.x, m.pose.position.y,
                                                                  m.pose.position.z],
                    "orientation": [m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
                                    m.pose.orientation.w], "t_rx": time.time()})
    node.create_subscription(PoseStamped, "/needletrack/needle_pose", on_pose, 10)
    cov: list = []

    def on_cov(m):
        cov.append({"stamp_ns": m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
                    "frame_id": m.header.frame_id, "position": [m.pose.pose.position.x, m.pose.pose.position.y,
                                                                  m.pose.pose.position.z],
                    "covariance": [float(x) for x in m.pose.covariance]})
    node.create_subscription(PoseWithCovarianceStamped, "/needletrack/needle_pose_with_covariance", on_cov, 10)
    pubs = {"left": node.create_publisher(Image, f"/{args.rig}/left/image_raw", 10),
            "right": node.create_publisher(Image, f"/{args.rig}/right/image_raw", qos_profile_sensor_data),
            "info_left": node.create_publisher(CameraInfo, f"/{args.rig}/left/camera_info", 10),
            "info_right": node.create_publisher(CameraInfo, f"/{args.rig}/right/camera_info", 10),
            "js": node.create_publisher(JointState, "/ECM/measured_js", 10),
            "needle": node.create_publisher(PoseStamped, "/needle/measured_cp", 10)}

    def stamp(msg, t_ns, frame_id=""):
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(t_ns), 1_000_000_000)
        msg.header.frame_id = frame_id
        return msg

    def frame_msgs(fr):
        t = STAMP_BASE_NS + int(fr.stamp_ns)      # restamped on each pass
        out = []
        for c in ("left", "right"):
            info = stamp(CameraInfo(), t, f"{args.rig}_{c}")
            info.width, info.height = map(int, ds.meta.image_size)
            info.distortion_model = "plumb_bob"
            info.d = [float(x) for x in ds.rig[c].dist]
            info.k = np.asarray(ds.rig[c].K, float).reshape(-1)
            info.r = np.eye(3).reshape(-1)
            info.p = np.hstack([ds.rig[c].K, np.zeros((3, 1))]).reshape(-1)
            out.append(("info_" + c, info))
        js = stamp(JointState(), t)
        js.name = list(DVRK_JOINTS)
        js.position = [float(x) for x in fr.ecm_joints]            # positions only, as many drivers
        out.append(("js", js))
        p, q = T_to_pose_fields(np.asarray(fr.T_world_needle, float), 1.0)
        nd = stamp(PoseStamped(), t, "ECM_base")
        nd.pose.position.x, nd.pose.position.y, nd.pose.position.z = map(float, p)
        nd.pose.orientation.x, nd.pose.orientation.y, nd.pose.orientation.z, nd.pose.orientation.w = map(float, q)
        out.append(("needle", nd))
        for c in ("left", "right"):
            img = ds.image(fr, c)
            im = stamp(Image(), t, c)
            im.height, im.width = img.shape[:2]
            im.encoding, im.is_bigendian, im.step = "bgr8", 0, img.shape[1] * 3
            im.data = array.array("B", img.tobytes())
            out.append((c, im))
        return out
    msgs = [frame_msgs(fr) for fr in frames]
    deadline = time.monotonic() + args.timeout
    i, next_t = 0, time.monotonic()
    while time.monotonic() < deadline and not want <= {frame_of(g["stamp_ns"], ds) for g in got}:
        if time.monotonic() >= next_t:
            t = STAMP_BASE_NS + (i // len(msgs)) * CYCLE_NS + int(frames[i % len(msgs)].stamp_ns)
            for role, m in msgs[i % len(msgs)]:
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 1_000_000_000)
                pubs[role].publish(m)
            i += 1
            next_t += 1.0 / args.hz
        rclpy.spin_once(node, timeout_sec=0.02)
    matched = {k: p.get_subscription_count() for k, p in pubs.items()}
    Path(args.out).write_text(json.dumps({"poses": got, "with_covariance": cov, "published_frames": i, "subscriptions": matched}))
    node.destroy_node()
    rclpy.shutdown()
    return 0


def talk_main(topic: str, seconds: float) -> int:
    import rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    rclpy.init()
    node = Node("needletrack_test_talker")
    pub = node.create_publisher(JointState, topic, 10)
    js = JointState()
    js.name, js.position = ["outer_yaw"], [0.25]
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        pub.publish(js)
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    if sys.argv[1] == "talk":
        sys.exit(talk_main(sys.argv[2], float(sys.argv[3])))
    if sys.argv[1] == "bytes":
        sys.exit(bytes_main())
    if sys.argv[1] == "live":
        sys.exit(live_main(sys.argv[2:]))
    raise SystemExit(f"unknown command {sys.argv[1]!r}")
