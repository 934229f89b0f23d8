"""Evaluator: collects truth, keypoints, triangulated points and every pose output by frame
``seq``; after the source's EndOfStream (plus a drain timeout for outputs still in flight) it
writes results.json, report.md, error_vs_distance.png and overlays/ (for moving takes also
tracking.png and tracking.mp4: ``common.evaluation.report.write_outputs``) into ``params.out`` and
exits 0.

Params: ``out`` (folder, required), ``dataset`` (the folder replayed: named in the results and
read for the overlays' images; frame ``seq`` = frames.jsonl ``index``), ``detector`` (name for
the results), ``noise_px`` (oracle noise, reported), ``support_normal_world`` (the refinement's
resting prior, reported), ``rrd`` (also write a Rerun recording of the frames, poses
and errors there: ``common.viewer.recording``), ``drain_s`` (default 3: how long to wait
after EndOfStream when some poses never come), ``quiet``.

``instruments`` (the source's ``InstrumentState``s, with ``holds_needle``) and ``in_hand`` (the
tracker's ``InHandPose``) give the moving takes' in-hand figures (``common.evaluation.moving``).
Inputs named after the pose methods (``pnp_average``, ``pnp_joint``, ``triangulation``,
``multiview``, ``refined``, ``multiview_refined``) carry ``PoseEstimate``; wire any subset.
Processing times of every node come from the graph's ``@stats`` key.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

from common.evaluation.collect import Collected
from common.frames import CAMERAS
from common.methods import EXTRA_METHODS, POSE_METHODS, REPORTED_METHODS
from common.constraints import required
from common.runtime.messages import (
    ArmCorrection,
    Calibration,
    EndOfStream,
    GroundTruth,
    InHandPose,
    InstrumentState,
    Keypoints,
    MessageError,
    NodeStats,
    Points3D,
    PoseEstimate,
    decode,
)
from common.runtime.node import Node, run
from nodes._pose import PoseMethodInputs



class EvaluatorNode(PoseMethodInputs, Node):
    """Compares every output of the graph with the ground truth and writes the evaluation."""

    INPUTS = {"truth": GroundTruth, "left": Keypoints, "right": Keypoints, "points3d": Points3D,
              "calib": Calibration, "eos": EndOfStream, "instruments": InstrumentState, "in_hand": InHandPose,
              "arm_correction": ArmCorrection,
              **{m: PoseEstimate for m in POSE_METHODS}}
    OUTPUTS = ()
    KEEP_ALL = tuple(INPUTS)

    @dataclass
    class Params:
        out: required("the output folder") = ""
        dataset: str | None = None
        detector: str = "unknown"
        drain_s: float = 3.0
        noise_px: float = 0.0
        support_normal_world: list[float] | None = None
        rrd: str | None = None            # also write the frames, poses and errors as a Rerun recording

    def setup(self):
        self.out = Path(self.p.out)
        self.dataset_path = self.p.dataset
        self.detector = self.p.detector
        self.drain_s = self.p.drain_s
        self.col = Collected()
        self.methods = [m for m in POSE_METHODS if self.wired(m)]
        self._eos_at = None
        self._last_msg = time.monotonic()
        self._stats_lock = threading.Lock()
        self._stats: dict = {}
        self._stats_sub = None
        self._cpu0: dict = {}
        self._subscribe_stats()

    # ---------------------------------------------------------------- node statistics
    def _subscribe_stats(self):
        """Every node's NodeStats, straight from ``<graph>/@stats/*`` on this node's session."""
        rt = getattr(self, "_runtime", None)
        if rt is None or getattr(rt, "session", None) is None:
            return
        from common.runtime.graph import stats_key

        def on_stats(sample):
            try:
                msg = decode(sample.payload.to_bytes(), NodeStats)
            except MessageError:
                return
            with self._stats_lock:
                self._stats[msg.node] = msg
        self._stats_sub = rt.session.declare_subscriber(stats_key(rt.graph.name), on_stats)

    # ---------------------------------------------------------------- handlers
    def _seen(self):
        self._last_msg = time.monotonic()
        return time.time_ns()

    def on_truth(self, msg):
        if not self.col.truths:
            self._cpu0 = self._cpu_snapshot()
        self.col.add_truth(msg, self._seen())

    def _cpu_snapshot(self) -> dict:
        """CPU seconds used so far by every node process known from its stats."""
        from common.evaluation.timing import process_cpu_seconds
        with self._stats_lock:
            pids = {n: st.pid for n, st in self._stats.items() if n != self.node_id}
        return {n: process_cpu_seconds(pid) for n, pid in pids.items()}

    def on_left(self, msg):
        self.col.add_keypoints(msg, self._seen())

    def on_right(self, msg):
        self.col.add_keypoints(msg, self._seen())

    def on_points3d(self, msg):
        self.col.add_points3d(msg, self._seen())

    def on_calib(self, msg):
        self.col.add_calib(msg)

    def on_instruments(self, msg):
        self.col.add_instrument(msg)

    def on_in_hand(self, msg):
        self.col.add_in_hand(msg, self._seen())

    def on_arm_correction(self, msg):
        self.col.add_arm_correction(msg, self._seen())

    def on_eos(self, msg):
        self._seen()
        self.col.add_eos(msg)
        self._eos_at = time.monotonic()
        self.log.info("end of stream after %d frames; waiting for the outputs in flight", msg.frames)

    def on_pose(self, method, msg):
        self.col.add_pose(method, msg, self._seen())

    # ---------------------------------------------------------------- the end
    def step(self):
        """Runs between input batches: finishes once the stream ended and everything came (or
        the drain timeout passed since the last message)."""
        time.sleep(0.02)
        if self._eos_at is None:
            return True
        if self.col.complete(self.methods):
            self.finish("every output arrived")
            return False
        if time.monotonic() - self._last_msg > self.drain_s:
            self.finish(f"no message for {self.drain_s:.1f} s after the end of the stream")
            return False
        return True

    def finish(self, why: str):
        from common.evaluation.report import write_outputs

        self.log.info("evaluating (%s)", why)
        with self._stats_lock:
            for msg in self._stats.values():
                if msg.node != self.node_id:
                    self.col.add_stats(msg)
        cpu1 = self._cpu_snapshot()
        frames = max(len(self.col.truths), 1)
        for n, c1 in cpu1.items():
            c0 = self._cpu0.get(n)
            if c0 is not None and c1 is not None:
                self.col.node_cpu_ms[n] = 1e3 * (c1 - c0) / frames
        loader = self._image_loader()
        extra = {"noise_px": self.p.noise_px,
                 "support_normal_world": self.p.support_normal_world,
                 "graph_methods": self.methods}
        res = write_outputs(self.out, self.col, dataset=str(self.dataset_path or ""),
                            detector=self.detector, load_images=loader, extra=extra,
                            visible=self._visible(),
                            methods=list(REPORTED_METHODS) + [m for m in EXTRA_METHODS
                                                     if m in self.methods or self.col.poses.get(m)])
        self.log.info("wrote %s (frames %d)", self.out, res["frames"])
        if self.p.rrd:
            self._write_rrd(loader)

    def _write_rrd(self, loader):
        from common.geometry.camera import StereoRig
        from common.geometry.ecm_kinematics import EcmArm
        from common.geometry.needle import NeedleModel
        from common.viewer.recording import write_rrd
        cal = self.col.calib
        if cal is None:
            self.log.error("no calibration came: no recording written")
            return
        n = write_rrd(self.p.rrd, self.col, StereoRig.from_dict(cal.cameras, cal.image_size),
                      NeedleModel.from_dict(cal.needle), EcmArm.from_calibration(cal.ecm), loader)
        self.log.info("wrote %s (%d frames)", self.p.rrd, n)

    def _visible(self) -> dict:
        """{seq: the share of the arc seen in both cameras} from the dataset folder's frames
        (``arc_visible``), else from the truth's visible keypoints."""
        from common.evaluation.moving import stereo_visible
        frames = {}
        if self.dataset_path:
            try:
                from common.data.dataset import Dataset
                frames = {fr.index: fr for fr in Dataset(self.dataset_path, check_files=False).frames}
            except Exception as exc:    # the truth's visible keypoints stand in
                self.log.warning("visible fractions from the truth's keypoints: %s", exc)
        return {s: stereo_visible(frames.get(s, gt)) for s, gt in self.col.truths.items()}

    def _image_loader(self):
        if not self.dataset_path:
            return None
        try:
            from common.data.dataset import Dataset
            ds = Dataset(self.dataset_path, check_files=False)
        except Exception as exc:  # overlays then draw on black; the numbers do not need images
            self.log.warning("overlays without images: %s", exc)
            return None

        def load(seq):
            return {c: ds.image(seq, c) for c in CAMERAS}
        return load

    def teardown(self):
        if self._stats_sub is not None:
            try:
                self._stats_sub.undeclare()
            except Exception:
                pass


NODE = EvaluatorNode
if __name__ == "__main__":
    run(NODE)
