"""``needletrack record [-g GRAPH] --out FILE.mcap [KEYS...]``: a running graph's messages to MCAP
with ROS 2 message schemas (``ros2msg`` schemas, CDR messages, profile ``ros2``), so a recording
opens as a ROS 2 bag (``ros2 bag play``, rosbags) and in MCAP viewers, and plays back through the
``rosbag`` source (with the topic map written beside it, ``FILE.mcap.topics.yaml``).

What each message becomes (topics under ``/<node>/<output>``):

| graph message | ROS 2 topic(s) and type |
| --- | --- |
| CameraImage | ``.../image_raw`` sensor_msgs/Image (bgr8), or ``.../image_raw/compressed`` CompressedImage (jpeg, png) |
| Calibration | ``.../left/camera_info``, ``.../right/camera_info`` sensor_msgs/CameraInfo; ``/tf_static`` tf2_msgs/TFMessage (ECM -> cameras) |
| EcmJoints | ``...`` sensor_msgs/JointState (outer_yaw, outer_pitch, insertion, outer_roll) |
| EcmPose | ``...`` geometry_msgs/PoseStamped (T_world_ecm, frame ``world``) |
| PoseEstimate | ``...`` PoseStamped (T_ecm_needle, frame ``ECM``), ``.../with_covariance`` PoseWithCovarianceStamped, ``.../world`` PoseStamped (T_world_needle) |
| Keypoints | ``...`` needletrack_msgs/msg/Keypoints (common/ros/types.py) |
| GroundTruth | ``.../needle`` PoseStamped (T_world_needle), ``.../ecm`` PoseStamped (T_world_ecm) |
| InstrumentState | ``.../<name>/measured_cp`` PoseStamped (T_world_jaw, frame ``world``), ``.../<name>/jaw/measured_js`` sensor_msgs/JointState (``jaw``: jaw_rad), as a dVRK arm publishes them |

Header stamps are the messages' ``stamp_ns``; log times the moment of receipt.

A recording survives its end: Ctrl-C, SIGTERM and SIGHUP finish the file; the chunk in progress
is written out every ``CHUNK_S`` (1 s), so a killed recorder's file (no summary) keeps all but
the last second, which ``from-bag`` and the ``rosbag`` source recover (common/ros/reader.py); a
failed write (a full disk) stops it with one line, the file cut back to its complete chunks; the
topic map is written as soon as it is known.
"""
from __future__ import annotations

import argparse
import os
import queue
import signal
import sys
import threading
import time

import numpy as np
import yaml

from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.ros import build
from common.ros.types import KEYPOINTS_MSG, typestore

FRAME_IDS = {"ecm": "ECM", "world": "world", "left": "left_camera_optical", "right": "right_camera_optical"}
JOINT_NAMES = ["outer_yaw", "outer_pitch", "insertion", "outer_roll"]


CHUNK_S = 1.0          # a chunk is closed at least this often: a killed recorder loses at most this


class McapRos2Writer:
    """A bare ``.mcap`` file of ROS 2 CDR messages (schemas registered on first use). The chunk in
    progress is written out once it is ``CHUNK_S`` old (``write`` and ``tick``), so the file on
    disk always holds complete chunks up to about a second ago; ``good_bytes`` is where the last
    one ends. A write that fails (a full disk) raises ``RecordError``; ``abandon()`` then cuts the
    file back to its complete chunks."""

    def __init__(self, path: str):
        from mcap.writer import Writer
        self.path = path
        self.f = open(path, "wb")
        self.w = Writer(self.f)
        self.w.start(profile="ros2", library="needletrack")
        self.store = typestore(2)
        self.schemas: dict = {}
        self.channels: dict = {}
        self.counts: dict = {}
        self.pending = 0                  # messages in the chunk in progress
        self.chunk_t0 = time.monotonic()
        self.good_bytes = 0
        self._flush()

    def _io(self, what: str, fn, *args, **kw):
        try:
            return fn(*args, **kw)
        except OSError as exc:
            raise RecordError(f"{self.path}: cannot write ({what}): {exc.strerror or exc}") from None

    def _flush(self) -> None:
        self._io("a chunk", self.w.flush)
        self.good_bytes = self.f.tell()
        self.pending = 0
        self.chunk_t0 = time.monotonic()

    def write(self, topic: str, msg, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        t = msg.__msgtype__
        if t not in self.schemas:
            text, _ = self.store.generate_msgdef(t, ros_version=2)
            self.schemas[t] = self._io("a schema", self.w.register_schema, name=t, encoding="ros2msg",
                                       data=text.encode())
        if topic not in self.channels:
            self.channels[topic] = self._io("a channel", self.w.register_channel, topic=topic,
                                            message_encoding="cdr", schema_id=self.schemas[t])
        data = bytes(self.store.serialize_cdr(msg, t))
        self._io("a message", self.w.add_message, self.channels[topic], log_time=int(log_time_ns), data=data,
                 publish_time=int(publish_time_ns if publish_time_ns is not None else log_time_ns),
                 sequence=self.counts.get(topic, 0) + 1)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.pending += 1
        self.tick()

    def tick(self) -> None:
        """Write the chunk in progress out if it is ``CHUNK_S`` old."""
        if self.pending and time.monotonic() - self.chunk_t0 >= CHUNK_S:
            self._flush()

    def close(self) -> None:
        self._io("the summary", self.w.finish)
        self._io("the summary", self.f.close)

    def abandon(self) -> None:
        """After a failed write: close the file and cut it back to its complete chunks (it has no
        summary then; the readers recover it)."""
        try:
            self.f.close()
        except OSError:
            pass
        try:
            os.truncate(self.path, self.good_bytes)
        except OSError:
            pass


class RecordError(NeedletrackError, RuntimeError):
    """A recording that cannot go on (the file cannot be written); the text names the file."""


def _pose_stamped(st, T, stamp, frame):
    return build.make(st, "geometry_msgs/msg/PoseStamped", header=build.header(st, stamp, frame),
                      pose=build.pose(st, np.asarray(T, float)))


def ros_messages(base: str, msg) -> list:
    """[(topic, ROS 2 message)] of a graph message published on ``/<node>/<output>`` = ``base``."""
    from common.ros.conventions import ros_covariance
    from common.runtime import messages as M
    st = typestore(2)
    out = []
    if isinstance(msg, M.CameraImage):
        if msg.encoding == "bgr8":
            out.append((f"{base}/image_raw", build.image(st, msg.stamp_ns, msg.to_bgr(), "bgr8",
                                                         FRAME_IDS[msg.camera], msg.seq)))
        else:
            fmt = "jpeg" if msg.encoding == "jpeg" else "png"
            out.append((f"{base}/image_raw/compressed", build.make(
                st, "sensor_msgs/msg/CompressedImage", header=build.header(st, msg.stamp_ns, FRAME_IDS[msg.camera]),
                format=f"bgr8; {fmt} compressed bgr8", data=np.frombuffer(bytes(msg.data), np.uint8))))
    elif isinstance(msg, M.Calibration):
        tfs = []
        for c in CAMERAS:
            cam = msg.cameras[c]
            out.append((f"{base}/{c}/camera_info", build.camera_info(
                st, msg.stamp_ns, cam["K"], cam.get("dist") or [0.0] * 5, msg.image_size, FRAME_IDS[c])))
            from common.ros.conventions import T_to_pose_fields
            p, q = T_to_pose_fields(np.asarray(cam["T_ecm_cam"], float))
            tfs.append(build.make(
                st, "geometry_msgs/msg/TransformStamped", header=build.header(st, msg.stamp_ns, FRAME_IDS["ecm"]),
                child_frame_id=FRAME_IDS[c],
                transform=build.make(st, "geometry_msgs/msg/Transform",
                                     translation=build.make(st, "geometry_msgs/msg/Vector3", x=p[0], y=p[1], z=p[2]),
                                     rotation=build.make(st, "geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2],
                                                         w=q[3]))))
        out.append(("/tf_static", build.make(st, "tf2_msgs/msg/TFMessage", transforms=tfs)))
    elif isinstance(msg, M.EcmJoints):
        out.append((base, build.make(st, "sensor_msgs/msg/JointState", header=build.header(st, msg.stamp_ns),
                                     name=list(JOINT_NAMES), position=np.asarray(msg.q, float),
                                     velocity=np.zeros(0), effort=np.zeros(0))))
    elif isinstance(msg, M.EcmPose):
        out.append((base, _pose_stamped(st, msg.T_world_ecm, msg.stamp_ns, FRAME_IDS["world"])))
    elif isinstance(msg, M.PoseEstimate):
        ps = _pose_stamped(st, msg.T_ecm_needle, msg.stamp_ns, FRAME_IDS["ecm"])
        out.append((base, ps))
        if msg.covariance is not None:
            cov = ros_covariance(msg.covariance, np.eye(3), 1.0)
            out.append((f"{base}/with_covariance", build.make(
                st, "geometry_msgs/msg/PoseWithCovarianceStamped", header=ps.header,
                pose=build.make(st, "geometry_msgs/msg/PoseWithCovariance", pose=ps.pose, covariance=cov.reshape(-1)))))
        if msg.T_world_needle is not None:
            out.append((f"{base}/world", _pose_stamped(st, msg.T_world_needle, msg.stamp_ns, FRAME_IDS["world"])))
    elif isinstance(msg, M.Keypoints):
        uv = np.full((5, 2), np.nan) if msg.uv is None else np.asarray(msg.uv, float).reshape(5, 2)
        sc = np.zeros(5) if msg.scores is None else np.asarray(msg.scores, float).reshape(5)
        out.append((base, build.make(st, KEYPOINTS_MSG[0], header=build.header(st, msg.stamp_ns, FRAME_IDS[msg.camera]),
                                     camera=msg.camera, u=uv[:, 0].copy(), v=uv[:, 1].copy(), score=sc)))
    elif isinstance(msg, M.InstrumentState):
        out.append((f"{base}/{msg.name}/measured_cp", _pose_stamped(st, msg.T_world_jaw, msg.stamp_ns,
                                                                    FRAME_IDS["world"])))
        out.append((f"{base}/{msg.name}/jaw/measured_js", build.make(
            st, "sensor_msgs/msg/JointState", header=build.header(st, msg.stamp_ns), name=["jaw"],
            position=np.array([msg.jaw_rad]), velocity=np.zeros(0), effort=np.zeros(0))))
    elif isinstance(msg, M.GroundTruth):
        if msg.T_world_needle is not None:
            out.append((f"{base}/needle", _pose_stamped(st, msg.T_world_needle, msg.stamp_ns, FRAME_IDS["world"])))
        if msg.T_world_ecm is not None:
            out.append((f"{base}/ecm", _pose_stamped(st, msg.T_world_ecm, msg.stamp_ns, FRAME_IDS["world"])))
    return out


def replay_topic_map(recorded: dict) -> dict | None:
    """The topic map that plays a recording back through the ``rosbag`` source: ``recorded``
    maps each ``/<node>/<output>`` to its graph message type name and the last Calibration, and
    (``instruments``) each InstrumentState output to the instrument names seen on it."""
    images = {c: [b + "/image_raw" for b, t in recorded["types"].items() if t == "CameraImage" and b.endswith("/" + c)]
              for c in CAMERAS}
    calib = recorded.get("calibration")
    if not images["left"] or not images["right"] or calib is None:
        return None
    left, right = images["left"][0], images["right"][0]
    src = left.rsplit("/", 2)[0]
    cal_base = recorded["calibration_topic"]
    m = {"images": {"left": [left, left + "/compressed"], "right": [right, right + "/compressed"]},
         "camera_info": {c: f"{cal_base}/{c}/camera_info" for c in CAMERAS},
         "registration": {c: np.asarray(calib.cameras[c]["T_ecm_cam"], float).tolist() for c in CAMERAS},
         "needle": {"radius_m": float(calib.needle["radius_m"]),
                    "keypoint_angles_deg": [float(a) for a in calib.needle.get("keypoint_angles_deg",
                                                                                (30, 60, 90, 120, 150))]},
         "unit": "m", "stereo_tolerance_ms": 1.0}
    types = recorded["types"]
    for b, t in types.items():
        if t == "EcmPose" and b.startswith(src + "/"):
            m["ecm_pose"] = b
    if "ecm_pose" not in m:
        for b, t in types.items():
            if t == "EcmPose":
                m["ecm_pose"] = b
    for b, t in types.items():
        if t == "GroundTruth" and b.startswith(src + "/"):
            m["needle_pose"] = b + "/needle"
            m.setdefault("ecm_pose", b + "/ecm")
    inst = recorded.get("instruments") or {}
    for b in sorted(inst, key=lambda b: not b.startswith(src + "/")):    # the camera source's first
        for name in sorted(inst[b]):
            m.setdefault("instruments", {}).setdefault(
                name, {"pose": f"{b}/{name}/measured_cp", "jaw": f"{b}/{name}/jaw/measured_js"})
    return m


def _write_topic_map(path: str, tm: dict) -> None:
    tmp = f"{path}.partial-{os.getpid()}"
    with open(tmp, "w") as f:
        f.write("# written by `needletrack record`: plays the recording back through the rosbag source\n")
        yaml.safe_dump(tm, f, sort_keys=False, default_flow_style=None, width=160)
    os.replace(tmp, path)


def record(graph, out: str, keys=(), duration: float = 0.0, stop_on_eos: bool = True, grace_s: float = 2.0,
           ready: threading.Event | None = None, stop: threading.Event | None = None) -> dict:
    """Record ``keys`` (default: every node output of the graph) until ``duration`` s pass, an
    EndOfStream arrives (+``grace_s``), or ``stop`` is set. The topic map
    (``out + ".topics.yaml"``) is written as soon as a calibration and both cameras' images have
    come, and again when it changes. Returns a summary; ``error`` says why a recording stopped
    early (a full disk: the file keeps its complete chunks)."""
    from common.runtime.messages import Calibration, EndOfStream, InstrumentState, MessageError, decode
    from common.runtime.tools import open_session
    keys = [graph.resolve_key(k) for k in keys] or [f"{graph.name}/*/*"]
    q: queue.Queue = queue.Queue(maxsize=4096)
    writer = McapRos2Writer(out)        # before the session: a path that cannot be written fails first

    def cb(sample):
        q.put((str(sample.key_expr), bytes(sample.payload.to_bytes()), time.time_ns()))
    session = open_session(graph)
    subs = [session.declare_subscriber(k, cb) for k in keys]
    recorded = {"types": {}, "calibration": None, "calibration_topic": None}
    skipped = bad = n = 0
    error = None
    tm_path, tm_written = out + ".topics.yaml", None
    t0 = time.monotonic()
    end = t0 + duration if duration > 0 else None
    stop = stop or threading.Event()
    if ready is not None:
        ready.set()
    try:
        while not stop.is_set():
            now = time.monotonic()
            if end is not None and now >= end:
                break
            try:
                key, data, t_rx = q.get(timeout=0.1)
            except queue.Empty:
                writer.tick()
                continue
            try:
                msg = decode(data)
            except MessageError:
                bad += 1
                continue
            base = "/" + key.split("/", 1)[1] if "/" in key else "/" + key
            if isinstance(msg, EndOfStream):
                if stop_on_eos:
                    end = min(end or float("inf"), time.monotonic() + grace_s)
                continue
            rows = ros_messages(base, msg)
            if not rows:
                skipped += 1
                continue
            new_topic = base not in recorded["types"]
            recorded["types"].setdefault(base, type(msg).__name__)
            if isinstance(msg, InstrumentState):
                names = recorded.setdefault("instruments", {}).setdefault(base, set())
                new_topic |= msg.name not in names
                names.add(msg.name)
            for topic, rmsg in rows:
                writer.write(topic, rmsg, t_rx, getattr(msg, "stamp_ns", t_rx) or t_rx)
                n += 1
            if isinstance(msg, Calibration):
                recorded["calibration"], recorded["calibration_topic"] = msg, base
            if new_topic or isinstance(msg, Calibration):
                tm = replay_topic_map(recorded)
                if tm is not None and tm != tm_written:
                    try:
                        _write_topic_map(tm_path, tm)
                    except OSError as exc:
                        raise RecordError(f"{tm_path}: cannot write: {exc.strerror or exc}") from None
                    tm_written = tm
    except KeyboardInterrupt:        # Ctrl-C ends a recording normally
        pass
    except RecordError as exc:
        error = str(exc)
    finally:
        for s in subs:
            s.undeclare()
        session.close()
        if error is None:
            try:
                writer.close()
            except RecordError as exc:
                error = str(exc)
        if error is not None:
            writer.abandon()
    return {"out": out, "messages": n, "topics": dict(writer.counts), "skipped": skipped, "undecodable": bad,
            "topic_map": tm_path if tm_written is not None else None, "error": error,
            "seconds": time.monotonic() - t0}


def record_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack record", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-g", "--graph", default="dataflow.yaml", help="graph YAML (default: dataflow.yaml)")
    ap.add_argument("--out", required=True, help="the MCAP file to write (FILE.mcap; its folder must exist)")
    ap.add_argument("keys", nargs="*", help="keys to record (default: every node output), e.g. camera/left "
                                            "'epnp_joint/*'")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C, "
                                                                 "SIGTERM, SIGHUP or the source's end of stream)")
    ap.add_argument("--no-eos-stop", action="store_true", help="keep recording after an EndOfStream")
    args = ap.parse_args(argv)
    from common.runtime.tools import load_or_report
    if not args.out.endswith(".mcap"):
        print("error: --out must name a .mcap file", file=sys.stderr)
        return 2
    if os.path.exists(args.out):
        print(f"error: {args.out} exists", file=sys.stderr)
        return 2
    folder = os.path.dirname(args.out) or "."
    if not os.path.isdir(folder):
        print(f"error: --out {args.out}: no folder {folder} (create it first)", file=sys.stderr)
        return 2
    graph = load_or_report(args.graph)
    if graph is None:
        return 2
    stop = threading.Event()

    def on_signal(signum, _frame):    # SIGINT, SIGTERM (timeout, systemd), SIGHUP (a closed terminal)
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, on_signal)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)     # past a file-size limit: a write error, said in one line
    try:
        r = record(graph, args.out, args.keys, args.duration, not args.no_eos_stop, stop=stop)
    except (OSError, RecordError) as exc:      # the file cannot even be started
        print(f"error: {exc}" if isinstance(exc, RecordError) else
              f"error: cannot write {args.out}: {exc.strerror or exc}", file=sys.stderr)
        if os.path.isfile(args.out) and os.path.getsize(args.out) == 0:
            os.unlink(args.out)
        return 1
    except KeyboardInterrupt:
        return 130
    if r["error"]:
        print(f"error: {r['error']}: stopped after {r['messages']} messages; the file keeps its complete chunks "
              f"(from-bag and the rosbag source read them)", file=sys.stderr)
        return 1
    if r["messages"] == 0:
        os.unlink(args.out)
        print(f"error: nothing recorded in {r['seconds']:.1f} s: no message on "
              f"{', '.join(args.keys) or 'any node output'} of graph {graph.name!r} (is it running?); "
              f"{args.out} not kept", file=sys.stderr)
        return 1
    print(f"{r['out']}: {r['messages']} messages on {len(r['topics'])} topics in {r['seconds']:.1f} s"
          + (f"; replay with the rosbag source and topics {r['topic_map']}" if r["topic_map"] else ""))
    for t, c in sorted(r["topics"].items()):
        print(f"  {t}: {c}")
    return 0
