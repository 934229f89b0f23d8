"""``needletrack bench fuzz``: poison payloads into every input of every node of a graph, in
process, the way the runtime hands them over (``decode`` with the input's type, then
``Node.deliver``), between frames of a clean stream.

For each node of the graph (default: dataflow.yaml; the ``sim`` camera is a source whose only
input is its command key) and each of its inputs (and its ``cmd`` key; a viewer's page too,
``@http``: poison HTTP requests over sockets to 127.0.0.1, ``common.evaluation.http_fuzz``), a fresh offline node gets
a clean warm-up stream, then ``--per-input`` poison payloads, one clean frame after every
``--clean-every`` of them, then clean frames until it publishes again. Payload kinds: random
bytes, truncated and bit-flipped valid payloads, type-confused fields, missing/extra fields,
wrong schema or version, non-finite and huge values (NaN/inf, 1e300, 2^64, 10^6-element arrays,
ndarray headers claiming 2^40 elements), far-future and negative ``seq``, and new ``epoch``s
(alone and as consistent runs). Figures: payloads, refused at decode, delivered, crashes (an
exception other than MessageError, from the codec or a handler), poses published that break
the pose invariant, and the clean frames each node needed to publish again after the poison
(at 30 Hz, 60 frames = 2 s).

``--bags N``: damaged bag files (cut short, corrupt chunks, bad CRCs and lengths, unfinished)
read through the bag reader (``common/ros/bagfuzz.py``).

The clean stream is the oracle's: a still needle seen by the default rig while the ECM yaws,
through the ecm, detector (oracle keypoints; an image backend gets a 1080p JPEG) and pose nodes.

The ROS 2 way in (``--node ros2``, included by default): CDR samples into an offline ``ros2``
source on bridge and rmw_zenoh keys, through its own queue and ``step``, between clean frames
of a dVRK-like system: random bytes, truncated and bit-flipped CDR, garbage after the message,
CDR padded as rmw_fastrtps writes it (accepted), another type's CDR on a topic (rmw_zenoh: a key
naming that type), a 389 KB PNG of 20000x20000, a JointState of 10^6 names, NaN/inf in
camera_info K/D and in a pose. Crashes, published messages the graph's codec refuses, and the
clean frames until a stereo pair comes out again.
"""
from __future__ import annotations

import argparse
import dataclasses
import io
import random
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Optional

import msgpack
import numpy as np

from common.runtime.messages import (
    Calibration,
    CameraImage,
    Command,
    EcmJoints,
    GroundTruth,
    InstrumentState,
    MessageError,
    PoseEstimate,
    decode,
    encode,
    pose_invariant_error,
)

FRAME_HZ = 30.0
RECOVERY_LIMIT = 60          # clean frames (2 s at 30 Hz) a node may need to publish again


# ====================================================================== the clean stream

class CleanStream:
    """Messages of frame ``seq`` per graph key (``camera/left``, ``ecm/pose``, ...), built once
    for ``period`` frames from the library nodes offline and re-stamped per seq."""

    def __init__(self, period: int = 16, seed: int = 0, image_size=(1920, 1080)):
        from common.geometry.camera import StereoRig
        from common.geometry.ecm_kinematics import EcmArm
        from common.geometry.needle import NeedleModel
        from common.geometry.oracle import random_needle_pose
        from common.geometry.transforms import make_T, rotvec_to_R
        from nodes.detector import DetectorNode
        from nodes.ecm import EcmNode
        from nodes.epnp import EpnpNode
        from nodes.fusion import FusionNode
        from nodes.triangulate import TriangulateNode
        w, h = image_size
        rig, model = StereoRig.default(w, h), NeedleModel()
        arm = EcmArm(make_T(rotvec_to_R([0, 0, 0.2]), [0.1, 0.0, 0.3]), 0.01, 0.02)
        self.calib = Calibration(0, np.array([w, h]), rig.to_dict(), model.to_dict(), arm.to_dict(), "fuzz")
        rng = np.random.default_rng(seed)
        T_en = random_needle_pose(rng, rig, model, max_offaxis=0.15)
        T_wn = arm.T_world_ecm([0, 0, 0.05, 0]) @ T_en
        import cv2
        img = np.full((h, w, 3), 90, np.uint8)
        jpeg = cv2.imencode(".jpg", img)[1].tobytes()
        ecm = EcmNode.offline({}, wired=["joints", "calib"])
        det = DetectorNode.offline({"backend": "oracle", "noise_px": 0.2, "seed": seed},
                                   wired=["truth", "calib"])
        stereo = ["left", "right", "calib", "ecm"]
        poses = {"pnp_average": EpnpNode.offline({"method": "average"}, wired=stereo),
                 "pnp_joint": EpnpNode.offline({"method": "joint"}, wired=stereo),
                 "triangulation": TriangulateNode.offline({}, wired=stereo)}
        fusion = FusionNode.offline({}, wired=["pose", "ecm", "truth"])
        for n in (ecm, det, *poses.values()):
            n.deliver("calib", self.calib)
        self.frames = []
        for i in range(period):
            k = i % 8 if i % 8 < 5 else 8 - i % 8
            q = np.array([-0.1 + 0.05 * k, 0.0, 0.05, 0.0])
            T_we = arm.T_world_ecm(q)
            stamp = int(i * 1e9 / FRAME_HZ)
            f = {"camera/joints": EcmJoints(i, stamp, q),
                 "camera/truth": GroundTruth(i, stamp, sequence=0, step=i, ecm_joints=q, T_world_ecm=T_we,
                                             T_world_needle=T_wn)}
            for cam in ("left", "right"):
                f[f"camera/{cam}"] = CameraImage(cam, i, stamp, w, h, "jpeg", jpeg)
            f["camera/instruments"] = InstrumentState("psm1", i, stamp, T_wn @ make_T(np.eye(3), [0, 0, 0.01]), 0.06, True)
            for node, key, msg in ((ecm, "joints", f["camera/joints"]), (det, "truth", f["camera/truth"])):
                node.published.clear()
                node.deliver(key, msg)
            f["ecm/pose"] = ecm.published[-1][1]
            kps = {o: m for o, m in det.published}
            f["detector_left/left"], f["detector_right/right"] = kps["left"], kps["right"]
            for name, node in poses.items():
                node.published.clear()
                node.deliver("ecm", f["ecm/pose"])
                node.deliver("left", kps["left"])
                node.deliver("right", kps["right"])
                out = [m for o, m in node.published if o == "pose"]
                if out:
                    f[f"{name}/pose"] = out[-1]
            fusion.published.clear()
            fusion.deliver("ecm", f["ecm/pose"])
            fusion.deliver("truth", f["camera/truth"])
            if "pnp_joint/pose" in f:
                fusion.deliver("pose", f["pnp_joint/pose"])
            if fusion.published:
                f["fusion/pose"] = fusion.published[-1][1]
            self.frames.append(f)
        self.aliases = {"epnp_average/pose": "pnp_average/pose", "epnp_joint/pose": "pnp_joint/pose",
                        "triangulate/pose": "triangulation/pose", "refine/pose": "pnp_joint/pose"}

    def message(self, key: str, seq: int, epoch: Optional[int] = None):
        """The clean message on ``key`` (a graph key) for frame ``seq``; None if there is none."""
        if key.endswith("/calib"):
            return self.calib
        f = self.frames[seq % len(self.frames)]
        msg = f.get(self.aliases.get(key, key))
        if msg is None:
            return None
        kw = {"seq": seq, "stamp_ns": int(seq * 1e9 / FRAME_HZ)}
        if hasattr(msg, "epoch"):
            kw["epoch"] = epoch
        if isinstance(msg, PoseEstimate) and msg.T_world_needle is not None:
            kw["T_world_needle"] = msg.T_world_needle.copy()
        return dataclasses.replace(msg, **kw)


# ====================================================================== poison

KINDS = ("random_bytes", "truncated", "bit_flips", "type_confused", "missing_field", "extra_field",
         "wrong_schema", "non_finite", "huge", "far_seq", "negative_seq", "new_epoch", "epoch_run")


def _ext_keep(code, data):
    return msgpack.ExtType(code, data)


def _random_value(rng: random.Random):
    return rng.choice([None, True, 0, -1, 2 ** 63, 2 ** 64 - 1, -2 ** 63, 1.5, float("nan"), float("inf"),
                       -float("inf"), 1e300, "", "x" * 1000, b"\x00" * 7, [], [1, "a"], [[1.0, 2.0], [3.0]],
                       {"a": 1}, {1: 2}, [[float("nan")] * 2] * 5, msgpack.ExtType(1, b"\x92\xa7float64\x91\xcf"
                       + (2 ** 40).to_bytes(8, "big")), msgpack.ExtType(7, b"zz")])


def poison(msg, kind: str, rng: random.Random, np_rng: np.random.Generator) -> bytes:
    """One poison payload of ``kind`` made from the clean message ``msg``."""
    payload = encode(msg)
    if kind == "random_bytes":
        return bytes(np_rng.integers(0, 256, rng.randint(0, 2048), dtype=np.uint8))
    if kind == "truncated":
        return payload[:rng.randint(0, max(0, len(payload) - 1))]
    if kind == "bit_flips":
        b = bytearray(payload[:4096]) if len(payload) > 4096 and rng.random() < 0.5 else bytearray(payload)
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b)
    if kind in ("type_confused", "missing_field", "extra_field", "wrong_schema"):
        d = msgpack.unpackb(payload, raw=False, ext_hook=_ext_keep, strict_map_key=False)
        body = d["body"]
        if kind == "type_confused":
            body[rng.choice(list(body))] = _random_value(rng)
        elif kind == "missing_field":
            body.pop(rng.choice(list(body)), None)
        elif kind == "extra_field":
            body[rng.choice(["zzz", "seq2", 7])] = _random_value(rng)
        else:
            r = rng.random()
            if r < 0.3:
                d["schema"] = rng.choice(["needletrack.PoseEstimate", "needletrack.Calibration", "x", 5])
            elif r < 0.6:
                d["version"] = rng.choice([0, 2, "1", None])
            else:
                d["body"] = _random_value(rng)
        return msgpack.packb(d, use_bin_type=True)
    m = dataclasses.replace(msg)
    fields = {f.name: getattr(m, f.name) for f in dataclasses.fields(m)}
    if kind in ("non_finite", "huge"):
        arrays = [k for k, v in fields.items() if isinstance(v, np.ndarray) and v.dtype.kind == "f" and v.size]
        floats = [k for k, v in fields.items() if isinstance(v, float)]
        dicts = [k for k, v in fields.items() if isinstance(v, dict)]
        bad = rng.choice([float("nan"), float("inf"), -float("inf")]) if kind == "non_finite" else \
            rng.choice([1e300, -1e300, 1e12, 3.4e38])
        choice = rng.random()
        if arrays and choice < 0.6:
            k = rng.choice(arrays)
            a = fields[k].copy()
            if kind == "huge" and rng.random() < 0.3:
                a = np.resize(a, (10 ** 6,) + a.shape[1:]) if a.ndim else a
            else:
                a.flat[rng.randrange(a.size)] = bad
            setattr(m, k, a)
        elif dicts and choice < 0.8:                       # nested (Calibration, GroundTruth maps)
            k = rng.choice(dicts)
            d = {kk: (dict(v) if isinstance(v, dict) else v) for kk, v in fields[k].items()}
            kk = rng.choice(list(d))
            if isinstance(d[kk], dict) and d[kk]:
                d[kk][rng.choice(list(d[kk]))] = bad
            else:
                d[kk] = bad if rng.random() < 0.5 else [bad, 1.0]
            setattr(m, k, d)
        elif floats:
            setattr(m, rng.choice(floats), bad)
        elif isinstance(m, CameraImage):
            m.width, m.height = rng.choice([(10 ** 9, 1080), (0, 0), (20000, 20000), (-5, 3)])
        else:
            ints = [k for k, v in fields.items() if isinstance(v, int) and not isinstance(v, bool)]
            if ints:
                setattr(m, rng.choice(ints), rng.choice([2 ** 64 - 1, 2 ** 63, -2 ** 63]))
        return _encode_any(m)
    if kind == "far_seq" and hasattr(m, "seq"):
        m.seq = rng.choice([2 ** 62, 2 ** 63 - 1, m.seq + 10 ** 6, rng.randrange(2 ** 40, 2 ** 62)])
    elif kind == "negative_seq" and hasattr(m, "seq"):
        m.seq = -rng.randint(1, 2 ** 40)
    elif kind in ("new_epoch", "epoch_run") and hasattr(m, "epoch"):
        m.epoch = rng.randrange(1, 2 ** 56)
    return _encode_any(m)


def _encode_any(m) -> bytes:
    try:
        return encode(m)
    except (TypeError, ValueError, OverflowError):      # not encodable as such: the raw body
        body = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in m.to_body().items()}
        try:
            return msgpack.packb({"schema": m.SCHEMA, "version": m.VERSION, "body": body}, use_bin_type=True)
        except (TypeError, ValueError, OverflowError):
            return b"\xc1"


# ====================================================================== the run

@dataclasses.dataclass
class InputResult:
    node: str
    input: str
    payloads: int = 0
    refused: int = 0
    delivered: int = 0
    crashes: int = 0
    invalid_published: int = 0
    recovery_frames: Optional[int] = None      # clean frames until the node published again
    first_crash: str = ""


def _node_specs(graph):
    import importlib

    from common.runtime.node import Node
    for spec in graph.nodes:
        if not spec.module:
            continue
        cls = importlib.import_module(f"nodes.{spec.module}").NODE
        if isinstance(cls, type) and issubclass(cls, Node):
            yield spec, cls


class _NoPacing:
    def wait(self, *a, **k):
        pass

    def delay(self):
        return 0.0


def _make(cls, spec):
    node = cls.offline(spec.params, wired=spec.inputs.keys(), node_id=spec.id)
    if hasattr(node, "out"):
        node.out = io.StringIO()               # the monitor's lines
    return node


def _feed_frame(node, spec, stream: CleanStream, seq: int, epoch) -> None:
    """One clean frame on every wired input (calibration included), in the graph's order."""
    for name, src in spec.inputs.items():
        msg = stream.message(src, seq, epoch)
        if msg is not None:
            node.deliver(name, decode(encode(msg), node.INPUTS[name]))


def _check_published(node, start: int) -> int:
    bad = 0
    for _, m in node.published[start:]:
        if isinstance(m, PoseEstimate):
            try:
                decode(encode(m))
                bad += pose_invariant_error(m, node.pose_volume_m) is not None
            except MessageError:
                bad += 1
    return bad


def fuzz_http(spec, cls, n: int, seed: int) -> InputResult:
    """The viewer's page (``@http``): ``n`` poison requests over sockets to 127.0.0.1
    (``common.evaluation.http_fuzz``), the node's own server with its params."""
    from common.evaluation.http_fuzz import fuzz_page
    node = cls.offline({**spec.params, "port": 0, "rerun": False}, wired=spec.inputs.keys(), node_id=spec.id)
    try:
        r = fuzz_page(node.page, n, seed)
    finally:
        node.teardown()
    return InputResult(spec.id, "@http", r["payloads"], r["refused"], r["delivered"], r["crashes"], 0,
                       r["recovery"], r["first_crash"])


def fuzz_input(spec, cls, input_name: str, stream: CleanStream, n: int, seed: int,
               clean_every: int = 50, warmup: int = 12) -> InputResult:
    """Fuzz one input (or ``@cmd``, or the viewer's ``@http``) of one node; see the module docstring."""
    if input_name == "@http":
        return fuzz_http(spec, cls, n, seed)
    rng, np_rng = random.Random(seed), np.random.default_rng(seed)
    res = InputResult(spec.id, input_name)
    node = _make(cls, spec)
    if cls.is_source() and hasattr(node, "pacer"):
        node.pacer = _NoPacing()                # no pacing offline
    epoch, seq = rng.randrange(1, 2 ** 56), 0
    for _ in range(warmup):
        _feed_frame(node, spec, stream, seq, epoch)
        seq += 1
    if input_name == "@cmd":
        args = {"T_world_needle": np.eye(4).tolist(), "seed": 3} if spec.module == "sim" else {"x": 0.01}
        expect, template = Command, Command(rng.choice(["place_needle", "set_motion", "reset", "x"]), args)
    else:
        expect, template = cls.INPUTS[input_name], None
    start = len(node.published)
    run = 0
    for i in range(n):
        src = spec.inputs.get(input_name, "")
        clean = template or stream.message(src, seq, epoch) or stream.message(src, seq + 1, epoch)
        if clean is None:
            break
        kind = KINDS[i % len(KINDS)] if run == 0 else "epoch_run"
        payload = poison(clean, kind, rng, np_rng)
        if kind == "epoch_run" and run == 0:
            run = rng.randint(2, 6)             # a consistent foreign stream for a few messages
        run = max(0, run - 1)
        res.payloads += 1
        try:
            msg = decode(payload, expect)
        except MessageError:
            res.refused += 1
            msg = None
        except Exception as exc:                # the codec must raise nothing else
            res.crashes += 1
            res.first_crash = res.first_crash or f"decode: {type(exc).__name__}: {exc}"[:300]
            msg = None
        if msg is not None:
            res.delivered += 1
            try:
                node.deliver(input_name, msg)
            except Exception as exc:
                res.crashes += 1
                res.first_crash = res.first_crash or f"{kind}: on_{input_name}: {type(exc).__name__}: {exc}"[:300]
        if (i + 1) % clean_every == 0:
            _feed_frame(node, spec, stream, seq, epoch)
            seq += 1
    res.invalid_published = _check_published(node, start)
    # recovery: clean frames until the node publishes (a sink: until its handlers run clean)
    if cls.OUTPUTS:
        mark = len(node.published)
        for k in range(1, RECOVERY_LIMIT * 3 + 1):
            try:
                if cls.is_source():
                    node.step()                 # a source: its next frame
                else:
                    _feed_frame(node, spec, stream, seq, epoch)
            except Exception as exc:
                res.crashes += 1
                res.first_crash = res.first_crash or f"recovery: {type(exc).__name__}: {exc}"[:300]
            seq += 1
            if len(node.published) > mark:
                res.recovery_frames = k
                break
    else:
        res.recovery_frames = 0
    return res


def run_fuzz(graph, per_input: int, seed: int = 0, nodes: Optional[list] = None, log=print) -> list:
    stream = CleanStream(seed=seed)
    results = []
    for j, (spec, cls) in enumerate(_node_specs(graph)):
        if nodes and spec.id not in nodes:
            continue
        inputs = list(spec.inputs) + ["@cmd"] + (["@http"] if spec.module == "viewer" else [])
        for i, name in enumerate(inputs):
            t0 = time.perf_counter()
            r = fuzz_input(spec, cls, name, stream, per_input, seed * 7919 + j * 101 + i)
            results.append(r)
            log(result_line(r, time.perf_counter() - t0))
    return results


def result_line(r: InputResult, seconds: float) -> str:
    """One fuzzed input's line of the report."""
    return (f"  {r.node:15s} {r.input:14s} {r.payloads:6d} payloads  {r.refused:6d} refused  "
            f"{r.delivered:6d} delivered  {r.crashes} crashes  {r.invalid_published} invalid published  "
            f"recovery {r.recovery_frames if r.recovery_frames is not None else 'NEVER'} frames  "
            f"({seconds:.1f} s)" + (f"\n    first crash: {r.first_crash}" if r.first_crash else ""))


def summary(results: list) -> dict:
    rec = [r.recovery_frames for r in results]
    return {"inputs": len(results), "payloads": sum(r.payloads for r in results),
            "refused": sum(r.refused for r in results), "delivered": sum(r.delivered for r in results),
            "crashes": sum(r.crashes for r in results),
            "invalid_poses_published": sum(r.invalid_published for r in results),
            "never_recovered": sum(x is None for x in rec),
            "max_recovery_frames": max((x for x in rec if x is not None), default=0)}


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
        reg = {c: self.rig[c].T_ecm_cam.tolist() for c in ("left", "right")}
        return {"preset": "dvrk", "rig": ROS_RIG, "keys": self.keys, "topics": {"registration": reg},
                "connect": ["tcp/127.0.0.1:9"], "max_queue": 64}

    def key(self, topic: str, msgtype: str) -> str:
        from common.ros.live import topic_key
        return topic_key(topic, msgtype, self.keys)

    def messages(self, stamp: int) -> list:
        """(topic, message) of one frame: calibration, ECM pose and joints, then the images."""
        b, st = self.build, self.st
        out = [(self.topics["info_" + c], b.camera_info(st, stamp, self.rig[c].K, self.rig[c].dist, self.size))
               for c in ("left", "right")]
        out.append((self.topics["pose"], b.make(st, "geometry_msgs/msg/PoseStamped", header=b.header(st, stamp),
                                                pose=b.pose(st, np.eye(4)))))
        out.append((self.topics["joints"], b.make(st, "sensor_msgs/msg/JointState", header=b.header(st, stamp),
                                                  name=["yaw", "pitch", "insertion", "roll"],
                                                  position=np.array([0.0, 0.1, 0.05, 0.0]))))
        out += [(self.topics[c], b.image(st, stamp, self.img, "bgr8")) for c in ("left", "right")]
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
        c = rng.choice(("left", "right"))
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

    from nodes.ros2 import Ros2Node
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


def live_check(args) -> int:
    """``--live``: the default graph in processes (camera: a replay at 30 Hz, as the soak), a
    clean period, then ``--poison-s`` seconds of poison payloads of every kind on every input
    key at ``--poison-hz``; prints, per output, the longest gap between messages in the clean
    period and the time from the end of the poison to its first message; and restarts."""
    import tempfile

    import zenoh  # noqa: F401

    from common.evaluation.graph_bench import ensure_dataset
    from common.evaluation.pipeline_graph import GraphRun
    from common.evaluation.soak import soak_graph
    from common.runtime.graph import graph_from_dict, output_key

    doc = soak_graph(ensure_dataset(args.dataset), 30.0)
    graph = graph_from_dict(doc)
    stream = CleanStream(seed=args.seed)
    rng, np_rng = random.Random(args.seed), np.random.default_rng(args.seed)
    targets = sorted({src for spec in graph.nodes for src in spec.inputs.values()})
    outputs = [f"{spec.id}/{o}" for spec in graph.nodes for o in spec.outputs
               if spec.id != "camera" and o != "points"] + ["camera/truth"]
    arrivals: dict = {k: [] for k in outputs}
    log_path = tempfile.mktemp(prefix="fuzz-live-", suffix=".log")
    with open(log_path, "w") as log, GraphRun(doc, log, source="camera") as run:
        run.start_consumers()
        session = run.client_session()

        def cb_for(key):
            def cb(_sample):
                arrivals[key].append(time.monotonic())
            return cb
        subs = [session.declare_subscriber(output_key(graph.name, *k.split("/")), cb_for(k)) for k in outputs]
        run.start_source()
        time.sleep(args.clean_s)                 # warm-up and the clean period
        t_clean0 = time.monotonic() - args.clean_s / 2
        t_poison0 = time.monotonic()
        kinds_sent: Counter = Counter()
        seq = 0
        while time.monotonic() - t_poison0 < args.poison_s:
            key = rng.choice(targets)
            clean = stream.message(key, seq) or stream.message(key, seq + 1)
            seq += 1
            if clean is None:
                continue
            kind = rng.choice(KINDS)
            session.put(output_key(graph.name, *key.split("/")), poison(clean, kind, rng, np_rng))
            kinds_sent[kind] += 1
            time.sleep(1.0 / args.poison_hz)
        t_stop = time.monotonic()
        time.sleep(args.after_s)
        failed = run.failed()
        restarts = {nid: s.restarts for l in (run.main, run.src) for nid, s in l.slots.items()}
        for s in subs:
            s.undeclare()
    print(f"fuzz --live: {sum(kinds_sent.values())} poison payloads in {args.poison_s:g} s on "
          f"{len(targets)} keys ({', '.join(targets)}); graph log {log_path}")
    worst = 0.0
    for k in outputs:
        ts = arrivals[k]
        clean = [t for t in ts if t_clean0 <= t < t_poison0]
        gaps = [b - a for a, b in zip(clean, clean[1:])]
        during = sum(t_poison0 <= t < t_stop for t in ts)
        after = [t - t_stop for t in ts if t >= t_stop]
        first = after[0] if after else None
        worst = max(worst, first if first is not None else float("inf"))
        print(f"  {k:22s} clean: {len(clean):4d} msgs, longest gap {max(gaps) if gaps else float('nan'):5.2f} s;"
              f" during poison {during:4d} msgs; first after it {'NEVER' if first is None else f'{first:.2f} s'}")
    print(f"fuzz --live: every output published again within {worst:.2f} s of the poison stopping; "
          f"restarts {sum(restarts.values())}; failed nodes {failed or 'none'}")
    return 0 if worst <= 2.0 and not any(restarts.values()) and not failed else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench fuzz", description=__doc__.split("\n\n")[0])
    ap.add_argument("--graph", default=str(Path(__file__).resolve().parents[2] / "dataflow.yaml"))
    ap.add_argument("--per-input", type=int, default=10_000, help="poison payloads per input (10000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--node", action="append", help="only these node ids (repeatable)")
    ap.add_argument("--bags", type=int, default=200,
                    help="damaged bag files per base bag (MCAP, ROS 1) read through the bag reader (200; 0: none)")
    ap.add_argument("--live", action="store_true",
                    help="instead: poison the default graph in processes (see live_check)")
    ap.add_argument("--dataset", help="--live: the replay's folder (default data/test, else data/bench)")
    ap.add_argument("--clean-s", type=float, default=25.0, help="--live: seconds before the poison")
    ap.add_argument("--poison-s", type=float, default=10.0, help="--live: seconds of poison")
    ap.add_argument("--poison-hz", type=float, default=200.0, help="--live: poison payloads per second")
    ap.add_argument("--after-s", type=float, default=8.0, help="--live: seconds watched after the poison")
    ap.add_argument("--intruder", action="store_true",
                    help="instead: a process without the run's credentials sends fake poses, handovers and "
                         "a swap to the default graph (common/evaluation/intruder.py)")
    ap.add_argument("--uid", type=int, help="--intruder: the intruder runs as this user (needs root)")
    ap.add_argument("--open", action="store_true", help="--intruder: the graph with zenoh.open: true")
    args = ap.parse_args(argv)
    if args.intruder:
        from common.evaluation.intruder import intruder_check
        return intruder_check(args.graph, args.clean_s, args.poison_s, args.uid, args.open)
    if args.live:
        return live_check(args)
    import logging

    from common.runtime.graph import load_graph
    logging.disable(logging.CRITICAL)          # the nodes log every refused message
    graph = load_graph(args.graph)
    t0 = time.perf_counter()
    print(f"fuzz: {args.graph}, {args.per_input} poison payloads per input (kinds: {', '.join(KINDS)})")
    results = run_fuzz(graph, args.per_input, args.seed, args.node)
    if not args.node or "ros2" in args.node:    # the ROS 2 way in (not in dataflow.yaml)
        results += run_fuzz_ros2(args.per_input, args.seed)
    s = summary(results)
    print(f"fuzz: {s['payloads']} payloads into {s['inputs']} inputs of {len({r.node for r in results})} nodes "
          f"in {time.perf_counter() - t0:.0f} s: {s['refused']} refused at decode, {s['delivered']} delivered; "
          f"{s['crashes']} crashes, {s['invalid_poses_published']} invalid poses published, "
          f"{s['never_recovered']} inputs never recovered; publishing again after at most "
          f"{s['max_recovery_frames']} clean frames ({s['max_recovery_frames'] / FRAME_HZ:.2f} s at {FRAME_HZ:g} Hz)")
    ok = s["crashes"] == 0 and s["invalid_poses_published"] == 0 and s["never_recovered"] == 0 \
        and s["max_recovery_frames"] <= RECOVERY_LIMIT
    if args.bags and not args.node:
        from common.ros.bagfuzz import fuzz_bags
        b = fuzz_bags(args.bags, args.seed)
        print(f"fuzz: {b.files} damaged bag files ({', '.join(sorted(b.kinds))}) in {b.seconds:.0f} s: "
              f"{b.read} read to the end ({b.recovered} recovered from unfinished files), {b.refused} refused "
              f"with a BagError; {b.crashes} crashes" + (f" (first: {b.first_crash})" if b.crashes else ""))
        ok = ok and b.crashes == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
