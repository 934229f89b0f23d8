"""``needletrack bench transport``: 1920x1080 stereo frames between two node processes.

Launches a two-node graph through the real launcher on a free loopback port: ``testpattern``
(publishes stereo ``CameraImage`` pairs, stamped just before encoding) -> ``framesink``
(decodes, pairs by seq, views the pixels, records the latency of each stereo frame). Runs it
paced at each ``--rate`` (0 = as fast as the source can) with Zenoh shared memory on and off,
and prints frames/s, latency p50/p99/max and frames lost. ``--codec`` prints instead the codec's
own cost per message, in process: encode and decode (with validation) of each message type.
"""
from __future__ import annotations

import argparse
import json
import socket
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_once(rate_hz: float, frames: int, width: int, height: int, shm: bool, encoding: str = "bgr8",
             warmup: int = 10, quiet: bool = True) -> dict:
    """One run; returns the figures (latencies in ms, fps over the frames after ``warmup``)."""
    import io

    from common.runtime.graph import load_graph
    from common.runtime.launcher import Launcher
    with tempfile.TemporaryDirectory(prefix="nt-bench-") as tmp:
        report = Path(tmp) / "sink.json"
        sender = Path(tmp) / "camera.json"
        graph = load_graph({
            "graph": f"bench{free_port()}",
            "zenoh": {"listen": [f"tcp/127.0.0.1:{free_port()}"], "shm_pool_mb": 96 if shm else 0},
            "nodes": [
                {"id": "camera", "module": "testpattern", "restart": "never",
                 "params": {"rate_hz": rate_hz, "width": width, "height": height, "count": frames + warmup,
                            "encoding": encoding, "start_delay_s": 1.0, "report": str(sender)}},
                {"id": "sink", "module": "framesink", "restart": "never",
                 "inputs": {"left": "camera/left", "right": "camera/right"},
                 "params": {"report": str(report), "log_every_s": 0}}]})
        out = io.StringIO() if quiet else sys.stdout
        launcher = Launcher(graph, out=out)
        launcher.start()
        try:
            t0 = time.monotonic()
            while not launcher.slots["camera"].done and time.monotonic() - t0 < 300:
                launcher._supervise_once()
                time.sleep(0.05)
            time.sleep(1.5)   # let the sink drain
        finally:
            launcher.shutdown()
        if not report.exists():
            raise RuntimeError("the sink wrote no report:\n" + (out.getvalue() if quiet else ""))
        rep = json.loads(report.read_text())
        sent = json.loads(sender.read_text()) if sender.exists() else {}
    seqs = np.asarray(rep["seqs"])
    keep = seqs >= warmup
    lat = np.asarray(rep["latency_ms"])[keep]
    arr = np.asarray(rep["arrival_s"])[keep]
    got = int(keep.sum())
    fps = (got - 1) / (arr[-1] - arr[0]) if got > 1 and arr[-1] > arr[0] else 0.0
    return {"rate_hz": rate_hz, "shm": shm, "encoding": encoding, "frames_sent": frames, "frames_received": got,
            "lost": frames - got, "fps": round(fps, 1),
            "latency_ms_p50": round(float(np.percentile(lat, 50)), 2) if got else None,
            "latency_ms_p99": round(float(np.percentile(lat, 99)), 2) if got else None,
            "latency_ms_max": round(float(lat.max()), 2) if got else None,
            "cpu_ms_per_frame_sender": round(1e3 * sent["cpu_s"] / max(1, sent["frames"]), 2) if sent else None,
            "cpu_ms_per_frame_receiver": round(1e3 * rep["cpu_s"] / max(1, rep["frames"]), 2)}


def codec_messages() -> dict:
    """One typical message of each kind the graph carries per frame, by label."""
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.runtime.messages import (Calibration, CameraImage, EcmPose, GroundTruth, Keypoints, NodeStats,
                                         PoseEstimate)
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.15]
    img = rng.integers(0, 255, (1080, 1920, 3), dtype=np.uint8)
    return {
        "CameraImage 1080p bgr8": CameraImage.from_bgr("left", 7, 123, img),
        "CameraImage 64x48 bgr8": CameraImage.from_bgr("left", 7, 123, img[:48, :64]),
        "Keypoints + centreline": Keypoints("left", 9, 11, True, rng.random((5, 2)) * 1000, rng.random(5), 0.9,
                                            np.array([1.0, 2.0, 30.0, 40.0]), "learned", None,
                                            rng.random((200, 2)) * 1000, rng.random(200), centreline_sigma_px=0.5),
        "PoseEstimate": PoseEstimate(4, 12, "multiview_refined", T, T_world_needle=T, T_world_ecm=np.eye(4),
                                     residual=0.4, residual_unit="px", n_views=2, covariance=np.eye(6) * 1e-6,
                                     ambiguous=False, sequence=1, end_identity=0.8),
        "EcmPose": EcmPose(3, 10, T, q=np.zeros(4), T_world_left=T, T_world_right=T),
        "GroundTruth": GroundTruth(1, 2, sequence=0, step=1, ecm_joints=np.zeros(4), T_world_ecm=T, T_world_needle=T,
                                   keypoints={"left": np.zeros((5, 2)), "right": np.ones((5, 2))},
                                   visible={"left": np.ones(5, bool), "right": np.ones(5, bool)}),
        "NodeStats": NodeStats("det", "detector", 42, 1, 2.5, {f"in.{k}": 3 for k in range(8)},
                               {f"in.{k}": 29.9 for k in range(8)}, 1.0, 2.0),
        "Calibration": Calibration(5, np.array([1920, 1080]), StereoRig.default().to_dict(), NeedleModel().to_dict()),
    }


def codec_figures(seconds: float = 0.3) -> list:
    """Encode and decode cost (us of this process's CPU time) of each of ``codec_messages``,
    decoding as a node's input does (``decode(payload, type)``: every field validated): the
    fastest of batches of about 2 ms (as ``timeit`` advises: the others carry interference from
    the rest of the machine)."""
    from common.runtime.messages import decode, encode
    rows = []
    for label, msg in codec_messages().items():
        payload = encode(msg)
        figures = {}
        for what, fn in (("encode", lambda: encode(msg)), ("decode", lambda: decode(payload, type(msg)))):
            t0 = time.process_time()
            fn()
            batch = max(1, int(2e-3 / max(time.process_time() - t0, 1e-6)))
            per_call, t_end = [], time.process_time() + seconds
            while time.process_time() < t_end or len(per_call) < 5:
                t0 = time.process_time()
                for _ in range(batch):
                    fn()
                per_call.append((time.process_time() - t0) / batch)
            figures[what] = round(1e6 * min(per_call), 1)
        rows.append({"message": label, "bytes": len(payload), "encode_us": figures["encode"],
                     "decode_us": figures["decode"]})
    return rows


def main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench transport", description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", default="30,60,0", help="comma-separated source rates in Hz; 0 = unpaced")
    ap.add_argument("--frames", type=int, default=300, help="stereo frames per run (after 10 warm-up frames)")
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--shm", choices=("on", "off", "both"), default="both", help="Zenoh shared memory")
    ap.add_argument("--encoding", choices=("bgr8", "jpeg", "png"), default="bgr8")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    ap.add_argument("-v", "--verbose", action="store_true", help="show the nodes' output")
    ap.add_argument("--codec", action="store_true", help="only the codec's cost per message, in process")
    args = ap.parse_args(argv)
    if args.codec:
        rows = codec_figures()
        print("codec: CPU time per message, in process (the fastest of ~2 ms batches; decode validates every "
              "field, as a node's input does)")
        print(f"{'message':<24} {'bytes':>9} {'encode us':>10} {'decode us':>10}")
        for r in rows:
            print(f"{r['message']:<24} {r['bytes']:>9} {r['encode_us']:>10.1f} {r['decode_us']:>10.1f}")
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
        return 0
    rates = [float(r) for r in args.rates.split(",")]
    shms = {"on": [True], "off": [False], "both": [True, False]}[args.shm]
    rows = []
    print(f"transport: {args.width}x{args.height} {args.encoding} stereo frames, testpattern -> framesink "
          f"(two processes, Zenoh on loopback), {args.frames} frames per run")
    print(f"{'rate':>8} {'shm':>4} {'fps':>7} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} {'lost':>5} "
          f"{'cpu ms/frame send':>18} {'recv':>6}")
    for shm in shms:
        for rate in rates:
            r = run_once(rate, args.frames, args.width, args.height, shm, args.encoding, quiet=not args.verbose)
            rows.append(r)
            print(f"{('max' if rate == 0 else f'{rate:g} Hz'):>8} {'on' if shm else 'off':>4} {r['fps']:>7.1f} "
                  f"{r['latency_ms_p50']:>8.1f} {r['latency_ms_p99']:>8.1f} {r['latency_ms_max']:>8.1f} {r['lost']:>5} "
                  f"{r['cpu_ms_per_frame_sender'] or float('nan'):>18.1f} {r['cpu_ms_per_frame_receiver']:>6.1f}",
                  flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0
