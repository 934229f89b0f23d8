"""ROS benchmarks (figures in docs/ros.md).

``needletrack bench ros-bag BAG [--preset P] [--topics MAP]``: how fast a bag is read into stereo
frames (``common.ros.bag.BagStereo``: deserialise, pair, decode the images, conventions), in
stereo frames/s, without writing anything.

``needletrack bench ros-live [--dataset DIR] [--rate HZ] [--duration S] [--keys bridge|rmw_zenoh]
[--transport zenoh|dds]``: the latency the live ROS 2 path adds. A stand-in ROS 2 system (a Zenoh
session here, or a Cyclone DDS participant with ``--transport dds``: run that inside a network
namespace, docs/ros.md) publishes a dataset's frames as CDR (camera_info, ECM and needle poses, bgr8 images, header stamp = wall
clock at publishing) at ``--rate``; graph A = ``ros2`` -> oracle detector -> ecm -> EPnP (joint)
-> ``ros2_out``, latency = receipt of the PoseStamped here - its header stamp. Graph B, the
native path: ``replay`` (decoded bgr8 frames in memory, stamp = wall clock at publishing) ->
the same nodes, latency = receipt of the pose message - its stamp. Prints p50/p99 of both and
their difference. The oracle detector keeps the detector's own cost out of the comparison.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from common.frames import CAMERAS


def bag_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench ros-bag", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bag")
    ap.add_argument("--preset", choices=["ambf", "dvrk"])
    ap.add_argument("--topics", metavar="MAP.yaml")
    ap.add_argument("--repeat", type=int, default=1, help="read the bag this many times (default 1)")
    args = ap.parse_args(argv)
    from common.ros.bag import BagError, BagStereo
    rates = []
    try:
        for _ in range(max(1, args.repeat)):
            t0 = time.perf_counter()
            n, nbytes = 0, 0
            with BagStereo(args.bag, args.preset, args.topics) as src:
                for s in src:
                    n += 1
                    nbytes += sum(im.nbytes for im in s.images.values())
                w, h = (s.image_size if n else (0, 0))
            dt = time.perf_counter() - t0
            rates.append(n / dt)
    except BagError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    enc = ", ".join(sorted(set(src.info["topics"].values())))
    print(f"{args.bag}: {n} stereo frames {w}x{h} in {dt:.2f} s: {np.median(rates):.1f} stereo frames/s "
          f"({nbytes / dt / 1e6:.0f} MB/s of decoded pixels; median of {len(rates)} reads)")
    print(f"  topics: {enc}")
    return 0


class _RosSystem:
    """A stand-in ROS 2 system: publishes a dataset's frames as CDR on its own Zenoh session
    (``keys``) or, with ``transport`` dds, as a DDS participant on ROS 2's DDS topics."""

    def __init__(self, port: int, keys: str, ds, rig: str = "jhu_daVinci", transport: str = "zenoh"):
        from common.ros.types import typestore
        self.transport, self.session, self.dds = transport, None, None
        if transport == "dds":
            from common.ros.dds import DdsLink
            self.dds = DdsLink(0)
        else:
            import zenoh
            c = zenoh.Config()
            c.insert_json5("mode", '"peer"')
            c.insert_json5("scouting/multicast/enabled", "false")
            c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
            self.session = zenoh.open(c)
        self.keys, self.ds, self.rig, self.st = keys, ds, rig, typestore(2)
        self.images = [{c: ds.image(fr, c) for c in CAMERAS} for fr in ds.frames]
        self.stop = threading.Event()
        self.seq = 0
        self.stamps: list = []  # header stamps of the frames published
        self.pubs = {}

    def _put(self, topic, msg):
        from common.ros.cdr import encode
        from common.ros.live import attachment, topic_key
        if self.dds is not None:
            if topic not in self.pubs:
                self.pubs[topic] = self.dds.publisher(topic, msg.__msgtype__)
            self.pubs[topic].put(encode(msg))
            return
        if topic not in self.pubs:
            self.pubs[topic] = self.session.declare_publisher(topic_key(topic, msg.__msgtype__, self.keys))
        self.seq += 1
        if self.keys == "rmw_zenoh":
            self.pubs[topic].put(encode(msg), attachment=attachment(self.seq, time.time_ns(), bytes(16)))
        else:
            self.pubs[topic].put(encode(msg))

    def run(self, rate: float):
        from common.ros import build
        from common.runtime.pacing import Pacer
        pacer, i, st, ds = Pacer(rate), 0, self.st, self.ds
        while not self.stop.is_set():
            pacer.wait()
            k = i % len(ds)
            fr = ds.frames[k]
            t = time.time_ns()
            for c in CAMERAS:
                self._put(f"/{self.rig}/{c}/camera_info", build.camera_info(st, t, ds.rig[c].K, ds.rig[c].dist,
                                                                             ds.meta.image_size))
            self._put("/ECM/measured_cp", build.make(st, "geometry_msgs/msg/PoseStamped", header=build.header(st, t),
                                                     pose=build.pose(st, fr.T_world_ecm)))
            self._put("/needle/measured_cp", build.make(st, "geometry_msgs/msg/PoseStamped",
                                                        header=build.header(st, t), pose=build.pose(st, fr.T_world_needle)))
            for c in CAMERAS:
                self._put(f"/{self.rig}/{c}/image_raw", build.image(st, t, self.images[k][c], "bgr8"))
            i += 1
            self.stamps.append(t)

    def subscribe_pose(self, callback):
        """``callback(cdr bytes)`` for each PoseStamped ``ros2_out`` sends back."""
        from common.ros.live import topic_key
        topic, t = "/needletrack/needle_pose", "geometry_msgs/msg/PoseStamped"
        if self.dds is not None:
            self.dds.subscribe(topic, t, lambda cdr, _ts: callback(cdr))
            return None
        return self.session.declare_subscriber(topic_key(topic, t, self.keys),
                                               lambda sample: callback(sample.payload.to_bytes()))

    def close(self):
        self.stop.set()
        if self.dds is not None:
            self.dds.close()
        else:
            self.session.close()


def pose_pipeline(source: dict, out: dict | None = None) -> list:
    """The graph's nodes: ``source`` (node id ``camera``) -> oracle detector -> ecm (joints when
    the source has them, else its measured pose) -> EPnP (joint) [-> ``out``]."""
    stereo = {"left": "detector/left", "right": "detector/right", "calib": "camera/calib", "ecm": "ecm/pose"}
    nodes = [source,
             {"id": "detector", "module": "detector", "params": {"backend": "oracle"},
              "inputs": {"left": "camera/left", "right": "camera/right", "truth": "camera/truth",
                         "calib": "camera/calib"}, "outputs": list(CAMERAS)},
             {"id": "ecm", "module": "ecm", "inputs": {"measured": "camera/measured", "calib": "camera/calib",
                                                       **({"joints": "camera/joints"}
                                                          if "joints" in source["outputs"] else {})},
              "outputs": ["pose"]},
             {"id": "epnp_joint", "module": "epnp", "params": {"method": "joint"}, "inputs": stereo,
              "outputs": ["pose"]}]
    if out:
        nodes.append(out)
    return nodes


def _pct(x) -> str:
    x = np.asarray(x, float)
    return f"p50 {np.percentile(x, 50):6.1f} ms  p99 {np.percentile(x, 99):6.1f} ms  (n={len(x)})"


def live_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench ros-live", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", help="dataset folder (default: generate 4 frames at --width x --height)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--rate", type=float, default=10.0, help="frames/s published (default 10)")
    ap.add_argument("--duration", type=float, default=20.0, help="measured seconds per graph (default 20)")
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--keys", default="bridge", choices=["bridge", "rmw_zenoh"])
    ap.add_argument("--transport", default="zenoh", choices=["zenoh", "dds"],
                    help="dds: ROS 2's DDS topics (Cyclone DDS); run it in a network namespace (docs/ros.md)")
    ap.add_argument("--dds-reliability", default="best_effort", choices=["best_effort", "reliable"],
                    help="the ros2 node's DDS reader (default best_effort)")
    args = ap.parse_args(argv)
    from common.data.dataset import Dataset
    from common.evaluation.pipeline_graph import GraphRun, free_port
    from common.ros.cdr import decode
    from common.runtime.graph import output_key
    from common.runtime.messages import decode as decode_msg
    tmp = tempfile.TemporaryDirectory(prefix="needletrack-ros-live-")
    path = args.dataset
    if path is None:
        from common.cli import dataset_main
        path = str(Path(tmp.name) / "ds")
        dataset_main(["generate", "--out", path, "--sequences", "4", "--steps", "1", "--width", str(args.width),
                      "--height", str(args.height), "--seed", "3", "--randomise", "none", "--jobs", "1", "--quiet"])
    ds = Dataset(path)
    w, h = ds.meta.image_size
    results = {}

    # ---- A: live ROS 2 in and out
    port = free_port()
    ros = _RosSystem(port, args.keys, ds, transport=args.transport)
    lat_a: list = []
    t_measure = [None]
    received: set = set()

    def on_pose(cdr):
        t = time.time_ns()
        m = decode(cdr, "geometry_msgs/msg/PoseStamped")
        received.add(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)
        if t_measure[0] is not None and time.monotonic() >= t_measure[0]:
            lat_a.append((t - (m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)) / 1e6)
    sub = ros.subscribe_pose(on_pose)
    tmap = {"preset": "dvrk", "needle_pose": "/needle/measured_cp",
            "registration": {c: ds.rig[c].T_ecm_cam.tolist() for c in CAMERAS}}
    link = ({"transport": "dds"} if args.transport == "dds" else
            {"connect": [f"tcp/127.0.0.1:{port}"], "keys": args.keys})
    doc = {"graph": "rosA", "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
           "nodes": pose_pipeline({"id": "camera", "module": "ros2", "outputs": ["left", "right", "measured", "truth",
                                                                            "calib"],
                               "params": {"preset": "dvrk", "rig": "jhu_daVinci", "topics": tmap, **link,
                                          **({"dds_reliability": args.dds_reliability}
                                             if args.transport == "dds" else {})}},
                              {"id": "out", "module": "ros2_out", "inputs": {"pose": "epnp_joint/pose"},
                               "params": {**link, "cov_topic": ""}})}
    log = open(Path(tmp.name) / "graphA.log", "w")
    thread = threading.Thread(target=ros.run, args=(args.rate,), daemon=True)
    try:
        with GraphRun(doc, log, source="camera") as run:
            run.start()
            thread.start()
            t_measure[0] = time.monotonic() + args.warmup
            window = [time.time_ns() + int(args.warmup * 1e9)]
            time.sleep(args.warmup + args.duration)
            window.append(time.time_ns() - 1_000_000_000)    # the last second's may be under way
    finally:
        ros.stop.set()
        thread.join(5)
        if sub is not None:
            sub.undeclare()
        ros.close()
    results["ros2"] = lat_a

    # ---- B: the native graph (replay of decoded frames)
    lat_b: list = []
    doc = {"graph": "rosB", "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
           "nodes": pose_pipeline({"id": "camera", "module": "replay",
                               "outputs": ["left", "right", "joints", "measured", "truth", "calib", "eos"],
                               "params": {"path": str(Path(path).resolve()), "rate": args.rate, "loop": True,
                                          "decode": True}}, None)}
    log = open(Path(tmp.name) / "graphB.log", "w")
    with GraphRun(doc, log, source="camera") as run:
        t0 = [None]

        def on_native(sample):
            t = time.time_ns()
            m = decode_msg(sample.payload.to_bytes())
            if t0[0] is not None and time.monotonic() >= t0[0]:
                lat_b.append((t - m.stamp_ns) / 1e6)
        run.start_consumers()
        s2 = run.client_session().declare_subscriber(output_key("rosB", "epnp_joint", "pose"), on_native)
        run.start_source()
        t0[0] = time.monotonic() + args.warmup
        time.sleep(args.warmup + args.duration)
        s2.undeclare()
    results["native"] = lat_b
    if not lat_a or not lat_b:
        print(f"error: no poses measured (ros2: {len(lat_a)}, native: {len(lat_b)}); logs in {tmp.name}",
              file=sys.stderr)
        tmp.cleanup = lambda: None      # keep the logs
        return 1
    via = (f"DDS (Cyclone DDS, rt/ topics, {args.dds_reliability} reader)" if args.transport == "dds"
           else f"{args.keys} keys")
    print(f"live ROS 2 path ({via}), {w}x{h} stereo at {args.rate:g} Hz, oracle detector + EPnP:")
    print(f"  ROS 2 image published -> PoseStamped received: {_pct(lat_a)}")
    sent = [t for t in ros.stamps if window[0] <= t <= window[1]]
    print(f"  poses back for {len(received.intersection(sent))} of the {len(sent)} frames published while measuring")
    print(f"  native replay frame published -> pose received:  {_pct(lat_b)}")
    d50 = np.percentile(lat_a, 50) - np.percentile(lat_b, 50)
    d99 = np.percentile(lat_a, 99) - np.percentile(lat_b, 99)
    print(f"  added by the ROS 2 path: p50 {d50:+.1f} ms, p99 {d99:+.1f} ms")
    return 0
