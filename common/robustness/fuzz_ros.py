"""The fuzz's ROS 2 way in (``needletrack bench fuzz --node ros2``, ``common.robustness.fuzz``).

CDR samples into an offline ``ros2``
source on bridge and rmw_zenoh keys, through its own queue and ``step``, between clean frames
of a dVRK-like system: random bytes, truncated and bit-flipped CDR, garbage after the message,
CDR padded as rmw_fastrtps writes it (accepted), another type's CDR on a topic (rmw_zenoh: a key
naming that type), a 389 KB PNG of 20000x20000, a JointState of 10^6 names, NaN/inf in
camera_info K/D and in a pose. Crashes, published messages the graph's codec refuses, and the
clean frames until a stereo pair comes out again.
"""
from __future__ import annotations

import random
import time

import numpy as np

from common.frames import CAMERAS
from common.runtime.messages import MessageError, decode, encode

from common.robustness.fuzz import RECOVERY_LIMIT, InputResult, result_line
from common.robustness.fuzz_payloads import FRAME_HZ


# ====================================================================== ROS 2 samples (the ros2 source)

ROS_KINDS = ("random_bytes", "truncated", "bit_flips", "trailing_garbage", "padded", "wrong_type",
             "huge_compressed_image", "huge_joint_state", "non_finite_calibration", "non_finite_pose")
ROS_RIG = "fuzz"


class RosSamples:
    """CDR samples of a dVRK-like ROS 2 system (stereo 320x240 images, camera_info, the ECM's
    pose and joints) on bridge or rmw_zenoh keys, as the ``ros2`` source receives them."""

    def __init__(self, keys: str, size=(320, 240)):
        from common.geometry.camera import StereoRig
        from common.ros import build
        from common.ros.types import typestore
        self.keys, self.size, self.st, self.build = keys, size, typestore(2), build
        self.rig = StereoRig.default(*size)
        self.img = np.full((size[1], size[0], 3), 90, np.uint8)
        self.topics = {"left": f"/{ROS_RIG}/left/image_raw", "right": f"/{ROS_RIG}/right/image_raw",
                       "info_left": f"/{ROS_RIG}/left/camera_info", "info_right": f"/{ROS_RIG}/right/camera_info",
                       "pose": "/ECM/measured_cp", "joints": "/ECM/measured_js",
                       "compressed": f"/{ROS_RIG}/left/image_raw/compressed"}

    def params(self) -> dict:
        """The ``ros2`` node's params for this system (its Zenoh endpoint is never reached)."""
        reg = {c: self.rig[c].T_ecm_cam.tolist() for c in CAMERAS}
        return {"preset": "dvrk", "rig": ROS_RIG, "keys": self.keys, "topics": {"registration": reg},
                "connect": ["tcp/127.0.0.1:9"], "max_queue": 64}

    def key(self, topic: str, msgtype: str) -> str:
        from common.ros.live import topic_key
        return topic_key(topic, msgtype, self.keys)

    def messages(self, stamp: int) -> list:
        """(topic, message) of one frame: calibration, ECM pose and joints, then the images."""
        b, st = self.build, self.st
        out = [(self.topics["info_" + c], b.camera_info(st, stamp, self.rig[c].K, self.rig[c].dist, self.size))
               for c in CAMERAS]
        out.append((self.topics["pose"], b.make(st, "geometry_msgs/msg/PoseStamped", header=b.header(st, stamp),
                                                pose=b.pose(st, np.eye(4)))))
        out.append((self.topics["joints"], b.make(st, "sensor_msgs/msg/JointState", header=b.header(st, stamp),
                                                  name=["yaw", "pitch", "insertion", "roll"],
                                                  position=np.array([0.0, 0.1, 0.05, 0.0]))))
        out += [(self.topics[c], b.image(st, stamp, self.img, "bgr8")) for c in CAMERAS]
        return out

    def frame(self, stamp: int) -> list:
        """(topic, key, payload) of one clean frame."""
        from common.ros.cdr import encode
        return [(t, self.key(t, m.__msgtype__), encode(m)) for t, m in self.messages(stamp)]


_HUGE: dict = {}


def _huge(kind: str, s: RosSamples) -> bytes:
    """The big poison payloads, made once: a 20000x20000 PNG (389 KB of zeros' deflate) and a
    JointState of 10^6 names."""
    if kind not in _HUGE:
        from common.ros.cdr import encode
        b, st = s.build, s.st
        if kind == "huge_compressed_image":
            import zlib
            z, rows = zlib.compressobj(9), b"\0" * (20000 + 1) * 500               # 8-bit grey
            raw = b"".join(z.compress(rows) for _ in range(40)) + z.flush()     # 20000 rows of zeros

            def chunk(tag, data):
                return len(data).to_bytes(4, "big") + tag + data + zlib.crc32(tag + data).to_bytes(4, "big")
            png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", (20000).to_bytes(4, "big") * 2 + b"\x08\x00\0\0\0")
                   + chunk(b"IDAT", raw) + chunk(b"IEND", b""))
            msg = b.make(st, "sensor_msgs/msg/CompressedImage", header=b.header(st, 1), format="png",
                         data=np.frombuffer(png, np.uint8))
        else:
            msg = b.make(st, "sensor_msgs/msg/JointState", header=b.header(st, 1), name=["j"] * 10 ** 6,
                         position=np.zeros(4))
        _HUGE[kind] = encode(msg)
    return _HUGE[kind]


def ros_poison(s: RosSamples, kind: str, stamp: int, rng: random.Random, np_rng) -> tuple:
    """One poison sample ``(topic, key, payload)`` of ``kind`` for the ros2 source."""
    from common.ros.cdr import encode, fastcdr_estimate
    b, st = s.build, s.st
    clean = s.messages(stamp)
    topic, msg = rng.choice(clean)
    key, payload = s.key(topic, msg.__msgtype__), encode(msg)
    if kind == "random_bytes":
        head = b"\x00\x01\x00\x00" if rng.random() < 0.5 else b""
        return topic, key, head + bytes(np_rng.integers(0, 256, rng.randint(0, 512), dtype=np.uint8))
    if kind == "truncated":
        return topic, key, payload[:rng.randint(0, len(payload) - 1)]
    if kind == "bit_flips":
        p = bytearray(payload)
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(min(len(p), 512))
            p[i] ^= 1 << rng.randrange(8)
        return topic, key, bytes(p)
    if kind == "trailing_garbage":
        return topic, key, payload + bytes(np_rng.integers(0, 256, rng.randint(4, 64), dtype=np.uint8)) + b"\xff" * 8
    if kind == "padded":                  # what rmw_fastrtps sends: accepted
        return topic, key, payload + b"\0" * (4 + fastcdr_estimate(msg, msg.__msgtype__) - len(payload))
    if kind == "wrong_type":              # another type's CDR on this topic (rmw_zenoh: its key says so)
        other_topic, other = rng.choice([x for x in clean if x[1].__msgtype__ != msg.__msgtype__])
        return topic, s.key(topic, other.__msgtype__), encode(other)
    if kind in ("huge_compressed_image", "huge_joint_state"):
        t = s.topics["compressed" if kind == "huge_compressed_image" else "joints"]
        mt = "sensor_msgs/msg/CompressedImage" if kind == "huge_compressed_image" else "sensor_msgs/msg/JointState"
        return t, s.key(t, mt), _huge(kind, s)
    bad = rng.choice([float("nan"), float("inf"), -float("inf")])
    if kind == "non_finite_calibration":
        c = rng.choice(CAMERAS)
        K, D = s.rig[c].K.copy(), np.array(s.rig[c].dist, float).reshape(-1).copy()
        if rng.random() < 0.5:
            K.flat[rng.choice([0, 2, 4, 5])] = bad
        else:
            D[rng.randrange(len(D))] = bad
        t = s.topics["info_" + c]
        return t, s.key(t, "sensor_msgs/msg/CameraInfo"), encode(b.camera_info(st, stamp, K, D, s.size))
    t = s.topics["pose"]
    m = b.make(st, "geometry_msgs/msg/PoseStamped", header=b.header(st, stamp), pose=b.pose(st, np.eye(4)))
    part = m.pose.position if rng.random() < 0.5 else m.pose.orientation
    setattr(part, rng.choice([f for f in ("x", "y", "z", "w") if hasattr(part, f)]), bad)
    return t, s.key(t, m.__msgtype__), encode(m)


def _ros_published_problem(node, start: int) -> int:
    """Messages the ros2 source published that the graph's codec refuses (a NaN calibration)."""
    bad = 0
    for _, m in node.published[start:]:
        try:
            decode(encode(m))
        except MessageError:
            bad += 1
    return bad


def fuzz_ros2(keys: str, kind: str, n: int, seed: int, clean_every: int = 10) -> InputResult:
    """``n`` poison samples of ``kind`` into an offline ``ros2`` source on ``keys`` keys, between
    clean frames, through the node's own path (its queue, then ``step``); then clean frames until
    it publishes a stereo pair again."""
    import logging

    from common.runtime.node import node_class
    Ros2Node = node_class("ros2")
    rng, np_rng = random.Random(seed), np.random.default_rng(seed)
    s = RosSamples(keys)
    res = InputResult("ros2", f"{keys}:{kind}")
    node = Ros2Node.offline(s.params(), node_id="ros2")
    node.log.setLevel(logging.CRITICAL)
    stamp = [1_700_000_000 * 10 ** 9]

    def put(item) -> None:
        node.queue.put((item[0], item[1], item[2], 0))
        try:
            node.step()
        except Exception as exc:              # step must swallow anything a peer sends
            res.crashes += 1
            res.first_crash = res.first_crash or f"{kind}: step: {type(exc).__name__}: {exc}"[:300]

    def clean_frame() -> None:
        stamp[0] += int(1e9 / FRAME_HZ)
        for item in s.frame(stamp[0]):
            put(item)
    try:
        for _ in range(4):
            clean_frame()
        start = len(node.published)
        for i in range(n):
            put(ros_poison(s, kind, stamp[0], rng, np_rng))
            res.payloads += 1
            if (i + 1) % clean_every == 0:
                clean_frame()
        res.refused = int(node.counters.get("bad_samples", 0))
        res.delivered = res.payloads - res.refused
        res.invalid_published = _ros_published_problem(node, start)
        mark = len(node.published)
        for k in range(1, RECOVERY_LIMIT + 1):
            clean_frame()
            if any(o == "left" for o, _ in node.published[mark:]):
                res.recovery_frames = k
                break
    finally:
        node.teardown()
    return res


def run_fuzz_ros2(per_input: int, seed: int = 0, log=print) -> list:
    """``fuzz_ros2`` for every kind on both key forms."""
    results = []
    for j, keys in enumerate(("bridge", "rmw_zenoh")):
        for i, kind in enumerate(ROS_KINDS):
            t0 = time.perf_counter()
            r = fuzz_ros2(keys, kind, per_input, seed * 7919 + j * 101 + i)
            results.append(r)
            log(result_line(r, time.perf_counter() - t0))
    return results
